"""``drake-rus imaging-pictures``: emulated frames with the kidney mask overlaid (seed Fig. 4).

For a patient (``--patient test:0``, ``seed:N``, ``phantom:N``, a folder...) and probe poses:
the transverse view straight down over the kidney centroid (always), ``--pose`` views given in
the patient frame Pt, and ``--views N`` random views looking at the kidney. Each view is one
PNG: label image | emulated image | emulated image with the segmenter's mask (filled in the
kidney's colour) and the true kidney outline, with legends (colours:
``drake_rus.anatomy.tissue_colors``); plus ``contact_sheet.png`` with every view's overlay.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from drake_rus.anatomy import load_patient
from drake_rus.anatomy.labels import is_kidney
from drake_rus.anatomy.tissue_colors import (
    TRUTH_OUTLINE_COLOR,
    label_image,
    labels_present,
    mask_handles,
    mask_overlay,
    tissue_handles,
)
from drake_rus.cli import UserError, add_scenario_arguments, load_scenario_from_args
from drake_rus.imaging.emulator import EmulatorModel, emulate
from drake_rus.imaging.phantoms import kidney_phantom
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.imaging.segment import iou, read_mask
from drake_rus.imaging.slicing import slice_volume
from drake_rus.imaging.systems import make_segmenter_backend
from drake_rus.imaging.training.dataset import ViewSampler
from drake_rus.io_utils import dumps_strict, save_figure, write_text_atomic


def add_commands(subparsers) -> None:
    p = subparsers.add_parser(
        "imaging-pictures", help="PNGs of emulated ultrasound frames with the kidney mask"
    )
    add_scenario_arguments(p)
    p.add_argument(
        "--patient",
        default="test:0",
        help="patient spec (test:K, train:K, seed:N, phantom:N, folder); default test:0",
    )
    p.add_argument(
        "--side",
        default=None,
        choices=["right", "left"],
        help="target kidney (default: the scenario's patient.side)",
    )
    p.add_argument(
        "--pose",
        action="append",
        default=[],
        metavar="X,Y,Z,ROLL,PITCH,YAW",
        help="probe tip pose X_PtP in the patient frame (m, deg); repeatable",
    )
    p.add_argument("--views", type=int, default=3, help="random views of the kidney (seeded)")
    p.add_argument(
        "--segmenter",
        default=None,
        choices=["oracle", "classical", "onnx"],
        help="segmenter backend (default: the scenario's imaging.segmenter)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the random views and speckle")
    p.add_argument("--out", default="runs/imaging_pictures", help="output folder")
    p.set_defaults(func=run_pictures)


def parse_pose(text: str):
    from pydrake.math import RigidTransform, RollPitchYaw

    try:
        v = [float(s) for s in text.split(",")]
    except ValueError:
        v = []
    if len(v) != 6 or not np.all(np.isfinite(v)):
        raise UserError(
            f"--pose: expected 6 finite numbers X,Y,Z,ROLL,PITCH,YAW (m, deg), got {text!r}"
        )
    return RigidTransform(RollPitchYaw(np.radians(v[3:])), v[:3])


def centred_view(volume, X_PtV, X_PtK, approach_V):
    """Probe straight down over the kidney centroid (x_P along x_Pt: a transverse view),
    face on the skin, pressed 4 mm in. Returns X_VP, or None if no skin above."""
    from pydrake.math import RigidTransform, RotationMatrix

    sampler = ViewSampler(volume, approach_V)
    c_V = X_PtV.inverse().multiply(X_PtK.translation())
    u = np.asarray(approach_V, float)
    skin = sampler._skin_along(c_V, u)
    if skin is None:
        return None
    z = -u
    x = X_PtV.rotation().inverse().multiply(np.array([1.0, 0.0, 0.0]))
    x = x - x.dot(z) * z
    x /= np.linalg.norm(x)
    R = RotationMatrix(np.column_stack([x, np.cross(z, x), z]))
    return RigidTransform(R, skin - (sampler.indent + 0.5 * volume.voxel_size) * u)


def run_pictures(args) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from pydrake.math import RigidTransform

    scenario = load_scenario_from_args(args)
    cfg = scenario.imaging
    if args.segmenter:
        cfg.segmenter = args.segmenter
    side = args.side or scenario.patient.side
    g = ProbeGeometry.from_config(cfg)
    model = EmulatorModel.from_config(cfg, g)
    backend = make_segmenter_backend(cfg, g)
    poses = [parse_pose(p) for p in args.pose]  # validate before the slow patient load

    head, _, tail = args.patient.partition(":")
    if head == "phantom":
        ph = kidney_phantom(np.random.default_rng(int(tail)))
        volume, X_PtV, X_PtK = ph.volume, RigidTransform(), ph.X_VK
    else:
        patient = load_patient(args.patient, side=side)
        volume, X_PtV, X_PtK = patient.labels, patient.labels.X_PtV, patient.X_PtK
    up_V = np.asarray(X_PtV.rotation().inverse().multiply(np.array([0.0, 0.0, 1.0])))

    views = []
    X_VP = centred_view(volume, X_PtV, X_PtK, up_V)
    if X_VP is not None:
        views.append(("centred", X_VP))
    for i, X_PtP in enumerate(poses):
        views.append((f"pose{i}", X_PtV.inverse().multiply(X_PtP)))
    sampler = ViewSampler(volume, up_V)
    rng = np.random.default_rng(args.seed)
    for i in range(args.views):
        X = sampler.sample(rng)
        if X is not None:
            views.append((f"view{i}", X))

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    extent = [g.x_min * 1e3, g.x_max * 1e3, g.z_max * 1e3, g.z_min * 1e3]
    summary, overlays = [], []
    for k, (name, X_VP) in enumerate(views):
        labels = slice_volume(
            g, volume, RigidTransform(), X_VP, cfg.elevation_planes, cfg.elevation_combine
        )
        us = emulate(labels, model, args.seed, k)
        mask = np.asarray(backend(us, labels, None), bool) & g.fan_mask
        truth = is_kidney(labels)
        readout = read_mask(mask, g, cfg.min_kidney_area)
        rgb = mask_overlay(us, mask)
        overlays.append((name, rgb, truth))
        fig, ax = plt.subplots(1, 3, figsize=(13, 5.4))
        ax[0].imshow(label_image(labels, g.fan_mask), extent=extent, interpolation="nearest")
        ax[0].set_title("label image")
        ax[1].imshow(us, cmap="gray", vmin=0, vmax=255, extent=extent)
        ax[1].set_title("emulated B-mode")
        ax[2].imshow(rgb, extent=extent)
        if truth.any():
            ax[2].contour(
                truth,
                [0.5],
                colors=TRUTH_OUTLINE_COLOR,
                linewidths=0.8,
                extent=extent,
                origin="upper",
            )
        score = iou(mask, truth) if truth.any() else float("nan")
        ax[2].set_title(
            f"{cfg.segmenter} mask, true outline: IoU {score:.2f}\n"
            f"visible {readout.visible}, c_msk {readout.centroid:.2f}",
            fontsize=9,
        )
        ax[0].legend(
            handles=tissue_handles(labels_present(labels[g.fan_mask])),
            loc="upper left",
            bbox_to_anchor=(0.0, -0.12),
            ncol=3,
            fontsize=7,
            frameon=False,
        )
        ax[2].legend(
            handles=mask_handles(truth=bool(truth.any())),
            loc="upper left",
            bbox_to_anchor=(0.0, -0.12),
            fontsize=7,
            frameon=False,
        )
        for a in ax:
            a.set_xlabel("x_P (mm)")
        ax[0].set_ylabel("z_P depth (mm)")
        fig.tight_layout()
        path = out / f"{k:02d}_{name}.png"
        save_figure(fig, path, dpi=90)
        X_PtP = X_PtV.multiply(X_VP)
        summary.append(
            {
                "file": path.name,
                "view": name,
                "iou": score,
                "visible": readout.visible,
                "c_msk": readout.centroid,
                "X_PtP": X_PtP.GetAsMatrix4().tolist(),
            }
        )
        print(f"{path}: IoU {score:.2f}, visible {readout.visible}")
    n = len(overlays)
    if n:
        cols = min(n, 4)
        rows = int(np.ceil(n / cols))
        fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.4 * rows), squeeze=False)
        for a in axes.flat:
            a.axis("off")
        for a, (name, rgb, truth) in zip(axes.flat, overlays):
            a.imshow(rgb, extent=extent)
            a.set_title(name, fontsize=9)
        fig.suptitle(f"{args.patient} ({side} kidney), segmenter {cfg.segmenter}")
        fig.legend(handles=mask_handles(), loc="lower center", fontsize=8, frameon=False)
        fig.tight_layout(rect=(0, 0.05, 1, 1))
        save_figure(fig, out / "contact_sheet.png", dpi=80)
    # Strict JSON: a view without a kidney has no IoU (null, not NaN).
    write_text_atomic(
        out / "pictures.json",
        dumps_strict(
            {"patient": args.patient, "side": side, "segmenter": cfg.segmenter, "views": summary},
            indent=2,
        )
        + "\n",
    )
    return 0
