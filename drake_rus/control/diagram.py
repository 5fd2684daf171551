"""Wires the controller and the safety layer to a station through its exported ports only.

    station.joint_position, joint_velocity, X_BP, probe_force
        -> ScanSupervisor -> (a_des, o_des, P_des, F_des)
        -> OrientationAlignment (eq. 1-5), ForcePD (eq. 6), PositionP (eq. 7)
        -> NullSpaceDiffIK (eq. 8-12) -> SafetyLayer -> station.joint_velocity_command

The same builder drives the simulated and the hardware station; building a whole closed
loop with a station is ``drake_rus.closed_loop`` (a layer above the stations).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import DiagramBuilder, LeafSystem, PortDataType

from drake_rus.control.systems import (
    ForcePD,
    NullSpaceDiffIK,
    OrientationAlignment,
    PositionP,
    SafetyLayer,
    ScanSupervisor,
)
from drake_rus.robot import MakeControlPlant, TipKinematics


class FrameTime(LeafSystem):
    """Time stamp (s) of an abstract image frame (a dataclass with ``time``, ``t`` or
    ``stamp``) as a 1-vector, for the safety layer's stale-image watchdog. NaN when the
    frame carries no stamp."""

    def __init__(self, model_value: AbstractValue):
        super().__init__()
        self._in = self.DeclareAbstractInputPort("frame", model_value)
        # A function of the frame alone: recomputed when a new frame arrives, not every
        # control period.
        self.DeclareVectorOutputPort(
            "time",
            1,
            self._calc,
            prerequisites_of_calc={self.input_port_ticket(self._in.get_index())},
        )

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
        self.DeclareVectorOutputPort(
            "y",
            1,
            lambda c, o: o.SetFromVector(
                [float(np.asarray(self._in.Eval(c), dtype=float).reshape(-1)[0])]
            ),
            prerequisites_of_calc={self.input_port_ticket(self._in.get_index())},
        )


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
    if port.get_data_type() == PortDataType.kVectorValued:
        return port
    adapter = builder.AddSystem(ToVector1(port.Allocate()))
    builder.Connect(port, adapter.get_input_port())
    return adapter.get_output_port()


def AddController(
    builder: DiagramBuilder,
    station,
    scenario,
    *,
    plant=None,
    tip_frame=None,
    use_supervisor: bool = True,
    use_null_space: bool = True,
    segmenter=None,
    kidney_pose_port=None,
    localization_ready_port=None,
    image_port=None,
    connect_command: bool = True,
) -> ControllerParts:
    """Adds controller + safety layer wired to ``station`` (a system in ``builder``).

    Args:
        plant, tip_frame: the control plant (FR3 + probe) for Jacobians; default
            ``MakeControlPlant(scenario.robot, scenario.probe)``.
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
        plant, tip_frame = MakeControlPlant(scenario.robot, scenario.probe)
    S = station.GetOutputPort
    # One tip-kinematics object (memoised on q) shared by the IK and the safety layer: one
    # forward kinematics and one Jacobian per control period.
    kinematics = TipKinematics(plant, tip_frame)
    orientation = builder.AddNamedSystem("orientation_alignment", OrientationAlignment(cfg))
    force = builder.AddNamedSystem("force_pd", ForcePD(cfg))
    position = builder.AddNamedSystem("position_p", PositionP(cfg))
    ik = builder.AddNamedSystem(
        "null_space_diff_ik",
        NullSpaceDiffIK(
            plant,
            tip_frame,
            cfg,
            use_null_space,
            kinematics=kinematics,
            # The hardware's command guard limits the command's acceleration; the IK sends
            # no joint towards its limit faster than that can stop (on every station, so
            # the simulation moves as the robot will).
            braking_acceleration=scenario.hardware_interface.max_joint_acceleration,
        ),
    )
    safety = builder.AddNamedSystem(
        "safety", SafetyLayer(plant, tip_frame, scfg, cfg.rate_hz, kinematics=kinematics)
    )

    for sys in (orientation, force, position):
        builder.Connect(S("X_BP"), sys.GetInputPort("X_BP"))
    builder.Connect(S("probe_force"), force.GetInputPort("probe_force"))
    builder.Connect(S("joint_position"), ik.GetInputPort("joint_position"))
    builder.Connect(orientation.GetOutputPort("omega_BP"), ik.GetInputPort("omega_BP"))
    builder.Connect(force.GetOutputPort("v_force"), ik.GetInputPort("v_force"))
    builder.Connect(position.GetOutputPort("v_position"), ik.GetInputPort("v_position"))

    builder.Connect(
        ik.GetOutputPort("joint_velocity_desired"), safety.GetInputPort("joint_velocity_desired")
    )
    for name in ("joint_position", "joint_velocity", "X_BP", "probe_force"):
        builder.Connect(S(name), safety.GetInputPort(name))
    segmented = False
    if image_port is None:
        # Watch the frames the controller actually uses: the segmenter's mask (stamped with
        # its source frame's time) if there is one, else the station's ultrasound images.
        if segmenter is not None and segmenter.HasOutputPort("kidney_mask"):
            image_port = segmenter.GetOutputPort("kidney_mask")
            segmented = True
        elif station.HasOutputPort("us_image"):
            image_port = S("us_image")
    if image_port is not None:
        stamp = builder.AddNamedSystem("image_stamp", FrameTime(image_port.Allocate()))
        builder.Connect(image_port, stamp.get_input_port())
        builder.Connect(stamp.get_output_port(), safety.GetInputPort("image_time"))
    if segmented and station.HasOutputPort("us_image"):
        # The station's newest frame too: a stale segmentation of a fresh video is
        # perception falling behind (an overloaded computer), not a stopped video.
        video = builder.AddNamedSystem("frame_stamp", FrameTime(S("us_image").Allocate()))
        builder.Connect(S("us_image"), video.get_input_port())
        builder.Connect(video.get_output_port(), safety.GetInputPort("frame_time"))

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
        builder.Connect(
            supervisor.GetOutputPort("segmentation_required"),
            safety.GetInputPort("segmentation_required"),
        )
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
        builder.Connect(
            safety.GetOutputPort("joint_velocity_command"),
            station.GetInputPort("joint_velocity_command"),
        )
    return ControllerParts(orientation, force, position, ik, safety, supervisor)
