"""Imaging speed and segmentation accuracy (``python -m benchmarks imaging``).

Speed, on one thread, default scenario imaging (256 x 256 image, 128 scan lines):
- ``fps_slice``: oblique slicing of a held-out patient's label volume;
- ``fps_slice_emulate``: + ultrasound emulation;
- ``fps_full``: + segmentation and the mask read-outs (visible, c_msk, boundary pixels), with
  the learned (onnx) backend when its model exists, else the classical one
  (``fps_full_backend`` says which; ``fps_full_classical`` / ``fps_full_onnx`` give both).
Frames per CPU second of this process (``time.process_time``), which the other jobs on a
shared machine disturb less than wall-clock time, best of 3 passes; ``wall_fps_*`` are the
wall-clock rates. ``load_average`` says how busy the machine was.

Accuracy: mean IoU against the true kidney mask over emulated frames (kidney area >= the
scenario's ``min_kidney_area``) of held-out test patients ``test:0..N-1``, which training never
uses (it uses ``train:K``): ``iou_classical`` and ``iou_onnx`` (null if no model), at the
scenario's depth, supine.

Across depths and postures (the onnx model, one segmenter per depth preset):
- ``iou_by_depth``: held-out generated patients ``test:0..M-1`` (``--depth-patients``, default
  the whole test split of 15) in both postures, the same ``--depth-views`` views of each
  imaged at every preset of ``imaging.depth_presets``; per preset the mean IoU, also split by
  posture; ``iou_by_depth_ci95``: its 95% interval, resampling whole patients-and-postures
  (their frames are correlated; with 15 patients x 30 views it is about +-0.02);
  ``depth_details``: per preset also the share of kidney-free frames marked as kidney,
  ``false_positive_rate``, and its 95% interval ``false_positive_rate_ci95``, resampled the
  same way (a few sources hold most marked frames: 0.04 reads 0.01-0.10);
- ``vh_female``: the real Visible Human female body (``/work/shared/anatomy``, never used in
  training) in both postures, ``--vh-views`` views each, scored against the right kidney at
  the preset a scan would pick (the shallowest holding the kidney below the upper skin,
  10 mm margin), and at every preset;
- ``ms_model_resample``: ms per frame of preprocessing (the physical-canvas resampling) +
  ONNX inference (``onnx_threads``, default 1) + mapping the probability back, per preset;
  ``ms_segment``: the whole onnx segment call (+ largest component, threshold);
  ``ms_segment_plain``: the whole call of the plain segmenter (no mirror average, no
  minimum region area, no guided filter) on the same frames, ``ms_segment_ratio_to_plain``
  the ratio of the means (what the inference-side options cost).
``--set`` measures another scenario's imaging section (e.g. the mirror average off).
With ``--source phantom`` the depth study uses the phantoms and the VH body is skipped.
The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace

import numpy as np
from tqdm import tqdm

from drake_rus.anatomy.cohort import DEFAULT_COUNTS
from drake_rus.io_utils import dumps_strict


def _rate(fn, items, repeat: int = 3):
    """(frames per CPU second, frames per wall second), best of ``repeat`` passes (the
    least disturbed by other jobs, as ``timeit`` does)."""
    best_cpu = best_wall = float("inf")
    for _ in range(repeat):
        t_cpu, t_wall = time.process_time(), time.perf_counter()
        for it in items:
            fn(it)
        best_cpu = min(best_cpu, time.process_time() - t_cpu)
        best_wall = min(best_wall, time.perf_counter() - t_wall)
    n = len(items)
    return n / max(best_cpu, 1e-9), n / max(best_wall, 1e-9)


_T0 = time.perf_counter()


def _stage(text: str) -> None:
    """One progress line on stderr (the JSON result stays the last line of stdout)."""
    print(f"[imaging {time.perf_counter() - _T0:5.0f} s] {text}", file=sys.stderr, flush=True)


def check_arguments(args) -> str | None:
    """The one-line error for a count the benchmark cannot use, or None."""
    for option, least in (
        ("frames", 1),
        ("patients", 1),
        ("iou_frames", 1),
        ("speed_frames", 1),
        ("depth_patients", 0),
        ("depth_views", 0),
        ("vh_views", 0),
    ):
        value = getattr(args, option)
        if value < least:
            return f"--{option.replace('_', '-')}: expected {least} or more, got {value}"
    return None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks imaging", description=__doc__)
    ap.add_argument("--frames", type=int, default=200, help="frames per speed measurement")
    ap.add_argument("--patients", type=int, default=3, help="test patients for the IoU")
    ap.add_argument("--iou-frames", type=int, default=60, help="frames per test patient")
    ap.add_argument(
        "--source",
        default="test",
        choices=["test", "phantom"],
        help="'test' (test:K patients) or 'phantom'",
    )
    ap.add_argument(
        "--depth-patients",
        type=int,
        default=DEFAULT_COUNTS["test"],
        help="held-out patients test:0..M-1 of the per-depth table (default: the "
        "whole test split; 0: skip it)",
    )
    ap.add_argument(
        "--depth-views",
        type=int,
        default=30,
        help="views per patient and posture in the per-depth table",
    )
    ap.add_argument(
        "--vh-views",
        type=int,
        default=240,
        help="views per posture of the VH female body (0: skip it; 60 views gave two "
        "samples 0.02 apart)",
    )
    ap.add_argument(
        "--speed-frames",
        type=int,
        default=60,
        help="frames per preset for the per-preset segmenter speed",
    )
    ap.add_argument("--no-progress", action="store_true", help="no tqdm bars")
    ap.add_argument(
        "--onnx-model",
        default=None,
        help="ONNX model to measure (default: the scenario's imaging.onnx_model)",
    )
    ap.add_argument(
        "--set",
        dest="overrides",
        default=None,
        help="YAML overrides of the default scenario, e.g. "
        '"{imaging: {onnx_mirror_average: false}}" (its imaging section is measured)',
    )
    args = ap.parse_args(argv)
    error = check_arguments(args)
    if error:
        print(error, file=sys.stderr)
        return 2

    from pydrake.math import RigidTransform

    from drake_rus.imaging.config import ImagingConfig
    from drake_rus.imaging.emulator import EmulatorModel, emulate
    from drake_rus.imaging.onnx_backend import OnnxSegmenter, resolve_model_path
    from drake_rus.imaging.probe import ProbeGeometry
    from drake_rus.imaging.segment import read_mask, segment_classical
    from drake_rus.imaging.slicing import slice_volume
    from drake_rus.imaging.training.dataset import ViewSampler
    from drake_rus.imaging.training.evaluation import load_volume, make_source_frames, mean_iou

    cfg = ImagingConfig()
    if args.overrides:
        from drake_rus.scenario import LoadScenario

        try:
            cfg = LoadScenario(scenario_text=args.overrides).imaging
        except ValueError as e:
            print(f"--set: {e}", file=sys.stderr)
            return 2
    if args.onnx_model:
        if not resolve_model_path(args.onnx_model).is_file():
            print(f"--onnx-model: no model at {args.onnx_model}", file=sys.stderr)
            return 2
        cfg = replace(cfg, onnx_model=args.onnx_model)
    g = ProbeGeometry.from_config(cfg)
    model = EmulatorModel.from_config(cfg, g)
    specs = (
        [f"test:{k}" for k in range(args.patients)]
        if args.source == "test"
        else [f"phantom:{5000 + k}" for k in range(args.patients)]
    )
    t0 = time.perf_counter()
    _stage(f"loading {specs[0]} and making {args.frames} frames for the speed measurements")
    vol, up = load_volume(specs[0])
    sampler = ViewSampler(vol, up)
    rng = np.random.default_rng(0)
    poses = [p for p in (sampler.sample(rng) for _ in range(args.frames)) if p is not None]
    X_BV = RigidTransform()
    labels = [slice_volume(g, vol, X_BV, X) for X in poses]
    images = [emulate(lab, model, 0, i) for i, lab in enumerate(labels)]

    onnx_path = resolve_model_path(cfg.onnx_model)
    onnx = OnnxSegmenter.from_config(cfg, g) if onnx_path.is_file() else None

    def classical(us):
        return segment_classical(us, g, None, cfg.min_kidney_area)

    def full(segment):
        def run(i):
            lab = slice_volume(g, vol, X_BV, poses[i])
            us = emulate(lab, model, 0, i)
            read_mask(segment(us), g, cfg.min_kidney_area)

        return run

    idx = list(range(len(poses)))
    _stage(f"speed: slicing, emulation, segmentation ({len(idx)} frames x 3 repeats each)")
    fps_slice, wall_slice = _rate(lambda i: slice_volume(g, vol, X_BV, poses[i]), idx)
    fps_se, wall_se = _rate(
        lambda i: emulate(slice_volume(g, vol, X_BV, poses[i]), model, 0, i), idx
    )
    fps_cl, wall_cl = _rate(full(classical), idx)
    fps_on = wall_on = None
    if onnx is not None:
        fps_on, wall_on = _rate(full(onnx), idx)
    seg_only_onnx = _rate(lambda i: onnx(images[i]), idx)[0] if onnx is not None else None
    seg_only_classical = _rate(lambda i: classical(images[i]), idx)[0]

    ious_cl, ious_on, details = [], [], {}
    for k, spec in enumerate(specs):
        _stage(f"IoU {k + 1}/{len(specs)}: {spec} ({args.iou_frames} frames)")
        frames = make_source_frames(spec, model, args.iou_frames, seed=777 + k)
        r_cl = mean_iou(classical, frames, g, cfg.min_kidney_area)
        r_on = mean_iou(onnx, frames, g, cfg.min_kidney_area) if onnx is not None else None
        details[spec] = {"classical": r_cl, "onnx": r_on}
        ious_cl.append(r_cl["iou"])
        if r_on is not None:
            ious_on.append(r_on["iou"])
        print(
            f"{spec}: classical IoU {r_cl['iou']:.3f}"
            + (f", onnx IoU {r_on['iou']:.3f}" if r_on else "")
            + f" ({r_cl['frames_with_kidney']} frames with kidney)",
            flush=True,
        )

    depth_part = {}
    if onnx is not None and args.depth_patients > 0 and args.depth_views > 0:
        _stage(
            f"per-depth table: {args.depth_patients} patients x 2 postures x "
            f"{args.depth_views} views per preset"
        )
        depth_part = depth_and_posture_study(cfg, args)

    def r(x):
        return None if x is None else round(float(x), 3)

    result = {
        "fps_slice": r(fps_slice),
        "fps_slice_emulate": r(fps_se),
        "fps_full": r(fps_on if fps_on is not None else fps_cl),
        "iou_classical": r(np.mean(ious_cl)),
        "iou_onnx": r(np.mean(ious_on)) if ious_on else None,
        "fps_full_backend": "onnx" if fps_on is not None else "classical",
        "fps_full_classical": r(fps_cl),
        "fps_full_onnx": r(fps_on),
        "fps_segment_only_onnx": r(seg_only_onnx),
        "fps_segment_only_classical": r(seg_only_classical),
        "wall_fps_slice": r(wall_slice),
        "wall_fps_slice_emulate": r(wall_se),
        "wall_fps_full": r(wall_on if wall_on is not None else wall_cl),
        "image_shape": list(g.image_shape),
        "iou_sources": specs,
        "iou_frames_per_source": args.iou_frames,
        "iou_details": details,
        "onnx_model": str(onnx_path) if onnx is not None else None,
        **depth_part,
        "seconds": round(time.perf_counter() - t0, 1),
        "load_average": [round(x, 2) for x in os.getloadavg()],
    }
    print(dumps_strict(result))  # NaN (e.g. no kidney-free frames) as null
    return 0


def _round(x, nd=3):
    return None if x is None or not np.isfinite(x) else round(float(x), nd)


def _segment_speed(segmenters: dict, frames_by_depth: dict, plain: dict | None = None):
    """({depth: ms of resampling + model + back-mapping}, {depth: ms of the whole segment
    call}, {depth: ms of the whole call of the ``plain`` segmenter}) per frame, best of 3
    passes (wall clock, one ONNX thread by default). ``plain`` ({depth: (config, geometry,
    segmenter)}, e.g. without the mirror average) is timed on the same frames right after
    each preset's, so both see the same load; without it the third dict is empty."""
    ms_model, ms_seg, ms_plain = {}, {}, {}
    for d, (_, _, seg) in segmenters.items():
        images = frames_by_depth[d]
        if not images:
            continue

        def model_only(us):
            return seg.to_image(seg.model_probability(us))

        ms_model[d] = 1e3 / _rate(model_only, images)[1]
        ms_seg[d] = 1e3 / _rate(seg, images)[1]
        if plain is not None:
            ms_plain[d] = 1e3 / _rate(plain[d][2], images)[1]
    return ms_model, ms_seg, ms_plain


def depth_and_posture_study(cfg, args) -> dict:
    """Per-depth IoU table (held-out generated patients, both postures), the VH female body
    per posture, and the per-preset segmenter speed."""
    from pydrake.math import RigidTransform

    from drake_rus.imaging.emulator import EmulatorModel, emulate
    from drake_rus.imaging.slicing import slice_volume
    from drake_rus.imaging.training.evaluation import (
        POSTURES,
        VH_FEMALE,
        cluster_bootstrap_ci,
        depth_study,
        load_source,
        sample_views,
        scan_preset,
        segmenters_by_depth,
        summarise,
    )

    presets = [float(p) for p in cfg.depth_presets]
    progress = not args.no_progress
    segmenters = segmenters_by_depth(presets, cfg)
    seg0 = next(iter(segmenters.values()))[2]
    if args.source == "test":
        specs = [(f"test:{k}", p) for k in range(args.depth_patients) for p in POSTURES]
    else:
        specs = [(f"phantom:{5000 + k}", "supine") for k in range(args.depth_patients)]
    sources = [
        load_source(spec, posture=post)
        for spec, post in tqdm(specs, desc="loading patients", disable=not progress)
    ]
    records = depth_study(
        sources, segmenters, args.depth_views, seed=4242, progress=progress, desc="per-depth IoU"
    )
    by_depth = summarise(records)
    by_depth_posture = summarise(records, key=lambda q: (q["depth"], q["posture"]))
    postures = sorted({q["posture"] for q in records}, key=lambda p: POSTURES.index(p))

    print(
        "\nheld-out generated patients "
        + ", ".join(sorted({s.name for s in sources}))
        + f" ({args.depth_views} views each per posture; IoU over frames with a kidney)"
    )
    head = f"{'depth':>7} | {'IoU all':>7} | {'95% interval':>13} | " + " | ".join(
        f"{p[:12]:>12}" for p in postures
    )
    print(
        head
        + f" | {'frames':>6} | {'FP rate (95% interval)':>22} | {'IoU unshadowed (frames)':>23}"
    )
    print("-" * (len(head) + 60))
    for d in presets:
        row = by_depth.get(d)
        if row is None:
            continue
        cells = " | ".join(
            f"{by_depth_posture.get((d, p), {}).get('iou', float('nan')):12.3f}" for p in postures
        )
        lo, hi = row["iou_ci95"]
        fp_lo, fp_hi = row["false_positive_rate_ci95"]
        print(
            f"{d * 1000:5.0f}mm | {row['iou']:7.3f} | {lo:6.3f}-{hi:6.3f} | {cells} | "
            f"{row['frames_with_kidney']:6d} | {row['false_positive_rate']:9.2f} "
            f"({fp_lo:4.2f}-{fp_hi:4.2f}) | "
            f"{row['iou_visible']:15.3f} ({row['frames_visible']:3d})"
        )

    out = {
        "pixel_size_mm": seg0.pixel_size_mm,
        "canvas_px": list(seg0.canvas.shape) if seg0.canvas is not None else None,
        "iou_by_depth": {f"{d:.2f}": _round(v["iou"]) for d, v in sorted(by_depth.items())},
        "iou_by_depth_posture": {
            f"{d:.2f}": {
                p: _round(by_depth_posture[(d, p)]["iou"])
                for p in postures
                if (d, p) in by_depth_posture
            }
            for d in presets
        },
        "iou_by_depth_ci95": {
            f"{d:.2f}": [_round(x) for x in v["iou_ci95"]] for d, v in sorted(by_depth.items())
        },
        "iou_by_depth_min": _round(min(v["iou"] for v in by_depth.values())),
        "iou_by_depth_unshadowed": {
            f"{d:.2f}": _round(v["iou_visible"]) for d, v in sorted(by_depth.items())
        },
        "depth_details": {
            f"{d:.2f}": {
                k: _round(x)
                if isinstance(x, float)
                else [_round(y) for y in x]
                if isinstance(x, tuple)
                else x
                for k, x in v.items()
            }
            for d, v in sorted(by_depth.items())
        },
        "depth_sources": sorted({s.name for s in sources}),
        "depth_views": args.depth_views,
    }

    vh = {}
    if args.source == "test" and args.vh_views > 0:
        vh_sources = [
            load_source(VH_FEMALE, posture=p)
            for p in tqdm(POSTURES, desc="loading VH female", disable=not progress)
        ]
        vh_records = depth_study(
            vh_sources, segmenters, args.vh_views, seed=99, progress=progress, desc="VH female"
        )
        by = summarise(vh_records, key=lambda q: (q["posture"], q["depth"]))
        print(f"\nVH female ({args.vh_views} views per posture; right kidney)")
        for src in vh_sources:
            p = src.posture
            preset = scan_preset(src, presets)
            row = by.get((p, preset), {})
            cells = "  ".join(
                f"{d * 1000:.0f}mm {by[(p, d)]['iou']:.3f} ({by[(p, d)]['frames_with_kidney']})"
                for d in presets
                if (p, d) in by
            )
            print(
                f"  {p}: scan preset {preset * 1000:.0f} mm (kidney needs "
                f"{src.needed_depth() * 1000:.0f} mm): IoU {row.get('iou', float('nan')):.3f} "
                f"over {row.get('frames_with_kidney', 0)} frames (unshadowed "
                f"{row.get('iou_visible', float('nan')):.3f}); per preset: {cells}"
            )
            at_preset = [
                q["iou"]
                for q in vh_records
                if q["posture"] == p and q["depth"] == preset and q["iou"] is not None
            ]
            # One body: the views are the sample (independent probe poses, one frame each
            # at the preset), so the interval resamples views.
            ci = cluster_bootstrap_ci(at_preset, list(range(len(at_preset))))
            print(
                f"    {p} at {preset * 1000:.0f} mm: 95% interval over views "
                f"{ci[0]:.3f}-{ci[1]:.3f}"
            )
            vh[p] = {
                "preset": preset,
                "needed_depth": _round(src.needed_depth()),
                "iou": _round(row.get("iou")),
                "iou_ci95_views": [_round(x) for x in ci],
                "views": args.vh_views,
                "frames_with_kidney": row.get("frames_with_kidney", 0),
                "iou_unshadowed": _round(row.get("iou_visible")),
                "false_positive_rate": _round(row.get("false_positive_rate")),
                "iou_by_depth": {
                    f"{d:.2f}": _round(by[(p, d)]["iou"]) for d in presets if (p, d) in by
                },
            }
    out["vh_female"] = vh or None
    out["vh_female_iou"] = {p: v["iou"] for p, v in vh.items()} or None

    # Speed per preset, on frames of the first source at that depth.
    src = sources[0]
    poses = sample_views(src, args.speed_frames, 5)
    frames_by_depth = {}
    for d, (c, g, _) in segmenters.items():
        model = EmulatorModel.from_config(c, g)
        frames_by_depth[d] = [
            emulate(slice_volume(g, src.volume, RigidTransform(), X), model, 0, i)
            for i, X in enumerate(poses)
        ]
    # The plain segmenter: the same model and threshold, one model run per frame (no mirror,
    # no ensemble), no minimum region area (the cost of the inference-side options, measured
    # in this run).
    plain_cfg = replace(
        cfg,
        onnx_mirror_average=False,
        onnx_min_region_area=0.0,
        onnx_guided_radius=0.0,
        onnx_ensemble_model="",
    )
    plain = segmenters_by_depth(presets, plain_cfg)
    ms_model, ms_seg, ms_plain = _segment_speed(segmenters, frames_by_depth, plain)
    print(
        "\nsegmenter speed (ms per frame, wall clock, "
        f"{cfg.onnx_threads} ONNX thread(s)): resampling + model + back-mapping / whole call"
        f" (mirror average {'on' if cfg.onnx_mirror_average else 'off'}) / whole call of the "
        "plain segmenter (one model run)"
    )
    print(
        "  "
        + "  ".join(
            f"{d * 1000:.0f}mm {ms_model[d]:.2f} / {ms_seg[d]:.2f} / {ms_plain[d]:.2f}"
            for d in ms_model
        )
    )
    ratio = float(np.mean(list(ms_seg.values())) / np.mean(list(ms_plain.values())))
    print(f"  whole call against the plain segmenter's: x{ratio:.2f} (mean over presets)")
    out["ms_model_resample"] = {f"{d:.2f}": _round(v, 2) for d, v in ms_model.items()}
    out["ms_segment"] = {f"{d:.2f}": _round(v, 2) for d, v in ms_seg.items()}
    out["ms_segment_plain"] = {f"{d:.2f}": _round(v, 2) for d, v in ms_plain.items()}
    out["ms_segment_ratio_to_plain"] = _round(ratio, 2)
    out["inference"] = {
        "threshold": cfg.onnx_threshold,
        "mirror_average": cfg.onnx_mirror_average,
        "ensemble_model": cfg.onnx_ensemble_model,
        "min_region_area_m2": cfg.onnx_min_region_area,
        "guided_radius_m": cfg.onnx_guided_radius,
        "guided_eps": cfg.onnx_guided_eps,
    }
    out["ms_model_resample_mean"] = _round(float(np.mean(list(ms_model.values()))), 2)
    return out


if __name__ == "__main__":
    raise SystemExit(main())
