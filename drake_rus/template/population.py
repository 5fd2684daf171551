"""Kidney templates built from another population: generated kidneys with other size statistics.

The repository's template (``models/kidney_template.npz``) and the virtual patients come from
the same generator, so the template matches the patients' population exactly. A template
from a *different population* tests how localization degrades when it does not (the seed
paper's template came from a public CT dataset, its patients from another one). A
population is the generator's kidney-shape sampler
(:func:`drake_rus.anatomy.kidney_shape.sample_kidney_shape_params`, Glodny 2009 length
108.5 +- 12.2 mm for right kidneys, Emamian 1993 width, textbook thickness; see
``docs/facts/anatomy_and_ultrasound.md``) with its statistics changed:

- ``length_shift_sd``: every kidney's length moved by this many Glodny SDs (12.2 mm right,
  12.6 mm left), with the generator's allometry (width +0.08 mm and thickness +0.03 mm per mm
  of length, as in the sampler), so ``short``/``long`` are populations whose mean length is
  one SD below/above the published one;
- ``width_shift_sd`` / ``thickness_shift_sd``: width and thickness moved by this many of the
  sampler's SDs (4.5 mm, 3.5 mm) at unchanged length (``slim``).

Every other shape parameter (hilum, bend, pole asymmetries, lobulation) is drawn as the
generator draws it. The subjects are *other people* than the training cohort: seeds
``POPULATION_OFFSET + K`` (disjoint from ``train:K``, ``test:K`` and the low ``seed:N``
range). Each kidney goes through the training pipeline: a 1 mm mask from the shape's
analytic inside test, marching cubes, canonical frame (eq. 13-14), then
:func:`drake_rus.template.builder.build_template` (FPS, FPFH+RANSAC+ICP, kNN
correspondence, mean shape eq. 15, PCA modes).

:func:`population_template` builds a population's template once and keeps it in a
content-addressed cache (the SHA-256 of the population, the build settings, the source of
the code that builds it and the library versions): ``$DRAKE_RUS_CACHE_DIR/templates`` if
that is set (the patient cache's folder), else ``$XDG_CACHE_HOME/drake_rus/templates``, else
``~/.cache/drake_rus/templates``. No network: everything is generated.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import re
import time
from functools import lru_cache
from pathlib import Path

import numpy as np
from pydrake.math import RigidTransform

from drake_rus.anatomy.cache import CACHE_DIR_ENV, library_versions, user_cache_home
from drake_rus.anatomy.kidney_shape import KidneyShape, sample_kidney_shape_params
from drake_rus.template.builder import build_template, save_template_to_cache, subject_from_mask

__all__ = [
    "Population",
    "POPULATIONS",
    "POPULATION_OFFSET",
    "GLODNY_LENGTH_SD",
    "parse_population",
    "population_shape_params",
    "population_subjects",
    "template_cache_dir",
    "population_template_path",
    "population_template",
]

# Seeds of population subjects: beyond train (1e6+K) and test (2e6+K).
POPULATION_OFFSET = 3_000_000
# Glodny 2009 (CT): kidney length SD, right / left (mm); the sampler's width and thickness SDs.
GLODNY_LENGTH_SD = {"right": 0.0122, "left": 0.0126}
WIDTH_SD = 0.0045
THICKNESS_SD = 0.0035
# The sampler's allometry: width and thickness change per unit of length.
WIDTH_PER_LENGTH = 0.08
THICKNESS_PER_LENGTH = 0.03
DEFAULT_SUBJECTS = 20  # the seed paper's N (II-D)
DEFAULT_POINTS = 2500  # as the repository's template
DEFAULT_VOXEL = 0.001  # 1 mm masks, as the repository's template
_HERE = Path(__file__).resolve().parent
_CODE_FILES = (
    _HERE / "population.py",
    _HERE / "builder.py",
    _HERE.parent / "anatomy" / "canonical_frame.py",
    _HERE.parent / "anatomy" / "kidney_shape.py",
    _HERE.parent / "anatomy" / "rasterize.py",
)
_LIBRARIES = ("numpy", "scipy", "open3d", "scikit-image", "trimesh")


@dataclasses.dataclass(frozen=True)
class Population:
    """A kidney population: the generator's sampler with shifted statistics (in SDs)."""

    name: str
    length_shift_sd: float = 0.0
    width_shift_sd: float = 0.0
    thickness_shift_sd: float = 0.0
    description: str = ""

    def length_shift(self, side: str = "right") -> float:
        """The length shift (m)."""
        return self.length_shift_sd * GLODNY_LENGTH_SD[side]


POPULATIONS = {
    "base": Population(
        "base",
        description="other people from the same statistics (Glodny "
        "2009 length 108.5 +- 12.2 mm): sampling only",
    ),
    "short": Population(
        "short",
        length_shift_sd=-1.0,
        description="kidney length 1 SD (12.2 mm) shorter than Glodny 2009, "
        "mean 96.3 mm; width/thickness by the allometry",
    ),
    "long": Population(
        "long",
        length_shift_sd=+1.0,
        description="kidney length 1 SD (12.2 mm) longer than Glodny 2009, "
        "mean 120.7 mm; width/thickness by the allometry",
    ),
    "slim": Population(
        "slim",
        width_shift_sd=-1.0,
        thickness_shift_sd=-1.0,
        description="width 4.5 mm and thickness 3.5 mm (1 SD each) smaller at the published length",
    ),
}
_CUSTOM = re.compile(r"length([+-]\d+(\.\d+)?)sd")


def parse_population(name: str) -> Population:
    """A named population (:data:`POPULATIONS`) or ``length+Xsd`` / ``length-Xsd`` (the
    length moved by X Glodny SDs, 0 < |X| <= 3). Raises ValueError naming the population."""
    name = str(name).strip()
    if name in POPULATIONS:
        return POPULATIONS[name]
    m = _CUSTOM.fullmatch(name)
    if m:
        x = float(m.group(1))
        if 0 < abs(x) <= 3:
            return Population(
                name, length_shift_sd=x, description=f"kidney length {x:+g} SD of Glodny 2009"
            )
    raise ValueError(
        f"population: expected one of {', '.join(POPULATIONS)} or length+Xsd / "
        f"length-Xsd (X up to 3), got {name!r}"
    )


def population_shape_params(population: Population, k: int, side: str = "right"):
    """Kidney-shape parameters of subject ``k`` of ``population`` (deterministic): the
    generator's draw for seed ``POPULATION_OFFSET + k`` with the population's shifts."""
    rng = np.random.default_rng(np.random.SeedSequence([20240, POPULATION_OFFSET + int(k), 7]))
    p = sample_kidney_shape_params(rng, side)
    dl = population.length_shift(side)
    p.length = float(p.length + dl)
    p.width = float(p.width + WIDTH_PER_LENGTH * dl + population.width_shift_sd * WIDTH_SD)
    p.thickness = float(
        p.thickness + THICKNESS_PER_LENGTH * dl + population.thickness_shift_sd * THICKNESS_SD
    )
    if not (p.length > 0.05 and p.width > p.thickness > 0.015):
        raise ValueError(
            f"population {population.name}: subject {k} has an impossible kidney "
            f"({p.length * 1e3:.1f} x {p.width * 1e3:.1f} x "
            f"{p.thickness * 1e3:.1f} mm)"
        )
    return p


def _shape_mask(shape: KidneyShape, voxel: float):
    """The kidney's mask (``voxel`` voxels) in its local frame L and the voxel frame X_LV."""
    v = np.asarray(shape.mesh.vertices)
    lo = v.min(axis=0) - 3 * voxel
    n = np.ceil((v.max(axis=0) + 3 * voxel - lo) / voxel).astype(int) + 1
    idx = np.stack(np.meshgrid(*[np.arange(m) for m in n], indexing="ij"), -1).reshape(-1, 3)
    mask = shape.inside(lo + voxel * idx).reshape(tuple(n))
    return mask, RigidTransform(lo)


def population_subjects(
    population: Population,
    n: int = DEFAULT_SUBJECTS,
    side: str = "right",
    voxel: float = DEFAULT_VOXEL,
) -> list:
    """The population's template subjects: per kidney a ``voxel`` mask (like a CT
    segmentation), marching cubes, canonical frame (eq. 13-14; x_ref = the shape's long axis
    towards the superior pole, y_ref = medial -> lateral, as in the generator)."""
    subjects = []
    for k in range(int(n)):
        shape = KidneyShape(population_shape_params(population, k, side))
        mask, X_LV = _shape_mask(shape, voxel)
        s = subject_from_mask(
            mask,
            X_LV,
            voxel,
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            name=f"population:{population.name}:{k}",
        )
        subjects.append(s)
    return subjects


def template_cache_dir() -> Path:
    """``$DRAKE_RUS_CACHE_DIR/templates``, else ``$XDG_CACHE_HOME/drake_rus/templates``, else
    ``~/.cache/drake_rus/templates`` (not created here)."""
    env = os.environ.get(CACHE_DIR_ENV)
    if env:
        return Path(env).expanduser() / "templates"
    return user_cache_home() / "templates"


@lru_cache(maxsize=1)
def _code_and_libraries() -> dict:
    h = hashlib.sha256()
    for p in _CODE_FILES:
        h.update(p.name.encode() + b"\0" + p.read_bytes() + b"\0")
    return {"code": h.hexdigest(), "libraries": library_versions(_LIBRARIES)}


def _inputs(population: Population, n: int, side: str, n_points: int, voxel: float) -> dict:
    return {
        "format": 1,
        "population": dataclasses.asdict(population) | {"description": ""},
        "n": int(n),
        "side": side,
        "n_points": int(n_points),
        "voxel": float(voxel),
        "seed_offset": POPULATION_OFFSET,
        **_code_and_libraries(),
    }


def population_template_path(
    population,
    n: int = DEFAULT_SUBJECTS,
    side: str = "right",
    n_points: int = DEFAULT_POINTS,
    voxel: float = DEFAULT_VOXEL,
) -> Path:
    """Where the cached template of ``population`` (a name or :class:`Population`) lives."""
    pop = parse_population(population) if isinstance(population, str) else population
    doc = json.dumps(_inputs(pop, n, side, n_points, voxel), sort_keys=True)
    digest = hashlib.sha256(doc.encode()).hexdigest()
    return template_cache_dir() / f"population-{pop.name}-{digest[:24]}.npz"


def population_template(
    population,
    n: int = DEFAULT_SUBJECTS,
    side: str = "right",
    n_points: int = DEFAULT_POINTS,
    voxel: float = DEFAULT_VOXEL,
    out=None,
    progress: bool = False,
) -> Path:
    """The template file of ``population`` (a name or :class:`Population`): from the cache
    when it was built before with the same inputs and code, else built (about 0.5 s per
    subject plus the registration; docs/studies.md) and stored. ``out``: write it there instead
    (no cache). Returns the .npz path (a .json with its metadata beside it)."""
    pop = parse_population(population) if isinstance(population, str) else population
    if int(n) < 1:
        raise ValueError(f"population template: expected at least 1 subject, got {n}")
    path = Path(out) if out is not None else population_template_path(pop, n, side, n_points, voxel)
    if out is None and path.is_file():
        return path
    t0 = time.time()
    subjects = population_subjects(pop, n, side, voxel)
    t1 = time.time()
    result = build_template(subjects, n_points=n_points, progress=progress)
    t2 = time.time()
    lengths = [population_shape_params(pop, k, side).length for k in range(int(n))]
    extra = {
        "split": f"population:{pop.name}",
        "side": side,
        "voxel_mm": voxel * 1e3,
        "population": dataclasses.asdict(pop),
        "sampled_length_mm": {
            "mean": round(float(np.mean(lengths)) * 1e3, 2),
            "sd": round(float(np.std(lengths, ddof=1)) * 1e3, 2) if len(lengths) > 1 else 0.0,
        },
        "seeds": [POPULATION_OFFSET, POPULATION_OFFSET + int(n) - 1],
        "subject_seconds": round(t1 - t0, 2),
        "total_seconds": round(t2 - t0, 2),
        "source": "drake-rus kidney-shape sampler with shifted statistics "
        "(drake_rus.template.population)",
    }
    return save_template_to_cache(result, path, extra, asked_for=out is not None)
