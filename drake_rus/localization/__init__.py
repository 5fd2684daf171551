"""drake-rus localization."""
