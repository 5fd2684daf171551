"""Labelled volumes by name, emulated test frames, and segmentation IoU.

Sources: ``phantom:N`` (a synthetic :func:`kidney_phantom`, rng seed N) or any
``drake_rus.anatomy.load_patient`` spec (``train:K``, ``test:K``, ``seed:N``, a folder...).
Probe views come from :class:`~drake_rus.imaging.dataset.ViewSampler` looking down from the
patient's upper surface (+z of the patient/bed frame), like the seed's probe on the bed.
"""

from __future__ import annotations

import numpy as np

from drake_rus.anatomy import load_patient
from drake_rus.anatomy.labels import LabelVolume
from drake_rus.imaging.dataset import make_frames
from drake_rus.imaging.emulator import EmulatorModel
from drake_rus.imaging.phantoms import kidney_phantom
from drake_rus.imaging.segment import iou


def load_volume(spec: str, side: str = "right") -> tuple[LabelVolume, np.ndarray]:
    """(label volume, unit approach direction in the volume's grid frame V) for a source."""
    head, _, tail = spec.partition(":")
    if head == "phantom":
        ph = kidney_phantom(np.random.default_rng(int(tail)))
        return ph.volume, np.array([0.0, 0.0, 1.0])
    patient = load_patient(spec, side=side, progress=False)
    vol = patient.labels
    # Up from the bed (+z_Pt) expressed in V.
    up_V = vol.X_PtV.rotation().inverse().multiply(np.array([0.0, 0.0, 1.0]))
    return vol, np.asarray(up_V)


def make_source_frames(spec: str, model: EmulatorModel, n: int, seed: int = 0,
                       side: str = "right"):
    """``n`` (us, mask, labels, X_VP) frames of one source, deterministic in ``seed``."""
    vol, up = load_volume(spec, side)
    return make_frames(vol, up, model, n, np.random.default_rng(seed), seed=seed)


def mean_iou(segment, frames, geometry, min_area: float = 1.0e-4) -> dict:
    """Mean IoU of ``segment(us) -> mask`` over frames whose true kidney area >= min_area,
    and the fraction of kidney-free frames where it (wrongly) reports a kidney."""
    ious, false_pos, n_empty = [], 0, 0
    for us, gt, *_ in frames:
        pred = np.asarray(segment(us), bool)
        if gt.sum() * geometry.pixel_area >= min_area:
            ious.append(iou(pred, gt))
        else:
            n_empty += 1
            false_pos += int(pred.sum() * geometry.pixel_area >= min_area)
    return {"iou": float(np.mean(ious)) if ious else float("nan"),
            "iou_median": float(np.median(ious)) if ious else float("nan"),
            "frames_with_kidney": len(ious), "frames_without_kidney": n_empty,
            "false_positive_rate": false_pos / n_empty if n_empty else 0.0}
