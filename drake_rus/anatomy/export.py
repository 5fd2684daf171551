"""Export a patient for 3D Slicer: label volume (NRRD or NIfTI) and meshes (STL).

Coordinates are the patient frame Pt in millimetres for both the volume and the meshes, so
they overlay in Slicer (Slicer reads STL as LPS by default and the volume header is written
by SimpleITK in LPS; the anatomical letters are then not the patient's, the geometry is
consistent). Every file is written to a temporary name first, then renamed.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np

from drake_rus.anatomy.labels import Label

FORMATS = {"nrrd": ".nrrd", "nifti": ".nii.gz"}


def _atomic(path: Path, write):
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = "".join(path.suffixes) or ".tmp"
    fd, tmp = tempfile.mkstemp(suffix=suffix, dir=str(path.parent))
    os.close(fd)
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return path


def write_label_volume(volume, path) -> Path:
    import SimpleITK as sitk
    path = Path(path)
    img = sitk.GetImageFromArray(np.ascontiguousarray(volume.labels.transpose(2, 1, 0)))
    img.SetSpacing([volume.voxel_size * 1000.0] * 3)
    img.SetOrigin((volume.X_PtV.translation() * 1000.0).tolist())
    img.SetDirection(volume.X_PtV.rotation().matrix().ravel().tolist())
    return _atomic(path, lambda tmp: sitk.WriteImage(img, tmp, True))


def write_mesh_mm(mesh, path) -> Path:
    m = mesh.copy()
    m.apply_scale(1000.0)
    return _atomic(Path(path), lambda tmp: m.export(tmp, file_type="stl"))


def export_patient(patient, out_dir, fmt: str = "nrrd") -> list[Path]:
    if fmt not in FORMATS:
        raise ValueError(f"format: expected one of {list(FORMATS)}, got {fmt!r}")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"export: {out} exists and is not a directory")
    stem = patient.name.replace(":", "_").replace("/", "_")
    paths = [
        write_label_volume(patient.labels, out / f"{stem}_labels{FORMATS[fmt]}"),
        write_mesh_mm(patient.kidney_mesh, out / f"{stem}_kidney.stl"),
        write_mesh_mm(patient.skin_mesh, out / f"{stem}_skin.stl"),
    ]
    if patient.liver_mesh is not None:
        paths.append(write_mesh_mm(patient.liver_mesh, out / f"{stem}_liver.stl"))
    info = {"name": patient.name, "side": patient.side, "posture": patient.posture,
            "units": "mm, patient frame Pt", "labels": {l.name: int(l) for l in Label},
            "X_PtK": patient.X_PtK.GetAsMatrix4().tolist()}
    p = out / f"{stem}_info.json"
    paths.append(_atomic(p, lambda tmp: Path(tmp).write_text(json.dumps(info, indent=2))))
    return paths
