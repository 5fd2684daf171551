"""A station and the controller in one closed loop, without the imaging chain's localizer:
the building block of the controller tests, the tuning notebook, the control benchmark and
``drake-rus hardware check``; and :class:`PressDiagram`, the station pressed by the minimal
press driver (``drake-rus demo``, the station benchmark, the force-loop tests).

``BuildClosedLoop`` wires ``drake_rus.control.diagram.AddController`` to any station;
``BuildClosedLoopOnPatient`` adds a virtual patient's images and the scenario's segmenter,
with the true kidney pose standing in for localization. Sensor corruption (tests) enters
only through ``sensor_hook``, passed in from outside (``drake_rus.reliability.injector``).
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np
from pydrake.math import RigidTransform
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource, LogVectorOutput, VectorLogSink

from drake_rus.anatomy import load_patient
from drake_rus.control.diagram import AddController, ControllerParts
from drake_rus.control.press import PressDriver
from drake_rus.control.supervisor import Phase
from drake_rus.imaging.systems import Segmenter
from drake_rus.robot import MakeControlPlant, SolveTipPose, TipKinematics
from drake_rus.scenario import ApplyOverrides
from drake_rus.stations import MakeStation

__all__ = [
    "ClosedLoop",
    "BuildClosedLoop",
    "BuildClosedLoopOnPatient",
    "AdvanceUntilScanEnds",
    "SensorHook",
    "PressDiagram",
]

# (builder, station, segmenter or None) -> (system whose outputs replace the station's
# sensor ports, segmenter stand-in or None, the added system): e.g. a fault injector.
SensorHook = Callable[[DiagramBuilder, object, object], tuple]


@dataclasses.dataclass
class ClosedLoop:
    """A built station + controller diagram and handles to its parts."""

    diagram: object
    station: object
    parts: ControllerParts
    injector: object | None  # what ``sensor_hook`` added, if anything
    references: dict  # name -> ConstantVectorSource when the supervisor is off
    loggers: dict  # name -> VectorLogSink

    def reference(self, context, name) -> np.ndarray:
        """The current value (a copy) of a constant reference source (a_des, o_des,
        a_des_dot, P_des, F_des) in the root ``context``."""
        src = self.references[name]
        return np.array(src.get_output_port().Eval(src.GetMyContextFromRoot(context)))

    def reference_value(self, context, name):
        """The mutable value of a constant reference source (a_des, o_des, a_des_dot, P_des,
        F_des) in the root ``context``."""
        src = self.references[name]
        return src.get_mutable_source_value(src.GetMyMutableContextFromRoot(context))


def _add_loggers(builder, ports: dict, period: float) -> dict:
    loggers = {}
    for name, port in ports.items():
        log = builder.AddNamedSystem(f"log_{name}", VectorLogSink(port.size(), period))
        builder.Connect(port, log.get_input_port())
        loggers[name] = log
    return loggers


def BuildClosedLoop(
    scenario,
    *,
    meshcat=None,
    station=None,
    use_supervisor: bool = True,
    use_null_space: bool = True,
    sensor_hook: SensorHook | None = None,
    segmenter=None,
    kidney_pose_port=None,
    kidney_view=None,
    log_period: float | None = None,
) -> ClosedLoop:
    """Station + controller + safety in one diagram (tests, notebook, benchmark).

    ``station`` defaults to ``MakeStation(scenario)``. ``sensor_hook`` inserts a system
    between the station's sensors and the controller (the command still goes straight to
    the station). Without the supervisor, constant reference sources hold the probe's
    initial orientation and tip x, y and the scenario's desired force; change them through
    :meth:`ClosedLoop.reference_value`. ``kidney_view`` (a
    :class:`~drake_rus.control.synthetic_view.GeometricKidneyView`) is added and wired as
    the segmenter and the kidney pose source. ``log_period`` (s) adds loggers of the
    command, the joint positions, probe_force and the filtered force.
    """
    builder = DiagramBuilder()
    if station is None:
        station = MakeStation(scenario, meshcat=meshcat)
    builder.AddNamedSystem("station", station)
    if kidney_view is not None:
        builder.AddNamedSystem("kidney_view", kidney_view)
        builder.Connect(station.GetOutputPort("X_BP"), kidney_view.GetInputPort("X_BP"))
        segmenter = kidney_view
        kidney_pose_port = kidney_view.GetOutputPort("X_BK")
    sensors, injector = station, None
    if sensor_hook is not None:
        sensors, segmenter, injector = sensor_hook(builder, station, segmenter)
    parts = AddController(
        builder,
        sensors,
        scenario,
        use_supervisor=use_supervisor,
        use_null_space=use_null_space,
        segmenter=segmenter,
        kidney_pose_port=kidney_pose_port,
        connect_command=False,
    )
    builder.Connect(
        parts.safety.GetOutputPort("joint_velocity_command"),
        station.GetInputPort("joint_velocity_command"),
    )
    refs = {}
    if not use_supervisor:
        X0 = station.GetOutputPort("X_BP").Eval(station.CreateDefaultContext())
        R0, p0 = X0.rotation().matrix(), X0.translation()
        values = {
            "a_des": (parts.orientation, R0[:, 2]),
            "o_des": (parts.orientation, R0[:, 0]),
            "a_des_dot": (parts.orientation, np.zeros(3)),
            "P_des": (parts.position, p0[:2]),
            "F_des": (parts.force, [scenario.controller.desired_force]),
        }
        for name, (sys, value) in values.items():
            src = builder.AddNamedSystem(
                f"reference_{name}", ConstantVectorSource(np.asarray(value, float))
            )
            builder.Connect(src.get_output_port(), sys.GetInputPort(name))
            refs[name] = src
    loggers = {}
    if log_period:
        ports = {
            "command": parts.safety.GetOutputPort("joint_velocity_command"),
            "q": station.GetOutputPort("joint_position"),
            "probe_force": station.GetOutputPort("probe_force"),
            "F_filtered": parts.force.GetOutputPort("F_filtered"),
            "stopped": parts.safety.GetOutputPort("stopped"),
        }
        if parts.supervisor is not None:
            ports["phase"] = parts.supervisor.GetOutputPort("phase")
            ports["P_des"] = parts.supervisor.GetOutputPort("P_des")
        if segmenter is not None:
            ports["kidney_visible"] = segmenter.GetOutputPort("kidney_visible")
            ports["mask_centroid"] = segmenter.GetOutputPort("mask_centroid")
        loggers = _add_loggers(builder, ports, log_period)
    diagram = builder.Build()
    return ClosedLoop(diagram, station, parts, injector, refs, loggers)


def BuildClosedLoopOnPatient(
    scenario, patient, *, log_period: float | None = 0.05, start_height: float = 0.22, meshcat=None
):
    """Station with a virtual patient's emulated images + the scenario's Segmenter +
    controller + safety; the supervisor's LOCALIZE reads the station's ``X_BK_true``
    (ground-truth stand-in). The robot starts ``start_height`` (m) above the kidney centre,
    with the orientation of the scenario's initial joints, and APPROACH lands the probe over
    it (the seed places the probe by hand where the kidney is visible). ``patient`` is a
    Patient or a spec such as ``"test:0"``.

    Returns (ClosedLoop, the scenario actually used).
    """
    if isinstance(patient, str):
        patient = load_patient(
            patient, side=scenario.patient.side, posture=scenario.patient.posture, progress=False
        )
    p_K = patient.X_BK(scenario.patient.X_BPt.GetDeterministicValue()).translation()
    plant, tip = MakeControlPlant(scenario.robot, scenario.probe)
    q_initial = np.asarray(scenario.robot.initial_joint_positions, dtype=float)
    R0 = TipKinematics(plant, tip).pose(q_initial).rotation()
    q0 = SolveTipPose(
        plant, tip, RigidTransform(R0, [p_K[0], p_K[1], p_K[2] + start_height]), q_nominal=q_initial
    )
    # It starts higher above the skin than an operator's placement: allow that approach.
    travel = max(scenario.controller.approach_max_travel, start_height)
    scenario = ApplyOverrides(
        scenario,
        "{robot: {initial_joint_positions: [%s]}, "
        "controller: {approach_max_travel: %.3f}}" % (", ".join(f"{v:.6f}" for v in q0), travel),
    )
    scenario.controller.start_xy = [float(v) for v in p_K[:2]]
    station = MakeStation(scenario, meshcat=meshcat, patient=patient)

    builder = DiagramBuilder()
    builder.AddNamedSystem("station", station)
    segmenter = builder.AddNamedSystem("segmenter", Segmenter(scenario.imaging))
    for name in ("us_image", "label_image"):
        builder.Connect(station.GetOutputPort(name), segmenter.GetInputPort(name))
    parts = AddController(
        builder,
        station,
        scenario,
        plant=plant,
        tip_frame=tip,
        segmenter=segmenter,
        kidney_pose_port=station.GetOutputPort("X_BK_true"),
    )
    loggers = {}
    if log_period:
        loggers = _add_loggers(
            builder,
            {
                "probe_force": station.GetOutputPort("probe_force"),
                "q": station.GetOutputPort("joint_position"),
                "mask_centroid": segmenter.GetOutputPort("mask_centroid"),
                "kidney_visible": segmenter.GetOutputPort("kidney_visible"),
                "phase": parts.supervisor.GetOutputPort("phase"),
            },
            log_period,
        )
    return ClosedLoop(builder.Build(), station, parts, None, {}, loggers), scenario


def AdvanceUntilScanEnds(simulator, scan_supervisor, t_max: float, step: float = 0.5) -> None:
    """Advances ``simulator`` in ``step`` s chunks until ``scan_supervisor`` (a ScanSupervisor
    in its diagram) reaches DONE or ABORT, or the time reaches ``t_max`` (s)."""
    context = simulator.get_mutable_context()
    supervisor_context = scan_supervisor.GetMyContextFromRoot(context)
    while context.get_time() < t_max and scan_supervisor.state(supervisor_context).phase not in (
        Phase.DONE,
        Phase.ABORT,
    ):
        simulator.AdvanceTo(min(t_max, context.get_time() + step))


class PressDiagram:
    """Station + PressDriver (+ loggers of the estimated and true probe wrench).

    The true wrench is logged at every plant step (cheap: the station samples it there), so
    an oscillation of the force loop, up to the controller's Nyquist rate, cannot alias
    into a false steady value; the estimate at every controller period (``log_period``
    overrides both)."""

    def __init__(
        self,
        scenario,
        meshcat=None,
        desired_force: float | None = None,
        log_period: float | None = None,
        patient=None,
        drive: bool = True,
        hold_orientation: bool = True,
    ):
        builder = DiagramBuilder()
        self.station = builder.AddNamedSystem(
            "station", MakeStation(scenario, meshcat=meshcat, patient=patient)
        )
        if drive:
            control_plant, tip_frame = MakeControlPlant(scenario.robot, scenario.probe)
            self.driver = builder.AddNamedSystem(
                "press_driver",
                PressDriver(
                    control_plant,
                    tip_frame,
                    scenario.controller,
                    desired_force,
                    hold_orientation=hold_orientation,
                ),
            )
            builder.Connect(
                self.station.GetOutputPort("joint_position"), self.driver.get_input_port(0)
            )
            builder.Connect(
                self.station.GetOutputPort("probe_force"), self.driver.get_input_port(1)
            )
            builder.Connect(
                self.driver.get_output_port(), self.station.GetInputPort("joint_velocity_command")
            )
        else:
            self.driver = builder.AddNamedSystem("zero_command", ConstantVectorSource(np.zeros(7)))
            builder.Connect(
                self.driver.get_output_port(), self.station.GetInputPort("joint_velocity_command")
            )
        self.force_log = LogVectorOutput(
            self.station.GetOutputPort("probe_force"),
            builder,
            log_period or 1.0 / scenario.controller.rate_hz,
        )
        self.truth_log = LogVectorOutput(
            self.station.GetOutputPort("probe_contact_wrench_true"),
            builder,
            log_period or scenario.contact.time_step,
        )
        self.diagram = builder.Build()
        self.diagram.set_name("press_demo")

    def logs(self, root_context):
        """(times (N,), estimated F_z (N,), true F_z (N,)) in s and N, at the estimate's
        log times."""
        est = self.force_log.FindLog(root_context)
        t_true, F_true = self.true_force(root_context)
        t = est.sample_times()
        i = np.clip(np.searchsorted(t_true, t - 1e-9), 0, max(len(t_true) - 1, 0))
        return t, -est.data()[5], F_true[i] if len(t_true) else np.zeros(len(t))

    def true_force(self, root_context):
        """(times (N,), true F_z (N,)) in s and N, at every plant step."""
        tru = self.truth_log.FindLog(root_context)
        return tru.sample_times(), -tru.data()[5]
