"""The scan diagram (seed Fig. 2) on ANY station: only the ports both stations export.

    station.us_image -> Segmenter -> PointCloudAccumulator (while EXPLOREing) -> IcpLocalizer
    IcpLocalizer -> RegisteredKidneySurface -> Segmenter (the template's section: its prior)
    station.{joint_position, joint_velocity, X_BP, probe_force} -> controller + safety
    ScanSupervisor phases: APPROACH -> EXPLORE -> LOCALIZE -> TRANSIT -> PIVOT -> DONE | ABORT
    KidneyTrackingMonitor (after LOCALIZE), ScanRecorder (every frame), loggers

The station is built by the caller (``drake_rus.stations.MakeStation``, or a wrapped one).
Optional station ports are used when present: ``label_image`` (the oracle segmenter reads
it; simulation only) and the input ``breath_prompt`` (the simulated patient hears the
breath-hold prompts). Respiration is sensed from the probe's pose and contact force
(``respiration.mode``, ``AddRespiration``); the scan reads no simulation truth, which is
attached separately by ``scan.truth``.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import DiagramBuilder, EventStatus, LeafSystem
from pydrake.systems.primitives import ConstantValueSource, LogVectorOutput

from drake_rus.config_schema import ScenarioError
from drake_rus.control.diagram import AddController
from drake_rus.control.respiration_systems import (
    BreathHoldProtocol,
    BreathPrompter,
    RespirationEstimator,
)
from drake_rus.control.supervisor import Phase, PivotModel
from drake_rus.executor import MakeExecutor
from drake_rus.imaging.frames import BoundaryPixels, UsFrame
from drake_rus.imaging.systems import PointCloudAccumulator, Segmenter
from drake_rus.localization.localize import IcpLocalizer, body_directions_B
from drake_rus.localization.tracking import KidneyTrackingMonitor, RegisteredKidneySurface

__all__ = [
    "BuildScanDiagram",
    "ScanHandles",
    "PhaseIs",
    "And2",
    "ScanRecorder",
    "ScanTerminator",
    "FrameRecord",
    "LOG_PERIOD",
]

# Period (s) of the scan's loggers (phase, force, a_des, manipulability, q).
LOG_PERIOD = 0.02


class PhaseIs(LeafSystem):
    """1-vector output ``value``: 1.0 while the input ``phase`` equals ``phase_value``."""

    def __init__(self, phase_value: int):
        super().__init__()
        self._value = int(phase_value)
        self.DeclareVectorInputPort("phase", 1)
        self.DeclareVectorOutputPort(
            "value",
            1,
            lambda c, o: o.SetAtIndex(
                0, float(int(round(self.get_input_port(0).Eval(c)[0])) == self._value)
            ),
        )


class And2(LeafSystem):
    """Output ``value`` (1-vector): 1.0 when both inputs ``a`` and ``b`` are > 0.5."""

    def __init__(self):
        super().__init__()
        a = self.DeclareVectorInputPort("a", 1)
        b = self.DeclareVectorInputPort("b", 1)
        self.DeclareVectorOutputPort(
            "value",
            1,
            lambda c, o: o.SetAtIndex(0, float(a.Eval(c)[0] > 0.5 and b.Eval(c)[0] > 0.5)),
        )


class ScanTerminator(LeafSystem):
    """Ends the simulation once the scan has ended: a periodic publish event (every
    ``period`` s, the controller's) that returns ReachedTermination while the input ``phase``
    is one of ``terminal_phases`` and ``enabled`` is True. This replaces a simulator monitor
    that called Python after every plant step. Set ``enabled = False`` to simulate on after
    the end (e.g. to let the robot settle)."""

    def __init__(self, terminal_phases, period: float):
        super().__init__()
        self._terminal = {int(p) for p in terminal_phases}
        self.enabled = True
        self._phase = self.DeclareVectorInputPort("phase", 1)
        self.DeclarePeriodicPublishEvent(period, 0.0, self._check)

    def _check(self, context):
        if self.enabled and int(round(self._phase.Eval(context)[0])) in self._terminal:
            return EventStatus.ReachedTermination(self, "scan finished")
        return EventStatus.DidNothing()


@dataclasses.dataclass
class FrameRecord:
    """One acquired frame as the scan saw it: capture time (s), frame index, supervisor
    phase, probe pose X_BP, kidney visible, filtered contact force F_z (N), and the index of
    the frame that ``visible`` was segmented from (the latest segmentation ready when the
    frame was recorded: this frame's, or an earlier one's while perception runs beside the
    loop; -1 before the first)."""

    time: float
    frame_index: int
    phase: int
    X_BP: RigidTransform
    visible: bool
    force: float
    mask_frame_index: int = -1


class ScanRecorder(LeafSystem):
    """Records every acquired frame (time, pose, phase, visibility, force) and keeps a few
    grey images and masks of the PIVOT phase for the report. A publish-only observer.

    Inputs ``us_image`` and ``kidney_mask`` (UsFrame), ``boundary_pixels``
    (BoundaryPixels: the segmentation's boundary the point cloud takes, with its frame's
    X_BP), ``phase``, ``kidney_visible``, ``contact_force`` (1-vectors; N for the force),
    optional ``motion_allowed`` (1-vector 0/1: the breath-hold protocol's or the gating's
    permission; unconnected: always). Keeps the boundary of every PIVOT frame taken while
    motion was allowed (``pivot_boundaries``) for the verdict's ``pivot_residual`` check:
    the registration's respiratory phase, as the explored cloud takes only such frames."""

    def __init__(self, frame_rate_hz: float, keep_every: int = 10, keep_max: int = 40):
        super().__init__()
        empty = UsFrame(np.zeros((1, 1), np.uint8))
        self._us = self.DeclareAbstractInputPort("us_image", AbstractValue.Make(empty))
        self._mask = self.DeclareAbstractInputPort("kidney_mask", AbstractValue.Make(empty))
        self._boundary = self.DeclareAbstractInputPort(
            "boundary_pixels", AbstractValue.Make(BoundaryPixels(np.zeros((0, 2))))
        )
        self._phase = self.DeclareVectorInputPort("phase", 1)
        self._visible = self.DeclareVectorInputPort("kidney_visible", 1)
        self._force = self.DeclareVectorInputPort("contact_force", 1)
        self._allowed = self.DeclareVectorInputPort("motion_allowed", 1)
        period = 1.0 / frame_rate_hz
        self.DeclarePeriodicPublishEvent(period, 0.5 * period, self._record)
        self.frames: list[FrameRecord] = []
        self.images: list[tuple] = []
        #: Kidney masks (bool, rows x cols) by frame index, of the phases ``keep_masks`` asks.
        self.sweep_masks: dict[int, np.ndarray] = {}
        #: The segmentation's boundary (BoundaryPixels, with its frame's index and X_BP) of
        #: every PIVOT frame that had one (a few kB a frame).
        self.pivot_boundaries: list[BoundaryPixels] = []
        self._last_boundary = -1
        self._mask_phases: frozenset = frozenset()
        #: With ``keep_frames``: (us_image UsFrame, kidney_mask UsFrame, phase, visible) of
        #: every frame (the frames are immutable: kept, not copied).
        self.kept_frames: list[tuple] = []
        self._keep_all = False
        self._keep_every, self._keep_max = keep_every, keep_max
        self._last_index = -1
        self._pivot_count = 0

    def keep_masks(self, phases) -> None:
        """Also keep the kidney mask of every frame acquired in one of ``phases`` (Phase
        values) in ``sweep_masks`` (about 64 kB a frame), e.g. for a volume reconstruction."""
        self._mask_phases = frozenset(int(p) for p in phases)

    def keep_frames(self) -> None:
        """Also keep every frame's grey image and kidney mask with its phase and visible flag
        (``kept_frames``, about 128 kB a frame), e.g. for ``scan --save-frames``."""
        self._keep_all = True

    def _record(self, context):
        us = self._us.Eval(context)
        if us.frame_index < 0 or us.frame_index == self._last_index:
            return EventStatus.DidNothing()
        self._last_index = us.frame_index
        phase = int(round(self._phase.Eval(context)[0]))
        visible = bool(self._visible.Eval(context)[0] > 0.5)
        self.frames.append(
            FrameRecord(
                us.time,
                us.frame_index,
                phase,
                RigidTransform(us.X_BP),
                visible,
                float(self._force.Eval(context)[0]),
                self._mask.Eval(context).frame_index,
            )
        )
        if phase in self._mask_phases:
            self.sweep_masks[us.frame_index] = np.array(self._mask.Eval(context).image, bool)
        if self._keep_all:
            self.kept_frames.append((us, self._mask.Eval(context), phase, visible))
        if phase == Phase.PIVOT:
            boundary = self._boundary.Eval(context)
            # A frame taken while the patient breathes shows the kidney displaced from where
            # the registration (one respiratory phase) put it: not a view to judge it by.
            allowed = not self._allowed.HasValue(context) or self._allowed.Eval(context)[0] > 0.5
            fresh = boundary.frame_index not in (-1, self._last_boundary)
            if fresh and allowed and len(boundary.pixels):
                self._last_boundary = boundary.frame_index
                self.pivot_boundaries.append(boundary)
            if self._pivot_count % self._keep_every == 0 and len(self.images) < self._keep_max:
                mask = self._mask.Eval(context)
                self.images.append((us.time, np.array(us.image), np.array(mask.image)))
            self._pivot_count += 1
        return EventStatus.Succeeded()


@dataclasses.dataclass
class ScanHandles:
    """The systems of a scan diagram, for reading their state after (or during) a run."""

    station: object
    segmenter: Segmenter
    accumulator: PointCloudAccumulator
    localizer: IcpLocalizer
    supervisor: object
    recorder: ScanRecorder
    parts: object  # ControllerParts
    tracking: KidneyTrackingMonitor
    logs: dict  # name -> VectorLogSink
    terminator: ScanTerminator | None = None
    # Respiration (``respiration.mode`` not "none"): estimator, protocol, prompter.
    respiration: RespirationEstimator | None = None
    protocol: BreathHoldProtocol | None = None
    prompter: BreathPrompter | None = None
    executor: object = None  # where perception runs (drake_rus.executor)

    def __getitem__(self, name):  # handles["supervisor"] reads like a dict
        return getattr(self, name)


def PivotModelFor(template, imaging) -> PivotModel:
    """The supervisor's pivot model: the registration template's points in K (m) and the
    fan of the probe at the scan's depth (m, rad), with half the elevational beam width as
    the image slab and the segmenter's visibility threshold (m^2) as the smallest section
    that puts the kidney in view."""
    return PivotModel(
        points_K=np.asarray(template.points, float),
        probe_radius=imaging.probe_radius,
        half_angle=math.radians(imaging.field_of_view_deg) / 2,
        depth=imaging.depth,
        slab_half_width=imaging.elevation_width / 2,
        min_section_area=imaging.min_kidney_area,
    )


def BuildScanDiagram(
    scenario, station, template, *, builder: DiagramBuilder | None = None, executor=None
):
    """Adds ``station`` (any station) and the scan around it to ``builder`` (default: a new
    one). Returns ``(builder, ScanHandles)``; the caller may add observers (simulation
    truth) before ``builder.Build()``. ``executor`` (``drake_rus.executor``): where the
    segmentation and the fits run (default: ``MakeExecutor(scenario.perception,
    paced=False)``, inline for ``auto``; the caller closes it, ``handles.executor``)."""
    builder = builder or DiagramBuilder()
    if executor is None:
        executor = MakeExecutor(scenario.perception, paced=False)
    # A template of the other side's kidneys is mirrored (RegistrationTemplate.for_side).
    template = template.for_side(scenario.patient.side)
    builder.AddNamedSystem("station", station)
    segmenter = builder.AddNamedSystem(
        "segmenter",
        Segmenter(
            scenario.imaging, executor=executor, poll_period=1.0 / scenario.controller.rate_hz
        ),
    )
    builder.Connect(station.GetOutputPort("us_image"), segmenter.GetInputPort("us_image"))
    if scenario.imaging.segmenter == "oracle":
        if not station.HasOutputPort("label_image"):
            raise ScenarioError(
                "field 'imaging.segmenter': 'oracle' reads the simulated "
                "station's label_image, which this station does not have; "
                "use 'onnx' or 'classical'"
            )
        builder.Connect(station.GetOutputPort("label_image"), segmenter.GetInputPort("label_image"))
    accumulator = builder.AddNamedSystem(
        "point_cloud_accumulator", PointCloudAccumulator(scenario.imaging)
    )
    builder.Connect(
        segmenter.GetOutputPort("boundary_pixels"), accumulator.GetInputPort("boundary_pixels")
    )
    X_BPt = scenario.patient.X_BPt.GetDeterministicValue()
    superior_B, lateral_B = body_directions_B(
        X_BPt, scenario.patient.side, scenario.patient.posture
    )
    localizer = builder.AddNamedSystem(
        "icp_localizer",
        IcpLocalizer(
            template,
            scenario.localization,
            superior_B,
            lateral_B,
            localize_phase=int(Phase.LOCALIZE),
            rate_hz=scenario.imaging.frame_rate_hz,
            explore_phase=int(Phase.EXPLORE),
            kidney_length=scenario.controller.kidney_length,
            executor=executor,
        ),
    )
    builder.Connect(accumulator.GetOutputPort("point_cloud"), localizer.GetInputPort("point_cloud"))
    # After localization, the registered template's section in each frame is the
    # segmenter's prior (the kidney found again after a pivot leg's end or any loss).
    surface = builder.AddNamedSystem("registered_surface", RegisteredKidneySurface(template))
    builder.Connect(localizer.GetOutputPort("localization"), surface.GetInputPort("localization"))
    builder.Connect(
        surface.GetOutputPort("kidney_surface"), segmenter.GetInputPort("kidney_surface")
    )
    parts = AddController(
        builder,
        station,
        scenario,
        segmenter=segmenter,
        kidney_pose_port=localizer.GetOutputPort("X_BK"),
        localization_ready_port=localizer.GetOutputPort("localization_ready"),
    )
    supervisor = parts.supervisor
    phase = supervisor.GetOutputPort("phase")
    builder.Connect(phase, localizer.GetInputPort("phase"))
    builder.Connect(
        supervisor.GetOutputPort("localization_round"), localizer.GetInputPort("localization_round")
    )
    builder.Connect(supervisor.GetOutputPort("cloud_reset"), accumulator.GetInputPort("reset"))
    builder.Connect(
        localizer.GetOutputPort("localization_error"), supervisor.GetInputPort("localization_error")
    )
    builder.Connect(
        localizer.GetOutputPort("exploration_sufficient"),
        supervisor.GetInputPort("exploration_sufficient"),
    )
    builder.Connect(
        localizer.GetOutputPort("kidney_length_estimate"),
        supervisor.GetInputPort("kidney_length_estimate"),
    )
    # The template in K and the probe's fan: what the predicted_end pivot strategy predicts
    # the kidney's ends from, and what tells an expected absence of the kidney from a loss
    # in PIVOT (supervisor.absence_expected).
    model = builder.AddNamedSystem(
        "pivot_model",
        ConstantValueSource(AbstractValue.Make(PivotModelFor(template, scenario.imaging))),
    )
    builder.Connect(model.get_output_port(0), supervisor.GetInputPort("pivot_model"))
    exploring = builder.AddNamedSystem("exploring", PhaseIs(Phase.EXPLORE))
    builder.Connect(phase, exploring.get_input_port(0))
    enable = exploring.get_output_port(0)
    respiration = AddRespiration(builder, scenario, station, parts, localizer)
    hold = None if respiration is None else respiration[1].GetOutputPort("motion_allowed")
    if hold is not None:
        # Exploration frames enter P_local only while the scan may move (a sensed hold, or
        # end-expiration when gated): one respiratory phase.
        gate = builder.AddNamedSystem("breath_hold_gate", And2())
        builder.Connect(enable, gate.GetInputPort("a"))
        builder.Connect(hold, gate.GetInputPort("b"))
        enable = gate.GetOutputPort("value")
    builder.Connect(enable, accumulator.GetInputPort("enable"))
    tracking = builder.AddNamedSystem(
        "kidney_tracking_monitor",
        KidneyTrackingMonitor(
            template,
            scenario.localization,
            scenario.imaging,
            check_phases=[int(Phase.TRANSIT), int(Phase.PIVOT)],
            executor=executor,
            # Gated free breathing: the breath itself slides the skin under the probe at
            # the windows' edges (1.6 N on test:5), so a slip is no sign of a shift there.
            slip_check=scenario.respiration.mode != "gated",
            # The second look (controller.second_look): the pivot's end awaits the
            # verdict's pivot_residual rule on the pivot's view so far.
            pivot_view=(
                (
                    scenario.verdict.pivot_residual_percentile,
                    scenario.verdict.pivot_residual_excess,
                    scenario.respiration.mode,
                )
                if scenario.controller.second_look
                else None
            ),
            pivot_phase=int(Phase.PIVOT),
        ),
    )
    builder.Connect(
        segmenter.GetOutputPort("boundary_pixels"), tracking.GetInputPort("boundary_pixels")
    )
    builder.Connect(localizer.GetOutputPort("localization"), tracking.GetInputPort("localization"))
    builder.Connect(phase, tracking.GetInputPort("phase"))
    # The probe's force: the patient sliding under it (localization/tracking.slip_update).
    builder.Connect(station.GetOutputPort("probe_force"), tracking.GetInputPort("probe_force"))
    builder.Connect(
        tracking.GetOutputPort("tracking_error"), supervisor.GetInputPort("tracking_error")
    )
    builder.Connect(
        accumulator.GetOutputPort("point_cloud"), tracking.GetInputPort("partial_cloud")
    )
    if scenario.controller.second_look and scenario.localization.tracking_check:
        builder.Connect(tracking.GetOutputPort("pivot_view"), supervisor.GetInputPort("pivot_view"))
    if hold is not None:
        builder.Connect(hold, tracking.GetInputPort("motion_allowed"))

    recorder = builder.AddNamedSystem("scan_recorder", ScanRecorder(scenario.imaging.frame_rate_hz))
    builder.Connect(station.GetOutputPort("us_image"), recorder.GetInputPort("us_image"))
    builder.Connect(segmenter.GetOutputPort("kidney_mask"), recorder.GetInputPort("kidney_mask"))
    builder.Connect(
        segmenter.GetOutputPort("boundary_pixels"), recorder.GetInputPort("boundary_pixels")
    )
    if hold is not None:
        builder.Connect(hold, recorder.GetInputPort("motion_allowed"))
    builder.Connect(phase, recorder.GetInputPort("phase"))
    builder.Connect(
        segmenter.GetOutputPort("kidney_visible"), recorder.GetInputPort("kidney_visible")
    )
    builder.Connect(parts.force.GetOutputPort("F_filtered"), recorder.GetInputPort("contact_force"))

    logs = {
        "phase": LogVectorOutput(phase, builder, LOG_PERIOD),
        "force": LogVectorOutput(parts.force.GetOutputPort("F_filtered"), builder, LOG_PERIOD),
        "a_des": LogVectorOutput(supervisor.GetOutputPort("a_des"), builder, LOG_PERIOD),
        "manipulability": LogVectorOutput(
            parts.ik.GetOutputPort("manipulability"), builder, LOG_PERIOD
        ),
        "q": LogVectorOutput(station.GetOutputPort("joint_position"), builder, LOG_PERIOD),
    }
    if respiration is not None:
        estimator, protocol, _ = respiration
        for name, port in (
            ("motion_allowed", protocol.GetOutputPort("motion_allowed")),
            ("breath_prompt", protocol.GetOutputPort("breath_prompt")),
            ("respiration_state", estimator.GetOutputPort("respiration_state")),
            ("probe_moving", estimator.GetOutputPort("probe_moving")),
        ):
            logs[name] = LogVectorOutput(port, builder, LOG_PERIOD)
    terminator = builder.AddNamedSystem(
        "scan_terminator",
        ScanTerminator((Phase.DONE, Phase.ABORT), 1.0 / scenario.controller.rate_hz),
    )
    builder.Connect(phase, terminator.get_input_port(0))
    return builder, ScanHandles(
        station=station,
        segmenter=segmenter,
        accumulator=accumulator,
        localizer=localizer,
        supervisor=supervisor,
        recorder=recorder,
        parts=parts,
        tracking=tracking,
        logs=logs,
        terminator=terminator,
        respiration=None if respiration is None else respiration[0],
        protocol=None if respiration is None else respiration[1],
        prompter=None if respiration is None else respiration[2],
        executor=executor,
    )


def AddRespiration(builder, scenario, station, parts, localizer):
    """With ``respiration.mode`` "breath_hold" or "gated": the respiration estimator (on the
    probe pose and the filtered contact force: any station), the protocol (the supervisor's
    motion_allowed and breathing_error) and the prompter (console, speech, and the
    simulated patient's ``breath_prompt`` when the station has one). Returns (estimator,
    protocol, prompter) or None."""
    cfg = scenario.respiration
    if cfg.mode == "none":
        return None
    period = 1.0 / scenario.controller.rate_hz
    supervisor = parts.supervisor
    estimator = builder.AddNamedSystem(
        "respiration_estimator",
        RespirationEstimator(cfg, scenario.controller.desired_force, period),
    )
    builder.Connect(station.GetOutputPort("X_BP"), estimator.GetInputPort("X_BP"))
    builder.Connect(
        parts.force.GetOutputPort("F_filtered"), estimator.GetInputPort("contact_force")
    )
    # The probe's own motion (the scan's commands): the wall's reading moves with it.
    builder.Connect(parts.position.GetOutputPort("v_position"), estimator.GetInputPort("v_command"))
    builder.Connect(
        parts.orientation.GetOutputPort("omega_BP"), estimator.GetInputPort("omega_command")
    )
    protocol = builder.AddNamedSystem("breath_hold_protocol", BreathHoldProtocol(cfg, period))
    builder.Connect(supervisor.GetOutputPort("phase"), protocol.GetInputPort("phase"))
    builder.Connect(
        localizer.GetOutputPort("localization_ready"), protocol.GetInputPort("localization_ready")
    )
    for name in ("respiration_state", "respiration_since"):
        builder.Connect(estimator.GetOutputPort(name), protocol.GetInputPort(name))
    builder.Connect(
        protocol.GetOutputPort("motion_allowed"), supervisor.GetInputPort("motion_allowed")
    )
    builder.Connect(
        protocol.GetOutputPort("breathing_error"), supervisor.GetInputPort("breathing_error")
    )
    prompter = builder.AddNamedSystem(
        "breath_prompter", BreathPrompter(period, speak=cfg.speak and scenario.hardware)
    )
    builder.Connect(protocol.GetOutputPort("breath_prompt"), prompter.GetInputPort("breath_prompt"))
    if station.HasInputPort("breath_prompt"):
        # The simulated patient hears the prompt (a real one hears the operator or the voice).
        builder.Connect(
            protocol.GetOutputPort("breath_prompt"), station.GetInputPort("breath_prompt")
        )
    return estimator, protocol, prompter
