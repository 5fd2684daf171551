"""Fine-tuning on a new machine's look (``python -m benchmarks segmenter_finetune``; the
``train`` extra).

The stand-in for a lab's own ultrasound machine: frames rendered by a second method and grey
map that training never used (:data:`MACHINE_B`): the emulator without speckle (a smooth,
speckle-free rendering, where scan-line to scan-line attenuation shows as streaks, as a
strongly compounded image approaches it) at a 30 dB dynamic range (training: 42-58 dB),
then a grey map with gamma 0.5 (training: linear gain and contrast changes only). The
shipped model has never seen such frames.

Fine-tuning frames: ``--tune-frames`` (50) frames showing the kidney, from training-split
patients ``train:0..`` (supine, each at the preset a scan would pick). Held-out frames:
``--held-out-views`` views of each of ``--held-out-patients`` test-split patients ``test:0..``
in the new look (and the same views in the emulator's own look, to see what fine-tuning
costs there). Both are written as folders in the Open Kidney layout (``--out``) and the
fine-tuning is the command's own (:func:`drake_rus.imaging.training.fine_tune.fine_tune`
with ``--held-out``). ``--interpolate``: the same fine-tune mixed with the original model,
weight by weight, at each of these weights of the fine-tune (WiSE-FT,
:mod:`drake_rus.imaging.training.interpolate`; ``fine-tune --interpolate``), scored on both
looks. Prints a table and, last, one JSON line.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from drake_rus.config_schema import SEED_MAX, SEED_RANGE
from drake_rus.io_utils import dumps_strict

MACHINE_B = {"speckle": False, "dynamic_range_db": 30.0}
GREY_GAMMA = 0.5


def machine_b_image(image: np.ndarray, fan: np.ndarray, gamma: float = GREY_GAMMA) -> np.ndarray:
    """The new machine's grey map: grey' = 255 (grey / 255)^gamma in the fan, 0 outside."""
    x = (np.asarray(image, np.float32) / 255.0) ** gamma
    return np.where(fan, np.clip(np.rint(255.0 * x), 0, 255), 0).astype(np.uint8)


def make_frames(specs, n_per_source, seed, config, look_b: bool, kidney_only: bool):
    """SavedFrame-like frames (and depths) of the sources: each at its scan preset, views
    from ``sample_views``; ``look_b``: the new machine's look; ``kidney_only``: only views
    showing the kidney (area >= min_kidney_area)."""
    from pydrake.math import RigidTransform

    from drake_rus.imaging.annotated import SavedFrame
    from drake_rus.imaging.emulator import EmulatorModel, emulate
    from drake_rus.imaging.probe import ProbeGeometry
    from drake_rus.imaging.slicing import slice_volume
    from drake_rus.imaging.training.evaluation import load_source, sample_views, scan_preset

    frames, depths = [], []
    for si, spec in enumerate(specs):
        src = load_source(spec, posture="supine")
        depth = scan_preset(src, config.depth_presets) or max(config.depth_presets)
        cfg = replace(config, depth=depth, **(MACHINE_B if look_b else {}))
        g = ProbeGeometry.from_config(cfg)
        model = EmulatorModel.from_config(cfg, g)
        poses = sample_views(src, 3 * n_per_source if kidney_only else n_per_source, seed + si)
        kept = 0
        for i, X in enumerate(poses):
            if kept == n_per_source:
                break
            labels = slice_volume(g, src.volume, RigidTransform(), X)
            mask = src.kidney_mask(labels, g, X)
            has = bool(mask.sum() * g.pixel_area >= config.min_kidney_area)
            if kidney_only and not has:
                continue
            us = emulate(labels, model, seed + si, i)
            if look_b:
                us = machine_b_image(us, g.fan_mask)
            index = 1000 * si + i
            frames.append(SavedFrame(us, mask & has, 0.0, index, spec, has, X))
            depths.append(depth)
            kept += 1
    return frames, depths


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m benchmarks segmenter_finetune", description=__doc__
    )
    ap.add_argument("--tune-patients", type=int, default=5, help="train:0..N-1")
    ap.add_argument("--tune-frames", type=int, default=50, help="fine-tuning frames in all")
    ap.add_argument("--held-out-patients", type=int, default=5, help="test:0..M-1")
    ap.add_argument("--held-out-views", type=int, default=30, help="views per held-out patient")
    ap.add_argument("--epochs", type=int, default=40)
    ap.add_argument("--lr", type=float, default=5e-4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="runs/segmenter_finetune_demo")
    ap.add_argument(
        "--interpolate",
        default="0.5,0.75",
        help="comma-separated weights of the fine-tune in (0, 1) to mix with the original "
        "model and score too ('' for none)",
    )
    args = ap.parse_args(argv)
    try:
        alphas = [float(a) for a in args.interpolate.split(",") if a.strip()]
    except ValueError:
        alphas = [float("nan")]
    if not all(0.0 < a < 1.0 for a in alphas):
        ap.error(
            f"--interpolate: expected weights in (0, 1) like 0.5,0.75, got {args.interpolate!r}"
        )
    if not 0 <= args.seed <= SEED_MAX:
        ap.error(f"--seed: expected {SEED_RANGE}, got {args.seed}")
    try:
        import torch  # noqa: F401
    except ImportError:
        print(dumps_strict({"skipped": "needs the train extra (PyTorch)"}))
        return 0

    from drake_rus.imaging.annotated import read_annotated_frames, write_annotated_frames
    from drake_rus.imaging.config import ImagingConfig
    from drake_rus.imaging.training.fine_tune import fine_tune, frames_iou, trainable_source
    from drake_rus.imaging.training.interpolate import interpolate_models

    t0 = time.perf_counter()
    config = ImagingConfig()
    out = Path(args.out)
    if out.exists() and any(out.iterdir()):
        print(f"--out: {out} is not empty; give a new folder", file=sys.stderr)
        return 2
    per = int(np.ceil(args.tune_frames / args.tune_patients))
    tune, tune_d = make_frames(
        [f"train:{k}" for k in range(args.tune_patients)], per, 100 + args.seed, config, True, True
    )
    tune, tune_d = tune[: args.tune_frames], tune_d[: args.tune_frames]
    held_specs = [f"test:{k}" for k in range(args.held_out_patients)]
    held_b, held_d = make_frames(held_specs, args.held_out_views, 500, config, True, False)
    held_a, _ = make_frames(held_specs, args.held_out_views, 500, config, False, False)
    shape = (config.image_height_px, config.image_width_px)
    folders = {}
    for name, frames, depths in (
        ("tune_machine_b", tune, tune_d),
        ("held_out_machine_b", held_b, held_d),
        ("held_out_emulator", held_a, held_d),
    ):
        folders[name] = read_annotated_frames(
            write_annotated_frames(out / name, frames, depths), shape
        )
    card = fine_tune(
        folders["tune_machine_b"],
        config,
        out / "model",
        epochs=args.epochs,
        lr=args.lr,
        seed=args.seed,
        held_out=folders["held_out_machine_b"],
        held_out_source=str(out / "held_out_machine_b"),
        frames_source=str(out / "tune_machine_b"),
        command="python -m benchmarks segmenter_finetune " + " ".join(argv or []),
    )
    new_model = out / "model" / card["model"]
    ev = card["evaluation"]
    before_a = frames_iou(config.onnx_model, folders["held_out_emulator"], config)
    after_a = frames_iou(new_model, folders["held_out_emulator"], config)
    rows = [
        ("new machine (held-out test:0..)", ev["before"], ev["after"]),
        ("the emulator's own look (same views)", before_a, after_a),
    ]
    mixes = []
    source = trainable_source(config.onnx_model)
    for alpha in alphas:
        mixed = interpolate_models(
            source, new_model, alpha, out / f"model_alpha_{alpha:g}", name=new_model.stem
        )
        mixes.append(
            (
                alpha,
                frames_iou(mixed, folders["held_out_machine_b"], config),
                frames_iou(mixed, folders["held_out_emulator"], config),
                mixed,
            )
        )
    print(
        f"\nfine-tuned on {len(tune)} frames of the new machine's look "
        f"({args.tune_patients} training patients); IoU on held-out frames"
    )
    print(
        f"{'frames':40s} {'n':>4s} {'before':>7s} {'after':>7s} {'FP before':>9s} {'FP after':>9s}"
        + "".join(f" {'alpha ' + format(a, 'g'):>10s}" for a in alphas)
    )
    for k, (name, b, a) in enumerate(rows):
        print(
            f"{name:40s} {b['frames_with_kidney']:4d} {b['iou']:7.3f} {a['iou']:7.3f} "
            f"{b['false_positive_rate']:9.2f} {a['false_positive_rate']:9.2f}"
            + "".join(f" {m[1 + k]['iou']:10.3f}" for m in mixes)
        )
    if mixes:
        print(
            "alpha: (1 - alpha) x the original + alpha x the fine-tune, weight by weight "
            "(after = alpha 1)"
        )
    print(
        dumps_strict(
            {
                "tune_frames": len(tune),
                "tune_sources": [f"train:{k}" for k in range(args.tune_patients)],
                "held_out_sources": held_specs,
                "machine_b": {**MACHINE_B, "grey_gamma": GREY_GAMMA},
                "before_model": ev["before_model"],
                "iou_machine_b_before": round(ev["before"]["iou"], 4),
                "iou_machine_b_after": round(ev["after"]["iou"], 4),
                "frames_machine_b": ev["after"]["frames_with_kidney"],
                "iou_emulator_before": round(before_a["iou"], 4),
                "iou_emulator_after": round(after_a["iou"], 4),
                "fp_machine_b_before": round(ev["before"]["false_positive_rate"], 3),
                "fp_machine_b_after": round(ev["after"]["false_positive_rate"], 3),
                "interpolated": [
                    {
                        "alpha": alpha,
                        "iou_machine_b": round(b["iou"], 4),
                        "iou_emulator": round(a["iou"], 4),
                        "fp_machine_b": round(b["false_positive_rate"], 3),
                        "fp_emulator": round(a["false_positive_rate"], 3),
                        "model": str(path),
                    }
                    for alpha, b, a, path in mixes
                ],
                "fp_emulator_before": round(before_a["false_positive_rate"], 3),
                "fp_emulator_after": round(after_a["false_positive_rate"], 3),
                "epochs": args.epochs,
                "train_seconds": card["fine_tuning"]["train_seconds"],
                "model": str(new_model),
                "seconds": round(time.perf_counter() - t0, 1),
            }
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
