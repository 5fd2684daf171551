"""Labelled volumes by name, emulated test frames, and segmentation IoU.

Sources: ``phantom:N`` (a synthetic :func:`kidney_phantom`, rng seed N) or any
``drake_rus.anatomy.load_patient`` spec (``train:K``, ``test:K``, ``seed:N``, a folder...),
in either posture. Probe views come from :class:`~drake_rus.imaging.training.dataset.ViewSampler`
looking down from above the patient (+z of the patient/bed frame), like the seed's probe on
the bed: through the upper (anterior) skin when supine, through the right flank in left
lateral decubitus.

Across depths (:func:`depth_study`): the same views of each source imaged at every depth
preset (``ImagingConfig.depth_presets``), segmented by a segmenter built for that depth,
scored against the target kidney (the patient's ``side``; a real body has both kidneys in
its label volume, and a scan of the right kidney must find the right one).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from pydrake.math import RigidTransform, RotationMatrix
from scipy import ndimage
from tqdm import tqdm

from drake_rus.anatomy import load_patient
from drake_rus.anatomy.labels import Label, LabelVolume, is_kidney
from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.emulator import EmulatorModel, emulate
from drake_rus.imaging.onnx_backend import OnnxSegmenter
from drake_rus.imaging.phantoms import kidney_phantom
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.imaging.segment import iou
from drake_rus.imaging.slicing import sample_labels, slice_volume
from drake_rus.imaging.training.dataset import ViewSampler, make_frames

POSTURES = ("supine", "left_lateral_decubitus")
VH_FEMALE = "/work/shared/anatomy/hubmap_vh_female"
# Grey level (0-255) above which a kidney pixel counts as out of acoustic shadow.
VISIBLE_GREY = 8


def load_volume(
    spec: str, side: str = "right", posture: str = "supine"
) -> tuple[LabelVolume, np.ndarray]:
    """(label volume, unit approach direction in the volume's grid frame V) for a source."""
    src = load_source(spec, side, posture, target=False)
    return src.volume, src.up_V


@dataclass
class Source:
    """A labelled volume to image: where "up" is, and the target kidney's voxels."""

    name: str
    posture: str
    volume: LabelVolume
    up_V: np.ndarray
    target: LabelVolume | None = field(default=None, repr=False)  # 1 = target kidney
    size_class: str | None = None

    @property
    def target_V(self) -> np.ndarray | None:
        """(N, 3) positions (m, in V) of the target kidney's voxels."""
        if self.target is None:
            return None
        return np.argwhere(self.target.labels > 0) * self.volume.voxel_size

    def kidney_mask(
        self, labels: np.ndarray, geometry: ProbeGeometry, X_VP: RigidTransform
    ) -> np.ndarray:
        """Ground truth of a slice: the target kidney (every kidney label if no target)."""
        if self.target is None:
            return is_kidney(labels)
        return slice_volume(geometry, self.target, RigidTransform(), X_VP) > 0

    def needed_depth(self, margin: float = 0.010) -> float:
        """Depth (m) a probe on the upper skin above the target kidney's centroid, looking
        straight down, needs to hold the whole kidney (plus ``margin``), like the start
        planner's vertical pivot."""
        p = (
            self.target_V
            if self.target is not None
            else (np.argwhere(is_kidney(self.volume.labels)) * self.volume.voxel_size)
        )
        up = self.up_V
        c = p.mean(axis=0)
        s = np.arange(0.0, 0.6, 0.5 * self.volume.voxel_size)
        lab = sample_labels(self.volume, c + s[:, None] * up)
        air = np.flatnonzero(lab == Label.OUTSIDE)
        skin = c + (s[air[0]] if len(air) else s[-1]) * up
        return float(((skin - p) @ up).max() + margin)


def _target_component(patient) -> LabelVolume | None:
    """The target kidney's voxels (the kidney component nearest the patient's kidney mesh)
    as a 0/1 volume, or None when the volume holds a single kidney."""
    vol = patient.labels
    comp, n = ndimage.label(is_kidney(vol.labels))
    if n <= 1:
        return None
    sizes = np.bincount(comp.ravel())
    c_Pt = np.asarray(patient.kidney_mesh.vertices).mean(axis=0)
    R, t = vol.X_PtV.rotation().matrix(), vol.X_PtV.translation()
    best, best_d = 0, np.inf
    for k in range(1, n + 1):
        if sizes[k] < 0.05 * sizes[1:].max():
            continue
        c_V = np.argwhere(comp == k).mean(axis=0) * vol.voxel_size
        d = np.linalg.norm(R @ c_V + t - c_Pt)
        if d < best_d:
            best, best_d = k, d
    return LabelVolume((comp == best).astype(np.uint8), vol.voxel_size, vol.X_PtV)


def load_source(
    spec: str, side: str = "right", posture: str = "supine", target: bool = True
) -> Source:
    """A :class:`Source` by spec (see the module doc)."""
    head, _, tail = spec.partition(":")
    if head == "phantom":
        ph = kidney_phantom(np.random.default_rng(int(tail)))
        return Source(spec, "supine", ph.volume, np.array([0.0, 0.0, 1.0]))
    patient = load_patient(spec, side=side, posture=posture, progress=False)
    vol = patient.labels
    # Up from the bed (+z_Pt) expressed in V.
    up_V = np.asarray(vol.X_PtV.rotation().inverse().multiply(np.array([0.0, 0.0, 1.0])))
    return Source(
        spec,
        posture,
        vol,
        up_V,
        _target_component(patient) if target else None,
        patient.meta.get("size_class"),
    )


def make_source_frames(
    spec: str,
    model: EmulatorModel,
    n: int,
    seed: int = 0,
    side: str = "right",
    posture: str = "supine",
):
    """``n`` (us, mask, labels, X_VP) frames of one source, deterministic in ``seed``."""
    vol, up = load_volume(spec, side, posture)
    return make_frames(vol, up, model, n, np.random.default_rng(seed), seed=seed)


def mean_iou(segment, frames, geometry, min_area: float = 1.0e-4) -> dict:
    """Mean IoU of ``segment(us) -> mask`` over frames whose true kidney area >= min_area,
    and the fraction of kidney-free frames where it (wrongly) reports a kidney (NaN, not
    measured, when no frame is kidney-free; as :func:`summarise`)."""
    ious, false_pos, n_empty = [], 0, 0
    for us, gt, *_ in frames:
        pred = np.asarray(segment(us), bool)
        if gt.sum() * geometry.pixel_area >= min_area:
            ious.append(iou(pred, gt))
        else:
            n_empty += 1
            false_pos += int(pred.sum() * geometry.pixel_area >= min_area)
    return {
        "iou": float(np.mean(ious)) if ious else float("nan"),
        "iou_median": float(np.median(ious)) if ious else float("nan"),
        "frames_with_kidney": len(ious),
        "frames_without_kidney": n_empty,
        "false_positive_rate": false_pos / n_empty if n_empty else float("nan"),
    }


# --- across depth presets and postures --------------------------------------------------------


def sample_views(
    source: Source, n: int, seed: int, max_depth: float = 0.40, **kw
) -> list[RigidTransform]:
    """``n`` probe poses X_VP looking down at the source's target kidney (deterministic)."""
    sampler = ViewSampler(
        source.volume, source.up_V, max_depth=max_depth, targets_V=source.target_V, **kw
    )
    rng = np.random.default_rng(seed)
    poses: list[RigidTransform] = []
    for _ in range(5 * n):
        if len(poses) == n:
            break
        X = sampler.sample(rng)
        if X is not None:
            poses.append(X)
    return poses


def centred_views(
    source: Source, angles_deg=(0.0, 60.0, 120.0), indent: float = 0.004
) -> list[RigidTransform]:
    """Probe poses X_VP straight down (against ``up_V``) over the target kidney's centroid,
    the face on the skin pressed ``indent`` in, the array turned by each of ``angles_deg``
    about the beam: the start of a scan's vertical pivot."""
    p = (
        source.target_V
        if source.target is not None
        else (np.argwhere(is_kidney(source.volume.labels)) * source.volume.voxel_size)
    )
    u = source.up_V / np.linalg.norm(source.up_V)
    c = p.mean(axis=0)
    h = source.volume.voxel_size
    s = np.arange(0.0, 0.6, 0.5 * h)
    air = np.flatnonzero(sample_labels(source.volume, c + s[:, None] * u) == Label.OUTSIDE)
    origin = c + (s[air[0]] if len(air) else s[-1]) * u - (indent + 0.5 * h) * u
    e1 = np.cross(u, [1.0, 0, 0] if abs(u[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    poses = []
    for a in np.radians(np.asarray(angles_deg, float)):
        x = np.cos(a) * e1 + np.sin(a) * e2
        z = -u
        poses.append(
            RigidTransform(RotationMatrix(np.column_stack([x, np.cross(z, x), z])), origin)
        )
    return poses


def segmenters_by_depth(presets, config: ImagingConfig | None = None) -> dict:
    """{depth: (config at that depth, geometry, OnnxSegmenter)} for the scenario's model."""
    config = config or ImagingConfig()
    out = {}
    for d in presets:
        cfg = replace(config, depth=float(d))
        g = ProbeGeometry.from_config(cfg)
        out[float(d)] = (cfg, g, OnnxSegmenter.from_config(cfg, g))
    return out


def emulated_views(sources: list[Source], by_depth: dict, n_views: int, seed: int = 0):
    """The frames of each source's ``n_views`` views (the same poses at every depth), imaged
    at every depth of ``by_depth`` ({depth: (config, geometry, anything)}) with that
    depth's emulator; the speckle is seeded per source. Yields (source index, depth,
    config, geometry, the entry's third item, grey frame, true kidney mask, whether the
    kidney is visible: its true section at least ``config.min_kidney_area``)."""
    for si, src in enumerate(sources):
        poses = sample_views(src, n_views, seed + 7919 * si)
        for depth, (cfg, g, item) in by_depth.items():
            model = EmulatorModel.from_config(cfg, g)
            for i, X_VP in enumerate(poses):
                labels = slice_volume(g, src.volume, RigidTransform(), X_VP)
                us = emulate(labels, model, seed + si, i)
                gt = src.kidney_mask(labels, g, X_VP)
                has = bool(gt.sum() * g.pixel_area >= cfg.min_kidney_area)
                yield si, depth, cfg, g, item, us, gt, has


def depth_study(
    sources: list[Source],
    segmenters: dict,
    n_views: int,
    seed: int = 0,
    progress: bool = True,
    desc: str = "frames",
) -> list[dict]:
    """Per-frame records ``{source, posture, depth, iou (None if no kidney), false_positive}``
    of each source's ``n_views`` views (the same poses at every depth) segmented by
    ``segmenters`` ({depth: (config, geometry, segment)}, see :func:`segmenters_by_depth`),
    imaged by :func:`emulated_views`."""
    records = []
    total = len(sources) * n_views * len(segmenters)
    with tqdm(total=total, desc=desc, unit="frame", disable=not progress, mininterval=1.0) as bar:
        for si, depth, cfg, g, segment, us, gt, has in emulated_views(
            sources, segmenters, n_views, seed
        ):
            src = sources[si]
            pred = np.asarray(segment(us), bool)
            records.append(
                {
                    "source": src.name,
                    "posture": src.posture,
                    "depth": depth,
                    "iou": iou(pred, gt) if has else None,
                    "visible": float(np.mean(us[gt] > VISIBLE_GREY)) if has else None,
                    "false_positive": (not has)
                    and bool(pred.sum() * g.pixel_area >= cfg.min_kidney_area),
                }
            )
            bar.update()
    return records


def cluster_bootstrap_ci(
    values, clusters, level: float = 0.95, n_resamples: int = 2000, seed: int = 0
) -> tuple[float, float]:
    """Percentile bootstrap interval (``level``) of the mean of ``values`` that resamples
    whole clusters (``clusters[i]`` names the cluster of ``values[i]``) with replacement.

    The frames of one patient and posture are not independent (one anatomy, one kidney
    shape): resampling frames would make the interval far too narrow. Deterministic in
    ``seed``; (nan, nan) without values, (mean, mean) with a single cluster."""
    values = np.asarray(values, float)
    if values.ndim != 1 or len(clusters) != len(values):
        raise ValueError(
            f"cluster_bootstrap_ci: values must be 1-D with one cluster each, "
            f"got {values.shape} values and {len(clusters)} clusters"
        )
    if not 0.0 < level < 1.0:
        raise ValueError(f"cluster_bootstrap_ci: level must be in (0, 1), got {level}")
    if values.size == 0:
        return float("nan"), float("nan")
    _, index = np.unique(np.asarray(clusters, object).astype(str), return_inverse=True)
    sums = np.bincount(index, weights=values)
    counts = np.bincount(index).astype(float)
    if len(sums) == 1:
        m = float(sums[0] / counts[0])
        return m, m
    pick = np.random.default_rng(seed).integers(0, len(sums), (n_resamples, len(sums)))
    means = sums[pick].sum(axis=1) / counts[pick].sum(axis=1)
    tail = 100.0 * (1.0 - level) / 2.0
    lo, hi = np.percentile(means, [tail, 100.0 - tail])
    return float(lo), float(hi)


def summarise(records: list[dict], key=lambda r: r["depth"]) -> dict:
    """{key: {iou, iou_ci95, iou_median, frames_with_kidney, frames_without_kidney,
    false_positive_rate, false_positive_rate_ci95, iou_visible, frames_visible}} of
    :func:`depth_study` records grouped by ``key``. ``iou_ci95`` and
    ``false_positive_rate_ci95``: the 95% intervals of the mean IoU and of the share of
    kidney-free frames marked as kidney, each resampling a source-and-posture with all its
    views at once (:func:`cluster_bootstrap_ci`; a few marked frames of a few sources make
    the second wide).
    ``iou_visible``: over the frames where at least half the kidney is out of acoustic shadow
    (grey > :data:`VISIBLE_GREY`; the others can hardly be segmented)."""
    groups: dict = {}
    for r in records:
        groups.setdefault(key(r), []).append(r)
    out = {}
    for k, rs in groups.items():
        ious = [r["iou"] for r in rs if r["iou"] is not None]
        clusters = [f"{r.get('source')}|{r.get('posture')}" for r in rs if r["iou"] is not None]
        seen = [r["iou"] for r in rs if r["iou"] is not None and (r.get("visible") or 0) >= 0.5]
        empty = [r for r in rs if r["iou"] is None]
        out[k] = {
            "iou": float(np.mean(ious)) if ious else float("nan"),
            "iou_ci95": cluster_bootstrap_ci(ious, clusters),
            "iou_median": float(np.median(ious)) if ious else float("nan"),
            "frames_with_kidney": len(ious),
            "frames_without_kidney": len(empty),
            "false_positive_rate": (
                # NaN without kidney-free frames: none were marked, but none could be.
                sum(r["false_positive"] for r in empty) / len(empty) if empty else float("nan")
            ),
            "false_positive_rate_ci95": cluster_bootstrap_ci(
                [float(r["false_positive"]) for r in empty],
                [f"{r.get('source')}|{r.get('posture')}" for r in empty],
            ),
            "iou_visible": float(np.mean(seen)) if seen else float("nan"),
            "frames_visible": len(seen),
        }
    return out


def scan_preset(source: Source, presets, margin: float = 0.010) -> float | None:
    """The shallowest preset holding the target kidney below the upper skin (the start
    planner's choice for a vertical view), None if none does."""
    need = source.needed_depth(margin)
    fitting = [p for p in sorted(presets) if p >= need]
    return fitting[0] if fitting else None
