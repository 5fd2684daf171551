"""Unit tests of the safety layer's pure logic: each fault stops within the same period."""

import dataclasses
import math

import numpy as np
import pytest

from drake_rus.control.config import SafetyConfig
from drake_rus.control.safety import (
    SafetyInputs,
    SafetyState,
    StopReason,
    limit_command,
    safety_step,
)

Q0 = np.array([0.0, 0.15, 0.0, -2.0, 0.0, 2.15, 0.785])


def nominal(kin, t=1.0, **kw):
    X = kin.pose(Q0)
    u = SafetyInputs(
        t=t,
        q=Q0 + 1e-3 * t,
        v=np.full(7, 0.01),
        qdot_desired=np.full(7, 0.02),
        R_BP=X.rotation().matrix(),
        p_BP=X.translation(),
        F_z=9.0,
        J=kin.jacobian(Q0),
        image_time=t - 0.02,
        kidney_visible=True,
    )
    return dataclasses.replace(u, **kw)


def test_nominal_passes_command(kin):
    cmd, s = safety_step(SafetyState(), nominal(kin), SafetyConfig())
    assert not s.stopped
    np.testing.assert_allclose(cmd, 0.02)


@pytest.mark.parametrize(
    "fault, reason",
    [
        (dict(F_z=25.0), StopReason.FORCE),
        (dict(F_z=math.nan), StopReason.NAN),
        (dict(p_BP=np.array([0.5, 0.0, math.nan])), StopReason.NAN),
        (dict(qdot_desired=np.array([0, 0, math.inf, 0, 0, 0, 0])), StopReason.NAN),
        (dict(p_BP=np.array([0.55, 0.6, 0.2])), StopReason.WORKSPACE),
        (dict(p_BP=np.array([0.55, 0.0, -0.2])), StopReason.WORKSPACE),
        (dict(v=np.array([0, 0, 0, 0, 0, 0, 3.5])), StopReason.JOINT_SPEED),
        (dict(image_time=0.5), StopReason.STALE_IMAGE),
        (dict(supervisor_abort=True, supervisor_reason="x"), StopReason.SUPERVISOR_ABORT),
        (dict(robot_ok=False), StopReason.ROBOT_FAULT),
    ],
)
def test_each_fault_stops_in_the_same_period(kin, fault, reason):
    cfg = SafetyConfig(retract_distance=0.0)
    u = nominal(kin, **fault)
    cmd, s = safety_step(SafetyState(), u, cfg)
    assert s.stopped and s.reason == reason
    np.testing.assert_array_equal(cmd, 0.0)
    assert len(s.events) == 1 and s.events[0].reason == reason and s.events[0].time == 1.0
    # Latched: the next healthy period is still stopped.
    cmd, s = safety_step(s, nominal(kin, t=1.005), cfg)
    np.testing.assert_array_equal(cmd, 0.0)
    assert len(s.events) == 1


def test_tip_speed_fault(kin):
    J = kin.jacobian(Q0)
    v = np.linalg.pinv(J) @ np.array([0, 0, 0, 0.2, 0, 0])  # 0.2 m/s > 0.15 m/s
    cmd, s = safety_step(SafetyState(), nominal(kin, v=v), SafetyConfig())
    assert s.reason == StopReason.TIP_SPEED
    np.testing.assert_array_equal(cmd, 0.0)


def test_force_stop_retracts_along_minus_a_then_zero(kin):
    cfg = SafetyConfig(retract_distance=0.01, retract_speed=0.02)
    u = nominal(kin, F_z=30.0)
    cmd, s = safety_step(SafetyState(), u, cfg)
    assert s.reason == StopReason.FORCE
    V = kin.jacobian(Q0) @ cmd
    a = u.R_BP[:, 2]
    np.testing.assert_allclose(V[3:], -0.02 * a, atol=1e-6)  # out of the body at 20 mm/s
    np.testing.assert_allclose(V[:3], 0.0, atol=1e-6)
    cmd, s = safety_step(s, nominal(kin, t=1.4), cfg)
    assert np.linalg.norm(cmd) > 0  # still retracting (0.5 s for 10 mm)
    cmd, s = safety_step(s, nominal(kin, t=1.5 + 1e-6), cfg)
    np.testing.assert_array_equal(cmd, 0.0)


def test_stale_state_watchdog(kin):
    cfg = SafetyConfig(state_timeout=0.05)
    s = SafetyState()
    q = Q0.copy()
    for k in range(10):  # joints frozen at t = 1.000 .. 1.045: fine
        cmd, s = safety_step(s, nominal(kin, t=1.0 + 0.005 * k, q=q), cfg)
        assert not s.stopped
    cmd, s = safety_step(s, nominal(kin, t=1.05, q=q), cfg)
    assert s.reason == StopReason.STALE_STATE
    np.testing.assert_array_equal(cmd, 0.0)
    # Frozen joints with a zero command are not a fault (holding still).
    s = SafetyState()
    for k in range(30):
        _, s = safety_step(s, nominal(kin, t=1.0 + 0.005 * k, q=q, qdot_desired=np.zeros(7)), cfg)
    assert not s.stopped


def test_segmentation_lost_timeout_only_when_required(kin):
    cfg = SafetyConfig(segmentation_timeout=0.2)
    s = SafetyState()
    for k in range(100):
        _, s = safety_step(
            s,
            nominal(kin, t=1.0 + 0.01 * k, kidney_visible=False, segmentation_required=False),
            cfg,
        )
    assert not s.stopped
    s = SafetyState()
    t = 1.0
    while not s.stopped:
        cmd, s = safety_step(s, nominal(kin, t=t, kidney_visible=False), cfg)
        t += 0.01
    assert s.reason == StopReason.SEGMENTATION_LOST
    assert s.stop_time == pytest.approx(1.20, abs=1e-9)
    np.testing.assert_array_equal(cmd, 0.0)
    # A brief loss that recovers resets the timer.
    s = SafetyState()
    for k in range(100):
        _, s = safety_step(s, nominal(kin, t=1.0 + 0.01 * k, kidney_visible=(k % 15 != 0)), cfg)
    assert not s.stopped


def test_limit_command_scales_into_limits(kin):
    J = kin.jacobian(Q0)
    lim = np.array([2, 1, 1.5, 1.25, 3, 1.5, 3])
    q = limit_command(np.full(7, 4.0), J, lim, 10.0)
    assert np.all(np.abs(q) <= lim + 1e-12)
    np.testing.assert_allclose(q / q[0], 1.0)  # direction kept
    qd = np.linalg.pinv(J) @ np.array([0, 0, 0, 0.0, 0.3, 0])
    q = limit_command(qd, J, lim, 0.08)
    assert np.linalg.norm(J[3:] @ q) == pytest.approx(0.08)


@pytest.mark.parametrize(
    "field, name",
    [
        ("q", "q"),
        ("v", "v"),
        ("qdot_desired", "commanded qdot"),
        ("R_BP", "R_BP"),
        ("p_BP", "p_BP"),
        ("J", "J"),
    ],
)
def test_nan_stop_names_the_non_finite_input(kin, field, name):
    u = nominal(kin)
    bad = np.array(getattr(u, field), dtype=float)
    bad.flat[bad.size // 2] = math.nan
    _, s = safety_step(SafetyState(), dataclasses.replace(u, **{field: bad}), SafetyConfig())
    assert s.reason == StopReason.NAN and s.events[0].detail == f"{name} is not finite"


def test_safety_step_leaves_the_state_it_was_given_unchanged(kin):
    before = SafetyState()
    _, after = safety_step(before, nominal(kin, F_z=25.0), SafetyConfig())
    assert after.stopped and after is not before
    assert not before.stopped and before.events == () and before.last_q is None


@pytest.mark.parametrize("stamp", [math.nan, math.inf, -math.inf])
def test_an_image_stamp_that_turns_non_finite_stops(kin, stamp):
    """NaN means "no images" only until a finite stamp has been seen; after that a
    non-finite stamp must not switch the stale-image watchdog off."""
    cfg = SafetyConfig(retract_distance=0.0)
    s = SafetyState()
    for k in range(5):  # no images yet: not a fault
        _, s = safety_step(s, nominal(kin, t=0.5 + 0.01 * k, image_time=math.nan), cfg)
    assert not s.stopped
    for k in range(5):
        _, s = safety_step(s, nominal(kin, t=1.0 + 0.01 * k), cfg)
    assert not s.stopped
    cmd, s = safety_step(s, nominal(kin, t=1.05, image_time=stamp), cfg)
    assert s.stopped and s.reason == StopReason.NAN and s.stop_time == 1.05
    assert "image time stamp" in s.events[0].detail
    np.testing.assert_array_equal(cmd, 0.0)


@pytest.mark.parametrize(
    "fault, reason",
    [
        (dict(v=np.array([0, 0, math.nan, 0, 0, 0, 0])), StopReason.NAN),
        (dict(F_z=math.nan), StopReason.NAN),
        (dict(p_BP=np.array([0.5, 0.0, math.nan])), StopReason.NAN),
        (dict(robot_ok=False), StopReason.ROBOT_FAULT),
        (dict(p_BP=np.array([0.55, 0.6, 0.2])), StopReason.WORKSPACE),
    ],
)
def test_a_fault_during_the_retract_ends_it(kin, fault, reason):
    """The retract after a force stop moves the robot: a non-finite input, a robot fault or
    a workspace exit while it runs ends it with zero velocity, logged."""
    cfg = SafetyConfig(retract_distance=0.01, retract_speed=0.02)
    cmd, s = safety_step(SafetyState(), nominal(kin, F_z=30.0), cfg)
    assert s.reason == StopReason.FORCE and np.linalg.norm(cmd) > 0
    cmd, s = safety_step(s, nominal(kin, t=1.1), cfg)
    assert np.linalg.norm(cmd) > 0  # retracting
    cmd, s = safety_step(s, nominal(kin, t=1.2, **fault), cfg)
    np.testing.assert_array_equal(cmd, 0.0)
    assert s.reason == StopReason.FORCE  # the stop's cause stays the first fault
    assert [e.reason for e in s.events] == [StopReason.FORCE, reason]
    cmd, s = safety_step(s, nominal(kin, t=1.3), cfg)  # healthy again, retract time left
    np.testing.assert_array_equal(cmd, 0.0)


def test_rest_is_not_a_stale_state(kin):
    """Joints unchanged while no motion is commanded (a driver repeating its last status at
    rest) do not count towards the stale-state timeout once motion is commanded."""
    cfg = SafetyConfig(state_timeout=0.05)
    s = SafetyState()
    q = Q0.copy()
    for k in range(200):  # 1 s at rest, zero command
        _, s = safety_step(s, nominal(kin, t=1.0 + 0.005 * k, q=q, qdot_desired=np.zeros(7)), cfg)
    # Commanded from t = 2.000 (the last period at rest: 1.995), joints not yet moving:
    # up to 45 ms after the last period at rest, still fine.
    for k in range(9):
        cmd, s = safety_step(s, nominal(kin, t=2.0 + 0.005 * k, q=q), cfg)
        assert not s.stopped
        assert np.linalg.norm(cmd) > 0
    cmd, s = safety_step(s, nominal(kin, t=2.045, q=q), cfg)  # 50 ms: stale
    assert s.reason == StopReason.STALE_STATE
    np.testing.assert_array_equal(cmd, 0.0)
