"""drake-rus experiments."""
