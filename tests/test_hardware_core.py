"""Pure functions of the hardware interface: signs, stamps, command guard, watchdog, crop,
pivot calibration, config validation."""

import math
import time

import numpy as np
import pytest
from pydrake.math import RollPitchYaw, RotationMatrix

from drake_rus.hardware import core
from drake_rus.hardware.calibration import flange_poses_from_joints, pivot_calibration
from drake_rus.robot import MakeControlPlant, estimate_tip_wrench
from drake_rus.scenario import ApplyOverrides, Scenario, ScenarioError

V_MAX = np.array([0.8, 0.4, 0.6, 0.5, 1.2, 0.6, 1.2])
A_MAX = np.full(7, 2.0)


def test_external_torque_sign_flip_gives_drake_convention():
    # A probe pressed down into a body: the environment pushes the probe up (+z in B).
    scenario = Scenario()
    plant, tip = MakeControlPlant(scenario.robot, scenario.probe)
    context = plant.CreateDefaultContext()
    plant.SetPositions(context, scenario.robot.initial_joint_positions)
    from pydrake.multibody.tree import JacobianWrtVariable

    W = plant.world_frame()
    J = plant.CalcJacobianSpatialVelocity(context, JacobianWrtVariable.kV, tip, np.zeros(3), W, W)
    F_env_on_probe_W = np.array([0, 0, 0, 0, 0, 8.0])
    tau_drake = J.T @ F_env_on_probe_W  # Drake: environment on the arm
    tau_libfranka = -tau_drake  # libfranka: robot on environment
    tau = core.external_torque_to_drake(tau_libfranka)
    np.testing.assert_allclose(tau, tau_drake)
    R_WP = tip.CalcPoseInWorld(context).rotation().matrix()
    F_P = estimate_tip_wrench(J, tau, R_WP)
    np.testing.assert_allclose(R_WP @ F_P[3:], [0, 0, 8.0], atol=1e-3)  # damped solve
    # Its own inverse, and it copies.
    np.testing.assert_allclose(core.external_torque_to_drake(tau), tau_libfranka)


def test_wall_clock_utime_and_freshness():
    now = time.time()
    utime = core.wall_clock_utime(now)
    assert abs(utime - now * 1e6) <= 1
    assert core.utime_age(utime, now + 0.02) == pytest.approx(0.02, abs=2e-6)
    assert core.is_command_fresh(utime, now + 0.01, 0.05)
    assert not core.is_command_fresh(utime, now + 0.2, 0.05)
    # Simulation-time stamps (seconds since the start of a run) are never fresh.
    assert not core.is_command_fresh(int(3.5e6), now, 0.05)
    # Stamps from the future beyond the window are refused too.
    assert not core.is_command_fresh(core.wall_clock_utime(now + 1.0), now, 0.05)


def test_limit_joint_velocity_keeps_direction():
    v = np.array([1.6, 0.0, 0.3, 0, 0, 0, 0])
    out = core.limit_joint_velocity(v, V_MAX)
    assert np.all(np.abs(out) <= V_MAX + 1e-12)
    np.testing.assert_allclose(out / np.linalg.norm(out), v / np.linalg.norm(v))
    np.testing.assert_allclose(core.limit_joint_velocity(0.5 * V_MAX, V_MAX), 0.5 * V_MAX)


def test_guard_command_limits_acceleration_and_zeroes_on_faults():
    dt = 0.005
    prev = np.zeros(7)
    desired = np.array([0.3, 0, 0, 0, 0, 0, -0.3])
    out = core.guard_command(desired, prev, dt, V_MAX, A_MAX)
    np.testing.assert_allclose(out, [0.01, 0, 0, 0, 0, 0, -0.01])  # a_max dt = 0.01
    steps = 0
    while not np.allclose(out, desired):
        out = core.guard_command(desired, out, dt, V_MAX, A_MAX)
        steps += 1
        assert np.all(np.abs(out) <= V_MAX + 1e-12)
    assert steps == 29  # 0.3 / 0.01 - 1
    # Disabled (dry run, stop, fault) or non-finite: zero at once.
    assert not np.any(core.guard_command(desired, out, dt, V_MAX, A_MAX, enabled=False))
    bad = desired.copy()
    bad[2] = math.nan
    assert not np.any(core.guard_command(bad, out, dt, V_MAX, A_MAX))
    # A zero command is not rate limited.
    assert not np.any(core.guard_command(np.zeros(7), out, dt, V_MAX, A_MAX))
    # A non-finite previous command counts as rest.
    np.testing.assert_allclose(
        core.guard_command(desired, np.full(7, math.nan), dt, V_MAX, A_MAX),
        [0.01, 0, 0, 0, 0, 0, -0.01],
    )


def test_watchdog_expired():
    assert core.watchdog_expired(1.0, math.nan, 0.05)
    assert not core.watchdog_expired(1.04, 1.0, 0.05)
    assert core.watchdog_expired(1.06, 1.0, 0.05)


def test_crop_and_grey_and_fit():
    picture = np.zeros((240, 320, 3), np.uint8)
    picture[40:200, 60:260] = (10, 200, 30)  # BGR
    assert core.check_crop([0, 0, 0, 0], picture.shape) == (0, 0, 320, 240)
    cropped = core.crop_image(picture, [60, 40, 200, 160])
    assert cropped.shape == (160, 200, 3)
    grey = core.to_grey(cropped)
    assert grey.dtype == np.uint8 and grey.shape == (160, 200)
    assert int(grey[0, 0]) == round(0.114 * 10 + 0.587 * 200 + 0.299 * 30)
    fitted = core.fit_image(grey, (256, 256))
    assert fitted.shape == (256, 256) and fitted.dtype == np.uint8
    assert core.fit_image(grey, (160, 200)) is grey
    for bad, what in (
        ([300, 0, 40, 40], "reaches past"),
        ([0, 0, 0, 10], "width"),
        ([0, 0, 10], "x, y, width, height"),
    ):
        with pytest.raises(ValueError, match="hardware_interface.video_crop") as e:
            core.check_crop(bad, picture.shape)
        assert what in str(e.value)
    with pytest.raises(ValueError, match="channels"):
        core.to_grey(np.zeros((4, 4, 2), np.uint8))


def test_check_robot_ip():
    assert core.check_robot_ip("172.16.0.2") == "172.16.0.2"
    assert core.check_robot_ip("fr3-lab.local") == "fr3-lab.local"
    for bad in ("300.1.1.1", "", "robot ip", "1.2.3"):
        with pytest.raises(ValueError, match="hardware_interface.robot_ip"):
            core.check_robot_ip(bad)


def test_pivot_calibration_recovers_tip_and_pivot():
    rng = np.random.default_rng(3)
    p_FT = np.array([0.004, -0.002, 0.2])
    p_BT = np.array([0.55, 0.05, 0.12])
    rotations, translations = [], []
    for _ in range(12):
        rpy = RollPitchYaw(
            np.pi + rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(-np.pi, np.pi)
        )
        R = RotationMatrix(rpy).matrix()
        rotations.append(R)
        translations.append(p_BT - R @ p_FT + rng.normal(0, 2e-4, 3))  # 0.2 mm noise
    result = pivot_calibration(rotations, translations)
    np.testing.assert_allclose(result.p_FT, p_FT, atol=1.5e-3)
    np.testing.assert_allclose(result.p_BT, p_BT, atol=1.5e-3)
    assert result.rms < 1e-3 and result.residuals.shape == (12,)
    # Exact data: exact answer.
    exact = pivot_calibration(rotations, [p_BT - R @ p_FT for R in rotations])
    np.testing.assert_allclose(exact.p_FT, p_FT, atol=1e-9)
    assert exact.rms < 1e-9


def test_pivot_calibration_rejects_poor_data():
    R = np.eye(3)
    with pytest.raises(ValueError, match="at least 3 poses"):
        pivot_calibration([R, R], np.zeros((2, 3)))
    with pytest.raises(ValueError, match="do not rotate enough"):
        pivot_calibration([R] * 5, np.zeros((5, 3)))
    with pytest.raises(ValueError, match="proper rotation"):
        pivot_calibration([2 * R] * 3, np.zeros((3, 3)))
    with pytest.raises(ValueError, match="translations"):
        pivot_calibration([R] * 3, np.zeros((2, 3)))


def test_pivot_calibration_from_joint_configurations():
    """Joint configurations pivoting about a point (solved by IK on our model) calibrate
    back to the scenario's tip offset."""
    from pydrake.multibody.inverse_kinematics import InverseKinematics
    from pydrake.solvers import Solve

    scenario = Scenario()
    plant, tip = MakeControlPlant(scenario.robot, scenario.probe)
    context = plant.CreateDefaultContext()
    q0 = np.asarray(scenario.robot.initial_joint_positions)
    plant.SetPositions(context, q0)
    X_BT0 = tip.CalcPoseInWorld(context)
    qs = []
    for ax, ay in ((0, 0), (0.3, 0), (-0.3, 0), (0, 0.3), (0, -0.3), (0.2, 0.2)):
        ik = InverseKinematics(plant)
        R_target = X_BT0.rotation() @ RotationMatrix(RollPitchYaw(ax, ay, 0.0))
        ik.AddPositionConstraint(
            tip,
            np.zeros(3),
            plant.world_frame(),
            X_BT0.translation() - 1e-6,
            X_BT0.translation() + 1e-6,
        )
        ik.AddOrientationConstraint(plant.world_frame(), R_target, tip, RotationMatrix(), 1e-4)
        ik.prog().SetInitialGuess(ik.q(), q0)
        result = Solve(ik.prog())
        assert result.is_success()
        qs.append(result.GetSolution(ik.q()))
    R, t = flange_poses_from_joints(scenario, qs)
    cal = pivot_calibration(R, t)
    p_FT_true = scenario.probe.X_FP.GetDeterministicValue().translation()
    np.testing.assert_allclose(cal.p_FT, p_FT_true, atol=1e-4)
    np.testing.assert_allclose(cal.p_BT, X_BT0.translation(), atol=1e-4)


def test_hardware_config_validation_names_fields():
    s = Scenario()
    for text, field in (
        ("{hardware_interface: {backend: ros}}", "backend"),
        ("{hardware_interface: {max_joint_velocity: [1, 2]}}", "max_joint_velocity"),
        (
            "{hardware_interface: {max_joint_acceleration: [20,1,1,1,1,1,1]}}",
            "max_joint_acceleration",
        ),
        ("{hardware_interface: {command_timeout: 0}}", "command_timeout"),
        ("{hardware_interface: {video_crop: [0, 0, -1, 4]}}", "video_crop"),
        ("{hardware_interface: {robot_ipp: 1.2.3.4}}", "robot_ipp"),
    ):
        with pytest.raises(ScenarioError, match=f"hardware_interface.{field}"):
            ApplyOverrides(s, text)
    ok = ApplyOverrides(
        s,
        "{hardware: true, hardware_interface: {backend: lcm, "
        "video_crop: [10, 20, 300, 200], dry_run: false}}",
    )
    assert ok.hardware_interface.backend == "lcm" and not ok.hardware_interface.dry_run
    assert ok.hardware_interface.video_crop == [10, 20, 300, 200]
    assert Scenario().hardware_interface.dry_run  # safe default: never moves


def test_command_guard_system_limits_latches_and_dry_runs():
    from pydrake.systems.analysis import Simulator

    from drake_rus.hardware.config import HardwareConfig
    from drake_rus.hardware.systems import CommandGuard

    guard = CommandGuard(HardwareConfig(dry_run=False), rate_hz=200.0)
    sim = Simulator(guard)
    ctx = sim.get_context()
    desired = np.array([0.3, 0, 0, 0, 0, 0, 5.0])
    guard.GetInputPort("joint_velocity_command").FixValue(ctx, desired)
    guard.GetInputPort("robot_ok").FixValue(ctx, [1.0])
    out = guard.GetOutputPort("joint_velocity_sent")
    # First period from rest: each joint moves by at most a_max dt = 0.01 rad/s.
    np.testing.assert_allclose(out.Eval(ctx)[[0, 6]], [0.01, 0.01], atol=1e-12)
    sim.AdvanceTo(1.0)
    v = out.Eval(ctx)
    # Scaled into the joint-7 limit (1.2 rad/s), direction kept.
    np.testing.assert_allclose(v, desired * 1.2 / 5.0, atol=1e-12)
    guard.GetInputPort("robot_ok").FixValue(ctx, [0.0])
    assert not np.any(out.Eval(ctx))
    sim.AdvanceTo(1.01)
    guard.GetInputPort("robot_ok").FixValue(ctx, [1.0])
    assert not np.any(out.Eval(ctx))  # a fault latches the stop
    assert guard.GetOutputPort("stopped").Eval(ctx)[0] == 1.0
    dry = CommandGuard(HardwareConfig(dry_run=True), rate_hz=200.0)
    dctx = dry.CreateDefaultContext()
    dry.GetInputPort("joint_velocity_command").FixValue(dctx, desired)
    assert not np.any(dry.GetOutputPort("joint_velocity_sent").Eval(dctx))
