"""Unit tests of the pure control laws (seed eq. 1-12)."""

import math

import numpy as np
import pytest
from pydrake.common.eigen_geometry import AngleAxis
from pydrake.math import RollPitchYaw, RotationMatrix

from drake_rus.control import kernels, laws

Q0 = np.array([0.0, 0.15, 0.0, -2.0, 0.0, 2.15, 0.785])


def rot(rpy):
    return RotationMatrix(RollPitchYaw(rpy)).matrix()


def so3_exp(w):
    th = np.linalg.norm(w)
    if th < 1e-15:
        return np.eye(3)
    k = w / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K


# ------------------------------------------------------------------ eq. 1-2
def test_approach_alignment_rotates_a_towards_a_des():
    a = np.array([0.0, 0.0, -1.0])
    a_des = np.array([math.sin(0.3), 0.0, -math.cos(0.3)])
    w = laws.approach_alignment(a, a_des, np.zeros(3), K_p1=2.0, K_p11=0.0)
    # eq. 1: e_a = a x a_des, times K_p1
    np.testing.assert_allclose(w, 2.0 * np.cross(a, a_des))
    # Rotating a by w (da/dt = w x a) reduces the angle to a_des.
    a_next = a + 1e-3 * np.cross(w, a)
    assert laws.angle_between(a_next, a_des) < laws.angle_between(a, a_des)


def test_approach_alignment_feedforward_term():
    a = np.array([0.0, 0.0, -1.0])
    a_dot = np.array([0.1, 0.0, 0.0])
    w = laws.approach_alignment(a, a, a_dot, K_p1=5.0, K_p11=1.0)
    # No error: only the K_p11 (a x da_des/dt) term, and it makes da/dt = a_dot.
    np.testing.assert_allclose(w, np.cross(a, a_dot))
    np.testing.assert_allclose(np.cross(w, a), a_dot, atol=1e-12)


# ------------------------------------------------------------------ eq. 3-5
def test_orientation_vector_term_is_about_a_only():
    R = rot([0.2, -0.1, 0.4])
    a, o = R[:, 2], R[:, 0]
    o_des = rot([0.2, -0.1, 0.9])[:, 0]
    w = laws.orientation_vector_alignment(o, o_des, a, K_p2=3.0)
    e_o = np.cross(o, o_des)
    np.testing.assert_allclose(w, 3.0 * (e_o @ a) * a)
    assert np.linalg.norm(np.cross(w, a)) < 1e-12  # parallel to a: does not tilt a


def test_orientation_alignment_converges_from_20_deg_step():
    """Closed loop of eq. 5 on a kinematic rotation: 20 deg error -> < 1 deg in 2 s."""
    R_des = rot([math.pi, 0.0, 0.3])
    R = R_des @ rot([math.radians(20.0), 0.0, 0.0]).T @ rot([0, 0, math.radians(30)])
    a_des, o_des = R_des[:, 2], R_des[:, 0]
    dt = 0.005
    for _ in range(int(2.0 / dt)):
        w = laws.orientation_alignment(R, a_des, o_des, np.zeros(3), 3.0, 1.0, 3.0)
        R = so3_exp(w * dt) @ R
    assert laws.angle_between(R[:, 2], a_des) < math.radians(1.0)
    assert laws.angle_between(R[:, 0], o_des) < math.radians(1.0)


def test_angle_between():
    assert laws.angle_between([1, 0, 0], [0, 1, 0]) == pytest.approx(math.pi / 2)
    assert laws.angle_between([1, 0, 0], [-1, 0, 0]) == pytest.approx(math.pi)
    assert laws.angle_between([1, 0, 0], [1, 1e-9, 0]) == pytest.approx(1e-9)


# ------------------------------------------------------------------ eq. 6
def test_force_pd_direction_and_value():
    a = np.array([0.0, 0.0, -1.0])
    v = laws.force_pd(9.0, 4.0, 0.0, a, K_p3=0.01, K_d1=0.0)
    np.testing.assert_allclose(v, 0.05 * a)  # too little force: move into the body (along a)
    v = laws.force_pd(9.0, 12.0, 0.0, a, K_p3=0.01, K_d1=0.0)
    assert v @ a < 0  # too much: back off
    v = laws.force_pd(9.0, 9.0, 10.0, a, K_p3=0.01, K_d1=0.002)
    np.testing.assert_allclose(v, 0.02 * a)


def test_lowpass_step_response_time_constant():
    dt, fc = 0.005, 10.0
    alpha = laws.lowpass_alpha(dt, fc)
    y, t = 0.0, 0.0
    tau = 1 / (2 * math.pi * fc)
    while t < tau - 1e-12:
        y = laws.lowpass_update(y, 1.0, alpha)
        t += dt
    assert y == pytest.approx(1 - math.exp(-1), abs=0.06)


def test_force_pd_step_filters_and_differentiates_filtered_error():
    a = np.array([0.0, 0.0, -1.0])
    dt, alpha = 0.005, 0.5
    state = (0.0, 0.0, 0.0)
    v, state = laws.force_pd_step(state, 2.0, 9.0, a, dt, alpha, 0.01, 0.001)
    # First call seeds the filter: no derivative kick.
    np.testing.assert_allclose(v, 0.01 * 7.0 * a)
    assert state[0] == pytest.approx(2.0)
    v, state = laws.force_pd_step(state, 4.0, 9.0, a, dt, alpha, 0.01, 0.001)
    F_f = 3.0  # 2 + 0.5 (4 - 2)
    e_rate = ((9 - F_f) - 7.0) / dt
    np.testing.assert_allclose(v, (0.01 * (9 - F_f) + 0.001 * e_rate) * a)
    # A single-sample spike moves the filtered force only by alpha of the spike.
    _, s2 = laws.force_pd_step(state, 100.0, 9.0, a, dt, alpha, 0.01, 0.001)
    assert s2[0] == pytest.approx(3.0 + 0.5 * 97.0)


def test_force_loop_settles_on_a_spring():
    """Eq. 6 on a 1-D spring body (k = 900 N/m) reaches 9 N +- 0.5 within 2 s."""
    k, dt = 900.0, 0.005
    a = np.array([0.0, 0.0, -1.0])
    depth, state = 0.0, (0.0, 0.0, 0.0)
    alpha = laws.lowpass_alpha(dt, 15.0)
    forces = []
    for _ in range(int(2.0 / dt)):
        F = k * max(depth, 0.0)
        v, state = laws.force_pd_step(state, F, 9.0, a, dt, alpha, 0.004, 0.0002)
        depth += float(v @ a) * dt
        forces.append(F)
    assert abs(forces[-1] - 9.0) < 0.5
    assert max(forces) < 12.0


# ------------------------------------------------------------------ eq. 7-9
def test_position_p():
    v = laws.position_p([0.5, 0.1], [0.4, 0.2, 0.3], K_p4=2.0, K_p5=3.0)
    np.testing.assert_allclose(v, [0.2, -0.3, 0.0])
    # A vertical probe: eq. 7 unchanged.
    v = laws.position_p([0.5, 0.1], [0.4, 0.2, 0.3], 2.0, 3.0, a_curr=[0, 0, -1])
    np.testing.assert_allclose(v, [0.2, -0.3, 0.0])


def test_position_p_never_presses_along_a_tilted_probe():
    """A probe tilted by 27 deg (towards +x) sliding towards +x: eq. 7's horizontal
    velocity has sin(27 deg) of itself along the probe's axis (into the body); in the
    plane normal to the axis it has none, and still moves the tip towards the target."""
    phi = math.radians(27.0)
    a = np.array([math.sin(phi), 0.0, -math.cos(phi)])
    v_seed = laws.position_p([0.44, 0.0], [0.40, 0.0, 0.2], 2.0, 2.0)
    assert float(v_seed @ a) == pytest.approx(0.08 * math.sin(phi))
    v = laws.position_p([0.44, 0.0], [0.40, 0.0, 0.2], 2.0, 2.0, a_curr=a)
    assert abs(float(v @ a)) < 1e-12
    assert v[0] > 0 and v[2] > 0  # towards the target, rising along the tilted skin
    np.testing.assert_allclose(laws.tangential([1.0, 2.0, 3.0], [0, 0, 2.0]), [1.0, 2.0, 0.0])


def _slide_on_tilted_skin(a_curr_in_position: bool, phi_deg: float = 27.0):
    """Peak contact force (N) of a probe tilted by phi, normal to skin of that slope
    (stiffness 3 N/mm), sliding 40 mm towards +x under eq. 6-9 at 100 Hz with the
    default gains: the tip follows the commanded velocity exactly."""
    phi = math.radians(phi_deg)
    a = np.array([math.sin(phi), 0.0, -math.cos(phi)])  # skin normal, into the body
    k, dt, alpha = 3000.0, 0.01, laws.lowpass_alpha(0.01, 1.25)
    p = np.array([0.0, 0.0, 0.0])
    depth0 = 9.0 / k
    state, peak = (0.0, 0.0, 0.0), 0.0
    for _ in range(300):
        F = k * max(depth0 + float(p @ a), 0.0)
        peak = max(peak, F)
        v_f, state = laws.force_pd_step(state, F, 9.0, a, dt, alpha, 0.004, 0.00001)
        v_p = laws.position_p([0.04, 0.0], p, 2.0, 2.0, a_curr=a if a_curr_in_position else None)
        xi = laws.assemble_twist(np.zeros(3), v_p, v_f, max_tip_speed=0.05)
        p = p + xi[3:] * dt
    return peak, p


def test_sliding_a_tilted_probe_keeps_the_force():
    """Case 9 of KiTS19 in small: with eq. 7 in the horizontal plane the slide presses the
    tilted probe into the skin, to more than 15 N; in the plane normal to the probe
    the force stays at the desired 9 N, and the tip still reaches the target."""
    peak_seed, _ = _slide_on_tilted_skin(False)
    peak, p = _slide_on_tilted_skin(True)
    assert peak_seed > 15.0
    assert peak < 9.5
    assert abs(p[0] - 0.04) < 2e-3


def test_assemble_twist_orders_and_saturates():
    xi = laws.assemble_twist([0.1, 0, 0], [0.01, 0, 0], [0, 0, -0.02])
    np.testing.assert_allclose(xi, [0.1, 0, 0, 0.01, 0, -0.02])
    xi = laws.assemble_twist(
        [3.0, 4.0, 0], [0.3, 0, 0], [0, 0, 0.04], max_tip_speed=0.05, max_angular_speed=0.5
    )
    np.testing.assert_allclose(np.linalg.norm(xi[:3]), 0.5)
    np.testing.assert_allclose(xi[:3] / 0.5, [0.6, 0.8, 0])  # direction kept
    np.testing.assert_allclose(np.linalg.norm(xi[3:]), 0.05)
    # The force loop first: its 40 mm/s is kept whole, the position loop gets the rest.
    np.testing.assert_allclose(xi[3:], [0.03, 0, 0.04])


def test_force_first_speed_limit():
    # Within the limit: the plain sum.
    np.testing.assert_allclose(
        laws.force_first_speed_limit([0.01, 0, 0], [0, 0, 0.02], 0.05), [0.01, 0, 0.02]
    )
    # A force velocity above the limit alone: scaled to it, no position motion at all.
    np.testing.assert_allclose(
        laws.force_first_speed_limit([0.05, 0, 0], [0, 0, -0.1], 0.05), [0, 0, -0.05]
    )
    # Opposed parts: the position part is scaled so that the sum is on the limit.
    v = laws.force_first_speed_limit([0.1, 0.0, 0.0], [-0.02, 0.0, 0.01], 0.05)
    assert np.linalg.norm(v) == pytest.approx(0.05)
    s = (v[0] + 0.02) / 0.1
    np.testing.assert_allclose(v, [-0.02 + 0.1 * s, 0.0, 0.01])
    assert 0 < s < 1
    # An unlimited speed: the sum.
    np.testing.assert_allclose(
        laws.force_first_speed_limit([1.0, 0, 0], [0, 1.0, 0], math.inf), [1.0, 1.0, 0]
    )


# ------------------------------------------------------------------ eq. 10-12
def test_manipulability_matches_singular_values(kin):
    J = kin.jacobian(Q0)
    s = np.linalg.svd(J, compute_uv=False)
    assert laws.manipulability(J) == pytest.approx(np.prod(s), rel=1e-9)
    assert laws.manipulability(np.zeros((6, 7))) == 0.0


def test_manipulability_gradient_matches_central_difference(kin):
    g = laws.manipulability_gradient(Q0, kin.jacobian, 1e-6)
    for i in range(7):
        dq = np.zeros(7)
        dq[i] = 1e-5
        c = (
            laws.manipulability(kin.jacobian(Q0 + dq)) - laws.manipulability(kin.jacobian(Q0 - dq))
        ) / 2e-5
        assert g[i] == pytest.approx(c, abs=1e-4)
    assert np.linalg.norm(g) > 1e-3


def test_damped_pinv_is_exact_away_from_singularity(kin):
    J = kin.jacobian(Q0)
    J_pinv, N, lam = laws.damped_pseudo_inverse(J, 0.03, 0.03)
    assert lam == 0.0
    np.testing.assert_allclose(J_pinv, np.linalg.pinv(J), atol=1e-9)
    np.testing.assert_allclose(J @ N, 0, atol=1e-9)
    np.testing.assert_allclose(N @ N, N, atol=1e-9)


def test_damped_pinv_bounded_at_singularity():
    J = np.zeros((6, 7))
    J[:5, :5] = np.eye(5)
    J[5, 5] = 1e-6  # nearly singular
    J_pinv, N, lam = laws.damped_pseudo_inverse(J, 0.03, 0.03)
    assert lam > 0.029
    assert np.abs(J_pinv).max() < 1.0 / (2 * 0.03) + 1e-9  # s/(s^2+l^2) <= 1/(2l)
    raw = np.linalg.pinv(J, rcond=1e-12)
    assert np.abs(raw).max() > 1e5


def test_null_space_ik_tracks_twist_and_null_motion_is_invisible(kin):
    J = kin.jacobian(Q0)
    xi = np.array([0.05, -0.02, 0.01, 0.01, 0.02, -0.03])
    rng = np.random.default_rng(0)
    q_null = rng.normal(size=7)
    qdot = laws.null_space_diff_ik(J, xi, q_null)
    np.testing.assert_allclose(J @ qdot, xi, atol=1e-9)
    qdot0 = laws.null_space_diff_ik(J, xi, np.zeros(7))
    assert np.linalg.norm(qdot - qdot0) > 1e-3  # the null-space term moved the joints


def test_joint_limit_bounds_and_scaling():
    q_min, q_max = -np.ones(3), np.ones(3)
    lo, up = laws.joint_velocity_bounds([0.0, 0.95, -1.2], q_min, q_max, [1, 1, 1], 0.1)
    np.testing.assert_allclose(up, [1, 0.5, 1])
    np.testing.assert_allclose(lo, [-1, -1, 0])
    qdot = laws.scale_into_bounds([0.2, 1.0, 0.1], lo, up)
    np.testing.assert_allclose(qdot, [0.1, 0.5, 0.05])  # uniform scaling keeps direction
    qdot = laws.scale_into_bounds([0.2, 0.1, -0.1], lo, up)
    np.testing.assert_allclose(qdot, 0)  # would push joint 3 further past its limit


def test_braking_speed_stops_a_rate_limited_command_at_the_limit():
    """From the braking speed, a command ramped down by a T a period (held one period
    first) stops within the distance, at most a T^2 / 8 short of it; the bound binds only
    near a limit."""
    a, T = 2.0, 0.01
    for d in (0.0, 0.001, 0.03, 0.1, 0.4):
        v = kernels.braking_speed(d, a, T)
        travelled, u = 0.0, v
        while u > 0.0:
            travelled += u * T
            u -= a * T
        assert 0.0 <= travelled <= d
        assert travelled >= d - 0.13 * a * T * T - 1e-12  # no slower than the ramp needs
    assert kernels.braking_speed(-0.01, a, T) == 0.0  # past the limit: nothing towards it
    assert kernels.braking_speed(0.1, 0.0, T) == math.inf  # no acceleration limit
    # Bounds: the ramp alone far from the limit's braking distance; braking where faster.
    q_min, q_max = -np.ones(4), np.ones(4)
    q = [0.0, 0.995, 0.95, 0.8]
    lo, up = laws.joint_velocity_bounds(q, q_min, q_max, [1] * 4, 0.1, braking_acceleration=2.0)
    brake = [kernels.braking_speed(d, 2.0, 0.01) for d in (0.05, 0.2)]
    np.testing.assert_allclose(up, [1.0, 0.05] + brake)  # free; the ramp; braking, twice
    assert brake[0] < 0.5 and brake[1] < 1.0
    np.testing.assert_allclose(lo, -1.0)  # away from the lower limits: not braked
    np.testing.assert_allclose(
        laws.joint_velocity_bounds(q, q_min, q_max, [1] * 4, 0.1)[1], [1.0, 0.05, 0.5, 1.0]
    )
    with pytest.raises(ValueError, match="braking_acceleration: expected one value or 4"):
        laws.joint_velocity_bounds(q, q_min, q_max, [1] * 4, 0.1, [2.0, 2.0])


def _guarded_wrist_turn(kin, braking_acceleration):
    """A 40 deg turn about the probe's axis into joint 7's limit from 0.3 rad before it, at
    the IK's 0.6 rad/s angular speed, each command passed through the hardware's command
    guard (hardware.core.guard_command, its default 2 rad/s^2 and joint speeds) before
    the joints integrate it. Returns joint 7's largest excursion past its limit (rad) and
    the turn's remaining angle (rad)."""
    from drake_rus.hardware.config import HardwareConfig
    from drake_rus.hardware.core import guard_command

    hw = HardwareConfig()
    q = Q0.copy()
    q[6] = kin.q_max[6] - 0.3
    X0 = kin.pose(q)
    axis = kin.jacobian(q)[:3, 6]
    axis /= np.linalg.norm(axis)
    R_goal = RotationMatrix(AngleAxis(math.radians(40.0), axis)) @ X0.rotation()
    dq_max = np.array([2, 1, 1.5, 1.25, 3, 1.5, 3]) * 0.5
    dt, sent, past = 0.01, np.zeros(7), -math.inf
    for _ in range(1000):
        X = kin.pose(q)
        aa = (R_goal @ X.rotation().inverse()).ToAngleAxis()
        w = 4.0 * aa.angle() * aa.axis()
        w *= min(1.0, 0.6 / max(np.linalg.norm(w), 1e-12))
        v = 2.0 * (X0.translation() - X.translation())
        qdot = _solve(kin, q, np.concatenate([w, v]), dq_max, np.zeros(7), braking_acceleration)
        sent = guard_command(qdot, sent, dt, hw.max_joint_velocity, hw.max_joint_acceleration)
        q = q + dt * sent
        past = max(past, q[6] - kin.q_max[6])
    left = (R_goal @ kin.pose(q).rotation().inverse()).ToAngleAxis().angle()
    return past, left


def test_a_fast_turn_into_a_limit_stops_before_it_under_the_command_guard(kin):
    """The joint-limit ramp assumes the command changes at once; the hardware's command
    guard lets it change by 2 rad/s^2. Without the braking bound joint 7, turning at 0.6
    rad/s, runs past its limit (the FR3 would stop on its own joint-limit reflex); with
    it the joint stops before the limit and the other joints complete the turn."""
    from drake_rus.hardware.config import HardwareConfig

    past_unbraked, _ = _guarded_wrist_turn(kin, braking_acceleration=None)
    past, left = _guarded_wrist_turn(
        kin, braking_acceleration=HardwareConfig().max_joint_acceleration
    )
    print(
        f"\njoint 7 past its limit: {1e3 * past_unbraked:.2f} mrad without the braking bound, "
        f"{1e3 * past:.4f} mrad with it ({math.degrees(left):.3f} deg of the turn left)"
    )
    assert past_unbraked > 0.01  # the ramp alone: the guard carries the joint past it
    assert past <= 0.0
    assert math.degrees(left) < 0.5


def test_solve_joint_velocities_respects_limits(kin):
    xi = np.array([0, 0, 0, 0.0, 0.0, -2.0])  # far too fast on purpose
    dq_max = np.array([2, 1, 1.5, 1.25, 3, 1.5, 3]) * 0.5
    qdot = laws.solve_joint_velocities(
        Q0,
        xi,
        kin.jacobian,
        K_p6=1.0,
        epsilon=1e-4,
        q_min=kin.q_min,
        q_max=kin.q_max,
        dq_max=dq_max,
        joint_limit_margin=0.1,
    )
    assert np.all(np.abs(qdot) <= dq_max + 1e-12)
    v = kin.jacobian(Q0) @ qdot
    assert v[5] < 0 and abs(v[3]) < 1e-3 * abs(v[5]) + 1e-9
    bad = laws.solve_joint_velocities(
        Q0 * np.nan,
        xi,
        kin.jacobian,
        K_p6=1.0,
        epsilon=1e-4,
        q_min=kin.q_min,
        q_max=kin.q_max,
        dq_max=dq_max,
        joint_limit_margin=0.1,
    )
    np.testing.assert_array_equal(bad, 0)


def test_null_space_gradient_raises_manipulability(kin):
    """Kinematic integration of eq. 10-11 along a long motion: min m is higher with K_p6."""
    # Start away from the best elbow posture (Q0 itself is a manipulability maximum of the
    # self-motion), then slide the tip 24 cm along +y.
    q_start = Q0 + np.array([0.4, 0.0, -1.0, 0.0, 0.6, 0.0, 0.0])

    def run(K_p6):
        q = q_start.copy()
        ms = []
        dt = 0.01
        for k in range(300):
            xi = np.array([0, 0, 0, 0.0, 0.08, 0.0])  # slide 24 cm along y
            qdot = laws.solve_joint_velocities(
                q,
                xi,
                kin.jacobian,
                K_p6=K_p6,
                epsilon=1e-4,
                q_min=kin.q_min,
                q_max=kin.q_max,
                dq_max=np.full(7, 2.0),
                joint_limit_margin=0.1,
            )
            q = q + qdot * dt
            ms.append(laws.manipulability(kin.jacobian(q)))
        return min(ms)

    m_with, m_without = run(5.0), run(0.0)
    assert m_with > m_without * 1.1


def test_jacobian_derivatives_match_finite_differences(kin):
    rng = np.random.default_rng(3)
    for q in (Q0, Q0 + rng.uniform(-0.4, 0.4, 7)):
        dJ = laws.jacobian_derivatives(kin.jacobian(q))
        for i in range(7):
            e = np.zeros(7)
            e[i] = 1e-6
            fd = (kin.jacobian(q + e) - kin.jacobian(q - e)) / 2e-6
            assert np.allclose(dJ[i], fd, atol=1e-7), i


def test_manipulability_gradient_analytic_matches_finite_differences(kin):
    rng = np.random.default_rng(4)
    for q in (Q0, Q0 + rng.uniform(-0.5, 0.5, 7), Q0 + rng.uniform(-0.5, 0.5, 7)):
        analytic = laws.manipulability_gradient_analytic(kin.jacobian(q))
        central = np.array(
            [
                (
                    laws.manipulability(kin.jacobian(q + 1e-6 * e))
                    - laws.manipulability(kin.jacobian(q - 1e-6 * e))
                )
                / 2e-6
                for e in np.eye(7)
            ]
        )
        assert np.allclose(analytic, central, atol=1e-8, rtol=1e-6)


def test_manipulability_gradient_analytic_zero_at_singularity():
    J = np.zeros((6, 7))
    J[:, :5] = np.eye(6)[:, :5]
    assert np.array_equal(laws.manipulability_gradient_analytic(J), np.zeros(7))


def _scale_into_bounds_loop(qdot, lower, upper):
    """The per-joint loop the vectorised scale_into_bounds replaced (reference)."""
    return np.asarray(qdot, dtype=float) * _bound_scale_loop(qdot, lower, upper)


def test_scale_into_bounds_matches_the_per_joint_rule():
    rng = np.random.default_rng(5)
    for _ in range(500):
        qdot = rng.normal(0.0, 1.0, 7)
        lo = -np.abs(rng.normal(0.0, 0.8, 7)) * (rng.random(7) > 0.2)
        up = np.abs(rng.normal(0.0, 0.8, 7)) * (rng.random(7) > 0.2)
        out = laws.scale_into_bounds(qdot, lo, up)
        np.testing.assert_allclose(out, _scale_into_bounds_loop(qdot, lo, up), atol=1e-15)
        assert np.all(out <= up + 1e-12) and np.all(out >= lo - 1e-12)


def test_tip_kinematics_memoises_on_q(kin):
    q2 = Q0 + 0.1
    J0 = kin.jacobian(Q0)
    assert kin.jacobian(Q0.copy()) is J0  # same q: the same evaluation
    J2 = kin.jacobian(q2)
    assert not np.allclose(J2, J0)  # another q: recomputed
    X2 = kin.pose(q2)
    np.testing.assert_allclose(kin.jacobian(Q0), J0)
    assert not np.allclose(kin.pose(Q0).translation(), X2.translation())


def test_null_space_diff_ik_equals_the_explicit_pseudo_inverse_and_projector(kin):
    rng = np.random.default_rng(6)
    singular = kin.jacobian(Q0).copy()
    singular[:, 3] = singular[:, 2]  # a rank-deficient J takes the damped branch
    for J in (kin.jacobian(Q0), kin.jacobian(Q0 + rng.uniform(-0.5, 0.5, 7)), singular):
        xi, qn = rng.normal(size=6), rng.normal(size=7)
        J_pinv, N, _ = laws.damped_pseudo_inverse(J, 0.03, 0.03)
        np.testing.assert_allclose(
            laws.null_space_diff_ik(J, xi, qn), J_pinv @ xi + N @ qn, atol=1e-10
        )


def test_all_finite_agrees_with_numpy_including_an_overflowing_sum():
    rng = np.random.default_rng(11)
    for _ in range(200):
        x = rng.normal(size=7)
        if rng.random() < 0.5:
            x[rng.integers(7)] = rng.choice([np.nan, np.inf, -np.inf])
        assert laws.all_finite(x) == bool(np.all(np.isfinite(x)))
    with np.errstate(over="ignore", invalid="ignore"):
        huge = np.full(7, 1e308)  # every entry finite, the sum overflows to inf
        assert laws.all_finite(huge)
        assert not laws.all_finite(np.array([np.inf, -np.inf]))  # inf - inf = nan


def test_compiled_damped_svd_matches_numpy(kin):
    """The compiled kernel's SVD gives numpy's singular values and reassembles J; near a
    singularity it damps (lambda^2 > 0) and the rank drops."""
    for J in (kin.jacobian(Q0), kin.jacobian(Q0 + 0.3)):
        U, Vt, inv, rank, lam2 = kernels.damped_svd(np.ascontiguousarray(J), 0.03, 0.03)
        s = np.linalg.svd(J, compute_uv=False)
        np.testing.assert_allclose(inv, 1.0 / s, rtol=1e-12)
        np.testing.assert_allclose(U * (1.0 / inv) @ Vt[:6], J, atol=1e-12)
        assert lam2 == 0.0 and rank == 6
    J = np.zeros((6, 7))
    J[:5, :5] = np.eye(5)
    U, Vt, inv, rank, lam2 = kernels.damped_svd(J, 0.03, 0.03)
    assert rank == 5 and lam2 == pytest.approx(0.03**2)
    assert inv[-1] == 0.0 and np.all(inv[:5] < 1.0)


def _solve(kin, q, xi, dq_max, qdot_null, braking_acceleration=None):
    """The whole IK on the FR3 with the 0.1 rad joint-limit margin (10 ms period)."""
    return laws.solve_joint_velocities(
        q,
        xi,
        kin.jacobian,
        q_min=kin.q_min,
        q_max=kin.q_max,
        dq_max=dq_max,
        joint_limit_margin=0.1,
        qdot_null=qdot_null,
        braking_acceleration=braking_acceleration,
        period=0.01,
    )


def _saturate_one_joint_reference(J, xi, qdot, lo, up, dq_max):
    """The joint-limit rule with numpy's solver: uniform scaling, blended with the most
    limiting ramped joint held at its bound and the other six solving J qdot = xi."""
    s0 = _bound_scale_loop(qdot, lo, up)
    if s0 >= 1.0:
        return qdot
    cands = []
    for i, v in enumerate(qdot):
        if v > up[i] and up[i] < dq_max[i]:
            cands.append((up[i] / v if v > 0 else 0.0, i, up[i]))
        elif v < lo[i] and -lo[i] < dq_max[i]:
            cands.append((lo[i] / v if v < 0 else 0.0, i, lo[i]))
    if not cands:
        return qdot * s0
    _, j, b = min(cands)
    free = [i for i in range(7) if i != j]
    sigma_min = np.linalg.svd(J[:, free], compute_uv=False)[-1]
    if sigma_min < 0.03:
        return qdot * s0
    held = np.empty(7)
    held[j] = b
    held[free] = np.linalg.solve(J[:, free], xi - J[:, j] * b)
    s1 = _bound_scale_loop(held, lo, up)
    if s1 <= s0:
        return qdot * s0
    depth = 1.0 - abs(b) / dq_max[j]
    w = (1 - (s0 / s1) ** 2) * depth * min(sigma_min / 0.03 - 1.0, 1.0)
    return (1 - w) * s0 * qdot + w * s1 * held


def _bound_scale_loop(qdot, lo, up):
    """The largest uniform scale in [0, 1] keeping qdot within [lo, up] (reference)."""
    s = 1.0
    for v, a, b in zip(qdot, lo, up):
        if v > b:
            s = min(s, b / v if v > 0 else 0.0)
        elif v < a:
            s = min(s, a / v if v < 0 else 0.0)
    return max(s, 0.0)


def test_a_joint_at_its_limit_no_longer_stops_the_probe(kin):
    """Joint 7 at its upper limit, the task the twist it alone would give (into the limit):
    uniform scaling stopped every joint; now the other six carry the task exactly."""
    # Shoulder lifted from Q0 (joints 1 and 3 nearly parallel there: the other six's
    # smallest singular value is 0.04, near the 0.03 threshold; here 0.15).
    q = Q0 + np.array([0.0, 0.5, 0.3, 0.0, 0.0, 0.0, 0.0])
    q[6] = kin.q_max[6]
    J = kin.jacobian(q)
    xi = J[:, 6] * 0.3  # rad/s of joint 7: its twist (angular about its axis, and linear)
    dq_max = np.array([2, 1, 1.5, 1.25, 3, 1.5, 3]) * 0.5
    qdot = _solve(kin, q, xi, dq_max, np.zeros(7))
    lo, up = laws.joint_velocity_bounds(q, kin.q_min, kin.q_max, dq_max, 0.1)
    assert qdot[6] == 0.0  # held at its bound (0: at the limit)
    assert np.all(qdot >= lo - 1e-12) and np.all(qdot <= up + 1e-12)
    v = J @ qdot
    scale = float(v @ xi / (xi @ xi))
    assert scale > 0.3, scale  # most of the commanded twist ...
    np.testing.assert_allclose(v, scale * xi, atol=1e-9)  # ... and in its direction
    # The old rule: the whole command scaled by joint 7's bound, zero.
    old = laws.scale_into_bounds(laws.null_space_diff_ik(J, xi, np.zeros(7)), lo, up)
    assert np.allclose(old, 0.0)


def test_a_turn_past_a_wrist_limit_completes_with_the_other_joints(kin):
    """Kinematic integration: the probe turned 25 deg about its own axis, the way joint 7
    turns, from 0.05 rad before joint 7's limit. The turn completes, the position held,
    joint 7 never passes its limit, and the command changes smoothly."""
    q = Q0.copy()
    q[6] = kin.q_max[6] - 0.05
    X0 = kin.pose(q)
    J = kin.jacobian(q)
    axis = J[:3, 6] / np.linalg.norm(J[:3, 6])  # joint 7's axis in B (the probe's)
    R_goal = RotationMatrix(AngleAxis(math.radians(25.0), axis)) @ X0.rotation()
    dq_max = np.array([1.0, 0.5, 0.75, 0.625, 1.5, 0.75, 1.5])
    dt = 0.01
    previous, largest_change = None, 0.0
    for _ in range(800):
        X = kin.pose(q)
        aa = (R_goal @ X.rotation().inverse()).ToAngleAxis()
        w = 2.0 * aa.angle() * aa.axis()
        v = 2.0 * (X0.translation() - X.translation())
        xi = np.concatenate([np.clip(w, -0.5, 0.5), v])
        qdot = _solve(kin, q, xi, dq_max, np.zeros(7))
        if previous is not None:
            largest_change = max(largest_change, float(np.abs(qdot - previous).max()))
        previous = qdot
        q = q + dt * qdot
        assert q[6] <= kin.q_max[6] + 1e-9
    # A continuous command: below the FR3's joint acceleration (10 rad/s^2, docs/facts/fr3.md)
    # per period. Choosing between the held and the scaled solution jumped 0.74 rad/s.
    assert largest_change < 10.0 * dt, largest_change
    X = kin.pose(q)
    left = (R_goal @ X.rotation().inverse()).ToAngleAxis().angle()
    assert math.degrees(left) < 0.5, math.degrees(left)
    assert np.linalg.norm(X.translation() - X0.translation()) < 1e-3


def test_solve_joint_velocities_kernel_equals_the_numpy_equations(kin):
    """The compiled IK against eq. 10 written with numpy's pseudo-inverse (away from
    singularities, where the damping is off) plus the same bounds and scaling."""
    rng = np.random.default_rng(3)
    dq_max = np.array([2, 1, 1.5, 1.25, 3, 1.5, 3]) * 0.5
    held = 0
    for k in range(60):
        q = Q0 + rng.uniform(-0.4, 0.4, 7)
        xi, qn = rng.normal(0, 0.05, 6), rng.normal(0, 0.1, 7)
        if k % 2:  # a joint 0-0.03 rad from a limit, the task what it would do towards it
            i, sign = rng.integers(7), 1.0 if k % 4 == 1 else -1.0
            q[i] = kin.q_max[i] - rng.uniform(0, 0.03) if sign > 0 else kin.q_min[i] + 0.02
            xi = sign * kin.jacobian(q)[:, i] * 0.2 + rng.normal(0, 0.02, 6)
        J = kin.jacobian(q)
        free = np.linalg.pinv(J) @ xi + (np.eye(7) - np.linalg.pinv(J) @ J) @ qn
        lo = -np.clip((q - kin.q_min) / 0.1, 0, 1) * dq_max
        up = np.clip((kin.q_max - q) / 0.1, 0, 1) * dq_max
        expected = _saturate_one_joint_reference(J, xi, free, lo, up, dq_max)
        held += not np.allclose(expected, free * _bound_scale_loop(free, lo, up))
        got = _solve(kin, q, xi, dq_max, qn)
        np.testing.assert_allclose(got, expected, atol=1e-10)
        assert np.all(got >= lo - 1e-12) and np.all(got <= up + 1e-12)
    assert held >= 5, held  # the held-joint blend was exercised, not only uniform scaling
