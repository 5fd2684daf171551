"""drake-rus: autonomous robotic kidney ultrasound by template-guided optimal pivoting."""

__version__ = "0.1.0"
