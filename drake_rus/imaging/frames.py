"""Values carried by the imaging systems' abstract ports.

Every image travels with the time it was acquired (s) and the probe pose ``X_BP`` used to
acquire it, so consumers can back-project it and detect stale frames. Frames are immutable:
their arrays are read-only and copying a frame (Drake clones abstract values) shares them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from pydrake.math import RigidTransform


def _freeze(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a)
    if a.flags.writeable:
        a = a.view()
        a.flags.writeable = False
    return a


@dataclass(frozen=True)
class UsFrame:
    """An image (rows, cols) with its acquisition time (s), probe pose X_BP and index.

    ``frame_index`` counts frames from 0; -1 means "no frame acquired yet" (empty image).
    Used for label images (uint8 tissue labels), ultrasound images (uint8 grey) and masks
    (bool).
    """

    image: np.ndarray
    time: float = 0.0
    X_BP: RigidTransform = field(default_factory=RigidTransform)
    frame_index: int = -1

    def __post_init__(self):
        object.__setattr__(self, "image", _freeze(self.image))

    @property
    def valid(self) -> bool:
        return self.frame_index >= 0

    def __copy__(self):
        return self

    def __deepcopy__(self, memo):
        return self  # immutable: sharing is safe and saves copying the image every step


@dataclass(frozen=True)
class BoundaryPixels:
    """Kidney-mask boundary pixels of one frame: ``pixels`` (N, 2) as (column u, row v),
    with the frame's acquisition time (s), probe pose X_BP and index."""

    pixels: np.ndarray
    time: float = 0.0
    X_BP: RigidTransform = field(default_factory=RigidTransform)
    frame_index: int = -1

    def __post_init__(self):
        object.__setattr__(self, "pixels", _freeze(np.asarray(self.pixels, float).reshape(-1, 2)))

    def __copy__(self):
        return self

    def __deepcopy__(self, memo):
        return self


@dataclass(frozen=True)
class PointCloud:
    """An accumulated point cloud ``points`` (N, 3) in the base frame B (m), the number of
    frames that contributed, and the probe poses X_BP (and times, s) of those frames;
    ``frames_inconsistent``: of those, the frames whose section jumped from its neighbours'
    (counted, their points left out: backprojection.accumulate_consistent)."""

    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    frame_count: int = 0
    poses: tuple = ()
    times: tuple = ()
    frames_inconsistent: int = 0

    def __post_init__(self):
        object.__setattr__(self, "points", _freeze(np.asarray(self.points, float).reshape(-1, 3)))

    def __copy__(self):
        return self

    def __deepcopy__(self, memo):
        return self


@dataclass(frozen=True)
class KidneySurface:
    """The registered kidney's surface: ``points_B`` (N, 3) in the base frame B (m), the
    registration template's points in K (with its fitted shape modes) mapped by the
    localizer's X_BK, and the time (s) of that registration. Empty (no points) before
    localization: the Segmenter then predicts nothing."""

    points_B: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    time: float = float("nan")

    def __post_init__(self):
        object.__setattr__(
            self, "points_B", _freeze(np.asarray(self.points_B, float).reshape(-1, 3))
        )

    @property
    def valid(self) -> bool:
        return len(self.points_B) >= 3

    def __copy__(self):
        return self

    def __deepcopy__(self, memo):
        return self
