"""Back-projection of kidney-mask boundary pixels into the base frame (seed II-E).

A boundary pixel (u, v) is a point p_P = (x0 + u dx, 0, z0 + v dz) of the image plane in the
probe tip frame P; with the frame's probe pose, p_B = X_BP p_P. Collected over the
exploration sweep these points form P_local, the partial kidney point cloud.
"""

from __future__ import annotations

import numpy as np
from pydrake.math import RigidTransform

from drake_rus.imaging.frames import BoundaryPixels, PointCloud
from drake_rus.imaging.probe import ProbeGeometry, check_pose


def backproject_pixels(geometry: ProbeGeometry, pixels: np.ndarray, X_BP: RigidTransform
                       ) -> np.ndarray:
    """Points (N, 3) in B (m) of pixels (N, 2) as (u, v) acquired at probe pose X_BP."""
    return geometry.pixel_to_B(pixels, check_pose(X_BP, "X_BP"))


def accumulate(cloud: PointCloud, boundary: BoundaryPixels, geometry: ProbeGeometry,
               max_points_per_frame: int = 0) -> PointCloud:
    """``cloud`` plus the back-projected boundary of one frame (a new PointCloud).

    ``max_points_per_frame`` > 0 keeps an evenly strided subset of each frame's boundary.
    A frame with no boundary still counts (and keeps its pose): the kidney was looked for.
    A frame with a non-finite pose (NaN or inf) is dropped.
    """
    if not np.all(np.isfinite(boundary.X_BP.GetAsMatrix4())):
        return cloud    # a frame whose pose is not finite cannot be placed in B: dropped
    px = boundary.pixels
    if max_points_per_frame > 0 and len(px) > max_points_per_frame:
        px = px[np.linspace(0, len(px) - 1, max_points_per_frame).astype(int)]
    new = backproject_pixels(geometry, px, boundary.X_BP)
    points = np.concatenate([cloud.points, new]) if len(new) else cloud.points
    return PointCloud(points=points, frame_count=cloud.frame_count + 1,
                      poses=cloud.poses + (boundary.X_BP,), times=cloud.times + (boundary.time,))
