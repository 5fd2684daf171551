"""Real CT kidneys (anatomy/ct_kidney.py): the patient frame from anatomy on a synthetic
KiTS-style label map with a known pose, stored permuted and mirrored in several ways; the
kidney pose and tumour after resampling; the one-line errors; 2 real KiTS cases (skip
without ../shared)."""

import gzip

import numpy as np
import pytest
import SimpleITK as sitk
from conftest import KITS, needs_kits, stored_as, synthetic_ct_case
from pydrake.math import RigidTransform

from drake_rus.anatomy.canonical_frame import mesh_canonical_frame
from drake_rus.anatomy.ct_kidney import (
    CLOSING_POLE_MAX_SHARE,
    LabelGrid,
    estimate_frame,
    import_ct_kidneys,
    kidney_components,
    kidney_fields_A,
    pole_closes_on_border,
    read_label_grid,
    right_lower_statistic,
    select_kidney,
    survey_case,
    survey_summary,
)
from drake_rus.anatomy.ct_patient import VoxelKidneyShape
from drake_rus.anatomy.rasterize import mask_to_mesh

# Stored layouts: (A axis of each stored axis, stored axes reversed). The KiTS one is
# (x, z, y) with z and y reversed: in-plane, in-plane, slices from the head down.
LAYOUTS = [
    ((0, 1, 2), ()),
    ((0, 2, 1), (1, 2)),
    ((2, 0, 1), (1,)),
    ((1, 2, 0), (0, 2)),
    ((2, 1, 0), (0, 1, 2)),
    ((1, 0, 2), ()),
]


@pytest.fixture(scope="module")
def case():
    return synthetic_ct_case()


def _write(path, a, spacing, R_AG, lie=None):
    """Writes numpy array ``a`` (axes with anatomical directions R_AG) as a label map whose
    direction matrix is right (or, with ``lie``, turned by the proper rotation ``lie``:
    wrong axis labels, right handedness)."""
    img = sitk.GetImageFromArray(a)
    img.SetSpacing([float(s) for s in spacing[::-1]])
    R_LPS_A = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    D = R_LPS_A @ R_AG[:, ::-1]
    if lie is not None:
        D = lie @ D
    img.SetDirection([float(v) for v in D.ravel()])
    sitk.WriteImage(img, str(path))
    return path


@pytest.mark.parametrize("perm,flips", LAYOUTS)
def test_frame_and_sides_from_anatomy_in_any_stored_layout(case, perm, flips):
    labels, spacing, _ = case
    a, sp, R_true = stored_as(labels, spacing, perm, flips)
    grid = LabelGrid(a, sp, int(round(np.linalg.det(R_true))), "synthetic")
    ct = import_ct_kidneys(grid)
    np.testing.assert_array_equal(ct.frame.R_AG, R_true)
    assert ct.frame.status == "agree"
    assert sorted(ct.frame.sides) == ["left", "right"]
    assert ct.by_side("right").tumour_ml > 10.0 and ct.by_side("left").tumour_ml == 0.0
    # The right kidney lies 20 mm lower than the left.
    assert ct.right_minus_left_mm() == pytest.approx(-20.0, abs=3.0)
    verdicts = {c["cue"]: c["verdict"] for c in ct.frame.cues}
    for cue in (
        "slice axis",
        "long axes",
        "separation",
        "poles medial",
        "poles posterior",
        "hilum",
        "posterior half",
    ):
        assert verdicts[cue] == "agrees", cue


def test_right_and_left_follow_the_grid_handedness(case):
    """Kidney labels alone cannot tell a body from its mirror image: the chirality of the
    grid does. The same array read as left-handed swaps right and left."""
    labels, spacing, _ = case
    a, sp, R = stored_as(labels, spacing, (0, 1, 2), ())
    right = import_ct_kidneys(LabelGrid(a, sp, 1, "x")).by_side("right")
    mirrored = import_ct_kidneys(LabelGrid(a, sp, -1, "x")).by_side("right")
    assert right.tumour_ml > 10 and mirrored.tumour_ml == 0.0


def test_file_round_trip_ignores_the_headers_axis_labels(case, tmp_path):
    labels, spacing, _ = case
    a, sp, R = stored_as(labels, spacing, (0, 2, 1), (1, 2))  # KiTS-like
    right_header = read_label_grid(_write(tmp_path / "a.nii.gz", a, sp, R))
    assert right_header.handedness == round(np.linalg.det(R)) == -1  # as in KiTS
    np.testing.assert_array_equal(right_header.header_R_AG, R)
    # A header whose axes are all wrong (a proper rotation: the handedness is kept).
    lie = np.array([[0.0, 1, 0], [0, 0, 1], [1, 0, 0]])
    wrong = read_label_grid(_write(tmp_path / "b.nrrd", a, sp, R, lie=lie))
    assert not np.allclose(wrong.header_R_AG, R)
    for grid in (right_header, wrong):
        ct = import_ct_kidneys(grid)
        np.testing.assert_array_equal(ct.frame.R_AG, R)
    report = survey_case(tmp_path / "b.nrrd")
    assert report["header_agrees"] == {"left": False, "superior": False, "anterior": False}
    assert report["usable"] == {"right": "ok", "left": "ok"}


def test_kidney_pose_and_tumour_survive_the_resampling(case):
    """The right kidney (with its tumour) resampled into A at 1 mm: its canonical (PCA)
    frame is the known shape's within 1.5 mm and 3 deg, the tumour keeps its volume."""
    labels, spacing, info = case
    a, sp, R = stored_as(labels, spacing, (2, 0, 1), (1,))
    ct = import_ct_kidneys(LabelGrid(a, sp, int(round(np.linalg.det(R))), "x"))
    k = select_kidney(ct, "right")
    fields = kidney_fields_A(k, ct.frame, voxel=0.001)
    shape = VoxelKidneyShape(fields, "with_tumour", "right")
    # A's origin is the stored grid's voxel 0: where is it in the synthetic frame?
    n = np.array(labels.shape)
    idx0 = np.zeros(3)
    for g in range(3):
        axis = int(np.flatnonzero(R[:, g])[0])
        idx0[axis] = 0 if R[axis, g] > 0 else n[axis] - 1
    shift = (info["origin"] + spacing * idx0) / 1000.0
    refs = ([0.0, 1.0, 0.0], [-1.0, 0.0, 0.0])
    X = mesh_canonical_frame(shape.mesh, *refs)
    # The known shape on a fine grid in the synthetic frame.
    lo, hi = np.array([-150.0, -90.0, -60.0]), np.array([0.0, 50.0, 60.0])
    step = 1.0
    g = np.meshgrid(*[np.arange(a, b, step) for a, b in zip(lo, hi)], indexing="ij")
    pts = np.column_stack([x.ravel() for x in g])
    fine = info["inside"]["right"](pts).reshape(g[0].shape)
    truth = mask_to_mesh(fine, RigidTransform(lo / 1000.0), step / 1000.0)
    X0 = mesh_canonical_frame(truth, *refs)
    d = np.linalg.norm(X.translation() + shift - X0.translation())
    ang = np.degrees(
        np.arccos(
            np.clip((np.trace(X.rotation().matrix().T @ X0.rotation().matrix()) - 1) / 2, -1, 1)
        )
    )
    assert d < 0.0015 and ang < 3.0, (d, ang)
    tumour_ml = 4.0 / 3.0 * np.pi * 16.0**3 / 1000.0
    # Most of the sphere lies outside the kidney (it bulges): at least half is tumour.
    assert 0.5 * tumour_ml < shape.volumes_ml["tumour"] < 1.1 * tumour_ml
    assert shape.volumes_ml["parenchyma"] == pytest.approx(k.parenchyma_ml, rel=0.15)


def test_one_line_errors_name_the_file(case, tmp_path):
    labels, spacing, _ = case
    a, sp, R = stored_as(labels, spacing, (0, 1, 2), ())
    bad = tmp_path / "broken.nii.gz"
    bad.write_bytes(b"not a label map")
    with pytest.raises(ValueError, match=r"broken\.nii\.gz: cannot read it"):
        read_label_grid(bad)
    with pytest.raises(FileNotFoundError, match="missing.nii.gz"):
        read_label_grid(tmp_path / "missing.nii.gz")
    # Cut short (an interrupted copy): SimpleITK would read the missing voxels as background.
    whole = _write(tmp_path / "whole.nii.gz", a, sp, R)
    data = whole.read_bytes()
    (tmp_path / "short.nii.gz").write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(ValueError, match=r"short\.nii\.gz: the file is truncated or corrupt"):
        read_label_grid(tmp_path / "short.nii.gz")
    raw = tmp_path / "whole.nii"
    raw.write_bytes(gzip.decompress(data))
    assert read_label_grid(raw).labels.shape == read_label_grid(whole).labels.shape
    (tmp_path / "short.nii").write_bytes(raw.read_bytes()[:-1000])
    with pytest.raises(ValueError, match=r"short\.nii: the file is truncated: its header"):
        read_label_grid(tmp_path / "short.nii")
    empty = _write(tmp_path / "empty.nii.gz", np.zeros_like(a), sp, R)
    with pytest.raises(ValueError, match=r"empty\.nii\.gz: no kidney labels"):
        read_label_grid(empty)
    other = a.copy()
    other[0, 0, 0] = 7
    with pytest.raises(ValueError, match=r"other\.nii\.gz: labels other than 0/1/2 \(found 7\)"):
        read_label_grid(_write(tmp_path / "other.nii.gz", other, sp, R))
    # Only the right kidney (a nephrectomy on the left).
    one, _, _ = synthetic_ct_case(left=False)
    ct = import_ct_kidneys(LabelGrid(one, spacing, 1, "one.nii.gz"))
    assert [k.side for k in ct.kidneys] == ["right"]
    with pytest.raises(ValueError, match=r"one\.nii\.gz: no left kidney"):
        select_kidney(ct, "left")
    # The left kidney's upper pole cut by the last slice.
    cut = labels[:, :38, :]
    ct = import_ct_kidneys(LabelGrid(np.ascontiguousarray(cut), spacing, 1, "cut.nii.gz"))
    assert select_kidney(ct, "right") is not None
    with pytest.raises(
        ValueError,
        match=r"cut\.nii\.gz: the left kidney is cut by the field "
        r"of view \(.*more than a pole's closing tip: axis 1 high",
    ):
        select_kidney(ct, "left")
    # Cut just past the same pole's tip: the border holds only the closing tip (3 voxels,
    # after 35): the kidney is whole, and its face is reported as a pole on the border.
    tip = labels[:, :41, :]
    ct = import_ct_kidneys(LabelGrid(np.ascontiguousarray(tip), spacing, 1, "tip.nii.gz"))
    left = select_kidney(ct, "left")
    assert left.touches == [] and left.pole_on_border == ["axis 1 high"]
    assert ct.report()["kidneys"][[k.side for k in ct.kidneys].index("left")]["pole_on_border"] == [
        "axis 1 high"
    ]


def test_a_pole_closing_on_the_border_is_not_a_cut():
    # KiTS case 10's right kidney along its slices (3 mm): the last section is a pole's tip.
    assert pole_closes_on_border([356, 4712, 4096, 1309, 930, 515, 77])
    # Cut across the pole's body: the border section is a fifth of the largest.
    assert not pole_closes_on_border([356, 4712, 4096, 1309, 930])
    # Small but not shrinking fast enough to close within a voxel.
    assert not pole_closes_on_border([4712, 930, 515, 300])
    # Shrinking fast but still large: a kidney cut through its middle.
    assert not pole_closes_on_border([1000, 4712, 2000])
    assert not pole_closes_on_border([5]) and not pole_closes_on_border([0, 0])
    # The rule's edges: a tenth of the largest and half the one before are still whole.
    assert pole_closes_on_border([1000, 200, 100])
    assert not pole_closes_on_border([1000, 199, 100])
    assert CLOSING_POLE_MAX_SHARE == pytest.approx(0.10)


def test_undetermined_frames_are_errors_not_guesses(case):
    labels, spacing, _ = case
    comps, _ = kidney_components(LabelGrid(labels, spacing, 1, "x"))
    # A grid whose odd (slice) axis is not the one the kidneys run along.
    with pytest.raises(ValueError, match="superior-inferior axis undetermined"):
        estimate_frame(comps, (128, 128, 50), (3.0, 3.0, 4.0), 1, source="x")
    with pytest.raises(ValueError, match="handedness"):
        estimate_frame(comps, labels.shape, spacing, 0)


def test_right_lower_statistic_counts():
    s = right_lower_statistic([-25.0, -12.0, 3.0, 15.0, None, -40.0])
    assert (s["right_lower"], s["level"], s["right_higher"]) == (3, 1, 1)
    assert s["right_lower_share_of_unequal"] == 0.75


@needs_kits
def test_real_kits_cases_have_an_agreed_frame():
    """Two KiTS cases: every cue agrees, the frame is the one the dataset's headers claim
    (here they are right), and both kidneys are usable."""
    rows = [survey_case(KITS / f"case_0000{i}" / "segmentation.nii.gz") for i in (0, 3)]
    for r in rows:
        assert r["frame"]["status"] == "agree", r["frame"]
        assert r["header_agrees"] == {"left": True, "superior": True, "anterior": True}
        assert r["usable"] == {"right": "ok", "left": "ok"}
        assert r["right_minus_left_mm"] < -10.0  # the right kidney lower
    s = survey_summary(rows)
    assert s["status"]["agree"] == 2 and s["right_lower"]["right_lower"] == 2


@needs_kits
def test_kits_case_10_reaches_the_last_slice_with_its_lower_pole_tip_only():
    """KiTS case 10's right kidney touches the scan's last slice (the inferior end) with a
    77-voxel tip after 515 and 930: whole, usable, and listed as such by the survey."""
    row = survey_case(KITS / "case_00010" / "segmentation.nii.gz")
    assert row["usable"] == {"right": "ok", "left": "ok"}
    right = next(k for k in row["kidneys"] if k["side"] == "right")
    assert right["cut"] == [] and right["pole_on_border"] == ["axis 2 high"]
    assert row["frame"]["axes"]["superior"] == "-2"  # axis 2 high is the inferior end
    s = survey_summary([row])
    assert s["usable"]["right"] == {"ok": 1, "missing": 0, "cut": 0}
    assert len(s["pole_on_border"]) == 1 and s["pole_on_border"][0].endswith("right: axis 2 high")


def test_a_detached_headers_voxels_are_part_of_its_digest(tmp_path):
    """A MetaImage header (.mhd) keeps its voxels in another file: the cache keys (the
    patient's and the real template's, both by file_digest) change when only that file
    changes, so no stale patient or template is reused."""
    from drake_rus.anatomy.cache import detached_data_files, file_digest

    a = np.zeros((6, 7, 8), np.uint8)
    a[2:4, 2:5, 3:6] = 1
    header = tmp_path / "segmentation.mhd"
    sitk.WriteImage(sitk.GetImageFromArray(a), str(header))
    (data,) = detached_data_files(header)
    assert data.is_file() and data.parent == tmp_path
    before = file_digest(header)
    a[2, 2, 3] = 2  # a tumour voxel: only the voxel file changes
    data.write_bytes(a.tobytes())
    assert header.read_text().count("ElementDataFile") == 1
    assert file_digest(header) != before
    assert detached_data_files(tmp_path / "x.nii.gz") == []
