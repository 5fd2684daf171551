"""Wires the controller and the safety layer to a station through its exported ports only.

    station.joint_position, joint_velocity, X_BP, probe_force
        -> ScanSupervisor -> (a_des, o_des, P_des, F_des)
        -> OrientationAlignment (eq. 1-5), ForcePD (eq. 6), PositionP (eq. 7)
        -> NullSpaceDiffIK (eq. 8-12) -> SafetyLayer -> station.joint_velocity_command

The same builder drives the simulated and the hardware station.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from pydrake.common.value import AbstractValue
from pydrake.systems.framework import DiagramBuilder, LeafSystem

from drake_rus.control.kinematics import MakeControlPlant
from drake_rus.control.systems import (ForcePD, NullSpaceDiffIK, OrientationAlignment,
                                       PositionP, SafetyLayer, ScanSupervisor)


class FrameTime(LeafSystem):
    """Time stamp (s) of an abstract image frame (a dataclass with ``time``, ``t`` or
    ``stamp``) as a 1-vector, for the safety layer's stale-image watchdog. NaN when the
    frame carries no stamp."""

    def __init__(self, model_value: AbstractValue):
        super().__init__()
        self._in = self.DeclareAbstractInputPort("frame", model_value)
        self.DeclareVectorOutputPort("time", 1, self._calc)

    def _calc(self, context, output):
        frame = self._in.Eval(context)
        for name in ("time", "t", "stamp", "timestamp"):
            if hasattr(frame, name):
                output.SetFromVector([float(getattr(frame, name))])
                return
        output.SetFromVector([math.nan])


class ToVector1(LeafSystem):
    """An abstract scalar/bool port (e.g. a segmenter's kidney_visible) as a 1-vector."""

    def __init__(self, model_value: AbstractValue):
        super().__init__()
        self._in = self.DeclareAbstractInputPort("u", model_value)
        self.DeclareVectorOutputPort("y", 1, lambda c, o: o.SetFromVector(
            [float(np.asarray(self._in.Eval(c), dtype=float).reshape(-1)[0])]))


@dataclasses.dataclass
class ControllerParts:
    """The systems AddController added (ports are documented on each class)."""
    orientation: OrientationAlignment
    force: ForcePD
    position: PositionP
    ik: NullSpaceDiffIK
    safety: SafetyLayer
    supervisor: ScanSupervisor | None


def _vector1(builder, port):
    """``port`` if vector-valued (size 1), else an adapter's output."""
    from pydrake.systems.framework import PortDataType
    if port.get_data_type() == PortDataType.kVectorValued:
        return port
    adapter = builder.AddSystem(ToVector1(port.Allocate()))
    builder.Connect(port, adapter.get_input_port())
    return adapter.get_output_port()


def AddController(builder: DiagramBuilder, station, scenario, *, plant=None,
                  tip_frame=None, use_supervisor: bool = True, use_null_space: bool = True,
                  segmenter=None, kidney_pose_port=None, localization_ready_port=None,
                  image_port=None, connect_command: bool = True) -> ControllerParts:
    """Adds controller + safety layer wired to ``station`` (a system in ``builder``).

    Args:
        plant, tip_frame: the control plant (FR3 + probe) for Jacobians; default
            ``MakeControlPlant(scenario)``.
        use_supervisor: add the ScanSupervisor and connect its references; if False the
            reference inputs (orientation a_des, o_des, a_des_dot; position P_des; force
            F_des) stay unconnected for the caller (tests, the tuning notebook).
        use_null_space: the eq. 11 manipulability term (False: K_p6 = 0).
        segmenter: a system with outputs kidney_visible and mask_centroid (optional).
        kidney_pose_port: an output port carrying X_BK (RigidTransform) for LOCALIZE
            (localizer estimate or a ground-truth stand-in).
        localization_ready_port: 1-vector output, 1 when X_BK is final (optional).
        image_port: the image frames port for the stale-image watchdog (default: the
            segmenter's ``kidney_mask`` if it has one, else the station's ``us_image``).
        connect_command: connect safety.joint_velocity_command to the station.
    """
    cfg, scfg = scenario.controller, scenario.safety
    if plant is None:
        plant, tip_frame = MakeControlPlant(scenario)
    S = station.GetOutputPort
    orientation = builder.AddNamedSystem("orientation_alignment", OrientationAlignment(cfg))
    force = builder.AddNamedSystem("force_pd", ForcePD(cfg))
    position = builder.AddNamedSystem("position_p", PositionP(cfg))
    ik = builder.AddNamedSystem("null_space_diff_ik",
                                NullSpaceDiffIK(plant, tip_frame, cfg, use_null_space))
    safety = builder.AddNamedSystem("safety", SafetyLayer(plant, tip_frame, scfg, cfg.rate_hz))

    for sys in (orientation, force, position):
        builder.Connect(S("X_BP"), sys.GetInputPort("X_BP"))
    builder.Connect(S("probe_force"), force.GetInputPort("probe_force"))
    builder.Connect(S("joint_position"), ik.GetInputPort("joint_position"))
    builder.Connect(orientation.GetOutputPort("omega_BP"), ik.GetInputPort("omega_BP"))
    builder.Connect(force.GetOutputPort("v_force"), ik.GetInputPort("v_force"))
    builder.Connect(position.GetOutputPort("v_position"), ik.GetInputPort("v_position"))

    builder.Connect(ik.GetOutputPort("joint_velocity_desired"),
                    safety.GetInputPort("joint_velocity_desired"))
    for name in ("joint_position", "joint_velocity", "X_BP", "probe_force"):
        builder.Connect(S(name), safety.GetInputPort(name))
    if image_port is None:
        # Watch the frames the controller actually uses: the segmenter's mask (stamped with
        # its source frame's time) if there is one, else the station's ultrasound images.
        if segmenter is not None and segmenter.HasOutputPort("kidney_mask"):
            image_port = segmenter.GetOutputPort("kidney_mask")
        elif station.HasOutputPort("us_image"):
            image_port = S("us_image")
    if image_port is not None:
        stamp = builder.AddNamedSystem("image_stamp", FrameTime(image_port.Allocate()))
        builder.Connect(image_port, stamp.get_input_port())
        builder.Connect(stamp.get_output_port(), safety.GetInputPort("image_time"))

    if station.HasOutputPort("robot_ok"):
        builder.Connect(_vector1(builder, S("robot_ok")), safety.GetInputPort("robot_ok"))

    supervisor = None
    if use_supervisor:
        supervisor = builder.AddNamedSystem("scan_supervisor", ScanSupervisor(cfg))
        builder.Connect(S("X_BP"), supervisor.GetInputPort("X_BP"))
        builder.Connect(force.GetOutputPort("F_filtered"), supervisor.GetInputPort("contact_force"))
        for name in ("a_des", "o_des", "a_des_dot"):
            builder.Connect(supervisor.GetOutputPort(name), orientation.GetInputPort(name))
        builder.Connect(supervisor.GetOutputPort("P_des"), position.GetInputPort("P_des"))
        builder.Connect(supervisor.GetOutputPort("F_des"), force.GetInputPort("F_des"))
        builder.Connect(supervisor.GetOutputPort("segmentation_required"),
                        safety.GetInputPort("segmentation_required"))
        builder.Connect(supervisor.GetOutputPort("abort"), safety.GetInputPort("supervisor_abort"))
        builder.Connect(safety.GetOutputPort("stopped"), supervisor.GetInputPort("safety_stopped"))
        if kidney_pose_port is not None:
            builder.Connect(kidney_pose_port, supervisor.GetInputPort("X_BK"))
        if localization_ready_port is not None:
            builder.Connect(localization_ready_port, supervisor.GetInputPort("localization_ready"))
    if segmenter is not None:
        visible = _vector1(builder, segmenter.GetOutputPort("kidney_visible"))
        centroid = _vector1(builder, segmenter.GetOutputPort("mask_centroid"))
        builder.Connect(visible, safety.GetInputPort("kidney_visible"))
        if supervisor is not None:
            builder.Connect(visible, supervisor.GetInputPort("kidney_visible"))
            builder.Connect(centroid, supervisor.GetInputPort("mask_centroid"))
    if connect_command:
        builder.Connect(safety.GetOutputPort("joint_velocity_command"),
                        station.GetInputPort("joint_velocity_command"))
    return ControllerParts(orientation, force, position, ik, safety, supervisor)


@dataclasses.dataclass
class ClosedLoop:
    """A built station + controller diagram and handles to its parts."""
    diagram: object
    station: object
    parts: ControllerParts
    injector: object | None
    references: dict      # name -> ConstantVectorSource when the supervisor is off
    loggers: dict         # name -> VectorLogSink

    def reference_value(self, context, name):
        """The mutable value of a constant reference source (a_des, o_des, a_des_dot, P_des,
        F_des) in the root ``context``."""
        src = self.references[name]
        return src.get_mutable_source_value(src.GetMyMutableContextFromRoot(context))


def BuildClosedLoop(scenario, *, meshcat=None, station=None, use_supervisor: bool = True,
                    use_null_space: bool = True, fault: str | None = None,
                    t_fault: float = math.inf, segmenter=None, kidney_pose_port=None,
                    kidney_view=None, log_period: float | None = None) -> ClosedLoop:
    """Station + controller + safety in one diagram (tests, notebook, benchmark).

    ``fault`` inserts a :class:`~drake_rus.control.faults.FaultInjector` between the
    station's sensors and the controller (the command still goes straight to the station).
    Without the supervisor, constant reference sources hold the probe's initial
    orientation and tip x, y and the scenario's desired force; change them through
    :meth:`ClosedLoop.reference_value`. ``kidney_view`` (a
    :class:`~drake_rus.control.synthetic_view.GeometricKidneyView`) is added and wired as
    the segmenter and the kidney pose source. ``log_period`` adds loggers of the command,
    the joint positions, probe_force and the filtered force at that period.
    """
    from pydrake.systems.primitives import ConstantVectorSource, VectorLogSink

    from drake_rus.control.faults import ConnectFaultInjector, FaultInjector

    builder = DiagramBuilder()
    if station is None:
        from drake_rus.station import MakeStation
        station = MakeStation(scenario, meshcat=meshcat)
    builder.AddNamedSystem("station", station)
    if kidney_view is not None:
        builder.AddNamedSystem("kidney_view", kidney_view)
        builder.Connect(station.GetOutputPort("X_BP"), kidney_view.GetInputPort("X_BP"))
        segmenter = kidney_view
        kidney_pose_port = kidney_view.GetOutputPort("X_BK")
    sensors, injector = station, None
    if fault is not None:
        injector = builder.AddNamedSystem(
            "fault_injector", FaultInjector(fault, t_fault,
                                            frame_rate_hz=scenario.imaging.frame_rate_hz))
        ConnectFaultInjector(builder, station, injector, segmenter)
        sensors, segmenter = injector, injector
    parts = AddController(builder, sensors, scenario, use_supervisor=use_supervisor,
                          use_null_space=use_null_space, segmenter=segmenter,
                          kidney_pose_port=kidney_pose_port, connect_command=False)
    builder.Connect(parts.safety.GetOutputPort("joint_velocity_command"),
                    station.GetInputPort("joint_velocity_command"))
    refs = {}
    if not use_supervisor:
        X0 = station.GetOutputPort("X_BP").Eval(station.CreateDefaultContext())
        R0, p0 = X0.rotation().matrix(), X0.translation()
        values = {"a_des": (parts.orientation, R0[:, 2]), "o_des": (parts.orientation, R0[:, 0]),
                  "a_des_dot": (parts.orientation, np.zeros(3)),
                  "P_des": (parts.position, p0[:2]),
                  "F_des": (parts.force, [scenario.controller.desired_force])}
        for name, (sys, value) in values.items():
            src = builder.AddNamedSystem(f"reference_{name}",
                                         ConstantVectorSource(np.asarray(value, float)))
            builder.Connect(src.get_output_port(), sys.GetInputPort(name))
            refs[name] = src
    loggers = {}
    if log_period:
        ports = {"command": parts.safety.GetOutputPort("joint_velocity_command"),
                 "q": station.GetOutputPort("joint_position"),
                 "probe_force": station.GetOutputPort("probe_force"),
                 "F_filtered": parts.force.GetOutputPort("F_filtered"),
                 "stopped": parts.safety.GetOutputPort("stopped")}
        if parts.supervisor is not None:
            ports["phase"] = parts.supervisor.GetOutputPort("phase")
            ports["P_des"] = parts.supervisor.GetOutputPort("P_des")
        if segmenter is not None:
            ports["kidney_visible"] = segmenter.GetOutputPort("kidney_visible")
            ports["mask_centroid"] = segmenter.GetOutputPort("mask_centroid")
        for name, port in ports.items():
            log = builder.AddNamedSystem(f"log_{name}", VectorLogSink(port.size(), log_period))
            builder.Connect(port, log.get_input_port())
            loggers[name] = log
    diagram = builder.Build()
    return ClosedLoop(diagram, station, parts, injector, refs, loggers)


def BuildClosedLoopOnPatient(scenario, patient, *, log_period: float | None = 0.05,
                             start_height: float = 0.22, meshcat=None):
    """Station with a virtual patient's emulated images + the scenario's Segmenter +
    controller + safety; the supervisor's LOCALIZE reads the station's ``X_BK_true``
    (ground-truth stand-in). The robot starts ``start_height`` (m) above the kidney centre
    and APPROACH lands the probe over it (the seed places the probe by hand where the kidney
    is visible). ``patient`` is a Patient or a spec such as ``"test:0"``.

    Returns (ClosedLoop, the scenario actually used).
    """
    from drake_rus.control.kinematics import JointsForTipPosition
    from drake_rus.imaging.systems import Segmenter
    from drake_rus.scenario import ApplyOverrides
    from drake_rus.station import MakeStation

    if isinstance(patient, str):
        from drake_rus.anatomy import load_patient
        patient = load_patient(patient, side=scenario.patient.side,
                               posture=scenario.patient.posture, progress=False)
    p_K = patient.X_BK(scenario.patient.X_BPt.GetDeterministicValue()).translation()
    plant, tip = MakeControlPlant(scenario)
    q0 = JointsForTipPosition(plant, tip, scenario.robot.initial_joint_positions,
                              [p_K[0], p_K[1], p_K[2] + start_height])
    scenario = ApplyOverrides(scenario, "{robot: {initial_joint_positions: [%s]}}"
                              % ", ".join(f"{v:.6f}" for v in q0))
    scenario.controller.start_xy = [float(v) for v in p_K[:2]]
    station = MakeStation(scenario, meshcat=meshcat, patient=patient)

    builder = DiagramBuilder()
    builder.AddNamedSystem("station", station)
    segmenter = builder.AddNamedSystem("segmenter", Segmenter(scenario.imaging))
    for name in ("us_image", "label_image"):
        builder.Connect(station.GetOutputPort(name), segmenter.GetInputPort(name))
    parts = AddController(builder, station, scenario, plant=plant, tip_frame=tip,
                          segmenter=segmenter,
                          kidney_pose_port=station.GetOutputPort("X_BK_true"))
    loggers = {}
    if log_period:
        from pydrake.systems.primitives import VectorLogSink
        ports = {"probe_force": station.GetOutputPort("probe_force"),
                 "q": station.GetOutputPort("joint_position"),
                 "mask_centroid": segmenter.GetOutputPort("mask_centroid"),
                 "kidney_visible": segmenter.GetOutputPort("kidney_visible"),
                 "phase": parts.supervisor.GetOutputPort("phase")}
        for name, port in ports.items():
            log = builder.AddNamedSystem(f"log_{name}", VectorLogSink(port.size(), log_period))
            builder.Connect(port, log.get_input_port())
            loggers[name] = log
    return ClosedLoop(builder.Build(), station, parts, None, {}, loggers), scenario


def AdvanceUntilScanEnds(simulator, supervisor, t_max: float, step: float = 0.5) -> None:
    """Advances ``simulator`` in ``step`` s chunks until ``supervisor`` (a ScanSupervisor in
    its diagram) reaches DONE or ABORT, or the time reaches ``t_max`` (s)."""
    from drake_rus.control import scan
    context = simulator.get_mutable_context()
    supervisor_context = supervisor.GetMyContextFromRoot(context)
    while context.get_time() < t_max and supervisor.state(supervisor_context).phase not in (
            scan.Phase.DONE, scan.Phase.ABORT):
        simulator.AdvanceTo(min(t_max, context.get_time() + step))
