"""Scenario section ``imaging``: probe fan geometry, sensor rate, emulator and segmenter."""

from dataclasses import dataclass, field


@dataclass
class ImagingConfig:
    # Frame rate of the slice sensor / frame grabber (Hz). The seed grabbed frames at 20 fps.
    frame_rate_hz: float = field(default=20.0, metadata={"positive": True})
