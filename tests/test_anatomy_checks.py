"""Anatomy that can exist (drake_rus.anatomy.checks): the checks on small synthetic patients
(an ellipsoid body and kidney on a 2 mm label grid), one failing case each, and the cohort
patients the scans use."""

import numpy as np
import pytest
import trimesh
from pydrake.math import RigidTransform

from drake_rus.anatomy import Label, LabelVolume, Patient, load_patient
from drake_rus.anatomy.checks import (
    AnatomyError,
    check_anatomy,
    check_label_map_body_size,
    check_mesh_units,
    kidney_surroundings,
)
from drake_rus.anatomy.rasterize import MAX_GRID_VOXELS, rasterize_mesh

VS = 0.002
SKIN = ((0.0, 0.0, 0.11), (0.15, 0.30, 0.11))  # centre, semi-axes (m): 300 x 220 mm
KIDNEY = ((-0.06, 0.0, 0.07), (0.028, 0.055, 0.02))  # right kidney, 110 mm long


def _ellipsoid(center, semi):
    m = trimesh.creation.icosphere(subdivisions=3)
    return trimesh.Trimesh(
        m.vertices * np.asarray(semi) + np.asarray(center), m.faces, process=False
    )


def _patient(
    kidney=KIDNEY, *, y_range=(-0.15, 0.15), liver_labels=None, liver_mesh=None, scale=1.0
):
    """A supine synthetic patient (Pt: x left, y superior, z up): soft tissue inside the
    skin, kidney cortex inside the kidney, liver (label) inside ``liver_labels`` (centre,
    semi-axes) around the kidney; everything scaled by ``scale``."""
    s = scale
    skin = _ellipsoid(np.multiply(SKIN[0], s), np.multiply(SKIN[1], s))
    kid = _ellipsoid(np.multiply(kidney[0], s), np.multiply(kidney[1], s))
    lo = np.array([skin.bounds[0, 0], y_range[0] * s, skin.bounds[0, 2]]) - VS * s
    hi = np.array([skin.bounds[1, 0], y_range[1] * s, skin.bounds[1, 2]]) + VS * s
    vs = VS * s
    shape = np.ceil((hi - lo) / vs).astype(int) + 1
    X_PtV = RigidTransform(lo)
    labels = np.zeros(shape, np.uint8)
    body = rasterize_mesh(skin, shape, X_PtV, vs)
    labels[body] = Label.SOFT_TISSUE
    if liver_labels is not None:
        labels[rasterize_mesh(_ellipsoid(*liver_labels), shape, X_PtV, vs) & body] = Label.LIVER
    labels[rasterize_mesh(kid, shape, X_PtV, vs)] = Label.KIDNEY_CORTEX
    return Patient(
        name="synthetic",
        side="right",
        posture="supine",
        kidney_mesh=kid,
        skin_mesh=skin,
        liver_mesh=liver_mesh,
        labels=LabelVolume(labels=labels, voxel_size=vs, X_PtV=X_PtV),
    )


def test_a_kidney_inside_the_body_passes_with_its_figures():
    fig = check_anatomy(_patient())
    assert fig["body_width"] == pytest.approx(0.30, abs=0.004)
    assert fig["body_depth"] == pytest.approx(0.22, abs=0.004)
    assert fig["kidney_length"] == pytest.approx(0.110, abs=0.002)
    assert fig["kidney_air_contact"] == 0.0 and fig["kidney_border_voxels"] == 0
    assert fig["kidney_organ_contact"] == {}
    assert fig["kidney_imaged_volume"] == pytest.approx(
        4 / 3 * np.pi * 0.028 * 0.055 * 0.02, rel=0.1
    )
    # The kidney's top is 90 mm above the bed, the skin above it about 211 mm.
    assert fig["depth_vertical"] == pytest.approx(0.121, abs=0.004)


def test_a_kidney_poking_out_of_the_skin_fails():
    with pytest.raises(
        AnatomyError,
        match=r"patient synthetic: the kidney is not inside the "
        r"body: \d+\.\d% of the voxels around it are air",
    ):
        check_anatomy(_patient(((-0.13, 0.0, 0.07), KIDNEY[1])))


def test_a_kidney_cut_by_the_volume_border_fails_saying_how_much_is_imaged():
    p = _patient(y_range=(0.0, 0.15))  # the grid starts at the kidney's middle
    with pytest.raises(AnatomyError, match="cut by the label volume's edge") as e:
        check_anatomy(p)
    text = str(e.value)
    assert "inferior face" in text
    whole = 4 / 3 * np.pi * 0.028 * 0.055 * 0.02 * 1e6
    imaged = float(text.split("only ")[1].split(" ml")[0])
    assert imaged == pytest.approx(whole / 2, rel=0.12)


def test_a_kidney_inside_the_liver_fails():
    liver = (KIDNEY[0], (0.05, 0.08, 0.035))
    with pytest.raises(
        AnatomyError,
        match=r"the kidney lies inside the liver: \d+% of the voxels "
        r"around it are liver",
    ):
        check_anatomy(_patient(liver_labels=liver))


def test_a_kidney_overlapping_a_liver_mesh_fails_and_a_touching_one_passes():
    c, a = KIDNEY
    overlapping = _ellipsoid((c[0], c[1] + 0.06, c[2]), (0.06, 0.05, 0.05))
    with pytest.raises(AnatomyError, match=r"overlaps the liver: \d+% of its volume"):
        check_anatomy(_patient(liver_mesh=overlapping))
    touching = _ellipsoid((c[0], c[1] + a[1] + 0.05, c[2]), (0.06, 0.05, 0.05))
    fig = check_anatomy(_patient(liver_mesh=touching))
    assert fig["kidney_in_liver_mesh"] < 0.01


def test_a_body_18_mm_wide_fails():
    with pytest.raises(
        AnatomyError,
        match=r"body width \(left-right, at the kidney's level\) "
        r"18(\.\d+)? mm is outside 180-800 mm",
    ):
        check_anatomy(_patient(scale=0.06))


def test_a_kidney_1000_times_too_small_fails_on_its_size():
    with pytest.raises(AnatomyError, match=r"kidney length 0\.11\d* mm is outside 50-250 mm"):
        check_anatomy(_patient((KIDNEY[0], np.multiply(KIDNEY[1], 1e-3))))


def test_kidney_surroundings_name_the_faces_and_skip_the_other_kidney():
    p = _patient(y_range=(-0.15, 0.0))
    lab = p.labels.labels.copy()
    # The other kidney (left), also cut by the same face, is not the target.
    lab[-40:-20, -3:, 40:50] = Label.KIDNEY_CORTEX
    lv = LabelVolume(labels=lab, voxel_size=VS, X_PtV=p.labels.X_PtV)
    sur = kidney_surroundings(lv, p.kidney_mesh.bounds, np.eye(3))
    assert sur["border_faces"] == ["superior"]
    assert sur["border_voxels"] == pytest.approx(np.pi * 14 * 10, rel=0.15)  # its cut face


def test_mesh_units_name_the_files_and_their_units():
    with pytest.raises(
        AnatomyError,
        match=r"skin mesh skin\.stl: 1652 across against the "
        r"kidney mesh kidney\.stl's 0\.1125.*the kidney "
        r"mesh seems to be in m and the skin mesh in mm",
    ):
        check_mesh_units(0.1125, 1652.0, "kidney.stl", "skin.stl", 1.0, "auto")
    with pytest.raises(AnatomyError, match="kidney mesh seems to be in mm and the skin mesh in m"):
        check_mesh_units(112.5, 1.652, "kidney.stl", "skin.stl", 1e-3, "auto")
    with pytest.raises(AnatomyError, match=r"1\.09 times the kidney, a body is 1\.5-60 times"):
        check_mesh_units(0.11, 0.12, "kidney.stl", "skin.stl", 1.0, "m")
    check_mesh_units(112.5, 1652.0, "kidney.stl", "skin.stl", 1e-3, "auto")  # the VH female
    check_mesh_units(112.5, 230.0, "kidney.stl", "liver.stl", 1e-3, "auto", other="liver")


def test_meshes_in_one_unit_read_wrongly_are_not_told_to_share_a_unit():
    """Both meshes in mm read as m (or both in cm) used to get "the kidney mesh seems to be
    in mm and the skin mesh in mm; give all meshes in one unit": they are in one unit."""
    with pytest.raises(AnatomyError) as e:
        check_mesh_units(110.0, 1700.0, "kidney.stl", "skin.stl", 1.0, "m")
    assert "kidney.stl" in str(e.value) and "skin.stl" in str(e.value)
    assert "seem to be in mm: units='mm' or 'auto'" in str(e.value)
    assert "give all meshes in one unit" not in str(e.value)
    with pytest.raises(AnatomyError, match="seem to be in cm: give the meshes in mm or m"):
        check_mesh_units(11.0, 170.0, "kidney.stl", "skin.stl", 1e-3, "auto")
    with pytest.raises(AnatomyError, match="seem to be in mm: units='mm'"):
        check_mesh_units(112.5, 230.0, "kidney.stl", "liver.stl", 1.0, "m", other="liver")


def test_label_map_spacing_giving_an_18_mm_body_names_the_spacing():
    body = np.zeros((200, 150, 60), bool)
    body[10:190, 10:140, :] = True  # 180 x 130 voxels across
    check_label_map_body_size(body, (1.6, 1.6, 3.0), 2, "seg.nii.gz")  # 288 x 208 mm
    with pytest.raises(
        AnatomyError,
        match=r"label map seg\.nii\.gz: with its voxel spacing "
        r"\(0\.1, 0\.1, 0\.1\) mm the body is 18 mm wide",
    ):
        check_label_map_body_size(body, (0.1, 0.1, 0.1), 2, "seg.nii.gz")
    with pytest.raises(AnatomyError, match="the body is 1.8e\\+04 mm wide"):
        check_label_map_body_size(body, (100.0, 100.0, 100.0), 2, "seg.nii.gz")


def test_rasterising_a_grid_larger_than_any_body_is_refused_before_allocating():
    sphere = _ellipsoid((0, 0, 0), (1000.0, 1000.0, 1000.0))  # a "body" in mm read as m
    shape = (2_000_000, 2_000_000, 2_000_000)
    assert np.prod(np.array(shape, float)) > MAX_GRID_VOXELS
    with pytest.raises(
        ValueError,
        match=r"voxel grid of 2e\+03 x 2e\+03 x 2e\+03 m .*mm "
        r"read as m",
    ):
        rasterize_mesh(sphere, shape, RigidTransform([-1000.0] * 3), 0.001)


@pytest.mark.parametrize("posture", ["supine", "left_lateral_decubitus"])
def test_test_patients_pass(posture):
    """Two evaluation patients in both postures (the scans' default and the seed's
    posture): load_patient checks them (the rest of test:0-14 and the Visible Human female:
    docs/facts, 'Checks on every patient')."""
    for spec in ("test:0", "test:1"):
        p = load_patient(spec, posture=posture, progress=False)
        fig = check_anatomy(p)
        assert fig["kidney_air_contact"] == 0.0 and fig["kidney_border_voxels"] == 0
        assert 0.2 < fig["body_width"] < 0.4
