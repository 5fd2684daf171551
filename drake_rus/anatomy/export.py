"""Export a patient for 3D Slicer: label volume (NRRD or NIfTI) and meshes (STL).

Coordinates are the patient frame Pt in millimetres for the volume, the meshes and
``X_PtK`` in the info file, so they overlay in Slicer. Pt is the bed frame (x across the bed
away from the robot, y towards the head, z up), not the anatomical LPS frame, so the NRRD
header says ``space: 3D-right-handed`` (not LPS) and names the frame; NIfTI has no field for
it (the info file does). Slicer reads STL as LPS: the geometry overlays, the anatomical
letters in Slicer's views are not the patient's. Every file is written to a temporary name
first, then renamed; files get mode 0644 (under the usual umask), like any new file.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from drake_rus.anatomy.labels import Label
from drake_rus.io_utils import FILE_MODE, dumps_strict

# What the NRRD header says about the frame (a key/value pair; the space is not LPS).
NRRD_SPACE = "3D-right-handed"
FRAME_TEXT = (
    "patient frame Pt (bed frame): x across the bed away from the robot, "
    "y towards the head, z up; mm"
)

FORMATS = {"nrrd": ".nrrd", "nifti": ".nii.gz"}


def _atomic(path: Path, write):
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = "".join(path.suffixes) or ".tmp"
    fd, tmp = tempfile.mkstemp(suffix=suffix, dir=str(path.parent))
    os.close(fd)
    try:
        write(tmp)
        os.chmod(tmp, FILE_MODE)
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

    def write(tmp):
        sitk.WriteImage(img, tmp, True)
        if path.name.lower().endswith(".nrrd"):
            _relabel_nrrd_space(tmp)

    return _atomic(path, write)


def _relabel_nrrd_space(path) -> None:
    """Replaces SimpleITK's ``space: left-posterior-superior`` with the honest
    ``3D-right-handed`` and adds the frame as a key/value pair (header text only)."""
    data = Path(path).read_bytes()
    end = data.index(b"\n\n")
    lines = [
        line
        for line in data[:end].decode("ascii").split("\n")
        if not line.startswith("drake_rus_frame:=")
    ]
    lines = [f"space: {NRRD_SPACE}" if line.startswith("space:") else line for line in lines]
    lines.append(f"drake_rus_frame:={FRAME_TEXT}")
    Path(path).write_bytes("\n".join(lines).encode("ascii") + data[end:])


def estimated_export_bytes(patient) -> int:
    """About how many bytes :func:`export_patient` writes (uncompressed volume, STL)."""
    n = int(np.prod(patient.labels.labels.shape))
    meshes = [patient.kidney_mesh, patient.skin_mesh]
    if patient.liver_mesh is not None:
        meshes.append(patient.liver_mesh)
    return n + sum(84 + 50 * len(m.faces) for m in meshes) + 65536


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
    X_PtK = patient.X_PtK.GetAsMatrix4()
    X_PtK[:3, 3] *= 1000.0  # mm, like the volume and the meshes
    info = {
        "name": patient.name,
        "side": patient.side,
        "posture": patient.posture,
        "units": "mm",
        "frame": FRAME_TEXT,
        "nrrd_space": f"{NRRD_SPACE} (the Pt frame above; not LPS)",
        "labels": {lab.name: int(lab) for lab in Label},
        "X_PtK": X_PtK.round(6).tolist(),
        "X_PtK_note": "kidney frame in Pt, 4x4 homogeneous, translation in mm",
    }
    p = out / f"{stem}_info.json"
    paths.append(_atomic(p, lambda tmp: Path(tmp).write_text(dumps_strict(info, indent=2) + "\n")))
    return paths
