"""Study runs in closed-loop mode: every run a full closed-loop scan on the Drake diagram
(``RunScan``: MultibodyPlant, controller, contact, the scan's own imaging, localization and
pivot), with the kinematic run's record.

- :func:`run_closed_loop_study`: one run of er-sweep, starts, efficiency or template
  (``StudyTask.mode`` "closed-loop"; run ids end in ``__cl``).
- :func:`closed_loop_setup`: the run's scenario (ER x the patient's kidney length as the
  controller's L_m, random starts landed at the twin's start) and what the study changed.
  ER 0 is the initial alignment alone (III-C, :func:`initial_alignment_record`), as in the
  twin. A run whose planned exploration is shorter than the product's
  ``min_exploration_travel`` registers it without the product's minimum and acceptance
  checks, as the paper and the twin do (:func:`study_localization`, the study's scenario
  only); a registration the product rejects is recorded
  (:func:`rejected_registration_record`).
- :func:`closed_loop_strategy_run`: the efficiency study's strategies, each its own scan
  (GT-OP and NOP pivot at a pose the study computes from the true kidney pose and gives the
  scan as ``controller.pivot_pose``, SL is the scan's ``controller.sweep: line``), the
  kidney volume reconstructed from each scan's masks (:func:`closed_loop_volume`).
- :func:`run_closed_loop`: the paper study's closed-loop check (``closed-loop`` study): a
  few closed-loop dynamic scans beside their kinematic twins.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from drake_rus.control.supervisor import Phase, pivot_pose_as_given
from drake_rus.experiments import kinematic as km
from drake_rus.experiments.keys import run_id, study_scenario, with_template
from drake_rus.experiments.kinematic_runs import sweep_entry
from drake_rus.experiments.patients import (
    exploration_travel,
    kidney_length,
    prepared_patient,
    start_visibility,
    task_scenario_and_patient,
    visible_random_start,
)
from drake_rus.experiments.specs import (
    CLOSED_LOOP_DEFAULT_STRATEGIES,
    CLOSED_LOOP_STRATEGY_HOW,
    POSE_FROM,
    STRATEGY_TEXT,
    StudyTask,
    check_strategies,
)
from drake_rus.experiments.templates import load_template, task_template, template_record
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.metrics.core import e_rot_x, e_trans
from drake_rus.metrics.reconstruction import reconstruct_kidney
from drake_rus.scan import RunScan, ScanMetrics
from drake_rus.scenario import CheckScenario

# GT-OP and NOP: the start planner puts the probe over this fraction of the kidney's length
# (the middle; an operator placing the probe), then TRANSIT slides it to the given pose.
GIVEN_POSE_START_FRACTION = 0.5
# A study run below the product's exploration minimum registers unchecked: these limits
# (m) stand for "no limit" (study_localization).
RELAXED_LIMIT = 1.0


# ------------------------------------------------------------------------------- set-up
def study_localization(config, er: float, planned_travel: float):
    """The localization settings of a closed-loop study run and a note ("" if unchanged).

    The product refuses to localize from an exploration shorter than
    ``min_exploration_travel`` (15 mm) and rejects registrations that fail its acceptance
    checks (RMS residual, inlier fraction, centre offset, points along a line); the paper's
    registration (II-F) has neither, and its ER sweep (III-C) reports both errors at every
    ER of its grid. So a study run whose planned exploration (ER x length) is shorter than
    the product's minimum registers whatever it explored, unchecked, as the paper (and the
    kinematic twin) do.
    ER 0 is left alone: it has nothing to register (the study takes the initial alignment,
    :func:`initial_alignment_record`). Only the study's scenario changes, never the product
    default."""
    if er <= 0 or planned_travel >= config.min_exploration_travel - 1e-12:
        return config, ""
    relaxed = dataclasses.replace(
        config,
        min_exploration_travel=0.0,
        min_inlier_fraction=0.0,
        min_cloud_spread=0.0,
        max_rms_residual=RELAXED_LIMIT,
        max_rms_residual_deformable=RELAXED_LIMIT,
        max_centroid_offset=RELAXED_LIMIT,
    )
    return relaxed, (
        f"planned exploration {planned_travel * 1e3:.1f} mm is below the "
        f"product's minimum {config.min_exploration_travel * 1e3:.0f} mm: the "
        "study registers it without the product's minimum travel and acceptance "
        "checks (the paper has none)"
    )


def closed_loop_scenario(task: StudyTask, kp, base):
    """The scenario of a closed-loop study run: ``base`` with the run's ER, localization
    method and segmenter. ER: with ``er_unit`` "kidney" the exploration travels ER x the
    patient's kidney length along the exploration line (the controller's reference length
    L_m set to it, ``exploration_length: fixed``: the simulation knows the truth, as the
    paper's simulation did), with "fixed" ER x the scenario's L_m; the scan's
    ``exploration_length: estimated`` is not used, so both modes explore the same travel.
    A random start (``starts``) lands the probe at the twin's start (x, y)
    (``controller.start_xy``), drawn where the kidney is visible (:func:`start_visibility`).
    A run whose planned exploration is below the product's ``min_exploration_travel``
    registers without the product's minimum and acceptance checks
    (:func:`study_localization`)."""
    return closed_loop_setup(task, kp, base)[:3]


def closed_loop_setup(task: StudyTask, kp, base):
    """:func:`closed_loop_scenario` and what the study changed for the run:
    ``(scenario, start_fraction, x_offset, notes)``, ``notes`` a dict with
    ``start_rejected_draws`` (random starts drawn where the kidney was not visible,
    :func:`start_visibility`) and ``study_relaxation`` (:func:`study_localization`)."""
    c = base.controller
    unit = task.er_unit
    length = kidney_length(kp) if unit == "kidney" else float(c.kidney_length)
    planned = exploration_travel(task.er, unit, kidney_length(kp), c.kidney_length)
    controller = dataclasses.replace(
        c, exploration_ratio=float(task.er), exploration_length="fixed", kidney_length=length
    )
    start_fraction, x_offset, notes = 0.0, 0.0, {}
    if task.study == "starts":
        imager = km.Imager(
            kp, km.imaging_for(kp, base.imaging, base.start), task.segmenter, seed=int(task.seed)
        )
        start_fraction, x_offset, rejected = visible_random_start(
            task, kp, c, start_visibility(kp, imager)
        )
        notes["start_rejected_draws"] = rejected
        xy = km.start_xy(kp, start_fraction, c.scan_direction, x_offset)
        controller = dataclasses.replace(controller, start_xy=[float(xy[0]), float(xy[1])])
    localization, relaxation = study_localization(
        dataclasses.replace(base.localization, method=task.method), float(task.er), planned
    )
    notes["study_relaxation"] = relaxation
    scenario = dataclasses.replace(
        base,
        controller=controller,
        localization=localization,
        imaging=dataclasses.replace(base.imaging, segmenter=task.segmenter),
    )
    return scenario, start_fraction, x_offset, notes


# ------------------------------------------------------------------------------- records
def rejected_registration_record(kp, loc) -> dict:
    """The errors of a registration the product's acceptance checks rejected (``loc``, the
    scan's LocalizationOutcome with ``rejected``): the scan stopped, as the product must,
    but the paper's registration has no such check and its studies report the errors of
    whatever it registered, so the study records them (the run has no pivot)."""
    X = loc.rejected.X_BK
    return {
        "e_trans_mm": e_trans(X, kp.X_BK_true) * 1e3,
        "e_rot_x_deg": math.degrees(e_rot_x(X, kp.X_BK_true)),
        "localization_note": f"the product rejected the registration ({loc.error}); its "
        "errors are recorded (the paper has no acceptance check)",
    }


def initial_alignment_record(kp, scan, start_xy) -> dict:
    """ER 0 of a closed-loop study run (the paper's III-C: "at ER = 0% ... the localization
    is purely based on the initial alignment"): E_trans and E_rot,x of the heuristic initial
    alignment (:func:`drake_rus.experiments.kinematic.heuristic_pose`, the twin's) at the
    tip's (x, y) where the scan's exploration began (its first EXPLORE frame, else its last
    frame, else ``start_xy``)."""
    explore = [f for f in scan.frames if f.phase == int(Phase.EXPLORE)]
    frames = explore or list(scan.frames)
    xy = (
        np.asarray(frames[0 if explore else -1].X_BP.translation()[:2], float)
        if frames
        else np.asarray(start_xy, float)
    )
    X0 = km.heuristic_pose(kp, xy)
    return {
        "e_trans_mm": e_trans(X0, kp.X_BK_true) * 1e3,
        "e_rot_x_deg": math.degrees(e_rot_x(X0, kp.X_BK_true)),
        "localization_note": "ER 0: initial alignment only (the paper's III-C)"
        + (f"; the scan: {scan.status} {scan.reason}".rstrip() if scan.reason else ""),
    }


# ------------------------------------------------------------------------------- strategies
@dataclasses.dataclass
class StrategyScan:
    """How the closed-loop scan of one efficiency strategy runs: its scenario (validated
    like any scenario), the start planner's start fraction, and what the run records about
    the pose (``pivot_pose``: "registered", "given" or None for SL; ``given_pivot_pose``
    [x m, y m, yaw rad] or None; ``pose_source`` the truth it came from, ``how`` and
    ``text`` for people)."""

    scenario: object
    start_fraction: float
    pose: dict


def closed_loop_strategy_run(
    scenario, strategy: str, kp=None, start_fraction: float = 0.0
) -> StrategyScan:
    """The closed-loop scan of efficiency strategy ``strategy`` from the run's ``scenario``
    (its ER, segmenter, registration) and start fraction:

    - OP: the scan as it is (two-leg pivot at the registered T*, ``pivot_pose`` []);
    - OP-PE: ``pivot_strategy: predicted_end``;
    - GT-OP, NOP: ``pivot_pose`` = the strategy's pose from the true kidney pose
      (:func:`~drake_rus.experiments.kinematic.strategy_pivot_pose`, the twin's), two-leg
      pivot, ER 0 (the scan skips exploration and localization; the start planner checks
      no sweep) and the probe's start over the kidney's middle
      (:data:`GIVEN_POSE_START_FRACTION`);
    - SL: ``sweep: line`` from ``start_xy`` beyond the E-ROI's end for at most the twin's
      travel (:func:`~drake_rus.experiments.kinematic.sl_line`), the start planner's start
      at the E-ROI's end, ER 100% (what the planner's window must hold; the line itself
      ends where the kidney leaves the image), no kidney-length estimation or adaptive stop
      (nothing to localize).

    The truth (``kp``, a prepared patient; needed by GT-OP, NOP, SL) enters only as these
    scenario values, checked by ``CheckScenario``: the scan never reads it."""
    check_strategies([strategy], "closed-loop")
    c = dataclasses.replace(
        scenario.controller, pivot_pose=[], sweep="pivot", pivot_strategy="two_leg"
    )
    loc = scenario.localization
    sf = float(start_fraction)
    pose = {"pivot_pose": "registered", "given_pivot_pose": None, "pose_source": None}
    if strategy in ("GT-OP", "NOP", "SL") and kp is None:
        raise ValueError(
            f"strategy {strategy}: needs the prepared patient (its true kidney pose or E-ROI)"
        )
    if strategy == "OP-PE":
        c = dataclasses.replace(c, pivot_strategy="predicted_end")
    elif strategy in ("GT-OP", "NOP"):
        given = pivot_pose_as_given(*km.strategy_pivot_pose(strategy, kp.X_BK_true))
        c = dataclasses.replace(c, pivot_pose=given, exploration_ratio=0.0)
        sf = GIVEN_POSE_START_FRACTION
        pose = {
            "pivot_pose": "given",
            "given_pivot_pose": given,
            "pose_source": "the true kidney pose (simulation truth, study only)",
        }
    elif strategy == "SL":
        start, travel = km.sl_line(kp, c.scan_direction)
        c = dataclasses.replace(
            c,
            sweep="line",
            start_xy=[float(v) for v in start],
            line_sweep_max_travel=travel,
            exploration_ratio=1.0,
        )
        loc = dataclasses.replace(loc, length_estimation=False, adaptive_exploration=False)
        sf = 0.0
        pose = {
            "pivot_pose": None,
            "given_pivot_pose": None,
            "pose_source": "the true kidney's E-ROI (the line's start, study only)",
        }
    out = dataclasses.replace(scenario, controller=c, localization=loc)
    CheckScenario(out)
    pose.update(
        pivot_pose_from=POSE_FROM[strategy],
        how=CLOSED_LOOP_STRATEGY_HOW[strategy],
        text=STRATEGY_TEXT[strategy],
    )
    return StrategyScan(out, sf, pose)


def closed_loop_strategy_scenario(scenario, strategy: str, kp=None):
    """The scenario of :func:`closed_loop_strategy_run` (OP the two-leg pivot at the
    registered T*, OP-PE the predicted_end one, GT-OP and NOP a given pivot pose, SL a
    line sweep)."""
    return closed_loop_strategy_run(scenario, strategy, kp).scenario


def closed_loop_entry(m: dict) -> dict:
    """A strategy entry (like
    :func:`~drake_rus.experiments.kinematic_runs.sweep_entry`'s) from a closed-loop scan's
    metrics."""
    at = m["at_matched_V"]
    sweep = m.get("sweep") or {}
    return {
        "n": int(m["n_frames"]),
        "eps_mm": m["eps_mm"],
        "V": m["volume_ratio"],
        "sweep": sweep.get("kind", "pivot"),
        "pivot_pose": sweep.get("pivot_pose"),
        "given_pivot_pose": sweep.get("given_pivot_pose"),
        "n_whole_pivot": int(m["n_whole_pivot"]),
        "eps_whole_pivot_mm": m["eps_whole_pivot_mm"],
        "V_whole_pivot": m["volume_ratio_whole_pivot"],
        "at_V": {k: v["pole_to_pole"] for k, v in at.items()},
        "at_V_whole_pivot": {k: v["whole_pivot"] for k, v in at.items()},
        "tilt_cap_legs": list(m["pivot"]["tilt_cap_legs"]),
        "events": [],
        "curve_eps_mm": np.round(np.asarray(m["eps_curve_mm"], float), 3).tolist(),
        "curve_V": np.round(np.asarray(m["V_curve"], float), 5).tolist(),
        "pole_to_pole": list(m["pivot"]["pole_to_pole_frames"]),
        "volume_ml": None,
        "volume_error_pct": None,
        "volume_note": "closed loop: reconstructed in the efficiency study only",
    }


def closed_loop_volume(scan, metrics: dict, kp, spacing: float) -> dict:
    """The kidney volume reconstructed from a closed-loop scan's pole-to-pole frames (the
    masks ``RunScan(keep_sweep_masks=True)`` kept, compounded as the kinematic study does:
    :func:`~drake_rus.metrics.reconstruction.reconstruct_kidney`) against the true kidney's:
    {volume_ml, volume_error_pct, volume_note}."""
    line = (metrics.get("sweep") or {}).get("kind") == "line"
    phase = int(Phase.EXPLORE if line else Phase.PIVOT)
    frames = [f for f in scan.frames if f.phase == phase]
    ends = metrics["pivot"]["pole_to_pole_frames"]
    out = {"volume_ml": None, "volume_error_pct": None}
    if not ends:
        return out | {"volume_note": "no pole-to-pole span to reconstruct"}
    span = frames[ends[0] : ends[1] + 1]
    masks = [scan.sweep_masks.get(f.frame_index) for f in span]
    if not span or any(m is None for m in masks):
        return out | {"volume_note": "the scan kept no masks (RunScan keep_sweep_masks)"}
    geometry = ProbeGeometry.from_config(scan.scenario.imaging)
    try:
        rec = reconstruct_kidney(masks, [f.X_BP for f in span], geometry, spacing=spacing)
    except ValueError as e:
        return out | {"volume_note": str(e)}
    return {
        "volume_ml": rec["volume_ml"],
        "volume_error_pct": 100 * (rec["volume_ml"] / (kp.kidney_volume * 1e6) - 1),
        "volume_note": f"closed loop: {len(span)} pole-to-pole masks compounded at "
        f"{spacing * 1e3:g} mm",
    }


# ------------------------------------------------------------------------------- the runs
def run_closed_loop_study(task: StudyTask) -> dict:
    """One study run (er-sweep, starts, efficiency, template) as a full closed-loop scan on
    the Drake diagram (``RunScan``: MultibodyPlant, controller, contact, the scan's own
    imaging, localization and OP pivot), with the kinematic run's record (E_trans,
    E_rot,x, the sweep costs pole to pole and over the whole pivot, V) plus the scan's
    ``status``, ``reason`` and simulated time. A scan that stops before localizing has
    E_trans and E_rot,x None, except at ER 0, where the paper localizes by the initial
    alignment alone (:func:`initial_alignment_record`), and after a registration the
    product's acceptance checks rejected (:func:`rejected_registration_record`).
    ``start_rejected_draws`` and ``study_relaxation`` say what the study changed
    (:func:`closed_loop_setup`)."""
    t0 = time.perf_counter()
    base, kp = task_scenario_and_patient(task)
    scenario, start_fraction, x_offset, notes = closed_loop_setup(task, kp, base)
    template = task_template(task, scenario)
    efficiency = task.study == "efficiency"
    scan = RunScan(
        scenario,
        kp.patient,
        template,
        progress=False,
        start_fraction=start_fraction,
        keep_sweep_masks=efficiency,
    )
    m = ScanMetrics(scan)
    loc = scan.localization
    explore = [f for f in scan.frames if f.phase == int(Phase.EXPLORE)]
    travel = (
        float(
            np.linalg.norm(explore[-1].X_BP.translation()[:2] - explore[0].X_BP.translation()[:2])
            * 1e3
        )
        if len(explore) > 1
        else 0.0
    )
    result = {
        "run_id": run_id(task),
        "task": task.to_dict(),
        "mode": "closed-loop",
        "status": scan.status,
        "reason": scan.reason,
        "patient": task.patient,
        "er": task.er,
        "start": task.start,
        "start_fraction": start_fraction,
        "x_offset_mm": x_offset * 1e3,
        "explore_frames": len(explore),
        "explore_travel_mm": travel,
        "kidney_length_mm": kidney_length(kp) * 1e3,
        "er_unit": task.er_unit,
        "points": int(len(scan.partial_cloud_B)),
        "e_trans_mm": m["e_trans_mm"],
        "e_rot_x_deg": m["e_rot_x_deg"],
        "registration_ms": loc.compute_s * 1e3 if loc.result is not None else None,
        "iterations": None if loc.result is None else int(loc.result.iterations),
        "localization_note": loc.error or "",
        "true_volume_ml": kp.kidney_volume * 1e6,
        "sim_s": scan.sim_s,
        "scan_wall_s": scan.wall_s,
        # The scan's pivot (OP) pole to pole and over the whole pivot, whatever the study.
        "sweep": {
            k: v
            for k, v in closed_loop_entry(m).items()
            if k not in ("curve_eps_mm", "curve_V", "events")
        },
        **notes,
    }
    if result["e_trans_mm"] is None and getattr(loc, "rejected", None) is not None:
        result.update(rejected_registration_record(kp, loc))
    if float(task.er) <= 0:
        xy = scenario.controller.start_xy or km.start_xy(
            kp, start_fraction, scenario.controller.scan_direction, x_offset
        )
        result.update(initial_alignment_record(kp, scan, xy))
        result["registration_ms"], result["iterations"] = None, None
    if task.study == "template":
        result.update(
            template_record(
                task.template_variant, template, kp, scenario.patient.posture, task.patient
            )
        )
    if efficiency:
        strategies = check_strategies(
            task.strategies or CLOSED_LOOP_DEFAULT_STRATEGIES, "closed-loop"
        )
        result["strategies"] = {}
        for s in strategies:
            run = closed_loop_strategy_run(scenario, s, kp, start_fraction)
            same = run.scenario == scenario and run.start_fraction == start_fraction
            other = (
                scan
                if same
                else RunScan(
                    run.scenario,
                    kp.patient,
                    template,
                    progress=False,
                    start_fraction=run.start_fraction,
                    keep_sweep_masks=True,
                )
            )
            mo = m if same else ScanMetrics(other)
            volume = closed_loop_volume(other, mo, kp, float(task.recon_spacing))
            result["strategies"][s] = (
                closed_loop_entry(mo)
                | run.pose
                | volume
                | {
                    "status": other.status,
                    "reason": other.reason,
                    "e_trans_mm": mo["e_trans_mm"],
                    "e_rot_x_deg": mo["e_rot_x_deg"],
                    "sim_s": other.sim_s,
                    "scan_wall_s": other.wall_s,
                    "scan": "the run's own scan" if same else "its own scan",
                }
            )
    result["wall_s"] = time.perf_counter() - t0
    return result


def run_closed_loop(task: StudyTask) -> dict:
    """One closed-loop dynamic scan (the lead's ``RunScan``: MultibodyPlant, controller,
    contact) and the same scan in kinematic mode (same patient, start, ER, segmenter,
    localization method): E_trans, E_rot,x, and n, eps, V pole to pole (the paper's) and
    over the whole pivot, both by :mod:`drake_rus.metrics.sweep`. The closed-loop scan's ER
    multiplies its controller's ``exploration_length`` (the estimated kidney length by
    default); the twin's the task's ``er_unit``."""
    t0 = time.perf_counter()
    base = with_template(
        study_scenario(task.scenario, task.scenarios_file, task.overrides), task.template_file
    )
    scenario = dataclasses.replace(
        base,
        controller=dataclasses.replace(base.controller, exploration_ratio=task.er),
        localization=dataclasses.replace(base.localization, method=task.method),
        imaging=dataclasses.replace(base.imaging, segmenter=task.segmenter),
    )
    X_BPt = scenario.patient.X_BPt.GetDeterministicValue()
    kp = prepared_patient(
        task.patient, scenario.patient.side, scenario.patient.posture, float(task.voxel), X_BPt
    )
    template = load_template(scenario.localization.template)
    scan = RunScan(
        scenario, kp.patient, template, progress=False, start_fraction=float(task.start_fraction)
    )
    m = ScanMetrics(scan)
    at = m["at_matched_V"]
    closed = {
        "status": scan.status,
        "reason": scan.reason,
        "e_trans_mm": m["e_trans_mm"],
        "e_rot_x_deg": m["e_rot_x_deg"],
        "n": m["n_frames"],
        "eps_mm": m["eps_mm"],
        "V": m["volume_ratio"],
        "n_whole_pivot": m["n_whole_pivot"],
        "eps_whole_pivot_mm": m["eps_whole_pivot_mm"],
        "V_whole_pivot": m["volume_ratio_whole_pivot"],
        "at_V": {k: v["pole_to_pole"] for k, v in at.items()},
        "at_V_whole_pivot": {k: v["whole_pivot"] for k, v in at.items()},
        "tilt_cap_legs": m["pivot"]["tilt_cap_legs"],
        "er_unit": getattr(scenario.controller, "exploration_length", "fixed"),
        "sim_s": scan.sim_s,
        "wall_s": scan.wall_s,
        "mode": "closed-loop dynamic simulation",
    }
    t1 = time.perf_counter()
    imager = km.Imager(
        kp,
        km.imaging_for(kp, scenario.imaging, scenario.start),
        task.segmenter,
        seed=int(task.seed),
    )
    sweep = km.explore(
        kp,
        imager,
        scenario.controller,
        exploration_ratio=task.er,
        start_fraction=float(task.start_fraction),
        travel=exploration_travel(
            task.er, task.er_unit, kidney_length(kp), scenario.controller.kidney_length
        ),
    )
    loc = km.localize_cloud(
        kp,
        sweep.point_cloud(),
        template,
        scenario.localization,
        sweep.frames[0].X_BP.translation()[:2],
    )
    op = km.strategy_sweep(kp, imager, "OP", scenario.controller, loc.X_BK)
    kin = sweep_entry(kp, op, imager.geometry, scenario.controller)
    for k in ("curve_eps_mm", "curve_V", "events", "pole_to_pole"):
        kin.pop(k)
    kin.update(
        {
            "e_trans_mm": e_trans(loc.X_BK, kp.X_BK_true) * 1e3,
            "e_rot_x_deg": math.degrees(e_rot_x(loc.X_BK, kp.X_BK_true)),
            "er_unit": task.er_unit,
            "wall_s": time.perf_counter() - t1,
            "mode": km.MODE,
        }
    )
    return {
        "run_id": run_id(task),
        "task": task.to_dict(),
        "mode": "closed-loop + kinematic twin",
        "patient": task.patient,
        "er": task.er,
        "start": -1,
        "kidney_length_mm": kidney_length(kp) * 1e3,
        "closed_loop": closed,
        "kinematic": kin,
        "wall_s": time.perf_counter() - t0,
    }
