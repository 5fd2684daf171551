"""Reading the kidney template file (``models/kidney_template.npz``)."""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from drake_rus.paths import MODELS_DIR

DEFAULT_TEMPLATE_PATH = MODELS_DIR / "kidney_template.npz"
_REQUIRED = ("points", "normals", "modes", "variances", "metadata")

# What a template file must satisfy (check_template_arrays). The fewest points `drake-rus
# template build --points` writes; below that the surface is too coarse for the
# plane-to-plane registration and the tracking's image-plane sections.
MIN_TEMPLATE_POINTS = 100
# Normals and shape modes are unit vectors; float32 storage alone leaves 1e-7.
UNIT_TOLERANCE = 1e-3
# The template's long axis (x_K) in metres: an adult kidney is 100-130 mm long (facts:
# 108.5 +- 12.2 mm), a child's from about 45 mm; outside this range the file is in other
# units (mm, cm) or not a kidney.
KIDNEY_LENGTH_RANGE = (0.04, 0.25)
# K's origin is the template's centroid (eq. 13): the points' mean lies within this
# fraction of the long-axis extent of it (the builder centres it exactly).
MAX_CENTROID_OFFSET_FRACTION = 0.1


@dataclass
class Template:
    """Kidney template in its canonical frame K (m): x_k inferior -> superior, y_k medial ->
    lateral, z_k = x_k x y_k, origin at the centroid.

    ``points`` (M, 3) and ``normals`` (M, 3, outward unit) are the mean shape (eq. 15);
    ``modes`` (k, M, 3) unit-norm shape modes with ``variances`` (k,) in m^2 (95% of the
    cohort's variance): a shape is ``points + sum_i b_i modes[i]``, b_i ~ N(0, variances[i]).
    """

    points: np.ndarray
    normals: np.ndarray
    modes: np.ndarray
    variances: np.ndarray
    meta: dict = field(default_factory=dict)
    convergence: dict = field(default_factory=dict)

    def shape(self, coefficients) -> np.ndarray:
        """Template deformed by mode coefficients b (m), (M, 3)."""
        b = np.asarray(coefficients, dtype=float)
        if b.shape != (len(self.variances),):
            raise ValueError(
                f"coefficients: expected shape ({len(self.variances)},), got {b.shape}"
            )
        return self.points + np.tensordot(b, self.modes, axes=1)

    def shape_sd(self, sds) -> np.ndarray:
        """Template deformed by ``sds`` standard deviations along each mode."""
        return self.shape(np.asarray(sds, dtype=float) * np.sqrt(self.variances))


def _numeric(a) -> bool:
    return np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)


def check_template_arrays(points, normals, modes, variances) -> str:
    """Why these arrays are not a usable template ('' if they are): one line naming the
    field. Points (M, 3) finite, at least MIN_TEMPLATE_POINTS, in metres (long-axis extent
    in KIDNEY_LENGTH_RANGE) and centred on K's origin; normals (M, 3) unit vectors; modes
    (k, M, 3) finite unit-norm fields with variances (k,) positive and finite (the
    registration's shape prior divides by them), a standard deviation moving the points by
    less than the kidney's length (RMS); k = 0 (no modes) allowed."""
    points, normals = np.asarray(points), np.asarray(normals)
    modes, variances = np.asarray(modes), np.asarray(variances)
    for name, a in (
        ("points", points),
        ("normals", normals),
        ("modes", modes),
        ("variances", variances),
    ):
        if not _numeric(a):
            return f"field '{name}': expected numbers, got an array of {a.dtype}"
    if points.ndim != 2 or points.shape[1] != 3:
        return f"field 'points': expected an (M, 3) array, got shape {points.shape}"
    m = len(points)
    if normals.shape != points.shape:
        return (
            f"field 'normals': expected an (M, 3) array matching 'points' {points.shape}, "
            f"got shape {normals.shape}"
        )
    for name, a in (("points", points), ("normals", normals)):
        bad = ~np.all(np.isfinite(a), axis=1)
        if bad.any():
            return f"field '{name}': {int(bad.sum())} of {m} rows contain NaN or inf"
    if m < MIN_TEMPLATE_POINTS:
        return f"field 'points': {m} points; expected at least {MIN_TEMPLATE_POINTS}"
    norms = np.linalg.norm(normals.astype(float), axis=1)
    off = np.abs(norms - 1.0) > UNIT_TOLERANCE
    if off.any():
        worst = norms[off][np.argmax(np.abs(norms[off] - 1.0))]
        return (
            f"field 'normals': {int(off.sum())} of {m} are not unit vectors (|n| = "
            f"{worst:.3g}); expected |n| within {UNIT_TOLERANCE:g} of 1"
        )
    p = points.astype(float)
    length = float(np.ptp(p[:, 0]))
    lo, hi = KIDNEY_LENGTH_RANGE
    if not lo <= length <= hi:
        return (
            f"field 'points': long-axis (x_K) extent {length:.4g}; expected a kidney in "
            f"metres, {lo:g}-{hi:g} m"
        )
    offset = float(np.linalg.norm(p.mean(axis=0)))
    if offset > MAX_CENTROID_OFFSET_FRACTION * length:
        return (
            f"field 'points': the points' centroid is {offset * 1e3:.1f} mm from K's "
            f"origin; expected the template centred on it (within "
            f"{MAX_CENTROID_OFFSET_FRACTION * length * 1e3:.1f} mm)"
        )
    if modes.size == 0 and variances.size == 0:
        return ""
    if modes.ndim != 3 or modes.shape[1:] != points.shape:
        return f"field 'modes': expected a (k, M, 3) array with M = {m}, got shape {modes.shape}"
    k = len(modes)
    if variances.shape != (k,):
        return (
            f"field 'variances': expected one variance per mode, shape ({k},), got "
            f"{variances.shape}"
        )
    bad = ~np.all(np.isfinite(modes.reshape(k, -1)), axis=1)
    if bad.any():
        return f"field 'modes': {int(bad.sum())} of {k} modes contain NaN or inf"
    mode_norms = np.linalg.norm(modes.reshape(k, -1).astype(float), axis=1)
    off = np.abs(mode_norms - 1.0) > UNIT_TOLERANCE
    if off.any():
        i = int(np.flatnonzero(off)[0])
        return (
            f"field 'modes': {int(off.sum())} of {k} are not unit-norm (mode {i}: "
            f"{mode_norms[i]:.3g}); expected norm within {UNIT_TOLERANCE:g} of 1"
        )
    v = variances.astype(float)
    bad = ~(np.isfinite(v) & (v > 0))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        return (
            f"field 'variances': {int(bad.sum())} of {k} are not positive finite numbers "
            f"(variance {i}: {v[i]:g}); expected m^2 > 0"
        )
    rms = np.sqrt(v / m)
    if np.any(rms > length):
        i = int(np.argmax(rms))
        return (
            f"field 'variances': one standard deviation of mode {i} moves the points by "
            f"{rms[i]:.3g} m RMS, more than the kidney's length ({length:.3g} m); expected "
            f"m^2"
        )
    return ""


def _timeless(meta: dict) -> str:
    """``meta`` without its timings (keys ending in ``_seconds``), as canonical JSON."""
    return json.dumps({k: v for k, v in meta.items() if not k.endswith("_seconds")}, sort_keys=True)


def _build_timings(npz_path: Path, meta: dict) -> dict:
    """The build's timings (the metadata keys ending in ``_seconds``) from the .json beside
    a template, where :func:`~drake_rus.template.builder.save_template` keeps them; {} when
    there is none, it does not read, or it describes another template: its other keys must
    be the file's ``meta`` exactly (a .json left by an earlier build, or beside an .npz
    copied over another, is not this file's)."""
    try:
        doc = json.loads(Path(npz_path).with_suffix(".json").read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(doc, dict) or _timeless(doc) != _timeless(meta):
        return {}
    return {k: v for k, v in doc.items() if k.endswith("_seconds")}


def load_template(path=None) -> Template:
    """Loads a template file; ``path`` defaults to ``models/kidney_template.npz``."""
    path = Path(path) if path is not None else DEFAULT_TEMPLATE_PATH
    if not path.is_file():
        raise FileNotFoundError(
            f"kidney template not found: {path} (build it: drake-rus template build)"
        )
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in _REQUIRED if k not in z.files]
            if missing:
                raise ValueError(f"kidney template {path}: missing arrays {missing}")
            data = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as e:
        if isinstance(e, ValueError) and str(path) in str(e):
            raise
        raise ValueError(f"kidney template {path}: not a readable .npz file ({e})") from None
    try:
        meta = json.loads(str(data["metadata"]))
    except json.JSONDecodeError as e:
        raise ValueError(f"kidney template {path}: 'metadata' is not valid JSON ({e})") from None
    if not isinstance(meta, dict):
        raise ValueError(
            f"kidney template {path}: 'metadata': expected a JSON object, got {type(meta).__name__}"
        )
    meta.update(_build_timings(path, meta))
    problem = check_template_arrays(
        data["points"], data["normals"], data["modes"], data["variances"]
    )
    if problem:
        raise ValueError(f"kidney template {path}: {problem}")
    pts, nrm = data["points"].astype(float), data["normals"].astype(float)
    conv = {}
    if "convergence_n" in data:
        conv = {
            "n": data["convergence_n"].tolist(),
            "change": data["convergence_change"].tolist(),
            "to_final": data["convergence_to_final"].tolist(),
        }
    return Template(
        points=pts,
        normals=nrm,
        modes=data["modes"].astype(float),
        variances=data["variances"].astype(float),
        meta=meta,
        convergence=conv,
    )
