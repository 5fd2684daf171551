"""Unit tests of the scan laws (eq. 17, 20-23) and the supervisor state machine."""

import dataclasses
import math

import numpy as np
import pytest
from pydrake.math import RollPitchYaw, RotationMatrix

from drake_rus.control import supervisor
from drake_rus.control.config import ControllerConfig
from drake_rus.control.laws import angle_between
from drake_rus.control.systems import ScanSupervisor

R_DOWN = np.diag([1.0, -1.0, -1.0])  # x_P = +x_B, z_P = -z_B


# ------------------------------------------------------------------ eq. 17
def test_exploration_update_advances_y_and_centres_x():
    P = supervisor.exploration_update([0.5, 0.0], 0.8, [1.0, 0.0, 0.0], 0.005, 0.02, 0.01)
    np.testing.assert_allclose(P, [0.5 + 0.02 * 0.3 * 0.01, 0.00005])
    # Probe x-axis pointing along -x_B: the same image offset moves the tip the other way.
    P = supervisor.exploration_update([0.5, 0.0], 0.8, [-1.0, 0.0, 0.0], -0.005, 0.02, 0.01)
    np.testing.assert_allclose(P, [0.5 - 0.02 * 0.3 * 0.01, -0.00005])
    # Centred mask or no mask: no x correction.
    for c in (0.5, math.nan):
        P = supervisor.exploration_update([0.5, 0.0], c, [1.0, 0.0, 0.0], 0.005, 0.02, 0.01)
        assert P[0] == 0.5


def test_exploration_speed_is_v_scan():
    P = np.array([0.5, 0.0])
    for _ in range(200):
        P = supervisor.exploration_update(P, 0.5, [1, 0, 0], 0.005, 0.02, 0.005)
    assert P[1] == pytest.approx(0.005 * 1.0)


# ------------------------------------------------------------------ eq. 20-22
def test_optimal_pivot_pose_is_a_rotation_with_r1_along_kidney_x():
    R_BK = RotationMatrix(RollPitchYaw(0.3, -0.4, 1.2)).matrix()
    p_BK = np.array([0.55, 0.05, 0.02])
    R, p = supervisor.optimal_pivot_pose(R_BK, p_BK)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R[:, 2], [0, 0, -1])
    x_k = R_BK[:, 0]
    expected = np.array([x_k[0], x_k[1], 0.0]) / np.linalg.norm(x_k[:2])
    np.testing.assert_allclose(R[:, 0], expected, atol=1e-12)
    np.testing.assert_allclose(p, p_BK)
    # The seed's eq. 22 (r1 x r3) is the same line as r2, opposite sign.
    np.testing.assert_allclose(R[:, 1], -np.cross(R[:, 0], R[:, 2]), atol=1e-12)


def test_optimal_pivot_pose_vertical_kidney_axis_falls_back():
    R_BK = RotationMatrix(RollPitchYaw(0.0, -math.pi / 2, 0.0)).matrix()  # x_k vertical
    R, _ = supervisor.optimal_pivot_pose(R_BK, np.zeros(3))
    assert np.linalg.det(R) == pytest.approx(1.0)
    assert np.all(np.isfinite(R))


# ------------------------------------------------------------------ eq. 23
def test_rodrigues_pivot_update():
    a, o = np.array([0.0, 0.0, -1.0]), np.array([0.0, 1.0, 0.0])
    a1 = supervisor.rodrigues_pivot_update(a, o, 0.1)
    np.testing.assert_allclose(a1, a * math.cos(0.1) + np.cross(o, a) * math.sin(0.1))
    assert a1 @ o == pytest.approx(0.0)
    # Many small steps equal one big rotation; the norm stays 1.
    ak = a
    for _ in range(1000):
        ak = supervisor.rodrigues_pivot_update(ak, o, 0.0005)
    np.testing.assert_allclose(ak, supervisor.rodrigues_pivot_update(a, o, 0.5), atol=1e-9)
    assert angle_between(ak, a) == pytest.approx(0.5)
    # The rate vector of eq. 2's feed-forward matches the finite difference.
    rate = supervisor.pivot_rate_vector(a, o, -1.0, 0.2)
    np.testing.assert_allclose(
        rate, (supervisor.rodrigues_pivot_update(a, o, -0.2e-6) - a) / 1e-6, atol=1e-6
    )


# ------------------------------------------------------------------ supervisor
def cfg(**kw):
    """The default controller config; contact without a dwell time unless a test sets one
    (the dwell has its own test), and a probe that need not follow the pivot (these tests
    hold it still; the follow guard has its own test)."""
    kw.setdefault("contact_dwell", 0.0)
    kw.setdefault("pivot_follow_limit", 3.2)
    kw.setdefault("explore_follow_limit", 1.0)
    return dataclasses.replace(ControllerConfig(), **kw)


def inputs(
    t, p=(0.55, 0.0, 0.1), F=9.0, visible=True, c=0.5, R=R_DOWN, R_BK=None, p_BK=None, ready=True
):
    return supervisor.SupervisorInputs(
        t=t,
        R_BP=np.asarray(R),
        p_BP=np.asarray(p, float),
        F_z=F,
        kidney_visible=visible,
        c_msk=c,
        R_BK=R_BK,
        p_BK=p_BK,
        localization_ready=ready,
    )


def _unseen(s, t, steps, c, dt):
    """``steps`` control periods without the kidney in the image; returns (state, time)."""
    for _ in range(steps):
        t += dt
        s = supervisor.supervisor_step(s, inputs(t, visible=False), c, dt)
    return s, t


def test_supervisor_approach_then_explore_distance():
    c = cfg(exploration_ratio=0.2, kidney_length=0.1, scan_direction="+y")
    dt = 0.01
    s = supervisor.SupervisorState()
    s = supervisor.supervisor_step(s, inputs(0.0, F=0.0), c, dt)
    assert s.phase == supervisor.Phase.APPROACH
    np.testing.assert_allclose(s.a_des, [0, 0, -1])
    assert s.F_des == 9.0
    s = supervisor.supervisor_step(s, inputs(0.01, F=8.0), c, dt)
    assert s.phase == supervisor.Phase.EXPLORE
    t = 0.01
    while s.phase == supervisor.Phase.EXPLORE and t < 10:
        t += dt
        s = supervisor.supervisor_step(s, inputs(t, p=(0.55, s.P_des[1], 0.1)), c, dt)
    assert s.phase == supervisor.Phase.LOCALIZE
    assert s.travel == pytest.approx(0.02)
    assert t == pytest.approx(0.01 + 0.02 / 0.005 + dt, abs=2 * dt)  # 5 mm/s
    np.testing.assert_allclose(s.a_des, [0, 0, -1])  # orientation unchanged


def test_supervisor_approach_to_start_xy():
    c = cfg(start_xy=[0.5, 0.02])
    dt = 0.01
    s = supervisor.supervisor_step(supervisor.SupervisorState(), inputs(0.0, F=0.0), c, dt)
    np.testing.assert_allclose(s.P_des, [0.5, 0.02])
    s = supervisor.supervisor_step(s, inputs(0.01, F=9.0), c, dt)  # contact, but not there yet
    assert s.phase == supervisor.Phase.APPROACH
    s = supervisor.supervisor_step(s, inputs(0.02, p=(0.5005, 0.02, 0.1), F=9.0), c, dt)
    assert s.phase == supervisor.Phase.EXPLORE
    with pytest.raises(ValueError, match="start_xy"):
        supervisor.supervisor_step(
            supervisor.SupervisorState(), inputs(0.0), cfg(start_xy=[0.5]), dt
        )


def test_a_bad_start_xy_is_refused_when_the_supervisor_is_built():
    # The scenario loader accepts any list of finite numbers; a start point that is not
    # [x, y] must fail when the diagram is built (as a bad pivot_pose does), not at the
    # first control period of the simulation.
    assert supervisor.given_start_xy([]) is None
    np.testing.assert_allclose(supervisor.given_start_xy([0.5, 0.02]), [0.5, 0.02])
    for bad in ([0.5], [0.5, 0.0, 0.1], [0.5, math.nan], [0.5, "a"]):
        with pytest.raises(ValueError, match="controller.start_xy"):
            supervisor.given_start_xy(bad)
        with pytest.raises(ValueError, match="controller.start_xy"):
            ScanSupervisor(cfg(start_xy=bad))


def test_supervisor_explore_ends_when_kidney_leaves_after_debounce():
    c = cfg(visibility_debounce=0.1, explore_min_seen_travel=0.0)
    dt = 0.01
    s = supervisor.supervisor_step(supervisor.SupervisorState(), inputs(0.0, F=9.0), c, dt)
    s = supervisor.supervisor_step(s, inputs(0.01), c, dt)
    assert s.phase == supervisor.Phase.EXPLORE
    s, t = _unseen(s, 0.01, 9, c, dt)
    assert s.phase == supervisor.Phase.EXPLORE  # 0.08 s invisible: not yet
    s, t = _unseen(s, t, 3, c, dt)
    assert s.phase == supervisor.Phase.LOCALIZE
    assert "left the image" in s.events[-1][2]


def test_transverse_orientation():
    a = np.array([0.0, 0.0, -1.0])
    np.testing.assert_allclose(supervisor.transverse_orientation(a, [0.7, -0.7, 0]), [1, 0, 0])
    np.testing.assert_allclose(supervisor.transverse_orientation(a, [-0.7, 0.7, 0]), [-1, 0, 0])
    a = np.array([math.sin(0.2), 0.0, -math.cos(0.2)])  # tilted about y
    o = supervisor.transverse_orientation(a, [1, 0, 0])
    assert o @ a == pytest.approx(0.0) and np.linalg.norm(o) == pytest.approx(1.0)
    assert o[1] == pytest.approx(0.0) and o[0] > 0.9


def test_supervisor_explore_centres_mask():
    c = cfg(K_p7=0.02)
    dt = 0.01
    s = supervisor.supervisor_step(supervisor.SupervisorState(), inputs(0.0), c, dt)
    s = supervisor.supervisor_step(s, inputs(0.01), c, dt)
    x0 = s.P_des[0]
    s = supervisor.supervisor_step(s, inputs(0.02, c=0.9), c, dt)
    assert s.P_des[0] == pytest.approx(x0 + 0.02 * 0.4 * dt)  # x_P = +x_B


def run_to_localize(c, dt=0.01):
    s = supervisor.supervisor_step(supervisor.SupervisorState(), inputs(0.0), c, dt)
    s = supervisor.supervisor_step(s, inputs(0.01), c, dt)
    t = 0.01
    while s.phase == supervisor.Phase.EXPLORE:
        t += dt
        s = supervisor.supervisor_step(s, inputs(t), c, dt)
    return s, t


def test_supervisor_localize_transit_pivot_done():
    c = cfg(
        exploration_ratio=0.05,
        localize_hold_time=0.2,
        pivot_rate=0.2,
        max_pivot_tilt=0.6,
        visibility_debounce=0.05,
    )
    dt = 0.01
    s, t = run_to_localize(c, dt)
    assert s.phase == supervisor.Phase.LOCALIZE
    R_BK = RotationMatrix(RollPitchYaw(0.1, 0.2, math.pi / 2 + 0.1)).matrix()
    p_BK = np.array([0.57, 0.03, 0.0])
    # Waits for the hold time and for the localizer.
    t += dt
    s = supervisor.supervisor_step(s, inputs(t, R_BK=R_BK, p_BK=p_BK, ready=False), c, dt)
    assert s.phase == supervisor.Phase.LOCALIZE
    t += 0.3
    s = supervisor.supervisor_step(s, inputs(t, R_BK=R_BK, p_BK=p_BK, ready=False), c, dt)
    assert s.phase == supervisor.Phase.LOCALIZE
    s = supervisor.supervisor_step(s, inputs(t + dt, R_BK=R_BK, p_BK=p_BK), c, dt)
    assert s.phase == supervisor.Phase.TRANSIT
    t += dt
    R_star, p_star = supervisor.optimal_pivot_pose(R_BK, p_BK)
    np.testing.assert_allclose(s.a_des, R_star[:, 2])
    np.testing.assert_allclose(s.o_des, R_star[:, 0])
    np.testing.assert_allclose(s.P_des, p_star[:2])
    # Not there yet.
    t += dt
    s = supervisor.supervisor_step(s, inputs(t, p=(0.55, 0.0, 0.1), R=R_star), c, dt)
    assert s.phase == supervisor.Phase.TRANSIT
    t += dt
    s = supervisor.supervisor_step(s, inputs(t, p=(0.5705, 0.03, 0.1), R=R_star), c, dt)
    assert s.phase == supervisor.Phase.PIVOT
    # Pivot: visible until tilt +0.3 rad, then invisible beyond; other side beyond -0.2 rad.
    tilts, a_dots, required = [], [], []
    while s.phase == supervisor.Phase.PIVOT and t < 60:
        t += dt
        vis = -0.2 < s.pivot_angle < 0.3
        s = supervisor.supervisor_step(
            s, inputs(t, p=(0.5705, 0.03, 0.1), R=R_star, visible=vis), c, dt
        )
        tilts.append(s.pivot_angle)
        required.append((vis, supervisor.segmentation_required(s)))
        a_dots.append(s.a_des_dot)
        np.testing.assert_allclose(s.o_des, R_star[:, 0])  # o_des unchanged
        assert s.a_des @ s.o_des == pytest.approx(0.0, abs=1e-9)
    assert s.phase == supervisor.Phase.DONE
    assert len(s.pivot_limits) == 2
    assert 0.3 <= s.pivot_limits[0] <= 0.3 + 0.2 * (0.05 + 2 * dt)
    assert -0.2 - 0.2 * (0.05 + 2 * dt) <= s.pivot_limits[1] <= -0.2
    # After a leg ends the tilt rate ramps down (pivot_acceleration): bounded overshoot.
    overshoot = 0.2**2 / (2 * c.pivot_acceleration)
    assert max(tilts) == pytest.approx(s.pivot_limits[0] + overshoot, abs=0.2 * dt + 1e-3)
    # The rate never jumps by more than pivot_acceleration dt per period.
    speeds = np.diff(tilts[:-1]) / dt  # (the last entry is DONE)
    assert np.abs(np.diff(speeds)).max() <= c.pivot_acceleration * dt + 1e-9
    assert angle_between(s.a_des, R_star[:, 2]) == pytest.approx(abs(s.pivot_limits[1]), abs=0.01)
    assert max(np.linalg.norm(a) for a in a_dots) == pytest.approx(0.2)
    # The kidney is required except while coming back from the first leg's end.
    assert any(not r for v, r in required) and all(r for v, r in required if v)
    # DONE ramps the last tilt rate down, then holds.
    for k in range(100):
        t += dt
        s = supervisor.supervisor_step(s, inputs(t, R=R_star, visible=False), c, dt)
    assert s.phase == supervisor.Phase.DONE and s.pivot_speed == 0.0
    assert np.linalg.norm(s.a_des_dot) == 0.0
    # a_des_dot is the rate of a_des actually applied (for eq. 2's feed-forward).
    assert all(np.linalg.norm(a) <= 0.2 + 1e-9 for a in a_dots)


def test_supervisor_pivot_bounded_by_max_tilt():
    c = cfg(exploration_ratio=0.02, localize_hold_time=0.0, pivot_rate=0.5, max_pivot_tilt=0.3)
    dt = 0.01
    s, t = run_to_localize(c, dt)
    s = supervisor.supervisor_step(s, inputs(t + dt, R_BK=np.eye(3), p_BK=[0.55, 0.0, 0.0]), c, dt)
    R_star, _ = supervisor.optimal_pivot_pose(np.eye(3), [0.55, 0, 0])
    t += 2 * dt
    s = supervisor.supervisor_step(s, inputs(t, p=(0.55, 0.0, 0.1), R=R_star), c, dt)
    assert s.phase == supervisor.Phase.PIVOT
    angles = []
    while s.phase == supervisor.Phase.PIVOT:
        t += dt
        s = supervisor.supervisor_step(s, inputs(t, p=(0.55, 0.0, 0.1), R=R_star), c, dt)
        angles.append(s.pivot_angle)
    assert s.phase == supervisor.Phase.DONE
    assert max(angles) == pytest.approx(0.3) and min(angles) == pytest.approx(-0.3)
    assert "maximum tilt" in s.events[-2][2]


def test_supervisor_aborts_with_reason():
    c = cfg(exploration_ratio=0.02, localize_hold_time=0.0, transit_timeout=0.5)
    dt = 0.01
    s = supervisor.supervisor_step(supervisor.SupervisorState(), inputs(0.0), c, dt)
    bad = supervisor.supervisor_step(s, inputs(0.01, p=(math.nan, 0, 0)), c, dt)
    assert bad.phase == supervisor.Phase.ABORT and "non-finite" in bad.reason
    s, t = run_to_localize(c, dt)
    waiting = supervisor.supervisor_step(
        s, inputs(t + dt, R_BK=np.eye(3), p_BK=[0.6, 0.1, 0], ready=False), c, dt
    )
    assert waiting.phase == supervisor.Phase.LOCALIZE
    late = supervisor.supervisor_step(
        waiting, inputs(t + c.localize_timeout + 1.0, ready=False), c, dt
    )
    assert late.phase == supervisor.Phase.ABORT and "LOCALIZE timeout" in late.reason
    nopose = supervisor.supervisor_step(s, inputs(t + dt, R_BK=None), c, dt)
    assert nopose.phase == supervisor.Phase.ABORT and "kidney pose" in nopose.reason
    s = supervisor.supervisor_step(s, inputs(t + dt, R_BK=np.eye(3), p_BK=[0.6, 0.1, 0]), c, dt)
    assert s.phase == supervisor.Phase.TRANSIT
    s = supervisor.supervisor_step(s, inputs(t + 1.0), c, dt)
    assert s.phase == supervisor.Phase.ABORT and "timeout" in s.reason
    stopped = supervisor.supervisor_step(
        supervisor.SupervisorState(), dataclasses.replace(inputs(0.0), safety_stopped=True), c, dt
    )
    assert stopped.phase == supervisor.Phase.ABORT and stopped.reason == "safety stop"
    # ABORT and DONE are terminal.
    s2 = supervisor.supervisor_step(s, inputs(t + 2.0), c, dt)
    assert s2.phase == supervisor.Phase.ABORT


# ------------------------------------------------------------------ respiration gating
def gated(t, allowed, **kw):
    return dataclasses.replace(inputs(t, **kw), motion_allowed=allowed)


def test_supervisor_exploration_holds_still_outside_breath_holds():
    """Outside a hold the exploration target stays put and the kidney may leave the image;
    travel resumes in the next hold and the total travel is unchanged."""
    c = cfg(exploration_ratio=0.1, kidney_length=0.1, visibility_debounce=0.05)
    dt = 0.01
    s = supervisor.supervisor_step(supervisor.SupervisorState(), inputs(0.0), c, dt)
    s = supervisor.supervisor_step(s, inputs(0.01), c, dt)
    assert s.phase == supervisor.Phase.EXPLORE
    t = 0.01
    for _ in range(50):  # 0.5 s of travel in a hold
        t += dt
        s = supervisor.supervisor_step(s, gated(t, True), c, dt)
    travel, P = s.travel, s.P_des.copy()
    assert travel == pytest.approx(51 * 0.005 * dt)  # the EXPLORE entry step moves too
    for _ in range(100):  # 1 s of breathing: kidney gone from the image
        t += dt
        s = supervisor.supervisor_step(s, gated(t, False, visible=False), c, dt)
        assert s.phase == supervisor.Phase.EXPLORE and s.paused
        assert not supervisor.segmentation_required(s)
    assert s.travel == travel
    np.testing.assert_array_equal(s.P_des, P)
    assert s.paused_time == pytest.approx(1.0)
    t += dt
    s = supervisor.supervisor_step(s, gated(t, True), c, dt)  # the next hold
    assert not s.paused and supervisor.segmentation_required(s)
    assert s.travel > travel
    while s.phase == supervisor.Phase.EXPLORE and t < 60:
        t += dt
        s = supervisor.supervisor_step(s, gated(t, True), c, dt)
    assert s.phase == supervisor.Phase.LOCALIZE and s.travel == pytest.approx(0.01)
    # A pause does not outlive its phase: paused, then the adaptive stop ends EXPLORE.
    s = supervisor.supervisor_step(supervisor.SupervisorState(), inputs(0.0), c, dt)
    s = supervisor.supervisor_step(s, gated(0.01, False), c, dt)
    s = supervisor.supervisor_step(s, gated(0.02, False), c, dt)
    assert s.phase == supervisor.Phase.EXPLORE and s.paused
    u = dataclasses.replace(gated(0.03, False), exploration_sufficient=True)
    s = supervisor.supervisor_step(s, u, c, dt)
    assert s.phase == supervisor.Phase.LOCALIZE and not s.paused


def test_a_hold_that_carries_the_kidney_out_of_view_does_not_end_exploration():
    """The breath taken in for the first hold may move the kidney out of the image before
    the sweep has started: it has not "left" the image (it was never in it while the probe
    could move), so the sweep goes on until it finds the kidney, and ends when the kidney
    leaves the image after that."""
    c = cfg(
        exploration_ratio=0.5,
        kidney_length=0.1,
        visibility_debounce=0.05,
        explore_min_seen_travel=0.0,
    )
    dt = 0.01
    s = supervisor.supervisor_step(supervisor.SupervisorState(), inputs(0.0), c, dt)
    s = supervisor.supervisor_step(s, gated(0.01, False), c, dt)
    assert s.phase == supervisor.Phase.EXPLORE
    t = 0.01
    for k in range(100):  # the hold starts with the kidney out of view: the sweep goes on
        t += dt
        glimpse = k == 50  # an edge in one frame is not the kidney in view
        s = supervisor.supervisor_step(s, gated(t, True, visible=glimpse), c, dt)
    assert s.phase == supervisor.Phase.EXPLORE and s.travel == pytest.approx(0.005, rel=0.05)
    for _ in range(20):  # the sweep reaches the kidney
        t += dt
        s = supervisor.supervisor_step(s, gated(t, True), c, dt)
    travel = s.travel
    while s.phase == supervisor.Phase.EXPLORE and t < 5:  # and then leaves it
        t += dt
        s = supervisor.supervisor_step(s, gated(t, True, visible=False), c, dt)
    assert s.phase == supervisor.Phase.LOCALIZE and "left the image" in s.events[-1][2]
    assert s.travel < travel + 0.001


def test_a_kidney_seen_too_briefly_to_localize_does_not_end_exploration():
    """A kidney that leaves the image before it has been seen over explore_min_seen_travel
    cannot be localized: the sighting is forgotten and the sweep goes on; once seen over
    that much, its leaving ends the exploration."""
    c = cfg(exploration_ratio=0.5, kidney_length=0.2, visibility_debounce=0.05)
    dt = 0.01
    s = supervisor.supervisor_step(supervisor.SupervisorState(), inputs(0.0), c, dt)
    s = supervisor.supervisor_step(s, gated(0.01, True), c, dt)
    assert s.phase == supervisor.Phase.EXPLORE
    t = 0.01
    for k in range(200):  # in view at the start, then gone after a few mm
        t += dt
        s = supervisor.supervisor_step(s, gated(t, True, visible=k < 40), c, dt)
    assert s.phase == supervisor.Phase.EXPLORE and not s.explore_seen
    start = s.travel
    while s.travel - start < c.explore_min_seen_travel + 0.002:  # found again, seen longer
        t += dt
        s = supervisor.supervisor_step(s, gated(t, True), c, dt)
    for _ in range(10):
        t += dt
        s = supervisor.supervisor_step(s, gated(t, True, visible=False), c, dt)
    assert s.phase == supervisor.Phase.LOCALIZE and "left the image" in s.events[-1][2]


def _to_pivot(c, dt=0.01):
    s, t = run_to_localize(c, dt)
    return _finish_to_pivot(s, t, c, dt)


def _finish_to_pivot(s, t, c, dt=0.01):
    """From LOCALIZE: a kidney pose, TRANSIT at p*, PIVOT."""
    R_BK = RotationMatrix(RollPitchYaw(0.0, 0.0, math.pi / 2)).matrix()
    p_BK = np.array([0.55, 0.0, 0.0])
    t += 1.0
    s = supervisor.supervisor_step(s, inputs(t, R_BK=R_BK, p_BK=p_BK), c, dt)
    R_star, _ = supervisor.optimal_pivot_pose(R_BK, p_BK)
    t += dt
    s = supervisor.supervisor_step(s, inputs(t, p=(0.55, 0.0, 0.1), R=R_star), c, dt)
    assert s.phase == supervisor.Phase.PIVOT
    return s, t, R_star


def test_supervisor_pivot_ramps_to_rest_outside_breath_holds_and_resumes():
    c = cfg(
        exploration_ratio=0.02,
        localize_hold_time=0.0,
        pivot_rate=0.2,
        max_pivot_tilt=0.5,
        visibility_debounce=0.05,
    )
    dt = 0.01
    s, t, R = _to_pivot(c, dt)
    for _ in range(100):
        t += dt
        s = supervisor.supervisor_step(s, gated(t, True, R=R), c, dt)
    angle = s.pivot_angle
    assert s.pivot_speed == pytest.approx(0.2)
    speeds = []
    for _ in range(200):  # 2 s outside a hold, kidney not visible
        t += dt
        s = supervisor.supervisor_step(s, gated(t, False, R=R, visible=False), c, dt)
        speeds.append(s.pivot_speed)
        assert s.phase == supervisor.Phase.PIVOT and s.pivot_legs_done == 0
    assert speeds[-1] == 0.0
    assert np.all(np.abs(np.diff([0.2] + speeds)) <= c.pivot_acceleration * dt + 1e-12)
    ramp = 0.2**2 / (2 * c.pivot_acceleration)  # the stopping distance
    assert s.pivot_angle == pytest.approx(angle + ramp, abs=0.2 * dt + 1e-6)
    held = s.pivot_angle
    t += dt
    s = supervisor.supervisor_step(s, gated(t, True, R=R), c, dt)
    assert s.pivot_angle > held and not s.paused


def test_supervisor_aborts_when_the_kidney_moved_after_localization():
    c = cfg(exploration_ratio=0.02, localize_hold_time=0.0, max_relocalizations=0)
    dt = 0.01
    s, t, R = _to_pivot(c, dt)
    t += dt
    u = dataclasses.replace(inputs(t, R=R), tracking_error="drift 12 mm")
    s = supervisor.supervisor_step(s, u, c, dt)
    assert s.phase == supervisor.Phase.ABORT
    assert s.reason == "kidney moved: drift 12 mm"
    # Before localization a tracking error has no meaning and is ignored.
    s2 = supervisor.supervisor_step(supervisor.SupervisorState(), inputs(0.0), c, dt)
    s2 = supervisor.supervisor_step(
        s2, dataclasses.replace(inputs(0.01), tracking_error="x"), c, dt
    )
    assert s2.phase == supervisor.Phase.EXPLORE


def test_a_moved_kidney_is_localized_again_a_bounded_number_of_times():
    """A tracking error in PIVOT starts a re-exploration from where the probe is (first
    turning it straight down and transverse, the cloud cleared, a new localization round);
    the next one after max_relocalizations aborts."""
    c = cfg(exploration_ratio=0.02, localize_hold_time=0.0, max_relocalizations=1)
    dt = 0.01
    s, t, R = _to_pivot(c, dt)
    assert s.localization_round == 0
    s.cap_slides = ((1, 0.007),)  # a slide at the tilt cap of the pivot being abandoned
    t += dt
    u = dataclasses.replace(inputs(t, R=R), tracking_error="drift 9 mm")
    s = supervisor.supervisor_step(s, u, c, dt)
    assert s.phase == supervisor.Phase.EXPLORE and s.reorienting
    assert s.cap_slides == () and s.cap_slide == 0
    assert s.localization_round == 1 and s.relocalizations == 1
    assert "re-localizing (1 of 1)" in s.events[-1][2]
    assert not supervisor.segmentation_required(s)
    np.testing.assert_allclose(s.a_des, [0.0, 0.0, -1.0])
    assert abs(s.o_des[1]) < 1e-9  # transverse: across the body (base x)
    # Still until the probe is turned (the pivot left it tilted): no travel.
    y0 = s.P_des[1]
    for _ in range(5):
        t += dt
        s = supervisor.supervisor_step(s, inputs(t, R=R), c, dt)
    assert s.reorienting and s.travel == 0.0 and s.P_des[1] == y0
    # Turned: it backs out of the kidney against the scan direction (-y: +y), the kidney's
    # leaving the image no loss, until it has left the image for visibility_debounce.
    R_transverse = np.column_stack([s.o_des, np.cross(s.a_des, s.o_des), s.a_des])
    t += dt
    s = supervisor.supervisor_step(s, inputs(t, R=R_transverse), c, dt)
    assert not s.reorienting and s.retreating
    assert "backing out" in s.events[-1][2]
    for _ in range(100):
        t += dt
        s = supervisor.supervisor_step(s, inputs(t, R=R_transverse), c, dt)
    assert s.retreating and s.P_des[1] > y0 + 0.004 and not supervisor.segmentation_required(s)
    while s.retreating:
        t += dt
        s = supervisor.supervisor_step(s, inputs(t, R=R_transverse, visible=False), c, dt)
        assert not supervisor.segmentation_required(s)
    assert "re-exploring from" in s.events[-1][2] and "left the image" in s.events[-1][2]
    assert s.travel == 0.0 and s.awaiting_kidney
    # Sweeping forward from behind the kidney: its absence is no loss until it comes into
    # view; then it explores and localizes with the new round.
    y_back = s.P_des[1]
    for _ in range(10):
        t += dt
        s = supervisor.supervisor_step(s, inputs(t, R=R_transverse, visible=False), c, dt)
    assert s.P_des[1] < y_back and not supervisor.segmentation_required(s)
    for _ in range(400):
        t += dt
        s = supervisor.supervisor_step(s, inputs(t, R=R_transverse), c, dt)
        if s.phase != supervisor.Phase.EXPLORE:
            break
    assert not s.awaiting_kidney
    assert not s.reorienting and s.phase == supervisor.Phase.LOCALIZE and s.travel > 0
    s, t, R = _finish_to_pivot(s, t, c, dt)
    t += dt
    s = supervisor.supervisor_step(
        s, dataclasses.replace(inputs(t, R=R), tracking_error="drift 9 mm"), c, dt
    )
    assert s.phase == supervisor.Phase.ABORT
    assert s.reason == "kidney moved: drift 9 mm (after 1 re-localizations)"


def test_reexploration_backs_out_at_most_one_kidney_length():
    """A kidney that never leaves the image while the probe backs out: the re-exploration
    sweeps forward after the kidney length the exploration plans with (retreat_limit)."""
    c = cfg(exploration_ratio=0.02, localize_hold_time=0.0, max_relocalizations=1)
    assert supervisor.retreat_limit(c) == pytest.approx(c.kidney_length)
    dt = 0.01
    s, t, R = _to_pivot(c, dt)
    t += dt
    s = supervisor.supervisor_step(
        s, dataclasses.replace(inputs(t, R=R), tracking_error="drift 9 mm"), c, dt
    )
    R_transverse = np.column_stack([s.o_des, np.cross(s.a_des, s.o_des), s.a_des])
    n, y_max = 0, -math.inf
    while (s.reorienting or s.retreating) and n < 10000:
        t += dt
        n += 1
        y_max = max(y_max, s.P_des[1])
        s = supervisor.supervisor_step(s, inputs(t, R=R_transverse), c, dt)
    assert not s.retreating
    assert s.events[-1][2] == "re-exploring from 100.0 mm back (one kidney length)"
    assert y_max == pytest.approx(c.kidney_length, abs=0.002)  # from y = 0, against -y


def test_reexploration_starts_a_few_degrees_short_of_vertical_after_settling():
    """A probe pressed on sloping skin that stops 4.5 or 7.3 deg short of straight down explores
    from there after REORIENT_SETTLE s (it used to wait out the transit timeout and abort);
    one still 10 deg off keeps turning."""
    c = cfg(exploration_ratio=0.02, localize_hold_time=0.0, max_relocalizations=1)
    dt = 0.01
    for tilt_deg, explores in ((4.5, True), (7.3, True), (10.0, False)):
        s, t, R = _to_pivot(c, dt)
        t += dt
        u = dataclasses.replace(inputs(t, R=R), tracking_error="drift 9 mm")
        s = supervisor.supervisor_step(s, u, c, dt)
        R_short = RotationMatrix(RollPitchYaw(math.radians(tilt_deg), 0.0, 0.0)).matrix()
        R_short = R_short @ np.column_stack([s.o_des, np.cross(s.a_des, s.o_des), s.a_des])
        t0 = t
        while s.reorienting and t - t0 < supervisor.REORIENT_SETTLE + 1.0:
            t += dt
            s = supervisor.supervisor_step(s, inputs(t, R=R_short), c, dt)
        assert s.reorienting != explores, tilt_deg
        if explores:
            assert t - t0 == pytest.approx(supervisor.REORIENT_SETTLE, abs=2 * dt)


def test_localize_waits_for_motion_allowed_and_a_breathing_error_aborts():
    """The breath-hold protocol: TRANSIT starts only in a sensed hold (motion_allowed); a
    protocol error (no hold sensed) aborts with its reason."""
    c = cfg(exploration_ratio=0.02, localize_hold_time=0.0)
    dt = 0.01
    s = supervisor.SupervisorState()
    t = 0.0
    while s.phase != supervisor.Phase.LOCALIZE:
        s = supervisor.supervisor_step(s, inputs(t), c, dt)
        t += dt
    R_BK, p_BK = np.eye(3), np.array([0.55, 0.0, 0.05])
    for _ in range(50):
        u = dataclasses.replace(inputs(t, R_BK=R_BK, p_BK=p_BK), motion_allowed=False)
        s = supervisor.supervisor_step(s, u, c, dt)
        t += dt
    assert s.phase == supervisor.Phase.LOCALIZE
    s = supervisor.supervisor_step(s, inputs(t, R_BK=R_BK, p_BK=p_BK), c, dt)
    assert s.phase == supervisor.Phase.TRANSIT
    u = dataclasses.replace(inputs(t + dt), breathing_error="no breath-hold sensed")
    s = supervisor.supervisor_step(s, u, c, dt)
    assert s.phase == supervisor.Phase.ABORT
    assert s.reason == "breath-hold protocol: no breath-hold sensed"


def test_approach_without_contact_aborts_after_the_travel_limit():
    """In free air (no force) APPROACH gives up with a clear reason once the tip has moved
    approach_max_travel along the beam; before that it keeps pressing."""
    c, dt = cfg(approach_max_travel=0.05), 0.01
    s = supervisor.supervisor_step(supervisor.SupervisorState(), inputs(0.0, F=0.0), c, dt)
    s = supervisor.supervisor_step(s, inputs(0.5, p=(0.5, 0.0, 0.07), F=0.0), c, dt)
    assert s.phase == supervisor.Phase.APPROACH  # 30 mm down: keep going
    s = supervisor.supervisor_step(s, inputs(1.0, p=(0.5, 0.0, 0.045), F=0.0), c, dt)
    assert s.phase == supervisor.Phase.ABORT
    assert s.reason.startswith("no contact") and "55 mm" in s.reason
    slow = cfg(approach_timeout=2.0)
    s = supervisor.supervisor_step(supervisor.SupervisorState(), inputs(0.0, F=0.0), slow, dt)
    s = supervisor.supervisor_step(s, inputs(2.5, F=0.0), slow, dt)
    assert s.phase == supervisor.Phase.ABORT and "no contact after 2 s" in s.reason


def test_contact_needs_the_force_held_for_the_dwell_time():
    """A force transient (an accelerating arm's torque estimate) is not contact: the force
    must stay at contact_fraction F_des for contact_dwell."""
    c, dt = cfg(contact_dwell=0.2), 0.01
    s = supervisor.supervisor_step(supervisor.SupervisorState(), inputs(0.0, F=0.0), c, dt)
    s = supervisor.supervisor_step(s, inputs(0.10, F=9.0), c, dt)  # spike ...
    s = supervisor.supervisor_step(s, inputs(0.15, F=1.0), c, dt)  # ... gone
    s = supervisor.supervisor_step(s, inputs(0.20, F=9.0), c, dt)
    s = supervisor.supervisor_step(s, inputs(0.35, F=9.0), c, dt)
    assert s.phase == supervisor.Phase.APPROACH  # 0.15 s held
    s = supervisor.supervisor_step(s, inputs(0.41, F=8.0), c, dt)
    assert s.phase == supervisor.Phase.EXPLORE  # 0.21 s held


# ------------------------------------------------------------------ exploration length
def test_exploration_target_rule():
    fixed = cfg(exploration_ratio=0.6, kidney_length=0.1, exploration_length="fixed")
    assert supervisor.exploration_target(fixed, 0.127) == pytest.approx(0.06)
    est = cfg(
        exploration_ratio=0.6,
        kidney_length=0.1,
        exploration_length="estimated",
        exploration_length_factor=1.5,
    )
    assert supervisor.exploration_target(est, math.nan) == pytest.approx(0.06)  # not known
    assert supervisor.exploration_target(est) == pytest.approx(0.06)
    assert supervisor.exploration_target(est, 0.127) == pytest.approx(0.6 * 0.127)
    assert supervisor.exploration_target(est, 0.088) == pytest.approx(0.6 * 0.088)
    # Never beyond the factor times the fixed travel, nor below it divided by the factor.
    assert supervisor.exploration_target(est, 0.30) == pytest.approx(1.5 * 0.06)
    assert supervisor.exploration_target(est, 0.02) == pytest.approx(0.06 / 1.5)
    assert supervisor.exploration_target(est, -1.0) == pytest.approx(0.06)
    # An unknown length (the latest fit failed its checks) is the longest allowed.
    assert supervisor.exploration_target(est, math.inf) == pytest.approx(1.5 * 0.06)
    assert supervisor.exploration_target(fixed, math.inf) == pytest.approx(0.06)


def _explore_until_localize(c, estimate, t_max=20.0):
    dt = 0.01
    s = supervisor.SupervisorState()
    s.initialised, s.phase, s.P_des = True, supervisor.Phase.EXPLORE, np.array([0.55, 0.0])
    t = 0.0
    while s.phase == supervisor.Phase.EXPLORE and t < t_max:
        t += dt
        u = dataclasses.replace(
            inputs(t, p=(0.55, s.P_des[1], 0.1)), kidney_length_estimate=estimate(s.travel)
        )
        s = supervisor.supervisor_step(s, u, c, dt)
    return s


def test_exploration_ends_at_er_times_the_estimated_length():
    c = cfg(exploration_ratio=0.5, kidney_length=0.1, exploration_length="estimated")
    # The estimate appears after 30 mm: a 127 mm kidney is explored for 63.5 mm.
    s = _explore_until_localize(c, lambda travel: 0.127 if travel >= 0.03 else math.nan)
    assert s.phase == supervisor.Phase.LOCALIZE
    assert s.travel == pytest.approx(0.5 * 0.127, abs=1e-6)
    assert "estimated kidney length 127 mm" in s.events[-1][2]
    # A short kidney ends it early, once the estimate is known.
    s = _explore_until_localize(c, lambda travel: 0.088 if travel >= 0.03 else math.nan)
    assert s.travel == pytest.approx(0.044, abs=1e-6)
    # Without an estimate, or with exploration_length: fixed, ER x L_m.
    assert _explore_until_localize(c, lambda travel: math.nan).travel == pytest.approx(0.05)
    fixed = dataclasses.replace(c, exploration_length="fixed")
    s = _explore_until_localize(fixed, lambda travel: 0.127)
    assert s.travel == pytest.approx(0.05) and "estimated" not in s.events[-1][2]


def test_exploration_goes_on_while_the_length_is_unknown():
    """After a failed length fit (+inf) the sweep goes on towards the longest kidney
    (1.5 x 0.5 x 100 mm); a later fit that passes ends it at ER x its length."""
    c = cfg(exploration_ratio=0.5, kidney_length=0.1, exploration_length="estimated")
    s = _explore_until_localize(c, lambda travel: math.inf if travel >= 0.03 else math.nan)
    assert s.travel == pytest.approx(0.075, abs=1e-6)
    assert "longest kidney length 150 mm" in s.events[-1][2]
    s = _explore_until_localize(
        c, lambda travel: 0.13 if travel >= 0.06 else (math.inf if travel >= 0.03 else math.nan)
    )
    assert s.travel == pytest.approx(0.065, abs=1e-6)
    assert "estimated kidney length 130 mm" in s.events[-1][2]


# ------------------------------------------------------------------ given pivot pose
def test_given_pivot_pose_is_t_star_shaped_and_round_trips():
    R_BK = RotationMatrix(RollPitchYaw(0.2, -0.3, 2.4)).matrix()
    p_BK = np.array([0.52, -0.04, 0.03])
    R_star, p_star = supervisor.optimal_pivot_pose(R_BK, p_BK)
    given = supervisor.pivot_pose_as_given(R_star, p_star)
    assert given[:2] == pytest.approx([0.52, -0.04])
    x_k = R_BK[:, 0]
    assert given[2] == pytest.approx(math.atan2(x_k[1], x_k[0]))
    R, p = supervisor.given_pivot_pose(given, z=0.2)
    np.testing.assert_allclose(R, R_star, atol=1e-12)  # eq. 20-22's T* again
    np.testing.assert_allclose(p, [0.52, -0.04, 0.2])
    assert np.linalg.det(R) == pytest.approx(1.0)
    R, _ = supervisor.given_pivot_pose([0.5, 0.0, math.pi / 2])
    np.testing.assert_allclose(R[:, 0], [0, 1, 0], atol=1e-12)  # yaw from base x about z
    np.testing.assert_allclose(R[:, 2], [0, 0, -1])
    for bad in (
        [0.5, 0.0],
        [0.5, math.nan, 0.0],
        [0.5, 0.0, 1.0, 2.0],
        [0.5, 0.0, "a"],
        [0.5, None, 0.0],
    ):
        with pytest.raises(ValueError, match="controller.pivot_pose"):
            supervisor.given_pivot_pose(bad)


def test_given_pivot_pose_goes_from_contact_to_transit_and_pivots_there():
    given = [0.56, 0.02, 0.3]
    c = cfg(
        pivot_pose=given, pivot_rate=0.2, max_pivot_tilt=0.3, pivot_strategy="predicted_end"
    )  # refused by the scenario checks; falls back
    dt = 0.01
    s = supervisor.supervisor_step(supervisor.SupervisorState(), inputs(0.0, F=0.0), c, dt)
    assert s.phase == supervisor.Phase.APPROACH
    s = supervisor.supervisor_step(s, inputs(0.01, F=9.0), c, dt)
    assert s.phase == supervisor.Phase.TRANSIT  # no EXPLORE, no LOCALIZE
    assert "given pivot pose" in s.events[-1][2]
    R_star, _ = supervisor.given_pivot_pose(given)
    np.testing.assert_allclose(s.P_des, given[:2])
    np.testing.assert_allclose(s.a_des, R_star[:, 2])
    np.testing.assert_allclose(s.o_des, R_star[:, 0])
    assert s.travel == 0.0
    # An identity X_BK (an unlocalized localizer's default) is never read.
    u = inputs(0.02, p=(0.5605, 0.02, 0.1), R=R_star, R_BK=np.eye(3), p_BK=np.zeros(3))
    s = supervisor.supervisor_step(s, u, c, dt)
    assert s.phase == supervisor.Phase.PIVOT and "two-leg" in s.events[-1][2]
    t = 0.02
    while s.phase == supervisor.Phase.PIVOT and t < 30:
        t += dt
        s = supervisor.supervisor_step(s, inputs(t, p=(0.5605, 0.02, 0.1), R=R_star), c, dt)
    assert s.phase == supervisor.Phase.DONE and len(s.pivot_limits) == 2
    np.testing.assert_allclose(s.o_des, R_star[:, 0])


# ------------------------------------------------------------------ line sweep (SL)
def test_line_sweep_waits_for_the_kidney_then_ends_when_it_leaves():
    c = cfg(
        sweep="line",
        visibility_debounce=0.1,
        line_sweep_max_travel=0.2,
        scan_direction="+y",
        exploration_ratio=0.05,
        kidney_length=0.1,
    )
    dt = 0.01
    s = supervisor.supervisor_step(supervisor.SupervisorState(), inputs(0.0, visible=False), c, dt)
    s = supervisor.supervisor_step(s, inputs(0.01, visible=False), c, dt)
    assert s.phase == supervisor.Phase.EXPLORE and s.awaiting_kidney
    t = 0.01
    for _ in range(100):  # 1 s beyond the kidney's end: not "left", not required
        t += dt
        s = supervisor.supervisor_step(
            s, inputs(t, p=(0.55, s.P_des[1], 0.1), visible=False, c=0.9), c, dt
        )
        assert s.phase == supervisor.Phase.EXPLORE
        assert not supervisor.segmentation_required(s)
    assert s.travel == pytest.approx(1.01 * c.scan_speed, abs=1e-9)  # contact came at t 0
    assert s.P_des[0] == pytest.approx(0.55)  # no centroid, no eq. 17 x correction
    for visible in [True] * 5 + [False] * 20:  # a glimpse of the pole (0.05 s) ...
        t += dt
        s = supervisor.supervisor_step(s, inputs(t, visible=visible), c, dt)
    assert s.phase == supervisor.Phase.EXPLORE and s.awaiting_kidney  # ... is not "seen"
    required = []
    for _ in range(175):  # 1.75 s of kidney: beyond ER x L_m (the pivot's 5 mm)
        t += dt
        s = supervisor.supervisor_step(s, inputs(t, p=(0.55, s.P_des[1], 0.1)), c, dt)
        assert s.phase == supervisor.Phase.EXPLORE
        required.append(supervisor.segmentation_required(s))
    # In view once seen for the debounce time (0.1 s), required from then on.
    assert required.index(True) == 10 and all(required[10:])
    travel = s.travel
    assert travel == pytest.approx(3.01 * c.scan_speed, abs=1e-9)
    s, t = _unseen(s, t, 9, c, dt)
    assert s.phase == supervisor.Phase.EXPLORE  # 0.09 s gone: not yet
    s, t = _unseen(s, t, 3, c, dt)
    assert s.phase == supervisor.Phase.DONE and "line sweep complete" in s.events[-1][2]
    assert s.reason == "" and s.travel < travel + 0.15 * c.scan_speed


def test_line_sweep_ends_at_its_maximum_travel():
    c = cfg(sweep="line", line_sweep_max_travel=0.01, scan_direction="-y")
    dt = 0.01

    def run(visible):
        s = supervisor.supervisor_step(supervisor.SupervisorState(), inputs(0.0), c, dt)
        t = 0.0
        while s.phase in (supervisor.Phase.APPROACH, supervisor.Phase.EXPLORE) and t < 10:
            t += dt
            s = supervisor.supervisor_step(
                s, inputs(t, p=(0.55, s.P_des[1], 0.1), visible=visible), c, dt
            )
        return s, t

    s, t = run(False)
    assert s.phase == supervisor.Phase.ABORT and "never came into view" in s.reason
    assert t == pytest.approx(0.01 / c.scan_speed, abs=3 * dt)
    s, _ = run(True)
    assert s.phase == supervisor.Phase.DONE and "line_sweep_max_travel" in s.events[-1][2]
    assert s.P_des[1] == pytest.approx(-0.01, abs=1e-4) and s.travel == pytest.approx(0.01)


def test_pivot_follow_error_is_the_angle_to_the_commanded_axis():
    R = R_DOWN @ RotationMatrix(RollPitchYaw(0.1, 0.0, 0.0)).matrix()  # tilted 0.1 rad
    assert supervisor.pivot_follow_error(R, R[:, 2]) == pytest.approx(0.0, abs=1e-7)
    assert supervisor.pivot_follow_error(R_DOWN, R[:, 2]) == pytest.approx(0.1)
    assert supervisor.pivot_follow_error(R_DOWN, -R_DOWN[:, 2]) == pytest.approx(math.pi)


def test_a_probe_that_stops_following_the_pivot_aborts_the_scan():
    """The probe follows a_des, then sticks (a joint at its limit): ABORT once it has lagged
    by more than pivot_follow_limit for pivot_follow_time, with the reason; a probe that
    follows never aborts."""
    c = cfg(
        exploration_ratio=0.02,
        localize_hold_time=0.0,
        pivot_rate=0.2,
        max_pivot_tilt=0.5,
        pivot_follow_limit=0.05,
        pivot_follow_time=0.5,
    )
    dt = 0.01
    s, t, R_star = _to_pivot(c, dt)

    def following(a):
        x = R_star[:, 0] - (R_star[:, 0] @ a) * a
        x /= np.linalg.norm(x)
        return np.column_stack([x, np.cross(a, x), a])

    for _ in range(100):  # 1 s following: no abort
        t += dt
        s = supervisor.supervisor_step(s, inputs(t, R=following(s.a_des)), c, dt)
        assert s.phase == supervisor.Phase.PIVOT
    stuck = following(s.a_des)
    lagging_from = None
    while s.phase == supervisor.Phase.PIVOT and t < 10:
        t += dt
        if lagging_from is None and supervisor.pivot_follow_error(stuck, s.a_des) > 0.05:
            lagging_from = t
        s = supervisor.supervisor_step(s, inputs(t, R=stuck), c, dt)
    assert s.phase == supervisor.Phase.ABORT
    assert "does not follow the pivot" in s.reason
    assert t - lagging_from == pytest.approx(0.5, abs=2 * dt)


def test_supervisor_state_copy_owns_its_arrays_and_keeps_every_field():
    s = supervisor.SupervisorState(
        phase=supervisor.Phase.PIVOT, travel=0.02, pivot_limits=(0.1,), reason="x"
    )
    c = s.copy()
    for f in dataclasses.fields(s):
        a, b = getattr(s, f.name), getattr(c, f.name)
        if isinstance(a, np.ndarray):
            assert a is not b and np.array_equal(a, b, equal_nan=True), f.name
            b[...] = 7.0  # writing the copy leaves the original alone
            assert not np.array_equal(a, b, equal_nan=True), f.name
        else:
            assert a == b or (a != a and b != b), f.name
    assert type(c) is supervisor.SupervisorState


# ------------------------------------------------------------------ slide at the tilt cap
def test_cap_slide_direction_is_horizontal_across_the_array_towards_the_lean():
    o = np.array([0.0, 1.0, 0.0])
    a_star = np.array([0.0, 0.0, -1.0])
    plus = supervisor.cap_slide_direction(o, a_star, 0.6)
    # a(theta) = a* cos + (o x a*) sin leans towards o x a* = -x for theta > 0.
    np.testing.assert_allclose(plus, [-1.0, 0.0])
    a = supervisor.rodrigues_pivot_update(a_star, o, 0.6)
    assert float(a[:2] @ plus) > 0.0  # the probe leans the way the tip slides
    np.testing.assert_allclose(supervisor.cap_slide_direction(o, a_star, -0.6), [1.0, 0.0])
    np.testing.assert_allclose(supervisor.cap_slide_direction(a_star, a_star, 0.6), [0.0, 0.0])


def _box_model(half_width: float, depth: float = 0.1):
    """A pivot model whose template is a box 80 mm long (along x), 2 half_width wide (along
    y) and 40 mm deep, a 100 mm fan (the probe pointing down from its tip)."""
    g, gy = np.linspace(-1.0, 1.0, 9), np.arange(-half_width, half_width + 1e-9, 0.001)
    pts = np.array([[0.04 * x, y, 0.02 * z] for x in g for y in gy for z in g])
    return supervisor.PivotModel(
        points_K=pts,
        probe_radius=0.05,
        half_angle=math.radians(30.0),
        depth=depth,
        slab_half_width=0.001,
        min_section_area=1.0e-4,
    )


def test_cap_slide_needed_is_where_the_template_leaves_the_image():
    # The array along x, the image plane x-z; the kidney (centre 50 mm below the tip)
    # reaches 20 mm across: a vertical probe leaves it after a 20 mm slide along y.
    model = _box_model(0.02)
    R_BP = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    tip = np.array([0.0, 0.0, 0.05])
    needed = supervisor.cap_slide_needed(model, np.eye(3), np.zeros(3), R_BP, tip, [0, 1], 0.05)
    assert needed == pytest.approx(0.021, abs=0.0015)
    assert supervisor.cap_slide_needed(
        model, np.eye(3), np.zeros(3), R_BP, tip + [0, 0.03, 0], [0, 1], 0.05
    ) == pytest.approx(0.0)  # already out of view
    assert supervisor.cap_slide_needed(
        _box_model(0.08), np.eye(3), np.zeros(3), R_BP, tip, [0, 1], 0.05
    ) == pytest.approx(0.05)  # still in view at the bound
    assert supervisor.cap_slide_limit(0.007, 0.01, 0.03) == pytest.approx(0.017)
    assert supervisor.cap_slide_limit(0.025, 0.01, 0.03) == pytest.approx(0.03)
    assert supervisor.cap_slide_limit(math.nan, 0.01, 0.03) == pytest.approx(0.03)


def _pivot_to_cap(c, dt, visible):
    """A two-leg pivot run until the first slide at the tilt cap starts; ``visible(s)``
    says whether the kidney is in the image."""
    s, t, R = _to_pivot(c, dt)
    p = (0.55, 0.0, 0.1)
    while s.phase == supervisor.Phase.PIVOT and not s.cap_slide:
        t += dt
        s = supervisor.supervisor_step(s, inputs(t, p=p, R=R, visible=visible(s)), c, dt)
    return s, t, R


def test_at_the_tilt_cap_with_the_kidney_in_view_the_tip_slides_until_it_leaves():
    c = cfg(
        exploration_ratio=0.02,
        localize_hold_time=0.0,
        pivot_rate=0.3,
        max_pivot_tilt=0.3,
        visibility_debounce=0.05,
        cap_slide_max=0.03,
    )
    dt = 0.01

    # The kidney is in view on the + side up to the cap and 8 mm of slide beyond; on the
    # - side until -0.2 rad.
    def visible(s):
        return s.pivot_angle > -0.2 and (s.cap_slide != 1 or s.cap_slide_travel < 0.008)

    s, t, R = _pivot_to_cap(c, dt, visible)
    assert s.cap_slide == 1 and s.pivot_angle == pytest.approx(0.3)
    assert "sliding up to 30 mm" in s.events[-1][2]  # no template: cap_slide_max
    start = s.P_des.copy()
    direction = supervisor.cap_slide_direction(s.o_des, s.a_star, 0.3)
    p = (0.55, 0.0, 0.1)
    travel, required = [], []
    while s.phase == supervisor.Phase.PIVOT and s.pivot_legs_done == 0:
        t += dt
        s = supervisor.supervisor_step(s, inputs(t, p=p, R=R, visible=visible(s)), c, dt)
        travel.append(float((s.P_des - start) @ direction))
        assert s.pivot_angle == pytest.approx(0.3)  # the tilt is held
    # Ended by the kidney leaving (debounced), at scan_speed, along the lean.
    assert s.sweep_end_causes == ("kidney_left",)
    assert 0.008 <= s.cap_slides[0][1] <= 0.008 + c.scan_speed * (0.05 + 3 * dt)
    assert np.all(np.diff(travel) <= c.scan_speed * dt + 1e-12)
    assert "mm of slide: kidney left the image" in s.events[-1][2]
    # Back to p* (tilt still held), then the second leg.
    while s.cap_slide:
        t += dt
        s = supervisor.supervisor_step(s, inputs(t, p=p, R=R, visible=visible(s)), c, dt)
        required.append(supervisor.segmentation_required(s))
        assert s.pivot_angle == pytest.approx(0.3)
    np.testing.assert_allclose(s.P_des, s.p_star[:2])
    while s.phase == supervisor.Phase.PIVOT:
        t += dt
        s = supervisor.supervisor_step(s, inputs(t, p=p, R=R, visible=visible(s)), c, dt)
    assert s.phase == supervisor.Phase.DONE
    assert s.sweep_end_causes == ("kidney_left", "kidney_left")
    assert s.pivot_limits[1] < -0.2


def test_the_slide_at_the_tilt_cap_is_bounded_and_can_be_switched_off():
    base = dict(
        exploration_ratio=0.02,
        localize_hold_time=0.0,
        pivot_rate=0.5,
        max_pivot_tilt=0.3,
        visibility_debounce=0.05,
    )
    dt = 0.01
    for slide in (0.01, 0.0):
        c = cfg(cap_slide_max=slide, **base)
        s, t, R = _to_pivot(c, dt)
        slid = 0.0
        start = s.P_des.copy()
        while s.phase == supervisor.Phase.PIVOT:  # the kidney always in view
            t += dt
            s = supervisor.supervisor_step(s, inputs(t, p=(0.55, 0.0, 0.1), R=R), c, dt)
            slid = max(slid, float(np.linalg.norm(s.P_des - start)))
        assert s.phase == supervisor.Phase.DONE
        assert s.sweep_end_causes == ("tilt_cap", "tilt_cap")
        assert slid == pytest.approx(slide, abs=1e-9)
        assert [d for _, d in s.cap_slides] == pytest.approx([slide, slide] if slide else [])


def test_the_slide_goes_on_to_the_templates_predicted_end_when_the_segmentation_loses_it():
    """The template (a box 80 mm wide, its centre 100 mm below the tip) is in view at the
    0.3 rad cap until the tip has slid 40 - 80 tan(0.3) = 15.3 mm (less the 1 mm slab);
    the segmentation loses the kidney after 5 mm: the slide goes on to the predicted 15
    mm, then the leg ends (kidney left)."""
    c = cfg(
        exploration_ratio=0.02,
        localize_hold_time=0.0,
        pivot_rate=0.3,
        max_pivot_tilt=0.3,
        visibility_debounce=0.05,
    )
    dt = 0.01
    model = _box_model(0.04, depth=0.15)
    s, t, R = _to_pivot(c, dt)
    R_BK = RotationMatrix(RollPitchYaw(0.0, 0.0, math.pi / 2)).matrix()
    p_BK = np.array([0.55, 0.0, 0.0])

    def step(s, t):
        u = inputs(
            t,
            p=(0.55, 0.0, 0.1),
            R=R,
            visible=s.cap_slide != 1 or s.cap_slide_travel < 0.005,
            R_BK=R_BK,
            p_BK=p_BK,
        )
        return supervisor.supervisor_step(s, dataclasses.replace(u, pivot_model=model), c, dt)

    while s.phase == supervisor.Phase.PIVOT and not s.cap_slide:
        t += dt
        s = step(s, t)
    assert s.cap_slide == 1 and "the template predicts 15 mm" in s.events[-1][2]
    assert s.cap_slide_limit == pytest.approx(s.cap_slide_predicted + c.cap_slide_margin)
    while s.cap_slide == 1:
        t += dt
        s = step(s, t)
        assert not supervisor.segmentation_required(s)  # looking for the edge: no loss
    assert s.sweep_end_causes == ("kidney_left",)
    assert s.cap_slides[0][1] == pytest.approx(s.cap_slide_predicted, abs=c.scan_speed * dt)
    assert 0.014 <= s.cap_slide_predicted <= 0.016


def test_a_stalled_turn_takes_the_other_transverse_direction():
    """A re-exploration whose array turn stalls short of transverse (the wrist at its limit)
    turns the array to the other transverse direction (the same image plane) once."""
    assert supervisor.turn_progress(math.inf, math.nan, 0.5, 1.0) == (0.5, 1.0)
    assert supervisor.turn_progress(0.5, 1.0, 0.499, 2.0) == (0.5, 1.0)  # creeping
    assert supervisor.turn_progress(0.5, 1.0, 0.4, 2.0) == (0.4, 2.0)
    stall = math.radians(11.8)
    assert supervisor.turn_stalled(0.3, 1.0, 1.0 + supervisor.REORIENT_SETTLE, stall)
    assert not supervisor.turn_stalled(0.3, 1.0, 1.0 + supervisor.REORIENT_SETTLE, 0.1)
    assert not supervisor.turn_stalled(0.3, 1.0, 2.0, stall)
    c = cfg(exploration_ratio=0.02, localize_hold_time=0.0, max_relocalizations=1)
    dt = 0.01
    s, t, R = _to_pivot(c, dt)
    t += dt
    s = supervisor.supervisor_step(
        s, dataclasses.replace(inputs(t, R=R), tracking_error="drift 9 mm"), c, dt
    )
    o_first = s.o_des.copy()
    # The probe stops with its array 11.8 deg short of o_first, about the vertical.
    R_target = np.column_stack([s.o_des, np.cross(s.a_des, s.o_des), s.a_des])
    R_short = RotationMatrix(RollPitchYaw(0.0, 0.0, stall)).matrix() @ R_target
    t0 = t
    while t - t0 < supervisor.REORIENT_SETTLE + 0.5:
        t += dt
        s = supervisor.supervisor_step(s, inputs(t, R=R_short), c, dt)
    assert s.reorienting and s.reorient_flipped
    np.testing.assert_allclose(s.o_des, -o_first)
    assert "other transverse direction" in s.events[-1][2]
    R_other = np.column_stack([s.o_des, np.cross(s.a_des, s.o_des), s.a_des])
    t += dt
    s = supervisor.supervisor_step(s, inputs(t, R=R_other), c, dt)
    assert not s.reorienting and s.retreating


# ------------------------------------------------------------------ the second look
CONTRADICTS = "the pivot's view contradicts the registration: 11.7 mm more (limit 6.87 mm)"


def test_second_look_rules():
    """The pivot's end awaits the check only with the field on, once, while a
    re-localization is allowed and a check is connected; the check's answer counts only
    once it covers the whole pivot, and a silent check ends in DONE after the timeout."""
    c = cfg()
    assert c.second_look
    wanted = supervisor.review_wanted
    assert wanted(c, False, 0, (math.nan, ""))
    assert not wanted(c, True, 0, (math.nan, ""))  # once per scan
    assert not wanted(c, False, c.max_relocalizations, (math.nan, ""))
    assert not wanted(c, False, 0, None)  # no check connected
    assert not wanted(cfg(second_look=False), False, 0, (math.nan, ""))
    assert not wanted(cfg(pivot_pose=[0.5, 0.0, 0.1, 0.0, 0.0, 0.0]), False, 0, (0.0, ""))
    outcome = supervisor.review_outcome
    assert outcome((9.9, CONTRADICTS), 10.0, 10.1) == "wait"  # asked before the end
    assert outcome((math.nan, ""), 10.0, 10.1) == "wait"
    assert outcome((10.0, CONTRADICTS), 10.0, 10.1) == "second_look"
    assert outcome((10.5, ""), 10.0, 10.6) == "done"
    assert outcome((9.0, CONTRADICTS), 10.0, 10.0 + supervisor.REVIEW_TIMEOUT) == "done"
    # Bounded by the longest kidney allowed past where the kidney came into view.
    assert supervisor.whole_kidney_target(c, 0.02) == pytest.approx(0.02 + 1.5 * 0.10)


def _pivot_to_end(s, t, c, R, dt, view):
    """Pivots (the kidney in view between -0.2 and +0.3 rad) until both legs ended, with
    the pivot-view check answering ``view(t)``; returns (state, time)."""
    while s.phase == supervisor.Phase.PIVOT and not s.reviewing and t < 60:
        t += dt
        vis = -0.2 < s.pivot_angle < 0.3
        u = dataclasses.replace(inputs(t, R=R, visible=vis), pivot_view=view(t))
        s = supervisor.supervisor_step(s, u, c, dt)
    return s, t


def test_a_pivot_view_contradicting_the_fit_takes_a_second_look_over_the_whole_kidney():
    """At the pivot's end the scan holds until the pivot-view check has covered the whole
    pivot: an agreeing view ends in DONE; a contradicting one backs out and explores until
    the kidney leaves the image (past ER x L), once; the next pivot then ends in DONE
    whatever its view (the verdict judges it)."""
    c = cfg(
        exploration_ratio=0.02,
        localize_hold_time=0.0,
        pivot_rate=0.2,
        max_pivot_tilt=0.6,
        visibility_debounce=0.05,
    )
    dt = 0.01
    for contradicts in (False, True):
        s, t, R = _to_pivot(c, dt)
        answer = CONTRADICTS if contradicts else ""
        s, t = _pivot_to_end(s, t, c, R, dt, lambda t: (t - 1.0, answer))
        assert s.phase == supervisor.Phase.PIVOT and s.reviewing and s.pivot_legs_done == 2
        assert "checking its view" in s.events[-1][2]
        assert not supervisor.segmentation_required(s)  # the sweep saw the kidney leave
        end = s.review_since
        while s.phase == supervisor.Phase.PIVOT:  # the answers lag the end by 0.05 s
            t += dt
            u = dataclasses.replace(inputs(t, R=R, visible=False), pivot_view=(t - 0.05, answer))
            s = supervisor.supervisor_step(s, u, c, dt)
        assert t >= end + 0.05 - 1e-9
        if not contradicts:
            assert s.phase == supervisor.Phase.DONE and not s.second_look_used
            assert "its view agrees with the fit" in s.events[-1][2]
            continue
        assert s.phase == supervisor.Phase.EXPLORE and s.whole_kidney and s.second_look_used
        assert s.second_look_reason == CONTRADICTS and s.relocalizations == 1
        assert "second look" in s.events[-1][2] and "whole kidney" in s.events[-1][2]
        R_transverse = np.column_stack([s.o_des, np.cross(s.a_des, s.o_des), s.a_des])
        while s.reorienting or s.retreating:
            t += dt
            s = supervisor.supervisor_step(s, inputs(t, R=R_transverse, visible=False), c, dt)
        while s.phase == supervisor.Phase.EXPLORE and s.travel < 0.05:
            t += dt
            s = supervisor.supervisor_step(s, inputs(t, R=R_transverse), c, dt)
        assert s.phase == supervisor.Phase.EXPLORE  # ER x L is 2 mm: the whole kidney goes on
        while s.phase == supervisor.Phase.EXPLORE:
            s, t = _unseen(s, t, 1, c, dt)
        assert s.phase == supervisor.Phase.LOCALIZE
        assert "(second look: the whole kidney)" in s.events[-1][2]
        s, t, R = _finish_to_pivot(s, t, c, dt)
        s, t = _pivot_to_end(s, t, c, R, dt, lambda t: (t, CONTRADICTS))
        assert s.phase == supervisor.Phase.DONE and not s.reviewing  # used once


def test_the_pivot_end_is_done_at_once_without_the_second_look():
    c = cfg(pivot_rate=0.2, max_pivot_tilt=0.6, visibility_debounce=0.05, second_look=False)
    dt = 0.01
    s, t, R = _to_pivot(c, dt)
    s, t = _pivot_to_end(s, t, c, R, dt, lambda t: (t, CONTRADICTS))
    assert s.phase == supervisor.Phase.DONE and s.events[-1][2] == "pivot sweep complete"


def test_a_probe_that_stops_following_the_sweep_aborts_the_scan():
    """EXPLORE: a tip that follows its set-point never aborts; a tip held still (a joint at
    its limit holds the whole arm) ABORTs once it has lagged the set-point by more than
    explore_follow_bound for explore_follow_time, and not while motion is held."""
    c = cfg(explore_follow_limit=0.015, explore_follow_time=2.0, exploration_ratio=2.0)
    assert supervisor.explore_follow_bound(c) == pytest.approx(0.015)
    fast = dataclasses.replace(c, scan_speed=0.02)
    assert supervisor.explore_follow_bound(fast) == pytest.approx(
        supervisor.EXPLORE_LAG_TIME * 0.02
    )
    dt = 0.01
    s = supervisor.supervisor_step(supervisor.SupervisorState(), inputs(0.0), c, dt)
    t = 0.0
    # Following, 3 mm behind the set-point (a normal sweep's lag): 20 s, no abort.
    while t < 20.0:
        t += dt
        behind = s.P_des - np.array([0.0, 0.003 * np.sign(c.scan_speed)])
        s = supervisor.supervisor_step(s, inputs(t, p=(*behind, 0.1)), c, dt)
        assert s.phase == supervisor.Phase.EXPLORE, s.reason
    # Stuck where it is: the set-point runs away at scan_speed.
    stuck = (*s.P_des, 0.1)
    held = dataclasses.replace(inputs(t, p=stuck), motion_allowed=False)
    for _ in range(1000):  # motion held (a breath-hold's gap): the set-point waits
        t += dt
        s = supervisor.supervisor_step(s, dataclasses.replace(held, t=t), c, dt)
    assert s.phase == supervisor.Phase.EXPLORE
    lagging_from = None
    while s.phase == supervisor.Phase.EXPLORE and t < 60.0:
        t += dt
        lag = float(np.linalg.norm(np.asarray(stuck[:2]) - s.P_des))
        if lagging_from is None and lag > 0.015:
            lagging_from = t
        s = supervisor.supervisor_step(s, inputs(t, p=stuck), c, dt)
    assert s.phase == supervisor.Phase.ABORT
    assert "does not follow the sweep" in s.reason and "limit 15.0 mm" in s.reason
    assert t - lagging_from == pytest.approx(2.0, abs=2 * dt)
    np.testing.assert_allclose(s.P_des, stuck[:2])  # no set-point left far away


def test_a_reexploration_turns_the_array_back_the_way_the_first_exploration_had_it():
    """After a pivot the array lies along the kidney (here along base y, a hair towards -x):
    the smaller turn to transverse would be to -x; the re-exploration turns it back to the
    first exploration's side (+x), the turn the wrist has already made (KiTS19 case 12,
    left: the other way held joint 7 at its limit)."""
    a = np.array([0.0, 0.0, -1.0])
    along_kidney = np.array([-0.02, 1.0, 0.0]) / np.linalg.norm([-0.02, 1.0, 0.0])
    np.testing.assert_allclose(supervisor.transverse_orientation(a, along_kidney), [-1, 0, 0])
    np.testing.assert_allclose(
        supervisor.reexploration_array(a, along_kidney, np.array([1.0, 0.0, 0.0])), [1, 0, 0]
    )
    np.testing.assert_allclose(supervisor.reexploration_array(a, along_kidney), [-1, 0, 0])
    # Through the state machine: the start's transverse array is remembered and used.
    c = cfg(exploration_ratio=0.02, localize_hold_time=0.0, max_relocalizations=1)
    dt = 0.01
    s, t, _ = _to_pivot(c, dt)
    np.testing.assert_allclose(s.o_explore, [1.0, 0.0, 0.0])
    R_along = np.column_stack([along_kidney, np.cross(a, along_kidney), a])
    t += dt
    s = supervisor.supervisor_step(
        s, dataclasses.replace(inputs(t, R=R_along), tracking_error="drift 9 mm"), c, dt
    )
    assert s.reorienting
    np.testing.assert_allclose(s.o_des, [1.0, 0.0, 0.0])


def test_lagging_since_keeps_the_start_of_an_unbroken_lag():
    """The follow checks' timer: NaN while following, the first lagging period's time
    while the lag goes on, NaN again after one period of following."""
    since = supervisor.lagging_since(math.nan, 1.0, False)
    assert math.isnan(since)
    since = supervisor.lagging_since(since, 1.1, True)
    assert since == 1.1
    assert supervisor.lagging_since(since, 1.5, True) == 1.1
    assert math.isnan(supervisor.lagging_since(since, 1.6, False))
