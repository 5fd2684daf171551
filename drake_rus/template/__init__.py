"""drake-rus template."""
