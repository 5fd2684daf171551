"""Bad-input corpus, data files: meshes, label volumes, images, templates, model files.
Each bad input gives one clear error that names the file or the field."""

import json
import os
import stat

import numpy as np
import pytest
import trimesh

from drake_rus.anatomy.importers import load_mesh, patient_from_label_map
from drake_rus.anatomy.labels import LabelVolume
from drake_rus.anatomy.patient import Patient
from drake_rus.config_schema import ScenarioError
from drake_rus.imaging.config import ImagingConfig
from drake_rus.io_utils import write_text_atomic
from drake_rus.scenario import ApplyOverrides, Scenario
from drake_rus.template.io import load_template


def _box():
    return trimesh.creation.box((0.10, 0.05, 0.04))


# ------------------------------------------------------------------------------ meshes
def test_missing_mesh_file_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"kidney mesh: file not found: .*x\.stl"):
        load_mesh(tmp_path / "x.stl", "kidney mesh")


@pytest.mark.parametrize(
    "name,content",
    [
        ("junk.stl", b"solid junk\nfacet nonsense\n"),
        ("empty.stl", b""),
        ("broken.obj", b"v 1 2\nf 1 2 3 4 5\n"),
        ("zeros.stl", bytes(84)),
    ],
    ids=["garbage_stl", "empty_stl", "broken_obj", "zero_triangle_binary_stl"],
)
def test_corrupt_mesh_file_is_named(tmp_path, name, content):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(ValueError) as e:
        load_mesh(path, "skin mesh")
    assert "skin mesh" in str(e.value) and name in str(e.value)


def test_point_cloud_is_not_a_mesh(tmp_path):
    path = tmp_path / "cloud.ply"
    trimesh.PointCloud(np.random.default_rng(0).random((20, 3))).export(path)
    with pytest.raises(ValueError, match=r"kidney mesh .*cloud\.ply: no triangles"):
        load_mesh(path, "kidney mesh")


def test_open_surface_is_not_watertight(tmp_path):
    path = tmp_path / "sheet.stl"
    plane = trimesh.Trimesh(
        [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0.5]], [[0, 1, 2], [0, 2, 3], [1, 4, 2]]
    )
    plane.export(path)
    with pytest.raises(ValueError, match=r"kidney mesh .*sheet\.stl: the mesh is not watertight"):
        load_mesh(path, "kidney mesh")


def test_non_manifold_mesh_is_not_watertight():
    box = _box()
    # A fin: one extra triangle on an existing edge makes that edge non-manifold.
    v = np.vstack([box.vertices, [[0.3, 0.3, 0.3]]])
    f = np.vstack([box.faces, [[box.faces[0][0], box.faces[0][1], len(v) - 1]]])
    with pytest.raises(ValueError, match="organ mesh: the mesh is not watertight"):
        load_mesh(trimesh.Trimesh(v, f, process=False), "organ mesh")


def test_inside_out_mesh_is_turned_outward():
    inverted = trimesh.Trimesh(_box().vertices, _box().faces[:, ::-1], process=False)
    assert inverted.volume < 0
    fixed = load_mesh(inverted, "kidney mesh")
    assert fixed.volume == pytest.approx(0.10 * 0.05 * 0.04)


def test_small_holes_are_repaired():
    box = _box()
    holed = trimesh.Trimesh(box.vertices, box.faces[:-1], process=False)
    assert not holed.is_watertight
    assert load_mesh(holed, "kidney mesh").is_watertight


@pytest.mark.parametrize("which", ["kidney mesh", "skin mesh"])
def test_patient_rejects_open_meshes(which):
    box, sheet = _box(), trimesh.Trimesh(_box().vertices, _box().faces[:-3], process=False)
    meshes = {"kidney mesh": box, "skin mesh": box}
    meshes[which] = sheet
    with pytest.raises(ValueError, match=f"p: {which}: the mesh is not watertight"):
        Patient(
            name="p",
            side="right",
            posture="supine",
            kidney_mesh=meshes["kidney mesh"],
            skin_mesh=meshes["skin mesh"],
            labels=LabelVolume(np.ones((2, 2, 2), np.uint8)),
        )


def test_patient_rejects_empty_mesh():
    with pytest.raises(ValueError, match="p: kidney mesh: the mesh is empty"):
        Patient(
            name="p",
            side="right",
            posture="supine",
            kidney_mesh=trimesh.Trimesh(),
            skin_mesh=_box(),
            labels=LabelVolume(np.ones((2, 2, 2), np.uint8)),
        )


# ------------------------------------------------------------------------ label volumes
@pytest.mark.parametrize(
    "labels,voxel,words",
    [
        (np.zeros((0, 4, 4), np.uint8), 0.001, ["LabelVolume.labels", "empty"]),
        (np.zeros((4, 4), np.uint8), 0.001, ["LabelVolume.labels", "3-D"]),
        (np.zeros((4, 4, 4), np.float32), 0.001, ["LabelVolume.labels", "integer"]),
        (np.zeros((4, 4, 4), np.uint8), 0.0, ["LabelVolume.voxel_size"]),
        (np.zeros((4, 4, 4), np.uint8), float("nan"), ["LabelVolume.voxel_size"]),
        (np.zeros((4, 4, 4), np.uint8), -0.001, ["LabelVolume.voxel_size"]),
        (np.full((4, 4, 4), 263, np.int16), 0.001, ["LabelVolume.labels", "0-255", "263"]),
        (np.full((4, 4, 4), -1, np.int64), 0.001, ["LabelVolume.labels", "0-255", "-1"]),
    ],
    ids=[
        "empty",
        "2d",
        "float",
        "zero_voxel",
        "nan_voxel",
        "negative_voxel",
        "label_above_255",
        "negative_label",
    ],
)
def test_bad_label_volume_names_field(labels, voxel, words):
    with pytest.raises(ValueError) as e:
        LabelVolume(labels, voxel_size=voxel)
    for w in words:
        assert w in str(e.value)


def test_label_volume_keeps_wide_integer_labels_in_range():
    """Labels 0-255 in a wider integer type are fine (slicing reads them as uint8); only
    values uint8 cannot hold are refused (263 would be sliced as the liver, -1 as gel)."""
    vol = LabelVolume(np.full((4, 4, 4), 255, np.int64), voxel_size=0.001)
    assert vol.labels.max() == 255


def _write_label_map(path, array, dtype=np.uint8):
    import SimpleITK as sitk

    sitk.WriteImage(sitk.GetImageFromArray(np.asarray(array, dtype)), str(path))
    return path


def test_empty_label_map_is_named(tmp_path):
    path = _write_label_map(tmp_path / "empty.nii.gz", np.zeros((10, 10, 10)))
    with pytest.raises(ValueError, match=r"label map .*empty\.nii\.gz: empty"):
        patient_from_label_map(path)


def test_label_map_without_kidney_is_named(tmp_path):
    path = _write_label_map(tmp_path / "nokidney.nii.gz", np.full((10, 10, 10), 200))
    with pytest.raises(ValueError, match=r"nokidney\.nii\.gz: no voxels of the right kidney"):
        patient_from_label_map(path)


def test_label_map_without_body_is_named(tmp_path):
    a = np.zeros((12, 12, 12))
    a[4:8, 4:8, 4:8] = 2
    path = _write_label_map(tmp_path / "nobody.nii.gz", a)
    with pytest.raises(ValueError, match=r"nobody\.nii\.gz: no body label"):
        patient_from_label_map(path)


def test_inside_out_label_map_is_named(tmp_path):
    a = np.full((30, 30, 30), 2)  # kidney everywhere ...
    a[8:22, 8:22, 8:22] = 200  # ... except a body-labelled core: inverted
    path = _write_label_map(tmp_path / "inverted.nii.gz", a)
    with pytest.raises(ValueError, match=r"inverted\.nii\.gz: .*inside-out"):
        patient_from_label_map(path)


def test_unreadable_label_map_is_named(tmp_path):
    path = tmp_path / "junk.nii.gz"
    path.write_bytes(b"not a nifti file")
    with pytest.raises(ValueError, match=r"label map .*junk\.nii\.gz: cannot read it"):
        patient_from_label_map(path)


def test_2d_label_map_is_named(tmp_path):
    path = _write_label_map(tmp_path / "flat.nii.gz", np.zeros((10, 10)))
    with pytest.raises(ValueError, match=r"flat\.nii\.gz: expected a 3-D image"):
        patient_from_label_map(path)


def test_float_label_map_is_named(tmp_path):
    path = _write_label_map(tmp_path / "float.nii.gz", np.full((5, 5, 5), 0.5), np.float32)
    with pytest.raises(ValueError, match=r"float\.nii\.gz: voxel values are not integer"):
        patient_from_label_map(path)


def test_missing_label_map_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"label map: file not found: .*gone\.nii\.gz"):
        patient_from_label_map(tmp_path / "gone.nii.gz")


@pytest.mark.parametrize(
    "spec,exc,words",
    [
        ("bogus:3", FileNotFoundError, ["bogus:3"]),
        ("test:x", ValueError, ["test:x", "integer"]),
    ],
    ids=["unknown_spec", "non_integer_index"],
)
def test_bad_patient_spec_is_named(spec, exc, words):
    from drake_rus.anatomy import load_patient

    with pytest.raises(exc) as e:
        load_patient(spec)
    for w in words:
        assert w in str(e.value)


def test_patient_directory_without_meshes_is_named(tmp_path):
    from drake_rus.anatomy import load_patient

    (tmp_path / "readme.txt").write_text("nothing here")
    with pytest.raises(ValueError, match=f"patient directory {tmp_path}: no kidney"):
        load_patient(str(tmp_path))


# -------------------------------------------------------------------------------- images
@pytest.mark.parametrize(
    "shape", [(10, 10), (256, 255), (256, 256, 3)], ids=["tiny", "off_by_one", "rgb"]
)
def test_wrong_image_size_emulator(shape):
    from drake_rus.imaging.emulator import EmulatorModel, emulate

    with pytest.raises(ValueError, match=r"emulate: label image has shape"):
        emulate(np.zeros(shape, np.uint8), EmulatorModel.from_config(ImagingConfig()))


@pytest.mark.parametrize("shape", [(10, 10), (257, 256)], ids=["tiny", "off_by_one"])
def test_wrong_image_size_segmenter(geometry, shape):
    from drake_rus.imaging.segment import segment_classical

    with pytest.raises(ValueError, match=r"segment_classical: image shape"):
        segment_classical(np.zeros(shape, np.uint8), geometry)


def test_wrong_image_size_segmenter_system_names_config_fields():
    from drake_rus.imaging.frames import UsFrame
    from drake_rus.imaging.systems import Segmenter

    seg = Segmenter(ImagingConfig(segmenter="oracle"))
    ctx = seg.CreateDefaultContext()
    seg.GetInputPort("label_image").FixValue(
        ctx, UsFrame(np.zeros((32, 32), np.uint8), frame_index=0)
    )
    with pytest.raises(ValueError, match="image_height_px x image_width_px"):
        seg.GetOutputPort("kidney_visible").Eval(ctx)


def test_non_finite_pose_is_named(geometry):
    from pydrake.math import RigidTransform

    from drake_rus.imaging.slicing import slice_volume

    with pytest.raises(ValueError, match="X_BP: pose has non-finite entries"):
        slice_volume(
            geometry,
            LabelVolume(np.zeros((5, 5, 5), np.uint8)),
            RigidTransform(),
            RigidTransform([np.nan, 0.0, 0.0]),
        )


def test_slice_sensor_rejects_raw_array():
    from pydrake.math import RigidTransform

    from drake_rus.imaging.systems import SliceSensor

    with pytest.raises(ValueError, match="SliceSensor: volume must be a LabelVolume"):
        SliceSensor(ImagingConfig(), np.zeros((5, 5, 5), np.uint8), RigidTransform())


# ------------------------------------------------------------------------------ templates
def _template_arrays(**changes):
    arrays = dict(
        points=np.zeros((4, 3)),
        normals=np.zeros((4, 3)),
        modes=np.zeros((0, 4, 3)),
        variances=np.zeros(0),
        metadata=json.dumps({}),
    )
    arrays.update(changes)
    return {k: v for k, v in arrays.items() if v is not None}


@pytest.mark.parametrize(
    "arrays,words",
    [
        (_template_arrays(normals=None, modes=None), ["missing arrays", "normals"]),
        (_template_arrays(points=np.zeros((4, 2)), normals=np.zeros((4, 2))), ["(M, 3)"]),
        (_template_arrays(metadata="{not json"), ["metadata", "JSON"]),
        (_template_arrays(points=np.full((4, 3), np.nan)), ["NaN"]),
    ],
    ids=["missing_arrays", "wrong_shape", "bad_metadata", "nan_points"],
)
def test_bad_template_is_named(tmp_path, arrays, words):
    path = tmp_path / "template.npz"
    np.savez(path, **arrays)
    with pytest.raises(ValueError) as e:
        load_template(path)
    assert "template.npz" in str(e.value)
    for w in words:
        assert w in str(e.value)


def test_unreadable_template_is_named(tmp_path):
    path = tmp_path / "junk.npz"
    path.write_bytes(b"junk")
    with pytest.raises(ValueError, match=r"junk\.npz: not a readable \.npz"):
        load_template(path)


def test_missing_template_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"kidney template not found: .*none\.npz"):
        load_template(tmp_path / "none.npz")


# ------------------------------------------------------------------------------ model files
@pytest.mark.parametrize(
    "section,url",
    [
        ("robot", "package://drake_rus_models/fr3/nope.urdf"),
        ("probe", "package://drake_rus_models/probe/nope.sdf"),
        ("robot", "/nonexistent/dir/fr3.urdf"),
        ("probe", "relative/missing_probe.sdf"),
    ],
    ids=["robot_package", "probe_package", "robot_absolute_path", "probe_relative_path"],
)
def test_missing_model_file_names_field(section, url):
    from drake_rus.robot import MakeControlPlant

    scenario = ApplyOverrides(Scenario(), f"{{{section}: {{model: '{url}'}}}}")
    with pytest.raises(ScenarioError) as e:
        MakeControlPlant(scenario.robot, scenario.probe)
    assert f"field '{section}.model'" in str(e.value) and "does not exist" in str(e.value)


def test_malformed_model_file_names_field(tmp_path):
    from drake_rus.robot import MakeControlPlant

    path = tmp_path / "broken.urdf"
    path.write_text("<robot name='x'><link name='a'></robot>")
    scenario = ApplyOverrides(Scenario(), f"{{robot: {{model: '{path}'}}}}")
    with pytest.raises(ScenarioError, match=r"field 'robot.model'.*broken\.urdf.*XML"):
        MakeControlPlant(scenario.robot, scenario.probe)


def test_missing_onnx_model_names_field():
    from drake_rus.imaging.systems import Segmenter

    with pytest.raises(ValueError, match=r"imaging\.onnx_model: .*not found"):
        Segmenter(ImagingConfig(segmenter="onnx", onnx_model="models/nope.onnx"))


# ------------------------------------------------------------------ nothing half-written
def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    from drake_rus.io_utils import atomic_path

    target = tmp_path / "out" / "summary.json"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("{partial")
            raise RuntimeError("crash mid-write")
    assert not target.exists()
    assert list(tmp_path.iterdir()) == []  # nor the folder made for it
    write_text_atomic(target, "{}")
    assert target.read_text() == "{}" and len(list(target.parent.iterdir())) == 1


def test_atomic_write_failure_removes_only_the_empty_folders_it_made(tmp_path):
    """A failed write leaves none of the folders it made when they are still empty, and
    keeps a folder that was there before (empty or not) and one that something else wrote
    into meanwhile."""
    from drake_rus.io_utils import atomic_path

    (tmp_path / "runs").mkdir()
    (tmp_path / "runs" / "old.json").write_text("{}")
    (tmp_path / "empty").mkdir()
    for target in (tmp_path / "runs/a/b/c.json", tmp_path / "empty/x.json"):
        with pytest.raises(RuntimeError):
            with atomic_path(target) as tmp:
                tmp.write_text("{partial")
                raise RuntimeError("the work failed")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty", "runs"]
    assert [p.name for p in (tmp_path / "runs").iterdir()] == ["old.json"]
    assert list((tmp_path / "empty").iterdir()) == []

    with pytest.raises(RuntimeError):
        with atomic_path(tmp_path / "runs/a/b/c.json") as tmp:
            (tmp_path / "runs/a/other.txt").write_text("not ours")
            raise RuntimeError("the work failed")
    assert [p.name for p in (tmp_path / "runs/a").iterdir()] == ["other.txt"]


def test_a_failed_diagram_render_leaves_no_folder(tmp_path, failing_dot):
    """Graphviz failing: one line, and no empty folder left for --out."""
    from drake_rus.cli import UserError
    from drake_rus.render import render_graphviz

    out = tmp_path / "pictures" / "scan.svg"
    with pytest.raises(UserError, match="Graphviz 'dot' failed"):
        render_graphviz("digraph { }", out)
    assert not (tmp_path / "pictures").exists()


# ------------------------------------------------------- issue 17: exports and strict JSON
def _small_patient():
    box = _box()
    labels = np.zeros((6, 6, 6), np.uint8)
    labels[2:4, 2:4, 2:4] = 2
    return Patient(
        name="test:9",
        side="right",
        posture="supine",
        kidney_mesh=box,
        skin_mesh=trimesh.creation.box((0.3, 0.3, 0.2)),
        labels=LabelVolume(labels, voxel_size=0.002),
    )


@pytest.mark.parametrize("fmt", ["nrrd", "nifti"])
def test_export_files_are_0644_under_umask_022(tmp_path, fmt):
    from drake_rus.anatomy.export import export_patient

    old = os.umask(0o022)
    try:
        paths = export_patient(_small_patient(), tmp_path / "exp", fmt)
    finally:
        os.umask(old)
    for p in paths:
        assert stat.S_IMODE(p.stat().st_mode) == 0o644, p
    assert sorted(x.name for x in (tmp_path / "exp").iterdir()) == sorted(p.name for p in paths)


def test_export_info_units_are_consistent(tmp_path):
    from drake_rus.anatomy.export import export_patient

    patient = _small_patient()
    paths = export_patient(patient, tmp_path, "nrrd")
    info = json.loads([p for p in paths if p.name.endswith("_info.json")][0].read_text())
    assert info["units"] == "mm"
    np.testing.assert_allclose(
        np.array(info["X_PtK"])[:3, 3], patient.X_PtK.translation() * 1000.0, atol=1e-6
    )
    assert "not LPS" in info["nrrd_space"]


def test_export_nrrd_space_is_not_labelled_lps(tmp_path):
    import SimpleITK as sitk

    from drake_rus.anatomy.export import export_patient

    paths = export_patient(_small_patient(), tmp_path, "nrrd")
    nrrd = [p for p in paths if p.name.endswith(".nrrd")][0]
    header = nrrd.read_bytes().split(b"\n\n")[0].decode()
    assert "space: 3D-right-handed" in header and "left-posterior-superior" not in header
    assert "drake_rus_frame:=" in header
    image = sitk.ReadImage(str(nrrd))  # still readable, same geometry
    assert image.GetSpacing() == pytest.approx((2.0, 2.0, 2.0))
    assert sitk.GetArrayFromImage(image).sum() > 0


def test_json_files_are_strict(tmp_path):
    from drake_rus.io_utils import dumps_strict

    path = write_text_atomic(
        tmp_path / "x.json", json.dumps({"a": float("nan"), "b": [1.0, float("inf")]})
    )
    text = path.read_text()
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"a": None, "b": [1.0, None]}
    assert json.loads(
        dumps_strict({"v": np.float64("nan"), "w": np.arange(2)}, default=lambda o: o.tolist())
    ) == {"v": None, "w": [0, 1]}
    # Not JSON files are written as they are.
    assert write_text_atomic(tmp_path / "x.txt", "NaN").read_text() == "NaN"


def test_atomic_writes_honour_the_umask(tmp_path):
    old = os.umask(0o022)
    try:
        path = write_text_atomic(tmp_path / "a.json", "{}")
    finally:
        os.umask(old)
    assert stat.S_IMODE(path.stat().st_mode) == 0o644


def test_output_lock_refuses_a_busy_folder_and_takes_a_stale_one(tmp_path):
    from drake_rus.io_utils import LOCK_NAME, OutputError, output_dir

    out = tmp_path / "run"
    with output_dir(out, "--out") as o:
        assert (o / LOCK_NAME).exists()
        with pytest.raises(OutputError, match="--out: .* in use"):
            with output_dir(out, "--out"):
                pass
        (o / "summary.json").write_text("{}")
    assert not (out / LOCK_NAME).exists() and (out / "summary.json").exists()
    (out / LOCK_NAME).write_text("999999999 scan\n")  # its process is gone
    with output_dir(out, "--out"):
        pass


def test_output_folder_removed_when_the_run_fails_before_writing(tmp_path):
    from drake_rus.io_utils import output_dir

    out = tmp_path / "a" / "b"
    with pytest.raises(RuntimeError):
        with output_dir(out, "--out"):
            raise RuntimeError("bad input found late")
    assert not (tmp_path / "a").exists()
    with pytest.raises(KeyboardInterrupt):
        with output_dir(out, "--out") as o:
            (o / "partial.json").write_text("{}")
            raise KeyboardInterrupt
    assert (out / "partial.json").exists()


def test_label_map_spacing_checked_from_the_header(tmp_path):
    from drake_rus.anatomy.cli import check_patient_spec
    from drake_rus.cli import UserError

    path = _write_label_map(tmp_path / "m.nrrd", np.zeros((4, 4, 4)))  # 1 mm: fine
    check_patient_spec(str(path))
    import SimpleITK as sitk

    img = sitk.GetImageFromArray(np.zeros((4, 4, 4), np.uint8))
    img.SetSpacing((1.0, 1.0, 30.0))
    sitk.WriteImage(img, str(tmp_path / "thick.nrrd"))
    with pytest.raises(UserError, match=r"--patient: label map .*thick\.nrrd: voxel spacing"):
        check_patient_spec(str(tmp_path / "thick.nrrd"))
