"""Sensor-fault models and their systems (fast, no full scan). Patient motion:
tests/test_patient_motion.py."""

import numpy as np
import pytest
from pydrake.math import RigidTransform

from drake_rus.anatomy.labels import Label, is_kidney
from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.frames import UsFrame
from drake_rus.reliability import faults as F
from drake_rus.reliability.config import FaultConfig, SensorFaultConfig
from drake_rus.reliability.systems import LabelImageFaults, RobotSensorFaults


def test_force_faults():
    spike = SensorFaultConfig(
        kind="force_spike",
        start=1.0,
        duration=2.0,
        magnitude=25.0,
        spike_period=0.5,
        spike_width=0.02,
    )
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


def _label_frame(geometry, index, t):
    labels = np.where(geometry.fan_mask, Label.SOFT_TISSUE, 0).astype(np.uint8)
    h, w = labels.shape
    labels[h // 3 : h // 2, w // 3 : 2 * w // 3] = Label.KIDNEY_CORTEX
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
    out = _run_label_faults(
        geometry, _faults(SensorFaultConfig(kind="image_dropout", start=0.1)), frames
    )
    assert [o.frame_index for o in out] == [0, 1, 1, 1, 1, 1]
    assert out[-1].time == pytest.approx(0.05)
    # Frozen: new stamps, old content.
    moved = [
        UsFrame(np.roll(f.image, 3 * k, axis=1), f.time, f.X_BP, f.frame_index)
        for k, f in enumerate(frames)
    ]
    out = _run_label_faults(
        geometry, _faults(SensorFaultConfig(kind="frozen_image", start=0.1)), moved
    )
    assert [o.frame_index for o in out] == list(range(6))
    assert all(np.array_equal(o.image, moved[1].image) for o in out[2:])
    # Segmentation miss: no kidney while active, untouched outside the window.
    out = _run_label_faults(
        geometry,
        _faults(SensorFaultConfig(kind="segmentation_miss", start=0.1, duration=0.1)),
        frames,
    )
    assert [bool(is_kidney(o.image).any()) for o in out] == [True, True, False, False, True, True]
    # False positive: extra kidney pixels, inside the fan only.
    out = _run_label_faults(
        geometry, _faults(SensorFaultConfig(kind="segmentation_false_positive", start=0.0)), frames
    )
    for o, f in zip(out, frames):
        assert is_kidney(o.image).sum() > is_kidney(f.image).sum()
        assert not np.any(is_kidney(o.image) & ~geometry.fan_mask)
    # NaN-stamped frames.
    out = _run_label_faults(
        geometry, _faults(SensorFaultConfig(kind="nan_image", start=0.1)), frames
    )
    assert np.all(np.isfinite(out[1].X_BP.translation()))
    assert np.all(np.isnan(out[2].X_BP.translation()))


def test_robot_sensor_faults_force_nan_and_delay():
    faults = _faults(
        SensorFaultConfig(kind="force_bias", start=1.0, magnitude=5.0),
        SensorFaultConfig(kind="nan_pose", start=2.0, duration=0.5),
        SensorFaultConfig(kind="joint_state_delay", start=0.0, delay=0.01),
    )
    system = RobotSensorFaults(faults, n=7, sample_period=1e-3)
    ctx = system.CreateDefaultContext()
    system.GetInputPort("probe_force").FixValue(ctx, np.array([0, 0, 0, 0, 0, -8.0]))
    system.GetInputPort("X_BP").FixValue(ctx, RigidTransform([0.5, 0.0, 0.1]))
    system.GetInputPort("joint_velocity").FixValue(ctx, np.zeros(7))
    from pydrake.systems.analysis import Simulator

    sim = Simulator(system, ctx)
    q_port = system.GetInputPort("joint_position")
    for k in range(40):  # q ramps 1 rad/s; sampled every ms
        q_port.FixValue(ctx, np.full(7, 0.001 * k))
        sim.AdvanceTo(0.001 * k + 1e-9)
    q_out = system.GetOutputPort("joint_position").Eval(ctx)[0]
    assert q_out == pytest.approx(0.039 - 0.01, abs=1.5e-3)  # 10 ms old
    assert system.GetOutputPort("probe_force").Eval(ctx)[5] == -8.0
    ctx.SetTime(1.5)
    assert system.GetOutputPort("probe_force").Eval(ctx)[5] == -13.0  # F_z 8 -> 13 N
    ctx.SetTime(2.1)
    assert np.all(np.isnan(system.GetOutputPort("X_BP").Eval(ctx).translation()))
    ctx.SetTime(2.6)
    assert np.all(np.isfinite(system.GetOutputPort("X_BP").Eval(ctx).translation()))


def test_nan_stamped_frame_is_not_accumulated(geometry):
    """A frame whose probe pose is NaN (fault nan_image) adds nothing to P_local."""
    from drake_rus.imaging.backprojection import BoundaryPixels, PointCloud, accumulate

    px = np.array([[100.0, 120.0], [110.0, 130.0]])
    good = accumulate(
        PointCloud(), BoundaryPixels(px, 0.0, RigidTransform([0.5, 0, 0.1]), 0), geometry
    )
    assert good.frame_count == 1 and len(good.points) == 2
    bad = accumulate(
        good, BoundaryPixels(px, 0.05, RigidTransform(np.full(3, np.nan)), 1), geometry
    )
    assert bad.frame_count == 1 and np.all(np.isfinite(bad.points))
