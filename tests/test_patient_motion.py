"""Patient motion (drake_rus.anatomy.motion): breathing and a shift as pure functions of time,
the slice sensor and true kidney pose moving with them, and the moving contact body."""

import dataclasses
import math

import numpy as np
import pytest
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.analysis import Simulator

from drake_rus.anatomy import load_patient
from drake_rus.anatomy import motion as M
from drake_rus.anatomy.labels import Label, LabelVolume, is_kidney
from drake_rus.anatomy.motion import BreathingConfig, PatientShiftConfig
from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.systems import SliceSensor
from drake_rus.patient_body import MovingPose, PatientMotionFor
from drake_rus.scenario import LoadScenario
from drake_rus.stations import MakeStation


def test_scheduled_holds_the_level_and_continuity():
    """A patient on their own schedule of holds: each hold at its level (inspiration:
    hold_depth, within hold_reproducibility; expiration: end-expiration) for
    hold_duration s, drifting cranially by hold_drift; the displacement is continuous."""
    cfg = BreathingConfig(
        enabled=True,
        amplitude=0.012,
        rate_per_min=15.0,
        hold_period=12.0,
        hold_duration=6.0,
        first_hold=4.0,
        hold_reproducibility=0.003,
    )
    t = np.arange(0.0, 60.0, 0.01)
    program = M.BreathingProgram(cfg, 3)
    d = np.array([cfg.amplitude * program.level(x) for x in t])
    hold = np.array([program.holding(x) for x in t])
    # 6 s every 12 s from 4 s, less the breath in to each hold.
    assert 0.25 < hold.mean() < 0.5
    assert M.breathing_displacement(30.0, cfg, seed=3) == pytest.approx(d[3000])
    # Continuous: no 10 ms step beyond the fastest breath's speed.
    assert np.max(np.abs(np.diff(d))) < 0.012 * 2.0 * 4 * math.pi / 4.0 * 0.01
    windows = M.hold_windows(60.0, cfg, seed=3)
    assert len(windows) >= 4
    for a, b in windows:
        seg = d[(t >= a) & (t < b)]
        # A hold breathed in: at the mean tidal depth within the reproducibility, and
        # drifting cranially (the displacement decreasing) by at most 1.5 x hold_drift.
        assert abs(seg[0] - cfg.hold_depth * 0.012) <= 0.003 + 1e-9
        assert 0.0 <= seg[0] - seg[-1] <= 1.5 * cfg.hold_drift * (b - a) + 1e-9
        assert b - a <= cfg.hold_duration + 0.01
    out = dataclasses.replace(cfg, hold_level="expiration")
    for a, b in M.hold_windows(60.0, out, seed=3):
        assert abs(M.breathing_displacement(a + 0.5, out, seed=3)) <= 0.003 + 0.002
    # Free breathing only: no holds; breaths of about a period, each from end-expiration.
    free = dataclasses.replace(cfg, hold_period=0.0)
    assert M.hold_windows(60.0, free) == []
    assert M.breathing_displacement(0.0, free) == pytest.approx(0.0)
    assert not M.breath_hold(1.0, free)
    assert not M.breath_hold(1.0, BreathingConfig(enabled=False))


def test_patient_shift_ramps_to_offset():
    cfg = PatientShiftConfig(enabled=True, time=2.0, offset=[0.0, 0.02, -0.005], ramp=0.5)
    np.testing.assert_allclose(M.shift_offset(1.9, cfg), 0.0)
    np.testing.assert_allclose(M.shift_offset(2.25, cfg), [0.0, 0.01, -0.0025])
    np.testing.assert_allclose(M.shift_offset(10.0, cfg), [0.0, 0.02, -0.005])


def test_slice_sensor_sees_the_kidney_move_with_the_patient(geometry):
    """A kidney block moved 10 mm caudally by breathing appears 10 mm further along the
    probe's x axis (the probe's array along the body's head-foot axis)."""
    labels = np.full((80, 80, 240), Label.SOFT_TISSUE, np.uint8)
    labels[30:50, 35:45, 40:160] = Label.KIDNEY_CORTEX  # x in [30, 50) mm
    volume = LabelVolume(labels, 0.001)
    # Probe at the grid's centre top, beam down (-z_B), array along +x_B; up = -x_B, so
    # d > 0 (caudal) moves the kidney along +x_B.
    X_BP = RigidTransform(RotationMatrix(np.diag([1.0, -1.0, -1.0])), [0.040, 0.040, 0.230])
    motion = M.PatientMotion(
        M.PatientMotionConfig(
            breathing=BreathingConfig(
                enabled=True,
                amplitude=0.01,
                ap_amplitude=0.0,
                rate_per_min=15.0,
                rate_cv=0.0,
                amplitude_cv=0.0,
                end_expiration_sd=0.0,
                shape_exponent=1.0,
            )
        ),
        [-1.0, 0.0, 0.0],
    )
    sensor = SliceSensor(ImagingConfig(), volume, RigidTransform(), motion)
    simulator = Simulator(sensor)
    ctx = simulator.get_mutable_context()
    sensor.GetInputPort("X_BP").FixValue(ctx, X_BP)
    simulator.Initialize()

    def kidney_columns(t):
        simulator.AdvanceTo(t + 1e-6)
        frame = sensor.GetOutputPort("label_image").Eval(ctx)
        assert frame.time == pytest.approx(t)
        return np.nonzero(is_kidney(frame.image).any(axis=0))[0].mean()

    c0, c1 = kidney_columns(0.0), kidney_columns(2.0)  # d = 0, then d = 10 mm
    assert (c1 - c0) * geometry.dx == pytest.approx(0.010, abs=0.0015)
    X0 = RigidTransform([0.1, 0.2, 0.3])
    pose = MovingPose(X0, motion)
    pctx = pose.CreateDefaultContext()
    pctx.SetTime(2.0)
    np.testing.assert_allclose(
        pose.get_output_port().Eval(pctx).translation(), [0.11, 0.2, 0.3], atol=1e-12
    )


def test_patient_contact_body_moves_with_breathing_and_shift():
    """With breathing or a shift the contact body is on driven joints and follows the
    same displacement as the imaged anatomy (sub-millimetre, with the robot pressing on
    it); without patient motion it stays welded (no extra degrees of freedom)."""
    patient = load_patient("test:0", progress=False)
    still = MakeStation(LoadScenario(scenario_name="quick"), patient=patient)
    assert not still.GetSubsystemByName("plant").HasModelInstanceNamed("patient")
    scenario = LoadScenario(
        scenario_name="quick",
        scenario_text=(
            "{patient: {motion: {breathing: {enabled: true, amplitude: 0.02, rate_per_min: 20, "
            "hold_period: 0}, shift: {enabled: true, time: 0.6, offset: [0.01, 0.0, "
            "0.005], ramp: 0.3}}}}"
        ),
    )
    station = MakeStation(scenario, patient=patient)
    plant = station.GetSubsystemByName("plant")
    assert plant.HasModelInstanceNamed("patient")
    simulator = Simulator(station)
    context = simulator.get_mutable_context()
    station.GetInputPort("joint_velocity_command").FixValue(context, np.zeros(7))
    motion = PatientMotionFor(scenario)
    moved = []
    for t in (0.5, 1.6):
        simulator.AdvanceTo(t)
        x = station.GetOutputPort("plant_state").Eval(context)
        q_patient = x[7 : len(x) // 2]
        want = motion.offset_B(t)
        assert np.linalg.norm(want) > (0.0005 if t < 0.6 else 0.004)
        np.testing.assert_allclose(q_patient, want, atol=0.001)
        moved.append(q_patient)
    assert moved[1][0] == pytest.approx(0.01, abs=0.001)  # the shift along x
    # A breathing patient's station reports its truth and hears prompts; a still one's not.
    for name in ("breath_hold", "respiratory_level_true", "patient_offset_true"):
        assert station.HasOutputPort(name) and not still.HasOutputPort(name)
    assert station.HasInputPort("breath_prompt") and not still.HasInputPort("breath_prompt")


def test_a_patient_nobody_prompts_holds_on_their_own_schedule():
    """The simulated station's patient with ``hold_period`` and no prompt heard (the
    rehearsal's simulated side, or a patient who does not listen) holds when their schedule
    says, as BreathingProgram does."""
    from drake_rus.anatomy.motion import BreathingProgram
    from drake_rus.patient_body import BreathingPatient

    for listens in (True, False):
        scenario = LoadScenario(
            scenario_name="quick",
            scenario_text=(
                "{patient: {motion: {breathing: {enabled: true, amplitude: 0.015, "
                "rate_per_min: 15, hold_period: 14, hold_duration: 6, first_hold: 5, "
                "follows_prompts: " + ("true" if listens else "false") + "}}}}"
            ),
        )
        motion = PatientMotionFor(scenario)
        patient = BreathingPatient(motion)
        simulator = Simulator(patient)
        context = simulator.get_mutable_context()
        program = BreathingProgram(scenario.patient.motion.breathing, motion.seed)
        hold = patient.GetOutputPort("breath_hold")
        level = patient.GetOutputPort("respiratory_level")
        held = []
        for t in np.arange(0.5, 30.0, 0.25) + 0.013:  # off the 10 ms update grid
            simulator.AdvanceTo(float(t))
            held.append(hold.Eval(context)[0] > 0.5)
            assert held[-1] == program.holding(float(t)), t
            assert level.Eval(context)[0] == pytest.approx(program.level(float(t)), abs=0.02)
        assert sum(held) > 30  # two holds of ~6 s
