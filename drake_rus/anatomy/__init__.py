"""drake-rus anatomy."""
