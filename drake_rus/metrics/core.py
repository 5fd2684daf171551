"""The seed's evaluation metrics (section III), as plain functions.

- ``e_trans``: E_trans, distance in the base x-y plane between estimated and true kidney
  centroids (m);
- ``e_rot_x``: E_rot,x, angle between the estimated and true kidney x-axes (rad);
- ``imaging_window_path_length``: eps of eq. 24, sum over consecutive probe poses of
  sqrt(|dp|^2 + (L dtheta)^2), L the image depth (m);
- ``CoverageAccumulator`` / ``volume_ratio``: V of eq. 25.

"Kidney volume measured so far" (V_i) is defined here as the volume of the true kidney's
voxels that lie inside the imaged slab of at least one acquired frame: inside the probe's fan
in the image plane (x_P-z_P, within the imaging depth) and within half the elevational beam
width of the plane (|y_P| <= w / 2). V = V_i / V_total with V_total the volume of all the
kidney's voxels on the same grid, so V is in [0, 1] and reaches 1 when every kidney voxel has
been inside some frame's slab.
"""

import numpy as np
from pydrake.math import RigidTransform


def e_trans(X_BK_estimated: RigidTransform, X_BK_true: RigidTransform) -> float:
    """E_trans (m): x-y distance between the estimated and true kidney centroids in B."""
    d = X_BK_estimated.translation()[:2] - X_BK_true.translation()[:2]
    return float(np.linalg.norm(d))


def e_trans_of_offset(offset_B) -> float:
    """E_trans (m) of a centroid offset (estimated minus true, m, in B; e.g. with a patient
    shift taken off): its x-y length, the paper's E_trans (section III-C); the depth (z)
    error is not part of it."""
    d = np.asarray(offset_B, float)
    if d.shape != (3,):
        raise ValueError(f"e_trans_of_offset: expected a 3-vector (m), got shape {d.shape}")
    return float(np.linalg.norm(d[:2]))


def e_rot_x(X_BK_estimated: RigidTransform, X_BK_true: RigidTransform) -> float:
    """E_rot,x (rad): absolute angle between the estimated and true kidney x-axes."""
    a = X_BK_estimated.rotation().matrix()[:, 0]
    b = X_BK_true.rotation().matrix()[:, 0]
    return float(np.arctan2(np.linalg.norm(np.cross(a, b)), float(a @ b)))


def geodesic_angle(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle (rad) of the rotation taking R_a to R_b."""
    R = np.asarray(R_a).T @ np.asarray(R_b)
    skew = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2
    return float(np.arctan2(np.linalg.norm(skew), (np.trace(R) - 1) / 2))


def imaging_window_path_length(poses: list[RigidTransform], image_depth: float) -> float:
    """eps (m), eq. 24: sum_t sqrt(|p_t|^2 + (L theta_t)^2) over consecutive probe poses.

    ``p_t`` is the tip's translation and ``theta_t`` its geodesic rotation between poses
    t-1 and t; ``image_depth`` is L, the depth of the ultrasound image (m).
    """
    if image_depth <= 0:
        raise ValueError(f"image_depth: expected a positive depth in m, got {image_depth}")
    return float(sum(window_steps(poses, image_depth)))


def window_steps(poses: list[RigidTransform], image_depth: float) -> np.ndarray:
    """The per-step terms of eq. 24 (m), len(poses) - 1 of them."""
    steps = []
    for a, b in zip(poses[:-1], poses[1:]):
        dp = np.linalg.norm(b.translation() - a.translation())
        dtheta = geodesic_angle(a.rotation().matrix(), b.rotation().matrix())
        steps.append(np.hypot(dp, image_depth * dtheta))
    return np.asarray(steps)


class CoverageAccumulator:
    """Tracks which true kidney voxels have been inside an acquired frame's slab (eq. 25).

    ``kidney_points_B``: (N, 3) centres of the kidney's voxels in B (m), each of volume
    ``voxel_volume`` (m^3). ``in_fan(p_P) -> bool mask`` tells whether probe-frame points
    lie inside the fan (the probe geometry's ``in_fan``). ``elevation_width``: slab
    thickness (m).
    """

    def __init__(
        self, kidney_points_B: np.ndarray, voxel_volume: float, in_fan, elevation_width: float
    ):
        self.points = np.asarray(kidney_points_B, dtype=float)
        if self.points.ndim != 2 or self.points.shape[1] != 3 or len(self.points) == 0:
            raise ValueError("kidney_points_B: expected a non-empty (N, 3) array of points")
        self.voxel_volume = float(voxel_volume)
        self.in_fan = in_fan
        self.half_width = 0.5 * float(elevation_width)
        self.covered = np.zeros(len(self.points), dtype=bool)
        self.history: list[float] = []

    @property
    def total_volume(self) -> float:
        return self.voxel_volume * len(self.points)

    def add_frame(self, X_BP: RigidTransform) -> float:
        """Marks the voxels in this frame's slab; returns V (ratio) after it."""
        X_PB = X_BP.inverse()
        p_P = self.points @ X_PB.rotation().matrix().T + X_PB.translation()
        in_slab = np.abs(p_P[:, 1]) <= self.half_width
        if in_slab.any():
            idx = np.flatnonzero(in_slab)
            inside = self.in_fan(p_P[idx])
            self.covered[idx[inside]] = True
        ratio = float(self.covered.mean())
        self.history.append(ratio)
        return ratio

    @property
    def ratio(self) -> float:
        return float(self.covered.mean())


def volume_ratio(kidney_points_B, voxel_volume, in_fan, elevation_width, poses) -> np.ndarray:
    """V after each frame (eq. 25) for frames acquired at ``poses``."""
    acc = CoverageAccumulator(kidney_points_B, voxel_volume, in_fan, elevation_width)
    return np.asarray([acc.add_frame(X) for X in poses])
