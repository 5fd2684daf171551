"""Cohorts of virtual patients and ``load_patient`` specs.

Seeds: ``seed:N`` is generator seed N; ``train:K`` is seed 1_000_000 + K (template subjects,
20 by default), ``test:K`` is seed 2_000_000 + K (evaluation patients, 15 by default). The
ranges never overlap, so training and test patients are disjoint by construction.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from tqdm import tqdm

from drake_rus.anatomy.cache import cached_patient, file_digest
from drake_rus.anatomy.canonical_frame import extents_in_frame, mesh_canonical_frame
from drake_rus.anatomy.checks import check_anatomy
from drake_rus.anatomy.ct_patient import (
    CT_PREFIX,
    build_ct_patient,
    ct_body_seed,
    ct_label_map_path,
    parse_ct_spec,
)
from drake_rus.anatomy.frames import check_side_posture
from drake_rus.anatomy.generator import (
    _Layout,
    generate_patient,
    patient_builders,
    sample_patient_params,
)
from drake_rus.anatomy.importers import (
    LABEL_MAP_SUFFIXES,
    find_mesh_files,
    patient_from_label_map,
    patient_from_mask_folder,
    patient_from_meshes,
    totalsegmentator_mask_files,
)
from drake_rus.anatomy.patient import Patient

__all__ = [
    "TRAIN_OFFSET",
    "TEST_OFFSET",
    "DEFAULT_COUNTS",
    "split_seed",
    "cohort_seeds",
    "load_patient",
    "check_regular_path",
    "kidney_statistics",
    "summarize",
    "cohort_stats",
]

TRAIN_OFFSET = 1_000_000
TEST_OFFSET = 2_000_000
SPLIT_OFFSETS = {"train": TRAIN_OFFSET, "test": TEST_OFFSET, "seed": 0}
DEFAULT_COUNTS = {"train": 20, "test": 15}


def split_seed(split: str, k: int) -> int:
    if split not in SPLIT_OFFSETS:
        raise ValueError(f"split: expected 'train', 'test' or 'seed', got {split!r}")
    k = int(k)
    if k < 0 or (split != "seed" and k >= 1_000_000):
        raise ValueError(f"{split}:{k}: index out of range (0 <= K < 1000000)")
    return SPLIT_OFFSETS[split] + k


def cohort_seeds(split: str, count: int | None = None) -> list[int]:
    count = DEFAULT_COUNTS.get(split, 15) if count is None else int(count)
    if count < 1:
        raise ValueError(f"count: expected at least 1, got {count}")
    return [split_seed(split, k) for k in range(count)]


def check_regular_path(path: Path, what: str) -> None:
    """Refuses a path that is neither a regular file nor a directory (a named pipe, a
    device, a socket) before anything opens it: reading one blocks or never ends."""
    if path.is_dir() or path.is_file():
        return
    kind = (
        "a named pipe"
        if path.is_fifo()
        else "a device"
        if path.is_char_device() or path.is_block_device()
        else "a socket"
        if path.is_socket()
        else "not a regular file"
    )
    raise ValueError(f"{what}: {path} is {kind}; expected a patient directory or a label-map file")


def load_patient(
    spec: str,
    side: str = "right",
    posture: str = "supine",
    *,
    voxel_size: float = 0.001,
    mapping="totalsegmentator",
    progress: bool = True,
    cache: bool = True,
    check: bool = True,
) -> Patient:
    """A patient from a spec: ``seed:N``, ``train:K``, ``test:K`` (virtual, deterministic),
    ``ct:PATH[#OPTIONS]`` (a real CT kidney in a generated body,
    :mod:`drake_rus.anatomy.ct_patient`), a directory of TotalSegmentator per-structure masks
    (kidney_right.nii.gz, body.nii.gz,
    ...), a directory of meshes (kidney_right/left, skin, liver by file name, like the HuBMAP
    folder) or a NIfTI/NRRD label map (multi-label, TotalSegmentator indices by default).

    ``cache``: reuse (and store) the patient in the on-disk patient cache
    (:mod:`drake_rus.anatomy.cache`), its label volume included once built; False builds it
    afresh and writes nothing.

    ``check``: the patient's anatomy must be able to exist
    (:func:`drake_rus.anatomy.checks.check_anatomy`: the kidney inside the body, wholly in
    the label volume and in no other organ, body and kidney of human size); an
    :class:`~drake_rus.anatomy.checks.AnatomyError` names the spec and the failed check.
    It builds the label volume (kept in the cache)."""
    check_side_posture(side, posture)
    inputs, build, builders = _resolve_spec(str(spec), side, posture, voxel_size, mapping, progress)
    patient = build() if not cache else cached_patient(inputs, build, builders=builders)
    if check:
        check_anatomy(patient, str(spec))
    return patient


def _mapping_key(mapping):
    if isinstance(mapping, str):
        return mapping.lower()
    return sorted([int(k), str(v).lower()] for k, v in dict(mapping).items())


def _resolve_spec(spec: str, side: str, posture: str, voxel_size: float, mapping, progress: bool):
    """(cache inputs, build(), builders() or None) of a patient spec: the inputs name the
    generator seed or the bytes of every file the import reads."""
    common = {"spec": spec, "side": side, "posture": posture, "voxel_size": float(voxel_size)}
    head, sep, tail = spec.partition(":")
    if spec.startswith(CT_PREFIX):
        ct = parse_ct_spec(spec)
        path = ct_label_map_path(ct.path, spec)
        digest = file_digest(path)
        options = {
            "ct_side": ct.ct_side or side,
            "body_seed": ct.body_seed if ct.body_seed is not None else ct_body_seed(digest),
            "kidney_definition": ct.kidney_definition,
            "pose": ct.pose,
        }
        return (
            {"kind": "ct_kidney", **common, "files": {str(path): digest}, "ct": options},
            lambda: build_ct_patient(
                ct,
                side,
                posture,
                name=spec,
                digest=digest,
                voxel_size=voxel_size,
                progress=progress,
            ),
            None,
        )
    if sep and head in SPLIT_OFFSETS:
        try:
            k = int(tail)
        except ValueError:
            raise ValueError(
                f"patient spec {spec!r}: expected an integer after '{head}:'"
            ) from None
        seed = split_seed(head, k)
        return (
            {"kind": "generator", "seed": seed, **common},
            lambda: generate_patient(
                seed, side, posture, name=spec, voxel_size=voxel_size, progress=progress
            ),
            lambda: patient_builders(seed, side, posture, voxel_size=voxel_size, progress=progress),
        )
    path = Path(spec)
    if not path.exists():
        raise FileNotFoundError(
            f"patient spec {spec!r}: not seed:N/train:K/test:K and no such file or directory"
        )
    check_regular_path(path, f"patient spec {spec!r}")

    def imported(route, files, build, with_mapping=False):
        inputs = {"kind": route, **common, "files": {str(p): file_digest(p) for p in files}}
        if with_mapping:
            inputs["mapping"] = _mapping_key(mapping)
        return inputs, build, None

    if path.is_dir():
        masks = totalsegmentator_mask_files(path)
        if f"kidney_{side}" in masks:
            return imported(
                "mask_folder",
                masks.values(),
                lambda: patient_from_mask_folder(
                    path, side=side, posture=posture, voxel_size=voxel_size
                ),
            )
        found = find_mesh_files(path, side)
        if found["kidney"] is None or found["skin"] is None:
            maps = [
                p
                for p in sorted(path.iterdir())
                if p.is_file() and p.name.lower().endswith(LABEL_MAP_SUFFIXES)
            ]
            if len(maps) == 1:
                return imported(
                    "label_map",
                    maps,
                    lambda: patient_from_label_map(
                        maps[0], mapping, side=side, posture=posture, voxel_size=voxel_size
                    ),
                    with_mapping=True,
                )
            missing = [k for k in ("kidney", "skin") if found[k] is None]
            raise ValueError(
                f"patient directory {path}: no {' and no '.join(missing)} mesh "
                f"found (expected file names containing 'kidney' and '{side}', "
                "and 'skin'), and not exactly one label map"
            )
        return imported(
            "meshes",
            [p for p in found.values() if p is not None],
            lambda: patient_from_meshes(
                found["kidney"],
                found["skin"],
                liver=found["liver"],
                other_kidney=found["other_kidney"],
                side=side,
                posture=posture,
                name=path.name,
                voxel_size=voxel_size,
            ),
        )
    if path.name.lower().endswith(LABEL_MAP_SUFFIXES):
        return imported(
            "label_map",
            [path],
            lambda: patient_from_label_map(
                path, mapping, side=side, posture=posture, voxel_size=voxel_size
            ),
            with_mapping=True,
        )
    raise ValueError(
        f"patient spec {spec!r}: unknown file type (label maps: "
        f"{', '.join(LABEL_MAP_SUFFIXES)}; meshes: give their directory)"
    )


def kidney_statistics(seed: int, side: str = "right", posture: str = "supine") -> dict:
    """Fast per-seed kidney statistics (no skin mesh, no label volume): canonical length,
    width, thickness, volume, measured hilum/coronal/sagittal angles, vertical depth (SI).
    Identical to ``Patient.metrics()`` for the same seed (tested)."""
    prm = sample_patient_params(seed, side, posture)
    lay = _Layout(prm)
    mesh = trimesh.Trimesh(lay.kidney_vertices_Bd, lay.shape.mesh.faces, process=False)
    lateral = np.array([-1.0, 0, 0]) if side == "right" else np.array([1.0, 0, 0])
    X = mesh_canonical_frame(mesh, [0, 1, 0], lateral)
    ext = extents_in_frame(mesh.vertices, X)
    x_k = X.rotation().matrix()[:, 0]
    depth = float(lay.torso.top_z(lay.p_c[0], lay.p_c[1]) - lay.kidney_top_z)
    out = {
        "seed": int(seed),
        "size_class": prm.torso.size_class,
        "length": float(ext[0]),
        "width": float(ext[1]),
        "thickness": float(ext[2]),
        "volume": float(mesh.volume),
        "hilum_angle": lay.hilum_angle_measured(x_k),
        "coronal_angle": float(np.arctan2(abs(x_k[0]), x_k[1])),
        "sagittal_angle": float(np.arctan2(-x_k[2], x_k[1])),
    }
    if posture == "supine":  # the analytic upper surface is the anterior one
        out["depth_vertical"] = depth
    return out


# Published values to compare with (facts file).
REFERENCE = {
    "length_mm": {"right": "108.5 +- 12.2 (Glodny 2009)", "left": "111.3 +- 12.6 (Glodny 2009)"},
    "width_mm": "58, 10-90th pct 51-64 (Emamian 1993)",
    "thickness_mm": "30-45 (textbook)",
    "volume_ml": {"right": "129 +- 30 (Lee 1996)", "left": "137 +- 30 (Lee 1996)"},
    "hilum_angle_deg": "40-45 (Sakate 2009)",
    "coronal_angle_deg": "15-20",
    "sagittal_angle_deg": "10-25 (sampled range, no published angle)",
    "depth_vertical_mm": "75-165 by body size (modelling choice; CT skin-to-kidney 100 +- 25-30)",
}

_UNITS = {
    "length": ("length_mm", 1e3),
    "width": ("width_mm", 1e3),
    "thickness": ("thickness_mm", 1e3),
    "volume": ("volume_ml", 1e6),
    "hilum_angle": ("hilum_angle_deg", 180 / np.pi),
    "coronal_angle": ("coronal_angle_deg", 180 / np.pi),
    "sagittal_angle": ("sagittal_angle_deg", 180 / np.pi),
    "depth_vertical": ("depth_vertical_mm", 1e3),
    "depth_min": ("depth_min_mm", 1e3),
}


def summarize(rows: list[dict], side: str = "right", posture: str = "supine") -> dict:
    """Mean, SD, min, max of each statistic, in report units (mm, mL, deg)."""
    out = {}
    for key, (name, scale) in _UNITS.items():
        vals = np.array([r[key] for r in rows if key in r], dtype=float) * scale
        if len(vals) == 0:
            continue
        ref = REFERENCE.get(name)
        out[name] = {
            "mean": round(float(vals.mean()), 2),
            "sd": round(float(vals.std(ddof=1)) if len(vals) > 1 else 0.0, 2),
            "min": round(float(vals.min()), 2),
            "max": round(float(vals.max()), 2),
        }
        if name == "depth_vertical_mm" and posture != "supine":
            ref = "less than supine: through the upper (right) flank; no published range"
        if ref is not None:
            out[name]["reference"] = ref[side] if isinstance(ref, dict) else ref
    classes = [r["size_class"] for r in rows if "size_class" in r]
    if classes:
        out["size_classes"] = {c: classes.count(c) for c in sorted(set(classes))}
    return out


def cohort_stats(
    split: str,
    count: int | None = None,
    side: str = "right",
    posture: str = "supine",
    full: bool = True,
    progress: bool = True,
) -> dict:
    """Summary statistics of a cohort. ``full``: build each Patient (meshes, exact depths
    through the meshes, shortest skin distance); else the fast per-seed statistics."""
    seeds = cohort_seeds(split, count)
    rows = []
    for k, seed in enumerate(tqdm(seeds, desc=f"cohort {split}", disable=not progress)):
        if full:
            p = generate_patient(seed, side, posture, name=f"{split}:{k}", progress=False)
            row = dict(p.metrics())
            row["size_class"] = p.meta["size_class"]
        else:
            row = kidney_statistics(seed, side, posture)
        rows.append(row)
    return {
        "split": split,
        "count": len(seeds),
        "side": side,
        "posture": posture,
        "seeds": [seeds[0], seeds[-1]],
        "statistics": summarize(rows, side, posture),
    }
