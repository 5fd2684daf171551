"""Pivot calibration of the probe tip (docs/hardware_bringup.md, "Probe calibration").

The probe tip rests in a small divot fixed in the robot's workspace while the arm is guided
through different orientations about it. For every pose i of the flange F in the base B
(R_i, t_i) the tip, at the unknown offset p_FT in F, sits at the same unknown pivot point
p_BT in B:

    R_i p_FT + t_i = p_BT       for all i,

i.e. [R_i  -I] [p_FT; p_BT] = -t_i: 3N linear equations in 6 unknowns, solved in the least-
squares sense. The translation of ``probe.X_FP`` in the scenario is p_FT (the tip frame's
orientation comes from the holder's CAD).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from drake_rus.robot import FLANGE_FRAME, MakeControlPlant

__all__ = ["PivotCalibration", "pivot_calibration", "flange_poses_from_joints"]


@dataclasses.dataclass(frozen=True)
class PivotCalibration:
    """Result: tip offset in the flange frame (m), pivot point in the base (m), residual
    distance of every pose's tip prediction from the pivot (m), their RMS (m), and the
    smallest singular value of the stacked system (poor rotation diversity when small)."""

    p_FT: np.ndarray
    p_BT: np.ndarray
    residuals: np.ndarray
    rms: float
    conditioning: float


def pivot_calibration(
    rotations, translations, min_singular_value: float = 0.05
) -> PivotCalibration:
    """Least-squares pivot calibration from flange poses.

    Args:
        rotations: (N, 3, 3) rotation matrices R_BF of the flange in the base.
        translations: (N, 3) positions p_BF (m) of the flange origin in the base.
        min_singular_value: below this smallest singular value of the stacked [R_i -I]
            matrix the poses do not rotate enough about the pivot to fix the tip: raises.

    Raises ValueError (shapes, fewer than 3 poses, non-rotation matrices, poor diversity).
    """
    R = np.asarray(rotations, dtype=float)
    t = np.asarray(translations, dtype=float)
    if R.ndim != 3 or R.shape[1:] != (3, 3):
        raise ValueError(f"pivot_calibration: rotations must be (N, 3, 3), got {R.shape}")
    if t.shape != (R.shape[0], 3):
        raise ValueError(
            f"pivot_calibration: translations must be ({R.shape[0]}, 3), got {t.shape}"
        )
    n = R.shape[0]
    if n < 3:
        raise ValueError(f"pivot_calibration: needs at least 3 poses, got {n}")
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        raise ValueError("pivot_calibration: non-finite pose")
    orth = np.abs(np.einsum("nij,nkj->nik", R, R) - np.eye(3)).max()
    if orth > 1e-6 or np.any(np.linalg.det(R) < 0):
        raise ValueError(
            f"pivot_calibration: rotations are not proper rotation matrices "
            f"(orthogonality error {orth:.2e})"
        )
    A = np.zeros((3 * n, 6))
    A[:, :3] = R.reshape(3 * n, 3)
    A[:, 3:] = -np.tile(np.eye(3), (n, 1))
    b = -t.reshape(3 * n)
    singular = np.linalg.svd(A, compute_uv=False)
    conditioning = float(singular[-1])
    if conditioning < min_singular_value:
        raise ValueError(
            f"pivot_calibration: the {n} poses do not rotate enough about the pivot "
            f"(smallest singular value {conditioning:.3g} < {min_singular_value}); tilt the "
            f"probe by 20-40 degrees about two different axes"
        )
    x, *_ = np.linalg.lstsq(A, b, rcond=None)
    p_FT, p_BT = x[:3], x[3:]
    residuals = np.linalg.norm(np.einsum("nij,j->ni", R, p_FT) + t - p_BT, axis=1)
    return PivotCalibration(
        p_FT, p_BT, residuals, float(np.sqrt(np.mean(residuals**2))), conditioning
    )


def flange_poses_from_joints(scenario, joint_positions):
    """Flange poses (R_BF (N, 3, 3), p_BF (N, 3)) by our FR3 model's forward kinematics for
    joint configurations (N, 7) rad recorded while pivoting."""
    plant, _ = MakeControlPlant(scenario.robot, scenario.probe)
    context = plant.CreateDefaultContext()
    flange = plant.GetFrameByName(FLANGE_FRAME)
    rotations, translations = [], []
    for q in np.asarray(joint_positions, dtype=float):
        plant.SetPositions(context, q)
        X = flange.CalcPoseInWorld(context)
        rotations.append(X.rotation().matrix())
        translations.append(X.translation())
    return np.array(rotations), np.array(translations)
