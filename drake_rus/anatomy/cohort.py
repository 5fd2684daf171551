"""Cohorts of virtual patients and ``load_patient`` specs.

Seeds: ``seed:N`` is generator seed N; ``train:K`` is seed 1_000_000 + K (template subjects,
20 by default), ``test:K`` is seed 2_000_000 + K (evaluation patients, 15 by default). The
ranges never overlap, so training and test patients are disjoint by construction.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from drake_rus.anatomy.frames import check_side_posture
from drake_rus.anatomy.generator import _Layout, generate_patient, sample_patient_params
from drake_rus.anatomy.patient import Patient
from drake_rus.template.pca import extents_in_frame, mesh_canonical_frame

__all__ = ["TRAIN_OFFSET", "TEST_OFFSET", "DEFAULT_COUNTS", "split_seed", "cohort_seeds",
           "load_patient", "kidney_statistics", "summarize", "cohort_stats"]

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


def load_patient(spec: str, side: str = "right", posture: str = "supine", *,
                 voxel_size: float = 0.001, mapping="totalsegmentator",
                 progress: bool = True) -> Patient:
    """A patient from a spec: ``seed:N``, ``train:K``, ``test:K`` (virtual, deterministic),
    a directory of TotalSegmentator per-structure masks (kidney_right.nii.gz, body.nii.gz,
    ...), a directory of meshes (kidney_right/left, skin, liver by file name, like the HuBMAP
    folder) or a NIfTI/NRRD label map (multi-label, TotalSegmentator indices by default)."""
    check_side_posture(side, posture)
    spec = str(spec)
    head, sep, tail = spec.partition(":")
    if sep and head in SPLIT_OFFSETS:
        try:
            k = int(tail)
        except ValueError:
            raise ValueError(f"patient spec {spec!r}: expected an integer after '{head}:'") from None
        seed = split_seed(head, k)
        return generate_patient(seed, side, posture, name=spec, voxel_size=voxel_size,
                                progress=progress)
    from drake_rus.anatomy.importers import (LABEL_MAP_SUFFIXES, find_mesh_files,
                                             patient_from_label_map, patient_from_mask_folder,
                                             patient_from_meshes, totalsegmentator_mask_files)
    path = Path(spec)
    if not path.exists():
        raise FileNotFoundError(
            f"patient spec {spec!r}: not seed:N/train:K/test:K and no such file or directory")
    if path.is_dir():
        masks = totalsegmentator_mask_files(path)
        if f"kidney_{side}" in masks:
            return patient_from_mask_folder(path, side=side, posture=posture,
                                            voxel_size=voxel_size)
        found = find_mesh_files(path, side)
        if found["kidney"] is None or found["skin"] is None:
            maps = [p for p in sorted(path.iterdir()) if p.name.lower().endswith(LABEL_MAP_SUFFIXES)]
            if len(maps) == 1:
                return patient_from_label_map(maps[0], mapping, side=side, posture=posture,
                                              voxel_size=voxel_size)
            missing = [k for k in ("kidney", "skin") if found[k] is None]
            raise ValueError(f"patient directory {path}: no {' and no '.join(missing)} mesh "
                             f"found (expected file names containing 'kidney' and '{side}', "
                             "and 'skin'), and not exactly one label map")
        return patient_from_meshes(found["kidney"], found["skin"], liver=found["liver"],
                                   other_kidney=found["other_kidney"], side=side,
                                   posture=posture, name=path.name, voxel_size=voxel_size)
    if path.name.lower().endswith(LABEL_MAP_SUFFIXES):
        return patient_from_label_map(path, mapping, side=side, posture=posture,
                                      voxel_size=voxel_size)
    raise ValueError(f"patient spec {spec!r}: unknown file type (label maps: "
                     f"{', '.join(LABEL_MAP_SUFFIXES)}; meshes: give their directory)")


def kidney_statistics(seed: int, side: str = "right", posture: str = "supine") -> dict:
    """Fast per-seed kidney statistics (no skin mesh, no label volume): canonical length,
    width, thickness, volume, measured hilum/coronal/sagittal angles, vertical depth (SI).
    Identical to ``Patient.metrics()`` for the same seed (tested)."""
    prm = sample_patient_params(seed, side, posture)
    lay = _Layout(prm)
    import trimesh
    mesh = trimesh.Trimesh(lay.kidney_vertices_Bd, lay.shape.mesh.faces, process=False)
    lateral = np.array([-1.0, 0, 0]) if side == "right" else np.array([1.0, 0, 0])
    X = mesh_canonical_frame(mesh, [0, 1, 0], lateral)
    ext = extents_in_frame(mesh.vertices, X)
    x_k = X.rotation().matrix()[:, 0]
    depth = float(lay.torso.top_z(lay.p_c[0], lay.p_c[1]) - lay.kidney_top_z)
    out = {
        "seed": int(seed), "size_class": prm.torso.size_class,
        "length": float(ext[0]), "width": float(ext[1]), "thickness": float(ext[2]),
        "volume": float(mesh.volume),
        "hilum_angle": lay.hilum_angle_measured(x_k),
        "coronal_angle": float(np.arctan2(abs(x_k[0]), x_k[1])),
        "sagittal_angle": float(np.arctan2(-x_k[2], x_k[1])),
    }
    if posture == "supine":    # the analytic upper surface is the anterior one
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
    "depth_vertical_mm": "80-105 (CT skin-to-kidney)",
}

_UNITS = {"length": ("length_mm", 1e3), "width": ("width_mm", 1e3),
          "thickness": ("thickness_mm", 1e3), "volume": ("volume_ml", 1e6),
          "hilum_angle": ("hilum_angle_deg", 180 / np.pi),
          "coronal_angle": ("coronal_angle_deg", 180 / np.pi),
          "sagittal_angle": ("sagittal_angle_deg", 180 / np.pi),
          "depth_vertical": ("depth_vertical_mm", 1e3), "depth_min": ("depth_min_mm", 1e3)}


def summarize(rows: list[dict], side: str = "right", posture: str = "supine") -> dict:
    """Mean, SD, min, max of each statistic, in report units (mm, mL, deg)."""
    out = {}
    for key, (name, scale) in _UNITS.items():
        vals = np.array([r[key] for r in rows if key in r], dtype=float) * scale
        if len(vals) == 0:
            continue
        ref = REFERENCE.get(name)
        out[name] = {"mean": round(float(vals.mean()), 2),
                     "sd": round(float(vals.std(ddof=1)) if len(vals) > 1 else 0.0, 2),
                     "min": round(float(vals.min()), 2), "max": round(float(vals.max()), 2)}
        if name == "depth_vertical_mm" and posture != "supine":
            ref = "less than supine: through the upper (right) flank; no published range"
        if ref is not None:
            out[name]["reference"] = ref[side] if isinstance(ref, dict) else ref
    classes = [r["size_class"] for r in rows if "size_class" in r]
    if classes:
        out["size_classes"] = {c: classes.count(c) for c in sorted(set(classes))}
    return out


def cohort_stats(split: str, count: int | None = None, side: str = "right",
                 posture: str = "supine", full: bool = True, progress: bool = True) -> dict:
    """Summary statistics of a cohort. ``full``: build each Patient (meshes, exact depths
    through the meshes, shortest skin distance); else the fast per-seed statistics."""
    from tqdm import tqdm
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
    return {"split": split, "count": len(seeds), "side": side, "posture": posture,
            "seeds": [seeds[0], seeds[-1]], "statistics": summarize(rows, side, posture)}
