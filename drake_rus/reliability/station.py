"""A faulty simulated station, built from the plain one from outside.

``MakeFaultyStation(scenario, meshcat=None, patient=None)`` is ``MakeSimStation`` with the
scenario's sensor faults (``faults.sensor``) added in two places, neither of which the
product knows about:

- image faults (dropout, frozen frame, segmentation miss / false positive, NaN stamp) as the
  imaging chain's ``label_image_hook`` (:class:`~drake_rus.reliability.systems.LabelImageFaults`
  on the label frames before the emulator, so the image and every segmenter see them);
- robot-sensor faults (force spike / bias, joint-state delay, NaN in q, v, force or pose) as
  a wrapper diagram re-exporting every station port under its own name, the robot ports
  through :class:`~drake_rus.reliability.systems.RobotSensorFaults`.

Without faults it returns the plain station. Patient motion (breathing, a shift) is not a
fault: it is the patient's (``patient.motion``), and the plain station already has it.
``MakeFaultyStation`` has ``MakeStation``'s signature, so ``RunScan(make_station=...)``
takes it.
"""

from __future__ import annotations

from pydrake.systems.framework import Diagram, DiagramBuilder

from drake_rus.reliability.systems import (
    IMAGE_FAULTS,
    ROBOT_FAULTS,
    LabelImageFaults,
    RobotSensorFaults,
)
from drake_rus.station import MakeSimStation
from drake_rus.station_interface import ROBOT_SENSOR_PORTS, CheckStationPorts

__all__ = ["MakeFaultyStation", "WithSensorFaults", "fault_seed", "ROBOT_PORTS"]

# The robot-sensor ports the faults corrupt: the interface's (drake_rus.station_interface).
ROBOT_PORTS = ROBOT_SENSOR_PORTS


def fault_seed(scenario) -> int:
    """The seed of the fault draws: the run's random_seed combined with ``faults.seed``."""
    return int(scenario.random_seed) * 1000003 + int(scenario.faults.seed)


def _image_fault_hook(scenario):
    if not any(f.kind in IMAGE_FAULTS for f in scenario.faults.sensor):
        return None

    def hook(builder, label_image):
        faults = builder.AddNamedSystem(
            "label_image_faults",
            LabelImageFaults(scenario.imaging, scenario.faults, fault_seed(scenario)),
        )
        builder.Connect(label_image, faults.GetInputPort("label_image"))
        return faults.GetOutputPort("label_image")

    return hook


def WithSensorFaults(station: Diagram, scenario, name: str = "station") -> Diagram:
    """``station`` itself when no robot-sensor fault is configured; otherwise a diagram
    with the same ports whose joint state, X_BP and probe_force carry the faults."""
    if not any(f.kind in ROBOT_FAULTS for f in scenario.faults.sensor):
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
    CheckStationPorts(diagram, "sim")
    return diagram


def MakeFaultyStation(scenario, meshcat=None, *, patient=None, name: str = "station") -> Diagram:
    """The simulated station with ``scenario.faults`` injected (see the module doc)."""
    station = MakeSimStation(
        scenario,
        meshcat=meshcat,
        patient=patient,
        name=name,
        label_image_hook=_image_fault_hook(scenario),
    )
    return WithSensorFaults(station, scenario, name)
