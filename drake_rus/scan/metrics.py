"""The paper's metrics of one scan (section III) and the scan's summary.

E_trans (x-y distance of the kidney centroids), E_rot,x (angle between the kidney x-axes),
and the sweep costs of :mod:`drake_rus.metrics.sweep` (the same functions the studies use):
eps (eq. 24, L = the image depth), n and V (eq. 25) **pole to pole** (the paper's
definition), the **whole pivot**'s n, eps and V (both legs) beside them, n and eps needed to
reach V = 0.9, and the pivot legs the tilt cap ended. E_trans, E_rot,x and V need the
simulation truth; without it (hardware) they are None.

The sweep is the PIVOT phase's frames, or with ``controller.sweep: line`` (the seed's
straight-line baseline) the EXPLORE phase's (a one-way sweep: pole to pole from its first to
its last frame showing the kidney; "whole pivot" then means the whole line).
:func:`SweepDescription` says which, and which pose the pivot used (the registered T* or a
given ``controller.pivot_pose``).
"""

from __future__ import annotations

import math

import numpy as np

from drake_rus.control.force_loop import phase_force_statistics
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.localization.tracking import tracking_limits
from drake_rus.metrics import (
    MATCHED_V,
    POLE_TO_POLE,
    WHOLE_PIVOT,
    CoverageAccumulator,
    e_rot_x,
    e_trans,
    pivot_legs,
    signed_pivot_angles,
    sweep_efficiency,
)
from drake_rus.scan.run import ScanResult
from drake_rus.scan.verdict import judged_sweep_frames

__all__ = ["METRIC_DEFINITIONS", "ScanMetrics", "Summary", "SweepDescription", "V_TARGETS"]

# Coverage levels at which the sweep costs are also compared (matched coverage).
V_TARGETS = (0.9,)
METRIC_DEFINITIONS = {
    "n_frames, eps_mm, volume_ratio": POLE_TO_POLE,
    "n_whole_pivot, eps_whole_pivot_mm, volume_ratio_whole_pivot": WHOLE_PIVOT,
    "at_matched_V": MATCHED_V,
    "volume_ratio_all_frames": "V (eq. 25) over every frame of the scan (exploration too)",
    "eps": "eq. 24, sum of sqrt(|dp|^2 + (L dtheta)^2), L = the image depth",
    "kidney_length_checks": "the localizer's kidney-length estimates during EXPLORE (time s, "
    "probe travel mm, estimated length mm; null: the fit failed its "
    "checks); with exploration_length: estimated, EXPLORE ends at "
    "exploration_ratio x the latest estimate",
    "checks": "the scan's checks of its own result (scan/verdict.py, thresholds in the "
    "scenario's verdict section), from what a real station has, never the truth: "
    "value, threshold and unit, rule (which way passes), passed (null: not "
    "applicable), detail; a DONE scan with a failed check ends INCOMPLETE",
    "sweep": "the frames the costs count: the PIVOT phase's, or with controller.sweep: line "
    "the EXPLORE phase's (then 'whole pivot' is the whole line); sweep.pivot_pose "
    "says where the pivot pivoted (registered T* or a given controller.pivot_pose)",
}


def SweepDescription(controller) -> dict:
    """What the scan swept and where it pivoted: ``kind`` "pivot" or "line" (the sweep's
    phase, PIVOT or EXPLORE); ``pivot_pose`` "registered" (T* of the registered kidney pose,
    eq. 20-22), "given" (``controller.pivot_pose``, then ``given_pivot_pose`` [x m, y m,
    yaw rad]) or None (a line); ``pivot_strategy``; ``text``, one line for people."""
    kind = getattr(controller, "sweep", "pivot")
    given = [float(v) for v in getattr(controller, "pivot_pose", None) or []]
    if kind == "line":
        return {
            "kind": "line",
            "phase": "EXPLORE",
            "pivot_pose": None,
            "given_pivot_pose": None,
            "pivot_strategy": None,
            "text": "straight line (controller.sweep: line): the exploration controller "
            "(eq. 17) over the whole kidney, no pivot",
        }
    strategy = controller.pivot_strategy
    if given:
        text = (
            f"{strategy} pivot at the given pose (controller.pivot_pose): tip ("
            f"{given[0] * 1e3:.1f}, {given[1] * 1e3:.1f}) mm, array "
            f"{math.degrees(given[2]):.1f} deg from base x, probe pointing down; no "
            "exploration or localization"
        )
    else:
        text = f"{strategy} pivot at T* of the registered kidney pose (eq. 20-22)"
    return {
        "kind": "pivot",
        "phase": "PIVOT",
        "pivot_pose": "given" if given else "registered",
        "given_pivot_pose": given or None,
        "pivot_strategy": strategy,
        "text": text,
    }


def _reach_mm(r):
    return None if r is None else {"n": r["n"], "eps_mm": r["eps"] * 1000}


def ScanMetrics(result: ScanResult) -> dict:
    """The seed's metrics for one scan (section III): E_trans, E_rot,x, and eps, n, V pole to
    pole (the paper's) with the whole pivot's beside them, on the sweep the verdict judges
    (after a re-localization, the last pivot only: :func:`verdict.judged_sweep_frames`)."""
    imaging = result.scenario.imaging
    ctrl = result.scenario.controller
    sweep = SweepDescription(ctrl)
    line = sweep["kind"] == "line"
    pivot = judged_sweep_frames(result, sweep["kind"])
    poses = [f.X_BP for f in pivot]
    angles = None if line else signed_pivot_angles([X.rotation() for X in poses])
    legs = np.zeros(len(poses), int) if line else pivot_legs(angles)
    truth = result.truth
    coverage = None
    if truth is not None:
        geometry = ProbeGeometry.from_config(imaging)

        def coverage():
            return CoverageAccumulator(
                truth.kidney_points_B, truth.voxel_volume, geometry.in_fan, imaging.elevation_width
            )

    eff = sweep_efficiency(
        poses,
        [f.visible for f in pivot],
        imaging.depth,
        legs=None if line else legs,
        coverage=coverage,
        V_targets=V_TARGETS,
        angles=angles,
        max_tilt=None if line else ctrl.max_pivot_tilt,
    )
    ends = (
        []
        if line
        else [
            float(np.rad2deg(angles[legs == k][np.argmax(np.abs(angles[legs == k]))]))
            for k in (1, 2)
            if np.any(legs == k)
        ]
    )
    metrics = {
        "n_frames": eff["n"],
        "eps_mm": eff["eps"] * 1000,
        "eps_curve_mm": (eff["eps_curve"] * 1000).tolist(),
        "n_whole_pivot": eff["n_whole_pivot"],
        "eps_whole_pivot_mm": eff["eps_whole_pivot"] * 1000,
        "eps_whole_pivot_curve_mm": (eff["eps_whole_pivot_curve"] * 1000).tolist(),
        "volume_ratio": eff["V"],
        "volume_ratio_whole_pivot": eff["V_whole_pivot"],
        "volume_ratio_all_frames": None,
        "V_curve": [] if eff["V_curve"] is None else eff["V_curve"].tolist(),
        "V_whole_pivot_curve": (
            [] if eff["V_whole_pivot_curve"] is None else eff["V_whole_pivot_curve"].tolist()
        ),
        "at_matched_V": {
            f"{t:g}": {
                "pole_to_pole": _reach_mm(eff["at_V"][t]),
                "whole_pivot": _reach_mm(eff["at_V_whole_pivot"][t]),
            }
            for t in V_TARGETS
        },
        "sweep": sweep,
        "pivot": {
            "legs": int(legs.max()) if len(legs) else 0,
            "leg_end_tilt_deg": ends,
            "tilt_cap_deg": float(np.rad2deg(ctrl.max_pivot_tilt)),
            "tilt_cap_legs": eff["tilt_cap_legs"],
            # Why each leg ended (the supervisor) and the slides at the tilt cap (mm).
            "end_causes": list(getattr(result, "sweep_end_causes", ())),
            "cap_slide_mm": {
                str(int(leg)): float(d) * 1000 for leg, d in getattr(result, "cap_slides", ())
            },
            "pole_to_pole_frames": (
                [int(eff["pole_to_pole"][0]), int(eff["pole_to_pole"][-1])]
                if len(eff["pole_to_pole"])
                else []
            ),
        },
        "e_trans_mm": None,
        "e_rot_x_deg": None,
    }
    if truth is None:
        return metrics
    all_cov = coverage()
    for f in result.frames:
        all_cov.add_frame(f.X_BP)
    metrics["volume_ratio_all_frames"] = all_cov.ratio
    if result.X_BK_estimated is not None:
        metrics["e_trans_mm"] = e_trans(result.X_BK_estimated, truth.X_BK) * 1000
        metrics["e_rot_x_deg"] = float(np.rad2deg(e_rot_x(result.X_BK_estimated, truth.X_BK)))
    return metrics


def _mode(scenario) -> str:
    if scenario.hardware:
        hw = scenario.hardware_interface
        robot = (
            f"FR3 at {hw.robot_ip} (franky-control)"
            if hw.backend == "franky"
            else f"FR3 through drake-franka-driver on {hw.lcm_url}"
        )
        video = hw.video_source.strip() or "none"
        return (
            f"hardware: {robot}, video {video}, controller "
            f"{scenario.controller.rate_hz:.0f} Hz, real time"
            + (", dry run (no motion commanded)" if hw.dry_run else "")
        )
    return (
        f"closed-loop dynamic simulation (MultibodyPlant "
        f"{scenario.contact.time_step * 1000:g} ms "
        f"{scenario.contact.discrete_contact_approximation.upper()}, controller "
        f"{scenario.controller.rate_hz:.0f} Hz, images "
        f"{scenario.imaging.frame_rate_hz:.0f} Hz)"
    )


def _length_checks(checks) -> list:
    """The localizer's length checks as JSON rows (mm; None for a failed fit)."""
    return [
        {
            "time_s": round(float(t), 3),
            "travel_mm": round(float(travel) * 1e3, 1),
            "length_mm": round(float(length) * 1e3, 1) if math.isfinite(length) else None,
        }
        for t, travel, length in checks
    ]


def _er_unit(controller) -> str:
    """What the scan's ER multiplies (the controller's ``exploration_length``)."""
    L_m = controller.kidney_length * 1000
    if getattr(controller, "exploration_length", "fixed") == "estimated":
        return (
            f"the kidney length estimated from the explored cloud (L_m = {L_m:g} mm until "
            f"an estimate exists, clipped to [L_m / {controller.exploration_length_factor:g}"
            f", {controller.exploration_length_factor:g} L_m])"
        )
    return f"the fixed kidney length L_m = {L_m:g} mm"


def _force_block(result: ScanResult) -> dict:
    """The contact force per phase: mean and ripple (RMS about the mean, N; EXPLORE after
    its first 0.5 s, the landing), from the true contact force in simulation, else from the
    estimated, low-pass filtered force the controller uses (hardware)."""
    if "force_true" in result.logs:
        t, wrench = result.logs["force_true"]
        F, source = -np.asarray(wrench)[5], "true contact force"
    else:
        t, F = result.logs["force"][0], result.logs["force"][1][0]
        source = "estimated contact force, low-pass filtered"
    stats = phase_force_statistics(t, F, result.phases)
    return {
        "source": source,
        "log_period_s": float(np.median(np.diff(t))) if len(t) > 1 else None,
        "ripple": "RMS about the phase's mean (its standard deviation)",
        **{name: {k: round(v, 4) for k, v in row.items()} for name, row in stats.items()},
    }


def Summary(result: ScanResult, metrics: dict, provenance: dict | None = None) -> dict:
    """The JSON summary of a scan (``summary.json``); ``provenance``
    (:func:`drake_rus.provenance.Provenance`): what a rerun needs, kept as given."""
    loc = result.localization
    diag = None
    if loc.result is not None:
        diag = {
            "iterations": loc.result.iterations,
            "converged": loc.result.converged,
            "rms_residual_mm": loc.result.rms_residual * 1000,
            "inlier_fraction": loc.result.inlier_fraction,
            "points": loc.n_points,
            "compute_ms": loc.compute_s * 1000,
            "method": result.scenario.localization.method,
            "stop_reason": loc.result.stop_reason,
            "cycle_period": loc.result.cycle_period,
        }
    # The kidney tracking's limits for this registration (the monitor computes the same).
    limits = tracking_limits(loc.result, result.scenario.localization)
    force = result.logs["force"][1][0]
    return {
        "status": result.status,
        "reason": result.reason,
        "patient": result.patient,
        # The scan's checks of its own result (scan/verdict.py): DONE only if none failed.
        "checks": {
            c.name: {k: v for k, v in c.as_dict().items() if k != "name"}
            for c in getattr(result, "checks", [])
        },
        "e_trans_mm": metrics["e_trans_mm"],
        "e_rot_x_deg": metrics["e_rot_x_deg"],
        "eps_mm": metrics["eps_mm"],
        "n_frames": metrics["n_frames"],
        "volume_ratio": metrics["volume_ratio"],
        "eps_whole_pivot_mm": metrics["eps_whole_pivot_mm"],
        "n_whole_pivot": metrics["n_whole_pivot"],
        "volume_ratio_whole_pivot": metrics["volume_ratio_whole_pivot"],
        "volume_ratio_all_frames": metrics["volume_ratio_all_frames"],
        "at_matched_V": metrics["at_matched_V"],
        "pivot": metrics["pivot"],
        "sweep": metrics["sweep"],
        "metric_definitions": METRIC_DEFINITIONS,
        "wall_s": result.wall_s,
        "sim_s": result.sim_s,
        "realtime_rate": result.sim_s / result.wall_s if result.wall_s > 0 else None,
        "phases": [
            {"phase": n, "start_s": a, "end_s": b, "duration_s": b - a} for n, a, b in result.phases
        ],
        "localization": diag,
        "localization_error": loc.error or None,
        "max_kidney_drift_mm": (
            max(d for _, d in result.tracking_drift) * 1000 if result.tracking_drift else None
        ),
        "tracking_limit_mm": limits.limit * 1000 if loc.result is not None else None,
        "tracking_axial_allowance_mm": (
            limits.axial_allowance * 1000 if loc.result is not None else None
        ),
        # The exploration the registration came from: "partial" (ER x L, the paper's) or
        # "whole_kidney" (the second look, controller.second_look), and why the second look
        # was taken (None: not taken).
        "exploration": (
            "whole_kidney" if getattr(result, "whole_kidney_exploration", False) else "partial"
        ),
        "second_look": getattr(result, "second_look_reason", "") or None,
        "exploration_length": result.scenario.controller.exploration_length,
        "exploration_ratio": result.scenario.controller.exploration_ratio,
        "exploration_ratio_unit": _er_unit(result.scenario.controller),
        "kidney_length_checks": _length_checks(result.length_checks),
        "image_depth_m": result.scenario.imaging.depth,
        "start": (
            result.start_plan.summary()
            if result.start_plan is not None
            else {"planner": "none" if result.scenario.hardware else result.scenario.start.planner}
        ),
        "segmenter": result.scenario.imaging.segmenter,
        "registration_method": result.scenario.localization.method,
        "peak_force_n": float(np.max(force)) if len(force) else 0.0,
        "force": _force_block(result),
        "frames_total": len(result.frames),
        # Exploration frames left out of the partial cloud: their section jumped from the
        # last frames' (imaging.cloud_section_jump; docs/imaging.md).
        "cloud_frames_inconsistent": getattr(result, "cloud_frames_inconsistent", 0),
        "safety_events": [str(e) for e in result.safety_events],
        "mode": _mode(result.scenario),
        # Where perception ran and its jobs' compute times and latencies (executor.py).
        "perception": getattr(result, "perception", None) or None,
        # A live run's per-tick compute time and lag (ms: p50, p99, p99.9, max), slips and
        # the load average (drake_rus/pacing.py); None when not paced at real time.
        "loop_timing": getattr(result, "loop_timing", None),
        **({} if provenance is None else {"provenance": provenance}),
    }
