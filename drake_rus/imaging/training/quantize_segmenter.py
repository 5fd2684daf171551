"""Quantizes the learned kidney segmenter to int8 for faster CPU inference (needs the
``train`` extra: ``.venv/bin/pip install onnx sympy``).

Static post-training quantization with ONNX Runtime: the fp32 model
(``models/segmenter/kidney_unet.onnx``, the trained master) goes through
``quant_pre_process`` (shape inference and graph optimisation), then ``quantize_static``
in the QDQ format with uint8 activations, int8 weights per output channel (U8S8), no
``reduce_range`` (which lost 0.004-0.005 IoU per preset), and MinMax calibration on frames of
the training split only (:func:`calibration_images`: ``--per-source`` random frames of each
``train:K`` patient and posture from the training recipe's cached canvas data; never a
``test:K`` patient nor a real body).

    nice .venv/bin/python -m drake_rus.imaging.training.quantize_segmenter \\
        --model models/segmenter/kidney_unet.onnx --out models/segmenter/kidney_unet_int8.onnx
    nice .venv/bin/python -m benchmarks imaging \\
        --onnx-model models/segmenter/kidney_unet_int8.onnx --no-progress > bench_int8.log
    .venv/bin/python -m drake_rus.imaging.training.quantize_segmenter \\
        --out models/segmenter/kidney_unet_int8.onnx --record-benchmark bench_int8.log

Writes the model and its card (``kidney_unet_int8.json``, found by the ONNX backend beside
the model): the fp32 card's fields (canvas, shapes, normalisation, training) without its
``evaluation`` (which belongs to the fp32 model), and a ``quantization`` section (format,
types, calibration, the fp32 model's sha256, the command, the ONNX Runtime version, the
speed of both models). ``--record-benchmark`` adds the int8 model's own evaluation.

Measured on the shared 2-core machine (AVX512-VNNI), one ONNX thread: the network 0.84-0.88
ms per 128 x 112 frame instead of 1.42-1.53 ms; the whole segment call 1.39-1.53 ms instead
of 2.06-2.21 ms; held-out IoU per preset within 0.002 of the fp32 model, the VH female's the
same (the card has the table). About 10 s with the training data cached; a rerun gives the
same file bit for bit.

Caveat: U8S8 on x86-64 CPUs without VNNI may saturate (ONNX Runtime's documented caveat)
and lose accuracy; ``tests/test_quantized_segmenter.py`` compares the int8 model with the
fp32 one on emulated frames, so such a machine fails that test. The fallback is the fp32
model: ``imaging.onnx_model: models/segmenter/kidney_unet.onnx``.
"""

from __future__ import annotations

import argparse
import copy
import hashlib
import json
import os
import shlex
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from drake_rus.config_schema import SEED_MAX, SEED_RANGE
from drake_rus.extras import MissingExtra, require
from drake_rus.imaging.onnx_backend import (
    cpu_has_vnni,
    cpu_session,
    read_model_card,
    resolve_model_path,
)
from drake_rus.imaging.training import train_segmenter
from drake_rus.imaging.training.evaluation import POSTURES
from drake_rus.io_utils import atomic_path
from drake_rus.paths import REPO_ROOT

DEFAULT_MODEL = "models/segmenter/kidney_unet.onnx"
DEFAULT_OUT = "models/segmenter/kidney_unet_int8.onnx"
DEFAULT_CACHE = "/tmp/drake_rus_segmenter_data/canvas"

#: The settings :func:`quantize_segmenter` uses (recorded in the card).
SETTINGS = {
    "format": "QDQ",
    "activation_type": "QUInt8",
    "weight_type": "QInt8",
    "per_channel": True,
    "reduce_range": False,
    "calibration_method": "MinMax",
}

CAVEAT = (
    "U8S8 (uint8 activations, int8 weights) may saturate on x86-64 CPUs without VNNI "
    "(ONNX Runtime's documented caveat) and lose accuracy; "
    "tests/test_quantized_segmenter.py compares this model with the fp32 one on "
    "emulated frames and fails on such a machine"
)


def _quantization_api():
    """(onnxruntime.quantization, quant_pre_process), or MissingExtra (an ImportError)
    naming the train extra."""
    require("onnx", "quantize_segmenter (onnxruntime's quantization tools)")
    require("sympy", "quantize_segmenter (onnxruntime's symbolic shape inference)")
    from onnxruntime import quantization
    from onnxruntime.quantization.shape_inference import quant_pre_process

    return quantization, quant_pre_process


def _input_spec(session) -> tuple[str, list]:
    """(input name, declared shape) of a one-input image model."""
    inputs = session.get_inputs()
    if len(inputs) != 1 or len(inputs[0].shape) != 4:
        raise ValueError(
            f"model_path: expected one (N, C, H, W) input, got "
            f"{[(i.name, i.shape) for i in inputs]}"
        )
    return inputs[0].name, list(inputs[0].shape)


def _batch(images: np.ndarray, shape: list) -> np.ndarray:
    """(N, H, W) frames as N model inputs (N, 1, C, H, W): C repeated as declared."""
    c = shape[1] if isinstance(shape[1], int) else 1
    return np.ascontiguousarray(
        np.broadcast_to(images[:, None, None], (len(images), 1, c) + images.shape[1:])
    )


def run_model(model_path: str | Path, images: np.ndarray, threads: int = 1) -> np.ndarray:
    """The model's first output for each frame of ``images`` (N, H, W) (model input units),
    one frame per run: (N, ...) float32."""
    session = cpu_session(model_path, threads)
    name, shape = _input_spec(session)
    x = _batch(np.asarray(images, np.float32), shape)
    out = session.get_outputs()[0].name
    return np.stack([session.run([out], {name: xi})[0][0] for xi in x]).astype(np.float32)


def time_model(
    model_path: str | Path, images: np.ndarray, threads: int = 1, repeats: int = 3
) -> float:
    """ms per frame of one model run (one frame per run, ``threads`` intra-op threads):
    the best of ``repeats`` passes over ``images`` (the least disturbed by other jobs)."""
    session = cpu_session(model_path, threads)
    name, shape = _input_spec(session)
    x = _batch(np.asarray(images, np.float32), shape)
    out = session.get_outputs()[0].name
    session.run([out], {name: x[0]})  # warm-up
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        for xi in x:
            session.run([out], {name: xi})
        best = min(best, time.perf_counter() - t)
    return 1e3 * best / len(x)


def check_calibration_images(images, hw: tuple | None, value_range=(0.0, 1.0)) -> np.ndarray:
    """``images`` as float32 (N, H, W), or ValueError naming ``calibration_images``: N >= 1,
    (H, W) = ``hw`` (None: any), every value finite and, unless ``value_range`` is None,
    within it."""
    try:
        x = np.asarray(images, dtype=np.float32)
    except (TypeError, ValueError) as e:
        raise ValueError(f"calibration_images: expected a float array (N, H, W): {e}") from None
    want = "(N, H, W)" if hw is None else f"(N, {hw[0]}, {hw[1]})"
    if x.ndim != 3:
        raise ValueError(f"calibration_images: expected shape {want}, got {x.shape}")
    if x.shape[0] < 1:
        raise ValueError("calibration_images: no frames (N = 0); at least one is needed")
    if hw is not None and x.shape[1:] != tuple(hw):
        raise ValueError(
            f"calibration_images: frames of {x.shape[1]} x {x.shape[2]} px but "
            f"the model's input is {hw[0]} x {hw[1]}; expected {want}"
        )
    bad = ~np.isfinite(x)
    if bad.any():
        raise ValueError(
            f"calibration_images: {int(bad.sum())} non-finite value(s) (NaN or inf) in {x.size}"
        )
    if value_range is not None:
        lo, hi = value_range
        if x.min() < lo or x.max() > hi:
            raise ValueError(
                f"calibration_images: values in [{x.min():g}, {x.max():g}], outside the "
                f"model's normalised input [{lo:g}, {hi:g}] (grey / 255 on the canvas; "
                f"uint8 grey must be divided by 255)"
            )
    return x


def quantize_segmenter(
    model_path: str | Path, out_path: str | Path, calibration_images, value_range=(0.0, 1.0)
) -> Path:
    """Writes the int8 (static, QDQ, U8S8, per-channel weights, MinMax) quantization of the
    ONNX model ``model_path`` to ``out_path``, calibrated on ``calibration_images``: float32
    (N, H, W) in the model's normalised input (grey / 255 on the physical canvas, as the
    training data stores it), (H, W) the model's input size; one frame per calibration run.
    ``value_range``: the range the frames must lie in (None: any finite values).

    Atomic: the model is produced in a temporary directory beside ``out_path``, checked to
    load and run, then moved over ``out_path``; on any failure nothing is left there (an
    older file stays as it was). Returns ``out_path``. Bad arguments raise ValueError naming
    them; without ``onnx`` installed, ImportError naming the ``train`` extra."""
    model_path, out_path = Path(model_path), Path(out_path)
    if not model_path.is_file():
        raise ValueError(f"model_path: ONNX model file not found: {model_path}")
    if out_path.resolve() == model_path.resolve():
        raise ValueError(f"out_path: {out_path} is the model to quantize; write elsewhere")
    if out_path.suffix != ".onnx":
        raise ValueError(f"out_path: expected a .onnx file name, got {out_path.name}")
    try:
        session = cpu_session(model_path)
    except Exception as e:  # onnxruntime raises its own Fail / InvalidGraph types
        raise ValueError(f"model_path: cannot load ONNX model {model_path}: {e}") from None
    name, shape = _input_spec(session)
    if "float" not in session.get_inputs()[0].type:
        raise ValueError(
            f"model_path: input '{name}' is {session.get_inputs()[0].type}; expected a float tensor"
        )
    hw = tuple(shape[2:]) if all(isinstance(d, int) for d in shape[2:]) else None
    x = check_calibration_images(calibration_images, hw, value_range)
    q, quant_pre_process = _quantization_api()

    class Frames(q.CalibrationDataReader):
        def __init__(self):
            self.batches = iter(_batch(x, shape))

        def get_next(self):
            xi = next(self.batches, None)
            return None if xi is None else {name: xi}

    out_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_path.stem}-", dir=out_path.parent))
    try:
        pre = tmp / "preprocessed.onnx"
        quant_pre_process(str(model_path), str(pre))
        staged = tmp / out_path.name
        q.quantize_static(
            str(pre),
            str(staged),
            Frames(),
            quant_format=q.QuantFormat.QDQ,
            activation_type=q.QuantType.QUInt8,
            weight_type=q.QuantType.QInt8,
            per_channel=SETTINGS["per_channel"],
            reduce_range=SETTINGS["reduce_range"],
            calibrate_method=q.CalibrationMethod.MinMax,
        )
        run_model(staged, x[:1])  # it loads and runs, before it replaces anything
        os.replace(staged, out_path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out_path


def training_sources(patients: int) -> list[str]:
    """The training split's first ``patients`` patients (``train:0..N-1``)."""
    if patients < 1:
        raise ValueError(f"patients: expected >= 1, got {patients}")
    return [f"train:{k}" for k in range(patients)]


def calibration_images(
    patients: int = 20,
    frames: int = 300,
    per_source: int = 10,
    seed: int = 0,
    cache: str | Path | None = DEFAULT_CACHE,
    postures=POSTURES,
    pixel_size_mm: float = 2.4,
    canvas_px: tuple[int, int] = (128, 112),
    canvas_top_mm: float = -4.0,
    data_seed: int = 0,
    log=print,
) -> np.ndarray:
    """float32 (N, H, W) calibration frames (grey / 255 on the canvas): ``per_source``
    frames of each training patient ``train:0..patients-1`` and posture, picked by a numpy
    Generator seeded with ``seed`` from the training recipe's frames
    (:func:`~drake_rus.imaging.training.train_segmenter.build_canvas_dataset` with ``frames`` per
    patient and posture, ``data_seed``, the canvas; read from ``cache`` when there, else
    built and cached, which takes minutes per patient). Training split only: never a
    ``test:K`` patient nor a real body. N = patients x postures x per_source."""
    specs = training_sources(patients)
    if not 1 <= per_source <= frames:
        raise ValueError(f"per_source: expected 1..frames ({frames}), got {per_source}")
    data = train_segmenter.build_canvas_dataset(
        specs,
        list(postures),
        frames,
        pixel_size_mm * 1e-3,
        tuple(canvas_px),
        canvas_top_mm * 1e-3,
        None if cache is None else Path(cache),
        data_seed,
        log=log,
    )
    rng = np.random.default_rng(seed)
    picked = []
    for i in range(len(specs)):
        for j in range(len(postures)):
            idx = np.flatnonzero((data["source"] == i) & (data["posture"] == j))
            picked.append(np.sort(rng.choice(idx, per_source, replace=False)))
    idx = np.concatenate(picked)
    return data["image"][idx].astype(np.float32) * np.float32(1.0 / 255.0)


def sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _repo_path(path: Path) -> str:
    """``path`` relative to the repository when inside it (as scenarios name models)."""
    try:
        return str(path.resolve().relative_to(REPO_ROOT))
    except ValueError:
        return str(path.resolve())


def quantized_card(fp32_card: dict, out_path: Path, quantization: dict) -> dict:
    """The int8 model's card: the fp32 card's fields with ``model`` and
    ``scenario.onnx_model`` naming ``out_path``, without the fp32 ``evaluation``, plus
    ``quantization``."""
    card = copy.deepcopy(fp32_card)
    card.pop("evaluation", None)
    card["model"] = out_path.name
    card.setdefault("scenario", {})["onnx_model"] = _repo_path(out_path)
    card["quantization"] = quantization
    return card


def _write_json(path: Path, data: dict) -> None:
    """Writes a model card (JSON) whole or not at all (``io_utils.atomic_path``: a
    temporary file beside it, then a rename), so a failed write (a full disk, a run
    stopped) leaves the old card as it was."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default=DEFAULT_MODEL, help="the fp32 model (its card beside it)")
    ap.add_argument("--out", default=DEFAULT_OUT, help="the int8 model to write")
    ap.add_argument(
        "--patients", type=int, default=20, help="calibrate on training patients train:0..N-1"
    )
    ap.add_argument(
        "--frames",
        type=int,
        default=300,
        help="the training recipe's frames per patient and posture (cache key)",
    )
    ap.add_argument(
        "--per-source", type=int, default=10, help="calibration frames per patient and posture"
    )
    ap.add_argument("--seed", type=int, default=0, help="seed of the frame choice")
    ap.add_argument("--cache", default=DEFAULT_CACHE, help="train_segmenter's data cache")
    ap.add_argument(
        "--record-benchmark",
        metavar="FILE",
        help="only add this `python -m benchmarks imaging` output (its JSON "
        "line) to the card beside --out",
    )
    args = ap.parse_args(argv)
    out = resolve_model_path(args.out)
    card_path = out.with_suffix(".json")
    if args.record_benchmark:
        if not card_path.is_file():
            ap.error(f"--out: no model card {card_path} to record the benchmark in")
        try:
            train_segmenter.record_benchmark(card_path, Path(args.record_benchmark))
        except (OSError, ValueError) as e:
            ap.error(f"--record-benchmark: {e}")
        print(f"recorded {args.record_benchmark} in {card_path}")
        return 0
    model = resolve_model_path(args.model)
    if not model.is_file():
        ap.error(f"--model: ONNX model file not found: {model}")
    fp32_card = read_model_card(model)
    if not fp32_card:
        ap.error(f"--model: no model card {model.with_suffix('.json')} beside the model")
    if "canvas_px" not in fp32_card or "pixel_size_mm" not in fp32_card:
        ap.error(
            f"--model: card {model.with_suffix('.json').name} declares no physical "
            f"canvas (pixel_size_mm, canvas_px): the calibration frames need one"
        )
    if args.per_source < 1 or args.per_source > args.frames:
        ap.error(f"--per-source: expected 1..--frames ({args.frames}), got {args.per_source}")
    if args.patients < 1:
        ap.error(f"--patients: expected >= 1, got {args.patients}")
    if not 0 <= args.seed <= SEED_MAX:
        ap.error(f"--seed: expected {SEED_RANGE}, got {args.seed}")
    try:
        _quantization_api()  # before the calibration frames: the extra is there
    except MissingExtra as e:
        print(f"quantize_segmenter: error: {e}", file=sys.stderr)
        return 2
    command = "nice .venv/bin/python -m drake_rus.imaging.training.quantize_segmenter " + " ".join(
        shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv)
    )

    def log(s):
        return print(s, flush=True)

    data_seed = int((fp32_card.get("training") or {}).get("seed", 0))
    t = time.time()
    images = calibration_images(
        args.patients,
        args.frames,
        args.per_source,
        args.seed,
        args.cache,
        POSTURES,
        float(fp32_card["pixel_size_mm"]),
        tuple(fp32_card["canvas_px"]),
        float(fp32_card.get("canvas_top_mm", 0.0)),
        data_seed,
        log=log,
    )
    log(f"calibration: {len(images)} training frames ({time.time() - t:.0f} s)")
    t = time.time()
    quantize_segmenter(model, out, images)
    log(
        f"quantized {model.name} -> {out} ({out.stat().st_size / 1e3:.0f} kB, "
        f"{time.time() - t:.0f} s)"
    )
    ref, got = run_model(model, images), run_model(out, images)
    agreement = float(np.mean((ref > 0) == (got > 0)))
    ms_fp32, ms_int8 = time_model(model, images[:100]), time_model(out, images[:100])
    log(
        f"on the calibration frames: logit sign agreement {agreement:.4f}, max |logit "
        f"difference| {np.abs(ref - got).max():.2f}; ONNX run {ms_fp32:.2f} ms (fp32) -> "
        f"{ms_int8:.2f} ms (int8) per frame, one thread"
    )
    import onnx
    import onnxruntime

    quantization = {
        "source_model": model.name,
        "source_sha256": sha256(model),
        "method": (
            "static post-training quantization: onnxruntime.quantization."
            "shape_inference.quant_pre_process, then quantize_static"
        ),
        **SETTINGS,
        "calibration_sources": training_sources(args.patients),
        "calibration_postures": list(POSTURES),
        "calibration_frames_per_source_and_posture": args.per_source,
        "calibration_frames": int(len(images)),
        "calibration_seed": args.seed,
        "calibration_data": (
            f"training split only (never test:K nor a real body): frames of "
            f"train_segmenter.build_canvas_dataset (frames={args.frames} per "
            f"patient and posture, seed {data_seed}, randomised as trained), "
            f"grey / 255 on the canvas"
        ),
        "calibration_logit_sign_agreement": round(agreement, 4),
        "onnx_ms_per_frame": {
            "fp32": round(ms_fp32, 2),
            "int8": round(ms_int8, 2),
            "threads": 1,
            "frames": int(min(len(images), 100)),
            "cpu_has_vnni": cpu_has_vnni(),
            "load_average": [round(v, 2) for v in os.getloadavg()],
        },
        "onnxruntime": onnxruntime.__version__,
        "onnx": onnx.__version__,
        "command": command,
        "caveat": CAVEAT,
        "fallback": (
            f"the fp32 master this model is derived from, same canvas and card "
            f"fields: imaging.onnx_model: {_repo_path(model)}"
        ),
    }
    _write_json(card_path, quantized_card(fp32_card, out, quantization))
    log(f"wrote {card_path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
