"""The full autonomous scan (seed Fig. 2) in the closed-loop Drake simulation.

land -> EXPLORE (transverse sweep at v_scan with image centring, eq. 17, collecting the partial
cloud) -> LOCALIZE (template registration, eq. 18-19) -> TRANSIT (slide to the optimal pivot
pose, eq. 20-22) -> PIVOT (eq. 23, bounded by the segmentation) -> DONE, or ABORT with a
reason. ``RunScan`` builds the diagram, runs it and returns a ``ScanResult``;
``WriteScanOutputs`` writes the summary, clouds, plots and frames a user looks at.
"""

import dataclasses
import json
import time
from pathlib import Path

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, EventStatus, LeafSystem

from drake_rus.io_utils import atomic_path, write_text_atomic

# Scan phases as the supervisor numbers them (drake_rus.control.scan.Phase).
PHASE_NAMES = ["APPROACH", "EXPLORE", "LOCALIZE", "TRANSIT", "PIVOT", "DONE", "ABORT"]


class PhaseIs(LeafSystem):
    """1-vector output ``value``: 1.0 while the input ``phase`` equals ``phase_value``."""

    def __init__(self, phase_value: int):
        super().__init__()
        self._value = phase_value
        self.DeclareVectorInputPort("phase", 1)
        self.DeclareVectorOutputPort(
            "value", 1, lambda c, o: o.SetAtIndex(
                0, float(int(round(self.get_input_port(0).Eval(c)[0])) == self._value)))


@dataclasses.dataclass
class FrameRecord:
    """One acquired frame as the scan saw it."""
    time: float
    frame_index: int
    phase: int
    X_BP: RigidTransform
    visible: bool
    force: float


class ScanRecorder(LeafSystem):
    """Records every acquired frame (time, pose, phase, visibility, force) and keeps a few
    grey images and masks of the PIVOT phase for the report. A publish-only observer."""

    def __init__(self, frame_rate_hz: float, keep_every: int = 10, keep_max: int = 40):
        super().__init__()
        from drake_rus.imaging.frames import UsFrame
        empty = UsFrame(np.zeros((1, 1), np.uint8))
        self._us = self.DeclareAbstractInputPort("us_image", AbstractValue.Make(empty))
        self._mask = self.DeclareAbstractInputPort("kidney_mask", AbstractValue.Make(empty))
        self._phase = self.DeclareVectorInputPort("phase", 1)
        self._visible = self.DeclareVectorInputPort("kidney_visible", 1)
        self._force = self.DeclareVectorInputPort("contact_force", 1)
        period = 1.0 / frame_rate_hz
        self.DeclarePeriodicPublishEvent(period, 0.5 * period, self._record)
        self.frames: list[FrameRecord] = []
        self.images: list[tuple] = []
        self._keep_every, self._keep_max = keep_every, keep_max
        self._last_index = -1
        self._pivot_count = 0

    def _record(self, context):
        us = self._us.Eval(context)
        if us.frame_index < 0 or us.frame_index == self._last_index:
            return EventStatus.DidNothing()
        self._last_index = us.frame_index
        phase = int(round(self._phase.Eval(context)[0]))
        visible = bool(self._visible.Eval(context)[0] > 0.5)
        self.frames.append(FrameRecord(us.time, us.frame_index, phase, RigidTransform(us.X_BP),
                                       visible, float(self._force.Eval(context)[0])))
        if phase == PHASE_NAMES.index("PIVOT"):
            if self._pivot_count % self._keep_every == 0 and len(self.images) < self._keep_max:
                mask = self._mask.Eval(context)
                self.images.append((us.time, np.array(us.image), np.array(mask.image)))
            self._pivot_count += 1
        return EventStatus.Succeeded()


@dataclasses.dataclass
class ScanResult:
    status: str                    # "DONE" or "ABORT" (or "TIMEOUT")
    reason: str
    patient: str
    sim_s: float
    wall_s: float
    phases: list                   # [(name, start s, end s)]
    frames: list                   # FrameRecord per acquired frame
    images: list                   # (time, grey, mask) of some PIVOT frames
    partial_cloud_B: np.ndarray
    localization: object           # LocalizationOutcome
    X_BK_true: RigidTransform
    X_BK_estimated: RigidTransform | None
    registered_template_B: np.ndarray | None
    kidney_points_B: np.ndarray
    voxel_volume: float
    logs: dict                     # name -> (times, data)
    safety_events: list
    scenario: object
    # Kidney tracking checks after localization: ((time s, apparent drift m), ...).
    tracking_drift: tuple = ()


def _kidney_voxels_B(patient, X_BPt, voxel_size):
    mask, X_PtV = patient.kidney_mask(voxel_size)
    ijk = np.argwhere(mask)
    p_Pt = X_PtV.multiply((ijk * voxel_size).T).T
    return X_BPt.multiply(p_Pt.T).T


def BuildScanDiagram(scenario, patient, template, *, meshcat=None):
    """Station (sim) + segmenter + cloud accumulator + localizer + controller + recorder."""
    from pydrake.systems.primitives import LogVectorOutput

    from drake_rus.control.diagram import AddController
    from drake_rus.imaging.systems import PointCloudAccumulator, Segmenter
    from drake_rus.localization.localize import IcpLocalizer, body_directions_B
    from drake_rus.localization.tracking import KidneyTrackingMonitor
    from drake_rus.station import MakeStation

    builder = DiagramBuilder()
    station = builder.AddNamedSystem("station",
                                     MakeStation(scenario, meshcat=meshcat, patient=patient))
    segmenter = builder.AddNamedSystem("segmenter", Segmenter(scenario.imaging))
    builder.Connect(station.GetOutputPort("us_image"), segmenter.GetInputPort("us_image"))
    builder.Connect(station.GetOutputPort("label_image"), segmenter.GetInputPort("label_image"))
    accumulator = builder.AddNamedSystem("point_cloud_accumulator",
                                         PointCloudAccumulator(scenario.imaging))
    builder.Connect(segmenter.GetOutputPort("boundary_pixels"),
                    accumulator.GetInputPort("boundary_pixels"))
    X_BPt = scenario.patient.X_BPt.GetDeterministicValue()
    superior_B, lateral_B = body_directions_B(X_BPt, scenario.patient.side,
                                              scenario.patient.posture)
    localizer = builder.AddNamedSystem("icp_localizer", IcpLocalizer(
        template, scenario.localization, superior_B, lateral_B,
        localize_phase=PHASE_NAMES.index("LOCALIZE"), rate_hz=scenario.imaging.frame_rate_hz,
        explore_phase=PHASE_NAMES.index("EXPLORE"),
        kidney_length=scenario.controller.kidney_length))
    builder.Connect(accumulator.GetOutputPort("point_cloud"), localizer.GetInputPort("point_cloud"))
    parts = AddController(builder, station, scenario, segmenter=segmenter,
                          kidney_pose_port=localizer.GetOutputPort("X_BK"),
                          localization_ready_port=localizer.GetOutputPort("localization_ready"))
    supervisor = parts.supervisor
    builder.Connect(supervisor.GetOutputPort("phase"), localizer.GetInputPort("phase"))
    builder.Connect(localizer.GetOutputPort("localization_error"),
                    supervisor.GetInputPort("localization_error"))
    builder.Connect(localizer.GetOutputPort("exploration_sufficient"),
                    supervisor.GetInputPort("exploration_sufficient"))
    exploring = builder.AddNamedSystem("exploring", PhaseIs(PHASE_NAMES.index("EXPLORE")))
    builder.Connect(supervisor.GetOutputPort("phase"), exploring.get_input_port(0))
    from drake_rus.reliability.station import BreathHoldPort, GateByBreathHold
    builder.Connect(GateByBreathHold(builder, scenario, station, exploring.get_output_port(0)),
                    accumulator.GetInputPort("enable"))
    tracking = builder.AddNamedSystem("kidney_tracking_monitor", KidneyTrackingMonitor(
        template, scenario.localization, scenario.imaging,
        check_phases=[PHASE_NAMES.index("TRANSIT"), PHASE_NAMES.index("PIVOT")]))
    builder.Connect(segmenter.GetOutputPort("boundary_pixels"),
                    tracking.GetInputPort("boundary_pixels"))
    builder.Connect(localizer.GetOutputPort("localization"), tracking.GetInputPort("localization"))
    builder.Connect(supervisor.GetOutputPort("phase"), tracking.GetInputPort("phase"))
    builder.Connect(tracking.GetOutputPort("tracking_error"),
                    supervisor.GetInputPort("tracking_error"))
    hold = BreathHoldPort(scenario, station)
    if hold is not None:
        builder.Connect(hold, supervisor.GetInputPort("motion_allowed"))
        builder.Connect(hold, tracking.GetInputPort("motion_allowed"))

    recorder = builder.AddNamedSystem("scan_recorder", ScanRecorder(scenario.imaging.frame_rate_hz))
    builder.Connect(station.GetOutputPort("us_image"), recorder.GetInputPort("us_image"))
    builder.Connect(segmenter.GetOutputPort("kidney_mask"), recorder.GetInputPort("kidney_mask"))
    builder.Connect(supervisor.GetOutputPort("phase"), recorder.GetInputPort("phase"))
    builder.Connect(segmenter.GetOutputPort("kidney_visible"),
                    recorder.GetInputPort("kidney_visible"))
    builder.Connect(parts.force.GetOutputPort("F_filtered"), recorder.GetInputPort("contact_force"))

    period = 0.02
    logs = {
        "phase": LogVectorOutput(supervisor.GetOutputPort("phase"), builder, period),
        "force": LogVectorOutput(parts.force.GetOutputPort("F_filtered"), builder, period),
        "force_true": LogVectorOutput(station.GetOutputPort("probe_contact_wrench_true"),
                                      builder, period),
        "a_des": LogVectorOutput(supervisor.GetOutputPort("a_des"), builder, period),
        "manipulability": LogVectorOutput(parts.ik.GetOutputPort("manipulability"), builder,
                                          period),
        "q": LogVectorOutput(station.GetOutputPort("joint_position"), builder, period),
    }
    diagram = builder.Build()
    diagram.set_name("scan")
    handles = dict(station=station, segmenter=segmenter, accumulator=accumulator,
                   localizer=localizer, supervisor=supervisor, recorder=recorder, parts=parts,
                   tracking=tracking,
                   logs=logs)
    return diagram, handles


def PrepareScenario(scenario, patient, start_fraction: float = 0.1):
    """The scenario with the robot's initial joints set above the exploration start."""
    from drake_rus.experiments.planning import exploration_start
    from drake_rus.sim.ik import SolveTipPose
    from drake_rus.station import MakeControlPlant

    X_BPt = scenario.patient.X_BPt.GetDeterministicValue()
    X_start = exploration_start(patient, X_BPt, scan_direction=scenario.controller.scan_direction,
                                start_fraction=start_fraction)
    plant, tip = MakeControlPlant(scenario)
    q0 = SolveTipPose(plant, tip, X_start)
    robot = dataclasses.replace(scenario.robot, initial_joint_positions=[float(v) for v in q0])
    return dataclasses.replace(scenario, robot=robot), X_start


def RunScan(scenario, patient, template, *, meshcat=None, max_sim_time: float = 150.0,
            progress: bool | None = None, start_fraction: float = 0.1) -> ScanResult:
    """Runs the closed-loop scan until DONE, ABORT or ``max_sim_time`` (s)."""
    from drake_rus.sim.run import AdvanceWithProgress

    scenario, _ = PrepareScenario(scenario, patient, start_fraction)
    diagram, h = BuildScanDiagram(scenario, patient, template, meshcat=meshcat)
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    supervisor_context = h["supervisor"].GetMyContextFromRoot(context)
    terminal = {PHASE_NAMES.index("DONE"), PHASE_NAMES.index("ABORT")}

    def phase_now():
        return int(round(h["supervisor"].GetOutputPort("phase").Eval(supervisor_context)[0]))

    def monitor(root_context):
        if phase_now() in terminal:
            return EventStatus.ReachedTermination(diagram, "scan finished")
        return EventStatus.Succeeded()

    simulator.set_monitor(monitor)
    simulator.Initialize()
    start = time.perf_counter()
    AdvanceWithProgress(simulator, max_sim_time, desc="scan", step=0.25,
                        disable=None if progress is None else not progress,
                        on_step=lambda c: PHASE_NAMES[phase_now()],
                        should_stop=lambda c: phase_now() in terminal)
    wall = time.perf_counter() - start
    return _collect(scenario, patient, template, diagram, h, simulator, wall)


def _collect(scenario, patient, template, diagram, h, simulator, wall,
             end_time: float | None = None) -> ScanResult:
    """The ScanResult of a finished simulation; ``end_time`` (s): when the scan proper
    ended, if the simulator ran on after it (default: the context's time)."""
    context = simulator.get_context()
    sup = h["supervisor"]
    sup_ctx = sup.GetMyContextFromRoot(context)
    state = sup.GetOutputPort("supervisor_state").Eval(sup_ctx)
    phase = PHASE_NAMES[int(state.phase)]
    status = phase if phase in ("DONE", "ABORT") else "TIMEOUT"
    reason = state.events[-1][2] if status == "ABORT" and state.events else ""
    safety_ctx = h["parts"].safety.GetMyContextFromRoot(context)
    events = list(h["parts"].safety.GetOutputPort("safety_events").Eval(safety_ctx))
    if status == "TIMEOUT":
        t_end = context.get_time() if end_time is None else end_time
        reason = f"still in {phase} after {t_end:.1f} s of simulated time"
    logs = {}
    for name, logger in h["logs"].items():
        log = logger.FindLog(context)
        logs[name] = (log.sample_times().copy(), log.data().copy())
    # Phase intervals from the phase log.
    t, ph = logs["phase"][0], logs["phase"][1][0].round().astype(int)
    phases = []
    start_index = 0
    for k in range(1, len(ph) + 1):
        if k == len(ph) or ph[k] != ph[start_index]:
            phases.append((PHASE_NAMES[ph[start_index]], float(t[start_index]),
                           float(t[k] if k < len(t) else context.get_time())))
            start_index = k
    if not phases or phases[-1][0] != phase:
        phases.append((phase, context.get_time(), context.get_time()))
    loc_ctx = h["localizer"].GetMyContextFromRoot(context)
    outcome = h["localizer"].GetOutputPort("localization").Eval(loc_ctx)
    cloud = h["accumulator"].GetOutputPort("point_cloud").Eval(
        h["accumulator"].GetMyContextFromRoot(context))
    X_BPt = scenario.patient.X_BPt.GetDeterministicValue()
    X_BK_est, registered = None, None
    if outcome.result is not None:
        X_BK_est = outcome.result.X_BK
        shape = template.points
        if outcome.result.shape_coefficients is not None:
            b = outcome.result.shape_coefficients
            shape = template.points + np.einsum("k,kij->ij", b, template.modes[:len(b)])
        registered = X_BK_est.multiply(shape.T).T
    voxel = 0.002
    recorder = h["recorder"]
    return ScanResult(
        status=status, reason=reason, patient=patient.name, sim_s=context.get_time(),
        wall_s=wall, phases=phases, frames=list(recorder.frames), images=list(recorder.images),
        partial_cloud_B=np.array(cloud.points), localization=outcome,
        X_BK_true=patient.X_BK(X_BPt), X_BK_estimated=X_BK_est,
        registered_template_B=registered,
        kidney_points_B=_kidney_voxels_B(patient, X_BPt, voxel), voxel_volume=voxel**3,
        logs=logs, safety_events=events, scenario=scenario,
        tracking_drift=h["tracking"].state(h["tracking"].GetMyContextFromRoot(context)).history)


def ScanMetrics(result: ScanResult) -> dict:
    """The seed's metrics for one scan (section III): E_trans, E_rot,x, eps, n, V."""
    from drake_rus.imaging.probe import ProbeGeometry
    from drake_rus.metrics import (
        CoverageAccumulator, e_rot_x, e_trans, imaging_window_path_length)

    imaging = result.scenario.imaging
    geometry = ProbeGeometry.from_config(imaging)
    pivot = [f for f in result.frames if f.phase == PHASE_NAMES.index("PIVOT")]
    coverage = CoverageAccumulator(result.kidney_points_B, result.voxel_volume, geometry.in_fan,
                                   imaging.elevation_width)
    V_curve = [coverage.add_frame(f.X_BP) for f in pivot]
    all_cov = CoverageAccumulator(result.kidney_points_B, result.voxel_volume, geometry.in_fan,
                                  imaging.elevation_width)
    for f in result.frames:
        all_cov.add_frame(f.X_BP)
    eps_curve = np.concatenate([[0.0], np.cumsum(
        _steps([f.X_BP for f in pivot], imaging.depth))]) if pivot else np.zeros(1)
    metrics = {
        "n_frames": len(pivot),
        "eps_mm": float(eps_curve[-1] * 1000) if pivot else 0.0,
        "volume_ratio": float(V_curve[-1]) if V_curve else 0.0,
        "volume_ratio_all_frames": all_cov.ratio,
        "V_curve": V_curve,
        "eps_curve_mm": (eps_curve * 1000).tolist(),
    }
    if result.X_BK_estimated is not None:
        metrics["e_trans_mm"] = e_trans(result.X_BK_estimated, result.X_BK_true) * 1000
        metrics["e_rot_x_deg"] = float(np.rad2deg(e_rot_x(result.X_BK_estimated,
                                                          result.X_BK_true)))
    else:
        metrics["e_trans_mm"] = None
        metrics["e_rot_x_deg"] = None
    return metrics


def _steps(poses, depth):
    from drake_rus.metrics import window_steps
    return window_steps(poses, depth)


def Summary(result: ScanResult, metrics: dict) -> dict:
    loc = result.localization
    diag = None
    if loc.result is not None:
        diag = {"iterations": loc.result.iterations, "converged": loc.result.converged,
                "rms_residual_mm": loc.result.rms_residual * 1000,
                "inlier_fraction": loc.result.inlier_fraction, "points": loc.n_points,
                "compute_ms": loc.compute_s * 1000,
                "method": result.scenario.localization.method}
    force_t, force = result.logs["force"][0], result.logs["force"][1][0]
    return {
        "status": result.status, "reason": result.reason, "patient": result.patient,
        "e_trans_mm": metrics["e_trans_mm"], "e_rot_x_deg": metrics["e_rot_x_deg"],
        "eps_mm": metrics["eps_mm"], "n_frames": metrics["n_frames"],
        "volume_ratio": metrics["volume_ratio"],
        "volume_ratio_all_frames": metrics["volume_ratio_all_frames"],
        "wall_s": result.wall_s, "sim_s": result.sim_s,
        "realtime_rate": result.sim_s / result.wall_s if result.wall_s > 0 else None,
        "phases": [{"phase": n, "start_s": a, "end_s": b, "duration_s": b - a}
                   for n, a, b in result.phases],
        "localization": diag, "localization_error": loc.error or None,
        "max_kidney_drift_mm": (max(d for _, d in result.tracking_drift) * 1000
                                if result.tracking_drift else None),
        "exploration_ratio": result.scenario.controller.exploration_ratio,
        "segmenter": result.scenario.imaging.segmenter,
        "peak_force_n": float(np.max(force)) if len(force) else 0.0,
        "frames_total": len(result.frames),
        "safety_events": [str(e) for e in result.safety_events],
        "mode": "closed-loop dynamic simulation (MultibodyPlant 1 ms SAP, controller "
                f"{result.scenario.controller.rate_hz:.0f} Hz, images "
                f"{result.scenario.imaging.frame_rate_hz:.0f} Hz)",
    }


# ------------------------------------------------------------------------------ the CLI
def add_commands(subparsers) -> None:
    import argparse

    from drake_rus.demo import add_scenario_arguments
    p = subparsers.add_parser(
        "scan", help="the full autonomous kidney scan on a virtual (or real) patient",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scenario_arguments(p)
    p.add_argument("--patient", default="test:0",
                   help="test:K or train:K (cohort member), seed:N (any generator seed), or a "
                        "patient directory/file (default test:0)")
    p.add_argument("--out", default="runs/scan", help="output directory (default runs/scan)")
    p.add_argument("--meshcat", action="store_true", help="live Meshcat (URL printed)")
    p.add_argument("--record", default=None,
                   help="Meshcat recording file (default OUT/scan.html)")
    p.add_argument("--no-record", action="store_true", help="skip the Meshcat recording")
    p.add_argument("--seed", type=int, default=None, help="random seed (speckle, noise)")
    p.add_argument("--max-sim-time", type=float, default=150.0,
                   help="give up after this much simulated time in s (default 150)")
    p.set_defaults(func=run_scan_command)


def run_scan_command(args) -> int:
    from drake_rus.anatomy import load_patient
    from drake_rus.demo import MakeMeshcat, load_scenario_from_args
    from drake_rus.localization.localize import load_registration_template
    from drake_rus.scan_report import WriteScanOutputs
    from drake_rus.sim.run import SaveMeshcatRecording

    scenario = load_scenario_from_args(args)
    if args.seed is not None:
        if args.seed < 0:
            raise ValueError(f"--seed: expected a non-negative integer, got {args.seed}")
        scenario = dataclasses.replace(scenario, random_seed=args.seed)
    if not (np.isfinite(args.max_sim_time) and args.max_sim_time > 0):
        raise ValueError(f"--max-sim-time: expected a positive time in s, got {args.max_sim_time}")
    try:
        template = load_registration_template(scenario.localization.template)
    except FileNotFoundError as e:
        raise FileNotFoundError(
            f"localization.template: {e} (build one with 'drake-rus template build')") from None
    print(f"patient {args.patient}: generating ...", flush=True)
    patient = load_patient(args.patient, side=scenario.patient.side,
                           posture=scenario.patient.posture)
    meshcat = None
    if args.meshcat or not args.no_record:
        meshcat = MakeMeshcat()
        if args.meshcat:
            print(f"Meshcat: {meshcat.web_url()}", flush=True)
        meshcat.StartRecording(frames_per_second=20.0)
    result = RunScan(scenario, patient, template, meshcat=meshcat,
                     max_sim_time=args.max_sim_time)
    out = Path(args.out)
    metrics = ScanMetrics(result)
    summary = Summary(result, metrics)
    written = WriteScanOutputs(result, metrics, summary, out)
    if meshcat is not None and not args.no_record:
        record = Path(args.record) if args.record else out / "scan.html"
        SaveMeshcatRecording(meshcat, record)
        written.append(record)
    e_t, e_r = summary["e_trans_mm"], summary["e_rot_x_deg"]
    print(f"{summary['status']}{': ' + summary['reason'] if summary['status'] != 'DONE' else ''}"
          f" | E_trans {e_t if e_t is None else round(e_t, 2)} mm, E_rot,x "
          f"{e_r if e_r is None else round(e_r, 2)} deg | eps {summary['eps_mm']:.1f} mm, "
          f"n {summary['n_frames']}, V {summary['volume_ratio']:.3f} | "
          f"{summary['sim_s']:.1f} sim s in {summary['wall_s']:.1f} s")
    print("wrote " + ", ".join(str(p) for p in written))
    return 0 if summary["status"] == "DONE" else 1
