"""drake-rus metrics."""
