"""Back-projection of kidney-mask boundary pixels into the base frame (seed II-E).

A boundary pixel (u, v) is a point p_P = (x0 + u dx, 0, z0 + v dz) of the image plane in the
probe tip frame P; with the frame's probe pose, p_B = X_BP p_P. Collected over the
exploration sweep these points form P_local, the partial kidney point cloud.
"""

from __future__ import annotations

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
    )


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
