"""Back-projection of kidney-mask boundary pixels into the base frame (seed II-E).

A boundary pixel (u, v) is a point p_P = (x0 + u dx, 0, z0 + v dz) of the image plane in the
probe tip frame P; with the frame's probe pose, p_B = X_BP p_P. Collected over the
exploration sweep these points form P_local, the partial kidney point cloud.
"""

from __future__ import annotations

import dataclasses
import weakref

import numpy as np
from pydrake.math import RigidTransform

from drake_rus.imaging.frames import BoundaryPixels, PointCloud
from drake_rus.imaging.probe import ProbeGeometry, check_pose


def backproject_pixels(
    geometry: ProbeGeometry, pixels: np.ndarray, X_BP: RigidTransform
) -> np.ndarray:
    """Points (N, 3) in B (m) of pixels (N, 2) as (u, v) acquired at probe pose X_BP."""
    return geometry.pixel_to_B(pixels, check_pose(X_BP, "X_BP"))


def accumulate(
    cloud: PointCloud,
    boundary: BoundaryPixels,
    geometry: ProbeGeometry,
    max_points_per_frame: int = 0,
) -> PointCloud:
    """``cloud`` plus the back-projected boundary of one frame (a new PointCloud).

    ``max_points_per_frame`` > 0 keeps an evenly strided subset of each frame's boundary.
    A frame with no boundary still counts (and keeps its pose): the kidney was looked for.
    A frame with a non-finite pose (NaN or inf) is dropped.
    """
    if not np.isfinite(boundary.X_BP.GetAsMatrix4()).all():
        return cloud  # a frame whose pose is not finite cannot be placed in B: dropped
    px = boundary.pixels
    if max_points_per_frame > 0 and len(px) > max_points_per_frame:
        px = px[np.linspace(0, len(px) - 1, max_points_per_frame).astype(int)]
    X_BP = boundary.X_BP
    if isinstance(X_BP, RigidTransform):
        # backproject_pixels without its pose checks (the pose was found finite above).
        new = geometry.pixel_to_P(px) @ X_BP.rotation().matrix().T + X_BP.translation()
    else:
        new = backproject_pixels(geometry, px, X_BP)
    points = _append(cloud.points, new) if len(new) else cloud.points
    return PointCloud(
        points=points,
        frame_count=cloud.frame_count + 1,
        poses=cloud.poses + (boundary.X_BP,),
        times=cloud.times + (boundary.time,),
        frames_inconsistent=cloud.frames_inconsistent,
    )


def section_extent(points_B: np.ndarray) -> np.ndarray:
    """(6,) the smallest then the largest x, y, z (m, B) of one frame's section points."""
    p = np.asarray(points_B, float).reshape(-1, 3)
    return np.concatenate([p.min(axis=0), p.max(axis=0)])


def consistent_section(extent: np.ndarray, recent, jump: float, min_recent: int = 3) -> bool:
    """Whether a frame's section (its ``section_extent``) continues the recent frames'.

    ``recent``: the extents (6,) of the sections of the last frames. A kidney's surface is
    smooth: between frames a fraction of a millimetre apart along a sweep its section's
    sides move millimetres (at a pole, where the image plane touches the surface, about 3
    mm for a 0.25 mm step on a 110 x 60 mm kidney); a side that lies more than ``jump`` m
    from the median of the recent frames' is a segmentation's outlier (a mask that leaked
    into a neighbour, or was drawn where the image shows nothing). True with fewer than
    ``min_recent`` recent frames, or ``jump`` <= 0 (the check off)."""
    if not jump > 0.0 or len(recent) < min_recent:
        return True
    median = np.median(np.stack(list(recent)), axis=0)
    return bool(np.max(np.abs(np.asarray(extent, float) - median)) <= jump)


def accumulate_consistent(
    cloud: PointCloud,
    recent: tuple,
    boundary: BoundaryPixels,
    geometry: ProbeGeometry,
    max_points_per_frame: int = 0,
    jump: float = 0.0,
    window: int = 5,
    max_age: float = 0.5,
) -> tuple[PointCloud, tuple]:
    """(cloud, recent) after one frame: :func:`accumulate`, leaving out the points of a
    frame whose section does not continue the recent frames' (:func:`consistent_section`;
    the frame still counts, in ``frames_inconsistent`` too).

    ``recent``: ((time s, extent (6,)), ...) of the last ``window`` frames with a section,
    within ``max_age`` s of this one; every section enters it, kept or not, so a section
    that moves for good (not an outlier) is followed again after half the window."""
    px = boundary.pixels
    if not len(px) or not np.isfinite(boundary.X_BP.GetAsMatrix4()).all():
        return accumulate(cloud, boundary, geometry, max_points_per_frame), recent
    extent = section_extent(geometry.pixel_to_B(px, boundary.X_BP))
    recent = tuple(r for r in recent if boundary.time - r[0] <= max_age)
    if consistent_section(extent, [r[1] for r in recent], jump):
        out = accumulate(cloud, boundary, geometry, max_points_per_frame)
    else:
        empty = BoundaryPixels(np.zeros((0, 2)), boundary.time, boundary.X_BP, boundary.frame_index)
        out = accumulate(cloud, empty, geometry, max_points_per_frame)
        out = dataclasses.replace(out, frames_inconsistent=out.frames_inconsistent + 1)
    return out, (recent + ((boundary.time, extent),))[-window:]


# Growth buffers of accumulated clouds: id(buffer) -> (weak reference, rows filled, address
# of its data). A cloud's points are a prefix of its buffer; the next frame is written in
# place after them when that cloud is the buffer's newest (its length is the rows filled),
# so a sweep of n frames copies each point O(1) times instead of O(n). Rows below
# ``filled`` are never written again: the points of every earlier cloud stay as they were.
_GROWING: dict[int, tuple] = {}


def _forget(key: int, ref) -> None:
    if _GROWING.get(key, (None,))[0] is ref:
        del _GROWING[key]


def _append(points: np.ndarray, new: np.ndarray) -> np.ndarray:
    """``np.concatenate([points, new])`` (N + K, 3), in place in ``points``' growth buffer
    when it has room and ``points`` is its newest prefix; else in a new buffer."""
    n, k = len(points), len(new)
    buf = points.base
    entry = _GROWING.get(id(buf)) if isinstance(buf, np.ndarray) else None
    if not (
        entry is not None
        and entry[0]() is buf
        and entry[1] == n
        and len(buf) >= n + k
        and points.ctypes.data == entry[2]
    ):
        buf = np.empty((max(2 * (n + k), 1024), 3))
        buf[:n] = points
        ref = weakref.ref(buf, lambda r, key=id(buf): _forget(key, r))
        entry = (ref, n, buf.ctypes.data)
    buf[n : n + k] = new
    _GROWING[id(buf)] = (entry[0], n + k, entry[2])
    return buf[: n + k]
