"""Pictures and masks: label slices, cohort overview, Meshcat scene, kidney masks."""

import numpy as np
import pytest
from conftest import write_small_label_map

from drake_rus.anatomy import patient_from_label_map, pictures
from drake_rus.anatomy.generator import generate_patient
from drake_rus.anatomy.pictures import plot_cohort_overview, plot_label_slices, show_in_meshcat
from drake_rus.cli import MakeMeshcat


@pytest.mark.parametrize("posture", ["supine", "left_lateral_decubitus"])
def test_kidney_mask_matches_mesh(posture):
    p = generate_patient(6, posture=posture)
    mask, X_PtV = p.kidney_mask(0.0015)
    vs = 0.0015
    assert mask.sum() * vs**3 == pytest.approx(p.kidney_mesh.volume, rel=0.03)
    c = X_PtV.multiply((np.argwhere(mask) * vs).T).T.mean(axis=0)
    # Volume centroid and surface centroid of a kidney differ by a few mm at most.
    assert np.linalg.norm(c - p.X_PtK.translation()) < 0.005


def test_pictures_are_written(tmp_path):
    p = generate_patient(8, voxel_size=0.004, progress=False)
    out = plot_label_slices(p, tmp_path / "slices.png")
    assert out.is_file() and out.stat().st_size > 10_000
    out = plot_cohort_overview([p, generate_patient(9)], tmp_path / "cohort.png")
    assert out.is_file()
    assert not list(tmp_path.glob("*.tmp.png"))


def test_label_slices_of_a_label_map_are_anatomical_planes(tmp_path, monkeypatch):
    """A label map keeps its scanner's (LPS) grid: i left, j posterior, k superior. The
    slice titled axial used to be the one normal to j, a coronal slice."""
    write_small_label_map(tmp_path / "seg.nii.gz")  # 320 x 240 x 160 mm
    n = (80, 60, 40)  # its grid (4 mm voxels)
    p = patient_from_label_map(tmp_path / "seg.nii.gz", voxel_size=0.004)
    drawn = []
    real = pictures.label_image
    monkeypatch.setattr(pictures, "label_image", lambda a: drawn.append(a.shape) or real(a))
    plot_label_slices(p, tmp_path / "slices.png")
    # Drawn transposed: axial = the (i, j) plane, coronal = (i, k), sagittal = (j, k).
    assert drawn == [(n[1], n[0]), (n[2], n[0]), (n[2], n[1])]
    # The generator's grid is the body's (Bd) in both postures: j superior, k anterior.
    for posture in ("supine", "left_lateral_decubitus"):
        q = generate_patient(8, posture=posture, voxel_size=0.004, progress=False)
        assert [a for _, a, _ in pictures.label_slice_views(q)] == [1, 2, 0]


def test_meshcat_scene():
    p = generate_patient(8)
    meshcat = MakeMeshcat()  # 127.0.0.1, not every interface
    show_in_meshcat(p, meshcat)
    assert meshcat.HasPath("patient/kidney") and meshcat.HasPath("patient/skin")
    assert meshcat.HasPath("patient/X_PtK/x")
