"""Diagram-level tests: controller + safety layer on the simulated station (MakeStation).

Each test simulates only as long as its claim needs. Figures are printed (pytest -s) for the
issue note.
"""

import math

import numpy as np
import pytest

from pydrake.math import RollPitchYaw, RotationMatrix
from pydrake.systems.analysis import Simulator
from pydrake.trajectories import PiecewisePolynomial

from drake_rus.control import scan
from drake_rus.control.diagram import BuildClosedLoop
from drake_rus.control.kinematics import TipKinematics
from drake_rus.control.laws import angle_between
from drake_rus.control.safety import StopReason
from drake_rus.scenario import LoadScenario

pytestmark = pytest.mark.slow


def scenario(text=""):
    return LoadScenario(scenario_text=text or None)


def logs(cl, context):
    return {k: v.FindLog(context) for k, v in cl.loggers.items()}


def tip_positions(cl, q_log):
    plant, frame = cl.parts.ik._kin.plant, cl.parts.ik._kin.frame
    kin = TipKinematics(plant, frame)
    return np.array([kin.pose(q).translation() for q in q_log.T])


def touch_time(t, F, threshold=0.5):
    i = int(np.argmax(F > threshold))
    assert F[i] > threshold, "the probe never touched the body"
    return t[i]


def test_force_settles_and_holds_while_exploring_at_5_mm_s():
    """APPROACH -> EXPLORE with the supervisor: F settles to 9 +- 0.5 N within 2 s of touching
    and stays there while the probe slides 30 mm along y over the curved body at 5 mm/s."""
    s = scenario("{controller: {exploration_ratio: 0.3}}")
    cl = BuildClosedLoop(s, log_period=0.01)
    sim = Simulator(cl.diagram)
    sup = cl.parts.supervisor
    ctx = sim.get_mutable_context()
    sup_ctx = sup.GetMyContextFromRoot(ctx)
    while sim.get_context().get_time() < 12.0:
        sim.AdvanceTo(sim.get_context().get_time() + 0.5)
        if sup.state(sup_ctx).phase != scan.Phase.APPROACH and \
                sup.state(sup_ctx).phase != scan.Phase.EXPLORE:
            break
    events = sup.state(sup_ctx).events
    phases = [e[1] for e in events]
    assert phases[:3] == ["APPROACH", "EXPLORE", "LOCALIZE"], events
    t_explore, t_end = events[1][0], events[2][0]
    L = logs(cl, ctx)
    t = L["probe_force"].sample_times()
    F = -L["probe_force"].data()[5]
    t_touch = touch_time(t, F)
    window = (t >= t_touch + 2.0) & (t <= t_end)
    assert t_end - (t_touch + 2.0) > 4.0  # holds through most of the slide
    err = np.abs(F[window] - 9.0)
    print(f"\ntouch at {t_touch:.2f} s, EXPLORE {t_explore:.2f}-{t_end:.2f} s; "
          f"|F - 9| max {err.max():.3f} N from touch + 2 s to end of exploration")
    assert err.max() <= 0.5
    # First time inside the band (and staying there).
    outside = np.abs(F - 9.0) > 0.5
    last_out = t[np.nonzero(outside & (t <= t_end))[0][-1]]
    print(f"settled (9 +- 0.5 N for good) {last_out - t_touch:.2f} s after touching")
    # Tip speed along y during exploration (after a 1 s transient).
    p = tip_positions(cl, L["q"].data())
    tq = L["q"].sample_times()
    m = (tq >= t_explore + 1.0) & (tq <= t_end)
    vy = np.polyfit(tq[m], p[m, 1], 1)[0]
    vx = np.polyfit(tq[m], p[m, 0], 1)[0]
    print(f"exploration tip velocity: v_y = {vy * 1e3:.3f} mm/s, v_x = {vx * 1e3:.3f} mm/s")
    assert abs(abs(vy) - 0.005) <= 0.0005
    assert np.sign(vy) == (1 if s.controller.scan_direction == "+y" else -1)
    # Every sample's speed (10 ms differences smoothed over 0.2 s) stays near 5 mm/s.
    k = 20
    v_inst = np.linalg.norm(p[m][k:, :2] - p[m][:-k, :2], axis=1) / (tq[m][k:] - tq[m][:-k])
    print(f"tip speed over 0.2 s windows: {v_inst.min() * 1e3:.2f}-{v_inst.max() * 1e3:.2f} mm/s")
    assert np.all(np.abs(v_inst - 0.005) <= 0.0005)
    assert not cl.parts.safety.safety_state(cl.parts.safety.GetMyContextFromRoot(ctx)).events


def test_orientation_error_below_1_deg_within_2_s_after_20_deg_step():
    s = scenario()
    cl = BuildClosedLoop(s, use_supervisor=False, log_period=0.01)
    sim = Simulator(cl.diagram)
    ctx = sim.get_mutable_context()
    sim.AdvanceTo(2.5)  # in contact and settled
    a0 = np.array(cl.references["a_des"].get_output_port().Eval(
        cl.references["a_des"].GetMyContextFromRoot(ctx)))
    o0 = np.array(cl.references["o_des"].get_output_port().Eval(
        cl.references["o_des"].GetMyContextFromRoot(ctx)))
    a1 = scan.rodrigues_pivot_update(a0, o0, math.radians(20.0))  # tilt 20 deg about o
    cl.reference_value(ctx, "a_des").set_value(a1)
    sim.AdvanceTo(4.5)
    L = logs(cl, ctx)
    kin = TipKinematics(cl.parts.ik._kin.plant, cl.parts.ik._kin.frame)
    t = L["q"].sample_times()
    errs = []
    for tk, q in zip(t, L["q"].data().T):
        if tk < 2.5:
            continue
        R = kin.pose(q).rotation().matrix()
        errs.append((tk, math.degrees(angle_between(R[:, 2], a1)),
                     math.degrees(angle_between(R[:, 0], o0))))
    errs = np.array(errs)
    print(f"\napproach error {errs[0, 1]:.2f} deg at the step, {errs[-1, 1]:.3f} deg 2 s later; "
          f"o error {errs[-1, 2]:.3f} deg; first below 1 deg after "
          f"{errs[np.argmax(errs[:, 1] < 1.0), 0] - 2.5:.2f} s")
    assert errs[0, 1] > 19.0
    assert errs[-1, 1] < 1.0 and errs[-1, 2] < 1.0
    F = -L["probe_force"].data()[5][L["probe_force"].sample_times() > 4.0]
    assert np.all(F > 5.0)  # stayed in contact while tilting


def _min_manipulability(use_null_space):
    q_start = [0.4, 0.15, -1.0, -2.0, 0.6, 2.15, 0.785]
    s = scenario("{robot: {initial_joint_positions: [%s]}, controller: {desired_force: 0.0}}"
                 % ", ".join(map(str, q_start)))
    cl = BuildClosedLoop(s, use_supervisor=False, use_null_space=use_null_space,
                         log_period=0.02)
    sim = Simulator(cl.diagram)
    ctx = sim.get_mutable_context()
    P0 = np.array(cl.references["P_des"].get_output_port().Eval(
        cl.references["P_des"].GetMyContextFromRoot(ctx)))
    # A long motion in free space: 20 cm along +y, 1 cm per step every 0.2 s.
    m = []
    for k in range(20):
        cl.reference_value(ctx, "P_des").set_value(P0 + [0.0, 0.01 * (k + 1)])
        sim.AdvanceTo(0.2 * (k + 1))
    sim.AdvanceTo(4.6)  # let the tip catch up
    L = logs(cl, ctx)
    kin = TipKinematics(cl.parts.ik._kin.plant, cl.parts.ik._kin.frame)
    from drake_rus.control.laws import manipulability
    ms = [manipulability(kin.jacobian(q)) for q in L["q"].data().T]
    p_end = kin.pose(L["q"].data()[:, -1]).translation()
    return min(ms), p_end[1] - P0[1]


def test_null_space_term_keeps_manipulability_higher_along_long_motion():
    m_with, dy_with = _min_manipulability(True)
    m_without, dy_without = _min_manipulability(False)
    print(f"\nmin manipulability over a 20 cm slide: with null space {m_with:.4f}, "
          f"without {m_without:.4f}")
    assert dy_with > 0.18 and dy_without > 0.18  # both performed the motion
    assert m_with > 1.05 * m_without


T_FAULT = 0.3023  # between two control ticks (200 Hz)


@pytest.mark.parametrize("fault, reason, extra", [
    ("force_spike", StopReason.FORCE, "{safety: {retract_distance: 0.0}}"),
    ("frozen_image", StopReason.STALE_IMAGE, "{safety: {image_timeout: 0.1}}"),
    ("nan_pose", StopReason.NAN, ""),
    ("segmentation_loss", StopReason.SEGMENTATION_LOST, "{safety: {segmentation_timeout: 0.1}}"),
    ("frozen_state", StopReason.STALE_STATE, ""),
])
def test_safety_stop_on_injected_fault(fault, reason, extra):
    s = scenario(extra)
    cl = BuildClosedLoop(s, use_supervisor=False, fault=fault, t_fault=T_FAULT,
                         log_period=1.0 / s.controller.rate_hz)
    sim = Simulator(cl.diagram)
    ctx = sim.get_mutable_context()
    sim.AdvanceTo(T_FAULT + 0.4)
    st = cl.parts.safety.safety_state(cl.parts.safety.GetMyContextFromRoot(ctx))
    assert st.stopped and len(st.events) == 1, st.events
    ev = st.events[0]
    assert ev.reason == reason
    timeouts = {"frozen_image": s.safety.image_timeout,
                "segmentation_loss": s.safety.segmentation_timeout,
                "frozen_state": s.safety.state_timeout}
    t_detectable = T_FAULT + timeouts.get(fault, 0.0)
    period = 1.0 / s.controller.rate_hz
    latency = ev.time - t_detectable
    print(f"\n{fault}: stop '{ev.reason}' ({ev.detail}) at {ev.time:.4f} s, "
          f"{latency * 1e3:.2f} ms after it became detectable")
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
    cl = BuildClosedLoop(s, use_supervisor=False, fault="force_spike", t_fault=T_FAULT,
                         log_period=1.0 / s.controller.rate_hz)
    sim = Simulator(cl.diagram)
    ctx = sim.get_mutable_context()
    sim.AdvanceTo(T_FAULT + 0.5)
    ev = cl.parts.safety.safety_state(cl.parts.safety.GetMyContextFromRoot(ctx)).events[0]
    assert ev.reason == StopReason.FORCE
    L = logs(cl, ctx)
    t, cmd, q = L["command"].sample_times(), L["command"].data(), L["q"].data()
    kin = TipKinematics(cl.parts.ik._kin.plant, cl.parts.ik._kin.frame)
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
    kin = TipKinematics(cl.parts.ik._kin.plant, cl.parts.ik._kin.frame)
    z = np.array([kin.pose(qk).translation()[2] for qk in q.T])
    crossed = t[int(np.argmax(z < z_min))]
    latency = st.events[0].time - crossed
    print(f"\nworkspace exit at {crossed:.4f} s, stop at {st.events[0].time:.4f} s "
          f"(latency {latency * 1e3:.2f} ms); overshoot {(z_min - z.min()) * 1e3:.2f} mm")
    assert latency <= 1.0 / s.controller.rate_hz + 1e-9
    assert np.all(cmd[:, t > st.events[0].time + 1e-9] == 0.0)
    assert z_min - z.min() < 0.002
