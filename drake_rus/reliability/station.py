"""Wiring of fault injection and patient motion into the simulated station.

Four hooks, each a no-op unless the scenario's ``faults`` section asks for it:

- :func:`moves_patient_body` / :func:`AddPatientMotionDriver` (``station.MakeSimStation``):
  with breathing or a shift the patient's contact body sits on driven x-y-z joints and moves
  with the same displacement as the imaged anatomy;

- :func:`AddFaultyImaging` (from ``station._AddImaging``): moving slice sensor ->
  label-frame faults -> ultrasound emulator; exports ``us_image``, ``label_image``,
  ``X_BK_true`` (moving with the patient) and ``breath_hold``;
- :func:`WithSensorFaults` (end of ``station.MakeSimStation``): wraps the station diagram so
  that its joint state, probe pose and force outputs pass through :class:`RobotSensorFaults`;
  every other port is re-exported unchanged under the same name;
- :func:`GateByBreathHold` (``scan.BuildScanDiagram``): the point-cloud accumulator's
  ``enable`` becomes exploring AND breath-hold when ``faults.breathing.gate_exploration``;
  :func:`BreathHoldPort` also drives the supervisor's and the tracking monitor's
  ``motion_allowed`` then (exploration and pivot move only during breath-holds).
"""

from __future__ import annotations

from pydrake.common.value import AbstractValue
from pydrake.systems.framework import Diagram, DiagramBuilder

from drake_rus.reliability.systems import (
    IMAGE_FAULTS, ROBOT_FAULTS, And2, BreathHoldSignal, LabelImageFaults, MovingPose,
    MovingSliceSensor, RobotSensorFaults)

ROBOT_PORTS = ("joint_position", "joint_velocity", "X_BP", "probe_force")


def needs_faulty_imaging(scenario) -> bool:
    f = scenario.faults
    return f.moves_patient or any(s.kind in IMAGE_FAULTS for s in f.sensor)


def needs_robot_faults(scenario) -> bool:
    return any(s.kind in ROBOT_FAULTS for s in scenario.faults.sensor)


def fault_seed(scenario) -> int:
    return int(scenario.random_seed) * 1000003 + int(scenario.faults.seed)


def superior_axis_B(scenario):
    """The patient's head direction (y of the patient frame) in the robot base frame."""
    X_BPt = scenario.patient.X_BPt.GetDeterministicValue()
    return X_BPt.rotation().matrix()[:, 1]


def AddFaultyImaging(builder: DiagramBuilder, scenario, patient, fk) -> None:
    """The station's imaging chain with patient motion and label-frame faults (sim only)."""
    from drake_rus.imaging.systems import UltrasoundEmulator

    seed = fault_seed(scenario)
    up = superior_axis_B(scenario)
    X_BPt = scenario.patient.X_BPt.GetDeterministicValue()
    volume = patient.labels
    sensor = builder.AddNamedSystem("slice_sensor", MovingSliceSensor(
        scenario.imaging, volume, X_BPt @ volume.X_PtV, scenario.faults, up, seed))
    builder.Connect(fk.get_output_port(), sensor.GetInputPort("X_BP"))
    faults = builder.AddNamedSystem("label_image_faults",
                                    LabelImageFaults(scenario.imaging, scenario.faults, seed))
    builder.Connect(sensor.GetOutputPort("label_image"), faults.GetInputPort("label_image"))
    emulator = builder.AddNamedSystem(
        "ultrasound_emulator", UltrasoundEmulator(scenario.imaging, scenario.random_seed))
    builder.Connect(faults.GetOutputPort("label_image"), emulator.GetInputPort("label_image"))
    builder.ExportOutput(emulator.GetOutputPort("us_image"), "us_image")
    builder.ExportOutput(faults.GetOutputPort("label_image"), "label_image")
    X_BK = builder.AddNamedSystem("X_BK_true", MovingPose(patient.X_BK(X_BPt), scenario.faults,
                                                          up, seed))
    builder.ExportOutput(X_BK.get_output_port(), "X_BK_true")
    hold = builder.AddNamedSystem("breath_hold", BreathHoldSignal(scenario.faults))
    builder.ExportOutput(hold.get_output_port(), "breath_hold")


def moves_patient_body(scenario, patient) -> bool:
    """Whether the contact body moves with the patient (breathing or a shift, virtual
    patient): the skin then moves under the probe as the kidney does in the images."""
    return patient is not None and scenario.faults.moves_patient


def AddPatientMotionDriver(builder: DiagramBuilder, plant, scenario, instance) -> None:
    """Drives the moving patient body: desired state = the patient displacement of the
    imaging chain (same model, same seed), gravity fed forward."""
    import numpy as np
    from pydrake.systems.primitives import ConstantVectorSource

    from drake_rus.reliability.systems import PatientMotionDesiredState
    desired = builder.AddNamedSystem("patient_motion", PatientMotionDesiredState(
        scenario.faults, superior_axis_B(scenario), fault_seed(scenario)))
    builder.Connect(desired.get_output_port(), plant.get_desired_state_input_port(instance))
    mass = sum(plant.get_body(b).default_mass() for b in plant.GetBodyIndices(instance))
    g = float(np.linalg.norm(plant.gravity_field().gravity_vector()))
    weight = builder.AddNamedSystem("patient_weight",
                                    ConstantVectorSource([0.0, 0.0, mass * g]))
    builder.Connect(weight.get_output_port(), plant.get_actuation_input_port(instance))


def WithSensorFaults(station: Diagram, scenario, name: str = "station") -> Diagram:
    """``station`` itself when no robot-sensor fault is configured; otherwise a diagram
    with the same ports whose joint state, X_BP and probe_force carry the faults."""
    if not needs_robot_faults(scenario):
        return station
    builder = DiagramBuilder()
    station.set_name(f"{name}_sim")
    inner = builder.AddSystem(station)
    faults = builder.AddNamedSystem("robot_sensor_faults", RobotSensorFaults(scenario.faults))
    for i in range(inner.num_input_ports()):
        port = inner.get_input_port(i)
        builder.ExportInput(port, port.get_name())
    for i in range(inner.num_output_ports()):
        port = inner.get_output_port(i)
        if port.get_name() in ROBOT_PORTS:
            builder.Connect(port, faults.GetInputPort(port.get_name()))
            builder.ExportOutput(faults.GetOutputPort(port.get_name()), port.get_name())
        else:
            builder.ExportOutput(port, port.get_name())
    diagram = builder.Build()
    diagram.set_name(name)
    return diagram


def BreathHoldPort(scenario, station):
    """The station's ``breath_hold`` output when respiration-aware scanning is on
    (``faults.breathing.enabled`` and ``gate_exploration``), else None."""
    cfg = scenario.faults.breathing
    if not (cfg.enabled and cfg.gate_exploration and station.HasOutputPort("breath_hold")):
        return None
    return station.GetOutputPort("breath_hold")


def GateByBreathHold(builder: DiagramBuilder, scenario, station, enable_port):
    """``enable_port`` AND the station's ``breath_hold`` when exploration frames are gated
    to breath-holds (``faults.breathing.gate_exploration``); else ``enable_port``."""
    hold = BreathHoldPort(scenario, station)
    if hold is None:
        return enable_port
    gate = builder.AddNamedSystem("breath_hold_gate", And2())
    builder.Connect(enable_port, gate.GetInputPort("a"))
    builder.Connect(hold, gate.GetInputPort("b"))
    return gate.GetOutputPort("value")
