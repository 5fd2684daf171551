"""``drake-rus segmenter``: the learned segmenter on a user's own frames.

``drake-rus segmenter fine-tune --frames DIR`` fine-tunes the scenario's ONNX model on a folder
of annotated frames (the Open Kidney Ultrasound Data Set's mask layout: ``images/NAME.png``
and ``capsule/NAME.png``, optional ``frames.csv``; ``drake-rus scan --save-frames`` writes
one) and writes the new model and its card (held-out IoU before and after) to ``--out``. Run
a scan with it: ``--set "{imaging: {onnx_model: OUT/kidney_unet_finetuned.onnx}}"``. Needs
the ``train`` extra (PyTorch; CPU). ``drake-rus segmenter check-frames --frames DIR`` only
reads the folder and says what it holds.
"""

from __future__ import annotations

import shlex
import sys
from pathlib import Path

from drake_rus.cli import UserError, add_scenario_arguments, load_scenario_from_args
from drake_rus.extras import require
from drake_rus.imaging.annotated import FramesError, read_annotated_frames
from drake_rus.imaging.training.fine_tune import check_model_name, fine_tune, trainable_source


def add_commands(subparsers) -> None:
    p = subparsers.add_parser(
        "segmenter",
        help="the learned segmenter on your own frames (fine-tune, check a frames folder)",
        description=__doc__,
    )
    sub = p.add_subparsers(dest="segmenter_command", required=True, metavar="COMMAND")
    ft = sub.add_parser(
        "fine-tune",
        help="fine-tune the scenario's ONNX segmenter on annotated frames (train extra)",
        description=__doc__,
    )
    _frames_arguments(ft)
    ft.add_argument(
        "--out",
        default="runs/segmenter_finetuned",
        help="folder of the new model and its card (default runs/segmenter_finetuned)",
    )
    ft.add_argument("--name", default="kidney_unet_finetuned", help="file name of the model")
    ft.add_argument(
        "--holdout",
        type=float,
        default=0.2,
        help="share of the frames (the last by name) kept aside to measure the IoU",
    )
    ft.add_argument(
        "--held-out",
        default=None,
        metavar="DIR",
        help="measure the IoU on this folder of annotated frames instead (all of --frames "
        "are then trained on)",
    )
    ft.add_argument("--epochs", type=int, default=40, help="passes over the training frames")
    ft.add_argument("--lr", type=float, default=5e-4, help="peak learning rate (one-cycle)")
    ft.add_argument("--batch", type=int, default=8, help="frames per step")
    ft.add_argument("--seed", type=int, default=0, help="seed of the shuffling and augmentation")
    ft.add_argument("--threads", type=int, default=1, help="PyTorch threads (CPU)")
    ft.add_argument(
        "--boundary-band-mm",
        type=float,
        default=0.0,
        help="weight the loss by 1 + --boundary-gain within this distance (mm) of the "
        "annotated kidney edge (0: unweighted, the default)",
    )
    ft.add_argument(
        "--boundary-gain",
        type=float,
        default=4.0,
        help="extra loss weight in the --boundary-band-mm band (default 4)",
    )
    ft.add_argument(
        "--interpolate",
        type=float,
        default=1.0,
        metavar="ALPHA",
        help="write (1 - ALPHA) x the original + ALPHA x the fine-tune, weight by weight "
        "(WiSE-FT; keeps more of the original's accuracy on its own looks), and the "
        "fine-tune alone beside it as NAME_alone.onnx (default 1: the fine-tune alone)",
    )
    ft.set_defaults(func=run_fine_tune, outputs={"out": "dir"})
    ck = sub.add_parser(
        "check-frames",
        help="read a folder of annotated frames and say what it holds (nothing written)",
        description=__doc__,
    )
    _frames_arguments(ck)
    ck.set_defaults(func=run_check_frames, outputs={})


def _frames_arguments(p) -> None:
    add_scenario_arguments(p)
    p.add_argument(
        "--frames",
        required=True,
        metavar="DIR",
        help="annotated frames: DIR/images/NAME.png, DIR/capsule/NAME.png (> 0 inside the "
        "kidney's capsule), optional DIR/frames.csv (name, kidney 0/1, depth_m)",
    )
    p.add_argument(
        "--depth-m",
        type=float,
        default=None,
        help="imaging depth (m) of frames whose frames.csv gives none (default: the "
        "scenario's imaging.depth)",
    )


def _read(args, scenario, folder=None):
    depth = args.depth_m if args.depth_m is not None else scenario.imaging.depth
    if not (0.03 <= depth <= 0.4):
        raise UserError(f"--depth-m: expected an imaging depth in m (0.03-0.4), got {depth:g}")
    shape = (scenario.imaging.image_height_px, scenario.imaging.image_width_px)
    try:
        return read_annotated_frames(args.frames if folder is None else folder, shape, depth)
    except FramesError as e:
        raise UserError(str(e)) from None


def run_check_frames(args) -> int:
    scenario = load_scenario_from_args(args)
    frames = _read(args, scenario)
    depths = sorted({round(float(d), 4) for d in frames.depth})
    print(
        f"{args.frames}: {len(frames)} frames ({int(frames.kidney.sum())} with the kidney), "
        f"{frames.images.shape[1]} x {frames.images.shape[2]} px, depth "
        + ", ".join(f"{d:g}" for d in depths)
        + " m"
    )
    return 0


def run_fine_tune(args) -> int:
    # The user's input is checked first: a bad folder is named with or without the train
    # extra; the packages are asked for only once there is something to fine-tune on.
    scenario = load_scenario_from_args(args)
    if scenario.imaging.segmenter != "onnx":
        raise UserError(
            f"field 'imaging.segmenter': {scenario.imaging.segmenter!r}; fine-tuning needs "
            "the onnx backend's model (imaging.onnx_model)"
        )
    try:
        check_model_name(args.name)
    except ValueError as e:
        raise UserError(str(e)) from None
    if args.epochs < 1 or args.batch < 1 or args.threads < 1:
        raise UserError("--epochs, --batch and --threads: expected integers >= 1")
    if not args.lr > 0:
        raise UserError(f"--lr: expected a learning rate > 0, got {args.lr}")
    if not args.boundary_band_mm >= 0 or not args.boundary_gain >= 0:
        raise UserError(
            "--boundary-band-mm / --boundary-gain: expected values >= 0 (mm, 1), got "
            f"{args.boundary_band_mm}, {args.boundary_gain}"
        )
    if not 0.0 < args.holdout < 1.0:
        raise UserError(f"--holdout: expected a share between 0 and 1, got {args.holdout}")
    if not 0.0 < args.interpolate <= 1.0:
        raise UserError(
            "--interpolate: expected the fine-tune's weight in (0, 1] (1: the fine-tune "
            f"alone), got {args.interpolate:g}"
        )
    frames = _read(args, scenario)
    held_out = None if args.held_out is None else _read(args, scenario, args.held_out)
    if len(frames) < 2 and held_out is None:
        raise UserError(f"--frames: {args.frames} holds 1 frame; fine-tuning needs at least 2")
    source = trainable_source(scenario.imaging.onnx_model)
    if not source.is_file():
        raise UserError(f"field 'imaging.onnx_model': {source}: no such model to fine-tune")
    require("torch", "drake-rus segmenter fine-tune")
    require("onnx", "drake-rus segmenter fine-tune")
    argv = getattr(args, "argv", None) or sys.argv[1:]
    out = Path(args.out)
    try:
        card = fine_tune(
            frames,
            scenario.imaging,
            out,
            holdout=args.holdout,
            epochs=args.epochs,
            lr=args.lr,
            batch=args.batch,
            seed=args.seed,
            threads=args.threads,
            name=args.name,
            command="drake-rus " + " ".join(shlex.quote(a) for a in argv),
            frames_source=str(Path(args.frames).resolve()),
            held_out=held_out,
            held_out_source=None if args.held_out is None else str(Path(args.held_out).resolve()),
            boundary_band_mm=args.boundary_band_mm,
            boundary_gain=args.boundary_gain,
            interpolate=args.interpolate,
            log=lambda line: print(line, flush=True),
        )
    except ValueError as e:
        raise UserError(str(e)) from None
    ev = card["evaluation"]
    print(
        f"held-out IoU on {ev['after']['frames_with_kidney']} frames with the kidney: "
        f"{ev['held_out_iou_before']:.3f} ({ev['before_model']}) -> "
        f"{ev['held_out_iou_after']:.3f} ({card['model']})"
    )
    if "held_out_iou_fine_tune_alone" in ev:
        print(
            f"the fine-tune alone ({args.name}_alone.onnx, beside it): "
            f"{ev['held_out_iou_fine_tune_alone']:.3f}; the written model mixes "
            f"{1 - args.interpolate:g} x the original with {args.interpolate:g} x it"
        )
    print(f"wrote {out / card['model']} and its card {out / (args.name + '.json')}")
    print('scan with it: --set "{imaging: {onnx_model: ' + str(out / card["model"]) + '}}"')
    return 0
