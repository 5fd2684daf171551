"""Fine-tuning the learned segmenter on a user's annotated frames (needs the ``train`` extra).

A lab's ultrasound machine has its own look (point-spread function, speckle, grey map); the
seed fine-tuned its network on 154 images of its own machine (80.8% IoU, docs/facts/paper.md).
Here the frames come as a folder in the Open Kidney Ultrasound Data Set's mask layout
(:mod:`drake_rus.imaging.annotated`; ``drake-rus scan --save-frames`` writes one, ready to
correct in an annotation tool). :func:`fine_tune` maps them onto the model's physical canvas
(:class:`~drake_rus.imaging.onnx_backend.PhysicalCanvas`, at each frame's imaging depth),
keeps the last ``holdout`` share (by name: the end of a recorded sequence, whose neighbours
are not in training) aside, rebuilds the U-Net from the ONNX model's weights
(:func:`~drake_rus.imaging.training.train_segmenter.unet_from_onnx`), trains it on the rest
(flips, gain and contrast jitter; one-cycle learning rate) and exports it with a card that
records the held-out IoU before (the model the scenario runs now) and after. With
``interpolate`` below 1 the model it writes is the weight-space mix ``(1 - alpha) x the
original + alpha x the fine-tune`` (:mod:`~drake_rus.imaging.training.interpolate`, WiSE-FT),
which keeps more of the original's accuracy on the looks it was trained on; the plain
fine-tune is written beside it (``NAME_alone.onnx``) and the card gives both held-out IoUs.

The plain functions: :func:`held_out_split`, :func:`frames_on_canvas`, :func:`frames_iou`.
"""

from __future__ import annotations

import shutil
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from drake_rus.imaging.annotated import AnnotatedFrames
from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.onnx_backend import (
    OnnxSegmenter,
    PhysicalCanvas,
    card_canvas,
    read_model_card,
    resolve_model_path,
)
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.imaging.segment import iou
from drake_rus.imaging.training.interpolate import (
    interpolated_model,
    interpolation_record,
    load_model,
    sha256,
)
from drake_rus.imaging.training.train_segmenter import export_onnx, train, unet_from_onnx
from drake_rus.io_utils import dumps_strict


def held_out_split(n: int, share: float) -> tuple[np.ndarray, np.ndarray]:
    """(training indices, held-out indices) of n frames in name order: the last
    round(share n) frames (at least 1, and at least 1 left to train on) are held out, the
    end of a recorded sequence, so that no held-out frame has its neighbour in training."""
    if n < 2:
        raise ValueError(f"fine-tuning needs at least 2 frames (1 to train, 1 held out), got {n}")
    if not 0.0 < share < 1.0:
        raise ValueError(f"--holdout: expected a share between 0 and 1, got {share}")
    k = min(max(int(round(share * n)), 1), n - 1)
    return np.arange(n - k), np.arange(n - k, n)


def _geometry(config: ImagingConfig, depth: float) -> ProbeGeometry:
    return ProbeGeometry.from_config(replace(config, depth=float(depth)))


def frames_on_canvas(
    frames: AnnotatedFrames, config: ImagingConfig, card: dict
) -> tuple[np.ndarray, np.ndarray]:
    """(images uint8 (N, H, W), kidney area fraction x 255 uint8 (N, H, W)) of the frames on
    the model card's physical canvas, each mapped from the probe's image grid at its depth
    (the training data's form, ``train_segmenter.build_canvas_dataset``)."""
    canvas = card_canvas(card, "the model card")
    if canvas is None:
        raise ValueError(
            "the model card declares no physical canvas (pixel_size_mm, canvas_px): "
            "fine-tuning works on models of train_segmenter"
        )
    H, W = canvas["shape"]
    X = np.zeros((len(frames), H, W), np.uint8)
    Y = np.zeros((len(frames), H, W), np.uint8)
    maps: dict = {}
    for i in range(len(frames)):
        d = round(float(frames.depth[i]), 6)
        m = maps.get(d)
        if m is None:
            m = maps[d] = PhysicalCanvas(
                _geometry(config, d), canvas["pixel_size"], canvas["shape"], canvas["top"]
            )
        X[i] = np.clip(np.rint(m.to_canvas(frames.images[i])), 0, 255).astype(np.uint8)
        Y[i] = np.rint(m.to_canvas(frames.masks[i].astype(np.float32)) * 255).astype(np.uint8)
    return X, Y


def frames_iou(model_path, frames: AnnotatedFrames, config: ImagingConfig) -> dict:
    """Mean IoU of an ONNX model (as the scan runs it: physical canvas, largest region, no
    tracking; the model alone, without an ``onnx_ensemble_model``) against the frames'
    masks, over the frames that show the kidney; and the share of frames without it where
    the model marks one (false positives; NaN, not measured, when every frame shows the
    kidney: the card writes it as null)."""
    cfg = replace(config, segmenter="onnx", onnx_model=str(model_path), onnx_ensemble_model="")
    segmenters: dict = {}
    ious, fp, empty = [], 0, 0
    for i in range(len(frames)):
        d = round(float(frames.depth[i]), 6)
        seg = segmenters.get(d)
        if seg is None:
            c = replace(cfg, depth=d)
            seg = segmenters[d] = OnnxSegmenter.from_config(c, ProbeGeometry.from_config(c))
        pred = np.asarray(seg(frames.images[i]), bool)
        if frames.kidney[i]:
            ious.append(iou(pred, frames.masks[i]))
        else:
            empty += 1
            fp += int(pred.sum() * seg.geometry.pixel_area >= config.min_kidney_area)
    return {
        "iou": float(np.mean(ious)) if ious else float("nan"),
        "iou_median": float(np.median(ious)) if ious else float("nan"),
        "frames_with_kidney": len(ious),
        "frames_without_kidney": empty,
        "false_positive_rate": fp / empty if empty else float("nan"),
    }


def _evaluation(before: dict, after: dict, before_model: str) -> dict:
    """The card's ``evaluation``: held-out IoU of the scenario's model before and of the
    written model after (:func:`frames_iou` records)."""
    return {
        "held_out_iou_before": round(before["iou"], 4),
        "held_out_iou_after": round(after["iou"], 4),
        "before": before,
        "after": after,
        "before_model": before_model,
        "measured_by": "drake-rus segmenter fine-tune (imaging.training.fine_tune.frames_iou)",
    }


def check_model_name(name) -> str:
    """``--name`` as a plain file name (no folder, not hidden, not empty), or ValueError
    naming it: the model, its card and, when mixed, ``NAME_alone`` go into ``out`` as
    ``NAME.onnx`` and ``NAME.json``."""
    text = str(name)
    if (
        not text.strip()
        or text != text.strip()
        or "/" in text
        or "\\" in text
        or "\0" in text
        or text.startswith(".")
    ):
        raise ValueError(
            f"--name: expected a file name without a folder (the model is written as "
            f"OUT/NAME.onnx beside its card OUT/NAME.json), got {name!r}"
        )
    return text


def _check_interpolate(alpha) -> float:
    """``--interpolate`` as a float in (0, 1], or ValueError naming it."""
    try:
        a = float(alpha)
    except (TypeError, ValueError):
        a = float("nan")
    if isinstance(alpha, bool) or not (np.isfinite(a) and 0.0 < a <= 1.0):
        raise ValueError(
            "--interpolate: expected the fine-tune's weight in (0, 1] (1: the fine-tune "
            f"alone; 0.5: halfway between the original and the fine-tune), got {alpha!r}"
        )
    return a


def _interpolate_into(
    source: Path,
    tuned: Path,
    alpha: float,
    target: Path,
    tuned_final: Path,
    command: str,
    source_card: dict,
) -> dict:
    """Writes ``target``, ``(1 - alpha)`` x ``source`` + ``alpha`` x ``tuned`` (both fp32
    ONNX, the same network), and returns the card's ``training.interpolation`` record, as
    the interpolation tool writes it (``tuned_final``: where the fine-tune alone will be;
    ``source_card``: the source's card, whose own mix record, if any, is kept)."""
    import onnx

    onnx.save(
        interpolated_model(load_model(source, "model"), load_model(tuned, "fine-tune"), alpha),
        str(target),
    )
    return interpolation_record(
        source, tuned, alpha, command, model_b_at=tuned_final, card_a=source_card
    )


def trainable_source(model_path) -> Path:
    """The fp32 ONNX model to fine-tune for a model: itself, or for an int8 model of
    ``quantize_segmenter`` the fp32 model its card names (``quantization.source_model``,
    beside it)."""
    path = resolve_model_path(str(model_path))
    card = read_model_card(path)
    source = (card.get("quantization") or {}).get("source_model")
    return path.with_name(source) if source else path


def fine_tune(
    frames: AnnotatedFrames,
    config: ImagingConfig,
    out: Path,
    *,
    holdout: float = 0.2,
    epochs: int = 40,
    lr: float = 5e-4,
    batch: int = 8,
    seed: int = 0,
    threads: int = 1,
    name: str = "kidney_unet_finetuned",
    command: str = "",
    frames_source: str = "",
    held_out: AnnotatedFrames | None = None,
    held_out_source: str = "",
    boundary_band_mm: float = 0.0,
    boundary_gain: float = 4.0,
    interpolate: float = 1.0,
    log=print,
) -> dict:
    """Fine-tunes the scenario's model (``config.onnx_model``; an int8 model's fp32 source)
    on ``frames`` (the first 1 - ``holdout``; the rest held out), writes
    ``out/NAME.onnx`` and its card ``out/NAME.json`` and returns the card. ``held_out``:
    frames of their own to measure on (every frame of ``frames`` is then trained on). The
    card's ``evaluation`` holds the held-out IoU of the scenario's model before and of the
    new one after. ``boundary_band_mm`` > 0: the BCE weighted by 1 + ``boundary_gain``
    within that distance (mm) of the true kidney edge on the canvas
    (``train_segmenter.boundary_band_weight``, as ``train_segmenter --boundary-band-mm``);
    0, the default, is the unweighted loss. ``interpolate`` (alpha in (0, 1]): below 1, the
    written model is ``(1 - alpha)`` x the scenario model's fp32 source ``+ alpha`` x the
    fine-tune (WiSE-FT, :func:`~drake_rus.imaging.training.interpolate.interpolated_model`;
    the card's ``training.interpolation`` as the interpolation tool records it),
    the fine-tune alone is written beside it as ``NAME_alone.onnx`` (and its card), and the
    card's ``evaluation`` adds ``held_out_iou_fine_tune_alone``."""
    alpha = _check_interpolate(interpolate)
    name = check_model_name(name)
    if not (np.isfinite(boundary_band_mm) and boundary_band_mm >= 0):
        raise ValueError(
            f"--boundary-band-mm: expected a distance >= 0 (mm), got {boundary_band_mm}"
        )
    if not (np.isfinite(boundary_gain) and boundary_gain >= 0):
        raise ValueError(f"--boundary-gain: expected a weight >= 0, got {boundary_gain}")
    scenario_model = resolve_model_path(config.onnx_model)
    source = trainable_source(scenario_model)
    card = read_model_card(source)
    if held_out is None:
        train_idx, held_idx = held_out_split(len(frames), holdout)
        held = frames.subset(held_idx)
        held_names = [frames.names[i] for i in held_idx]
        rule = f"the last {holdout:.0%} of the frames by name"
    else:
        train_idx, held = np.arange(len(frames)), held_out
        held_names = list(held_out.names)
        rule = f"the frames of {held_out_source or 'a folder of their own'}"
    train_frames = frames.subset(train_idx)
    if not held.kidney.any():
        raise ValueError(
            f"the {len(held)} held-out frames show no kidney: nothing to measure the IoU "
            "on; hold out more frames (--holdout) or give --held-out frames with the kidney"
        )
    log(f"held-out IoU of {scenario_model.name} (before) on {len(held)} frames ...")
    before = frames_iou(scenario_model, held, config)
    X, Y = frames_on_canvas(train_frames, config, card)
    net = unet_from_onnx(source, card.get("architecture") or {})
    boundary = None
    if boundary_band_mm > 0:
        boundary = (float(card["pixel_size_mm"]) * 1e-3, boundary_band_mm * 1e-3, boundary_gain)
    t0 = time.time()
    net = train(
        X,
        Y,
        0,
        epochs,
        batch=batch,
        lr=lr,
        seed=seed,
        threads=threads,
        log=log,
        net=net,
        boundary=boundary,
    )
    seconds = round(time.time() - t0, 1)
    out = Path(out)
    onnx_name = f"{name}.onnx"
    new = {k: v for k, v in card.items() if k not in ("evaluation", "quantization", "training")}
    new["model"] = onnx_name
    new["architecture"] = {**(card.get("architecture") or {}), "batch_norm": False}
    new["scenario"] = {**(card.get("scenario") or {}), "onnx_model": str(out / onnx_name)}
    new["fine_tuned_from"] = {
        "model": str(source),
        "sha256": sha256(source),
        "scenario_model": str(scenario_model),
    }
    new["fine_tuning"] = {
        "frames": frames_source,
        "training_frames": [frames.names[i] for i in train_idx],
        "held_out_frames": held_names,
        "holdout_rule": rule,
        "epochs": epochs,
        "lr": lr,
        "batch": batch,
        "seed": seed,
        "augmentation": "left-right flip; grey x U(0.85, 1.15) + U(-0.05, 0.05) in the fan",
        "loss": "BCE + soft Dice on the canvas kidney area fraction"
        + (
            f"; BCE weighted 1 + {boundary_gain:g} within {boundary_band_mm:g} mm of the "
            "true edge (boundary_band_weight)"
            if boundary is not None
            else ""
        ),
        "train_seconds": seconds,
        "command": command,
    }
    # Written whole or not at all: the model and its card (the canvas the backend reads)
    # go to a temporary folder, are measured there, then moved into ``out``.
    tmp = out.parent / f".{out.name}.{name}.partial"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    written = [onnx_name, f"{name}.json"]
    try:
        export_onnx(net, tmp / onnx_name, tuple(card["canvas_px"]))
        (tmp / f"{name}.json").write_text(dumps_strict(new, indent=2) + "\n")
        after = frames_iou(tmp / onnx_name, held, config)
        if alpha < 1.0:
            alone = f"{name}_alone"
            alone_card = {
                **new,
                "model": f"{alone}.onnx",
                "scenario": {**new["scenario"], "onnx_model": str(out / f"{alone}.onnx")},
                "evaluation": _evaluation(before, after, scenario_model.name),
            }
            (tmp / onnx_name).replace(tmp / f"{alone}.onnx")
            (tmp / f"{alone}.json").write_text(dumps_strict(alone_card, indent=2) + "\n")
            written += [f"{alone}.onnx", f"{alone}.json"]
            new["training"] = {
                "interpolation": _interpolate_into(
                    source,
                    tmp / f"{alone}.onnx",
                    alpha,
                    tmp / onnx_name,
                    out / f"{alone}.onnx",
                    command,
                    card,
                )
            }
            (tmp / f"{name}.json").write_text(dumps_strict(new, indent=2) + "\n")
            new["evaluation"] = {
                **_evaluation(
                    before, frames_iou(tmp / onnx_name, held, config), scenario_model.name
                ),
                "held_out_iou_fine_tune_alone": round(after["iou"], 4),
                "fine_tune_alone": after,
            }
        else:
            new["evaluation"] = _evaluation(before, after, scenario_model.name)
        (tmp / f"{name}.json").write_text(dumps_strict(new, indent=2) + "\n")
        out.mkdir(parents=True, exist_ok=True)
        for f in written:
            (tmp / f).replace(out / f)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return new
