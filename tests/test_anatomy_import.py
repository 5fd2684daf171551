"""Real-data import: meshes (STL written here), label maps (NIfTI/NRRD written here), the
HuBMAP Visible Human Female body from ../shared, export, CLI, and clear errors."""

import json

import numpy as np
import pytest
import SimpleITK as sitk
import trimesh
from conftest import HUBMAP, needs_hubmap  # the real body beside the clone, or a skip

from drake_rus.anatomy import (
    Label,
    is_kidney,
    load_patient,
    patient_from_label_map,
    patient_from_meshes,
)
from drake_rus.anatomy.generator import generate_patient
from drake_rus.cli import main as cli_main


@pytest.fixture(scope="module")
def mesh_dir(tmp_path_factory):
    """A virtual patient's meshes written as STL in mm, in the LSA body frame."""
    d = tmp_path_factory.mktemp("meshes")
    p = generate_patient(7)
    for name, m in (("kidney_right", p.kidney_mesh), ("skin", p.skin_mesh)):
        q = m.copy()
        q.apply_scale(1000.0)
        q.export(d / f"case_{name}.stl")
    return d, p


def test_from_meshes_reproduces_the_generated_patient(mesh_dir):
    d, ref = mesh_dir
    p = patient_from_meshes(d / "case_kidney_right.stl", d / "case_skin.stl")
    m, r = p.metrics(), ref.metrics()
    for key in ("length", "width", "thickness", "volume", "depth_min"):
        assert m[key] == pytest.approx(r[key], rel=1e-3, abs=2e-4), key
    # Imported bodies measure the vertical depth on a re-surfaced torso section (5 mm voxels).
    assert m["depth_vertical"] == pytest.approx(r["depth_vertical"], abs=0.0015)
    R, R0 = p.X_PtK.rotation().matrix(), ref.X_PtK.rotation().matrix()
    np.testing.assert_allclose(R, R0, atol=1e-6)
    # Pt origin: kidney centroid level, on the bed (lowest skin point of the section).
    assert abs(p.X_PtK.translation()[1]) < 1e-9
    assert p.skin_mesh.bounds[0, 2] == pytest.approx(0.0, abs=0.002)
    q = load_patient(str(d))
    assert q.X_PtK.IsNearlyEqualTo(p.X_PtK, 1e-12)


def test_mesh_patient_labels_and_torso(mesh_dir):
    d, _ = mesh_dir
    p = patient_from_meshes(d / "case_kidney_right.stl", d / "case_skin.stl", voxel_size=0.003)
    lv = p.labels
    kid = is_kidney(lv.labels)
    assert kid.sum() * lv.voxel_size**3 == pytest.approx(p.kidney_mesh.volume, rel=0.12)
    for lab in (
        Label.FAT,
        Label.MUSCLE,
        Label.SOFT_TISSUE,
        Label.KIDNEY_CORTEX,
        Label.KIDNEY_SINUS,
    ):
        assert (lv.labels == lab).any(), lab.name
    t = p.torso_section(0.08)
    assert t.is_watertight
    assert t.bounds[1, 1] - t.bounds[0, 1] == pytest.approx(0.16, abs=0.012)


def test_bad_meshes_give_clear_errors(tmp_path, mesh_dir):
    d, _ = mesh_dir
    with pytest.raises(FileNotFoundError, match="kidney mesh"):
        patient_from_meshes(tmp_path / "none.stl", d / "case_skin.stl")
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=30.0)
    keep = np.ones(len(sphere.faces), bool)
    keep[sphere.vertex_faces[0][sphere.vertex_faces[0] >= 0]] = False  # a hole around vertex 0
    keep[sphere.vertex_faces[5][sphere.vertex_faces[5] >= 0]] = False  # and another
    box = trimesh.Trimesh(sphere.vertices, sphere.faces[keep])
    open_path = tmp_path / "open.stl"
    box.export(open_path)
    with pytest.raises(ValueError, match="not watertight"):
        patient_from_meshes(open_path, d / "case_skin.stl")
    garbage = tmp_path / "garbage.stl"
    garbage.write_bytes(b"\x00\x01 not an stl")
    with pytest.raises(ValueError, match="garbage.stl"):
        patient_from_meshes(garbage, d / "case_skin.stl")
    with pytest.raises(ValueError, match="axes"):
        patient_from_meshes(d / "case_kidney_right.stl", d / "case_skin.stl", axes="LSS")


def _write_label_map(path, labels, spacing_mm, origin_mm=(0, 0, 0), direction=None):
    img = sitk.GetImageFromArray(np.ascontiguousarray(labels.transpose(2, 1, 0)))
    img.SetSpacing(spacing_mm)
    img.SetOrigin(origin_mm)
    if direction is not None:
        img.SetDirection(direction)
    sitk.WriteImage(img, str(path))


def _synthetic_label_volume():
    """A TotalSegmentator-like map in LPS (i: left, j: posterior, k: superior), 2 mm voxels:
    body ellipse (200), right kidney (2), liver (5)."""
    n = (160, 120, 80)
    ii, jj, kk = np.meshgrid(*[np.arange(s) for s in n], indexing="ij")
    x, y, z = (ii - 80) * 2.0, (jj - 60) * 2.0, (kk - 40) * 2.0  # mm, LPS
    lab = np.zeros(n, np.uint8)
    lab[(x / 150) ** 2 + (y / 100) ** 2 <= 1] = 200
    # right kidney: patient's right = -x (LPS), posterior = +y
    kid = ((x + 75) / 28) ** 2 + ((y - 40) / 20) ** 2 + (z / 55) ** 2 <= 1
    lab[kid] = 2
    liver = ((x + 60) / 70) ** 2 + ((y + 10) / 50) ** 2 + ((z - 60) / 40) ** 2 <= 1
    lab[liver & (lab == 200)] = 5
    return lab, kid


@pytest.mark.parametrize("suffix", [".nii.gz", ".nrrd"])
def test_from_label_map(tmp_path, suffix):
    lab, kid = _synthetic_label_volume()
    path = tmp_path / f"seg{suffix}"
    _write_label_map(path, lab, (2.0, 2.0, 2.0), (-160.0, -120.0, -80.0))
    p = patient_from_label_map(path, voxel_size=0.002)
    m = p.metrics()
    # Kidney semi-axes 28, 20, 55 mm: the long axis is superior (z), length ~110 mm.
    assert m["length"] == pytest.approx(0.110, abs=0.006)
    assert m["volume"] == pytest.approx(4 / 3 * np.pi * 0.028 * 0.020 * 0.055, rel=0.08)
    R = p.X_PtK.rotation().matrix()
    assert abs(R[1, 0]) > 0.99 and R[1, 0] > 0  # x_k superior
    assert R[:, 1] @ np.array([-1.0, 0, 0]) > 0  # y_k towards patient's right
    assert p.X_PtK.translation()[0] < -0.05  # right kidney towards robot
    # Posterior kidney: the back (bed) is below it.
    assert 0.02 < p.X_PtK.translation()[2] < 0.08
    lv = p.labels
    assert (lv.labels == Label.LIVER).any()
    pts = lv.voxel_centers_in_patient(np.argwhere(is_kidney(lv.labels)))
    np.testing.assert_allclose(pts.mean(axis=0), p.X_PtK.translation(), atol=0.003)


def test_totalsegmentator_mask_folder(tmp_path):
    """TotalSegmentator's default output: one binary mask per structure."""
    lab, kid = _synthetic_label_volume()
    d = tmp_path / "ts"
    d.mkdir()
    for name, value in (("body", 200), ("kidney_right", 2), ("liver", 5)):
        m = (lab > 0) if name == "body" else (lab == value)
        _write_label_map(
            d / f"{name}.nii.gz", m.astype(np.uint8), (2.0, 2.0, 2.0), (-160.0, -120.0, -80.0)
        )
    (d / "notes.txt").write_text("ignored")
    p = load_patient(str(d), voxel_size=0.002)
    assert p.meta["source"] == "mask_folder"
    assert p.metrics()["length"] == pytest.approx(0.110, abs=0.006)
    assert (p.labels.labels == Label.LIVER).any()
    _write_label_map(d / "rib_right_11.nii.gz", np.zeros((10, 10, 10), np.uint8), (2.0, 2.0, 2.0))
    with pytest.raises(ValueError, match="rib_right_11.nii.gz is not on the same grid"):
        load_patient(str(d), voxel_size=0.002)
    (d / "body.nii.gz").unlink()
    (d / "rib_right_11.nii.gz").unlink()
    with pytest.raises(ValueError, match="no body mask"):
        load_patient(str(d), voxel_size=0.002)


def test_label_map_errors(tmp_path):
    lab, _ = _synthetic_label_volume()
    path = tmp_path / "seg.nrrd"
    _write_label_map(path, lab, (2.0, 2.0, 2.0))
    with pytest.raises(ValueError, match="left kidney"):
        patient_from_label_map(path, side="left", voxel_size=0.002)
    with pytest.raises(ValueError, match="unknown label name 'spleen'"):
        patient_from_label_map(path, {2: "kidney_right", 1: "spleen"})
    with pytest.raises(ValueError, match="no body label"):
        patient_from_label_map(path, {2: "kidney_right"}, voxel_size=0.002)
    empty = tmp_path / "empty.nii.gz"
    _write_label_map(empty, np.zeros((10, 10, 10), np.uint8), (1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="empty"):
        patient_from_label_map(empty)
    with pytest.raises(FileNotFoundError, match="label map"):
        patient_from_label_map(tmp_path / "missing.nrrd")


def test_label_of_a_few_voxels_is_named_not_a_marching_cubes_error(tmp_path):
    """A kidney label of one stray voxel used to end in skimage's "Surface level must be
    within volume data range" without the file; a liver the map only grazes has no mesh."""
    lab, _ = _synthetic_label_volume()
    lab[lab == 2] = 200
    lab[40, 80, 40] = 2
    path = tmp_path / "stray_kidney.nii.gz"
    _write_label_map(path, lab, (2.0, 2.0, 2.0), (-160.0, -120.0, -80.0))
    with pytest.raises(ValueError, match=r"stray_kidney.nii.gz: the right kidney: .* 1 voxel"):
        patient_from_label_map(path, voxel_size=0.002)
    lab, _ = _synthetic_label_volume()
    lab[lab == 5] = 200
    lab[90, 50, 70] = 5
    path = tmp_path / "grazed_liver.nii.gz"
    _write_label_map(path, lab, (2.0, 2.0, 2.0), (-160.0, -120.0, -80.0))
    p = patient_from_label_map(path, voxel_size=0.002)
    assert p.liver_mesh is None
    assert (p.labels.labels == Label.LIVER).sum() == 1


def test_export_and_reimport(tmp_path):
    p = generate_patient(3, voxel_size=0.003, progress=False)
    paths = p.export(tmp_path / "out", "nifti")
    names = sorted(x.name for x in paths)
    assert names == [
        "seed_3_info.json",
        "seed_3_kidney.stl",
        "seed_3_labels.nii.gz",
        "seed_3_skin.stl",
    ]
    assert not [x for x in (tmp_path / "out").iterdir() if "tmp" in x.name]
    img = sitk.ReadImage(str(tmp_path / "out" / "seed_3_labels.nii.gz"))
    arr = sitk.GetArrayFromImage(img).transpose(2, 1, 0)
    np.testing.assert_array_equal(arr, p.labels.labels)
    np.testing.assert_allclose(
        np.array(img.GetOrigin()) / 1000, p.labels.X_PtV.translation(), atol=1e-6
    )
    k = trimesh.load(tmp_path / "out" / "seed_3_kidney.stl")
    assert k.volume * 1e-9 == pytest.approx(p.kidney_mesh.volume, rel=1e-6)
    with pytest.raises(ValueError, match="format"):
        p.export(tmp_path / "x", "vtk")


@needs_hubmap
def test_hubmap_real_body_imports():
    from drake_rus.anatomy.cli import patient_info

    p = load_patient(str(HUBMAP))
    m = p.metrics()
    assert 0.110 <= m["length"] <= 0.140  # issue: plausible 110-140 mm
    assert m["volume"] == pytest.approx(196e-6, rel=0.05)  # README: 196 mL
    assert p.skin_mesh.is_watertight and p.kidney_mesh.is_watertight
    R = p.X_PtK.rotation().matrix()
    assert R[1, 0] > 0.7 and R[0, 1] < 0  # superior; lateral = -x (right)
    assert p.X_PtK.translation()[0] < -0.03  # right kidney towards the robot
    assert 0.06 < m["depth_vertical"] < 0.2 and m["depth_min"] > 0.02
    assert p.liver_mesh is not None
    info = patient_info(p)  # what `patient info` prints
    assert 110 <= info["length_mm"] <= 140
    assert set(info["X_PtK"]) == {"p_mm", "x_k", "y_k", "z_k"}


def test_cli_errors(capsys, tmp_path):
    assert cli_main(["patient", "info", str(tmp_path / "nothing")]) == 2
    assert "no such file" in capsys.readouterr().err
    assert cli_main(["patient", "info", "seed:abc"]) == 2
    assert "integer" in capsys.readouterr().err
    assert cli_main(["cohort", "--split", "test", "--count", "0", "--stats"]) == 2


def test_cli_cohort_stats_small(capsys):
    assert cli_main(["cohort", "--split", "test", "--count", "2", "--stats", "--quiet"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["count"] == 2 and out["seeds"] == [2000000, 2000001]
    assert 80 <= out["statistics"]["depth_vertical_mm"]["min"] <= 105


def test_cli_patient_export(tmp_path, capsys):
    out = tmp_path / "exp"
    assert (
        cli_main(
            [
                "patient",
                "export",
                "seed:2",
                "--out",
                str(out),
                "--voxel-mm",
                "4",
                "--format",
                "nrrd",
            ]
        )
        == 0
    )
    written = json.loads(capsys.readouterr().out)["written"]
    assert any(w.endswith("seed_2_labels.nrrd") for w in written)
    img = sitk.ReadImage(str(out / "seed_2_labels.nrrd"))
    assert img.GetSpacing() == pytest.approx((4.0, 4.0, 4.0))
