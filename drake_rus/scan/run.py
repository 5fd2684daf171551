"""Running the scan: the start pose, the simulation loop, monitors, and the result.

``RunScan(scenario, patient, template)`` plans the start pose over the patient's kidney (the
stand-in for the paper's manual probe placement), builds the station with ``make_station``
(default ``drake_rus.stations.MakeStation``; a caller may pass a wrapped station, e.g. with
faults), the scan diagram and the simulation-truth observer, runs it until DONE, ABORT or
``max_sim_time``, checks a DONE result (``scan.verdict``: INCOMPLETE when a check fails) and
returns a :class:`ScanResult`. ``monitors`` watch every simulator step.
"""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import math
import sys
import time
from typing import Callable, Sequence

import numpy as np
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import EventStatus

from drake_rus import interrupts
from drake_rus.control.safety import StopReason
from drake_rus.control.supervisor import Phase
from drake_rus.executor import MakeExecutor
from drake_rus.hardware.station import HardwareSession
from drake_rus.imaging.annotated import SavedFrame
from drake_rus.localization.localize import fitted_shape_K
from drake_rus.pacing import GcPauses, RealtimePacer, gc_statistics, load_average
from drake_rus.patient_body import PatientMotionFor
from drake_rus.progress import AdvanceWithProgress
from drake_rus.robot import IkError, MakeControlPlant, SolveTipPose
from drake_rus.scan.diagram import BuildScanDiagram, ScanHandles
from drake_rus.scan.planning import DrawStartPlan, PlanStart, exploration_start
from drake_rus.scan.truth import AttachSimulationTruth, SimulationTruth
from drake_rus.scan.verdict import JudgeScan, Verdict
from drake_rus.stations import MakeStation

__all__ = [
    "RunScan",
    "ExpectedScanTime",
    "PrepareScenario",
    "ScanResult",
    "ScanMonitor",
    "CollectScanResult",
    "TERMINAL_PHASES",
]

TERMINAL_PHASES = (Phase.DONE, Phase.ABORT)


def ExpectedScanTime(scenario) -> float:
    """About how long (simulated s) a scan with ``scenario`` takes when all goes well, for
    the progress bar: landing, the exploration (ER x L_m at v_scan), LOCALIZE, TRANSIT and
    a pivot through about 1 rad in all (out to both sides of r3*); a line sweep (``sweep:
    line``) its longest travel, a given pivot pose no exploration or localization."""
    c = scenario.controller
    if getattr(c, "sweep", "pivot") == "line":
        return 1.5 + c.line_sweep_max_travel / c.scan_speed
    if getattr(c, "pivot_pose", None):
        return 1.5 + 2.0 + 1.0 / c.pivot_rate
    explore = c.exploration_ratio * c.kidney_length / c.scan_speed
    return 1.5 + explore + c.localize_hold_time + 0.5 + 2.0 + 1.0 / c.pivot_rate


class ScanMonitor:
    """Watches a running scan at every simulator step (override what you need).

    ``attach(diagram, handles, root_context)`` before the run; ``observe(root_context)`` after
    every step (it must not change the state); ``finish(root_context)`` once the run (and any
    settling time) is over."""

    def attach(self, diagram, handles: ScanHandles, root_context) -> None:
        pass

    def observe(self, root_context) -> None:
        pass

    def finish(self, root_context) -> None:
        pass


@dataclasses.dataclass
class ScanResult:
    """A finished scan: outcome, timing, what was recorded, and the truth if simulated."""

    # "DONE", "INCOMPLETE" (ran to its end but failed a check of its result, ``checks``),
    # "ABORT", "TIMEOUT" or "INTERRUPTED" (a signal: Ctrl-C or SIGTERM)
    status: str
    reason: str
    patient: str
    sim_s: float
    wall_s: float
    phases: list  # [(name, start s, end s)]
    frames: list  # FrameRecord per acquired frame
    images: list  # (time, grey, mask) of some PIVOT frames
    partial_cloud_B: np.ndarray
    localization: object  # LocalizationOutcome
    X_BK_estimated: RigidTransform | None
    registered_template_B: np.ndarray | None
    logs: dict  # name -> (times, data)
    safety_events: list
    scenario: object
    truth: SimulationTruth | None = None
    # Kidney tracking checks after localization: ((time s, apparent drift m), ...).
    tracking_drift: tuple = ()
    # The start planner's choice (simulation; None for the vertical planner or hardware).
    start_plan: object = None
    # Process CPU time (s) of the simulation loop (wall_s's counterpart, robust to other jobs
    # on the machine; benchmarks report sim_s / cpu_s).
    cpu_s: float = float("nan")
    # Kidney masks (bool, rows x cols) by frame index of the EXPLORE and PIVOT frames, when
    # RunScan was asked to keep them (keep_sweep_masks); else empty.
    sweep_masks: dict = dataclasses.field(default_factory=dict)
    # The segmentation's boundary (imaging.frames.BoundaryPixels: pixels, frame index,
    # X_BP) of every PIVOT frame that had one: the verdict's pivot_residual check.
    pivot_boundaries: list = dataclasses.field(default_factory=list)
    # The localizer's kidney-length estimates during EXPLORE: ((time s, travel m, length m
    # or NaN), ...); empty without length estimation.
    length_checks: tuple = ()
    # The supervisor's account of the sweep's ends: tilt angles (rad, from r3*) where each
    # pivot leg ended and why each end was declared (SupervisorState.sweep_end_causes).
    pivot_limits: tuple = ()
    sweep_end_causes: tuple = ()
    # The slides at the tilt cap ((leg, slide m), ...; SupervisorState.cap_slides).
    cap_slides: tuple = ()
    # The second look (controller.second_look): whether the latest registration came from
    # a whole-kidney exploration, and why it was taken ("" none was).
    whole_kidney_exploration: bool = False
    second_look_reason: str = ""
    # The scan's own checks of its result before it may say DONE (scan/verdict.py):
    # a list of Check; empty when the scan did not reach DONE.
    checks: list = dataclasses.field(default_factory=list)
    # Every frame's grey image and kidney mask (imaging.annotated.SavedFrame), when RunScan
    # was asked to keep them (keep_frames); else empty.
    saved_frames: list = dataclasses.field(default_factory=list)
    # The supervisor's events ((time s, phase name, message), ...): every phase change and
    # why, re-localizations included.
    events: tuple = ()
    # The respiration systems' record (``_respiration_record``; empty with mode none).
    respiration: dict = dataclasses.field(default_factory=dict)
    # Exploration frames whose section jumped from its neighbours' and whose points the
    # partial cloud left out (PointCloud.frames_inconsistent).
    cloud_frames_inconsistent: int = 0
    # A live run's loop timing (drake_rus.pacing.loop_statistics: per-tick compute time and lag,
    # slips, load average) and its per-tick trace (t, compute, lag arrays, s); None when
    # the run was not paced at real time.
    loop_timing: dict | None = None
    loop_trace: dict | None = None
    # Where perception ran ("inline" or "worker") and, per kind of job, its count, compute
    # time and latency (drake_rus.executor.Executor.statistics); frames skipped.
    perception: dict = dataclasses.field(default_factory=dict)

    @property
    def X_BK_true(self) -> RigidTransform | None:
        return None if self.truth is None else self.truth.X_BK


def _can_reach(plant, tip):
    def reachable(X_BP: RigidTransform) -> bool:
        try:
            SolveTipPose(plant, tip, X_BP)
        except IkError:
            return False
        return True

    return reachable


def PlacementPose(scenario) -> RigidTransform:
    """Where the simulated operator sees the patient when placing the probe: X_BPt, moved
    to the breath-hold's level when the scan holds the breath in (``respiration.mode``
    breath_hold, ``hold_level`` in: the sonographer places the probe during a hold, where
    the kidney then is). Simulation only (the stand-in for the operator's placement)."""
    X_BPt = scenario.patient.X_BPt.GetDeterministicValue()
    breathing = scenario.patient.motion.breathing
    r = scenario.respiration
    if not (breathing.enabled and r.mode == "breath_hold" and r.hold_level == "in"):
        return X_BPt
    offset = PatientMotionFor(scenario).offset_at(breathing.hold_depth, 0.0)
    offset = offset - PatientMotionFor(scenario).offset_at(0.0, 0.0)  # no shift
    return RigidTransform(offset) @ X_BPt


def PrepareScenario(scenario, patient, start_fraction: float | None = None):
    """The scenario set up for the start of a scan on ``patient`` (simulation's stand-in for
    the operator's placement, ``scenario.start``): the robot's initial joints put the probe
    over the planned start, and with the window planner ``imaging.depth`` follows the chosen
    depth preset. ``start_fraction`` overrides ``start.start_fraction``. Returns
    ``(scenario, X_start, plan)``; ``plan`` is the :class:`StartPlan` (None for the vertical
    planner). Raises StartPlanError or IkError with a clear message when no start works."""
    X_BPt = PlacementPose(scenario)
    plant, tip = MakeControlPlant(scenario.robot, scenario.probe)
    sf = scenario.start.start_fraction if start_fraction is None else start_fraction
    plan = None
    if scenario.start.planner == "vertical":
        X_start = exploration_start(
            patient,
            X_BPt,
            scan_direction=scenario.controller.scan_direction,
            start_fraction=sf,
            hover=scenario.start.hover,
        )
    else:
        plan = PlanStart(
            patient,
            X_BPt,
            scenario.imaging,
            scenario.start,
            reachable=_can_reach(plant, tip),
            seed=scenario.random_seed,
            scan_direction=scenario.controller.scan_direction,
            start_fraction=sf,
            exploration_ratio=scenario.controller.exploration_ratio,
        )
        X_start = plan.X_start
        scenario = dataclasses.replace(
            scenario, imaging=dataclasses.replace(scenario.imaging, depth=plan.depth_preset)
        )
    # The start posture closest to the scenario's initial joint positions (the arm's
    # redundancy at a fixed probe pose: the elbow's split), so the field means what it says.
    q0 = SolveTipPose(plant, tip, X_start, q_nominal=scenario.robot.initial_joint_positions)
    robot = dataclasses.replace(scenario.robot, initial_joint_positions=[float(v) for v in q0])
    return dataclasses.replace(scenario, robot=robot), X_start, plan


def _phase_intervals(times, phases, end_time: float, final_phase: str) -> list:
    """[(name, start, end)] from a phase log; closes with the final phase."""
    out = []
    start = 0
    for k in range(1, len(phases) + 1):
        if k == len(phases) or phases[k] != phases[start]:
            out.append(
                (
                    Phase(phases[start]).name,
                    float(times[start]),
                    float(times[k] if k < len(times) else end_time),
                )
            )
            start = k
    if not out or out[-1][0] != final_phase:
        out.append((final_phase, end_time, end_time))
    return out


def CollectScanResult(
    scenario,
    patient_name: str,
    template,
    handles: ScanHandles,
    truth: SimulationTruth | None,
    root_context,
    wall: float,
    end_time: float | None = None,
) -> ScanResult:
    """The ScanResult of a finished run; ``end_time`` (s): when the scan proper ended, if the
    simulator ran on after it (default: the context's time)."""
    h = handles
    now = root_context.get_time()
    t_end = now if end_time is None else end_time
    state = h.supervisor.GetOutputPort("supervisor_state").Eval(
        h.supervisor.GetMyContextFromRoot(root_context)
    )
    phase = Phase(int(state.phase)).name
    status = phase if phase in ("DONE", "ABORT") else "TIMEOUT"
    reason = state.events[-1][2] if status == "ABORT" and state.events else ""
    if status == "TIMEOUT":
        reason = f"still in {phase} after {t_end:.1f} s of simulated time"
    safety = h.parts.safety
    events = list(
        safety.GetOutputPort("safety_events").Eval(safety.GetMyContextFromRoot(root_context))
    )
    if status == "ABORT" and reason == "safety stop":
        # The safety layer stopped on its own: say why (the first stop is the cause).
        for e in events[:1]:
            if e.reason != StopReason.SUPERVISOR_ABORT:
                reason = f"safety stop: {e.reason}" + (f" ({e.detail})" if e.detail else "")
    logs = {}
    for name, logger in h.logs.items():
        log = logger.FindLog(root_context)
        logs[name] = (log.sample_times().copy(), log.data().copy())
    if truth is not None and truth.force_log is not None:
        log = truth.force_log.FindLog(root_context)
        logs["force_true"] = (log.sample_times().copy(), log.data().copy())
    for name, logger in ({} if truth is None else truth.motion_logs).items():
        log = logger.FindLog(root_context)
        logs[name] = (log.sample_times().copy(), log.data().copy())
    t, ph = logs["phase"][0], logs["phase"][1][0].round().astype(int)
    phases = _phase_intervals(t, ph, now, phase)
    outcome = h.localizer.GetOutputPort("localization").Eval(
        h.localizer.GetMyContextFromRoot(root_context)
    )
    cloud = h.accumulator.GetOutputPort("point_cloud").Eval(
        h.accumulator.GetMyContextFromRoot(root_context)
    )
    X_BK_est, registered = None, None
    if outcome.result is not None:
        X_BK_est = outcome.result.X_BK
        shape = fitted_shape_K(template, outcome.result)
        registered = X_BK_est.multiply(shape.T).T
    return ScanResult(
        status=status,
        reason=reason,
        patient=patient_name,
        sim_s=now,
        wall_s=wall,
        phases=phases,
        frames=list(h.recorder.frames),
        images=list(h.recorder.images),
        partial_cloud_B=np.array(cloud.points),
        cloud_frames_inconsistent=cloud.frames_inconsistent,
        localization=outcome,
        X_BK_estimated=X_BK_est,
        registered_template_B=registered,
        logs=logs,
        safety_events=events,
        scenario=scenario,
        truth=truth,
        sweep_masks=dict(h.recorder.sweep_masks),
        pivot_boundaries=list(h.recorder.pivot_boundaries),
        tracking_drift=h.tracking.state(h.tracking.GetMyContextFromRoot(root_context)).history,
        length_checks=h.localizer.length_checks(h.localizer.GetMyContextFromRoot(root_context)),
        pivot_limits=tuple(state.pivot_limits),
        sweep_end_causes=tuple(state.sweep_end_causes),
        cap_slides=tuple(state.cap_slides),
        whole_kidney_exploration=bool(state.whole_kidney),
        second_look_reason=state.second_look_reason,
        events=tuple(state.events),
        respiration=_respiration_record(h, root_context),
    )


def _respiration_record(h: ScanHandles, root_context) -> dict:
    """What the respiration systems did (empty without them): the estimator's transitions
    ((estimated time s, decided time s, from, to), ...), the prompts ((time s, Prompt),
    ...) and the number of breath-holds used."""
    if h.respiration is None:
        return {}
    estimate = h.respiration.state(h.respiration.GetMyContextFromRoot(root_context))
    protocol = h.protocol.state(h.protocol.GetMyContextFromRoot(root_context))
    return {
        "transitions": tuple(estimate.transitions),
        "prompts": tuple(protocol.prompts),
        "holds": int(protocol.holds),
    }


def RunScan(
    scenario,
    patient,
    template,
    *,
    make_station: Callable = MakeStation,
    meshcat=None,
    max_sim_time: float = 150.0,
    progress: bool | None = None,
    start_fraction: float | None = None,
    monitors: Sequence[ScanMonitor] = (),
    settle: float = 0.0,
    keep_sweep_masks: bool = False,
    keep_frames: bool = False,
    make_executor: Callable = MakeExecutor,
) -> ScanResult:
    """Runs the closed-loop scan until DONE, ABORT or ``max_sim_time`` (s).

    ``patient``: the virtual patient (simulation: plans the start pose and attaches the
    truth), or None on hardware (the scan starts where the operator placed the probe).
    ``make_station(scenario, meshcat=..., patient=...)`` builds the station; a station that
    can ``stop()`` a real robot runs paced at real time inside a ``HardwareSession`` (zero
    velocity on every exit) and is stopped if it falls ``safety.realtime_lag`` behind the wall
    clock. ``settle`` (s):
    keep simulating this long after the scan ends (monitors still observe), e.g. to check
    the robot comes to rest; the result describes the scan proper. ``keep_sweep_masks``:
    keep every EXPLORE and PIVOT frame's kidney mask (``ScanResult.sweep_masks``, for a
    volume reconstruction; about 64 kB a frame). ``keep_frames``: keep every frame's grey
    image, kidney mask, pose, time and phase (``ScanResult.saved_frames``, for ``scan
    --save-frames``; about 128 kB a frame).

    A live run is paced tick by tick (``drake_rus.pacing.RealtimePacer``: per-tick compute time
    and lag in ``ScanResult.loop_timing``; stopped at zero velocity, ABORT naming the
    overload, when the loop falls ``safety.realtime_lag`` behind) and its perception runs
    in worker processes beside the loop (``perception.execution: auto``, drake_rus.executor);
    otherwise perception runs inline with the scenario's latency model.
    ``make_executor(scenario.perception, paced=...)`` builds the executor (default
    ``drake_rus.executor.MakeExecutor``).
    """
    plan = None
    if patient is not None and not scenario.hardware:
        scenario, _, plan = PrepareScenario(scenario, patient, start_fraction)
    if meshcat is not None and plan is not None:
        DrawStartPlan(meshcat, plan)
    station = make_station(scenario, meshcat=meshcat, patient=patient)
    # A station that drives a real robot (it can stop() it) runs at real time, inside a
    # session that commands zero velocity on every exit (end, exception, Ctrl-C, SIGTERM),
    # and must keep up with the wall clock; its perception runs beside the loop.
    live = callable(getattr(station, "stop", None))
    try:
        executor = make_executor(scenario.perception, paced=live)
    except BaseException:
        _close(station, live)
        raise
    try:
        return _run(
            scenario,
            patient,
            template,
            station,
            executor,
            live,
            plan,
            meshcat=meshcat,
            max_sim_time=max_sim_time,
            progress=progress,
            monitors=monitors,
            settle=settle,
            keep_sweep_masks=keep_sweep_masks,
            keep_frames=keep_frames,
        )
    finally:
        executor.close()


@contextlib.contextmanager
def _live_interpreter(gc_pauses: list):
    """The interpreter set for a live loop: what exists before the run (the diagram, the
    template, the models) is kept out of the garbage collector's full passes (a pause of
    every thread), the collections are recorded in ``gc_pauses``, and a thread holding the
    interpreter lock (the video capture, the perception results' receivers) gives it up to
    the control loop within 1 ms instead of 5 ms."""
    switch = sys.getswitchinterval()
    gc.freeze()
    sys.setswitchinterval(0.001)
    try:
        with GcPauses(gc_pauses):
            yield
    finally:
        sys.setswitchinterval(switch)
        gc.unfreeze()


def _close(station, live: bool) -> None:
    # A live station holds a robot connection and a video capture thread: release them
    # once the robot is at rest (the session already commanded zero velocity).
    if live and callable(getattr(station, "close", None)):
        station.close()


def _run(
    scenario,
    patient,
    template,
    station,
    executor,
    live,
    plan,
    *,
    meshcat,
    max_sim_time,
    progress,
    monitors,
    settle,
    keep_sweep_masks,
    keep_frames,
) -> ScanResult:
    """RunScan's body once the station and the executor exist (the caller closes the
    executor)."""
    # The template for the scanned kidney's side (a right template mirrored for a left
    # kidney): the diagram, the fitted shape and the verdict all use this one.
    template = template.for_side(scenario.patient.side)
    try:
        builder, h = BuildScanDiagram(scenario, station, template, executor=executor)
    except BaseException:
        _close(station, live)
        raise
    if keep_sweep_masks:
        h.recorder.keep_masks((Phase.EXPLORE, Phase.PIVOT))
    if keep_frames:
        h.recorder.keep_frames()
    truth = (
        AttachSimulationTruth(builder, station, patient, scenario) if patient is not None else None
    )
    diagram = builder.Build()
    diagram.set_name("scan")
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    phase_port = h.supervisor.GetOutputPort("phase")
    supervisor_context = h.supervisor.GetMyContextFromRoot(context)
    stop_at_terminal = [True]

    def phase_now() -> Phase:
        return Phase(int(round(phase_port.Eval(supervisor_context)[0])))

    def monitor(root_context):
        for m in monitors:
            m.observe(root_context)
        if stop_at_terminal[0] and phase_now() in TERMINAL_PHASES:
            return EventStatus.ReachedTermination(diagram, "scan finished")
        return EventStatus.Succeeded()

    # The scan's end is caught by the diagram's ScanTerminator (an event at the controller
    # rate); a per-step monitor (Python after every plant step) only when monitors watch.
    if monitors:
        simulator.set_monitor(monitor)
    for m in monitors:
        m.attach(diagram, h, context)
    interrupted = []
    pacer = None
    if live:
        tick = min(1.0 / scenario.controller.rate_hz, getattr(station, "period", math.inf))
        pacer = RealtimePacer(simulator, tick, scenario.safety.realtime_lag)
    try:
        executor.warm_up()
        simulator.Initialize()
    except BaseException:
        _close(station, live)
        raise
    start = time.perf_counter()
    cpu_start = time.process_time()

    def should_stop(root_context) -> bool:
        if pacer is not None and pacer.overload is not None:
            return True
        return phase_now() in TERMINAL_PHASES

    gc_pauses: list = []
    try:
        try:
            with (
                HardwareSession(station) if live else contextlib.nullcontext(),
                _live_interpreter(gc_pauses) if live else contextlib.nullcontext(),
            ):
                AdvanceWithProgress(
                    simulator,
                    max_sim_time,
                    desc="scan",
                    step=0.1 if live else 0.25,
                    disable=None if progress is None else not progress,
                    on_step=lambda c: phase_now().name,
                    should_stop=should_stop,
                    expected=ExpectedScanTime(scenario),
                    advance=None if pacer is None else pacer.advance_to,
                )
                t_end = context.get_time()
                if settle > 0.0 and (pacer is None or pacer.overload is None):
                    stop_at_terminal[0] = False
                    h.terminator.enabled = False
                    (simulator.AdvanceTo if pacer is None else pacer.advance_to)(t_end + settle)
        except BaseException as e:
            # Ctrl-C or SIGTERM (drake_rus.interrupts; on hardware the session's own
            # handler): the session has already commanded zero velocity; collect what there
            # is (status INTERRUPTED). Any other error propagates, unless a signal caused it.
            if not (isinstance(e, KeyboardInterrupt) or interrupts.pending() is not None):
                raise
            interrupted.append(interrupts.signal_of(e))
            interrupts.note(interrupted[0])  # the exit status follows it
            t_end = context.get_time()
        wall = time.perf_counter() - start
        cpu = time.process_time() - cpu_start
        for m in monitors:
            m.finish(context)
        name = patient.name if patient is not None else "patient on the bed"
        result = CollectScanResult(
            scenario, name, template, h, truth, context, wall, end_time=t_end
        )
    finally:
        _close(station, live)
    result.sim_s = t_end
    result.cpu_s = cpu
    result.saved_frames = [
        SavedFrame(
            us.image, mask.image, us.time, us.frame_index, Phase(phase).name, visible, us.X_BP
        )
        for us, mask, phase, visible in h.recorder.kept_frames
    ]
    result.start_plan = plan
    result.perception = {
        "execution": executor.mode,
        "jobs": executor.statistics(),
        "frames_skipped": int(getattr(h.segmenter, "frames_skipped", 0)),
    }
    if pacer is not None:
        result.loop_timing = pacer.statistics(load_average())
        result.loop_timing["gc"] = gc_statistics(gc_pauses)
        result.loop_trace = pacer.trace()
    if interrupted:
        result.status = "INTERRUPTED"
        result.reason = (
            f"interrupted by {interrupts.signal_text(interrupted[0])} at "
            f"{t_end:.2f} s of simulated time, in {phase_now().name}; the "
            "outputs are partial"
        )
    elif pacer is not None and pacer.overload is not None:
        load = result.loop_timing["load_average"]
        result.status = "ABORT"
        result.reason = (
            f"the computer is overloaded: {pacer.overload} at {t_end:.2f} s, in "
            f"{phase_now().name} (load average {load['1min']:.1f} on {load['cpus']} CPUs): "
            "stopped at zero velocity"
        )
    # DONE only if the result passes its own checks (scan/verdict.py; never the truth).
    result.checks = JudgeScan(result, template)
    if result.status == "DONE":
        result.status, result.reason = Verdict(result.checks)
    return result
