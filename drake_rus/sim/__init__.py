"""drake-rus sim."""
