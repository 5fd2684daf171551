"""Probe wrench from external joint torques (pure functions, same formula in sim and hardware).

The robot senses the environment only through its external joint torques tau_ext (on the FR3,
``tau_ext_hat_filtered``; in simulation, the plant's generalized contact forces on the arm).
With J_WP the 6x7 spatial-velocity Jacobian of the probe tip frame P (about P's origin,
expressed in the base/world frame W), a wrench F_W applied at P gives tau_ext = J_WP^T F_W.
Seven equations, six unknowns: F_W is their (damped) least-squares solution.
"""

import numpy as np
from scipy.linalg.lapack import dposv as _posv

_DAMPING_MATRICES: dict = {}


def _damping_matrix(damping: float) -> np.ndarray:
    """damping^2 I (6 x 6), cached per damping (read-only)."""
    D = _DAMPING_MATRICES.get(damping)
    if D is None:
        D = _DAMPING_MATRICES[damping] = np.eye(6) * damping**2
        D.flags.writeable = False
    return D


def estimate_tip_wrench(
    J_WP: np.ndarray, tau_external: np.ndarray, R_WP: np.ndarray, damping: float = 1e-3
) -> np.ndarray:
    """Spatial force on the probe from the environment, expressed in P, about P's origin.

    Args:
        J_WP: (6, 7) Jacobian [w; v] of frame P's spatial velocity in W, w.r.t. joint rates.
        tau_external: (7,) external joint torques (N m) caused by the environment.
        R_WP: (3, 3) rotation of P in W.
        damping: Tikhonov damping of the least-squares solve (keeps it finite near
            singularities; its effect is below 1e-6 relative away from them).

    Returns:
        (6,) [tau_x, tau_y, tau_z, f_x, f_y, f_z] in P (N m, N).
    """
    J_WP = np.asarray(J_WP, dtype=float)
    tau = np.asarray(tau_external, dtype=float)
    if J_WP.shape != (6, tau.shape[0]):
        raise ValueError(f"J_WP: expected shape (6, {tau.shape[0]}), got {J_WP.shape}")
    # Solve min |J^T F - tau|^2 + damping^2 |F|^2  ->  (J J^T + d^2 I) F = J tau.
    A = J_WP @ J_WP.T
    np.add(A, _damping_matrix(damping), out=A)  # one ufunc call (this runs at 100 Hz)
    # A is symmetric positive definite: LAPACK's Cholesky solve, called directly (numpy's
    # solve wrapper costs three times the solve at this size); anything else, numpy's.
    _, F_W, info = _posv(A, J_WP @ tau)
    if info != 0:
        F_W = np.linalg.solve(A, J_WP @ tau)
    R_PW = np.asarray(R_WP, dtype=float).T
    return np.concatenate([R_PW @ F_W[:3], R_PW @ F_W[3:]])


def contact_force_along_approach(F_P: np.ndarray) -> float:
    """The pressing force F_z (N) of the seed's eq. 6: positive when the probe pushes in.

    The environment pushes back on the probe along -z_P, so F_z = -f_z of the probe wrench.
    """
    return float(-np.asarray(F_P)[5])
