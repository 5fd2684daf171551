"""Scenario sections ``controller`` and ``safety``."""

from dataclasses import dataclass, field


@dataclass
class ControllerConfig:
    # Controller update rate (Hz); the plant runs at 1 kHz, images at 20 Hz.
    rate_hz: float = field(default=200.0, metadata={"positive": True})
    # Desired contact force along the approach vector (N); the seed used 9 N in vivo.
    desired_force: float = field(default=9.0, metadata={"min": 0.0})


@dataclass
class SafetyConfig:
    # Contact force ceiling (N): passive force limiters sit around 20 N (facts).
    force_ceiling: float = field(default=20.0, metadata={"positive": True})
