"""Fault and patient-motion models and their systems (fast, no full scan)."""

import dataclasses
import math

import numpy as np
import pytest
from pydrake.math import RigidTransform

from drake_rus.anatomy.labels import Label, LabelVolume, is_kidney
from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.frames import UsFrame
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.reliability import faults as F
from drake_rus.reliability.config import (
    BreathingConfig, FaultConfig, PatientShiftConfig, SensorFaultConfig)
from drake_rus.reliability.systems import (
    LabelImageFaults, MovingPose, MovingSliceSensor, RobotSensorFaults)


def test_breathing_amplitude_rate_and_holds():
    cfg = BreathingConfig(enabled=True, amplitude=0.012, rate_per_min=15.0, hold_period=12.0,
                          hold_duration=8.0, hold_reproducibility=0.003)
    t = np.arange(0.0, 60.0, 0.001)
    d = np.array([F.breathing_displacement(x, cfg, seed=3) for x in t])
    hold = np.array([F.breath_hold(x, cfg) for x in t])
    # Continuous: no 1 ms step beyond twice the peak breathing speed A pi f (one breath per
    # 4 s of free breathing), bounded by amplitude + hold offset.
    peak_speed = 0.012 * math.pi * 0.25
    assert np.max(np.abs(np.diff(d))) < 2 * peak_speed * 0.001
    assert d.min() >= 0.0 and d.max() <= 0.012 + 0.003 + 1e-12
    assert d.max() > 0.0119
    # Holds: 8 of every 12 s, still and within the reproducibility of end-expiration.
    assert hold.mean() == pytest.approx(8 / 12, abs=0.01)
    assert np.all(d[hold] <= 0.003)
    for a, b in F.hold_windows(60.0, cfg):
        seg = d[(t >= a) & (t < b)]
        assert np.ptp(seg) == 0.0
    # Free breathing only: 15 breaths/min peaks every 4 s.
    free = dataclasses.replace(cfg, hold_period=0.0)
    assert F.breathing_displacement(2.0, free) == pytest.approx(0.012)
    assert F.breathing_displacement(4.0, free) == pytest.approx(0.0, abs=1e-12)
    assert not F.breath_hold(1.0, free)
    assert F.breath_hold(1.0, BreathingConfig(enabled=False))


def test_patient_shift_ramps_to_offset():
    cfg = PatientShiftConfig(enabled=True, time=2.0, offset=[0.0, 0.02, -0.005], ramp=0.5)
    np.testing.assert_allclose(F.shift_offset(1.9, cfg), 0.0)
    np.testing.assert_allclose(F.shift_offset(2.25, cfg), [0.0, 0.01, -0.0025])
    np.testing.assert_allclose(F.shift_offset(10.0, cfg), [0.0, 0.02, -0.005])


def test_force_faults():
    spike = SensorFaultConfig(kind="force_spike", start=1.0, duration=2.0, magnitude=25.0,
                              spike_period=0.5, spike_width=0.02)
    assert F.force_offset(0.99, spike) == 0.0
    assert F.force_offset(1.01, spike) == 25.0
    assert F.force_offset(1.1, spike) == 0.0
    assert F.force_offset(1.51, spike) == 25.0
    assert F.force_offset(3.01, spike) == 0.0
    bias = SensorFaultConfig(kind="force_bias", start=0.0, magnitude=-4.0)
    assert F.force_offset(100.0, bias) == -4.0


def test_frame_probability_is_deterministic_and_about_right():
    f = SensorFaultConfig(kind="image_dropout", probability=0.3)
    hits = [F.frame_affected(k, f, seed=5) for k in range(2000)]
    assert hits == [F.frame_affected(k, f, seed=5) for k in range(2000)]
    assert np.mean(hits) == pytest.approx(0.3, abs=0.04)


@pytest.fixture(scope="module")
def geometry():
    return ProbeGeometry.from_config(ImagingConfig())


def _label_frame(geometry, index, t):
    labels = np.where(geometry.fan_mask, Label.SOFT_TISSUE, 0).astype(np.uint8)
    h, w = labels.shape
    labels[h // 3:h // 2, w // 3:2 * w // 3] = Label.KIDNEY_CORTEX
    return UsFrame(labels, t, RigidTransform([0.5, 0.0, 0.1]), index)


def _faults(*sensor):
    return FaultConfig(sensor=list(sensor))


def _run_label_faults(geometry, config, frames):
    """Feeds frames through LabelImageFaults at 20 Hz like the sensor would; returns outputs."""
    system = LabelImageFaults(ImagingConfig(), config, seed=1)
    ctx = system.CreateDefaultContext()
    port = system.GetInputPort("label_image")
    outputs = []
    for frame in frames:
        ctx.SetTime(frame.time)
        port.FixValue(ctx, frame)
        outputs.append(system.GetOutputPort("label_image").Eval(ctx))
        # The mid-period update that remembers the delivered frame.
        state = ctx.get_mutable_abstract_state(0)
        state.set_value(outputs[-1])
    return outputs


def test_label_faults_dropout_frozen_miss_false_positive(geometry):
    frames = [_label_frame(geometry, k, 0.05 * k) for k in range(6)]
    # Dropout from t = 0.1 s: the stream stalls on the last good frame (index and time).
    out = _run_label_faults(geometry, _faults(SensorFaultConfig(kind="image_dropout",
                                                                start=0.1)), frames)
    assert [o.frame_index for o in out] == [0, 1, 1, 1, 1, 1]
    assert out[-1].time == pytest.approx(0.05)
    # Frozen: new stamps, old content.
    moved = [UsFrame(np.roll(f.image, 3 * k, axis=1), f.time, f.X_BP, f.frame_index)
             for k, f in enumerate(frames)]
    out = _run_label_faults(geometry, _faults(SensorFaultConfig(kind="frozen_image",
                                                                start=0.1)), moved)
    assert [o.frame_index for o in out] == list(range(6))
    assert all(np.array_equal(o.image, moved[1].image) for o in out[2:])
    # Segmentation miss: no kidney while active, untouched outside the window.
    out = _run_label_faults(geometry, _faults(SensorFaultConfig(kind="segmentation_miss",
                                                                start=0.1, duration=0.1)), frames)
    assert [bool(is_kidney(o.image).any()) for o in out] == [True, True, False, False, True, True]
    # False positive: extra kidney pixels, inside the fan only.
    out = _run_label_faults(geometry, _faults(SensorFaultConfig(
        kind="segmentation_false_positive", start=0.0)), frames)
    for o, f in zip(out, frames):
        assert is_kidney(o.image).sum() > is_kidney(f.image).sum()
        assert not np.any(is_kidney(o.image) & ~geometry.fan_mask)
    # NaN-stamped frames.
    out = _run_label_faults(geometry, _faults(SensorFaultConfig(kind="nan_image",
                                                                start=0.1)), frames)
    assert np.all(np.isfinite(out[1].X_BP.translation()))
    assert np.all(np.isnan(out[2].X_BP.translation()))


def test_robot_sensor_faults_force_nan_and_delay():
    faults = _faults(SensorFaultConfig(kind="force_bias", start=1.0, magnitude=5.0),
                     SensorFaultConfig(kind="nan_pose", start=2.0, duration=0.5),
                     SensorFaultConfig(kind="joint_state_delay", start=0.0, delay=0.01))
    system = RobotSensorFaults(faults, n=7, sample_period=1e-3)
    ctx = system.CreateDefaultContext()
    system.GetInputPort("probe_force").FixValue(ctx, np.array([0, 0, 0, 0, 0, -8.0]))
    system.GetInputPort("X_BP").FixValue(ctx, RigidTransform([0.5, 0.0, 0.1]))
    system.GetInputPort("joint_velocity").FixValue(ctx, np.zeros(7))
    from pydrake.systems.analysis import Simulator
    sim = Simulator(system, ctx)
    q_port = system.GetInputPort("joint_position")
    for k in range(40):           # q ramps 1 rad/s; sampled every ms
        q_port.FixValue(ctx, np.full(7, 0.001 * k))
        sim.AdvanceTo(0.001 * k + 1e-9)
    q_out = system.GetOutputPort("joint_position").Eval(ctx)[0]
    assert q_out == pytest.approx(0.039 - 0.01, abs=1.5e-3)     # 10 ms old
    assert system.GetOutputPort("probe_force").Eval(ctx)[5] == -8.0
    ctx.SetTime(1.5)
    assert system.GetOutputPort("probe_force").Eval(ctx)[5] == -13.0   # F_z 8 -> 13 N
    ctx.SetTime(2.1)
    assert np.all(np.isnan(system.GetOutputPort("X_BP").Eval(ctx).translation()))
    ctx.SetTime(2.6)
    assert np.all(np.isfinite(system.GetOutputPort("X_BP").Eval(ctx).translation()))


def test_moving_slice_sensor_sees_the_kidney_move(geometry):
    """A kidney block moved 10 mm caudally by breathing appears 10 mm further along the
    probe's x axis (the probe's array along the body's head-foot axis)."""
    labels = np.full((80, 80, 240), Label.SOFT_TISSUE, np.uint8)
    labels[30:50, 35:45, 40:160] = Label.KIDNEY_CORTEX    # x in [30, 50) mm
    volume = LabelVolume(labels, 0.001)
    # Probe at the grid's centre top, beam down (-z_B), array along +x_B; up = -x_B, so
    # d > 0 (caudal) moves the kidney along +x_B.
    from pydrake.math import RotationMatrix
    X_BP = RigidTransform(RotationMatrix(np.diag([1.0, -1.0, -1.0])), [0.040, 0.040, 0.230])
    faults = FaultConfig(breathing=BreathingConfig(enabled=True, amplitude=0.01,
                                                   rate_per_min=15.0, hold_period=0.0))
    sensor = MovingSliceSensor(ImagingConfig(), volume, RigidTransform(), faults,
                               superior_B=[-1.0, 0.0, 0.0])
    from pydrake.systems.analysis import Simulator
    simulator = Simulator(sensor)
    ctx = simulator.get_mutable_context()
    sensor.GetInputPort("X_BP").FixValue(ctx, X_BP)
    simulator.Initialize()

    def kidney_columns(t):
        simulator.AdvanceTo(t + 1e-6)
        frame = sensor.GetOutputPort("label_image").Eval(ctx)
        assert frame.time == pytest.approx(t)
        return np.nonzero(is_kidney(frame.image).any(axis=0))[0].mean()

    c0, c1 = kidney_columns(0.0), kidney_columns(2.0)     # d = 0, then d = 10 mm
    assert (c1 - c0) * geometry.dx == pytest.approx(0.010, abs=0.0015)
    X0 = RigidTransform([0.1, 0.2, 0.3])
    pose = MovingPose(X0, faults, [-1.0, 0.0, 0.0])
    pctx = pose.CreateDefaultContext()
    pctx.SetTime(2.0)
    np.testing.assert_allclose(pose.get_output_port().Eval(pctx).translation(),
                               [0.11, 0.2, 0.3], atol=1e-12)


def test_nan_stamped_frame_is_not_accumulated(geometry):
    """A frame whose probe pose is NaN (fault nan_image) adds nothing to P_local."""
    from drake_rus.imaging.backprojection import BoundaryPixels, PointCloud, accumulate
    px = np.array([[100.0, 120.0], [110.0, 130.0]])
    good = accumulate(PointCloud(), BoundaryPixels(px, 0.0, RigidTransform([0.5, 0, 0.1]), 0),
                      geometry)
    assert good.frame_count == 1 and len(good.points) == 2
    bad = accumulate(good, BoundaryPixels(px, 0.05, RigidTransform(np.full(3, np.nan)), 1),
                     geometry)
    assert bad.frame_count == 1 and np.all(np.isfinite(bad.points))


def test_patient_contact_body_moves_with_breathing_and_shift():
    """With breathing or a shift the contact body is on driven joints and follows the
    same displacement as the imaged anatomy (sub-millimetre, with the robot pressing on
    it); without patient motion it stays welded (no extra degrees of freedom)."""
    from pydrake.systems.analysis import Simulator

    from drake_rus.anatomy import load_patient
    from drake_rus.reliability.station import fault_seed, superior_axis_B
    from drake_rus.scenario import LoadScenario
    from drake_rus.station import MakeStation

    patient = load_patient("test:0", progress=False)
    still = MakeStation(LoadScenario(scenario_name="quick"), patient=patient)
    assert not still.GetSubsystemByName("plant").HasModelInstanceNamed("patient")
    scenario = LoadScenario(scenario_name="quick", scenario_text=(
        "{faults: {breathing: {enabled: true, amplitude: 0.02, rate_per_min: 20, "
        "hold_period: 0}, patient_shift: {enabled: true, time: 0.6, offset: [0.01, 0.0, "
        "0.005], ramp: 0.3}}}"))
    station = MakeStation(scenario, patient=patient)
    plant = station.GetSubsystemByName("plant")
    assert plant.HasModelInstanceNamed("patient")
    simulator = Simulator(station)
    context = simulator.get_mutable_context()
    station.GetInputPort("joint_velocity_command").FixValue(context, np.zeros(7))
    up = superior_axis_B(scenario)
    moved = []
    for t in (0.5, 1.2):
        simulator.AdvanceTo(t)
        x = station.GetOutputPort("plant_state").Eval(context)
        q_patient = x[7:len(x) // 2]
        want = F.patient_offset_B(t, scenario.faults.breathing, scenario.faults.patient_shift,
                                  up, fault_seed(scenario))
        assert np.linalg.norm(want) > 0.004
        np.testing.assert_allclose(q_patient, want, atol=0.001)
        moved.append(q_patient)
    assert moved[1][0] == pytest.approx(0.01, abs=0.001)        # the shift along x
