"""Size modes of the deformable registration: the template scaled along its canonical axes.

A template's shape modes reach only the shapes of the kidneys that built it. The shipped
template's 20 generated kidneys vary in width and thickness about five times less than real
kidneys (issue 27: 58 +- 3 by 38 +- 4 mm against 78 +- 17 by 63 +- 14 mm), so its modes
cannot fit a wide, thick real kidney and the residual stays above the gate. Three extra
modes scale the template about the origin of its canonical frame K (the kidney's
area-weighted centre) along x_k (length), y_k (width) and z_k (thickness):

    q_j(b, s) = q_j + sum_k b_k phi_kj + sum_a s_a (q_j . e_a) e_a,

s_a the relative change of the kidney's size along axis a (dimensionless; 0.1 = 10% larger).
They are fitted with the pose and the shape weights in the same MAP estimate, each with a
Gaussian prior of variance

    sigma_a^2 = max(0, SD_a^2 - (the relative size variance the fitted modes already give)),

SD_a the published relative spread of kidney size along that axis (the scenario's
``localization.size_sd_*``; ``docs/facts/anatomy_and_ultrasound.md``). A template whose
modes already carry the population's size variance (built from real kidneys) gets small
size priors or none; the generated template gets the published spread.
"""

import numpy as np

AXES = ("length", "width", "thickness")


def size_modes_K(points_K: np.ndarray) -> np.ndarray:
    """(3, N, 3) displacement fields (m per unit relative scale) scaling ``points_K`` about
    K's origin along x_k, y_k and z_k: mode a moves point q by (q . e_a) e_a."""
    Q = np.asarray(points_K, dtype=float).reshape(-1, 3)
    modes = np.zeros((3, len(Q), 3))
    for a in range(3):
        modes[a, :, a] = Q[:, a]
    return modes


def explained_size_variances(
    points_K: np.ndarray, modes: np.ndarray | None, variances: np.ndarray | None
) -> np.ndarray:
    """(3,) the variance of the relative size along x_k, y_k, z_k that shape ``modes``
    ((k, N, 3), m per unit weight) with weight ``variances`` (m^2 ... per unit^2) carry:
    each mode's least-squares projection on the scale field of that axis, c_ka =
    <phi_k, s_a> / <s_a, s_a>, summed as sum_k c_ka^2 var_k. Zeros without modes."""
    if modes is None or variances is None or len(variances) == 0:
        return np.zeros(3)
    S = size_modes_K(points_K)
    phi = np.asarray(modes, dtype=float).reshape(len(variances), -1, 3)
    c = np.einsum("kij,aij->ka", phi, S) / np.einsum("aij,aij->a", S, S)
    return np.einsum("ka,k->a", c**2, np.asarray(variances, dtype=float))


def size_mode_prior(
    points_K: np.ndarray,
    modes: np.ndarray | None,
    variances: np.ndarray | None,
    relative_sd,
    min_sd: float = 0.01,
) -> tuple[np.ndarray, np.ndarray]:
    """(axes, variances): the size modes to fit (indices into x_k, y_k, z_k) and their
    prior variances (relative scale^2): the published relative SD squared (``relative_sd``,
    length, width, thickness) less what the fitted ``modes`` already explain
    (:func:`explained_size_variances`). An axis whose remaining SD is below ``min_sd``
    (1%: 1 mm on a 100 mm kidney) is not fitted."""
    sd = np.asarray(relative_sd, dtype=float).reshape(3)
    if np.any(sd < 0) or not np.all(np.isfinite(sd)):
        raise ValueError(f"size prior: expected three non-negative relative SDs, got {sd}")
    remaining = sd**2 - explained_size_variances(points_K, modes, variances)
    axes = np.flatnonzero(remaining >= min_sd**2)
    return axes, remaining[axes]


def scaled_shape(points_K: np.ndarray, axes, scale: np.ndarray | None) -> np.ndarray:
    """``points_K`` scaled by the relative size changes ``scale`` along ``axes``."""
    Q = np.asarray(points_K, dtype=float)
    if scale is None or len(scale) == 0:
        return Q
    out = Q.copy()
    for a, s in zip(axes, scale):
        out[:, a] += s * Q[:, a]
    return out
