"""The scan's checks of its own result before it says DONE.

A scan that reached DONE has only done its job if (a) its sweep saw the kidney leave the
image on both sides (each pivot leg ended because the segmentation lost the kidney, not at
the tilt cap), (b) what the segmentation saw agrees with the registered template (where
the kidney left the image on each side against where the template predicts, and how much
of the registered kidney the frames that showed it swept) and (c) the registration is
sound (RMS residual, inlier fraction, shape weights, pose uncertainty, and a kidney placed
where anatomy puts one: below the probe face within the image, its long axis along the
body). Every check uses only what a real station has: probe poses, the segmentation's
kidney-visible flag, the registration, the template and the patient's placement on the
bed; never the simulation truth. Thresholds: the scenario's ``verdict`` section
(:class:`~drake_rus.scan.config.VerdictConfig`, with their reasons).

Each check is a plain function returning a :class:`Check`; :func:`JudgeScan` runs them on
a finished scan and :func:`Verdict` turns them into the final status: DONE when none
failed, else INCOMPLETE naming the failed checks and their figures.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from drake_rus.control.supervisor import Phase
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.localization.localize import body_directions_B, max_rms_residual
from drake_rus.localization.pivot_view import pivot_residual, pivot_residual_bound

__all__ = [
    "Check",
    "INCOMPLETE",
    "JudgeScan",
    "Verdict",
    "check_axis_direction",
    "check_inlier_fraction",
    "check_kidney_depth",
    "check_pivot_residual",
    "pivot_residual_bound",
    "check_pole_offsets",
    "equivalent_tilts",
    "sweep_frames",
    "check_rms_residual",
    "check_shape_weights",
    "check_sweep_ends",
    "check_template_coverage",
    "check_translation_sd",
    "imaged_counts",
    "template_volume_sample",
]

# The status of a scan that ran to its end but whose result failed a check.
INCOMPLETE = "INCOMPLETE"


@dataclasses.dataclass(frozen=True)
class Check:
    """One check of a scan's result: ``value`` against ``threshold`` (both in ``unit``;
    ``rule`` says which way passes, e.g. ">="), ``passed`` (None: not applicable to this
    scan, e.g. no registration on a line sweep), ``detail`` one line for people."""

    name: str
    value: float | None
    threshold: float | None
    unit: str
    rule: str
    passed: bool | None
    detail: str

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def _na(name: str, unit: str, rule: str, why: str) -> Check:
    return Check(name, None, None, unit, rule, None, f"not applicable: {why}")


def _judge(name, value, threshold, unit, rule, what) -> Check:
    ok = value >= threshold if rule == ">=" else value <= threshold
    # Lengths are stored in m and shown in mm.
    k, shown = (1e3, " mm") if unit == "m" else (1.0, "" if unit == "fraction" else f" {unit}")
    return Check(
        name,
        float(value),
        float(threshold),
        unit,
        rule,
        bool(ok),
        f"{what} {value * k:.3g}{shown} ({'' if ok else 'not '}{rule} {threshold * k:.3g})",
    )


# ----------------------------------------------------------------------------- (a) sweep
def check_sweep_ends(causes, kind: str) -> Check:
    """(a) The sweep saw the kidney leave the image at each of its ends: a pivot's two ends
    (both legs, or the predicted_end strategy's pre-tilt and sweep), a line's one end, each
    declared because the segmentation lost the kidney (``causes`` from the supervisor:
    "kidney_left", "tilt_cap", "max_travel"). Value: the ends where the kidney left."""
    needed = 1 if kind == "line" else 2
    causes = list(causes)
    left = sum(c == "kidney_left" for c in causes)
    ok = len(causes) >= needed and left >= needed
    other = [
        f"end {i + 1}: {c.replace('_', ' ')}" for i, c in enumerate(causes) if c != "kidney_left"
    ]
    detail = (
        f"the kidney left the image at {left} of the {needed} sweep ends"
        + (f" ({', '.join(other)})" if other else "")
        + ("" if len(causes) >= needed else f"; only {len(causes)} ended")
    )
    return Check("sweep_ends", float(left), float(needed), "ends", ">=", ok, detail)


# ---------------------------------------------------------------- (b) seen vs predicted
def template_volume_sample(surface_B: np.ndarray, layers: int = 10):
    """(points (L N, 3), weights (L N,)): a volume sample of the solid bounded by the
    registered template surface ``surface_B`` (N, 3): the surface scaled about its centroid
    by s = 1/L .. 1, each copy weighted by s^2 (the area of its shell), so that the
    weighted fraction of points inside a region approximates its volume fraction."""
    surface = np.asarray(surface_B, float).reshape(-1, 3)
    c = surface.mean(axis=0)
    scales = np.arange(1, layers + 1) / layers
    points = np.concatenate([c + s * (surface - c) for s in scales])
    weights = np.repeat(scales**2, len(surface))
    return points, weights / weights.sum()


def _in_slab_and_fan(points_B, X_BP, geometry: ProbeGeometry, slab_half_width: float):
    M = np.asarray(X_BP.GetAsMatrix4() if hasattr(X_BP, "GetAsMatrix4") else X_BP, float)
    p_P = (points_B - M[:3, 3]) @ M[:3, :3]
    inside = np.abs(p_P[:, 1]) <= slab_half_width
    idx = np.flatnonzero(inside)
    if len(idx):
        inside[idx] = geometry.in_fan(p_P[idx])
    return inside


def check_template_coverage(
    surface_B, poses, visible, geometry: ProbeGeometry, min_coverage: float
) -> Check:
    """(b) Fraction of the registered kidney's volume (:func:`template_volume_sample` of
    ``surface_B``) inside the slab (the elevational beam width) and fan of some sweep frame
    that showed the kidney (``poses``: X_BP per frame, ``visible`` its flag): how much of
    the kidney the registration says is there the scan actually imaged."""
    points, weights = template_volume_sample(surface_B)
    covered = np.zeros(len(points), bool)
    for X, v in zip(poses, visible):
        if v:
            covered |= _in_slab_and_fan(points, X, geometry, 0.5 * geometry.elevation_width)
    value = float(weights[covered].sum())
    return _judge(
        "template_coverage",
        value,
        min_coverage,
        "fraction",
        ">=",
        "fraction of the registered kidney's volume swept by frames showing it:",
    )


def imaged_counts(
    points_B, pivot_point, a0, o, thetas, geometry: ProbeGeometry, slab_half_width: float
) -> np.ndarray:
    """How many of ``points_B`` (N, 3) a probe with its tip at ``pivot_point`` images when
    its approach ``a0`` is turned by each of ``thetas`` (rad) about the array ``o`` (eq. 23;
    the geometry of laws.pivot_end_angles, both signs at once): points within
    ``slab_half_width`` of the image plane and inside the fan. (T,) ints."""
    o = np.asarray(o, float).reshape(3)
    o = o / np.linalg.norm(o)
    a0 = np.asarray(a0, float).reshape(3)
    a0 = a0 - float(a0 @ o) * o
    a0 = a0 / np.linalg.norm(a0)
    b0 = np.cross(o, a0)
    q = np.asarray(points_B, float).reshape(-1, 3) - np.asarray(pivot_point, float).reshape(3)
    x, qa, qb = q @ o, q @ a0, q @ b0
    th = np.asarray(thetas, float).reshape(-1, 1)
    c, s = np.cos(th), np.sin(th)
    z = qa * c + qb * s
    y = qa * s - qb * c
    zc = z + geometry.radius
    line = np.arctan2(np.broadcast_to(x, zc.shape), zc)
    d = np.hypot(x, zc) - geometry.radius
    seen = (
        (np.abs(y) <= slab_half_width)
        & (np.abs(line) <= geometry.half_angle)
        & (d >= 0.0)
        & (d <= geometry.depth)
    )
    return seen.sum(axis=1)


def equivalent_tilts(poses, p0, a0, o, depth: float) -> np.ndarray:
    """The tilt (rad, about ``o`` from ``a0``, eq. 23's sign) that a probe with its tip at
    ``p0`` needs for its image plane to pass where each pose's plane does at ``depth`` (m)
    below p0 along a0: atan(l / depth), l the plane's offset across the array there. A
    pose whose tip is at p0 gives its own tilt; a tip slid across (the slide at the tilt
    cap) adds the slide to l. ``poses``: 4x4 X_BP matrices whose array is along ``o``."""
    o = np.asarray(o, float).reshape(3)
    a0 = np.asarray(a0, float).reshape(3)
    p0 = np.asarray(p0, float).reshape(3)
    b0 = np.cross(o, a0)
    out = []
    for M in poses:
        M = np.asarray(M, float)
        p, a = M[:3, 3], M[:3, 2]
        s = (depth - float((p - p0) @ a0)) / max(float(a @ a0), 1e-9)
        out.append(math.atan2(float((p - p0 + s * a) @ b0), depth))
    return np.asarray(out, float)


def check_pole_offsets(
    surface_B,
    poses,
    visible,
    geometry: ProbeGeometry,
    max_offset: float,
    min_points: int = 1,
    angle_range: float = 1.2,
    step: float = math.radians(0.25),
) -> Check:
    """(b) Where the pivot saw the kidney against where the registered template predicts
    it: the sweep's tilt angles (about the first frame's array axis, from its approach;
    :func:`equivalent_tilts`, so that a slide at the tilt cap counts as far as it moved
    the image plane at the kidney's depth) of the first and last frames showing the
    kidney, against the tilts at which at least ``min_points`` of the registered template
    ``surface_B`` lie in the slab and fan
    (:func:`imaged_counts` on a grid of ``step`` over +-``angle_range``). Each end's
    disagreement as a distance at the registered kidney's depth D below the pivot point,
    D |tan(theta_seen) - tan(theta_predicted)| (m); value: the larger of the two."""
    poses = list(poses)
    visible = np.asarray(visible, bool)
    if not visible.any():
        return Check(
            "pole_offsets",
            None,
            float(max_offset),
            "m",
            "<=",
            False,
            "the kidney was never seen during the sweep",
        )
    mats = [np.asarray(X.GetAsMatrix4() if hasattr(X, "GetAsMatrix4") else X, float) for X in poses]
    p0, o, a0 = mats[0][:3, 3], mats[0][:3, 0], mats[0][:3, 2]
    surface = np.asarray(surface_B, float).reshape(-1, 3)
    depth = float((surface.mean(axis=0) - p0) @ a0)
    grid = np.arange(-angle_range, angle_range + 0.5 * step, step)
    counts = imaged_counts(
        surface,
        p0,
        o=o,
        a0=a0,
        thetas=grid,
        geometry=geometry,
        slab_half_width=0.5 * geometry.elevation_width,
    )
    in_view = grid[counts >= min_points]
    if len(in_view) == 0 or depth <= 0:
        return Check(
            "pole_offsets",
            None,
            float(max_offset),
            "m",
            "<=",
            False,
            "the registered kidney is never in view of the pivot",
        )
    # Each frame's tilt; a slide at the tilt cap counts as far as it moved the plane at D.
    angles = equivalent_tilts(mats, p0, a0, o, depth)
    seen = (float(angles[visible].min()), float(angles[visible].max()))
    predicted = (float(in_view.min()), float(in_view.max()))
    offsets = [abs(depth * (math.tan(s) - math.tan(p))) for s, p in zip(seen, predicted)]
    worst = int(np.argmax(offsets))
    value = offsets[worst]
    ok = value <= max_offset
    side = ("negative", "positive")[worst]
    detail = (
        f"the kidney was seen from {math.degrees(seen[0]):.1f} to "
        f"{math.degrees(seen[1]):.1f} deg of tilt (a slide at the cap as the tilt reaching "
        f"as far at its depth), the registered template predicts "
        f"{math.degrees(predicted[0]):.1f} to {math.degrees(predicted[1]):.1f} deg: "
        f"{value * 1e3:.1f} mm apart at its depth ({depth * 1e3:.0f} mm) on the "
        f"{side} side ({'' if ok else 'not '}<= {max_offset * 1e3:.3g} mm)"
    )
    return Check("pole_offsets", float(value), float(max_offset), "m", "<=", ok, detail)


def check_pivot_residual(
    surface_B, cloud_B, pivot_B, max_excess: float, percentile: float = 90.0
) -> Check:
    """(b) How far the kidney the pivot saw lies from the registered template, against how
    far the explored cloud the template was fitted to lies: the ``percentile`` of the
    distances from the pivot frames' boundary points ``pivot_B`` (M, 3) to the nearest
    point of the registered template ``surface_B`` (N, 3), minus the same of the explored
    cloud ``cloud_B`` (K, 3) (m); at most ``max_excess``. The rule is
    ``localization.pivot_view.pivot_residual``, the one the scan evaluates at the pivot's
    end before DONE (its second look)."""
    pivot = np.asarray(pivot_B, float).reshape(-1, 3)
    cloud = np.asarray(cloud_B, float).reshape(-1, 3)
    if len(pivot) == 0 or len(cloud) == 0:
        what = "no pivot boundary points" if len(pivot) == 0 else "no explored cloud"
        return _na("pivot_residual", "m", "<=", what)
    seen, fitted = pivot_residual(surface_B, cloud, pivot, percentile)
    value = seen - fitted
    ok = value <= max_excess
    detail = (
        f"{percentile:g}th percentile of the distances to the registered template: pivot "
        f"boundary {seen * 1e3:.1f} mm, explored cloud {fitted * 1e3:.1f} mm, "
        f"{value * 1e3:.1f} mm more ({'' if ok else 'not '}<= {max_excess * 1e3:.3g} mm)"
    )
    return Check("pivot_residual", value, float(max_excess), "m", "<=", ok, detail)


def pivot_boundary_points(boundaries, frames, geometry: ProbeGeometry) -> np.ndarray:
    """(M, 3) in B: the boundary pixels (``boundaries``: BoundaryPixels of the PIVOT
    frames) of the sweep ``frames`` that showed the kidney, each back-projected with its
    own frame's X_BP."""
    if not len(boundaries):
        return np.zeros((0, 3))
    shown = {int(f.frame_index) for f in frames if f.visible}
    points = [
        geometry.pixel_to_B(b.pixels, b.X_BP)
        for b in boundaries
        if int(b.frame_index) in shown and len(b.pixels)
    ]
    return np.concatenate(points) if points else np.zeros((0, 3))


# ------------------------------------------------------------------- (c) registration
def check_rms_residual(rms: float, max_rms: float, min_rms: float = 0.0) -> Check:
    """(c) The registration's RMS plane-to-plane residual (m) within the localizer's bound
    ``max_rms``, and not below ``min_rms``: boundary points come from pixels, so a fit that
    measured anything leaves at least their quantization (a degenerate template, e.g. with
    all-zero normals, leaves exactly 0)."""
    if rms < min_rms:
        return Check(
            "rms_residual",
            float(rms),
            float(min_rms),
            "m",
            ">=",
            False,
            f"registration RMS residual {rms * 1e3:.3g} mm, below the boundary "
            f"pixels' quantization ({min_rms * 1e3:.3g} mm): a degenerate fit",
        )
    return _judge("rms_residual", rms, max_rms, "m", "<=", "registration RMS residual")


def check_inlier_fraction(fraction: float, min_fraction: float) -> Check:
    """(c) Fraction of the explored points within 3 mm of the registered template."""
    return _judge(
        "inlier_fraction",
        fraction,
        min_fraction,
        "fraction",
        ">=",
        "explored points near the registered template:",
    )


def check_shape_weights(b, variances, max_sd: float) -> Check:
    """(c) The deformable registration's shape-mode weights within ``max_sd`` standard
    deviations of the template's cohort; value: the largest |b_k| / sqrt(variance_k)."""
    b = np.asarray(b, float).reshape(-1)
    sd = np.sqrt(np.asarray(variances, float).reshape(-1)[: len(b)])
    z = np.abs(b) / sd
    k = int(np.argmax(z))
    check = _judge(
        "shape_weights", float(z[k]), max_sd, "SD", "<=", f"largest shape-mode weight (mode {k})"
    )
    return check


def check_translation_sd(covariance, max_sd: float) -> Check:
    """(c) The registration's translation uncertainty (m): the root of the trace of the
    6x6 pose covariance's translation block ([dtheta, dt] order)."""
    trace = float(np.trace(np.asarray(covariance, float).reshape(6, 6)[3:, 3:]))
    value = math.sqrt(max(0.0, trace)) if math.isfinite(trace) else math.inf
    return _judge(
        "translation_sd", value, max_sd, "m", "<=", "registration translation uncertainty"
    )


def check_kidney_depth(p_BK, pivot_point, a0, min_depth: float, max_depth: float) -> Check:
    """(c) The registered kidney's centre below the probe face at the pivot, along the beam
    ``a0`` (m): between ``min_depth`` (skin, fat and muscle) and ``max_depth`` (the image
    depth)."""
    a = np.asarray(a0, float) / np.linalg.norm(a0)
    depth = float((np.asarray(p_BK, float) - np.asarray(pivot_point, float)) @ a)
    ok = min_depth <= depth <= max_depth
    return Check(
        "kidney_depth",
        depth,
        float(max_depth if depth > max_depth else min_depth),
        "m",
        "<=" if depth > max_depth else ">=",
        ok,
        f"registered kidney centre {depth * 1e3:.0f} mm below the probe face "
        f"({'' if ok else 'not '}within {min_depth * 1e3:.0f}-{max_depth * 1e3:.0f}"
        " mm)",
    )


def check_axis_direction(x_K_B, superior_B, max_angle: float) -> Check:
    """(c) The registered long axis (x_K, towards the upper pole) within ``max_angle``
    (rad) of the body's superior direction."""
    x = np.asarray(x_K_B, float) / np.linalg.norm(x_K_B)
    u = np.asarray(superior_B, float) / np.linalg.norm(superior_B)
    angle = math.degrees(math.atan2(np.linalg.norm(np.cross(x, u)), float(x @ u)))
    return _judge(
        "axis_direction",
        angle,
        math.degrees(max_angle),
        "deg",
        "<=",
        "registered long axis from the body's superior direction:",
    )


# -------------------------------------------------------------------------- the scan
def sweep_frames(frames, kind: str, registered_at: float = -math.inf) -> list:
    """The frames of the sweep (``kind`` "line": EXPLORE, else PIVOT) acquired from
    ``registered_at`` (s, the time of the registration judged) on: after a re-localization
    the PIVOT frames about the former registration's pivot point belong to another sweep
    (a patient shift moved the kidney 10-20 mm between them) and would be judged against
    the new one."""
    phase = int(Phase.EXPLORE if kind == "line" else Phase.PIVOT)
    return [f for f in frames if int(f.phase) == phase and f.time >= registered_at]


def judged_sweep_frames(result, kind: str) -> list:
    """The frames of ``result``'s sweep that the verdict judges and the metrics measure
    (:func:`sweep_frames` from the time of the registration the scan ended with: after a
    re-localization, only the last pivot)."""
    outcome = getattr(result, "localization", None)
    registered_at = -math.inf
    if kind != "line" and outcome is not None and outcome.result is not None:
        registered_at = float(outcome.time)
    return sweep_frames(result.frames, kind, registered_at)


def JudgeScan(result, template) -> list[Check]:
    """Every check of a finished scan (a ScanResult; ``template`` the RegistrationTemplate
    it registered), with the thresholds of ``result.scenario.verdict``. Checks that need a
    registration are not applicable (passed None) without one: a line sweep or a given
    pivot pose, or a scan that stopped before localizing."""
    sc = result.scenario
    cfg = sc.verdict
    kind = getattr(sc.controller, "sweep", "pivot")
    checks = [check_sweep_ends(result.sweep_end_causes, kind)]
    frames = judged_sweep_frames(result, kind)
    poses = [f.X_BP for f in frames]
    visible = [bool(f.visible) for f in frames]
    loc = result.localization.result if result.localization is not None else None
    names = (
        "pole_offsets",
        "template_coverage",
        "pivot_residual",
        "rms_residual",
        "inlier_fraction",
        "shape_weights",
        "translation_sd",
        "kidney_depth",
        "axis_direction",
    )
    units = ("m", "fraction", "m", "m", "fraction", "SD", "m", "m", "deg")
    rules = ("<=", ">=", "<=", "<=", ">=", "<=", "<=", ">=", "<=")
    if loc is None or result.registered_template_B is None:
        why = (
            "a line sweep has no registration"
            if kind == "line"
            else "the pivot pose was given (controller.pivot_pose), no registration"
            if getattr(sc.controller, "pivot_pose", None)
            else "no registration"
        )
        return checks + [_na(n, u, r, why) for n, u, r in zip(names, units, rules)]
    geometry = ProbeGeometry.from_config(sc.imaging)
    surface = np.asarray(result.registered_template_B, float)
    if frames:
        min_points = max(1, math.ceil(cfg.view_min_fraction * len(surface) - 1e-9))
        checks.append(
            check_pole_offsets(surface, poses, visible, geometry, cfg.max_pole_offset, min_points)
        )
        checks.append(
            check_template_coverage(surface, poses, visible, geometry, cfg.min_template_coverage)
        )
    else:
        checks += [
            Check(n, None, None, u, r, False, "no sweep frames")
            for n, u, r in zip(names[:2], units[:2], rules[:2])
        ]
    lc = sc.localization
    b = loc.shape_coefficients
    max_rms = max_rms_residual(lc, template, b is not None)
    pivot_B = (
        pivot_boundary_points(getattr(result, "pivot_boundaries", ()), frames, geometry)
        if kind != "line"
        else np.zeros((0, 3))
    )
    checks.append(
        check_pivot_residual(
            surface,
            np.zeros((0, 3))
            if getattr(result, "partial_cloud_B", None) is None
            else result.partial_cloud_B,
            pivot_B,
            pivot_residual_bound(
                cfg.pivot_residual_excess,
                max_rms,
                sc.respiration.mode,
                lc.tracking_hold_allowance,
            ),
            cfg.pivot_residual_percentile,
        )
    )
    checks.append(
        check_rms_residual(
            loc.rms_residual,
            max_rms,
            cfg.min_rms_residual_pixels * min(geometry.dx, geometry.dz),
        )
    )
    checks.append(check_inlier_fraction(loc.inlier_fraction, lc.min_inlier_fraction))
    if b is not None and len(b) and template.variances is not None:
        checks.append(check_shape_weights(b, template.variances, cfg.max_shape_sd))
    else:
        checks.append(_na("shape_weights", "SD", "<=", "a rigid registration (no shape modes)"))
    checks.append(check_translation_sd(loc.covariance, cfg.max_translation_sd))
    X_BK = loc.X_BK
    if frames:
        M0 = frames[0].X_BP.GetAsMatrix4()
        checks.append(
            check_kidney_depth(
                X_BK.translation(), M0[:3, 3], M0[:3, 2], cfg.min_kidney_depth, sc.imaging.depth
            )
        )
    else:
        checks.append(Check("kidney_depth", None, None, "m", ">=", False, "no sweep frames"))
    superior_B, _ = body_directions_B(
        sc.patient.X_BPt.GetDeterministicValue(), sc.patient.side, sc.patient.posture
    )
    checks.append(
        check_axis_direction(
            X_BK.rotation().matrix()[:, 0], superior_B, math.radians(cfg.max_axis_angle_deg)
        )
    )
    return checks


def Verdict(checks) -> tuple[str, str]:
    """("DONE", "") when no check failed, else (INCOMPLETE, the failed checks named with
    their figures)."""
    failed = [c for c in checks if c.passed is False]
    if not failed:
        return "DONE", ""
    return INCOMPLETE, "failed checks: " + "; ".join(f"{c.name}: {c.detail}" for c in failed)
