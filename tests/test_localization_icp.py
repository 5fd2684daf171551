"""Constrained plane-to-plane ICP (eq. 18-19) on a synthetic, asymmetric kidney-like shape."""

import numpy as np
import pytest
import trimesh
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix

from drake_rus.localization.icp import (
    heuristic_initial_rotation,
    register_plane_to_plane,
    rotation_from_vector,
)


def bean_template(subdivisions: int = 4):
    """Points and normals (K frame, m) of an egg-shaped bean: long axis x, dent on -y."""
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    v = mesh.vertices.copy()
    x, y, z = v.T
    # Superior pole fuller than the inferior one, medial (-y) concavity (hilum).
    sx = np.where(x > 0, 0.058, 0.050)
    v = np.column_stack([sx * x, 0.030 * y, 0.022 * z])
    v[:, 1] += 0.010 * np.exp(-((x / 0.45) ** 2)) * (y < 0) * np.abs(y) ** 0.5 * 1.0
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
    result = register_plane_to_plane(
        P_B, Q, N, heuristic_initial_rotation(SUPERIOR_B, LATERAL_B), theta_max=np.deg2rad(2.0)
    )
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
    result = register_plane_to_plane(
        P_B,
        Q,
        N,
        heuristic_initial_rotation(SUPERIOR_B, LATERAL_B),
        theta_max=theta_max,
        max_iterations=40,
    )
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

    def err(r):
        return np.linalg.norm(r.X_BK.translation() - X_BK.translation())

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
    deform = register_plane_to_plane(
        P_B, Q, N, R0, shape_modes_K=modes, shape_variances=np.array([0.01**2])
    )
    assert deform.shape_coefficients[0] == pytest.approx(b_true, abs=1.5e-3)
    assert deform.rms_residual < rigid.rms_residual


@pytest.mark.parametrize(
    "bad, match",
    [
        (np.zeros((3, 3)), "at least 6 points"),
        (np.zeros((10, 2)), r"\(N, 3\)"),
        (np.full((10, 3), np.nan), "NaN"),
    ],
)
def test_bad_input(bad, match):
    Q, N, _ = bean_template(2)
    with pytest.raises(ValueError, match=match):
        register_plane_to_plane(bad, Q, N, RotationMatrix())


def test_rotation_from_vector_is_exact():
    w = np.array([0.3, -0.2, 0.5])
    R = rotation_from_vector(w)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(RotationMatrix(R).ToAngleAxis().angle(), np.linalg.norm(w))


# ------------------------------------------------------------------ stopping: cycles
# A tiny template (four points with normals) and six points (mm) on which plane-to-plane
# ICP alternates between two poses for ever: each pose's nearest neighbours pull the
# solve to the other one, the error alternates between 1.02 and 0.85 mm RMS, neither the
# error-change test nor the step test ever fires.
CYCLE_Q_MM = [[8, -1, 0], [-8, 3, -7], [4, -4, -10], [-8, 9, 4]]
CYCLE_N = [[0, 0, 1], [0, 0, 1], [1, 0, 1], [0, 1, 1]]
CYCLE_P_MM = [[-4, 1, 1], [8, 5, 6], [-4, -5, 1], [-3, 10, -3], [-4, 9, 10], [4, 4, 6]]


def _cycle_case():
    N = np.asarray(CYCLE_N, float)
    return (
        np.asarray(CYCLE_P_MM, float) / 1000,
        np.asarray(CYCLE_Q_MM, float) / 1000,
        N / np.linalg.norm(N, axis=1, keepdims=True),
    )


def test_a_two_cycle_runs_to_the_cap_without_detection():
    P, Q, N = _cycle_case()
    r = register_plane_to_plane(P, Q, N, RotationMatrix(), max_iterations=100, cycle_max_period=0)
    assert r.iterations == 100 and not r.converged and r.stop_reason == "iteration cap"
    e = r.errors[-8:]
    np.testing.assert_allclose(e[2:], e[:-2], rtol=1e-9)  # period 2 ...
    assert abs(e[-1] - e[-2]) > 1e-8  # ... not a fixed point


def test_a_two_cycle_is_caught():
    P, Q, N = _cycle_case()
    r = register_plane_to_plane(P, Q, N, RotationMatrix(), max_iterations=100)
    assert r.stop_reason == "cycle" and not r.converged
    assert r.cycle_period == 2 and r.iterations < 30
    # The member of the cycle with the lower error is returned, with the cycle's spread.
    assert r.rms_residual**2 == pytest.approx(min(r.errors[-2:]), rel=1e-9)
    assert r.cycle_translation_spread > 1e-3 and r.cycle_rotation_spread > np.deg2rad(1.0)


def test_a_clean_registration_stops_as_converged():
    Q, N, _ = bean_template(3)
    P_B = true_pose().multiply(Q.T).T
    R0 = heuristic_initial_rotation(SUPERIOR_B, LATERAL_B)
    for kwargs in (
        {},
        {"shape_modes_K": np.zeros((1,) + Q.shape), "shape_variances": np.array([1e-4])},
    ):
        r = register_plane_to_plane(P_B, Q, N, R0, **kwargs)
        assert r.converged and r.stop_reason == "converged" and r.cycle_period == 0
        assert r.cycle_translation_spread == 0.0 and r.iterations < 100


def test_cycle_detector_needs_a_return_after_an_excursion():
    from drake_rus.localization.icp import _cycle_period

    def state(x, angle=0.0):
        return (
            rotation_from_vector(np.array([0.0, 0.0, angle])),
            np.array([x, 0.0, 0.0]),
            np.zeros(0),
        )

    # Slow monotone convergence and a damped oscillation (equal errors: the poses decide):
    # not cycles.
    for ratio in (0.97, -0.8):
        states = [state(0.01 * ratio**k) for k in range(60)]
        for k in range(3, len(states) + 1):
            assert _cycle_period(states[:k], [1e-6] * k, 8, 1e-4, 1e-11, None) == 0
    # A period-3 cycle of 2 mm / 1 deg excursions: found with its period.
    cyc = [state(0.0), state(0.002, 0.0175), state(-0.002)] * 3
    errors = [1e-6, 2e-6, 3e-6] * 3
    assert _cycle_period(cyc, errors, 8, 1e-4, 1e-11, None) == 3
    assert _cycle_period(cyc, errors, 2, 1e-4, 1e-11, None) == 0  # longer than looked for


def test_warm_start_from_a_registration_of_part_of_the_cloud():
    """A registration of the cloud's first part, then of the whole cloud started from it:
    as close to the true pose as from the heuristic start, in fewer iterations; with shape
    modes the weights start from the earlier ones (clipped to 3 standard deviations)."""
    Q, N, _ = bean_template(3)
    mode = np.zeros_like(Q)
    mode[:, 0] = Q[:, 0] / np.abs(Q[:, 0]).max()
    variances = np.array([0.01**2])
    X_BK = true_pose((10.0, -6.0, 12.0))
    K = Q + 0.006 * mode
    R0 = heuristic_initial_rotation(SUPERIOR_B, LATERAL_B)
    part = X_BK.multiply(K[K[:, 0] > 0.0].T).T
    whole = X_BK.multiply(K[K[:, 0] > -0.5 * K[:, 0].max()].T).T
    kw = dict(shape_modes_K=mode[None], shape_variances=variances)
    first = register_plane_to_plane(part, Q, N, R0, **kw)
    cold = register_plane_to_plane(whole, Q, N, R0, **kw)
    warm = register_plane_to_plane(
        whole, Q, N, R0, initial_X_BK=first.X_BK, initial_shape=first.shape_coefficients, **kw
    )

    def errors(result):
        return (
            np.linalg.norm(result.X_BK.translation() - X_BK.translation()),
            angle_between(result.X_BK.rotation().matrix(), X_BK.rotation().matrix()),
        )

    assert warm.iterations < cold.iterations
    (dp_warm, dr_warm), (dp_cold, dr_cold) = errors(warm), errors(cold)
    assert dp_warm < dp_cold + 2e-4 and dr_warm < dr_cold + np.deg2rad(0.1)
    assert warm.shape_coefficients[0] == pytest.approx(cold.shape_coefficients[0], abs=5e-4)
    # Started at the answer, it stops at once.
    again = register_plane_to_plane(
        whole, Q, N, R0, initial_X_BK=warm.X_BK, initial_shape=warm.shape_coefficients, **kw
    )
    assert again.iterations <= 3
    with pytest.raises(ValueError, match="initial_shape"):
        register_plane_to_plane(whole, Q, N, R0, initial_shape=np.zeros(2), **kw)
    # Weights beyond the model's 3 standard deviations start clipped.
    start = dict(initial_X_BK=warm.X_BK, max_iterations=1, **kw)
    clipped = register_plane_to_plane(whole, Q, N, R0, initial_shape=[1.0], **start)
    at_bound = register_plane_to_plane(whole, Q, N, R0, initial_shape=[0.03], **start)
    assert clipped.errors[0] == at_bound.errors[0]


def test_template_tree_finds_the_same_neighbours():
    from scipy.spatial import cKDTree

    from drake_rus.localization.icp import _template_tree

    Q, _, _ = bean_template(3)
    p = np.random.default_rng(1).normal(scale=0.04, size=(500, 3))
    d0, j0 = cKDTree(Q).query(p)
    d1, j1 = _template_tree(Q).query(p)
    assert np.array_equal(j0, j1) and np.array_equal(d0, d1)


# ------------------------------------------------------------------ cost: stopping, kd-trees
def cKDTree_of(points):
    """A fresh (balanced) kd-tree: the reference nearest neighbours."""
    from scipy.spatial import cKDTree

    return cKDTree(points)


def pose_gap(a, b) -> tuple[float, float]:
    """(translation m, rotation rad) between two registrations' poses."""
    return (
        float(np.linalg.norm(a.X_BK.translation() - b.X_BK.translation())),
        angle_between(a.X_BK.rotation().matrix(), b.X_BK.rotation().matrix()),
    )


@pytest.mark.parametrize("modes", [False, True])
def test_a_converged_registration_stops_early_where_a_longer_run_ends(modes):
    """The step and error-change tests end a registration once its update is negligible,
    far below the iteration cap; iterating on until the iterates stop changing at all
    (tolerances near zero) moves the pose by less than 0.01 mm and 0.001 deg. Started at
    its own answer, it stops at once."""
    Q, N, _ = bean_template(3)
    P_B = true_pose().multiply(Q.T).T + np.random.default_rng(2).normal(scale=2e-4, size=Q.shape)
    R0 = heuristic_initial_rotation(SUPERIOR_B, LATERAL_B)
    kw = {}
    if modes:
        mode = np.zeros_like(Q)
        mode[:, 0] = Q[:, 0] / np.abs(Q[:, 0]).max()
        kw = dict(shape_modes_K=mode[None], shape_variances=np.array([0.01**2]))
    quick = register_plane_to_plane(P_B, Q, N, R0, **kw)
    assert quick.stop_reason == "converged" and quick.iterations < 50
    longer = register_plane_to_plane(
        P_B,
        Q,
        N,
        R0,
        step_tolerance=1e-13,
        error_change_tol=1e-30,
        cycle_max_period=0,
        max_iterations=100,
        **kw,
    )
    assert longer.iterations > quick.iterations
    dp, dr = pose_gap(quick, longer)
    assert dp < 1e-5 and np.rad2deg(dr) < 1e-3, (dp, np.rad2deg(dr))
    again = register_plane_to_plane(
        P_B, Q, N, R0, initial_X_BK=quick.X_BK, initial_shape=quick.shape_coefficients, **kw
    )
    assert again.stop_reason == "converged" and again.iterations <= 3


def test_template_tree_cache_is_keyed_by_content():
    from drake_rus.localization.icp import _template_tree

    Q, _, _ = bean_template(3)
    tree = _template_tree(Q)
    assert _template_tree(Q.copy()) is tree  # the same points: the same tree
    moved = Q + np.array([0.001, 0.0, 0.0])
    other = _template_tree(moved)
    assert other is not tree and np.array_equal(other.data, moved)
    # The tree keeps its own copy: changing the caller's array afterwards neither corrupts
    # it nor returns it for the changed points.
    scratch = Q.copy() * 1.01
    first = _template_tree(scratch)
    scratch[0] += 0.002
    second = _template_tree(scratch)
    assert second is not first and np.array_equal(second.data, scratch)
    assert not np.array_equal(first.data, scratch)
    p = np.random.default_rng(4).normal(scale=0.03, size=(200, 3))
    assert np.array_equal(second.query(p)[1], cKDTree_of(scratch).query(p)[1])


def test_moving_nearest_is_the_kd_trees_answer_with_fewer_queries():
    """A cloud moving in steps from 0.02 to 5 mm over a template that deforms (each step's
    motion bound given): every answer equals a fresh kd-tree's (index and distance), the
    tree is asked for a fraction of the points and rebuilt only for some steps."""
    from drake_rus.localization.icp import MovingNearest

    Q, _, _ = bean_template(3)
    rng = np.random.default_rng(5)
    mode = rng.normal(scale=1.0, size=Q.shape) * 0.002
    x = Q[rng.choice(len(Q), 400, replace=False)] + rng.normal(scale=0.002, size=(400, 3))
    moving, built, b, shape = MovingNearest(), [], 0.0, Q
    steps = [2e-5] * 10 + [5e-3] * 3 + [1e-4] * 10
    for step in steps:
        x = x + rng.normal(size=3) * step / np.sqrt(3)
        new_b = b + step / 0.004 * rng.normal()  # template points move ~ step too
        new_shape = Q + new_b * mode
        moving.template_moved(np.max(np.linalg.norm(new_shape - shape, axis=1)))
        b, shape = new_b, new_shape
        dist, idx = moving.query(x, shape, lambda: built.append(1) or cKDTree_of(shape))
        d_ref, j_ref = cKDTree_of(shape).query(x)
        assert np.array_equal(idx, j_ref) and np.array_equal(dist, d_ref)
    assert moving.queried < 0.5 * len(steps) * len(x)
    assert len(built) < len(steps)


def test_icp_with_moving_nearest_equals_plain_kd_tree_queries(monkeypatch, moving_nearest_doubles):
    """The candidate reuse changes nothing: a deformable registration (noisy partial cloud,
    ending in a cycle) with every correspondence from a fresh kd-tree of the current
    template gives bit-identical errors, pose and shape weights, while the reuse sends
    under half of the points to a kd-tree."""
    from drake_rus.localization import icp

    Q, N, _ = bean_template(3)
    rng = np.random.default_rng(0)
    modes = rng.normal(size=(2,) + Q.shape) * 0.003
    P_B = true_pose().multiply((Q + 0.004 * modes[0]).T).T[Q[:, 0] > -0.01]
    P_B = P_B + rng.normal(scale=0.002, size=P_B.shape)
    R0 = heuristic_initial_rotation(SUPERIOR_B, LATERAL_B)
    kw = dict(shape_modes_K=modes, shape_variances=np.array([1.0, 0.5]), step_tolerance=1e-6)
    Counted, Plain, made = moving_nearest_doubles

    monkeypatch.setattr(icp, "MovingNearest", Counted)
    fast = register_plane_to_plane(P_B, Q, N, R0, **kw)
    assert made[0].queried < 0.5 * len(P_B) * (fast.iterations + 1)
    monkeypatch.setattr(icp, "MovingNearest", Plain)
    plain = register_plane_to_plane(P_B, Q, N, R0, **kw)
    assert fast.iterations == plain.iterations > 20
    assert np.array_equal(fast.errors, plain.errors)
    assert np.array_equal(fast.X_BK.GetAsMatrix4(), plain.X_BK.GetAsMatrix4())
    assert np.array_equal(fast.shape_coefficients, plain.shape_coefficients)


@pytest.mark.parametrize(
    "superior, lateral, match",
    [
        ([0, 0, 0], [-1, 0, 0], "superior_B: expected a non-zero direction"),
        ([np.nan, 1, 0], [-1, 0, 0], "superior_B: expected a finite 3-vector"),
        ([0, 1, 0], [0, 0, 0], "lateral_B: expected a non-zero direction"),
        ([0, 1, 0], [np.inf, 0, 0], "lateral_B: expected a finite 3-vector"),
        ([0, 1], [-1, 0, 0], "superior_B: expected a finite 3-vector"),
    ],
)
def test_heuristic_initial_rotation_refuses_a_degenerate_direction(superior, lateral, match):
    # A zero or NaN body direction used to give a NaN rotation without a word (and a zero
    # lateral direction was reported as parallel to the superior one).
    with pytest.raises(ValueError, match=match):
        heuristic_initial_rotation(superior, lateral)
