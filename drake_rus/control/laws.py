"""Pure control laws of the seed's section II-C (eq. 1-12): numpy in, numpy out.

Frames (docs/design.md): B is the robot base (= world, z up); P is the probe tip frame with
z_P = a (approach vector, into the body) and x_P = o (orientation vector, along the array).
Twists are Drake-ordered [omega; v] of frame P's origin, expressed in B.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg.lapack import dposv as _posv
from scipy.spatial import ConvexHull, QhullError

from drake_rus.control import kernels


def _f64(x) -> np.ndarray:
    """``x`` as a C-contiguous float64 array (no copy when it already is one)."""
    return np.ascontiguousarray(x, dtype=np.float64)


def all_finite(x: np.ndarray) -> bool:
    """Every entry of the float array ``x`` is finite. A sum is finite only if every term is
    (NaN and inf propagate); only a sum that overflows needs the element-wise check. About
    half the cost of ``np.all(np.isfinite(x))`` on the controller's small arrays."""
    return math.isfinite(float(x.sum())) or bool(np.isfinite(x).all())


def _vec3(x) -> np.ndarray:
    x = np.asarray(x, dtype=float).reshape(-1)
    if x.shape != (3,):
        raise ValueError(f"expected a 3-vector, got shape {x.shape}")
    return x


def cross3(u, v) -> np.ndarray:
    """u x v for 3-vectors (numpy's cross is ~20x slower on tiny arrays)."""
    return np.array(
        [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]]
    )


# ----------------------------------------------------------------------------- orientation
def approach_alignment(a_curr, a_des, a_des_dot, K_p1: float, K_p11: float) -> np.ndarray:
    """Angular velocity (rad/s, in B) tilting the approach vector (eq. 1-2).

    e_a = a_curr x a_des (eq. 1); omega_a = K_p1 e_a + K_p11 (a_curr x da_des/dt) (eq. 2).
    """
    a = _vec3(a_curr)
    e_a = cross3(a, _vec3(a_des))
    return K_p1 * e_a + K_p11 * cross3(a, _vec3(a_des_dot))


def orientation_vector_alignment(o_curr, o_des, a_curr, K_p2: float) -> np.ndarray:
    """Angular velocity (rad/s, in B) rotating the array about a only (eq. 3-4).

    e_o = o_curr x o_des (eq. 3); omega_o = K_p2 (e_o . a_curr) a_curr (eq. 4). The paper
    writes the scalar K_p2 (e_o . a); the rotation it commands is about a_curr, so the
    vector is that scalar times a_curr (which does not disturb the tilt task).
    """
    a = _vec3(a_curr)
    e_o = cross3(_vec3(o_curr), _vec3(o_des))
    return K_p2 * float(e_o @ a) * a


def orientation_alignment(
    R_BP, a_des, o_des, a_des_dot, K_p1: float, K_p11: float, K_p2: float
) -> np.ndarray:
    """omega_total = omega_a + omega_o (eq. 5), from the tip rotation R_BP (3x3).

    a_curr = R_BP[:, 2] (z_P), o_curr = R_BP[:, 0] (x_P).
    """
    R = np.asarray(R_BP, dtype=float)
    a, o = R[:, 2], R[:, 0]
    return approach_alignment(a, a_des, a_des_dot, K_p1, K_p11) + orientation_vector_alignment(
        o, o_des, a, K_p2
    )


def angle_between(u, v) -> float:
    """Angle (rad) between two vectors, robust near 0 and pi."""
    u, v = _vec3(u), _vec3(v)
    return math.atan2(float(np.linalg.norm(cross3(u, v))), float(u @ v))


# ----------------------------------------------------------------------------- force
def lowpass_alpha(dt: float, cutoff_hz: float) -> float:
    """Smoothing factor of a first-order low-pass y += alpha (x - y), sampled every dt (s)."""
    tau = 1.0 / (2.0 * math.pi * cutoff_hz)
    return dt / (tau + dt)


def lowpass_update(y_prev: float, x: float, alpha: float) -> float:
    """One step of the first-order low-pass filter on the force estimate (eq. 6's F_z)."""
    return y_prev + alpha * (x - y_prev)


def force_pd(
    F_des: float, F_filtered: float, error_rate: float, a_curr, K_p3: float, K_d1: float
) -> np.ndarray:
    """Linear velocity (m/s, in B) along a that regulates the contact force (eq. 6).

    v_z = [K_p3 (F_des - F_z) + K_d1 d/dt(F_des - F_z)] a_curr, with F_z the low-pass
    filtered contact force (N, positive when pressing) and ``error_rate`` (N/s) the
    derivative of the filtered error. Too little force -> move along +a (into the body).
    """
    return (K_p3 * (F_des - F_filtered) + K_d1 * error_rate) * _vec3(a_curr)


def force_pd_step(
    state,
    F_measured: float,
    F_des: float,
    a_curr,
    dt: float,
    alpha: float,
    K_p3: float,
    K_d1: float,
):
    """One controller period of eq. 6 with filter and derivative on the filtered signal.

    ``state`` = (F_filtered, e_prev, initialised). Returns (v_z (3,), new_state). The first
    call seeds the filter with the measurement and uses a zero derivative (no kick).
    """
    F_f, e_prev, initialised = state
    if not initialised:
        F_f = F_measured
        e_prev = F_des - F_measured
    F_f = lowpass_update(F_f, F_measured, alpha)
    e = F_des - F_f
    e_rate = (e - e_prev) / dt
    v = force_pd(F_des, F_f, e_rate, a_curr, K_p3, K_d1)
    return v, (F_f, e, 1.0)


# ----------------------------------------------------------------------------- position
def position_p(P_des_xy, p_BP, K_p4: float, K_p5: float, a_curr=None) -> np.ndarray:
    """Tip linear velocity (m/s, in B) tracking the desired tip x, y (eq. 7).

    v_x = K_p4 (P_x_des - P_x), v_y = K_p5 (P_y_des - P_y); the z component is left to the
    force loop (eq. 6), so this returns [v_x, v_y, 0]. With ``a_curr`` (the probe's approach
    vector, unit, in B) the velocity is [v_x, v_y, 0] minus its component along a_curr:
    the position loop moves the tip in the plane normal to the probe's axis and leaves
    the axis to the force loop alone (:func:`tangential`). For a vertical probe (the
    seed's, eq. 8) nothing changes; a probe tilted by phi would otherwise push into the
    body at sin(phi) times the sliding speed, faster than the force loop backs off.
    """
    P_des_xy = np.asarray(P_des_xy, dtype=float).reshape(2)
    p = _vec3(p_BP)
    v = np.array([K_p4 * (P_des_xy[0] - p[0]), K_p5 * (P_des_xy[1] - p[1]), 0.0])
    return v if a_curr is None else tangential(v, a_curr)


def tangential(v, a_curr) -> np.ndarray:
    """``v`` (3,) without its component along the unit vector ``a_curr``: v - (v . a) a."""
    v = _vec3(v)
    a = _vec3(a_curr)
    n = float(np.linalg.norm(a))
    if not n > 0.0:
        return v.copy()
    a = a / n
    return v - float(v @ a) * a


def assemble_twist(
    omega_total,
    v_position,
    v_force,
    max_tip_speed: float = math.inf,
    max_angular_speed: float = math.inf,
) -> np.ndarray:
    """Task twist xi_b = [omega_total; v_total] (eq. 8-9), saturated.

    v_total = v_position + v_force: eq. 8 stacks v_x, v_y (eq. 7) with the force velocity
    (eq. 6), which is a vector along a_curr; for a vertical probe this is exactly
    [v_x, v_y, v_z]. The angular part is scaled down (direction kept) to
    ``max_angular_speed`` (rad/s). The linear part is limited to ``max_tip_speed`` (m/s)
    with the force loop first (:func:`force_first_speed_limit`): a pressing force that
    rises while the tip slides is backed off at the force law's full rate, not slowed down
    with the sliding.
    """
    w = _vec3(omega_total).copy()
    nw = np.linalg.norm(w)
    if nw > max_angular_speed:
        w *= max_angular_speed / nw
    v = force_first_speed_limit(v_position, v_force, max_tip_speed)
    return np.concatenate([w, v])


def force_first_speed_limit(v_position, v_force, max_speed: float) -> np.ndarray:
    """v_force + s v_position (m/s) within ``max_speed``: v_force alone is scaled down to
    ``max_speed`` if it exceeds it (direction kept), then s in [0, 1] is the largest scale of
    v_position keeping |v_force + s v_position| <= max_speed. The force loop (eq. 6) has
    priority over the position loop (eq. 7): a sliding tip slows down for it."""
    vf = _vec3(v_force).copy()
    vp = _vec3(v_position)
    if not math.isfinite(max_speed):
        return vf + vp
    nf = float(np.linalg.norm(vf))
    if nf > max_speed:
        return vf * (max_speed / nf)
    total = vf + vp
    if float(np.linalg.norm(total)) <= max_speed:
        return total
    # |vf + s vp|^2 = max^2: pp s^2 + 2 fp s + (ff - max^2) = 0, ff <= max^2: one root >= 0.
    pp = float(vp @ vp)
    fp = float(vf @ vp)
    c = nf * nf - max_speed * max_speed
    s = (-fp + math.sqrt(max(fp * fp - pp * c, 0.0))) / pp
    return vf + min(max(s, 0.0), 1.0) * vp


# ----------------------------------------------------------------------------- diff IK
def manipulability(J) -> float:
    """Yoshikawa manipulability m = sqrt(det(J J^T)) (section II-C, after eq. 10)."""
    J = np.asarray(J, dtype=float)
    d = float(np.linalg.det(J @ J.T))
    return math.sqrt(max(d, 0.0))


def manipulability_gradient(q, jacobian, epsilon: float = 1e-4) -> np.ndarray:
    """Forward-difference gradient of m(q) (eq. 12); ``jacobian(q)`` returns the 6xn J.

    dm/dq_i ~ (m(q + eps e_i) - m(q)) / eps.
    """
    q = np.asarray(q, dtype=float).reshape(-1)
    m0 = manipulability(jacobian(q))
    grad = np.empty_like(q)
    for i in range(q.size):
        qi = q.copy()
        qi[i] += epsilon
        grad[i] = (manipulability(jacobian(qi)) - m0) / epsilon
    return grad


_UPPER_MASKS: dict = {}


def _upper_mask(n: int) -> np.ndarray:
    """(n, 1, n) bool mask of i <= j (cached per n)."""
    mask = _UPPER_MASKS.get(n)
    if mask is None:
        mask = _UPPER_MASKS[n] = np.triu(np.ones((n, n), bool))[:, None, :]
    return mask


def jacobian_derivatives(J) -> np.ndarray:
    """dJ/dq_i of the 6xn geometric Jacobian [w; v] of a frame on the last link of a serial
    chain of revolute joints (columns in chain order), from J alone: (n, 6, n), [i] = dJ/dq_i.

    Column j is the twist of joint j about the frame's origin: angular part the joint axis
    z_j, linear part v_j. Turning joint i <= j rotates joint j's axis and lever arm rigidly,
    so d(column j)/dq_i = [z_i x z_j; z_i x v_j]; turning a later joint i > j moves only the
    frame's origin (by v_i), so d(column j)/dq_i = [0; z_j x v_i].
    """
    J = np.asarray(J, dtype=float)
    z, v = J[:3], J[3:]  # (3, n) each
    n = J.shape[1]
    # S[i] = [z_i]x, the cross-product matrix of joint i's axis: S[i] @ w = z_i x w.
    S = np.zeros((n, 3, 3))
    S[:, 0, 1], S[:, 0, 2], S[:, 1, 2] = -z[2], z[1], -z[0]
    S[:, 1, 0], S[:, 2, 0], S[:, 2, 1] = z[2], -z[1], z[0]
    zz = S @ z  # [i] = z_i x z_j (3, n)
    zv = S @ v  # [i] = z_i x v_j
    later = zv.transpose(2, 1, 0)  # [i][:, j] = z_j x v_i
    upper = _upper_mask(n)  # i <= j
    dw = np.where(upper, zz, 0.0)
    dv = np.where(upper, zv, later)
    return np.concatenate([dw, dv], axis=1)


def manipulability_gradient_analytic(J) -> np.ndarray:
    """grad m(q) of m = sqrt(det(J J^T)) (eq. 12) from J alone, for a serial revolute chain
    (see :func:`jacobian_derivatives`): dm/dq_i = m tr((J J^T)^-1 dJ/dq_i J^T). One Jacobian
    instead of n + 1 (the forward difference of :func:`manipulability_gradient`). Zero at a
    singularity (m = 0)."""
    J = np.asarray(J, dtype=float)
    A = J @ J.T
    # Cholesky A = L L^T (LAPACK's posv, which also solves B = A^-1 J): m = sqrt(det A) =
    # prod(diag L). Not positive definite (info != 0): J is singular, m = 0.
    L, B, info = _posv(A, J)  # B = A^-1 J  (6, n)
    if info != 0:
        return np.zeros(J.shape[1])
    m = float(np.prod(np.diag(L)))
    if not m > 0.0:
        return np.zeros(J.shape[1])
    dJ = jacobian_derivatives(J)  # (n, 6, n)
    # tr(A^-1 dJ_i J^T) = sum_kl (A^-1 J)_kl (dJ_i)_kl  (A symmetric)
    return m * (dJ.reshape(dJ.shape[0], -1) @ B.ravel())


def damped_pseudo_inverse(J, sigma_threshold: float = 0.03, damping_max: float = 0.03):
    """Damped Moore-Penrose pseudo-inverse and exact null-space projector of J (eq. 10).

    Singular-value decomposition J = U S V^T. Each singular value s_i is inverted as
    s_i / (s_i^2 + lambda^2) with variable damping lambda^2 = damping_max^2 (1 - (s_min /
    sigma_threshold)^2) when s_min < sigma_threshold, else 0 (the plain J^+ away from
    singularities). The null-space projector I - V_r V_r^T uses the rank-r row space of J
    (equal to I - J^+ J for a full-rank J), so the secondary task never leaks into the task.

    Returns (J_pinv (n x 6), N (n x n), lambda).
    """
    J = np.ascontiguousarray(J, dtype=float)
    U, Vt, inv, rank, lam2 = kernels.damped_svd(J, float(sigma_threshold), float(damping_max))
    m = inv.size
    J_pinv = (Vt[:m].T * inv) @ U[:, :m].T
    Vr = Vt[:rank]
    N = np.eye(J.shape[1]) - Vr.T @ Vr
    return J_pinv, N, math.sqrt(lam2)


def joint_velocity_bounds(
    q, q_min, q_max, dq_max, margin: float, braking_acceleration=None, period: float = 0.01
):
    """Per-joint velocity bounds (rad/s) from speed limits and a joint-limit margin.

    Within ``margin`` (rad) of a limit, the allowed speed towards it ramps linearly from
    dq_max down to 0 at the limit (and stays 0 beyond it); away from the limit is always
    allowed. With ``braking_acceleration`` (rad/s^2 per joint; None or 0: unlimited) the
    speed towards a limit is also at most the one from which a command changing by at most
    that much each ``period`` (s) still stops before the limit
    (:func:`drake_rus.control.kernels.braking_speed`): the hardware's command guard limits
    the command's acceleration (``hardware_interface.max_joint_acceleration``), and a ramp
    it cannot follow would carry the joint past its limit. Returns (lower <= 0, upper >= 0).
    """
    q = _f64(q)
    return kernels.joint_velocity_bounds(
        q,
        _f64(q_min),
        _f64(q_max),
        _f64(dq_max),
        float(margin),
        braking_accelerations(braking_acceleration, q.size),
        float(period),
    )


def braking_accelerations(acceleration, n: int) -> np.ndarray:
    """Per-joint braking accelerations (rad/s^2) for the kernels from one value or ``n``;
    zeros (unlimited) for None. A clear ValueError for any other shape."""
    if acceleration is None:
        return np.zeros(n)
    a = np.asarray(acceleration, dtype=np.float64)
    if a.ndim == 0:
        return np.full(n, float(a))
    if a.shape != (n,):
        raise ValueError(
            f"braking_acceleration: expected one value or {n} (one per joint, rad/s^2), "
            f"got shape {a.shape}"
        )
    return np.ascontiguousarray(a)


def scale_into_bounds(qdot, lower, upper) -> np.ndarray:
    """Scales qdot uniformly (direction kept) so that lower <= qdot <= upper."""
    return kernels.scale_into_bounds(_f64(qdot), _f64(lower), _f64(upper))


def null_space_diff_ik(
    J, xi_b, qdot_null, *, sigma_threshold: float = 0.03, damping_max: float = 0.03
) -> np.ndarray:
    """qdot = J^+ xi_b + (I - J^+ J) qdot_null (eq. 10) with the damped pseudo-inverse.

    The same arithmetic as :func:`damped_pseudo_inverse` applied to the two vectors, without
    forming J^+ and N (one SVD, a few matrix-vector products)."""
    return kernels.null_space_diff_ik(
        _f64(J), _f64(xi_b), _f64(qdot_null), float(sigma_threshold), float(damping_max)
    )


def solve_joint_velocities(
    q,
    xi_b,
    jacobian,
    *,
    q_min,
    q_max,
    dq_max,
    joint_limit_margin: float,
    K_p6: float = 0.0,
    epsilon: float = 1e-4,
    qdot_null=None,
    sigma_threshold: float = 0.03,
    damping_max: float = 0.03,
    braking_acceleration=None,
    period: float = 0.01,
) -> np.ndarray:
    """The whole differential IK: eq. 10-12 then the joint-limit margin and speed limits.

    qdot_null = K_p6 grad m(q) (eq. 11-12) unless given precomputed; qdot from eq. 10;
    finally qdot is brought into the per-joint bounds of :func:`joint_velocity_bounds`
    (``braking_acceleration``, ``period``: the braking distance to a limit) so the
    probe path keeps its direction while slowing before a joint limit: scaled uniformly,
    blended with a joint near its limit held at its bound while the other six solve the task
    exactly (the arm's one redundant degree of freedom;
    :func:`drake_rus.control.kernels.saturate_one_joint`). A joint at its limit therefore no
    longer stops the probe: only a task the other joints cannot carry slows down. Non-finite
    input gives zeros.
    """
    q = _f64(q)
    xi_b = _f64(xi_b)
    if not (all_finite(q) and all_finite(xi_b)):
        return np.zeros_like(q)
    J = jacobian(q)
    if qdot_null is None:
        qdot_null = (
            K_p6 * manipulability_gradient(q, jacobian, epsilon) if K_p6 > 0 else np.zeros_like(q)
        )
    return kernels.solve_joint_velocities(
        q,
        xi_b,
        _f64(J),
        _f64(qdot_null),
        _f64(q_min),
        _f64(q_max),
        _f64(dq_max),
        float(joint_limit_margin),
        braking_accelerations(braking_acceleration, q.size),
        float(period),
        float(sigma_threshold),
        float(damping_max),
    )


# ----------------------------------------------------------------------------- pivot ends
def pivot_end_angles(
    R_BK,
    p_BK,
    points_K,
    pivot_point,
    a0,
    o,
    *,
    probe_radius: float,
    half_angle: float,
    depth: float,
    slab_half_width: float,
    max_angle: float,
    step: float = math.radians(0.25),
) -> tuple:
    """Predicted tilt angles (rad) where the kidney leaves the image on each side of a pivot
    (beyond the seed; its pivot is eq. 23).

    The probe tip stays at ``pivot_point`` (B) and its approach vector a(theta) = a0 cos theta
    + (o x a0) sin theta turns about the array direction ``o`` (eq. 23's sign: positive
    theta is a positive rotation about o). The probe frame at theta is x_P = o, z_P = a,
    y_P = a x o (origin at the tip, the face centre). A template point (``points_K``, in K,
    placed by X_BK = (R_BK, p_BK)) is imaged when it lies in the image plane's slab
    |y_P| <= ``slab_half_width`` and inside the curvilinear fan (apex ``probe_radius`` behind
    the face, |scan-line angle| <= ``half_angle``, 0 <= depth along the line <= ``depth``).

    Returns (theta_plus >= 0, theta_minus <= 0): on each side the largest tilt (on a grid of
    ``step``, up to ``max_angle``) at which some point is imaged; 0 on a side where none is
    imaged past the start; +-``max_angle`` when the kidney is still imaged there.
    """
    o = np.asarray(o, float).reshape(3)
    o = o / np.linalg.norm(o)
    a0 = np.asarray(a0, float).reshape(3)
    a0 = a0 - float(a0 @ o) * o
    a0 = a0 / np.linalg.norm(a0)
    b0 = np.cross(o, a0)  # a(theta) = a0 cos + b0 sin
    q = (
        np.asarray(points_K, float).reshape(-1, 3) @ np.asarray(R_BK, float).T
        + np.asarray(p_BK, float).reshape(3)
        - np.asarray(pivot_point, float).reshape(3)
    )
    x = q @ o  # along the array: unchanged by the tilt
    qa, qb = q @ a0, q @ b0
    n = max(1, int(math.ceil(max_angle / step)))
    ends = []
    for side in (1.0, -1.0):
        th = side * np.linspace(0.0, max_angle, n + 1)  # (T,)
        c, s = np.cos(th)[:, None], np.sin(th)[:, None]
        z = qa[None, :] * c + qb[None, :] * s  # along a(theta)
        # y_P = (a x o) . q with a x o = a0 sin - b0 cos:
        y = qa[None, :] * s - qb[None, :] * c
        zc = z + probe_radius
        line = np.arctan2(x[None, :], zc)
        d = np.hypot(x[None, :], zc) - probe_radius
        seen = (
            (np.abs(y) <= slab_half_width)
            & (np.abs(line) <= half_angle)
            & (d >= 0.0)
            & (d <= depth)
        ).any(axis=1)
        idx = np.flatnonzero(seen)
        ends.append(float(th[idx[-1]]) if len(idx) else 0.0)
    return ends[0], ends[1]


def template_section_area(
    R_BK,
    p_BK,
    points_K,
    R_BP,
    p_BP,
    *,
    probe_radius: float,
    half_angle: float,
    depth: float,
    slab_half_width: float,
) -> float:
    """Area (m^2) of the registered template's section in the image of a probe at (R_BP,
    p_BP): the convex hull, in the image plane, of the template points (``points_K``, in K,
    placed by X_BK = (R_BK, p_BK)) that are imaged (within ``slab_half_width`` of the plane
    and inside the curvilinear fan, as :func:`pivot_end_angles` counts them). 0 when fewer
    than 3 points are imaged or they span no area: the template puts the kidney out of
    view."""
    R_BP = np.asarray(R_BP, float)
    q = (
        np.asarray(points_K, float).reshape(-1, 3) @ np.asarray(R_BK, float).T
        + np.asarray(p_BK, float).reshape(3)
        - np.asarray(p_BP, float).reshape(3)
    ) @ R_BP  # in P
    zc = q[:, 2] + probe_radius
    d = np.hypot(q[:, 0], zc) - probe_radius
    seen = (
        (np.abs(q[:, 1]) <= slab_half_width)
        & (np.abs(np.arctan2(q[:, 0], zc)) <= half_angle)
        & (d >= 0.0)
        & (d <= depth)
    )
    if np.count_nonzero(seen) < 3:
        return 0.0
    try:
        return float(ConvexHull(q[seen][:, [0, 2]]).volume)  # a 2-D hull's volume is its area
    except QhullError:
        return 0.0
