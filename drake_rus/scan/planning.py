"""Where a scan starts: the exploration region of interest (E-ROI) and the start pose.

The seed places the probe by hand where the kidney is visible (II-E) and, in simulation,
defines the E-ROI by projecting the kidney's bounding box onto the body along the base z-axis
(III-C, Fig. 6b); exploration runs along the base y-axis. We do the same from the true kidney
mesh: this stands in for the operator's placement and is the only use of ground truth before
the scan's metrics.
"""

import dataclasses

import numpy as np
from pydrake.math import RigidTransform, RotationMatrix

# Probe pointing down (z_P = -z_B) with its array across the body (x_P = +x_B): a transverse
# image, the seed's exploration view.
R_B_TRANSVERSE = RotationMatrix(np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]))


@dataclasses.dataclass
class ExplorationRoi:
    """The kidney's x-y bounding box in the base frame (m) and its centroid."""
    x_min: float
    x_max: float
    y_min: float
    y_max: float
    centroid_B: np.ndarray

    @property
    def length_y(self) -> float:
        return self.y_max - self.y_min


def exploration_roi(patient, X_BPt: RigidTransform) -> ExplorationRoi:
    """E-ROI of ``patient`` lying at ``X_BPt`` (III-C)."""
    v = patient.kidney_mesh.vertices
    p_B = v @ X_BPt.rotation().matrix().T + X_BPt.translation()
    lo, hi = p_B.min(axis=0), p_B.max(axis=0)
    return ExplorationRoi(lo[0], hi[0], lo[1], hi[1],
                          patient.X_BK(X_BPt).translation().copy())


def skin_height_B(patient, X_BPt: RigidTransform, x: float, y: float) -> float:
    """Height z (m, base frame) of the body surface above the point (x, y)."""
    mesh = patient.skin_mesh
    X_PtB = X_BPt.inverse()
    origin_B = np.array([x, y, 10.0])
    origin = X_PtB.multiply(origin_B)
    direction = X_PtB.rotation().multiply(np.array([0.0, 0.0, -1.0]))
    hits, _, _ = mesh.ray.intersects_location([origin], [direction])
    if len(hits) == 0:
        raise ValueError(f"no body surface below (x, y) = ({x:.3f}, {y:.3f}) m in the base "
                         "frame: is the patient placed under the robot (patient.X_BPt)?")
    hits_B = X_BPt.multiply(np.asarray(hits).T).T
    return float(hits_B[:, 2].max())


def exploration_start_xy(roi: ExplorationRoi, scan_direction: str = "-y",
                         start_fraction: float = 0.0) -> tuple[float, float]:
    """(x, y) of the exploration start: over the kidney centroid's x, at the E-ROI's end the
    scan leaves from, ``start_fraction`` of the E-ROI's length inside it."""
    if scan_direction == "-y":
        y = roi.y_max - start_fraction * roi.length_y
    elif scan_direction == "+y":
        y = roi.y_min + start_fraction * roi.length_y
    else:
        raise ValueError(f"scan_direction: expected '+y' or '-y', got {scan_direction!r}")
    return float(roi.centroid_B[0]), float(y)


def exploration_start(patient, X_BPt: RigidTransform, *, scan_direction: str = "-y",
                      start_fraction: float = 0.0, hover: float = 0.015) -> RigidTransform:
    """Tip pose (transverse view, pointing down) ``hover`` m above the skin at the start.

    The start lies over the kidney centroid's x, at the E-ROI's end the scan leaves from
    (its superior end for a "-y" scan when the head is at +y), moved into the E-ROI by
    ``start_fraction`` of its length (0: at the pole; randomised starts use more).
    """
    x, y = exploration_start_xy(exploration_roi(patient, X_BPt), scan_direction,
                                start_fraction)
    z = skin_height_B(patient, X_BPt, x, y) + hover
    return RigidTransform(R_B_TRANSVERSE, [x, y, z])
