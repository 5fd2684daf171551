"""Diagram-level tests: controller + safety layer on the simulated station (MakeStation).

Each test simulates only as long as its claim needs. Figures are printed (pytest -s) for the
issue note.
"""

import math

import numpy as np
import pytest
from pydrake.common.eigen_geometry import AngleAxis
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from pydrake.systems.analysis import Simulator

from drake_rus.closed_loop import AdvanceUntilScanEnds, BuildClosedLoop
from drake_rus.control import supervisor
from drake_rus.control.laws import angle_between, manipulability
from drake_rus.control.safety import StopReason
from drake_rus.control.synthetic_view import GeometricKidneyView
from drake_rus.reliability.injector import BuildClosedLoopWithFault
from drake_rus.scenario import FR3_Q_MAX, LoadScenario

pytestmark = pytest.mark.slow


def scenario(text=""):
    return LoadScenario(scenario_text=text or None)


def logs(cl, context):
    return {k: v.FindLog(context) for k, v in cl.loggers.items()}


def tip_positions(cl, q_log):
    kin = cl.parts.ik.kinematics
    return np.array([kin.pose(q).translation() for q in q_log.T])


def touch_time(t, F, threshold=0.5):
    i = int(np.argmax(F > threshold))
    assert F[i] > threshold, "the probe never touched the body"
    return t[i]


# A kidney (ellipsoid 110 x 60 x 50 mm) under the placeholder torso, long axis 15 deg off the
# base y-axis, about 7 cm below the skin; seen through GeometricKidneyView (a geometric
# stand-in for image + segmenter) which also gives the ground-truth X_BK for LOCALIZE.
X_BK_TRUE = RigidTransform(RollPitchYaw(0.1, 0.0, math.radians(105.0)), [0.595, -0.035, 0.035])
KIDNEY_SEMI_AXES = [0.055, 0.03, 0.025]


@pytest.fixture(scope="module")
def full_scan():
    """APPROACH -> EXPLORE (30 mm) -> LOCALIZE -> TRANSIT -> PIVOT -> DONE on the station."""
    # The default joint pose hovers about 0.1 m above the placeholder torso, higher than an
    # operator's placement: allow that approach.
    s = scenario(
        "{controller: {exploration_ratio: 0.3, pivot_rate: 0.15, approach_max_travel: 0.2}}"
    )
    view = GeometricKidneyView(X_BK_TRUE, KIDNEY_SEMI_AXES, frame_rate_hz=s.imaging.frame_rate_hz)
    cl = BuildClosedLoop(s, kidney_view=view, log_period=0.01)
    sim = Simulator(cl.diagram)
    ctx = sim.get_mutable_context()
    sup = cl.parts.supervisor
    sup_ctx = sup.GetMyContextFromRoot(ctx)
    AdvanceUntilScanEnds(sim, sup, 40.0)
    L = logs(cl, ctx)
    state = sup.state(sup_ctx)
    safety_events = cl.parts.safety.safety_state(cl.parts.safety.GetMyContextFromRoot(ctx)).events
    print("\nsupervisor events:", *state.events, sep="\n  ")
    p = tip_positions(cl, L["q"].data())
    return dict(
        s=s, cl=cl, L=L, state=state, safety_events=safety_events, p=p, t=L["q"].sample_times()
    )


def _phase_times(state, name):
    times = [e[0] for e in state.events if e[1] == name]
    return times[0]


def test_full_scan_runs_through_every_phase_without_a_safety_stop(full_scan):
    state = full_scan["state"]
    names = [e[1] for e in state.events]
    assert names == [
        "APPROACH",
        "EXPLORE",
        "LOCALIZE",
        "TRANSIT",
        "PIVOT",
        "PIVOT",
        "PIVOT",
        "DONE",
    ], state.events
    assert not full_scan["safety_events"]


def test_force_settles_within_2_s_of_touching_and_holds_while_exploring(full_scan):
    """F settles to 9 +- 0.5 N within 2 s of touching and stays there while the probe slides
    along y over the curved body at 5 mm/s."""
    L, state = full_scan["L"], full_scan["state"]
    t_end = _phase_times(state, "LOCALIZE")
    t = L["probe_force"].sample_times()
    F = -L["probe_force"].data()[5]
    t_touch = touch_time(t, F)
    window = (t >= t_touch + 2.0) & (t <= t_end)
    assert t_end - (t_touch + 2.0) > 2.5
    err = np.abs(F[window] - 9.0)
    outside = np.abs(F - 9.0) > 0.5
    last_out = t[np.nonzero(outside & (t <= t_end))[0][-1]]
    print(
        f"\ntouch at {t_touch:.2f} s; settled (9 +- 0.5 N for good) "
        f"{last_out - t_touch:.2f} s later; max |F - 9| while exploring {err.max():.3f} N"
    )
    assert err.max() <= 0.5
    assert last_out - t_touch <= 2.0


def test_exploration_speed_and_mask_centring(full_scan):
    L, state, p, tq = full_scan["L"], full_scan["state"], full_scan["p"], full_scan["t"]
    s = full_scan["s"]
    t0, t1 = _phase_times(state, "EXPLORE"), _phase_times(state, "LOCALIZE")
    m = (tq >= t0 + 1.5) & (tq <= t1)  # after the start-up transient
    vy = np.polyfit(tq[m], p[m, 1], 1)[0]
    k = 100  # 1 s windows (the gel-on-skin friction makes small stick-slip steps)
    v_inst = np.abs(p[m][k:, 1] - p[m][:-k, 1]) / (tq[m][k:] - tq[m][:-k])
    c = L["mask_centroid"].data()[0][m]
    vis = L["kidney_visible"].data()[0][m]
    print(
        f"\nexploration: v_y = {vy * 1e3:.3f} mm/s; |v_y| over 1 s windows "
        f"{v_inst.min() * 1e3:.2f}-{v_inst.max() * 1e3:.2f} mm/s; mask centroid "
        f"{c.min():.3f}-{c.max():.3f}"
    )
    assert abs(abs(vy) - s.controller.scan_speed) <= 0.0005
    assert np.sign(vy) == (1 if s.controller.scan_direction == "+y" else -1)
    assert np.all(np.abs(v_inst - 0.005) <= 0.0005)
    assert np.all(vis == 1.0)
    assert np.all(np.abs(c - 0.5) <= 0.1)


def test_pivot_keeps_tip_at_p_star_and_ends_on_both_sides(full_scan):
    L, state, p, tq = full_scan["L"], full_scan["state"], full_scan["p"], full_scan["t"]
    t0, t1 = _phase_times(state, "PIVOT"), _phase_times(state, "DONE")
    m = (tq >= t0) & (tq <= t1)
    d = np.linalg.norm(p[m, :2] - state.p_star[:2], axis=1)
    F = -L["probe_force"].data()[5][m]
    legs = [e for e in state.events if e[1] == "PIVOT" and "leg" in e[2]]
    print(
        f"\npivot: tip within {d.max() * 1e3:.2f} mm of p* (xy); legs ended at "
        f"{np.degrees(state.pivot_limits[0]):.1f} and {np.degrees(state.pivot_limits[1]):.1f}"
        f" deg; F {F.min():.2f}-{F.max():.2f} N"
    )
    assert d.max() <= 0.002
    assert len(legs) == 2 and all("kidney left the image" in e[2] for e in legs)
    assert state.pivot_limits[0] * state.pivot_limits[1] < 0  # one leg each side
    assert min(abs(a) for a in state.pivot_limits) > math.radians(5.0)
    np.testing.assert_allclose(state.p_star, X_BK_TRUE.translation())


def test_orientation_error_below_1_deg_within_2_s_after_20_deg_step():
    s = scenario()
    cl = BuildClosedLoop(s, use_supervisor=False, log_period=0.01)
    sim = Simulator(cl.diagram)
    ctx = sim.get_mutable_context()
    sim.AdvanceTo(2.5)  # in contact and settled
    a0 = cl.reference(ctx, "a_des")
    o0 = cl.reference(ctx, "o_des")
    a1 = supervisor.rodrigues_pivot_update(a0, o0, math.radians(20.0))  # tilt 20 deg about o
    cl.reference_value(ctx, "a_des").set_value(a1)
    sim.AdvanceTo(4.5)
    L = logs(cl, ctx)
    kin = cl.parts.ik.kinematics
    t = L["q"].sample_times()
    errs = []
    for tk, q in zip(t, L["q"].data().T):
        if tk < 2.5:
            continue
        R = kin.pose(q).rotation().matrix()
        errs.append(
            (tk, math.degrees(angle_between(R[:, 2], a1)), math.degrees(angle_between(R[:, 0], o0)))
        )
    errs = np.array(errs)
    print(
        f"\napproach error {errs[0, 1]:.2f} deg at the step, {errs[-1, 1]:.3f} deg 2 s later; "
        f"o error {errs[-1, 2]:.3f} deg; first below 1 deg after "
        f"{errs[np.argmax(errs[:, 1] < 1.0), 0] - 2.5:.2f} s"
    )
    assert errs[0, 1] > 19.0
    assert errs[-1, 1] < 1.0 and errs[-1, 2] < 1.0
    F = -L["probe_force"].data()[5][L["probe_force"].sample_times() > 4.0]
    assert np.all(F > 5.0)  # stayed in contact while tilting


def test_a_turn_into_the_wrist_limit_completes_on_the_station():
    """The array turned 25 deg about the probe's axis, the way joint 7 turns, from 0.05 rad
    before joint 7's limit, in contact with the body: the diagram (force PD, orientation
    alignment, differential IK, safety layer, FR3 plant) completes the turn with the other
    six joints, joint 7 stays within its limit, the probe stays in contact and the held
    joint's solution enters without a jump. Uniform scaling into the bounds (before c61f2ae)
    stopped the arm 22.05 deg short, the probe still pressed on the body."""
    q0 = np.array(scenario().robot.initial_joint_positions, dtype=float)
    q_max_7 = FR3_Q_MAX[6]
    q0[6] = q_max_7 - 0.05
    s = scenario("{robot: {initial_joint_positions: [%s]}}" % ", ".join(map(str, q0)))
    cl = BuildClosedLoop(s, use_supervisor=False, log_period=0.01)
    kin = cl.parts.ik.kinematics
    assert kin.q_max[6] == pytest.approx(q_max_7)
    sim = Simulator(cl.diagram)
    ctx = sim.get_mutable_context()
    sim.AdvanceTo(2.5)  # in contact and settled
    a0, o0 = cl.reference(ctx, "a_des"), cl.reference(ctx, "o_des")
    q_step = logs(cl, ctx)["q"].data()[:, -1]
    axis = kin.jacobian(q_step)[:3, 6]  # joint 7's axis in B: the probe's, +q7's turn
    axis /= np.linalg.norm(axis)
    o1 = RotationMatrix(AngleAxis(math.radians(25.0), axis)).multiply(o0)
    cl.reference_value(ctx, "o_des").set_value(o1)
    sim.AdvanceTo(5.0)
    L = logs(cl, ctx)
    t, Q = L["q"].sample_times(), L["q"].data()
    after = t >= 2.5
    R_end = kin.pose(Q[:, -1]).rotation().matrix()
    o_error = math.degrees(angle_between(R_end[:, 0], o1))
    a_error = math.degrees(angle_between(R_end[:, 2], a0))
    # The command's changes from one 10 ms period to the next, after the first: that one is
    # the 25 deg step of o_des itself (0.585 rad/s on joint 7, before and since c61f2ae).
    command = L["command"].data()[:, L["command"].sample_times() >= 2.505]
    largest_step = float(np.abs(np.diff(command, axis=1)).max())
    F = -L["probe_force"].data()[5][L["probe_force"].sample_times() >= 2.5]
    print(
        f"\nwrist turn into joint 7's limit: o error 25 -> {o_error:.2f} deg in 2.5 s, "
        f"a error {a_error:.2f} deg; q7 {q_step[6]:.4f} -> max {Q[6, after].max():.4f} "
        f"(limit {q_max_7:.4f}); force {F.min():.1f}-{F.max():.1f} N; largest command step "
        f"{largest_step:.3f} rad/s"
    )
    assert q_max_7 - q_step[6] > 0.04  # the turn starts before the limit ...
    assert Q[6, after].max() > q_max_7 - 1e-3  # ... and reaches it
    assert Q[6, after].max() <= q_max_7 + 1e-4  # never past it
    assert o_error < 1.0 and a_error < 1.0  # completed by the other joints
    assert np.all(F > 5.0)  # in contact throughout
    # The other joints take over continuously: below the FR3's joint acceleration (10
    # rad/s^2, docs/facts/fr3.md) per 10 ms period (0.078 rad/s; joint 7 braking from 0.05
    # rad before its limit, laws.joint_velocity_bounds), where choosing between the held
    # and the scaled solution jumped 0.74 rad/s (and the ramp alone, joint 7 running into
    # it at 0.585 rad/s, gave 0.126).
    assert largest_step < 10.0 * 0.01, largest_step


def _min_manipulability(use_null_space):
    q_start = [0.4, 0.15, -1.0, -2.0, 0.6, 2.15, 0.785]
    s = scenario(
        "{robot: {initial_joint_positions: [%s]}, controller: {desired_force: 0.0}}"
        % ", ".join(map(str, q_start))
    )
    cl = BuildClosedLoop(s, use_supervisor=False, use_null_space=use_null_space, log_period=0.02)
    sim = Simulator(cl.diagram)
    ctx = sim.get_mutable_context()
    P0 = cl.reference(ctx, "P_des")
    # A long motion in free space: 20 cm along +y, 1 cm per step every 0.2 s.
    for k in range(20):
        cl.reference_value(ctx, "P_des").set_value(P0 + [0.0, 0.01 * (k + 1)])
        sim.AdvanceTo(0.2 * (k + 1))
    sim.AdvanceTo(4.6)  # let the tip catch up
    L = logs(cl, ctx)
    kin = cl.parts.ik.kinematics
    ms = [manipulability(kin.jacobian(q)) for q in L["q"].data().T]
    p_end = kin.pose(L["q"].data()[:, -1]).translation()
    return min(ms), p_end[1] - P0[1]


def test_null_space_term_keeps_manipulability_higher_along_long_motion():
    m_with, dy_with = _min_manipulability(True)
    m_without, dy_without = _min_manipulability(False)
    print(
        f"\nmin manipulability over a 20 cm slide: with null space {m_with:.4f}, "
        f"without {m_without:.4f}"
    )
    assert dy_with > 0.18 and dy_without > 0.18  # both performed the motion
    assert m_with > 1.05 * m_without


T_FAULT = 0.3023  # between two control ticks


@pytest.mark.parametrize(
    "fault, reason, extra",
    [
        ("force_spike", StopReason.FORCE, "{safety: {retract_distance: 0.0}}"),
        ("frozen_image", StopReason.STALE_IMAGE, "{safety: {image_timeout: 0.1}}"),
        ("nan_pose", StopReason.NAN, ""),
        (
            "segmentation_loss",
            StopReason.SEGMENTATION_LOST,
            "{safety: {segmentation_timeout: 0.1}}",
        ),
        ("frozen_state", StopReason.STALE_STATE, ""),
    ],
)
def test_safety_stop_on_injected_fault(fault, reason, extra):
    s = scenario(extra)
    cl = BuildClosedLoopWithFault(
        s, fault, T_FAULT, use_supervisor=False, log_period=1.0 / s.controller.rate_hz
    )
    sim = Simulator(cl.diagram)
    ctx = sim.get_mutable_context()
    sim.AdvanceTo(T_FAULT + 0.4)
    st = cl.parts.safety.safety_state(cl.parts.safety.GetMyContextFromRoot(ctx))
    assert st.stopped and len(st.events) == 1, st.events
    ev = st.events[0]
    assert ev.reason == reason
    timeouts = {
        "frozen_image": s.safety.image_timeout,
        "segmentation_loss": s.safety.segmentation_timeout,
        "frozen_state": s.safety.state_timeout,
    }
    t_detectable = T_FAULT + timeouts.get(fault, 0.0)
    period = 1.0 / s.controller.rate_hz
    latency = ev.time - t_detectable
    print(
        f"\n{fault}: stop '{ev.reason}' ({ev.detail}) at {ev.time:.4f} s, "
        f"{latency * 1e3:.2f} ms after it became detectable"
    )
    assert -1e-9 <= latency <= period + 1e-9
    L = logs(cl, ctx)
    t, cmd = L["command"].sample_times(), L["command"].data()
    before = t < T_FAULT - 1e-9
    assert np.linalg.norm(cmd[:, before], axis=0).max() > 1e-3  # was moving before
    # Loggers publish before the updates at the same time: the sample at ev.time still shows
    # the last command; every later sample (the held command from ev.time on) is zero.
    after = t > ev.time + 1e-9
    assert after.sum() >= 10 and np.all(cmd[:, after] == 0.0)


def test_force_ceiling_stop_retracts_then_zero():
    s = scenario("{safety: {retract_distance: 0.004, retract_speed: 0.02}}")
    cl = BuildClosedLoopWithFault(
        s, "force_spike", T_FAULT, use_supervisor=False, log_period=1.0 / s.controller.rate_hz
    )
    sim = Simulator(cl.diagram)
    ctx = sim.get_mutable_context()
    sim.AdvanceTo(T_FAULT + 0.5)
    ev = cl.parts.safety.safety_state(cl.parts.safety.GetMyContextFromRoot(ctx)).events[0]
    assert ev.reason == StopReason.FORCE
    L = logs(cl, ctx)
    t, cmd, q = L["command"].sample_times(), L["command"].data(), L["q"].data()
    kin = cl.parts.ik.kinematics
    i = int(np.argmax(t > ev.time + 1e-9))  # first sample after the stop
    X = kin.pose(q[:, i])
    V = kin.jacobian(q[:, i]) @ cmd[:, i]
    a = X.rotation().matrix()[:, 2]
    assert V[3:] @ a < -0.019  # moving out of the body at the retract speed
    assert np.linalg.norm(V[:3]) < 1e-3
    t_end = ev.time + 0.004 / 0.02
    assert np.all(cmd[:, t > t_end + 1.5 / s.controller.rate_hz] == 0.0)
    z = np.array([kin.pose(qk).translation()[2] for qk in q.T])
    j = int(np.argmax(t > t_end + 0.1))
    print(f"\nforce stop: retracted {(z[j] - z[i]) * 1e3:.2f} mm along -a, then stopped")
    assert z[j] - z[i] > 0.003


def test_workspace_exit_stops():
    s0 = scenario()
    cl0 = BuildClosedLoop(s0, use_supervisor=False)
    z0 = cl0.station.GetOutputPort("X_BP").Eval(cl0.station.CreateDefaultContext()).translation()[2]
    z_min = z0 - 0.02
    s = scenario("{safety: {workspace_min: [0.2, -0.5, %f]}}" % z_min)
    cl = BuildClosedLoop(s, use_supervisor=False, log_period=1.0 / s.controller.rate_hz)
    sim = Simulator(cl.diagram)
    ctx = sim.get_mutable_context()
    sim.AdvanceTo(1.2)
    st = cl.parts.safety.safety_state(cl.parts.safety.GetMyContextFromRoot(ctx))
    assert st.stopped and st.events[0].reason == StopReason.WORKSPACE
    L = logs(cl, ctx)
    t, cmd, q = L["command"].sample_times(), L["command"].data(), L["q"].data()
    kin = cl.parts.ik.kinematics
    z = np.array([kin.pose(qk).translation()[2] for qk in q.T])
    crossed = t[int(np.argmax(z < z_min))]
    latency = st.events[0].time - crossed
    print(
        f"\nworkspace exit at {crossed:.4f} s, stop at {st.events[0].time:.4f} s "
        f"(latency {latency * 1e3:.2f} ms); overshoot {(z_min - z.min()) * 1e3:.2f} mm"
    )
    assert latency <= 1.0 / s.controller.rate_hz + 1e-9
    assert np.all(cmd[:, t > st.events[0].time + 1e-9] == 0.0)
    assert z_min - z.min() < 0.002
