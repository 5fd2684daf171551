"""Anatomical axis conventions and the posture transform (body frame Bd -> patient frame Pt).

Body frame Bd: x_Bd towards the patient's left, y_Bd superior (head), z_Bd anterior.

Patient frame Pt = bed frame (docs/design.md, PatientConfig): origin on the bed surface, x_Pt across
the bed away from the robot, y_Pt towards the head, z_Pt up.

- supine: Bd axes = Pt axes (patient's left = +x_Pt, anterior = up); the right side (right
  kidney) is towards the robot.
- left lateral decubitus (the seed's in-vivo posture): the patient lies on the left side, right
  flank up. Rolling onto the left side about the long axis is R_y(+90 deg):
  left (+x_Bd) -> down (-z_Pt), anterior (+z_Bd) -> +x_Pt (facing away from the robot, back
  towards the robot), right flank (-x_Bd) -> up (+z_Pt).
"""

import numpy as np
from pydrake.math import RigidTransform, RotationMatrix

POSTURES = ("supine", "left_lateral_decubitus")
SIDES = ("right", "left")

_AXIS = {
    "L": (1, 0, 0),
    "R": (-1, 0, 0),
    "S": (0, 1, 0),
    "I": (0, -1, 0),
    "A": (0, 0, 1),
    "P": (0, 0, -1),
}


def check_side_posture(side: str, posture: str) -> None:
    if side not in SIDES:
        raise ValueError(f"side: expected one of {SIDES}, got {side!r}")
    if posture not in POSTURES:
        raise ValueError(f"posture: expected one of {POSTURES}, got {posture!r}")


def R_BdS(axes: str) -> np.ndarray:
    """Rotation from a source frame S, whose +x, +y, +z point to the anatomical directions
    ``axes`` (three letters from L/R, S/I, A/P; e.g. "LPS" for ITK/DICOM, "RAS" for NIfTI world,
    "LSA" for the glTF/HuBMAP body frame), to the body frame Bd."""
    axes = axes.upper()
    if len(axes) != 3 or any(a not in _AXIS for a in axes):
        raise ValueError(f"axes: expected three letters from L/R, S/I, A/P, got {axes!r}")
    R = np.column_stack([_AXIS[a] for a in axes]).astype(float)
    if abs(np.linalg.det(R) - 1.0) > 1e-9:
        raise ValueError(f"axes {axes!r}: not a right-handed set of anatomical directions")
    return R


def R_PtBd(posture: str) -> np.ndarray:
    if posture == "supine":
        return np.eye(3)
    if posture == "left_lateral_decubitus":
        return RotationMatrix.MakeYRotation(np.pi / 2).matrix()
    raise ValueError(f"posture: expected one of {POSTURES}, got {posture!r}")


def lateral_direction_Bd(side: str) -> np.ndarray:
    """Medial -> lateral direction of the given kidney in Bd."""
    return np.array([-1.0, 0.0, 0.0]) if side == "right" else np.array([1.0, 0.0, 0.0])


def reference_axes_Pt(side: str, posture: str):
    """(x_ref, y_ref) of the canonical-frame sign rules (eq. 13-14) expressed in Pt:
    inferior -> superior, and medial -> lateral of the target kidney."""
    R = R_PtBd(posture)
    return R @ np.array([0.0, 1.0, 0.0]), R @ lateral_direction_Bd(side)


def transform_mesh(mesh, X: RigidTransform):
    m = mesh.copy()
    m.apply_transform(X.GetAsMatrix4())
    return m
