"""Imaging: probe geometry, slice sensor, ultrasound emulator, segmenter, back-projection."""
