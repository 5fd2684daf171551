"""Compiled kernels (numba) of the differential IK's arithmetic (eq. 10-12), run every
control period.

The laws in :mod:`drake_rus.control.laws` call these; they are the same equations written
as loops over 6 x 7 arrays, compiled once (``cache=True``: later processes load the machine
code from ``__pycache__``, or numba's user cache when the package directory is read-only).
In Python the same arithmetic is a few dozen numpy calls of 1-5 us each, most of it call
overhead on arrays this small. :func:`warm_up` compiles (or loads) every kernel; the systems
call it when they are built, so a live run never compiles inside the control loop.

Arguments are float64 arrays (C-contiguous) and floats; the wrappers in ``laws`` convert.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def damped_svd(J, sigma_threshold, damping_max):
    """(U, V^T, damped inverse singular values, rank, lambda^2) of J (m x n, m <= n): the
    variable damping of ``laws.damped_pseudo_inverse`` (s / (s^2 + lambda^2) with lambda^2 =
    damping_max^2 (1 - (s_min / sigma_threshold)^2) below the threshold, else 1 / s, 0 for
    s <= 1e-12); rank counts s > 1e-9."""
    U, s, Vt = np.linalg.svd(J)
    s_min = s[s.size - 1]
    lam2 = 0.0
    if s_min < sigma_threshold:
        lam2 = damping_max * damping_max * (1.0 - (s_min / sigma_threshold) ** 2)
    inv = np.empty(s.size)
    rank = 0
    for i in range(s.size):
        if lam2 > 0.0:
            inv[i] = s[i] / (s[i] * s[i] + lam2)
        elif s[i] > 1e-12:
            inv[i] = 1.0 / max(s[i], 1e-300)
        else:
            inv[i] = 0.0
        if s[i] > 1e-9:
            rank += 1
    return U, Vt, inv, rank, lam2


@njit(cache=True)
def null_space_diff_ik(J, xi_b, qdot_null, sigma_threshold, damping_max):
    """qdot = J^+ xi_b + (I - V_r V_r^T) qdot_null (eq. 10), with the damped pseudo-inverse
    from :func:`damped_svd` and the rank-r row space V_r of J."""
    U, Vt, inv, rank, _ = damped_svd(J, sigma_threshold, damping_max)
    m, n = J.shape
    # w = inv * (U^T xi_b); qdot = V_m w
    w = np.zeros(m)
    for k in range(m):
        acc = 0.0
        for i in range(m):
            acc += U[i, k] * xi_b[i]
        w[k] = inv[k] * acc
    qdot = qdot_null.copy()
    for k in range(m):
        for j in range(n):
            qdot[j] += Vt[k, j] * w[k]
    # minus V_r (V_r^T qdot_null)
    for k in range(rank):
        c = 0.0
        for j in range(n):
            c += Vt[k, j] * qdot_null[j]
        for j in range(n):
            qdot[j] -= Vt[k, j] * c
    return qdot


@njit(cache=True)
def braking_speed(distance, acceleration, period):
    """The largest speed (rad/s) from which a command whose change is limited to
    ``acceleration`` (rad/s^2) each ``period`` (s) still stops within ``distance`` (rad): v
    with v^2 / (2 a) + v T / 2 = d - a T^2 / 8: a command held one period, then ramped down
    by a T each period to 0, travels v^2 / (2 a) + v T / 2 plus at most a T^2 / 8 (the last,
    partial step of the ramp). inf when ``acceleration`` is not positive (no limit); 0 at or
    past the limit."""
    if not acceleration > 0.0:
        return math.inf
    h = 0.5 * acceleration * period
    d = max(distance - 0.125 * acceleration * period * period, 0.0)
    return math.sqrt(h * h + 2.0 * acceleration * d) - h


@njit(cache=True)
def joint_velocity_bounds(q, q_min, q_max, dq_max, margin, acceleration, period):
    """(lower <= 0, upper >= 0) per-joint velocity bounds (rad/s): dq_max, ramping linearly
    to 0 over the last ``margin`` (rad) before a joint limit (towards it only), and no
    faster towards a limit than a command changing by at most ``acceleration`` (rad/s^2,
    per joint; 0: unlimited) each ``period`` (s) can stop before it
    (:func:`braking_speed`)."""
    n = q.size
    lo = np.empty(n)
    up = np.empty(n)
    for i in range(n):
        up[i] = min(max((q_max[i] - q[i]) / margin, 0.0), 1.0) * dq_max[i]
        lo[i] = -(min(max((q[i] - q_min[i]) / margin, 0.0), 1.0) * dq_max[i])
        up[i] = min(up[i], braking_speed(q_max[i] - q[i], acceleration[i], period))
        lo[i] = max(lo[i], -braking_speed(q[i] - q_min[i], acceleration[i], period))
    return lo, up


@njit(cache=True)
def _joint_scale(v, lower, upper):
    """The largest admissible scale of one joint's velocity v within [lower, upper]: 1 when
    inside, 0 when its bound has the other sign."""
    if v > upper:
        return upper / v if v > 0.0 else 0.0
    if v < lower:
        return lower / v if v < 0.0 else 0.0
    return 1.0


@njit(cache=True)
def bound_scale(qdot, lower, upper):
    """The largest s in [0, 1] with lower <= s qdot <= upper: the smallest joint's
    :func:`_joint_scale`."""
    s = 1.0
    for i in range(qdot.size):
        s = min(s, _joint_scale(qdot[i], lower[i], upper[i]))
    return max(s, 0.0)


@njit(cache=True)
def scale_into_bounds(qdot, lower, upper):
    """qdot scaled uniformly (direction kept) into lower <= qdot <= upper by
    :func:`bound_scale`. A copy of qdot when nothing is violated."""
    return qdot * bound_scale(qdot, lower, upper)


@njit(cache=True)
def saturate_one_joint(J, xi_b, qdot, lower, upper, dq_max, sigma_threshold, damping_max):
    """qdot (from eq. 10) brought into lower <= qdot <= upper, keeping the task J qdot = xi_b
    where the arm's redundancy allows. Returns (qdot, share of the task kept).

    Uniform scaling (:func:`bound_scale`, share s0) unless a joint near its position limit
    (its bound lowered below ``dq_max`` by :func:`joint_velocity_bounds`) limits it: then
    that joint (the most limiting such) is held at its bound and the other joints solve the
    task exactly (one step of the saturation in the null space of Flacco, De Luca and
    Khatib, ICRA 2012), scaled into the bounds (share s1). The two are blended with the
    held solution's weight w = (1 - (s0 / s1)^2) d c (0 when s1 <= s0), d the depth into the
    joint's ramp (0 at its start, 1 at the limit) and c the remaining joints' conditioning
    (0 at a smallest singular value of ``sigma_threshold``, 1 from twice that): a command
    continuous in q and the task, where choosing one or the other jumped. Both solve the task
    in the same direction and lie in the box of bounds, and so does the blend."""
    s0 = bound_scale(qdot, lower, upper)
    m, n = J.shape
    if s0 >= 1.0 or n != m + 1:
        return qdot * s0, s0
    j = -1
    worst = 1.0
    depth = 0.0
    for i in range(n):
        r = _joint_scale(qdot[i], lower[i], upper[i])
        bound = upper[i] if qdot[i] > upper[i] else -lower[i]  # its magnitude, if violated
        if r < worst and dq_max[i] > 0.0 and bound < dq_max[i]:  # violated, near its limit
            worst = r
            j = i
            depth = min(max(1.0 - bound / dq_max[i], 0.0), 1.0)
    if j < 0:
        return qdot * s0, s0
    b = upper[j] if qdot[j] > upper[j] else lower[j]
    Jf = np.empty((m, m))
    rhs = xi_b.copy()
    for r in range(m):
        rhs[r] -= J[r, j] * b
        c = 0
        for i in range(n):
            if i != j:
                Jf[r, c] = J[r, i]
                c += 1
    U, Vt, inv, rank, lam2 = damped_svd(Jf, sigma_threshold, damping_max)
    if rank < m or lam2 > 0.0 or not inv[m - 1] > 0.0:
        return qdot * s0, s0
    conditioning = min(max((1.0 / inv[m - 1]) / sigma_threshold - 1.0, 0.0), 1.0)
    qf = null_space_diff_ik(Jf, rhs, np.zeros(m), sigma_threshold, damping_max)
    held = np.empty(n)
    c = 0
    for i in range(n):
        if i == j:
            held[i] = b
        else:
            held[i] = qf[c]
            c += 1
    s1 = bound_scale(held, lower, upper)
    if not s1 > s0:
        return qdot * s0, s0
    w = (1.0 - (s0 / s1) ** 2) * depth * conditioning
    return (1.0 - w) * s0 * qdot + w * s1 * held, (1.0 - w) * s0 + w * s1


@njit(cache=True)
def _finite(x):
    for v in x.flat:
        if not math.isfinite(v):
            return False
    return True


@njit(cache=True)
def solve_joint_velocities(
    q,
    xi_b,
    J,
    qdot_null,
    q_min,
    q_max,
    dq_max,
    margin,
    acceleration,
    period,
    sigma_threshold,
    damping_max,
):
    """eq. 10 then the joint-limit margin, braking distance and speed limits, one joint
    saturated (:func:`saturate_one_joint`; ``laws.solve_joint_velocities`` with the Jacobian
    and the null-space velocity given); zeros for non-finite input."""
    if not (_finite(q) and _finite(xi_b)):
        return np.zeros(q.size)
    qdot = null_space_diff_ik(J, xi_b, qdot_null, sigma_threshold, damping_max)
    lo, up = joint_velocity_bounds(q, q_min, q_max, dq_max, margin, acceleration, period)
    qdot, _ = saturate_one_joint(J, xi_b, qdot, lo, up, dq_max, sigma_threshold, damping_max)
    if not _finite(qdot):
        return np.zeros(q.size)
    return qdot


def warm_up() -> None:
    """Compiles (or loads from the cache) every kernel for the types the laws pass."""
    J = np.hstack([np.eye(6), np.zeros((6, 1))])
    q = np.zeros(7)
    solve_joint_velocities(
        q, np.zeros(6), J, q, q - 1.0, q + 1.0, q + 1.0, 0.1, q + 2.0, 0.01, 0.03, 0.03
    )
