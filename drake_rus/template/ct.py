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
(x left, y superior, z anterior), so the sign rules can be applied. It reads them with the
project's CT-kidney importer (:mod:`drake_rus.anatomy.ct_kidney`), the one place where the
patient frame of a label map is established; a case whose frame the importer cannot
establish is an error, and its kidneys build no template.

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
from scipy.spatial import cKDTree

from drake_rus.anatomy.cache import file_digest, library_versions
from drake_rus.anatomy.ct_kidney import (
    KIDNEY_VALUE,
    TUMOUR_VALUE,
    KidneyComponent,
    import_ct_kidneys,
    read_label_grid,
)
from drake_rus.anatomy.ct_patient import CT_PREFIX, ct_label_map_path, parse_ct_spec
from drake_rus.anatomy.frames import lateral_direction_Bd
from drake_rus.anatomy.rasterize import mask_to_mesh
from drake_rus.paths import MODELS_DIR, REPO_ROOT
from drake_rus.template import builder as builder_module
from drake_rus.template.builder import (
    Subject,
    build_template,
    save_template_to_cache,
    subject_from_mesh,
)
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
# A kidney's long axis lies within about 10-50 deg of the body's long axis (coronal and
# sagittal inclinations), so at least ~40 deg from the left-right axis; a labelled piece whose
# long axis is nearer the left-right axis than this is not one kidney (fused or horseshoe
# kidneys, or a tumour larger than its kidney).
MIN_LR_ANGLE_DEG = 35.0
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
    of kidneys), read by the project's CT-kidney importer (:mod:`drake_rus.anatomy.ct_kidney`:
    the patient frame established from anatomy, right and left from the grid's handedness).
    Raises ValueError naming the file when it cannot be read, holds no kidney label, or its
    frame cannot be established (the importer's errors); a frame decided by the majority of
    the cues (status ``conflict``) is used, its status kept in ``frame``."""
    path = Path(path)
    try:
        case = import_ct_kidneys(read_label_grid(path))
    except FileNotFoundError as e:
        raise ValueError(str(e)) from None
    frame = {
        "method": "anatomy (drake_rus.anatomy.ct_kidney.import_ct_kidneys)",
        "handedness": int(case.frame.handedness),
        **case.frame.summary(),
    }
    name = case_name_of(path)
    return [_ct_kidney(k, case.frame.R_AG, name, frame) for k in case.kidneys]


def _ct_kidney(k: KidneyComponent, R_AG: np.ndarray, case: str, frame: dict) -> CtKidney:
    """A CtKidney from the importer's component: its crop of the grid G (numpy axes, mm) as
    the voxel grid V, posed in Bd (the importer's anatomical frame A: x left, y superior,
    z anterior). A left-handed grid makes R_AG improper: the crop's first axis is then
    reversed so that V's axes form a rotation."""
    labels = k.labels
    sp = np.asarray(k.spacing, dtype=float) / 1000.0  # m
    origin_G = np.asarray(k.lo, dtype=float) * sp
    R = np.asarray(R_AG, dtype=float)
    if np.linalg.det(R) < 0:
        labels = labels[::-1]
        origin_G = origin_G + np.array([(labels.shape[0] - 1) * sp[0], 0.0, 0.0])
        R = R @ np.diag([-1.0, 1.0, 1.0])
    X_BdV = RigidTransform(RotationMatrix(R), R_AG @ origin_G)
    cut = ""
    if k.touches:
        cut = "touches the edge of the volume (" + ", ".join(k.touches) + ")"
    p = np.argwhere(labels > 0)
    step = max(1, len(p) // 200_000)
    q = p[::step] * sp
    _, V = np.linalg.eigh(np.cov((q - q.mean(axis=0)).T))
    v1_Bd = R @ V[:, -1]
    lr_deg = float(np.degrees(np.arccos(min(1.0, abs(v1_Bd[0])))))
    anomaly = ""
    if lr_deg < MIN_LR_ANGLE_DEG:
        anomaly = (
            f"long axis {lr_deg:.0f} deg from the left-right axis (a kidney's is at least "
            f"{MIN_LR_ANGLE_DEG:g}): fused or horseshoe kidneys, or a tumour larger than "
            f"the kidney"
        )
    return CtKidney(
        name=f"{case}:{k.side}",
        case=case,
        side=k.side,
        kidney=np.ascontiguousarray(labels == KIDNEY_VALUE),
        tumour=np.ascontiguousarray(labels == TUMOUR_VALUE),
        spacing=tuple(float(x) for x in sp),
        X_BdV=X_BdV,
        cut=cut,
        anomaly=anomaly,
        frame=frame,
    )


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
    frame's module and marching cubes' (found through the functions, wherever they live),
    and every module of the packages they live in (``drake_rus.anatomy``,
    ``drake_rus.template``): a helper they call (the importer's frame cues, the body's
    directions) changes the template as much as they do, and a key that missed it would
    serve a template the running code no longer builds."""
    direct = {
        _source_file(f)
        for f in (
            subject_from_ct_kidney,
            import_ct_kidneys,
            build_template,
            builder_module.mesh_canonical_frame,
            mask_to_mesh,
        )
    }
    return {str(p.resolve()) for d in {Path(f).parent for f in direct} for p in d.glob("*.py")}


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
            "status": {
                st: sum(f.get("status") == st for f in frames) for st in ("agree", "conflict")
            },
        },
        "licence": "derived from CC BY-NC-SA data: keep out of the repository",
        "survey_seconds": round(t_survey, 2),
        "subject_seconds": round(t2 - t1, 2),
        "total_seconds": round(t3 - t0, 2),
    }
    return save_template_to_cache(result, path, extra, asked_for=out is not None)


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


def _spec_target(item: str) -> str:
    """A ``ct:PATH[#OPTIONS]`` patient spec as the label map it names (a folder as given
    when it holds none, an unparsable spec as is); any other item unchanged."""
    if not item.startswith(CT_PREFIX):
        return item
    try:
        path = parse_ct_spec(item).path
    except ValueError:
        return item
    try:
        return str(ct_label_map_path(path, item))
    except (ValueError, OSError):
        return str(path)


def _exclusions(names, cases) -> list[str]:
    """Case names among ``names`` that ``cases`` (names, numbers, ranges, paths) selects;
    items that select nothing are ignored (a generated patient has no case)."""
    out = []
    for c in [cases] if isinstance(cases, (str, Path)) else list(cases or ()):
        c = _spec_target(str(c))
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
        p = Path(_spec_target(c)).expanduser()
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
