"""Patients that carry a real CT kidney: ``ct:PATH[#OPTIONS]`` patient specs.

A real kidney (with its tumour) from a KiTS-style label map (:mod:`.ct_kidney`: the patient
frame from anatomy) is put into a generated body (:func:`~.generator.generate_patient_with_kidney`):
at the body's kidney position and depth, with the kidney's own tilt from its CT, off the
spine, the organs it overlaps carved. Everything downstream (label volume, emulator
tissues, contact body, start planner, true pose) works as for a generated kidney.

Spec: ``ct:PATH[#OPTION,OPTION...]``; PATH is a label map or a folder holding one (a KiTS
case folder: ``case_00003`` holds ``segmentation.nii.gz``). Options:

- ``right`` / ``left``: which CT kidney (default: the scenario's target side,
  ``patient.side``); a kidney of the other side is mirrored through the sagittal plane;
- ``body=N``: the generator seed of the body (default: derived from the label map's
  content, ``3000000 + int(SHA-256[:12], 16) mod 1000000``: the digest's first 12 hex
  digits), disjoint from train/test seeds; if the kidney does not fit between that body's
  spine and flank, the next of ``CT_BODY_TRIES`` seeds, then those bodies widened within
  adult abdominal widths, ``body_attempts``; a given ``body=N`` is used as drawn);
- ``kidney=with_tumour|parenchyma``: what "the kidney" is when a tumour bulges from it
  (default ``with_tumour``): the true pose, kidney mask and segmentation target include
  the tumour, or only the parenchyma (the tumour is then a separate tissue beside it). Both
  give the same body, placement and images; only membership differs (docs/real_kidneys.md
  measures the difference);
- ``pose=ct|generator``: the kidney's orientation from its CT (default) or the generator's
  sampled angles (the kidney's canonical frame turned onto them).

Example: ``ct:../shared/anatomy/kits19/case_00003#left,body=7``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydrake.math import RigidTransform
from scipy import ndimage

from drake_rus.anatomy.cache import file_digest
from drake_rus.anatomy.canonical_frame import extents_in_frame, mesh_canonical_frame
from drake_rus.anatomy.ct_kidney import (
    CTKidneys,
    KidneyFields,
    concavities,
    import_ct_kidneys,
    kidney_fields_A,
    read_label_grid,
    select_kidney,
)
from drake_rus.anatomy.frames import check_side_posture
from drake_rus.anatomy.generator import (
    KidneyDoesNotFit,
    generate_patient_with_kidney,
    sample_patient_params,
)
from drake_rus.anatomy.importers import LABEL_MAP_SUFFIXES
from drake_rus.anatomy.kidney_shape import KidneyShapeParams
from drake_rus.anatomy.labels import Label
from drake_rus.anatomy.patient import Patient
from drake_rus.anatomy.rasterize import mask_to_mesh

__all__ = [
    "CTSpec",
    "parse_ct_spec",
    "ct_label_map_path",
    "ct_body_seed",
    "VoxelKidneyShape",
    "build_ct_patient",
    "KIDNEY_DEFINITIONS",
    "DEFAULT_KIDNEY_DEFINITION",
    "CT_PREFIX",
    "CT_BODY_OFFSET",
    "CtKidneyDoesNotFit",
    "kidney_definition_difference",
]

log = logging.getLogger(__name__)


class CtKidneyDoesNotFit(ValueError):
    """A CT kidney (a large tumour) fits none of the bodies tried: the patient cannot be
    built (a benchmark skips the case with this reason; no scan is possible)."""


CT_PREFIX = "ct:"
KIDNEY_DEFINITIONS = ("with_tumour", "parenchyma")
DEFAULT_KIDNEY_DEFINITION = "with_tumour"
POSES = ("ct", "generator")
# Default body seeds of CT patients: this offset plus the label map's digest mod 10^6; when
# the kidney (a large tumour) does not fit that body, the next seeds are tried.
CT_BODY_OFFSET = 3_000_000
CT_BODY_TRIES = 10
# When the kidney fits none of those bodies as drawn (a large tumour: in the real patient it
# displaces the liver, bowel and flank muscles, which a generated body does not move), the
# same bodies are tried again with the torso widened at the kidney's level in steps of
# CT_BODY_WIDEN_STEP, as long as the half-width stays within adult abdominal transverse
# diameters (about 260-380 mm at L1-L2, anatomy/body.py): at most CT_BODY_MAX_HALF_WIDTH.
# The smallest widening that fits wins (then the first seed). KiTS19 case 28 (176 x 123 x
# 78 mm with a 286 mL tumour) and case 56 (189 x 123 x 114 mm, 737 mL) fit none as drawn.
CT_BODY_WIDEN_STEP = 0.05
CT_BODY_MAX_HALF_WIDTH = 0.190
# Glodny 2009 (facts file): cortex 6.6 mm, parenchyma 15.4 mm (the generator's defaults).
CORTEX_M = 0.0066
PARENCHYMA_M = 0.0154
# Perirenal fat around the kidney (Gerota's fascia; the generator's 7 mm).
PERIRENAL_M = 0.007
_SMOOTH_VOX = 1.0  # Gaussian smoothing (voxels) before the surface, like mask_to_mesh
_PAD = 2
_FORM = (
    "expected ct:PATH[#right|#left][,body=N][,kidney=with_tumour|parenchyma][,pose=ct|generator]"
)


@dataclass(frozen=True)
class CTSpec:
    """A parsed ``ct:`` spec; None fields take their defaults at build time."""

    path: Path
    ct_side: str | None = None
    body_seed: int | None = None
    kidney_definition: str = DEFAULT_KIDNEY_DEFINITION
    pose: str = "ct"


def parse_ct_spec(spec: str) -> CTSpec:
    """Parses ``ct:PATH[#OPTIONS]`` (module docstring); errors name the spec."""
    if not spec.startswith(CT_PREFIX):
        raise ValueError(f"patient spec {spec!r}: {_FORM}")
    body = spec[len(CT_PREFIX) :]
    path_text, sep, opts = body.rpartition("#") if "#" in body else (body, "", "")
    if not path_text.strip():
        raise ValueError(f"patient spec {spec!r}: no path; {_FORM}")
    fields: dict = {}
    for raw in (o.strip() for o in opts.split(",")) if sep else ():
        if raw in ("right", "left"):
            fields["ct_side"] = raw
            continue
        key, eq, value = raw.partition("=")
        if not eq:
            raise ValueError(f"patient spec {spec!r}: unknown option {raw!r}; {_FORM}")
        if key == "body":
            if not value.isdigit():
                raise ValueError(
                    f"patient spec {spec!r}: body=N needs a non-negative integer "
                    f"seed, got {value!r}"
                )
            fields["body_seed"] = int(value)
        elif key == "kidney":
            if value not in KIDNEY_DEFINITIONS:
                raise ValueError(
                    f"patient spec {spec!r}: kidney= expects one of "
                    f"{', '.join(KIDNEY_DEFINITIONS)}, got {value!r}"
                )
            fields["kidney_definition"] = value
        elif key == "pose":
            if value not in POSES:
                raise ValueError(
                    f"patient spec {spec!r}: pose= expects one of {', '.join(POSES)}, got {value!r}"
                )
            fields["pose"] = value
        else:
            raise ValueError(f"patient spec {spec!r}: unknown option {key!r}; {_FORM}")
    return CTSpec(path=Path(path_text).expanduser(), **fields)


def ct_label_map_path(path: Path, spec: str = "") -> Path:
    """The label map a ``ct:`` path names: the file itself, or the one label map in a folder
    (``segmentation.*`` when there are several)."""
    where = f"patient spec {spec!r}" if spec else f"CT label map {path}"
    if path.is_file():
        if not path.name.lower().endswith(LABEL_MAP_SUFFIXES):
            raise ValueError(
                f"{where}: {path.name} is not a label map ({', '.join(LABEL_MAP_SUFFIXES)})"
            )
        return path
    if path.is_dir():
        maps = [
            p
            for p in sorted(path.iterdir())
            if p.is_file() and p.name.lower().endswith(LABEL_MAP_SUFFIXES)
        ]
        seg = [p for p in maps if p.name.lower().startswith("segmentation")]
        if len(maps) == 1:
            return maps[0]
        if len(seg) == 1:
            return seg[0]
        raise ValueError(
            f"{where}: folder {path} holds {len(maps)} label maps; expected one "
            "(or one named segmentation.*)"
        )
    raise FileNotFoundError(f"{where}: no such file or folder: {path}")


def ct_body_seed(digest: str) -> int:
    """The default body seed of a label map with SHA-256 ``digest``."""
    return CT_BODY_OFFSET + int(digest[:12], 16) % 1_000_000


class VoxelKidneyShape:
    """A CT kidney as the generator's kidney shape (see ``generator._Layout``), in its frame
    L = the anatomical frame A of its CT (m): surfaces by marching cubes of the smoothed
    masks, inside tests on the same smoothed fields (trilinear), sub-labels by depth below
    the kidney+tumour surface (cortex 6.6 mm, parenchyma 15.4 mm: Glodny 2009; medullary
    pyramids in the generator's pattern), the tumour labelled TUMOUR or KIDNEY_TUMOUR by the
    kidney definition.

    ``mesh``: "the kidney" by ``definition``; ``placement_mesh``: kidney and tumour (what is
    placed in the body, the same for both definitions)."""

    def __init__(self, fields: KidneyFields, definition: str, side: str):
        if definition not in KIDNEY_DEFINITIONS:
            raise ValueError(
                f"kidney definition: expected one of {KIDNEY_DEFINITIONS}, got {definition!r}"
            )
        self.definition = definition
        self.side = side
        vs = float(fields.voxel)
        self._vs = vs
        self._origin = np.asarray(fields.origin_A, dtype=float)
        union = fields.sdf_union > 0
        tumour = fields.tumour & union
        parenchyma = union & ~tumour
        if not parenchyma.any():
            raise ValueError("the kidney has no parenchyma outside its tumour")
        body = union if definition == "with_tumour" else parenchyma
        X = RigidTransform(self._origin)
        self.mesh = mask_to_mesh(body, X, vs, sigma_vox=_SMOOTH_VOX, what="CT kidney")
        self.placement_mesh = (
            self.mesh
            if definition == "with_tumour"
            else mask_to_mesh(union, X, vs, sigma_vox=_SMOOTH_VOX, what="CT kidney and tumour")
        )

        def smooth(m):
            return ndimage.gaussian_filter(np.pad(m.astype(np.float32), _PAD), _SMOOTH_VOX)

        self._phi_body = smooth(body)
        self._phi_union = self._phi_body if definition == "with_tumour" else smooth(union)
        self._tumour = np.pad(tumour, _PAD)
        self._depth = (ndimage.distance_transform_edt(np.pad(union, _PAD)) * vs).astype(np.float32)
        self._sdf = np.pad(fields.sdf_union, _PAD, constant_values=-1.0)
        lateral = [-1.0, 0.0, 0.0] if side == "right" else [1.0, 0.0, 0.0]
        self.reference_axes = ([0.0, 1.0, 0.0], lateral)
        X_LK = mesh_canonical_frame(self.placement_mesh, *self.reference_axes)
        self._R_LK = X_LK.rotation().matrix()
        self._c_K = X_LK.translation()
        self._half = 0.5 * extents_in_frame(self.placement_mesh.vertices, X_LK)
        self.extents = 2.0 * self._half
        self.volumes_ml = {
            "parenchyma": float(parenchyma.sum()) * vs**3 * 1e6,
            "tumour": float(tumour.sum()) * vs**3 * 1e6,
        }
        # The hilum: the largest medial concavity of the parenchyma's hull (2 mm grid).
        step = max(1, int(round(0.002 / vs)))
        found = concavities(
            parenchyma[::step, ::step, ::step],
            union[::step, ::step, ::step],
            [step * vs * 1000.0] * 3,
        )
        points = [self._origin + c * step * vs for c, _ in found]
        medial = [p for p in points if (p - self._c_K) @ np.asarray(lateral) < 0]
        self._hilum = (medial or points or [self._c_K.copy()])[0]

    # --- the generator's kidney-shape interface ------------------------------------------
    def _idx(self, p_L):
        return ((np.asarray(p_L, dtype=float) - self._origin) / self._vs + _PAD).T

    def _sample(self, field, p_L, order=1, cval=0.0):
        return ndimage.map_coordinates(
            field, self._idx(p_L), order=order, mode="constant", cval=cval
        )

    def inside(self, p_L) -> np.ndarray:
        """Points (N, 3) in L inside "the kidney" (the definition's surface)."""
        return self._sample(self._phi_body, p_L) >= 0.5

    def inside_placement(self, p_L) -> np.ndarray:
        """Points inside the kidney or its tumour."""
        return self._sample(self._phi_union, p_L) >= 0.5

    def hilum_point(self) -> np.ndarray:
        """Centre of the largest concavity (the hilum and sinus opening), in L (m)."""
        return self._hilum.copy()

    def label_codes(self, p_L):
        """(labels, perirenal) at points (N, 3) in L: kidney sub-labels and tumour labels
        (0 outside), and where perirenal fat replaces soft tissues (within 7 mm)."""
        p_L = np.asarray(p_L, dtype=float)
        inside = self._sample(self._phi_union, p_L) >= 0.5
        out = np.zeros(len(p_L), dtype=np.uint8)
        if not inside.any():
            return out, self._sample(self._sdf, p_L, cval=-1.0) > -PERIRENAL_M
        q = p_L[inside]
        depth = self._sample(self._depth, q)
        tumour = self._sample(self._tumour.astype(np.uint8), q, order=0) > 0
        v = ((q - self._c_K) @ self._R_LK) / self._half
        d = v / np.maximum(np.linalg.norm(v, axis=1), 1e-12)[:, None]
        pyramids = (np.cos(4.0 * np.pi * d[:, 0]) > -0.35) & (np.abs(d[:, 2]) < 0.85)
        codes = np.full(len(q), int(Label.KIDNEY_CORTEX), np.uint8)
        codes[(depth >= CORTEX_M) & (depth < PARENCHYMA_M) & pyramids] = Label.KIDNEY_MEDULLA
        codes[depth >= PARENCHYMA_M] = Label.KIDNEY_SINUS
        codes[tumour] = Label.KIDNEY_TUMOUR if self.definition == "with_tumour" else Label.TUMOUR
        out[inside] = codes
        peri = self._sample(self._sdf, p_L, cval=-1.0) > -PERIRENAL_M
        return out, peri | inside


def build_ct_patient(
    spec: CTSpec,
    side: str = "right",
    posture: str = "supine",
    *,
    name: str | None = None,
    digest: str | None = None,
    voxel_size: float = 0.001,
    progress: bool = True,
) -> Patient:
    """The patient of a ``ct:`` spec (see the module docstring); ``side`` is the target
    side of the patient (the scenario's ``patient.side``)."""
    check_side_posture(side, posture)
    path = ct_label_map_path(spec.path)
    digest = digest or file_digest(path)
    seed = spec.body_seed if spec.body_seed is not None else ct_body_seed(digest)
    ct_side = spec.ct_side or side
    case = import_ct_kidneys(read_label_grid(path))
    if case.frame.status != "agree":
        log.warning(
            "label map %s: the frame cues disagree (%s); the majority decided",
            path,
            ", ".join(case.frame.conflicts),
        )
    kidney = select_kidney(case, ct_side)
    mirrored = ct_side != side
    fields = kidney_fields_A(kidney, case.frame, voxel=voxel_size, mirror=mirrored)
    shape = VoxelKidneyShape(fields, spec.kidney_definition, side)
    length, width, thickness = (float(x) for x in shape.extents)
    R_BdL = np.eye(3) if spec.pose == "ct" else None
    meta = {
        "ct": {
            "path": str(path),
            "sha256": digest,
            "ct_side": ct_side,
            "mirrored": mirrored,
            "kidney_definition": spec.kidney_definition,
            "pose": spec.pose,
            "parenchyma_ml": round(shape.volumes_ml["parenchyma"], 1),
            "tumour_ml": round(shape.volumes_ml["tumour"], 1),
            "frame": case.frame.summary(),
            "fragments": case.extra,
            "right_minus_left_mm": case.right_minus_left_mm(),
        }
    }
    seeds = [seed] if spec.body_seed is not None else [seed + i for i in range(CT_BODY_TRIES)]
    why = ""
    given = spec.body_seed is not None  # a given body is used as drawn
    attempts = [(1.0, seed)] if given else body_attempts(seeds, side, posture)
    for widen, body in attempts:
        prm = sample_patient_params(body, side, posture)
        drawn_half_width = prm.torso.half_width
        prm.torso.half_width = drawn_half_width * widen
        prm.kidney = KidneyShapeParams(
            length=length,
            width=width,
            thickness=thickness,
            cortex_thickness=CORTEX_M,
            parenchyma_thickness=PARENCHYMA_M,
        )
        meta["ct"]["body_seed"] = body
        meta["ct"]["body_tries"] = body - seed + 1
        meta["ct"]["body_widened"] = round(widen, 3)
        meta["ct"]["body_half_width_mm"] = [
            round(drawn_half_width * 1e3, 1),
            round(prm.torso.half_width * 1e3, 1),
        ]
        try:
            return generate_patient_with_kidney(
                prm,
                shape,
                R_BdL=R_BdL,
                name=name or f"ct:{path}",
                voxel_size=voxel_size,
                progress=progress,
                meta=_jsonable(meta),
            )
        except KidneyDoesNotFit as e:
            why = why or str(e)
    tried = f"body {seeds[0]}" if len(seeds) == 1 else f"bodies {seeds[0]}-{seeds[-1]}"
    raise CtKidneyDoesNotFit(
        f"label map {path}: the {ct_side} kidney ({width * 1e3:.0f} mm wide with "
        f"its tumour) fits none of {tried}"
        + ("" if given else f", even widened up to {CT_BODY_MAX_HALF_WIDTH * 2e3:.0f} mm across")
        + f": {why}"
    )


def body_attempts(seeds, side: str, posture: str):
    """(widening factor, seed) in the order tried: every seed as drawn, then every seed
    whose torso, widened by 1 + k x ``CT_BODY_WIDEN_STEP`` (k = 1, 2, ...), keeps a
    half-width of at most ``CT_BODY_MAX_HALF_WIDTH`` (the smallest widening first)."""
    half_widths = {b: sample_patient_params(b, side, posture).torso.half_width for b in seeds}
    for b in seeds:
        yield 1.0, b
    k = 1
    while True:
        widen = 1.0 + k * CT_BODY_WIDEN_STEP
        fits = [b for b in seeds if half_widths[b] * widen <= CT_BODY_MAX_HALF_WIDTH + 1e-9]
        if not fits:
            return
        for b in fits:
            yield widen, b
        k += 1


def kidney_definition_difference(case: CTKidneys, side: str, voxel: float = 0.001) -> dict:
    """How far apart the true poses of the two kidney definitions are for the ``side``
    kidney of a case: the canonical (PCA) frames of parenchyma+tumour and of parenchyma
    alone (placement does not change it: both are placed as kidney and tumour). Returns
    mm, deg (whole rotation and long axis x_k), and the volumes (mL)."""
    k = select_kidney(case, side)
    fields = kidney_fields_A(k, case.frame, voxel=voxel)
    frames, volumes = {}, {}
    for d in KIDNEY_DEFINITIONS:
        shape = VoxelKidneyShape(fields, d, side)
        frames[d] = mesh_canonical_frame(shape.mesh, *shape.reference_axes)
        volumes = shape.volumes_ml
    a, b = (frames[d] for d in KIDNEY_DEFINITIONS)
    Ra, Rb = a.rotation().matrix(), b.rotation().matrix()
    cos = np.clip((np.trace(Ra.T @ Rb) - 1.0) / 2.0, -1.0, 1.0)
    return {
        "definition_dt_mm": round(
            float(np.linalg.norm(a.translation() - b.translation())) * 1e3, 2
        ),
        "definition_rot_deg": round(float(np.degrees(np.arccos(cos))), 2),
        "definition_rot_x_deg": round(
            float(np.degrees(np.arccos(np.clip(Ra[:, 0] @ Rb[:, 0], -1.0, 1.0)))), 2
        ),
        "definition_side": side,
        "definition_tumour_ml": round(volumes["tumour"], 1),
        "definition_parenchyma_ml": round(volumes["parenchyma"], 1),
    }


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    return x
