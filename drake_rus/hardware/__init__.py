"""drake-rus hardware."""
