"""The localizer's safeguards and the IcpLocalizer LeafSystem in isolation."""

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from pydrake.common.eigen_geometry import AngleAxis
from pydrake.math import RigidTransform, RotationMatrix

from drake_rus.control import supervisor
from drake_rus.control.config import ControllerConfig
from drake_rus.imaging.frames import PointCloud
from drake_rus.localization.config import LocalizationConfig
from drake_rus.localization.icp import heuristic_initial_rotation, register_plane_to_plane
from drake_rus.localization.localize import (
    IcpLocalizer,
    RegistrationTemplate,
    check_geometry,
    check_registration,
    cloud_axis_offset,
    cloud_spread,
    estimate_kidney_length,
    exploration_travel,
    load_registration_template,
    max_rms_residual,
    updated_length_estimate,
)

sys.path.insert(0, str(Path(__file__).parent))
from test_localization_icp import LATERAL_B, SUPERIOR_B, bean_template, true_pose  # noqa: E402


@pytest.fixture(scope="module")
def template():
    Q, N, _ = bean_template(3)
    return RegistrationTemplate(Q, N)


def partial_cloud(template, fraction=0.6):
    X_BK = true_pose()
    Q = template.points
    seen = Q[:, 0] > Q[:, 0].max() - fraction * np.ptp(Q[:, 0])
    return X_BK, X_BK.multiply(Q[seen].T).T


def test_check_registration_accepts_good_and_rejects_bad(template):
    config = LocalizationConfig()
    X_BK, P = partial_cloud(template)
    R0 = heuristic_initial_rotation(SUPERIOR_B, LATERAL_B)
    good = register_plane_to_plane(P, template.points, template.normals, R0)
    assert check_registration(good, P, config) == ""
    far = dataclasses.replace(
        good, X_BK=RigidTransform(good.X_BK.rotation(), good.X_BK.translation() + [0.3, 0, 0])
    )
    assert "from the explored points" in check_registration(far, P, config)
    sloppy = dataclasses.replace(good, inlier_fraction=0.1)
    assert "only 10%" in check_registration(sloppy, P, config)
    rough = dataclasses.replace(good, rms_residual=0.01)
    assert "RMS residual 10.0 mm" in check_registration(rough, P, config)


@pytest.mark.parametrize("radius", [0.0, 0.0005])
def test_points_along_a_line_are_refused(template, radius):
    # One point a frame along the sweep (or a thin streak): the template lays itself along
    # them with a residual and inlier fraction no kidney reaches, and that pose used to pass.
    rng = np.random.default_rng(0)
    y = np.linspace(0.0, 0.045, 60)
    a = rng.uniform(0.0, 2 * np.pi, len(y))
    P = np.column_stack([0.5 + radius * np.cos(a), y, 0.02 + radius * np.sin(a)])
    R0 = heuristic_initial_rotation(SUPERIOR_B, LATERAL_B)
    fit = register_plane_to_plane(P, template.points, template.normals, R0)
    assert fit.rms_residual < 1e-3 and fit.inlier_fraction > 0.9  # a "perfect" fit
    assert "explored points lie along a line" in check_registration(fit, P, LocalizationConfig())
    assert check_registration(fit, P, LocalizationConfig(min_cloud_spread=0.0)) == ""
    # A kidney's partial cloud spreads far more.
    assert cloud_spread(partial_cloud(template, 0.15)[1]) > 0.004


def test_a_refusal_shows_the_value_beyond_its_limit(template):
    # Rounded to the usual digits, a value just beyond its limit read as the limit itself
    # ("RMS residual 5.0 mm > 5.0 mm", "only 25% ... (need 25%)").
    config = LocalizationConfig()
    X_BK, P = partial_cloud(template)
    R0 = heuristic_initial_rotation(SUPERIOR_B, LATERAL_B)
    good = register_plane_to_plane(P, template.points, template.normals, R0)
    rough = dataclasses.replace(good, rms_residual=0.00602)
    assert check_registration(rough, P, config).endswith("RMS residual 6.02 mm > 6.00 mm")
    sparse = dataclasses.replace(good, inlier_fraction=0.2496)
    assert "only 24.96% of the" in check_registration(sparse, P, config)
    assert "(need 25.00%)" in check_registration(sparse, P, config)
    far = dataclasses.replace(
        good, X_BK=RigidTransform(good.X_BK.rotation(), P.mean(axis=0) + [0.0803, 0, 0])
    )
    assert "centre is 80.3 mm from the explored points (limit 80.0 mm)" in (
        check_registration(far, P, config)
    )
    # Far enough apart, the usual digits.
    assert check_registration(dataclasses.replace(good, rms_residual=0.01), P, config).endswith(
        "RMS residual 10.0 mm > 6.0 mm"
    )


def test_cloud_axis_offset_follows_a_tilted_line_of_sections():
    """A tube of points whose axis leans 30 deg off the sweep direction: a point on its axis
    is 0 mm off the sections' line, one 10 mm across the sweep 10 mm (a plain centroid,
    not following the lean, would put the on-axis point 15 mm off at 30 mm along it)."""
    rng = np.random.default_rng(0)
    up = np.array([0.0, 0.0, 1.0])
    c = np.radians(30)
    axis = np.array([np.sin(c), 0.0, np.cos(c)])
    t = rng.uniform(-0.06, 0.06, 6000)
    phi = rng.uniform(0, 2 * np.pi, 6000)
    ring = 0.01 * np.outer(np.cos(phi), [np.cos(c), 0, -np.sin(c)])
    ring += 0.01 * np.outer(np.sin(phi), [0.0, 1.0, 0.0])
    centre = np.array([0.1, 0.2, 0.3])
    P = np.outer(t, axis) + ring + centre
    for along in (0.0, 0.03):
        on_axis = centre + along * axis
        assert cloud_axis_offset(P, on_axis, up) == pytest.approx(0.0, abs=2e-3)
        assert cloud_axis_offset(P, on_axis + [0, 0.01, 0], up) == pytest.approx(0.01, abs=2e-3)
    # One slab only: the cloud's centroid.
    flat = P[np.abs(P[:, 2] - 0.3) < 0.001]
    assert cloud_axis_offset(flat, flat.mean(axis=0) + [0.005, 0, 0], up) == pytest.approx(0.005)


def test_geometry_check_refuses_a_turned_or_displaced_fit(template):
    """The geometric check (off by default) passes the correct fit, refuses the same fit
    with its long axis turned 60 deg off the body's axis, or its centre moved 20 mm across
    the sweep (both still within the centroid-offset gate), and names why."""
    X_BK, P = partial_cloud(template)
    R0 = heuristic_initial_rotation(SUPERIOR_B, LATERAL_B)
    good = register_plane_to_plane(P, template.points, template.normals, R0)
    config = LocalizationConfig(geometry_check=True)
    assert check_registration(good, P, config, None, SUPERIOR_B) == ""
    assert check_geometry(good, P, config, SUPERIOR_B) == ""
    lateral = np.cross(SUPERIOR_B, np.cross(LATERAL_B, SUPERIOR_B))
    turn = RotationMatrix(AngleAxis(np.radians(60), lateral / np.linalg.norm(lateral)))
    R_turned = turn.multiply(good.X_BK.rotation())
    turned = dataclasses.replace(good, X_BK=RigidTransform(R_turned, good.X_BK.translation()))
    why = check_registration(turned, P, config, None, SUPERIOR_B)
    assert "long axis lies" in why and "limit 45 deg" in why
    across = lateral / np.linalg.norm(lateral) * 0.02
    moved = dataclasses.replace(
        good, X_BK=RigidTransform(good.X_BK.rotation(), good.X_BK.translation() + across)
    )
    # 14.1 mm: the refusal shows the decimal that puts it past the limit.
    assert "14.1 mm from the explored sections' axis (limit 14.0 mm)" in check_geometry(
        moved, P, config, SUPERIOR_B
    )
    # Off by default, and without the body's axis.
    assert check_registration(turned, P, LocalizationConfig(), None, SUPERIOR_B) == ""
    assert check_registration(turned, P, config) == ""


def test_translation_step_is_bounded(template):
    # One thin cross-section: degenerate along the long axis. Steps stay bounded.
    X_BK, P = partial_cloud(template, 0.05)
    R0 = heuristic_initial_rotation(SUPERIOR_B, LATERAL_B)
    r = register_plane_to_plane(
        P, template.points, template.normals, R0, max_translation_step=0.005, max_iterations=30
    )
    assert np.linalg.norm(r.X_BK.translation() - P.mean(axis=0)) <= 30 * 0.005 + 0.06


def _cloud(points, travel_m):
    poses = tuple(RigidTransform([0.5, -travel_m * k / 9, 0.2]) for k in range(10))
    return PointCloud(
        points=points, frame_count=10, poses=poses, times=tuple(0.05 * k for k in range(10))
    )


@pytest.mark.parametrize("travel, expect_pose", [(0.04, True), (0.005, False), (0.01496, False)])
def test_icp_localizer_system(template, travel, expect_pose):
    X_BK, P = partial_cloud(template)
    phase = supervisor.Phase.LOCALIZE
    system = IcpLocalizer(
        template,
        LocalizationConfig(method="seed"),
        SUPERIOR_B,
        LATERAL_B,
        localize_phase=int(phase),
    )
    from pydrake.systems.analysis import Simulator

    simulator = Simulator(system)
    context = simulator.get_mutable_context()
    system.GetInputPort("point_cloud").FixValue(context, _cloud(P, travel))
    system.GetInputPort("phase").FixValue(context, [float(supervisor.Phase.EXPLORE)])
    simulator.AdvanceTo(0.2)  # not in LOCALIZE: nothing happens
    assert system.GetOutputPort("localization_ready").Eval(context)[0] == 0.0
    assert system.GetOutputPort("localization_error").Eval(context) == ""
    system.GetInputPort("phase").FixValue(context, [float(phase)])
    simulator.AdvanceTo(0.4)
    ready = system.GetOutputPort("localization_ready").Eval(context)[0]
    error = system.GetOutputPort("localization_error").Eval(context)
    if expect_pose:
        assert ready == 1.0 and error == ""
        X = system.GetOutputPort("X_BK").Eval(context)
        assert np.linalg.norm(X.translation() - X_BK.translation()) < 2e-3
    elif travel == 0.005:
        assert ready == 0.0 and "5.0 mm of exploration" in error
    else:  # just short of the 15 mm: not "15.0 mm (need 15 mm)"
        assert ready == 0.0 and "only 14.96 mm of exploration (need 15.00 mm)" in error


@pytest.mark.parametrize(
    "travel, limit, words",
    [
        (0.005, 0.015, "only 5.0 mm of exploration (need 15.0 mm)"),
        # The value and the limit widened together: "need 15 mm" hid a 14.54 mm limit.
        (0.01446, 0.01454, "only 14.46 mm of exploration (need 14.54 mm)"),
    ],
)
def test_short_exploration_states_value_and_limit_alike(template, travel, limit, words):
    X_BK, P = partial_cloud(template)
    phase = supervisor.Phase.LOCALIZE
    config = LocalizationConfig(method="seed", min_exploration_travel=limit)
    system = IcpLocalizer(template, config, SUPERIOR_B, LATERAL_B, localize_phase=int(phase))
    from pydrake.systems.analysis import Simulator

    simulator = Simulator(system)
    context = simulator.get_mutable_context()
    system.GetInputPort("point_cloud").FixValue(context, _cloud(P, travel))
    system.GetInputPort("phase").FixValue(context, [float(phase)])
    simulator.AdvanceTo(0.2)
    assert words in system.GetOutputPort("localization_error").Eval(context)


def test_exploration_travel():
    assert exploration_travel(()) == 0.0
    poses = [RigidTransform([0, -0.001 * k, 0]) for k in range(11)]
    assert exploration_travel(poses) == pytest.approx(0.01)


def test_supervisor_aborts_on_localization_error():
    s = supervisor.SupervisorState()
    s.initialised = True
    s.phase = supervisor.Phase.LOCALIZE
    s.phase_start = 1.0
    u = supervisor.SupervisorInputs(
        t=1.2,
        R_BP=np.diag([1.0, -1, -1]),
        p_BP=np.array([0.5, 0, 0.2]),
        F_z=9.0,
        kidney_visible=True,
        c_msk=0.5,
        localization_ready=False,
        localization_error="only 3 kidney boundary points were explored",
    )
    s = supervisor.supervisor_step(s, u, ControllerConfig(), 0.01)
    assert s.phase == supervisor.Phase.ABORT
    assert "localization failed: only 3 kidney" in s.reason


@pytest.mark.parametrize("enabled", [True, False])
def test_adaptive_exploration_flags_a_settled_estimate(template, enabled):
    from pydrake.systems.analysis import Simulator

    X_BK, P = partial_cloud(template)
    config = LocalizationConfig(method="seed", adaptive_exploration=enabled, adaptive_period=0.2)
    system = IcpLocalizer(
        template,
        config,
        SUPERIOR_B,
        LATERAL_B,
        localize_phase=int(supervisor.Phase.LOCALIZE),
        explore_phase=int(supervisor.Phase.EXPLORE),
        kidney_length=0.1,
    )
    simulator = Simulator(system)
    context = simulator.get_mutable_context()
    system.GetInputPort("point_cloud").FixValue(context, _cloud(P, 0.04))
    system.GetInputPort("phase").FixValue(context, [float(supervisor.Phase.EXPLORE)])
    simulator.AdvanceTo(0.05)
    assert system.GetOutputPort("exploration_sufficient").Eval(context)[0] == 0.0
    simulator.AdvanceTo(0.5)  # two interim estimates of the same cloud agree
    assert system.GetOutputPort("exploration_sufficient").Eval(context)[0] == float(enabled)


def test_supervisor_ends_exploration_when_sufficient():
    s = supervisor.SupervisorState()
    s.initialised = True
    s.phase = supervisor.Phase.EXPLORE
    s.P_des = np.array([0.5, 0.0])
    u = supervisor.SupervisorInputs(
        t=2.0,
        R_BP=np.diag([1.0, -1, -1]),
        p_BP=np.array([0.5, 0, 0.2]),
        F_z=9.0,
        kidney_visible=True,
        c_msk=0.5,
        exploration_sufficient=True,
    )
    s = supervisor.supervisor_step(s, u, ControllerConfig(), 0.01)
    assert s.phase == supervisor.Phase.LOCALIZE
    assert "adaptive" in s.events[-1][2]


def test_rms_bound_depends_on_the_method(template):
    """A rigid template leaves a real kidney's whole shape difference in the residual (up to
    5.6 mm on the VH female's kidneys); the deformable fit absorbs part of it."""
    config = LocalizationConfig()
    X_BK, P = partial_cloud(template)
    good = register_plane_to_plane(
        P, template.points, template.normals, heuristic_initial_rotation(SUPERIOR_B, LATERAL_B)
    )
    rigid = dataclasses.replace(good, rms_residual=0.0055)
    assert check_registration(rigid, P, config) == ""
    assert "RMS residual 6.5 mm > 6.0 mm" in check_registration(
        dataclasses.replace(rigid, rms_residual=0.0065), P, config
    )
    deformable = dataclasses.replace(rigid, shape_coefficients=np.zeros(3))
    assert "RMS residual 5.5 mm > 5.0 mm" in check_registration(deformable, P, config)


def test_rms_gate_widens_with_the_templates_own_shape_variability(template):
    """The shipped template keeps the measured gates; a template whose subjects vary more
    beyond the fitted modes widens them in quadrature (z SD of the excess per-point SD),
    and check_registration applies the gate of the template it is given."""
    config = LocalizationConfig()
    shipped = load_registration_template(None)
    assert max_rms_residual(config, shipped, True) == config.max_rms_residual_deformable
    assert max_rms_residual(config, shipped, False) == config.max_rms_residual
    n = len(template.points)
    # Modes whose variances beyond the third give a per-point SD of 4 mm (shipped: 0.70).
    var = np.array([4e-6, 3e-6, 2e-6, 0.5 * 0.004**2 * n, 0.5 * 0.004**2 * n])
    varied = RegistrationTemplate(template.points, template.normals, np.zeros((5, n, 3)), var)
    assert varied.unexplained_sd(3) == pytest.approx(0.004)
    s_ref = shipped.unexplained_sd(3)
    z = config.rms_shape_allowance_sd
    expected = np.sqrt(0.005**2 + z**2 * (0.004**2 - s_ref**2))
    assert max_rms_residual(config, varied, True) == pytest.approx(expected)
    assert expected > 0.0062
    off = dataclasses.replace(config, rms_shape_allowance_sd=0.0)
    assert max_rms_residual(off, varied, True) == 0.005
    X_BK, P = partial_cloud(template)
    good = register_plane_to_plane(
        P, template.points, template.normals, heuristic_initial_rotation(SUPERIOR_B, LATERAL_B)
    )
    fit = dataclasses.replace(good, rms_residual=0.006, shape_coefficients=np.zeros(3))
    assert "RMS residual 6.0 mm > 5.0 mm" in check_registration(fit, P, config, shipped)
    assert check_registration(fit, P, config, varied) == ""
    assert "> 5.0 mm" in check_registration(fit, P, off, varied)


def test_localizer_needs_the_kidney_seen_along_the_body(template):
    """The probe travelled 40 mm but the kidney showed in one place only (a few frames):
    too little of it to register."""
    X_BK, P = partial_cloud(template)
    y = P @ SUPERIOR_B
    P = P[np.abs(y - np.median(y)) < 0.002]  # a 4 mm band of the kidney
    system = IcpLocalizer(
        template,
        LocalizationConfig(method="seed"),
        SUPERIOR_B,
        LATERAL_B,
        localize_phase=int(supervisor.Phase.LOCALIZE),
        min_points=10,
    )
    from pydrake.systems.analysis import Simulator

    simulator = Simulator(system)
    context = simulator.get_mutable_context()
    system.GetInputPort("point_cloud").FixValue(context, _cloud(P, 0.04))
    system.GetInputPort("phase").FixValue(context, [float(supervisor.Phase.LOCALIZE)])
    simulator.AdvanceTo(0.1)
    assert "the kidney was seen over only" in system.GetOutputPort("localization_error").Eval(
        context
    )


def lengthening_template(template):
    """The bean with one shape mode that lengthens it (poles +-1 m per unit weight)."""
    Q = template.points
    mode = np.zeros_like(Q)
    mode[:, 0] = Q[:, 0] / np.abs(Q[:, 0]).max()
    return RegistrationTemplate(Q, template.normals, mode[None], np.array([0.01**2])), mode


def test_kidney_length_estimate_from_a_partial_cloud(template):
    shaped, mode = lengthening_template(template)
    b_true = 0.012  # 24 mm longer
    X_BK = true_pose((5.0, -4.0, 6.0))
    K = template.points + b_true * mode
    seen = K[:, 0] > K[:, 0].max() - 0.6 * np.ptp(K[:, 0])  # 60% from the upper pole
    P = X_BK.multiply(K[seen].T).T
    config = LocalizationConfig(length_shape_modes=1)
    length, result = estimate_kidney_length(P, shaped, config, SUPERIOR_B, LATERAL_B)
    assert np.ptp(template.points[:, 0]) + 0.02 < length  # longer than the template
    assert length == pytest.approx(np.ptp(K[:, 0]), abs=0.004)
    assert result.shape_coefficients is not None
    # Without shape modes the template's own length says nothing about the kidney.
    assert np.isnan(estimate_kidney_length(P, template, config, SUPERIOR_B, LATERAL_B)[0])


def test_kidney_length_fit_is_checked_like_the_registration(template):
    """With the geometry check on, a length fit whose long axis lies further from the
    body's axis than the check allows gives no length, as the registration would be
    refused; with it off the same fit gives one."""
    shaped, mode = lengthening_template(template)
    X_BK = true_pose((5.0, -4.0, 6.0))  # the long axis about 7 deg from SUPERIOR_B
    K = template.points + 0.012 * mode
    P = X_BK.multiply(K[K[:, 0] > K[:, 0].max() - 0.6 * np.ptp(K[:, 0])].T).T
    loose = LocalizationConfig(length_shape_modes=1, geometry_check=True)
    assert np.isfinite(estimate_kidney_length(P, shaped, loose, SUPERIOR_B, LATERAL_B)[0])
    strict = dataclasses.replace(loose, max_axis_tilt_deg=2.0)
    length, result = estimate_kidney_length(P, shaped, strict, SUPERIOR_B, LATERAL_B)
    assert np.isnan(length)
    assert "long axis" in check_geometry(result, P, strict, SUPERIOR_B)


def _length_localizer(template, **config):
    """An IcpLocalizer on a template that lengthens along its one shape mode, checking the
    length every 0.2 s from 30 mm of travel; and the 60% of a 12 mm-longer kidney K it
    sees (P, placed at a known pose). Returns (system, simulator, context, K, P)."""
    from pydrake.systems.analysis import Simulator

    shaped, mode = lengthening_template(template)
    K = template.points + 0.012 * mode
    X_BK = true_pose((5.0, -4.0, 6.0))
    P = X_BK.multiply(K[K[:, 0] > K[:, 0].max() - 0.6 * np.ptp(K[:, 0])].T).T
    system = IcpLocalizer(
        shaped,
        LocalizationConfig(
            length_shape_modes=1, adaptive_period=0.2, length_min_travel=0.03, **config
        ),
        SUPERIOR_B,
        LATERAL_B,
        localize_phase=int(supervisor.Phase.LOCALIZE),
        explore_phase=int(supervisor.Phase.EXPLORE),
    )
    simulator = Simulator(system)
    return system, simulator, simulator.get_mutable_context(), K, P


@pytest.mark.parametrize("enabled", [True, False])
def test_icp_localizer_kidney_length_estimate_port(template, enabled):
    system, simulator, context, K, P = _length_localizer(template, length_estimation=enabled)
    port = system.GetOutputPort("kidney_length_estimate")
    system.GetInputPort("phase").FixValue(context, [float(supervisor.Phase.EXPLORE)])
    system.GetInputPort("point_cloud").FixValue(context, _cloud(P, 0.02))
    simulator.AdvanceTo(0.3)
    assert np.isnan(port.Eval(context)[0])  # 20 mm explored: not yet
    system.GetInputPort("point_cloud").FixValue(context, _cloud(P, 0.04))
    simulator.AdvanceTo(0.6)
    if enabled:
        assert port.Eval(context)[0] == pytest.approx(np.ptp(K[:, 0]), abs=0.004)
    else:
        assert np.isnan(port.Eval(context)[0])


def test_updated_length_estimate_after_a_failed_fit():
    assert updated_length_estimate(0.11, 0.12, "unknown") == 0.12
    assert updated_length_estimate(0.11, 0.12, "keep") == 0.12
    assert updated_length_estimate(0.11, math.nan, "unknown") == math.inf
    assert updated_length_estimate(0.11, math.nan, "keep") == 0.11
    assert np.isnan(updated_length_estimate(math.nan, math.nan, "keep"))
    with pytest.raises(ValueError, match="length_failed_fit"):
        updated_length_estimate(0.11, math.nan, "guess")


def test_updated_length_estimate_needs_confirmation_to_shorten():
    """A reading lowers the estimate only when the check before read within the
    tolerance; unconfirmed, it may only lengthen the exploration."""
    tol = 0.006

    def update(previous, length, previous_reading, reference=0.10):
        return updated_length_estimate(
            previous,
            length,
            "unknown",
            previous_reading=previous_reading,
            confirm_tolerance=tol,
            reference=reference,
        )

    assert update(0.132, 0.080, 0.132) == 0.132  # a jump down: the estimate stays
    assert update(0.132, 0.082, 0.080) == 0.082  # confirmed by the check before
    assert update(0.122, 0.132, 0.122) == 0.132  # a jump up lengthens at once
    assert update(0.132, 0.127, 0.132) == 0.127  # within the tolerance
    assert update(math.inf, 0.118, math.nan) == math.inf  # after a failed fit: unknown
    assert update(math.inf, 0.118, 0.119) == 0.118  # until two readings agree
    # The first reading: the reference length L_m is the estimate it would lower.
    assert update(math.nan, 0.09, math.nan) == 0.10
    assert update(math.nan, 0.12, math.nan) == 0.12
    assert update(math.nan, 0.09, math.nan, reference=math.nan) == 0.09
    # Off: every reading that passed is the estimate, as before.
    assert updated_length_estimate(0.132, 0.080, "unknown", 0.132, 0.0, 0.10) == 0.080


@pytest.mark.parametrize("failed_fit", ["unknown", "keep"])
def test_icp_localizer_length_after_a_failed_fit(template, failed_fit):
    """A length fit that fails its checks (here: a cloud far wider than the template, RMS
    above the gate) makes the estimate unknown (+inf) or keeps the previous one; the next
    fit starts from the last one that passed."""
    system, simulator, context, K, P = _length_localizer(template, length_failed_fit=failed_fit)
    port = system.GetOutputPort("kidney_length_estimate")
    system.GetInputPort("phase").FixValue(context, [float(supervisor.Phase.EXPLORE)])
    system.GetInputPort("point_cloud").FixValue(context, _cloud(P, 0.04))
    simulator.AdvanceTo(0.1)  # the first check passes
    passed = port.Eval(context)[0]
    assert passed == pytest.approx(np.ptp(K[:, 0]), abs=0.004)
    fit = context.get_abstract_state(system._length).get_value().fit
    centre = P.mean(axis=0)
    wide = centre + 3.0 * (P - centre)  # three times the kidney's size in every direction
    system.GetInputPort("point_cloud").FixValue(context, _cloud(wide, 0.06))
    simulator.AdvanceTo(0.3)  # the second check fails
    state = context.get_abstract_state(system._length).get_value()
    assert len(state.checks) == 2 and np.isnan(state.checks[-1][2])
    assert state.fit is fit
    expected = math.inf if failed_fit == "unknown" else passed
    assert port.Eval(context)[0] == expected


def test_icp_localizer_length_lowered_only_when_confirmed(template):
    """A reading 24 mm shorter than the previous one leaves the estimate where it was; the
    next check, reading the same again, confirms it and lowers the estimate."""
    system, simulator, context, K, P = _length_localizer(template)
    port = system.GetOutputPort("kidney_length_estimate")
    system.GetInputPort("phase").FixValue(context, [float(supervisor.Phase.EXPLORE)])
    system.GetInputPort("point_cloud").FixValue(context, _cloud(P, 0.04))
    simulator.AdvanceTo(0.1)  # the first check
    long = port.Eval(context)[0]
    assert long == pytest.approx(np.ptp(K[:, 0]), abs=0.004)
    shaped, mode = lengthening_template(template)
    short = template.points - 0.012 * mode  # 48 mm shorter than K
    seen = short[short[:, 0] > short[:, 0].max() - 0.6 * np.ptp(short[:, 0])]
    P_short = true_pose((5.0, -4.0, 6.0)).multiply(seen.T).T
    system.GetInputPort("point_cloud").FixValue(context, _cloud(P_short, 0.05))
    simulator.AdvanceTo(0.3)  # the second check reads the short kidney: not confirmed
    checks = context.get_abstract_state(system._length).get_value().checks
    assert len(checks) == 2 and checks[-1][2] == pytest.approx(np.ptp(short[:, 0]), abs=0.004)
    assert port.Eval(context)[0] == long
    simulator.AdvanceTo(0.5)  # the third reads it again: confirmed
    assert port.Eval(context)[0] == pytest.approx(np.ptp(short[:, 0]), abs=0.004)


@pytest.mark.parametrize("warm", [True, False])
def test_icp_localizer_length_fits_start_from_the_previous_one(template, warm, monkeypatch):
    """Every length check after the first that passed starts from that fit's pose and
    shape weights (``length_warm_start``), and reads the length the heuristic start reads."""
    import drake_rus.localization.localize as localize_module

    starts = []
    original = localize_module.register_plane_to_plane

    def spy(*args, **kwargs):
        starts.append((kwargs.get("initial_X_BK"), kwargs.get("initial_shape")))
        return original(*args, **kwargs)

    monkeypatch.setattr(localize_module, "register_plane_to_plane", spy)
    system, simulator, context, K, P = _length_localizer(template, length_warm_start=warm)
    system.GetInputPort("phase").FixValue(context, [float(supervisor.Phase.EXPLORE)])
    system.GetInputPort("point_cloud").FixValue(context, _cloud(P, 0.04))
    simulator.AdvanceTo(0.1)  # the first check
    state = context.get_abstract_state(system._length).get_value()
    assert state.fit is not None and len(starts) == 1 and starts[0] == (None, None)
    simulator.AdvanceTo(0.3)  # the second check
    assert len(starts) == 2
    if warm:
        assert starts[1][0] is state.fit.X_BK
        assert np.array_equal(starts[1][1], state.fit.shape_coefficients)
    else:
        assert starts[1] == (None, None)
    length = system.GetOutputPort("kidney_length_estimate").Eval(context)[0]
    assert length == pytest.approx(np.ptp(K[:, 0]), abs=0.004)


def test_relocalization_registers_anew_through_the_executor(template):
    """A new localization round (the supervisor re-localizes) drops the estimate and submits
    a new registration to the executor's fits lane, like the first one: not ready until the
    lane's latency has passed (the supervisor holds still in LOCALIZE meanwhile), then the
    new pose, stamped with the new round."""
    from pydrake.systems.analysis import Simulator

    from drake_rus.executor import InlineExecutor

    executor = InlineExecutor({"frames": 0.0, "fits": 0.3})
    X_BK, P = partial_cloud(template)
    phase = supervisor.Phase.LOCALIZE
    system = IcpLocalizer(
        template,
        LocalizationConfig(method="seed"),
        SUPERIOR_B,
        LATERAL_B,
        localize_phase=int(phase),
        executor=executor,
    )
    simulator = Simulator(system)
    context = simulator.get_mutable_context()
    system.GetInputPort("point_cloud").FixValue(context, _cloud(P, 0.04))
    system.GetInputPort("phase").FixValue(context, [float(phase)])
    system.GetInputPort("localization_round").FixValue(context, [0.0])
    ready = system.GetOutputPort("localization_ready")
    outcome = system.GetOutputPort("localization")
    simulator.AdvanceTo(0.2)
    assert ready.Eval(context)[0] == 0.0  # asked for, not back yet
    simulator.AdvanceTo(0.5)
    assert ready.Eval(context)[0] == 1.0 and outcome.Eval(context).round == 0
    first = outcome.Eval(context)
    # The kidney moved 12 mm along the body; the re-exploration saw it there.
    shifted = P + 0.012 * np.asarray(SUPERIOR_B)
    system.GetInputPort("phase").FixValue(context, [float(supervisor.Phase.EXPLORE)])
    system.GetInputPort("localization_round").FixValue(context, [1.0])
    simulator.AdvanceTo(0.6)
    assert ready.Eval(context)[0] == 0.0 and outcome.Eval(context).round == 1
    system.GetInputPort("point_cloud").FixValue(context, _cloud(shifted, 0.04))
    system.GetInputPort("phase").FixValue(context, [float(phase)])
    simulator.AdvanceTo(0.75)
    assert ready.Eval(context)[0] == 0.0  # the new registration is running
    simulator.AdvanceTo(1.1)
    second = outcome.Eval(context)
    assert ready.Eval(context)[0] == 1.0 and second.round == 1
    assert second.ready_time - second.time == pytest.approx(0.3, abs=0.06)
    assert second.time > first.ready_time
    moved = second.result.X_BK.translation() - first.result.X_BK.translation()
    assert np.linalg.norm(moved - 0.012 * np.asarray(SUPERIOR_B)) < 2e-3
    assert executor.statistics()["registration"]["count"] == 2
