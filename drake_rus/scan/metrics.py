"""The paper's metrics of one scan (section III) and the scan's summary.

E_trans (x-y distance of the kidney centroids), E_rot,x (angle between the kidney x-axes),
eps (eq. 24, L = the image depth), n (frames during the pivot) and V (eq. 25). E_trans,
E_rot,x and V need the simulation truth; without it (hardware) they are None.
"""

from __future__ import annotations

import numpy as np

from drake_rus.control.supervisor import Phase
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.localization.tracking import tracking_limits
from drake_rus.metrics import CoverageAccumulator, e_rot_x, e_trans, window_steps
from drake_rus.scan.run import ScanResult

__all__ = ["ScanMetrics", "Summary"]


def ScanMetrics(result: ScanResult) -> dict:
    """The seed's metrics for one scan (section III): E_trans, E_rot,x, eps, n, V."""
    imaging = result.scenario.imaging
    pivot = [f for f in result.frames if f.phase == Phase.PIVOT]
    eps_curve = np.concatenate([[0.0], np.cumsum(
        window_steps([f.X_BP for f in pivot], imaging.depth))]) if pivot else np.zeros(1)
    metrics = {
        "n_frames": len(pivot),
        "eps_mm": float(eps_curve[-1] * 1000) if pivot else 0.0,
        "eps_curve_mm": (eps_curve * 1000).tolist(),
        "volume_ratio": None, "volume_ratio_all_frames": None, "V_curve": [],
        "e_trans_mm": None, "e_rot_x_deg": None,
    }
    truth = result.truth
    if truth is None:
        return metrics
    geometry = ProbeGeometry.from_config(imaging)
    coverage = CoverageAccumulator(truth.kidney_points_B, truth.voxel_volume, geometry.in_fan,
                                   imaging.elevation_width)
    V_curve = [coverage.add_frame(f.X_BP) for f in pivot]
    all_cov = CoverageAccumulator(truth.kidney_points_B, truth.voxel_volume, geometry.in_fan,
                                  imaging.elevation_width)
    for f in result.frames:
        all_cov.add_frame(f.X_BP)
    metrics.update(volume_ratio=float(V_curve[-1]) if V_curve else 0.0,
                   volume_ratio_all_frames=all_cov.ratio, V_curve=V_curve)
    if result.X_BK_estimated is not None:
        metrics["e_trans_mm"] = e_trans(result.X_BK_estimated, truth.X_BK) * 1000
        metrics["e_rot_x_deg"] = float(np.rad2deg(e_rot_x(result.X_BK_estimated, truth.X_BK)))
    return metrics


def _mode(scenario) -> str:
    if scenario.hardware:
        hw = scenario.hardware_interface
        robot = (f"FR3 at {hw.robot_ip} (franky-control)" if hw.backend == "franky"
                 else f"FR3 through drake-franka-driver on {hw.lcm_url}")
        video = hw.video_source.strip() or "none"
        return (f"hardware: {robot}, video {video}, controller "
                f"{scenario.controller.rate_hz:.0f} Hz, real time"
                + (", dry run (no motion commanded)" if hw.dry_run else ""))
    return (f"closed-loop dynamic simulation (MultibodyPlant "
            f"{scenario.contact.time_step * 1000:g} ms "
            f"{scenario.contact.discrete_contact_approximation.upper()}, controller "
            f"{scenario.controller.rate_hz:.0f} Hz, images "
            f"{scenario.imaging.frame_rate_hz:.0f} Hz)")


def Summary(result: ScanResult, metrics: dict) -> dict:
    """The JSON summary of a scan (``summary.json``)."""
    loc = result.localization
    diag = None
    if loc.result is not None:
        diag = {"iterations": loc.result.iterations, "converged": loc.result.converged,
                "rms_residual_mm": loc.result.rms_residual * 1000,
                "inlier_fraction": loc.result.inlier_fraction, "points": loc.n_points,
                "compute_ms": loc.compute_s * 1000,
                "method": result.scenario.localization.method,
                "stop_reason": loc.result.stop_reason, "cycle_period": loc.result.cycle_period}
    # The kidney tracking's limits for this registration (the monitor computes the same).
    limits = tracking_limits(loc.result, result.scenario.localization)
    force = result.logs["force"][1][0]
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
        "tracking_limit_mm": limits.limit * 1000 if loc.result is not None else None,
        "tracking_axial_allowance_mm": (limits.axial_allowance * 1000
                                        if loc.result is not None else None),
        "exploration_length": result.scenario.controller.exploration_length,
        "exploration_ratio": result.scenario.controller.exploration_ratio,
        "image_depth_m": result.scenario.imaging.depth,
        "start": (result.start_plan.summary() if result.start_plan is not None
                  else {"planner": "none" if result.scenario.hardware
                        else result.scenario.start.planner}),
        "segmenter": result.scenario.imaging.segmenter,
        "peak_force_n": float(np.max(force)) if len(force) else 0.0,
        "frames_total": len(result.frames),
        "safety_events": [str(e) for e in result.safety_events],
        "mode": _mode(result.scenario),
    }
