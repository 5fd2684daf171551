"""Constrained plane-to-plane ICP (eq. 18-19) on a synthetic, asymmetric kidney-like shape."""

import numpy as np
import pytest
import trimesh
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix

from drake_rus.localization.icp import (
    heuristic_initial_rotation, register_plane_to_plane, rotation_from_vector)


def bean_template(subdivisions: int = 4):
    """Points and normals (K frame, m) of an egg-shaped bean: long axis x, dent on -y."""
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    v = mesh.vertices.copy()
    x, y, z = v.T
    # Superior pole fuller than the inferior one, medial (-y) concavity (hilum).
    sx = np.where(x > 0, 0.058, 0.050)
    v = np.column_stack([sx * x, 0.030 * y, 0.022 * z])
    v[:, 1] += 0.010 * np.exp(-(x / 0.45) ** 2) * (y < 0) * np.abs(y) ** 0.5 * 1.0
    mesh = trimesh.Trimesh(v, mesh.faces, process=True)
    return mesh.vertices - mesh.vertices.mean(axis=0), mesh.vertex_normals, mesh


def angle_between(R_a, R_b) -> float:
    R = R_a.T @ R_b
    return float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))


# The body lies along the base y-axis; the right kidney's lateral direction is the base -x.
SUPERIOR_B = np.array([0.0, 1.0, 0.0])
LATERAL_B = np.array([-1.0, 0.0, 0.0])


def true_pose(rpy_deg=(12.0, -8.0, 15.0), p=(0.52, 0.04, 0.02)):
    R0 = heuristic_initial_rotation(SUPERIOR_B, LATERAL_B)
    return RigidTransform(R0 @ RotationMatrix(RollPitchYaw(np.deg2rad(rpy_deg))), p)


def test_heuristic_initial_rotation():
    R = heuristic_initial_rotation([0, 1, 0], [-1, 0.2, 0]).matrix()
    np.testing.assert_allclose(R[:, 0], [0, 1, 0])
    np.testing.assert_allclose(R[:, 1], [-1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0)
    with pytest.raises(ValueError, match="lateral_B"):
        heuristic_initial_rotation([0, 1, 0], [0, 2, 0])


def test_full_cloud_recovers_known_pose():
    Q, N, _ = bean_template()
    X_BK = true_pose()
    P_B = X_BK.multiply(Q.T).T
    result = register_plane_to_plane(P_B, Q, N, heuristic_initial_rotation(SUPERIOR_B, LATERAL_B),
                                     theta_max=np.deg2rad(2.0))
    position_error = np.linalg.norm(result.X_BK.translation() - X_BK.translation())
    angle = angle_between(result.X_BK.rotation().matrix(), X_BK.rotation().matrix())
    assert position_error < 0.5e-3, position_error
    assert np.rad2deg(angle) < 0.5, np.rad2deg(angle)
    assert result.converged and result.rms_residual < 1e-4
    assert result.inlier_fraction > 0.99


def test_every_iteration_rotation_is_clamped():
    Q, N, _ = bean_template(3)
    X_BK = true_pose((25.0, -20.0, 30.0))
    P_B = X_BK.multiply(Q.T).T
    theta_max = np.deg2rad(0.5)
    result = register_plane_to_plane(P_B, Q, N, heuristic_initial_rotation(SUPERIOR_B, LATERAL_B),
                                     theta_max=theta_max, max_iterations=40)
    assert len(result.max_rotation_steps) > 5
    assert np.all(result.max_rotation_steps <= theta_max + 1e-15)
    # The clamp was active: the unclamped solve wanted bigger steps at the start.
    assert np.isclose(result.max_rotation_steps[0], theta_max)


def test_partial_noisy_cloud_within_tolerance():
    """60% of the kidney along its long axis, 1 mm noise: 3 mm and 3 deg.

    The tolerance reflects what a partial view constrains: the missing pole leaves the
    long-axis position determined only by the curvature of the seen part.
    """
    Q, N, _ = bean_template()
    X_BK = true_pose()
    rng = np.random.default_rng(0)
    x_extent = Q[:, 0].max() - Q[:, 0].min()
    seen = Q[:, 0] > Q[:, 0].max() - 0.6 * x_extent
    P_B = X_BK.multiply(Q[seen].T).T + rng.normal(scale=0.001, size=(seen.sum(), 3))
    result = register_plane_to_plane(P_B, Q, N, heuristic_initial_rotation(SUPERIOR_B, LATERAL_B))
    position_error = np.linalg.norm(result.X_BK.translation() - X_BK.translation())
    angle = angle_between(result.X_BK.rotation().matrix(), X_BK.rotation().matrix())
    assert position_error < 3e-3, position_error
    assert np.rad2deg(angle) < 3.0, np.rad2deg(angle)
    # The covariance is a proper covariance and shrinks with more data.
    assert np.all(np.linalg.eigvalsh(result.covariance) > 0)


def test_seed_zero_translation_is_available_and_slower():
    Q, N, _ = bean_template(3)
    X_BK = true_pose()
    P_B = X_BK.multiply(Q.T).T
    R0 = heuristic_initial_rotation(SUPERIOR_B, LATERAL_B)
    ours = register_plane_to_plane(P_B, Q, N, R0, init_translation="centroid")
    seed = register_plane_to_plane(P_B, Q, N, R0, init_translation="zero")
    err = lambda r: np.linalg.norm(r.X_BK.translation() - X_BK.translation())
    # The unclamped translation lets the seed's t0 = 0 recover too, in more iterations.
    assert err(ours) < 1e-3 and err(seed) < 1e-3
    assert ours.iterations < seed.iterations


def test_deformable_fit_recovers_shape_mode():
    Q, N, _ = bean_template(3)
    # One shape mode: lengthen along x.
    mode = np.zeros_like(Q)
    mode[:, 0] = Q[:, 0] / np.abs(Q[:, 0]).max()
    modes = mode[None]
    b_true = 0.008  # 8 mm at the poles
    X_BK = true_pose((5.0, -4.0, 6.0))
    P_B = X_BK.multiply((Q + b_true * mode).T).T
    R0 = heuristic_initial_rotation(SUPERIOR_B, LATERAL_B)
    rigid = register_plane_to_plane(P_B, Q, N, R0)
    deform = register_plane_to_plane(P_B, Q, N, R0, shape_modes_K=modes,
                                     shape_variances=np.array([0.01**2]))
    assert deform.shape_coefficients[0] == pytest.approx(b_true, abs=1.5e-3)
    assert deform.rms_residual < rigid.rms_residual


@pytest.mark.parametrize("bad, match", [
    (np.zeros((3, 3)), "at least 6 points"),
    (np.zeros((10, 2)), r"\(N, 3\)"),
    (np.full((10, 3), np.nan), "NaN"),
])
def test_bad_input(bad, match):
    Q, N, _ = bean_template(2)
    with pytest.raises(ValueError, match=match):
        register_plane_to_plane(bad, Q, N, RotationMatrix())


def test_rotation_from_vector_is_exact():
    w = np.array([0.3, -0.2, 0.5])
    R = rotation_from_vector(w)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(RotationMatrix(R).ToAngleAxis().angle(), np.linalg.norm(w))
