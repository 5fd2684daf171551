"""Kidney template (seed II-D): resampling, alignment, correspondence, mean shape (eq. 15),
shape model, convergence, file round trip, and a ground truth the pipeline cannot cheat."""

import json
import sys
import tempfile

import numpy as np
import pytest
import trimesh
from pydrake.math import RigidTransform, RotationMatrix
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from drake_rus.anatomy.canonical_frame import mesh_canonical_frame
from drake_rus.anatomy.kidney_shape import KidneyShape, sample_kidney_shape_params
from drake_rus.anatomy.rasterize import mesh_mask_on_aligned_grid
from drake_rus.cli import main as cli_main
from drake_rus.template import load_template
from drake_rus.template.builder import (
    TemplateResult,
    align_to_reference,
    axis_agreement_deg,
    build_template,
    centred_shapes,
    convergence,
    correspond,
    farthest_point_sampling,
    feature_ransac,
    mean_shape,
    order_free_sum,
    point_area_weights,
    point_to_plane_icp,
    save_template,
    save_template_to_cache,
    shape_model,
    subject_from_mask,
    subject_from_mesh,
    write_metadata_json,
    write_npz_reproducibly,
)
from drake_rus.template.io import DEFAULT_TEMPLATE_PATH


def test_mean_shape_is_eq15():
    rng = np.random.default_rng(0)
    a = rng.standard_normal((5, 7, 3))
    np.testing.assert_allclose(mean_shape(a), a.sum(axis=0) / 5)
    with pytest.raises(ValueError, match="aligned shapes"):
        mean_shape(np.zeros((0, 3)))


def test_shape_model_recovers_planted_modes():
    rng = np.random.default_rng(1)
    base = rng.standard_normal((50, 3))
    m1 = rng.standard_normal((50, 3))
    m1 /= np.linalg.norm(m1)
    m2 = rng.standard_normal((50, 3))
    m2 -= (m2.ravel() @ m1.ravel()) * m1
    m2 /= np.linalg.norm(m2)
    b = rng.standard_normal((40, 2)) * [3.0, 1.0]
    shapes = (
        base + b[:, :1, None] * m1 + b[:, 1:, None] * m2 + 1e-3 * rng.standard_normal((40, 50, 3))
    )
    mean, modes, var, frac = shape_model(shapes, keep=0.95)
    assert len(var) == 2
    assert abs(modes[0].ravel() @ m1.ravel()) > 0.99
    assert var[0] == pytest.approx(np.var(b[:, 0], ddof=1), rel=0.05)
    assert np.cumsum(frac)[-1] >= 0.95


def test_centred_shapes_give_centroid_free_orthonormal_modes():
    """Shapes that differ by a deformation and by a translation each (the scatter of kNN
    correspondence): PCA of the raw shapes carries the translation in its modes; PCA of
    the centred shapes gives modes that do not move the centroid, still orthonormal, the
    same mean, and the deformation's mode."""
    rng = np.random.default_rng(5)
    base = rng.standard_normal((60, 3)) * 0.02
    m1 = rng.standard_normal((60, 3))
    m1 -= m1.mean(axis=0)  # a pure deformation
    m1 /= np.linalg.norm(m1)
    b = rng.standard_normal(30) * 0.01
    shift = rng.standard_normal((30, 1, 3)) * 0.002
    shapes = base + b[:, None, None] * m1 + shift
    _, raw, _, _ = shape_model(shapes, keep=0.99)
    assert np.abs(raw.mean(axis=1)).max() > 1e-3  # the raw modes translate
    centred = centred_shapes(shapes)
    np.testing.assert_allclose(mean_shape(centred), mean_shape(shapes), atol=1e-15)
    mean, modes, var, _ = shape_model(centred, keep=0.99)
    assert np.abs(modes.mean(axis=1)).max() < 1e-12
    G = np.einsum("imk,jmk->ij", modes, modes)
    np.testing.assert_allclose(G, np.eye(len(modes)), atol=1e-12)
    assert len(var) == 1 and abs(modes[0].ravel() @ m1.ravel()) > 0.999


def test_point_area_weights_give_the_surface_centroid():
    """An ellipsoid's surface sampled four times as densely on its +x half (as kNN
    correspondence can leave a template's points): the plain mean of the points lies
    several mm off the centre, the area-weighted one within 0.3 mm."""
    rng = np.random.default_rng(6)
    u = rng.standard_normal((20000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    keep = (u[:, 0] > 0) | (rng.uniform(size=len(u)) < 0.25)
    p = u[keep][:3000] * [0.055, 0.03, 0.025]
    w = point_area_weights(p)
    assert w.sum() == pytest.approx(1.0)
    assert np.linalg.norm(p.mean(axis=0)) > 0.008
    assert np.linalg.norm(w @ p) < 0.0003


def test_axis_agreement_flags_an_upside_down_subject():
    up = np.eye(3)
    tilted = RotationMatrix.MakeZRotation(0.3).matrix()
    flipped = RotationMatrix.MakeZRotation(np.pi).matrix()  # superior on inferior
    d = axis_agreement_deg([up, tilted, flipped])
    np.testing.assert_allclose(d, [0.0, np.degrees(0.3), 180.0], atol=1e-9)


def test_convergence_decreases_with_n():
    rng = np.random.default_rng(2)
    shapes = rng.standard_normal((20, 100, 3)) * 0.003
    conv = convergence(shapes)
    ch = np.asarray(conv["change"][1:])
    assert np.mean(ch[-5:]) < 0.5 * np.mean(ch[:3])
    assert conv["to_final"][-1] == 0.0
    assert conv["to_final"][0] > conv["to_final"][10]


def test_farthest_point_sampling_spreads_points():
    rng = np.random.default_rng(3)
    p = rng.uniform(0, 1, (3000, 3))
    idx = farthest_point_sampling(p, 100)
    assert len(set(idx.tolist())) == 100
    d_fps = cKDTree(p[idx]).query(p[idx], k=2)[0][:, 1].min()
    d_rnd = cKDTree(p[:100]).query(p[:100], k=2)[0][:, 1].min()
    assert d_fps > 2 * d_rnd


def test_alignment_recovers_known_transform():
    shape = KidneyShape(sample_kidney_shape_params(np.random.default_rng(5)))
    sub = subject_from_mesh(shape.mesh, [1, 0, 0], [0, 1, 0])
    idx = farthest_point_sampling(sub.points, 400)  # copies: every triple passes
    ref_p, ref_n = sub.points[idx], sub.normals[idx]
    R = Rotation.from_rotvec([0.08, -0.05, 0.1]).as_matrix()
    t = np.array([0.004, -0.003, 0.002])
    src_p = (ref_p - t) @ R  # ref = R src + t
    src_n = ref_n @ R
    T, info = align_to_reference(src_p, src_n, ref_p, ref_n, use_features=True, seed=0)
    np.testing.assert_allclose(T[:3, :3], R, atol=2e-3)
    np.testing.assert_allclose(T[:3, 3], t, atol=5e-4)
    assert info["fitness"] > 0.95


def test_order_free_sum_is_the_same_in_any_order():
    rng = np.random.default_rng(8)
    terms = rng.normal(size=(5000, 6)) * np.logspace(-6, 2, 5000)[:, None]
    total = order_free_sum(terms)
    np.testing.assert_allclose(total, terms.sum(axis=0), rtol=1e-10)  # 2^-40 of the largest
    for _ in range(5):
        assert np.array_equal(order_free_sum(terms[rng.permutation(len(terms))]), total)
    assert np.array_equal(order_free_sum(np.zeros((0, 3))), np.zeros(3))
    assert np.array_equal(order_free_sum(np.zeros((4, 2))), np.zeros(2))


def test_order_free_sum_refuses_non_finite_terms_and_sums_tiny_ones_exactly():
    """A NaN or an inf among the terms is an error, not a sum of 0 or of garbage integers
    (the old grid made NaN's sum 0 and cast inf to int64's minimum); subnormal terms, below
    the grid's 2^-40 of a subnormal, are still summed exactly."""
    for bad in (np.nan, np.inf, -np.inf):
        with pytest.raises(ValueError, match="order_free_sum: terms must be finite"):
            order_free_sum([[bad, 0.0], [1.0, 2.0]])
    tiny = np.array([[5e-324], [5e-324], [1e-320]])
    assert np.array_equal(order_free_sum(tiny), [1e-323 + 1e-320])


def test_point_to_plane_icp_refuses_non_finite_input():
    """A NaN normal (say, a mean of opposite normals) made the normal equations NaN, their
    fixed-point sum 0 and the ICP return its start as if aligned; now one line names it."""
    rng = np.random.default_rng(1)
    ref = rng.normal(size=(50, 3)) * 0.02
    nrm = ref / np.linalg.norm(ref, axis=1, keepdims=True)
    bad = nrm.copy()
    bad[7] = np.nan
    with pytest.raises(ValueError, match="ref_nrm: 1 of 50 rows contain NaN"):
        point_to_plane_icp(ref + 0.001, ref, bad, np.eye(4), 0.01)
    with pytest.raises(ValueError, match="ref_nrm: expected one normal per reference point"):
        point_to_plane_icp(ref, ref, nrm[:10], np.eye(4), 0.01)
    with pytest.raises(ValueError, match=r"src_pts: expected an \(N, 3\) array"):
        point_to_plane_icp(ref[:, :2], ref, nrm, np.eye(4), 0.01)
    with pytest.raises(ValueError, match="T0: expected a finite 4x4"):
        point_to_plane_icp(ref, ref, nrm, np.eye(3), 0.01)


def test_point_to_plane_icp_does_not_depend_on_the_order_of_the_points():
    """The builder's ICP gives the same transform, to the last bit, for the source points in
    any order (Open3D's does not: its sums follow the order and its threads), so a template
    built twice from the same kidneys is the same template."""
    shape = KidneyShape(sample_kidney_shape_params(np.random.default_rng(6)))
    sub = subject_from_mesh(shape.mesh, [1, 0, 0], [0, 1, 0])
    idx = farthest_point_sampling(sub.points, 1200)
    ref_p, ref_n = sub.points[idx], sub.normals[idx]
    R = Rotation.from_rotvec([0.03, -0.02, 0.04]).as_matrix()
    t = np.array([0.002, -0.001, 0.0015])
    src = (sub.points[::7] - t) @ R  # ref = R src + t, other points than the reference's
    T, fitness, rmse = point_to_plane_icp(src, ref_p, ref_n, np.eye(4), 0.01)
    np.testing.assert_allclose(T[:3, :3], R, atol=2e-3)
    np.testing.assert_allclose(T[:3, 3], t, atol=5e-4)
    assert fitness > 0.95 and rmse < 2e-3  # point to point, to a sparser reference
    rng = np.random.default_rng(0)
    for _ in range(3):
        order = rng.permutation(len(src))
        T2, fitness2, rmse2 = point_to_plane_icp(src[order], ref_p, ref_n, np.eye(4), 0.01)
        assert np.array_equal(T2, T) and (fitness2, rmse2) == (fitness, rmse)
    # Nothing within reach: the start comes back, with no pairs.
    T_far, fitness_far, _ = point_to_plane_icp(src + 1.0, ref_p, ref_n, np.eye(4), 0.01)
    assert np.array_equal(T_far, np.eye(4)) and fitness_far == 0.0


def test_point_to_plane_icp_moves_along_what_a_symmetric_surface_determines():
    """On a cylinder the pairs fix the shift across the axis but not along it: the normal
    equations are singular (exactly, with exact normals; nearly, with normals off by 1e-7).
    The ICP still recovers the shift across the axis, as Open3D's does, and stays put along
    it: it used to stop at its start (singular) or jump kilometres along the axis."""
    rng = np.random.default_rng(0)
    th, x = rng.uniform(0, 2 * np.pi, 4000), rng.uniform(-0.05, 0.05, 4000)
    cyl = np.c_[x, 0.02 * np.cos(th), 0.02 * np.sin(th)]
    exact = np.c_[0 * x, np.cos(th), np.sin(th)]
    rough = exact + 1e-7 * rng.standard_normal(exact.shape)
    rough /= np.linalg.norm(rough, axis=1, keepdims=True)
    t = np.array([0.0, 0.002, 0.001])
    for nrm in (exact, rough):
        T, fitness, rmse = point_to_plane_icp(cyl[::3] - t, cyl, nrm, np.eye(4), 0.01)
        np.testing.assert_allclose(T[1:3, 3], t[1:], atol=2e-5)
        assert abs(T[0, 3]) < 1e-4 and fitness == 1.0 and rmse < 5e-5


def test_feature_ransac_finds_a_large_turn_the_same_way_every_time():
    """FPFH matches + RANSAC recover a 20 deg turn and 8 mm shift (beyond ICP's reach), and
    the same inputs give the same transform to the bit (Open3D's RANSAC did not)."""
    import open3d as o3d

    shape = KidneyShape(sample_kidney_shape_params(np.random.default_rng(9)))
    sub = subject_from_mesh(shape.mesh, [1, 0, 0], [0, 1, 0])
    idx = farthest_point_sampling(sub.points, 800)
    ref_p, ref_n = sub.points[idx], sub.normals[idx]
    R = Rotation.from_rotvec(np.radians(20) * np.array([0.3, -0.5, 0.81]) / 1.0).as_matrix()
    t = np.array([0.008, -0.004, 0.003])
    src_p, src_n = (ref_p - t) @ R, ref_n @ R  # ref = R src + t

    def fpfh(p, n):
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
        pc.normals = o3d.utility.Vector3dVector(n)
        param = o3d.geometry.KDTreeSearchParamHybrid(radius=0.012, max_nn=100)
        return np.asarray(o3d.pipelines.registration.compute_fpfh_feature(pc, param).data).T

    f_src, f_ref = fpfh(src_p, src_n), fpfh(ref_p, ref_n)
    T = feature_ransac(src_p, ref_p, f_src, f_ref, 0.01, seed=3, iterations=1000)
    assert np.degrees(np.arccos((np.trace(T[:3, :3].T @ R) - 1) / 2)) < 5.0
    assert np.linalg.norm(T[:3, 3] - t) < 0.004
    again = feature_ransac(src_p, ref_p, f_src, f_ref, 0.01, seed=3, iterations=1000)
    assert np.array_equal(again, T)
    # No match that passes the checkers: the identity.
    far = feature_ransac(src_p, ref_p * 3.0, f_src, f_ref, 0.001, seed=3, iterations=200)
    assert np.array_equal(far, np.eye(4))


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"iterations": 0}, "iterations"),
        ({"iterations": -5}, "iterations"),
        ({"iterations": 2.5}, "iterations"),
        ({"iterations": True}, "iterations"),
        ({"chunk": 0}, "chunk"),
        ({"chunk": -1}, "chunk"),
        ({"chunk": 10.0}, "chunk"),
    ],
)
def test_feature_ransac_refuses_a_count_that_is_not_a_positive_integer(kwargs, name):
    """0 iterations silently gave the identity, a zero chunk failed in range() and a float
    count in range(): each is one line naming the argument."""
    p = np.random.default_rng(0).normal(size=(20, 3))
    f = np.random.default_rng(1).normal(size=(20, 33))
    with pytest.raises(ValueError, match=f"feature_ransac: {name}: expected a positive integer"):
        feature_ransac(p, p, f, f, 0.01, **kwargs)


def test_correspond_reindexes_by_nearest_neighbour():
    ref = np.array([[0, 0, 0], [1, 0, 0]], float)
    pts = np.array([[1.1, 0, 0], [0.05, 0, 0], [5, 5, 5]], float)
    nrm = np.eye(3)
    P, N = correspond(ref, pts, nrm)
    np.testing.assert_allclose(P, [[0.05, 0, 0], [1.1, 0, 0]])
    np.testing.assert_allclose(N, [[0, 1, 0], [1, 0, 0]])


def test_template_reproduces_known_correspondence_mean():
    """Kidneys from the parametric generator share vertex topology (vertex j = same landmark),
    so their true mean shape is known without any registration. The builder sees only masks
    in random poses and must recover that mean within 1 mm."""
    truth, subjects = [], []
    for i in range(6):
        rng = np.random.default_rng(50 + i)
        shape = KidneyShape(sample_kidney_shape_params(rng))
        m = shape.mesh.copy()
        R = Rotation.random(random_state=i).as_matrix()
        m.apply_transform(
            RigidTransform(RotationMatrix(R), rng.uniform(-0.2, 0.2, 3)).GetAsMatrix4()
        )
        x_ref, y_ref = R[:, 0], R[:, 1]
        X_SK = mesh_canonical_frame(m, x_ref, y_ref)
        truth.append(X_SK.inverse().multiply(m.vertices.T).T)
        mask, X_SV = mesh_mask_on_aligned_grid(m, 0.001)
        subjects.append(subject_from_mask(mask, X_SV, 0.001, x_ref, y_ref, name=str(i)))
    true_mean = trimesh.Trimesh(np.mean(truth, axis=0), shape.mesh.faces, process=False)
    true_mean.apply_transform(
        mesh_canonical_frame(true_mean, [1, 0, 0], [0, 1, 0]).inverse().GetAsMatrix4()
    )
    res = build_template(subjects, n_points=1500, progress=False)
    # Modes deform about the centroid; every subject aligned the right way up.
    assert np.abs(res.modes.mean(axis=1)).max() < 1e-12
    assert max(res.meta["x_axis_agreement_deg"]) < 30.0
    # No registration between template and truth: both in their canonical frames.
    _, d, _ = trimesh.proximity.closest_point(true_mean, res.points)
    assert d.mean() < 0.001
    _, idx = cKDTree(res.points).query(true_mean.vertices)
    back = np.abs(np.sum((true_mean.vertices - res.points[idx]) * res.normals[idx], axis=1))
    assert back.mean() < 0.001
    # Normals are unit and outward.
    np.testing.assert_allclose(np.linalg.norm(res.normals, axis=1), 1.0, atol=1e-9)
    assert np.mean(np.sum(res.points * res.normals, axis=1) > 0) > 0.85


def test_the_same_kidneys_give_the_same_template_file(tmp_path):
    """Two builds of the same kidneys save to the same bytes (a study's key and a
    benchmark's digest hash the file), and the build's timings, kept beside it in the
    .json, still load with it."""
    rng = np.random.default_rng(11)
    subjects = [
        subject_from_mesh(
            KidneyShape(sample_kidney_shape_params(rng)).mesh, [1, 0, 0], [0, 1, 0], name=str(i)
        )
        for i in range(3)
    ]
    paths = []
    for k in range(2):
        res = build_template(subjects, n_points=300, refine_passes=1, progress=False)
        paths.append(save_template(res, tmp_path / f"t{k}.npz", {"total_seconds": 1.5 + k}))
    assert paths[0].read_bytes() == paths[1].read_bytes()
    t = load_template(paths[1])
    assert t.meta["total_seconds"] == 2.5 and t.meta["build_seconds"] >= 0
    assert "total_seconds" not in json.loads(str(np.load(paths[1])["metadata"]))
    np.testing.assert_array_equal(t.points, load_template(paths[0]).points)


def test_write_npz_reproducibly_leaves_nothing_half_written(tmp_path):
    """An array that cannot be stored (object dtype) fails after the first entries are
    written: the file that was there stays as it was, and no temporary is left. (It used to
    open the path itself: the old file was truncated and a half-written zip left.)"""
    path = tmp_path / "t.npz"
    write_npz_reproducibly(path, {"a": np.arange(3.0)})
    before = path.read_bytes()
    with pytest.raises(ValueError, match="allow_pickle"):
        write_npz_reproducibly(path, {"a": np.arange(5.0), "b": np.array([{"x": 1}], dtype=object)})
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["t.npz"]
    np.testing.assert_array_equal(np.load(path)["a"], np.arange(3.0))


def test_write_npz_reproducibly_gives_the_same_bytes_on_windows(tmp_path, monkeypatch):
    """zipfile marks an entry as made on Windows when run there: the same arrays gave
    another file, and another digest, on another operating system."""
    arrays = {"a": np.arange(4.0), "metadata": np.asarray("{}")}
    write_npz_reproducibly(tmp_path / "unix.npz", arrays)
    monkeypatch.setattr(sys, "platform", "win32")
    write_npz_reproducibly(tmp_path / "windows.npz", arrays)
    assert (tmp_path / "windows.npz").read_bytes() == (tmp_path / "unix.npz").read_bytes()


def _ellipsoid_template(meta: dict) -> TemplateResult:
    """A minimal valid template (an ellipsoid, no modes), built without registration."""
    k = np.arange(400) + 0.5
    phi, z = np.pi * (1 + 5**0.5) * k, 1 - 2 * k / 400
    u = np.c_[np.sqrt(1 - z**2) * np.cos(phi), np.sqrt(1 - z**2) * np.sin(phi), z]
    axes = np.array([0.055, 0.03, 0.025])
    n = u / axes
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    conv = {"n": [1], "change": [float("nan")], "to_final": [0.0]}
    return TemplateResult(
        points=u * axes,
        normals=n,
        aligned=(u * axes)[None],
        modes=np.zeros((0, 400, 3)),
        variances=np.zeros(0),
        explained=np.zeros(0),
        convergence=conv,
        meta=dict(meta, convergence=conv),
    )


def test_load_template_takes_timings_only_from_its_own_json(tmp_path):
    """The timings live in the .json beside the .npz; a .json that describes another
    template (left by an earlier build, or beside an .npz copied over another) is not
    merged: its timings used to be reported as this template's."""
    a = save_template(_ellipsoid_template({"n_subjects": 1}), tmp_path / "a.npz")
    write_metadata_json(a, {**json.loads(a.with_suffix(".json").read_text()), "total_seconds": 1.0})
    assert load_template(a).meta["total_seconds"] == 1.0  # its own .json
    b = save_template(
        _ellipsoid_template({"n_subjects": 2}), tmp_path / "b.npz", {"total_seconds": 9.0}
    )
    a.with_suffix(".json").write_bytes(b.with_suffix(".json").read_bytes())
    meta = load_template(a).meta
    assert "total_seconds" not in meta and meta["n_subjects"] == 1
    assert load_template(b).meta["total_seconds"] == 9.0


def test_the_template_study_reads_the_build_time_as_load_template_does(tmp_path):
    """The template study's "built in N s" came from whatever .json sat beside the file."""
    from drake_rus.experiments.cli import _build_seconds

    a = save_template(_ellipsoid_template({"n_subjects": 1}), tmp_path / "a.npz")
    b = save_template(
        _ellipsoid_template({"n_subjects": 2}), tmp_path / "b.npz", {"total_seconds": 9.0}
    )
    assert _build_seconds(b) == 9.0 and _build_seconds(a) is None
    a.with_suffix(".json").write_bytes(b.with_suffix(".json").read_bytes())
    assert _build_seconds(a) is None  # another build's .json
    assert _build_seconds(tmp_path / "missing.npz") is None


def test_save_template_writes_nothing_when_the_json_cannot_be(tmp_path):
    """A timing JSON cannot hold (a numpy float32) used to fail only after the new .npz had
    replaced the old one, which was left beside the old build's .json."""
    path = save_template(_ellipsoid_template({"n_subjects": 1}), tmp_path / "t.npz")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    with pytest.raises(TypeError, match="float32"):
        save_template(
            _ellipsoid_template({"n_subjects": 2}), path, {"total_seconds": np.float32(1.5)}
        )
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_save_load_round_trip(tmp_path, capsys, monkeypatch):
    rng = np.random.default_rng(4)
    subjects = [
        subject_from_mesh(
            KidneyShape(sample_kidney_shape_params(rng)).mesh, [1, 0, 0], [0, 1, 0], name=str(i)
        )
        for i in range(3)
    ]
    res = build_template(subjects, n_points=400, refine_passes=1, progress=False)
    out = save_template(res, tmp_path / "t.npz", {"note": "test"})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.json", "t.npz"]  # no temporaries
    assert json.loads((tmp_path / "t.json").read_text())["note"] == "test"
    t = load_template(out)
    np.testing.assert_allclose(t.points, res.points)
    assert t.modes.shape[1:] == t.points.shape and len(t.variances) == len(t.modes)
    assert t.meta["note"] == "test" and t.meta["n_subjects"] == 3
    np.testing.assert_allclose(t.shape(np.zeros(len(t.variances))), t.points)
    with pytest.raises(ValueError, match="coefficients"):
        t.shape(np.zeros(len(t.variances) + 1))
    bad = tmp_path / "bad.npz"
    bad.write_text("not a zip")
    with pytest.raises(ValueError, match="bad.npz"):
        load_template(bad)
    # Metadata that is JSON but not an object: one line naming it (was an AttributeError).
    arrays = dict(np.load(out))
    arrays["metadata"] = np.asarray("[1, 2]")
    write_npz_reproducibly(bad, arrays)
    with pytest.raises(ValueError, match="'metadata': expected a JSON object, got list"):
        load_template(bad)

    # A cache folder that cannot be written: the template goes to a temporary file, with a
    # warning; a path the user asked for is never silently replaced. (The temporary folder
    # is made under tmp_path, so the test leaves nothing in the machine's /tmp.)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    blocked = tmp_path / "a_file" / "cache" / "t.npz"
    (tmp_path / "a_file").write_text("not a folder")
    fallback = save_template_to_cache(res, blocked, {"note": "x"}, asked_for=False)
    assert "not writable" in capsys.readouterr().err
    assert fallback != blocked and fallback.name == "t.npz" and fallback.is_file()
    assert fallback.parent.parent == tmp_path
    np.testing.assert_allclose(load_template(fallback).points, res.points)
    with pytest.raises(OSError):
        save_template_to_cache(res, blocked, {"note": "x"}, asked_for=True)
    with pytest.raises(FileNotFoundError, match="template build"):
        load_template(tmp_path / "missing.npz")


def test_shipped_template():
    t = load_template()
    assert t.points.shape == t.normals.shape and t.points.shape[1] == 3
    assert t.meta["n_subjects"] == 20
    # Canonical frame: centred, long axis x, then y, then z.
    np.testing.assert_allclose(t.points.mean(axis=0), 0.0, atol=1e-9)
    ext = np.ptp(t.points, axis=0)
    assert ext[0] > ext[1] > ext[2]
    assert 0.095 < ext[0] < 0.125
    assert np.sum(t.explained if hasattr(t, "explained") else t.meta["explained"]) >= 0.95
    ch = np.asarray(t.convergence["change"][1:])
    assert np.mean(ch[-5:]) < 0.5 * np.mean(ch[:3])
    assert DEFAULT_TEMPLATE_PATH.with_name("kidney_template_convergence.png").is_file()


def test_cli_template_build_small(tmp_path, capsys):
    out = tmp_path / "t.npz"
    rc = cli_main(
        [
            "template",
            "build",
            "--n",
            "3",
            "--points",
            "300",
            "--voxel-mm",
            "2",
            "--out",
            str(out),
            "--quiet",
        ]
    )
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["n_subjects"] == 3 and out.is_file()
    assert (tmp_path / "t_convergence.png").is_file()
    assert cli_main(["template", "build", "--n", "0", "--out", str(out)]) == 2
    assert "--n" in capsys.readouterr().err
    assert cli_main(["template", "info", str(tmp_path / "nope.npz")]) == 2
