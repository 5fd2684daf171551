"""Canonical kidney frame (seed eq. 13-14): covariance, sign rules, surface moments."""

import numpy as np
import pytest
import trimesh
from pydrake.math import RigidTransform, RotationMatrix
from scipy.spatial.transform import Rotation

from drake_rus.anatomy.canonical_frame import (
    canonical_frame,
    covariance_eigen,
    extents_in_frame,
    mesh_canonical_frame,
    mesh_surface_moments,
)


def _ellipsoid_points(rng, n=4000, axes=(0.055, 0.029, 0.019)):
    d = rng.standard_normal((n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * np.asarray(axes)


def test_covariance_matches_eq13():
    rng = np.random.default_rng(0)
    p = rng.standard_normal((500, 3)) * [3.0, 2.0, 1.0]
    c, evals, V = covariance_eigen(p)
    np.testing.assert_allclose(c, p.mean(axis=0))
    C = np.cov(p.T)  # 1/(M-1) normalisation, like eq. 13
    np.testing.assert_allclose(V @ np.diag(evals) @ V.T, C, atol=1e-12)
    assert evals[0] >= evals[1] >= evals[2]


@pytest.mark.parametrize("trial", range(25))
def test_sign_rules_under_random_rotations(trial):
    rng = np.random.default_rng(100 + trial)
    p_K = _ellipsoid_points(rng)  # x long, y mid, z short in the true frame K
    R = Rotation.random(random_state=trial).as_matrix()
    t = rng.uniform(-0.5, 0.5, 3)
    p_S = p_K @ R.T + t
    # References: the true x and y axes, perturbed by up to ~40 degrees.
    x_ref = R[:, 0] + 0.6 * rng.uniform(-1, 1, 3) * 0.5
    y_ref = R[:, 1] + 0.6 * rng.uniform(-1, 1, 3) * 0.5
    X_SK = canonical_frame(p_S, x_ref, y_ref)
    Rk = X_SK.rotation().matrix()
    assert Rk[:, 0] @ x_ref > 0  # x_k = sgn(v1 . x_ref) v1
    assert Rk[:, 1] @ y_ref > 0  # y_k = sgn(v2 . y_ref) v2
    np.testing.assert_allclose(np.cross(Rk[:, 0], Rk[:, 1]), Rk[:, 2], atol=1e-12)
    np.testing.assert_allclose(Rk.T @ Rk, np.eye(3), atol=1e-12)
    assert np.linalg.det(Rk) == pytest.approx(1.0)
    # The recovered frame is the true one (up to sampling noise of the ellipsoid points).
    assert np.degrees(np.arccos(np.clip((np.trace(Rk.T @ R) - 1) / 2, -1, 1))) < 3.0
    np.testing.assert_allclose(X_SK.translation(), p_S.mean(axis=0), atol=1e-12)


def test_flipped_references_flip_axes():
    rng = np.random.default_rng(1)
    p = _ellipsoid_points(rng)
    X1 = canonical_frame(p, [1, 0, 0], [0, 1, 0]).rotation().matrix()
    X2 = canonical_frame(p, [-1, 0, 0], [0, 1, 0]).rotation().matrix()
    np.testing.assert_allclose(X2[:, 0], -X1[:, 0], atol=1e-12)
    np.testing.assert_allclose(X2[:, 1], X1[:, 1], atol=1e-12)
    np.testing.assert_allclose(X2[:, 2], -X1[:, 2], atol=1e-12)


def test_mesh_surface_moments_match_dense_sampling():
    m = trimesh.creation.icosphere(subdivisions=3)
    m.vertices *= [0.05, 0.03, 0.02]
    m.apply_transform(
        RigidTransform(RotationMatrix.MakeZRotation(0.4), [0.1, -0.2, 0.3]).GetAsMatrix4()
    )
    area, c, C = mesh_surface_moments(m.vertices, m.faces)
    assert area == pytest.approx(m.area)
    pts, _ = trimesh.sample.sample_surface(m, 400000, seed=3)
    np.testing.assert_allclose(c, pts.mean(axis=0), atol=2e-4)
    np.testing.assert_allclose(C, np.cov(pts.T), atol=5e-6)


def test_mesh_canonical_frame_and_extents():
    m = trimesh.creation.icosphere(subdivisions=4)
    m.vertices *= [0.055, 0.029, 0.02]
    R = RotationMatrix.MakeXRotation(0.3).multiply(RotationMatrix.MakeZRotation(1.0))
    X = RigidTransform(R, [0.01, 0.02, 0.03])
    m.apply_transform(X.GetAsMatrix4())
    x_ref = R.matrix()[:, 0]
    y_ref = R.matrix()[:, 1]
    X_SK = mesh_canonical_frame(m, x_ref, y_ref)
    np.testing.assert_allclose(X_SK.rotation().matrix(), R.matrix(), atol=1e-6)
    ext = extents_in_frame(m.vertices, X_SK)
    np.testing.assert_allclose(ext, [0.11, 0.058, 0.04], atol=1e-4)


def test_bad_points_are_rejected():
    with pytest.raises(ValueError, match="points"):
        canonical_frame(np.zeros((2, 3)), [1, 0, 0], [0, 1, 0])
    p = np.random.default_rng(0).standard_normal((10, 3))
    p[3, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        canonical_frame(p, [1, 0, 0], [0, 1, 0])
