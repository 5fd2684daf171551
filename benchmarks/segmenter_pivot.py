"""The segmenter in the pivot's own views, models paired on the same frames (``python -m
benchmarks segmenter_pivot``).

Why: the validation study (``segmenter_inference``) images views sampled around the kidney,
and a model that marks fewer of its kidney-free frames marked more in the scan's pivot
(docs/results/segmenter.md, 2026-11-28 fifth: R, 6.4-8.5% against the shipped 6.4-9.4% on
validation, 46 against 35 pivot false marks in 62 scans). The pivot images something else:
a plane holding the kidney's long axis, tilted about it past the kidney's edge, where the
liver, the spleen, the bowel and the psoas lie beside it. A scan's count is also one draw of
a closed loop: each model's scans take other paths.

What it does, without a scan: each validation patient (``train:A..B``, generated, never a
test patient nor the VH female), in both postures, placed on the bed as the scenario places
it, gets the scan's pivot (eq. 20-23, ``two_leg``): the pivot pose T* of a registered
kidney pose, the probe tilted about its array at the scan's step (``controller.pivot_rate``
/ ``imaging.frame_rate_hz``) from T* past one edge of the kidney, then back through T* past
the other, each leg ending ``--margin`` rad beyond the last frame that shows the true kidney
(at most ``controller.max_pivot_tilt``). The registered pose is the truth in draw 0 and the
truth moved by a registration error in every further draw (``REGISTRATION_ERROR``). Each
frame is imaged once (the emulator at the depth the scan's window planner picks) and
segmented by every model as the scan's Segmenter does (:func:`segment_frame` with its
tracker over the sweep in order and the registered template's predicted section as the
prior: :func:`segment_sweep`), so every model sees the same frames, and the legs' ends do
not depend on any model. What the scan adds and this leaves out: the legs end where the
scan's own segmentation loses the kidney, and the probe indents the skin.

Per model: kidney-free frames (no true kidney in the image) marked as kidney (the pivot's
false marks), frames with the true section at least ``imaging.min_kidney_area`` not marked
(misses), and the IoU of those frames; each against the first model (the scenario's, or
``--onnx-model``) as a paired difference with a 95% interval that resamples whole
patient-postures. Simulation truth judges; nothing here feeds the scan. The last line is
one JSON object.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import sys
import time

import numpy as np
from pydrake.math import RigidTransform, RollPitchYaw

from benchmarks._scan_rows import scenario_from_args
from benchmarks.segmenter_inference import paired_intervals, patients_and_draws
from drake_rus.io_utils import dumps_strict

# A registration error of the size the default scan leaves on fresh generated patients
# (docs/results/segmenter.md, 2026-11-28 fifth: median E_trans 1.6-1.7 mm over 62 scans;
# docs/results/real_kidneys.md: mean E_rot,x 3-4 deg on real kidneys): per draw after the
# first, a translation with this standard deviation (m) on each axis and a rotation about
# each axis with this one (rad).
REGISTRATION_ERROR = (0.0015, math.radians(2.0))
# Beyond the last frame with the true kidney in view, each leg goes on this far (rad): the
# scan's pivot imaged about 18 kidney-free frames a scan (1145 in 62 scans, the same
# section), 9 a leg end, i.e. 0.045 rad at 0.005 rad a frame.
PIVOT_MARGIN = 0.05
VIEW_SEED = 5150
DRAW_STRIDE = 7919
POSTURES = ("supine", "left_lateral_decubitus")


def pivot_angles(
    first_end: float, second_end: float, step: float, margin: float, max_tilt: float
) -> tuple[np.ndarray, np.ndarray]:
    """(angles (rad), leg (1 or 2)) of a ``two_leg`` pivot from T* (angle 0): leg 1 from 0
    to ``first_end`` + ``margin``, leg 2 back through 0 to ``second_end`` - ``margin`` (the
    reversal frame not taken twice), in steps of ``step``, each end within ``max_tilt``.
    ``first_end`` >= 0 >= ``second_end``: the true kidney's last angles in view on each
    side."""
    if not step > 0.0 or not max_tilt > 0.0 or margin < 0.0:
        raise ValueError(
            f"pivot_angles: step and max_tilt must be > 0 and margin >= 0 (rad), got "
            f"{step}, {max_tilt}, {margin}"
        )
    if first_end < 0.0 or second_end > 0.0:
        raise ValueError(
            f"pivot_angles: expected first_end >= 0 >= second_end, got {first_end}, {second_end}"
        )
    hi = min(first_end + margin, max_tilt)
    lo = max(second_end - margin, -max_tilt)
    leg1 = np.arange(0.0, hi + 0.5 * step, step)
    leg1 = np.minimum(leg1, hi)
    leg2 = np.arange(leg1[-1] - step, lo - 0.5 * step, -step)
    leg2 = np.maximum(leg2, lo)
    angles = np.concatenate([leg1, leg2])
    return angles, np.concatenate([np.ones(len(leg1), int), np.full(len(leg2), 2)])


def in_view_ends(angles: np.ndarray, areas: np.ndarray) -> tuple[float, float] | None:
    """(last angle >= 0, first angle <= 0) with a true kidney section (``areas`` > 0) on a
    grid of ``angles`` (rad) through 0, walking out from 0 on each side until the first
    angle without one; None when the kidney is not in view at 0."""
    angles, areas = np.asarray(angles, float), np.asarray(areas, float)
    zero = int(np.argmin(np.abs(angles)))
    if areas[zero] <= 0.0:
        return None
    hi = zero
    while hi + 1 < len(angles) and areas[hi + 1] > 0.0:
        hi += 1
    lo = zero
    while lo > 0 and areas[lo - 1] > 0.0:
        lo -= 1
    return float(max(angles[hi], 0.0)), float(min(angles[lo], 0.0))


def perturbed_pose(X: RigidTransform, rng: np.random.Generator, error=REGISTRATION_ERROR):
    """``X`` moved by a registration error: a translation N(0, error[0]) m per axis and a
    rotation N(0, error[1]) rad about each axis (roll, pitch, yaw in the pose's own frame)."""
    t = rng.normal(0.0, error[0], 3)
    rpy = rng.normal(0.0, error[1], 3)
    R = X.rotation().multiply(RollPitchYaw(rpy).ToRotationMatrix())
    return RigidTransform(R, X.translation() + t)


@dataclasses.dataclass
class PivotFrame:
    """One pivot frame: grey image (uint8), true kidney mask (bool), time (s), pose X_BP."""

    image: np.ndarray
    truth: np.ndarray
    time: float
    X_BP: RigidTransform


def segment_sweep(frames: list[PivotFrame], config, geometry, surface_B: np.ndarray | None):
    """[(kidney visible, mask)] of each of ``frames`` in order, segmented as the scan's
    Segmenter does with ``config`` (its backend and tracker, :func:`segment_frame` and
    :func:`track_update`) and the registered surface ``surface_B`` (N, 3; m, B; None: no
    template prior)."""
    from drake_rus.imaging.frames import UsFrame
    from drake_rus.imaging.segment import KidneyTrack, track_settings, track_update
    from drake_rus.imaging.systems import make_segmenter_backend, segment_frame

    backend = make_segmenter_backend(config, geometry)
    prior = KidneyTrack()
    out = []
    for i, f in enumerate(frames):
        mask_frame, readout, _ = segment_frame(
            backend,
            geometry,
            config.min_kidney_area,
            UsFrame(f.image, f.time, f.X_BP, i),
            prior,
            follows=True,
            uses_prior=True,
            track_confirm=config.track_confirm,
            source="us_image",
            surface_points=surface_B,
            slab=0.5 * config.elevation_width,
            shadow_floor=config.shadow_floor,
            shadow_max_fraction=config.shadow_max_fraction,
        )
        prior = track_update(
            prior,
            mask_frame.image,
            readout.visible,
            f.time,
            geometry,
            **track_settings(config),
        )
        out.append((bool(readout.visible), np.asarray(mask_frame.image, bool)))
    return out


def frame_scores(marked: bool, mask: np.ndarray, truth: np.ndarray, min_pixels: float) -> dict:
    """One frame's record against its truth: ``kind`` "free" (no true kidney), "in_view"
    (the true section at least ``min_pixels``) or "edge" (either answer is right); ``marked``;
    ``iou`` (in view only, else None)."""
    n = int(np.count_nonzero(truth))
    kind = "free" if n == 0 else ("in_view" if n >= min_pixels else "edge")
    iou = None
    if kind == "in_view":
        union = np.count_nonzero(mask | truth)
        iou = float(np.count_nonzero(mask & truth) / union) if union else 0.0
    return {"kind": kind, "marked": bool(marked), "iou": iou}


def pivot_frames(kp, imaging, controller, template_points_K, X_BK_reg, margin, seed):
    """(frames, depth, registered surface in B) of one pivot of patient ``kp`` about the
    pivot pose of the registered kidney pose ``X_BK_reg``: the angles of
    :func:`pivot_angles` with the legs' ends where the true kidney leaves the image;
    ``imaging`` already at the patient's depth. None for frames when the true kidney is not
    in view at T*."""
    from pydrake.math import RotationMatrix

    from drake_rus.control.supervisor import optimal_pivot_pose, rodrigues_pivot_update
    from drake_rus.imaging.emulator import EmulatorModel, emulate
    from drake_rus.imaging.probe import ProbeGeometry
    from drake_rus.imaging.segment import segment_oracle
    from drake_rus.imaging.slicing import slice_volume

    g = ProbeGeometry.from_config(imaging)
    R_star, p_star = optimal_pivot_pose(X_BK_reg.rotation().matrix(), X_BK_reg.translation())
    o, a0 = R_star[:, 0], R_star[:, 2]
    p = np.array([p_star[0], p_star[1], kp.skin(p_star[0], p_star[1])])
    step = controller.pivot_rate / imaging.frame_rate_hz
    max_tilt = controller.max_pivot_tilt

    def pose(angle):
        a = rodrigues_pivot_update(a0, o, angle)
        return RigidTransform(RotationMatrix(np.column_stack([o, np.cross(a, o), a])), p)

    def labels_at(X_BP):
        return slice_volume(
            g,
            kp.volume,
            kp.X_BV,
            X_BP,
            int(imaging.elevation_planes),
            imaging.elevation_combine,
        )

    grid = np.arange(-max_tilt, max_tilt + 0.5 * step, step)
    areas = np.array(
        [np.count_nonzero(segment_oracle(labels_at(pose(t))) & g.fan_mask) for t in grid]
    )
    ends = in_view_ends(grid, areas.astype(float))
    surface_B = X_BK_reg.multiply(np.asarray(template_points_K, float).T).T
    if ends is None:
        return None, surface_B
    angles, _ = pivot_angles(ends[0], ends[1], step, margin, max_tilt)
    model = EmulatorModel.from_config(imaging, g)
    frames = []
    for i, t in enumerate(angles):
        X_BP = pose(float(t))
        labels = labels_at(X_BP)
        frames.append(
            PivotFrame(
                image=emulate(labels, model, seed, i),
                truth=segment_oracle(labels) & g.fan_mask,
                time=i / imaging.frame_rate_hz,
                X_BP=X_BP,
            )
        )
    return frames, surface_B


def arguments(argv=None):
    """(args, (A, B)), or None after one line on stderr naming the bad argument."""
    from drake_rus.cli import add_scenario_arguments

    ap = argparse.ArgumentParser(
        prog="python -m benchmarks segmenter_pivot", description=__doc__.split("\n")[0]
    )
    ap.add_argument("--patients", default="30..37", help="validation patients train:A..B")
    ap.add_argument("--draws", type=int, default=1, help="registration draws (the first exact)")
    ap.add_argument(
        "--margin", type=float, default=PIVOT_MARGIN, help="rad past the kidney's last view"
    )
    ap.add_argument("--onnx-model", default=None, help="the reference (default: the scenario's)")
    ap.add_argument("--compare-models", default="", help="M1,M2,..: paired with the reference")
    ap.add_argument("--no-progress", action="store_true")
    add_scenario_arguments(ap)
    args = ap.parse_args(argv)
    ab, error = patients_and_draws(args)
    if error is None and not 0.0 <= args.margin <= 0.5:
        error = f"--margin: expected 0 to 0.5 rad, got {args.margin}"
    if error:
        print(error, file=sys.stderr)
        return None
    models = [m.strip() for m in args.compare_models.split(",")] if args.compare_models else []
    if not all(models):
        print(
            f"--compare-models: expected comma-separated ONNX model paths, got "
            f"{args.compare_models!r}",
            file=sys.stderr,
        )
        return None
    for m in models + ([args.onnx_model] if args.onnx_model else []):
        if not os.path.isfile(m):
            print(f"--compare-models/--onnx-model: ONNX model file not found: {m}", file=sys.stderr)
            return None
    args.compare_models = models
    return args, ab


def summarise(records: dict, clusters: list, models: list) -> dict:
    """Totals and paired intervals of per-frame ``records`` ({model: [frame_scores]}, every
    model on the same frames, ``clusters`` naming each frame's patient-posture) against
    ``models[0]``: per model the kidney-free frames and how many it marked, the frames in
    view and how many it missed, the mean IoU there, each share's and the IoU's paired
    difference with its 95% interval."""
    ref = records[models[0]]
    kinds = np.array([r["kind"] for r in ref])
    clusters = np.asarray(clusters)
    free, seen = kinds == "free", kinds == "in_view"
    marked = {m: np.array([r["marked"] for r in records[m]], float) for m in models}
    ious = {
        m: np.array([r["iou"] if r["iou"] is not None else np.nan for r in records[m]])
        for m in models
    }
    fp = paired_intervals({m: marked[m][free] for m in models}, list(clusters[free]), models[0])
    miss = paired_intervals(
        {m: 1.0 - marked[m][seen] for m in models}, list(clusters[seen]), models[0]
    )
    iou = paired_intervals({m: ious[m][seen] for m in models}, list(clusters[seen]), models[0])
    return {
        m: {
            "kidney_free": int(free.sum()),
            "marked": int(marked[m][free].sum()),
            "in_view": int(seen.sum()),
            "missed": int((1.0 - marked[m][seen]).sum()),
            "false_mark_share": fp[m],
            "miss_share": miss[m],
            "iou": iou[m],
        }
        for m in models
    }


def _ci(c, scale=1.0, digits=4):
    lo, hi = c
    return f"{scale * lo:+.{digits}f}..{scale * hi:+.{digits}f}"


def main(argv=None) -> int:
    parsed = arguments(argv)
    if parsed is None:
        return 2
    args, (a, b) = parsed
    scenario, error = scenario_from_args(args)
    if error:
        print(error, file=sys.stderr)
        return 2
    from tqdm import tqdm

    from drake_rus.experiments import kinematic as km
    from drake_rus.experiments.patients import prepared_patient
    from drake_rus.imaging.probe import ProbeGeometry
    from drake_rus.localization.localize import load_registration_template

    t0 = time.perf_counter()
    base = dataclasses.replace(scenario.imaging, segmenter="onnx")
    if args.onnx_model:
        base = dataclasses.replace(base, onnx_model=args.onnx_model)
    models = [base.onnx_model] + [m for m in args.compare_models if m != base.onnx_model]
    template = load_registration_template(scenario.localization.template)
    records = {m: [] for m in models}
    clusters, skipped, depths = [], [], {}
    sources = [(k, p) for k in range(a, b + 1) for p in POSTURES]
    seconds = {m: 0.0 for m in models}
    bar = tqdm(
        total=len(sources) * args.draws, desc="pivots", unit="pivot", disable=args.no_progress
    )
    for k, posture in sources:
        name = f"train:{k} {posture}"
        kp = prepared_patient(
            f"train:{k}",
            scenario.patient.side,
            posture,
            0.002,
            scenario.patient.X_BPt.GetDeterministicValue(),
        )
        imaging = km.imaging_for(kp, base, scenario.start)
        depths[name] = float(imaging.depth)
        geometry = ProbeGeometry.from_config(imaging)
        min_pixels = imaging.min_kidney_area / geometry.pixel_area
        for draw in range(args.draws):
            rng = np.random.default_rng([VIEW_SEED, k, POSTURES.index(posture), draw])
            X_BK = kp.X_BK_true if draw == 0 else perturbed_pose(kp.X_BK_true, rng)
            seed = VIEW_SEED + DRAW_STRIDE * draw + 31 * k + POSTURES.index(posture)
            frames, surface_B = pivot_frames(
                kp, imaging, scenario.controller, template.points, X_BK, args.margin, seed
            )
            bar.update()
            if frames is None:
                skipped.append(f"{name} draw {draw}: the kidney is not in view at T*")
                continue
            for m in models:
                cfg = dataclasses.replace(imaging, onnx_model=m)
                t1 = time.perf_counter()
                decisions = segment_sweep(frames, cfg, geometry, surface_B)
                seconds[m] += time.perf_counter() - t1
                records[m] += [
                    frame_scores(v, mask, f.truth, min_pixels)
                    for (v, mask), f in zip(decisions, frames)
                ]
            clusters += [name] * len(frames)
    bar.close()
    if not clusters:
        print("segmenter_pivot: no pivot had the kidney in view at T*", file=sys.stderr)
        return 1
    table = summarise(records, clusters, models)
    ref = models[0]
    print(
        f"\npivot views: train:{a}..{b}, both postures, {args.draws} draw(s), margin "
        f"{args.margin:.3f} rad; depths (mm): "
        + ", ".join(f"{n} {d * 1e3:.0f}" for n, d in depths.items())
    )
    for s in skipped:
        print(f"skipped: {s}")
    for m in models:
        r = table[m]
        line = (
            f"{m}: kidney-free {r['marked']} of {r['kidney_free']} marked "
            f"({100 * r['false_mark_share']['mean']:.1f}%), in view {r['missed']} of "
            f"{r['in_view']} missed ({100 * r['miss_share']['mean']:.1f}%), IoU "
            f"{r['iou']['mean']:.4f}"
        )
        if m != ref:
            fp, miss, iou = r["false_mark_share"], r["miss_share"], r["iou"]
            line += (
                f" | against the reference: marked {100 * fp['difference']:+.2f} points "
                f"({_ci(fp['difference_ci95'], 100, 2)}), missed "
                f"{100 * miss['difference']:+.2f} ({_ci(miss['difference_ci95'], 100, 2)}), "
                f"IoU {iou['difference']:+.4f} ({_ci(iou['difference_ci95'])})"
            )
        print(line)

    def cell(c):
        return {
            "mean": round(c["mean"], 5),
            "ci95": [round(x, 5) for x in c["ci95"]],
            "difference": round(c["difference"], 5),
            "difference_ci95": [round(x, 5) for x in c["difference_ci95"]],
        }

    print(
        dumps_strict(
            {
                "validation": f"train:{a}..{b}",
                "draws": args.draws,
                "margin_rad": args.margin,
                "reference": ref,
                "models": {
                    m: {
                        "kidney_free": table[m]["kidney_free"],
                        "marked": table[m]["marked"],
                        "in_view": table[m]["in_view"],
                        "missed": table[m]["missed"],
                        "false_mark_share": cell(table[m]["false_mark_share"]),
                        "miss_share": cell(table[m]["miss_share"]),
                        "iou": cell(table[m]["iou"]),
                        "segment_seconds": round(seconds[m], 1),
                    }
                    for m in models
                },
                "pivots": len(sources) * args.draws - len(skipped),
                "skipped": skipped,
                "seconds": round(time.perf_counter() - t0, 1),
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
