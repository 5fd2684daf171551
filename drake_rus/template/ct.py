"""Kidney templates from real CT kidneys: the seed's section II-D on KiTS-style label maps.

The seed built its template from N = 20 real CT kidneys. This module does the same on a
folder of CT label maps (KiTS layout: ``DIR/case_*/segmentation.nii.gz``, labels 0
background, 1 kidney, 2 tumour), with the same builder as the generated template
(:func:`drake_rus.template.builder.build_template`):

- per kidney: its voxels (anisotropic CT voxels, slices 0.5-5 mm) -> signed distance ->
  1 mm isotropic mask (shape-based interpolation between slices) -> marching cubes ->
  canonical frame by PCA with the sign rules (eq. 13-14: x_k inferior -> superior, y_k
  medial -> lateral, z_k = x_k x y_k) in the body frame the kidney source establishes;
- across kidneys: farthest-point sampling, FPFH + RANSAC (the seed's ref. [34]) and ICP to
  the kidney of median size, kNN re-indexing, mean shape (eq. 15), shape modes, and the
  convergence over N (seed Fig. 3d).

**Where kidneys come from.** The builder reads kidneys through one function,
:func:`kidney_masks` ``(path) -> list[CtKidney]``: every kidney of a label map as its mask, its
tumour mask, the voxel spacing and the pose ``X_BdV`` of the voxel grid in the body frame Bd
(x left, y superior, z anterior), so the sign rules can be applied. Today it calls the
private adapter :func:`_kits_layout_kidneys`; the project's CT-kidney importer replaces it
when it is merged (the builder only needs masks and a frame).

**Tumours** (``tumour_policy``): ``exclude`` (default) leaves out every kidney whose tumour is
more than ``max_tumour_fraction`` of its volume (default 0: only tumour-free kidneys, as in the
seed's healthy TotalSegmentator kidneys, its ref. [33]); ``include`` keeps every kidney with
its tumour as part of the organ (what an ultrasound image would show); ``mask`` keeps every
kidney without its tumour voxels (label 1 only; a large tumour leaves a dent).

**Sides**: ``right`` or ``left`` builds from that kidney of each case, in its own canonical
frame; ``both`` takes both kidneys and mirrors the left ones onto right ones (a reflection
through the body's sagittal plane, which in the canonical frame is z_k -> -z_k), so the
template is a right kidney's.

**The split**: the seed tested on subjects that did not build its template. Cases are taken
from the *last* case in sorted order backwards (the benchmarks test on the first ones), or in
the order of a case list; ``exclude`` removes cases. The template's metadata names every case
and label-map digest used (``cases``, ``subjects``); :func:`split_warnings` says when a case
is scored against a template it built.

**Cache**: never shipped (the KiTS data are CC BY-NC-SA: nothing derived goes into the
repository). :func:`ct_template` keeps templates in the template cache
(:func:`drake_rus.template.population.template_cache_dir`), named by the SHA-256 of the label
maps used (their bytes), the subjects, the options, the source of the code that builds them
(this module, the builder, the canonical frame, marching cubes, the kidney source) and the
library versions; a per-file survey (which kidneys a label map holds, their tumour fractions) is
cached the same way, so the selection is known without reading every file again.
"""

from __future__ import annotations

import hashlib
import inspect
import json
import os
import re
import sys
import tempfile
import time
import warnings
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Callable

import numpy as np
from pydrake.math import RigidTransform, RotationMatrix
from scipy import ndimage
from scipy.spatial import ConvexHull, Delaunay, cKDTree

from drake_rus.anatomy.cache import file_digest, library_versions
from drake_rus.anatomy.frames import lateral_direction_Bd
from drake_rus.anatomy.rasterize import mask_to_mesh
from drake_rus.paths import MODELS_DIR, REPO_ROOT
from drake_rus.template import builder as builder_module
from drake_rus.template.builder import Subject, build_template, save_template, subject_from_mesh
from drake_rus.template.io import DEFAULT_TEMPLATE_PATH, load_template
from drake_rus.template.population import template_cache_dir

__all__ = [
    "CtKidney",
    "kidney_masks",
    "find_label_maps",
    "match_cases",
    "case_name_of",
    "TUMOUR_POLICIES",
    "SIDES",
    "CtTemplateOptions",
    "survey_label_map",
    "select_kidneys",
    "kidney_surface",
    "subject_from_ct_kidney",
    "ct_template",
    "ct_template_path",
    "resolve_template",
    "is_template_spec",
    "split_warnings",
    "TemplateSplitWarning",
    "canonical_kidney_points",
    "template_distance",
    "principal_extents",
    "label_map_digest",
    "DEFAULT_CT_DIR",
    "DEFAULT_SUBJECTS",
    "CtTemplateError",
]

DEFAULT_CT_DIR = REPO_ROOT.parent / "shared" / "anatomy" / "kits19"
DEFAULT_SUBJECTS = 20  # the seed's N (II-D)
DEFAULT_POINTS = 2500  # as the shipped template
DEFAULT_VOXEL = 0.001  # 1 mm isotropic masks, as the shipped template
TUMOUR_POLICIES = ("exclude", "include", "mask")
SIDES = ("right", "left", "both")
# Connected label pieces smaller than this are not kidneys (segmentation fragments).
MIN_KIDNEY_ML = 20.0
# A kidney's long axis lies within about 10-50 deg of the body's long axis (coronal and
# sagittal inclinations), so at least ~40 deg from the left-right axis; a labelled piece whose
# long axis is nearer the left-right axis than this is not one kidney (fused or horseshoe
# kidneys, or a tumour larger than its kidney).
MIN_LR_ANGLE_DEG = 35.0
# Below this margin of the frame's vote (see _kits_frame) a case's kidneys are not used to
# build a template: a wrong superior direction would put a kidney in upside down.
MIN_FRAME_MARGIN = 0.5
LABEL_MAP_SUFFIXES = (".nii.gz", ".nii", ".nrrd", ".nhdr", ".mha", ".mhd")
FORMAT = 1
_LIBRARIES = ("numpy", "scipy", "open3d", "scikit-image", "trimesh", "SimpleITK")


class CtTemplateError(ValueError):
    """Bad input to the CT template builder: ``field`` names the input (``folder``,
    ``cases``, ``case_list``, ``side``, ``tumour_policy``, ``max_tumour_fraction``,
    ``points``, ``voxel``, ``out``, ``template``), ``detail`` says what is wrong; the text
    is ``"<what>: <detail>"``."""

    def __init__(self, field: str, detail: str, what: str | None = None):
        super().__init__(f"{what or field.replace('_', ' ')}: {detail}")
        self.field, self.detail = field, detail


class TemplateSplitWarning(UserWarning):
    """A case is scored against a template it helped to build."""


# ------------------------------------------------------------------------- the interface
@dataclass(eq=False)
class CtKidney:
    """One kidney of a CT label map, placed in the body frame Bd (x left, y superior, z
    anterior). ``kidney`` and ``tumour`` are boolean masks (I, J, K) on the voxel grid V:
    voxel (i, j, k) is centred at ``X_BdV * (i*sx, j*sy, k*sz)`` with ``spacing`` (sx, sy,
    sz) in m. ``cut``: why the kidney is cut by the field of view ("" when it is whole);
    ``anomaly``: why it is not one normal kidney's shape ("" when it is). ``frame``: how the body
    frame was established (the source's own record)."""

    name: str
    case: str
    side: str
    kidney: np.ndarray
    tumour: np.ndarray
    spacing: tuple
    X_BdV: RigidTransform
    cut: str = ""
    anomaly: str = ""
    frame: dict = field(default_factory=dict)

    @property
    def volume_ml(self) -> float:
        return float((self.kidney | self.tumour).sum() * np.prod(self.spacing) * 1e6)

    @property
    def tumour_fraction(self) -> float:
        """Tumour voxels over kidney-and-tumour voxels."""
        n = int((self.kidney | self.tumour).sum())
        return float(self.tumour.sum() / n) if n else 0.0


KidneySource = Callable[[Path], list]


def kidney_masks(path) -> list[CtKidney]:
    """Every kidney of the label map at ``path`` in the body frame (the builder's one source
    of kidneys; see the module doc). Raises ValueError naming the file when it cannot be
    read or holds no kidney label."""
    return _kits_layout_kidneys(Path(path))


# ------------------------------------------------------- private adapter: the KiTS layout
def _read_label_map(path: Path):
    """(labels (I, J, K) uint8 in the file's storage order, spacing (3,) m)."""
    import SimpleITK as sitk

    if not path.is_file():
        raise ValueError(f"label map {path}: file not found")
    try:
        img = sitk.ReadImage(str(path))
    except Exception as e:
        why = (str(e).strip().splitlines() or ["unreadable"])[-1]
        raise ValueError(f"label map {path}: cannot read it ({why})") from None
    if img.GetDimension() != 3 or img.GetNumberOfComponentsPerPixel() != 1:
        raise ValueError(f"label map {path}: expected a 3-D image of integer labels")
    arr = sitk.GetArrayFromImage(img).transpose(2, 1, 0)  # (i, j, k): storage order
    if arr.dtype.kind not in "iu":
        if not np.all(np.isfinite(arr)) or np.any(arr != np.round(arr)):
            raise ValueError(f"label map {path}: voxel values are not integer labels")
    values = np.unique(arr[::4, ::4, ::4])
    if np.any((values < 0) | (values > 2)):
        raise ValueError(
            f"label map {path}: expected labels 0 (background), 1 (kidney), 2 "
            f"(tumour), found {values[(values < 0) | (values > 2)][:5].tolist()}"
        )
    spacing = np.array(img.GetSpacing(), dtype=float) / 1000.0
    if not np.all(np.isfinite(spacing) & (spacing > 0)):
        raise ValueError(f"label map {path}: voxel spacing {spacing * 1e3} mm is not positive")
    return np.ascontiguousarray(arr, dtype=np.uint8), spacing


def _hilum_direction(sub: np.ndarray, origin_ijk, spacing, centroid, v1) -> np.ndarray:
    """Unit direction (index-physical frame) from the kidney's centroid to the centroid of
    its largest concavity (the convex hull minus the kidney, on a ~2 mm grid): the renal
    sinus opening, i.e. the hilum. Component along the long axis ``v1`` removed."""
    stride = np.maximum(1, np.round(0.002 / spacing)).astype(int)
    g = sub[:: stride[0], :: stride[1], :: stride[2]]
    if g.sum() < 10:
        return np.zeros(3)
    gi = np.indices(g.shape).reshape(3, -1).T
    gp = (gi * stride + origin_ijk) * spacing
    inside = g.ravel()
    try:
        hull = Delaunay(gp[inside][ConvexHull(gp[inside]).vertices])
    except Exception:  # a flat or degenerate piece: no hilum cue
        return np.zeros(3)
    deficit = ((hull.find_simplex(gp) >= 0) & ~inside).reshape(g.shape)
    lab, n = ndimage.label(deficit)
    if n == 0:
        return np.zeros(3)
    sizes = ndimage.sum(deficit, lab, range(1, n + 1))
    d = gp[(lab == int(np.argmax(sizes)) + 1).ravel()].mean(axis=0) - centroid
    d = d - (d @ v1) * v1
    norm = np.linalg.norm(d)
    return d / norm if norm > 0 else d


def _kits_frame(pieces, shape, spacing) -> tuple[np.ndarray, dict]:
    """R_BdV (rotation from the index-physical frame V to the body frame Bd) of a KiTS-layout
    label map, from its kidneys' anatomy; and a record of the cues.

    The KiTS README states the array order (axial slice, row, column); which way each axis
    points is decided by anatomy, the file's orientation header being unreliable. With s = +1
    when the slice index runs inferiorly and r = +1 when the row index runs posteriorly:

    - the lower pole lies anterior to the upper pole (the kidney lies on the psoas): the long
      axis' row component, oriented along +slice, is negative when s r = +1;
    - the kidneys lie posterior to the centre of the field of view (the body's centre): +r;
    - the hilum (sinus opening) faces anteriorly: its row component is negative when r = +1
      (with two kidneys, only a concavity facing the other kidney counts);
    - the lower poles lie more laterally than the upper poles (two kidneys): +s.

    Each cue votes (scaled to about +-1 and clipped; a kidney's weight falls linearly to 0
    at 20% tumour), the last one with half weight (on the 140 KiTS19 cases it disagreed
    with the others in 10, the first in none), and the best of the four (s, r) wins. Right
    and left then follow from the frame being right-handed: a label map stored as a mirror
    image of the patient cannot be told from its kidneys alone (both kidneys are mirror
    images of each other); the shape of each kidney, which the template uses, is right
    either way (a mirrored right kidney is geometrically a left kidney).
    """
    centre = (np.array(shape) - 1) * spacing / 2
    # A large tumour bends a kidney's principal axes and fills or fakes its concavity: its
    # kidney's cues count less (none above 20% tumour, unless every kidney is so).
    w = np.array([max(0.0, 1.0 - p["tumour_fraction"] / 0.2) for p in pieces])
    w = w / w.sum() if w.sum() > 0 else np.full(len(pieces), 1.0 / len(pieces))
    v1row = float(w @ [p["v1"][1] for p in pieces])
    post = float(w @ [p["centroid"][1] - centre[1] for p in pieces])
    div = 0.0
    w_hilum = w.copy()
    if len(pieces) == 2:
        mid = 0.5 * (pieces[0]["centroid"][2] + pieces[1]["centroid"][2])
        lateral = [np.sign(p["centroid"][2] - mid) for p in pieces]
        div = float(w @ [lat * p["v1"][2] for lat, p in zip(lateral, pieces)])
        # A concavity that does not face the other kidney is not the hilum (a tumour's
        # notch, a malrotated kidney): it does not vote.
        w_hilum = w * np.array([float(-lat * p["hilum"][2] > 0) for lat, p in zip(lateral, pieces)])
    hilum_row = float(w_hilum @ [p["hilum"][1] for p in pieces])
    cues = {
        "lower_pole_anterior": float(np.clip(-v1row / 0.15, -1, 1)),
        "posterior_of_centre": float(np.clip(post / 0.02, -1, 1)),
        "hilum_anterior": float(np.clip(-hilum_row / 0.3, -1, 1)),
        "lower_poles_lateral": float(np.clip(div / 0.2, -1, 1)),
    }
    scores = {}
    for s in (1, -1):
        for r in (1, -1):
            scores[(s, r)] = (
                s * r * cues["lower_pole_anterior"]
                + r * (cues["posterior_of_centre"] + cues["hilum_anterior"])
                + 0.5 * s * cues["lower_poles_lateral"]
            )
    ranked = sorted(scores, key=scores.get, reverse=True)
    s, r = ranked[0]
    e_i = s * np.array([0.0, -1.0, 0.0])  # +slice: inferior when s = +1
    e_j = r * np.array([0.0, 0.0, -1.0])  # +row: posterior when r = +1
    R = np.column_stack([e_i, e_j, np.cross(e_i, e_j)])
    record = {
        "method": "kits-layout adapter: array (slice, row, column); directions from "
        "anatomy (drake_rus.template.ct._kits_frame)",
        "slice_axis": "inferior" if s > 0 else "superior",
        "row_axis": "posterior" if r > 0 else "anterior",
        "column_axis": "left" if s * r > 0 else "right",
        "cues": {k: round(v, 3) for k, v in cues.items()},
        "margin": round(float(scores[ranked[0]] - scores[ranked[1]]), 3),
    }
    return R, record


def _kits_layout_kidneys(path: Path) -> list[CtKidney]:
    """Private adapter (until the CT-kidney importer is merged): the kidneys of a KiTS-layout
    label map. Kidneys are the (at most two) largest 26-connected pieces of labels 1-2 of at
    least ``MIN_KIDNEY_ML``; smaller pieces are ignored. The frame is :func:`_kits_frame`'s;
    a kidney is right or left by its side of the midpoint between the two kidneys (one
    kidney: of the field of view's centre). A kidney touching the volume's border is cut;
    one whose long axis is within ``MIN_LR_ANGLE_DEG`` of the column (left-right) axis is an
    anomaly."""
    labels, spacing = _read_label_map(path)
    any_k = labels > 0
    if not any_k.any():
        raise ValueError(f"label map {path}: no kidney label (1 or 2)")
    bounds = []
    for ax in range(3):
        prof = np.flatnonzero(any_k.any(axis=tuple(a for a in range(3) if a != ax)))
        bounds.append((int(prof[0]), int(prof[-1]) + 1))
    del any_k
    off = np.array([b[0] for b in bounds])
    crop = labels[tuple(slice(a, b) for a, b in bounds)]
    lab, n = ndimage.label(crop > 0, structure=np.ones((3, 3, 3), bool))
    objects = ndimage.find_objects(lab)
    voxel_ml = float(np.prod(spacing) * 1e6)
    sizes = np.array([np.count_nonzero(lab[o] == k + 1) for k, o in enumerate(objects)])
    order = [int(k) for k in np.argsort(sizes)[::-1][:2] if sizes[k] * voxel_ml >= MIN_KIDNEY_ML]
    if not order:
        raise ValueError(
            f"label map {path}: no kidney of at least {MIN_KIDNEY_ML:g} ml "
            f"(largest labelled piece {sizes.max() * voxel_ml:.1f} ml)"
        )
    pieces = []
    for k in order:
        o = objects[k]
        sub = lab[o] == k + 1
        start = off + np.array([s.start for s in o])
        idx = np.argwhere(sub)
        p = (idx + start) * spacing
        c = p.mean(axis=0)
        step = max(1, len(p) // 200_000)
        _, V = np.linalg.eigh(np.cov((p[::step] - c).T))
        v1 = V[:, -1] * (np.sign(V[0, -1]) or 1.0)  # along +slice
        stop = start + np.array(sub.shape)
        touches = [ax for ax in range(3) if start[ax] == 0 or stop[ax] == labels.shape[ax]]
        sub_labels = np.where(sub, crop[o], 0)
        n_tumour = int(np.count_nonzero(sub_labels == 2))
        lr_deg = float(np.degrees(np.arccos(min(1.0, abs(v1[2])))))
        pieces.append(
            {
                "k": k,
                "o": o,
                "sub": sub,
                "labels": sub_labels,
                "start": start,
                "centroid": c,
                "v1": v1,
                "tumour_fraction": n_tumour / len(p),
                "hilum": _hilum_direction(sub, start, spacing, c, v1),
                "touches": touches,
                "lr_deg": lr_deg,
            }
        )
    R, record = _kits_frame(pieces, labels.shape, spacing)
    x_Bd = [float(R[0] @ p["centroid"]) for p in pieces]
    if len(pieces) == 2:
        mid = 0.5 * sum(x_Bd)
    else:
        mid = float(R[0] @ ((np.array(labels.shape) - 1) * spacing / 2))
    case = case_name_of(path)
    out = []
    for p, x in zip(pieces, x_Bd):
        side = "left" if x > mid else "right"  # x_Bd points to the patient's left
        axes = {0: "slice", 1: "row", 2: "column"}
        cut = ""
        if p["touches"]:
            cut = (
                "touches the edge of the volume along the "
                + " and ".join(axes[a] for a in p["touches"])
                + " axis"
            )
        anomaly = ""
        if p["lr_deg"] < MIN_LR_ANGLE_DEG:
            anomaly = (
                f"long axis {p['lr_deg']:.0f} deg from the left-right axis (a kidney's "
                f"is at least {MIN_LR_ANGLE_DEG:g}): fused or horseshoe kidneys, or a "
                f"tumour larger than the kidney"
            )
        X_BdV = RigidTransform(RotationMatrix(R), R @ (p["start"] * spacing))
        out.append(
            CtKidney(
                name=f"{case}:{side}",
                case=case,
                side=side,
                kidney=p["labels"] == 1,
                tumour=p["labels"] == 2,
                spacing=tuple(float(s) for s in spacing),
                X_BdV=X_BdV,
                cut=cut,
                anomaly=anomaly,
                frame=record,
            )
        )
    if len(out) == 2 and out[0].side == out[1].side:  # cannot happen with two pieces
        raise ValueError(f"label map {path}: both kidneys on the {out[0].side} side")
    return out


# ------------------------------------------------------------------- cases and selection
def case_name_of(path) -> str:
    """The case name of a label map: its folder's name for ``.../NAME/segmentation.*``, else
    the file name without its suffix."""
    p = Path(path)
    name = p.name
    for suf in LABEL_MAP_SUFFIXES:
        if name.lower().endswith(suf):
            name = name[: -len(suf)]
            break
    return p.parent.name if name == "segmentation" else name


def find_label_maps(ct_dir) -> list[tuple[str, Path]]:
    """(case name, label map) of a folder, sorted by name: the KiTS layout
    ``DIR/CASE/segmentation.nii.gz`` (any suffix SimpleITK reads), else label maps directly
    in DIR. Raises CtTemplateError naming the folder when there is none."""
    d = Path(ct_dir).expanduser()
    if not d.is_dir():
        raise CtTemplateError("folder", f"{d}: not a folder", "CT folder")
    found = {}
    for sub in sorted(p for p in d.iterdir() if p.is_dir()):
        for suf in LABEL_MAP_SUFFIXES:
            f = sub / f"segmentation{suf}"
            if f.is_file():
                found[sub.name] = f
                break
    if not found:
        for f in sorted(d.iterdir()):
            if f.is_file() and f.name.lower().endswith(LABEL_MAP_SUFFIXES):
                found[case_name_of(f)] = f
    if not found:
        raise CtTemplateError(
            "folder",
            f"{d}: no label maps (expected DIR/case_*/"
            f"segmentation.nii.gz, or label map files in DIR)",
            "CT folder",
        )
    return sorted(found.items())


def _case_number(name: str):
    m = re.search(r"(\d+)$", name)
    return int(m.group(1)) if m else None


def match_cases(names, spec) -> list[str]:
    """The names among ``names`` that ``spec`` selects: case names and case numbers or
    ranges of them (``0-29``, ``5``, ``case_00005``), separated by commas or spaces; a list
    of such items also works. Raises CtTemplateError for an item that selects nothing
    or is malformed."""
    items = (
        spec if isinstance(spec, (list, tuple, set, frozenset)) else re.split(r"[,\s]+", str(spec))
    )
    names = list(names)
    chosen = []
    for item in (str(i).strip() for i in items):
        if not item:
            continue
        m = re.fullmatch(r"(\d+)\s*-\s*(\d+)", item)
        if m:
            lo, hi = int(m.group(1)), int(m.group(2))
            if hi < lo:
                raise CtTemplateError("cases", f"range {item!r} runs backwards")
            hit = [n for n in names if (k := _case_number(n)) is not None and lo <= k <= hi]
        elif item.isdigit():
            hit = [n for n in names if _case_number(n) == int(item)]
        else:
            hit = [n for n in names if n == item or n == case_name_of(item)]
        if not hit and not re.fullmatch(r"[\w.\-]+", item):
            raise CtTemplateError(
                "cases", f"{item!r} is not a case name, number or range (e.g. case_00005, 5, 0-29)"
            )
        chosen.extend(h for h in hit if h not in chosen)
    return chosen


@dataclass(frozen=True)
class CtTemplateOptions:
    """What a CT template is built from (with the cases): see the module doc."""

    n: int = DEFAULT_SUBJECTS
    side: str = "right"
    tumour_policy: str = "exclude"
    max_tumour_fraction: float = 0.0
    n_points: int = DEFAULT_POINTS
    voxel: float = DEFAULT_VOXEL
    strict_n: bool = False  # True: fewer than n eligible kidneys is an error

    def check(self) -> None:
        if int(self.n) < 1:
            raise CtTemplateError("n", f"expected at least 1 kidney, got {self.n}", "kidneys")
        if self.side not in SIDES:
            raise CtTemplateError("side", f"expected one of {', '.join(SIDES)}, got {self.side!r}")
        if self.tumour_policy not in TUMOUR_POLICIES:
            raise CtTemplateError(
                "tumour_policy",
                f"expected one of {', '.join(TUMOUR_POLICIES)}, got {self.tumour_policy!r}",
            )
        if not 0.0 <= float(self.max_tumour_fraction) <= 1.0:
            raise CtTemplateError(
                "max_tumour_fraction", f"expected 0-1, got {self.max_tumour_fraction}"
            )
        if int(self.n_points) < 100:
            raise CtTemplateError("points", f"expected at least 100, got {self.n_points}")
        if not 0.0002 <= float(self.voxel) <= 0.005:
            raise CtTemplateError("voxel", f"expected 0.2-5 mm, got {self.voxel * 1e3:g} mm")

    def key(self) -> dict:
        return {
            "n": int(self.n),
            "side": self.side,
            "tumour_policy": self.tumour_policy,
            "max_tumour_fraction": float(self.max_tumour_fraction)
            if self.tumour_policy == "exclude"
            else None,
            "n_points": int(self.n_points),
            "voxel": float(self.voxel),
        }


def _code_files() -> set:
    """The source files a CT template is made by: this module, the builder, the canonical
    frame's module and marching cubes' (found through the functions, wherever they live)."""
    return {
        _source_file(f)
        for f in (
            subject_from_ct_kidney,
            build_template,
            builder_module.mesh_canonical_frame,
            mask_to_mesh,
        )
    }


@lru_cache(maxsize=4)
def _code_key(source_file: str) -> dict:
    h = hashlib.sha256()
    for p in sorted(Path(f) for f in _code_files() | {source_file}):
        h.update(p.name.encode() + b"\0" + p.read_bytes() + b"\0")
    return {"code": h.hexdigest(), "libraries": library_versions(_LIBRARIES)}


def _source_file(function) -> str:
    return str(Path(inspect.getsourcefile(function)).resolve())


@lru_cache(maxsize=1024)
def _digest(path: str, size: int, mtime_ns: int) -> str:
    return file_digest(path)


def label_map_digest(path) -> str:
    """SHA-256 of a label map's bytes (kept per process by path, size and time)."""
    st = os.stat(path)
    return _digest(str(Path(path).resolve()), st.st_size, st.st_mtime_ns)


def _write_json_atomic(path: Path, doc: dict) -> bool:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=".json", dir=str(path.parent))
        with os.fdopen(fd, "w") as f:
            json.dump(doc, f)
        os.replace(tmp, path)
        return True
    except OSError:
        return False


def survey_label_map(path, source: KidneySource = kidney_masks) -> dict:
    """What a label map holds, per kidney: side, volume (ml), tumour fraction, cut (why), and
    the frame record; ``error`` when it cannot be read. Cached by the file's digest and the
    code (one small JSON file per label map in the template cache's ``ct-survey``)."""
    path = Path(path)
    digest = label_map_digest(path)
    key = hashlib.sha256(
        json.dumps({"file": digest, **_code_key(_source_file(source))}, sort_keys=True).encode()
    ).hexdigest()
    cache = template_cache_dir() / "ct-survey" / f"{key[:32]}.json"
    if cache.is_file():
        try:
            doc = json.loads(cache.read_text())
            if doc.get("digest") == digest:
                return doc
        except (OSError, json.JSONDecodeError):
            pass
    doc = {"digest": digest, "case": case_name_of(path), "kidneys": []}
    try:
        for k in source(path):
            doc["kidneys"].append(
                {
                    "side": k.side,
                    "volume_ml": round(k.volume_ml, 2),
                    "tumour_fraction": round(k.tumour_fraction, 4),
                    "cut": k.cut,
                    "anomaly": k.anomaly,
                    "frame": k.frame,
                }
            )
    except ValueError as e:
        doc["error"] = str(e)
    _write_json_atomic(cache, doc)
    return doc


def _eligible(info: dict, opts: CtTemplateOptions) -> str:
    """'' if the kidney may build the template, else why not."""
    if info["cut"]:
        return f"cut by the field of view ({info['cut']})"
    if info.get("anomaly"):
        return info["anomaly"]
    margin = (info.get("frame") or {}).get("margin", np.inf)
    if margin < MIN_FRAME_MARGIN:
        return (
            f"body frame uncertain (the anatomical cues' margin {margin:.2f} < "
            f"{MIN_FRAME_MARGIN:g})"
        )
    if opts.tumour_policy == "exclude" and info["tumour_fraction"] > opts.max_tumour_fraction:
        return (
            f"tumour {100 * info['tumour_fraction']:.1f}% of the kidney (policy exclude, "
            f"max {100 * opts.max_tumour_fraction:g}%)"
        )
    return ""


def select_kidneys(pool, surveys: dict, opts: CtTemplateOptions):
    """The kidneys that build the template: walking ``pool`` ((case, path) in order), the
    requested side's kidney of each case (``both``: right, then left) when eligible, until
    ``opts.n``. Returns (selected [{case, side, path, digest}], skipped [{case, side, why}])."""
    sides = ("right", "left") if opts.side == "both" else (opts.side,)
    selected, skipped = [], []
    for case, path in pool:
        doc = surveys[case]
        if doc.get("error"):
            skipped.append({"case": case, "side": "-", "why": doc["error"]})
            continue
        for side in sides:
            if len(selected) >= opts.n:
                break
            info = [k for k in doc["kidneys"] if k["side"] == side]
            if not info:
                skipped.append({"case": case, "side": side, "why": f"no {side} kidney"})
                continue
            why = _eligible(info[0], opts)
            if why:
                skipped.append({"case": case, "side": side, "why": why})
                continue
            selected.append(
                {
                    "case": case,
                    "side": side,
                    "path": str(path),
                    "digest": doc["digest"],
                    "tumour_fraction": info[0]["tumour_fraction"],
                    "volume_ml": info[0]["volume_ml"],
                }
            )
        if len(selected) >= opts.n:
            break
    return selected, skipped


# ---------------------------------------------------------------- one kidney -> subject
def kidney_surface(kidney: CtKidney, tumour_policy: str = "exclude", voxel: float = DEFAULT_VOXEL):
    """The kidney's watertight surface in Bd (m): its mask (with the tumour, or without it
    for ``mask``) -> signed distance on the CT grid -> linear interpolation onto a ``voxel``
    isotropic grid (shape-based interpolation between thick slices) -> marching cubes."""
    if tumour_policy == "mask":
        m = kidney.kidney
        lab, n = ndimage.label(m, structure=np.ones((3, 3, 3), bool))
        if n > 1:
            sizes = ndimage.sum(m, lab, range(1, n + 1))
            m = lab == int(np.argmax(sizes)) + 1
    else:
        m = kidney.kidney | kidney.tumour
    if not m.any():
        raise ValueError(f"{kidney.name}: empty kidney mask")
    sp = np.asarray(kidney.spacing, dtype=float)
    pad = 2
    mp = np.pad(m, pad)
    sdf = ndimage.distance_transform_edt(~mp, sampling=sp) - ndimage.distance_transform_edt(
        mp, sampling=sp
    )
    extent = (np.array(mp.shape) - 1) * sp
    n_iso = np.floor(extent / voxel).astype(int) + 1
    axes = [np.arange(k) * voxel / s for k, s in zip(n_iso, sp)]
    grid = np.meshgrid(*axes, indexing="ij")
    iso = ndimage.map_coordinates(sdf, grid, order=1, mode="nearest") < 0
    X_BdIso = kidney.X_BdV.multiply(RigidTransform(-pad * sp))
    return mask_to_mesh(iso, X_BdIso, voxel, sigma_vox=1.0, what=f"{kidney.name}: kidney mask")


def subject_from_ct_kidney(
    kidney: CtKidney,
    tumour_policy: str = "exclude",
    voxel: float = DEFAULT_VOXEL,
    mirror: bool = False,
) -> Subject:
    """A template subject (surface in its canonical frame, eq. 13-14 with x_ref the body's
    superior and y_ref the kidney's lateral direction); ``mirror``: reflected through the
    sagittal plane (z_k -> -z_k), a left kidney made a right one."""
    mesh = kidney_surface(kidney, tumour_policy, voxel)
    s = subject_from_mesh(
        mesh, [0.0, 1.0, 0.0], lateral_direction_Bd(kidney.side), name=kidney.name
    )
    if mirror:
        flip = np.array([1.0, 1.0, -1.0])
        s = Subject(
            name=f"{kidney.name} (mirrored)",
            points=s.points * flip,
            normals=s.normals * flip,
            X_SK=None,
            volume=s.volume,
        )
    return s


# ------------------------------------------------------------------- the cached template
def _pool(maps, exclude, case_list) -> tuple[list, list]:
    """(pool [(case, path)] in build order, excluded case names)."""
    names = [c for c, _ in maps]
    by_name = dict(maps)
    excluded = match_cases(names, exclude) if exclude else []
    if case_list is not None:
        try:
            order = match_cases(names, case_list)
        except CtTemplateError as e:
            raise CtTemplateError("case_list", e.detail) from None
        if not order:
            raise CtTemplateError("case_list", f"selects none of the {len(names)} cases")
    else:
        order = names[::-1]  # the last cases first: the first ones stay for testing
    return [(c, by_name[c]) for c in order if c not in excluded], excluded


def _inputs(selected, opts, source) -> dict:
    return {
        "format": FORMAT,
        "subjects": [(s["case"], s["side"], s["digest"]) for s in selected],
        "options": opts.key(),
        **_code_key(_source_file(source)),
    }


def ct_template_path(
    selected, opts: CtTemplateOptions, source: KidneySource = kidney_masks
) -> Path:
    """The cache file of a template built from ``selected`` kidneys with ``opts``."""
    doc = json.dumps(_inputs(selected, opts, source), sort_keys=True)
    return template_cache_dir() / f"ct-{hashlib.sha256(doc.encode()).hexdigest()[:24]}.npz"


def _refuse_models_dir(out: Path) -> None:
    try:
        inside = out.resolve().is_relative_to(MODELS_DIR.resolve())
    except OSError:
        inside = False
    if inside or out.resolve() == DEFAULT_TEMPLATE_PATH.resolve():
        raise CtTemplateError(
            "out",
            f"{out} is in the repository's models/ folder; a template "
            f"from CT data (CC BY-NC-SA) is never shipped: write it to the "
            f"cache (the default) or elsewhere",
        )


def ct_template(
    ct_dir,
    opts: CtTemplateOptions | None = None,
    *,
    exclude=(),
    case_list=None,
    out=None,
    progress: bool = False,
    source: KidneySource = kidney_masks,
    log=None,
) -> Path:
    """The template of the CT kidneys in ``ct_dir`` (see the module doc): from the cache when
    it was built before from the same kidneys, options and code, else built and stored
    (``out``: written there instead, never under models/). ``exclude``: cases never used
    (names, numbers, ranges); ``case_list``: the cases to use, in order (default: all, the
    last first). ``progress``: progress bars; ``log``: a function taking one line of
    progress (default: none). Returns the .npz path (its metadata also in a .json beside it)."""
    opts = opts or CtTemplateOptions()
    opts.check()
    if out is not None:
        out = Path(out)
        if out.suffix != ".npz":
            raise CtTemplateError("out", f"expected a .npz file name, got {out}")
        _refuse_models_dir(out)
    say = log or (lambda line: None)
    ct_dir = Path(ct_dir).expanduser().resolve()
    maps = find_label_maps(ct_dir)
    pool, excluded = _pool(maps, exclude, case_list)
    t0 = time.time()
    surveys, selected, skipped = {}, [], []
    for case, path in pool:  # survey only as far as the selection needs
        if case not in surveys:
            surveys[case] = survey_label_map(path, source)
        selected, skipped = select_kidneys([p for p in pool if p[0] in surveys], surveys, opts)
        if len(selected) >= opts.n:
            break
    t_survey = time.time() - t0
    if not selected:
        raise CtTemplateError(
            "folder",
            f"{ct_dir}: no eligible kidney among {len(pool)} cases ({_skip_summary(skipped)})",
            "CT folder",
        )
    if len(selected) < opts.n:
        msg = (
            f"{len(selected)} eligible {opts.side} kidneys of the {opts.n} asked for in "
            f"{ct_dir} ({_skip_summary(skipped)})"
        )
        if opts.strict_n:
            raise CtTemplateError("n", msg, "kidneys")
        warnings.warn(msg + f"; building from {len(selected)}", stacklevel=2)
    path = out if out is not None else ct_template_path(selected, opts, source)
    if out is None and path.is_file():
        return path
    say(
        f"CT template: building from {len(selected)} kidneys of {ct_dir} (first use; "
        f"cached in {path.parent}) ..."
    )
    t1 = time.time()
    subjects, frames = [], []
    for s in selected:
        name = f"{s['case']}:{s['side']}"
        try:
            kidneys = [k for k in source(Path(s["path"])) if k.side == s["side"]]
            if not kidneys:
                raise ValueError(f"no {s['side']} kidney (the label map changed?)")
            k = kidneys[0]
            mirror = opts.side == "both" and k.side == "left"
            subjects.append(subject_from_ct_kidney(k, opts.tumour_policy, opts.voxel, mirror))
        except ValueError as e:
            raise CtTemplateError(
                "folder",
                f"{ct_dir}: kidney {name}: {e} (leave it out with --exclude-cases {s['case']})",
                "CT folder",
            ) from None
        frames.append(k.frame)
        say(f"  {k.name}: {k.volume_ml:.0f} ml, tumour {100 * k.tumour_fraction:.1f}%")
    t2 = time.time()
    result = build_template(subjects, n_points=opts.n_points, progress=progress)
    t3 = time.time()
    ext = np.array([np.ptp(s.points, axis=0) for s in subjects]) * 1e3
    extra = {
        "split": f"ct:{ct_dir}",
        "source": "CT label maps (seed II-D on real kidneys; drake_rus.template.ct)",
        "ct_dir": str(ct_dir),
        "side": opts.side,
        "mirrored_left": opts.side == "both",
        "tumour_policy": opts.tumour_policy,
        "max_tumour_fraction": opts.max_tumour_fraction
        if opts.tumour_policy == "exclude"
        else None,
        "voxel_mm": opts.voxel * 1e3,
        "n_requested": int(opts.n),
        "cases": sorted({s["case"] for s in selected}),
        "subjects_used": [
            {k: s[k] for k in ("case", "side", "digest", "tumour_fraction", "volume_ml")}
            for s in selected
        ],
        "excluded_cases": excluded,
        "case_order": "case list" if case_list is not None else "last case first",
        "skipped": skipped,
        "subject_extent_mm": {
            "mean": ext.mean(axis=0).round(2).tolist(),
            "sd": ext.std(axis=0, ddof=1).round(2).tolist() if len(ext) > 1 else [0.0, 0.0, 0.0],
        },
        "frame": {
            "method": frames[0].get("method") if frames else None,
            "min_margin": min((f.get("margin", np.inf) for f in frames), default=None),
        },
        "licence": "derived from CC BY-NC-SA data: keep out of the repository",
        "survey_seconds": round(t_survey, 2),
        "subject_seconds": round(t2 - t1, 2),
        "total_seconds": round(t3 - t0, 2),
    }
    try:
        save_template(result, path, extra)
    except OSError as e:
        if out is not None:
            raise
        tmp = Path(tempfile.mkdtemp(prefix="drake_rus_template_")) / path.name
        print(
            f"warning: template cache {path.parent} not writable ({e}); using {tmp}",
            file=sys.stderr,
        )
        save_template(result, tmp, extra)
        return tmp
    return path


def _skip_summary(skipped) -> str:
    if not skipped:
        return "none skipped"
    reasons = {}
    for s in skipped:
        why = re.sub(r"\d+(\.\d+)?%", "N%", s["why"])
        why = re.sub(r"label map .*?: ", "", why)
        reasons[why] = reasons.get(why, 0) + 1
    return "; ".join(f"{n} x {w}" for w, n in sorted(reasons.items(), key=lambda x: -x[1])[:4])


# -------------------------------------------------------------------- template selection
_SPEC = re.compile(r"(generated|real)(:(.+))?")


def is_template_spec(value) -> bool:
    """True for the symbolic template values ``generated``, ``real`` and ``real:DIR``."""
    return isinstance(value, str) and _SPEC.fullmatch(value.strip()) is not None


def resolve_template(
    spec,
    exclude_cases=(),
    *,
    opts: CtTemplateOptions | None = None,
    progress: bool = False,
    log=None,
) -> Path:
    """The template file that ``spec`` names, for scans, benchmarks and studies:

    - None, ``""`` or ``generated``: the shipped template of generated kidneys
      (``models/kidney_template.npz``);
    - ``real``: the template of real CT kidneys from ``../shared/anatomy/kits19`` (beside the
      repository), built on first use into the cache (:func:`ct_template`, default options:
      20 tumour-free right kidneys, the last cases first);
    - ``real:DIR``: the same from the label maps in DIR;
    - anything else: a template file (relative paths from the repository's root).

    ``exclude_cases``: cases that will be scored (names, numbers, ranges, or label-map paths):
    a real template is built without them; a template file that used any of them warns
    (:class:`TemplateSplitWarning`). Raises CtTemplateError (ValueError) for a bad spec.
    """
    if spec is None or str(spec).strip() in ("", "generated"):
        return DEFAULT_TEMPLATE_PATH
    text = str(spec).strip()
    m = _SPEC.fullmatch(text)
    if m and m.group(1) == "real":
        ct_dir = Path(m.group(3)).expanduser() if m.group(3) else DEFAULT_CT_DIR
        if not ct_dir.is_absolute():
            ct_dir = Path.cwd() / ct_dir
        if not ct_dir.is_dir():
            raise CtTemplateError("template", f"{text!r}: CT folder {ct_dir} not found")
        names = [c for c, _ in find_label_maps(ct_dir)]
        exclude = _exclusions(names, exclude_cases)
        return ct_template(ct_dir, opts, exclude=exclude, progress=progress, log=log)
    if m and m.group(1) == "generated":
        raise CtTemplateError("template", f"{text!r}: 'generated' takes no folder")
    path = Path(text).expanduser()
    if not path.is_absolute():
        path = REPO_ROOT / path
    for w in split_warnings(path, exclude_cases):
        warnings.warn(w, TemplateSplitWarning, stacklevel=2)
    return path


def _exclusions(names, cases) -> list[str]:
    """Case names among ``names`` that ``cases`` (names, numbers, ranges, paths) selects;
    items that select nothing are ignored (a generated patient has no case)."""
    out = []
    for c in [cases] if isinstance(cases, (str, Path)) else list(cases or ()):
        c = str(c)
        item = case_name_of(c) if ("/" in c or c.lower().endswith(LABEL_MAP_SUFFIXES)) else c
        try:
            hit = match_cases(names, [item])
        except CtTemplateError:
            hit = []
        if not hit:  # a patient spec naming a case folder: .../case_00012...
            token = re.search(r"case_\d+", c)
            hit = [n for n in names if token and n == token.group(0)]
        out.extend(h for h in hit if h not in out)
    return out


def split_warnings(template, cases) -> list[str]:
    """One line per case of ``cases`` (names, or label-map paths / patient specs naming a
    case folder) that built ``template`` (a path, a Template or its metadata dict): scoring
    it against this template is not a test on unseen data."""
    if template is None:
        return []
    if isinstance(template, dict):
        meta = template
    elif hasattr(template, "meta"):
        meta = template.meta
    else:
        try:
            meta = load_template(template).meta
        except (OSError, ValueError):
            return []
    used = meta.get("subjects_used") or []
    if not used:
        return []
    names = {u["case"] for u in used}
    digests = {u["digest"]: u["case"] for u in used}
    out = []
    for c in [cases] if isinstance(cases, (str, Path)) else list(cases or ()):
        c = str(c)
        hit = None
        p = Path(c).expanduser()
        if p.is_dir():
            maps = [p / f"segmentation{s}" for s in LABEL_MAP_SUFFIXES]
            p = next((f for f in maps if f.is_file()), p)
        if p.is_file():
            try:
                hit = digests.get(label_map_digest(p))
            except OSError:
                hit = None
        if hit is None:
            token = re.search(r"case_\d+", c)
            name = token.group(0) if token else c
            hit = name if name in names else None
        if hit is not None:
            out.append(
                f"template {meta.get('ct_dir', '')}: case {hit} helped build it "
                f"(its subjects: {len(used)}); scoring {c} against it is not a test "
                f"on an unseen kidney"
            )
    return out


# ------------------------------------------------------------------------ measurements
def canonical_kidney_points(
    kidney: CtKidney,
    tumour_policy: str = "include",
    voxel: float = DEFAULT_VOXEL,
    mirror: bool = False,
) -> np.ndarray:
    """The kidney's surface points (marching-cubes vertices) in its canonical frame K (m)."""
    return subject_from_ct_kidney(kidney, tumour_policy, voxel, mirror).points


def template_distance(points_K: np.ndarray, template_points: np.ndarray) -> float:
    """Symmetric mean nearest-neighbour distance (m) between a kidney's surface points and a
    template's points, both in their canonical frames (principal axes, no scaling, no ICP):
    the measure of the template study (``drake_rus.experiments.templates.template_distance``)."""
    a = cKDTree(points_K).query(template_points)[0].mean()
    b = cKDTree(template_points).query(points_K)[0].mean()
    return float(0.5 * (a + b))


def principal_extents(points: np.ndarray) -> np.ndarray:
    """Extents (3,) of points along their own principal axes (m): length, width, thickness."""
    p = np.asarray(points, dtype=float)
    c = p.mean(axis=0)
    _, V = np.linalg.eigh(np.cov((p - c).T))
    return np.ptp((p - c) @ V[:, ::-1], axis=0)
