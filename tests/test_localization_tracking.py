"""Kidney tracking after localization: drift estimate, the latch, and the LeafSystem."""

import dataclasses
import math

import numpy as np
import pytest
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix

from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.frames import BoundaryPixels
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.localization.config import LocalizationConfig
from drake_rus.localization.icp import IcpResult
from drake_rus.localization.localize import LocalizationOutcome, load_registration_template
from drake_rus.localization.tracking import (
    DriftEstimate,
    KidneyTrackingMonitor,
    TrackingLimits,
    TrackingState,
    changed_across_stretches,
    estimate_drift,
    group_medians,
    judged_drift,
    kidney_in_view,
    same_view,
    slip_update,
    tangential_force_change,
    tracking_limits,
    tracking_update,
    window_view,
)

X_BK = RigidTransform(RollPitchYaw(0.05, -0.1, math.pi / 2 + 0.2), [0.55, 0.02, 0.08])


@pytest.fixture(scope="module")
def template():
    return load_registration_template()


def long_axis_slab(template, half_width=0.004):
    """Template points near the kidney's long-axis plane (what a pivot frame sees), in B."""
    Q = template.points
    return X_BK.multiply(Q[np.abs(Q[:, 1]) < half_width].T).T


@pytest.mark.parametrize(
    "shift_mm", [[0.0, 0.0, 0.0], [0.0, 12.0, 0.0], [8.0, 0.0, 3.0], [-5.0, 9.0, -2.0]]
)
def test_estimate_drift_recovers_a_shift_of_the_seen_points(template, shift_mm):
    rng = np.random.default_rng(3)
    P = long_axis_slab(template) + np.asarray(shift_mm) / 1000
    P += rng.normal(scale=0.0005, size=P.shape)
    d = estimate_drift(P, X_BK, template.points, template.normals)
    assert d.n_points == len(P)
    # In-plane components come back to ~1 mm; the plane's normal direction (kidney y) is
    # only weakly seen by a single slab, the regularisation keeps it small.
    y_K = X_BK.rotation().matrix()[:, 1]
    in_plane = lambda v: v - (v @ y_K) * y_K  # noqa: E731
    np.testing.assert_allclose(
        in_plane(d.drift_B) * 1000, in_plane(np.asarray(shift_mm, float)), atol=1.5
    )
    assert d.rms_residual < 0.002


def test_estimate_drift_ignores_points_off_the_surface(template):
    """A fan edge cutting the kidney adds boundary points inside it: trimmed away."""
    P = long_axis_slab(template)
    inside = X_BK.multiply((0.5 * template.points[::10]).T).T  # well inside the kidney
    P = np.concatenate([P, inside[: len(P) // 5]])
    assert estimate_drift(P, X_BK, template.points, template.normals).magnitude < 0.002


def test_estimate_drift_of_no_points_is_zero(template):
    d = estimate_drift(np.zeros((0, 3)), X_BK, template.points, template.normals)
    assert d.magnitude == 0.0 and d.n_points == 0 and math.isnan(d.rms_residual)


def test_tracking_update_latches_after_successive_confirmations():
    cfg = LocalizationConfig(tracking_max_drift=0.007, tracking_confirmations=2)
    big = DriftEstimate(np.array([0.0, 0.010, 0.0]), 0.001, 100)
    small = DriftEstimate(np.array([0.0, 0.002, 0.0]), 0.001, 100)
    s = tracking_update(TrackingState(), 1.0, big, cfg)
    assert s.exceed_count == 1 and not s.error  # one check is not enough
    s = tracking_update(s, 1.5, small, cfg)
    assert s.exceed_count == 0 and not s.error  # ... and a good one resets
    s = tracking_update(tracking_update(s, 2.0, big, cfg), 2.5, big, cfg)
    assert "10.0 mm" in s.error and "limit 7.0 mm" in s.error
    assert [round(d, 3) for _, d in s.history] == [0.01, 0.002, 0.01, 0.01]
    latched = tracking_update(s, 3.0, small, cfg)
    assert latched.error == s.error  # latched
    assert tracking_update(TrackingState(), 1.0, None, cfg).last_check == 1.0


def test_estimate_drift_leaves_out_outlier_frames_but_not_a_shift(template):
    """Six frames of the kidney's section and four of a region 60 mm away (a muscle band
    taken for the kidney; 40% of the points, more than the trimming drops): with the frames
    named, the outliers are left out; a shift that every frame shows is still measured."""
    section = long_axis_slab(template)
    z_B = X_BK.rotation().matrix()[:, 2]
    band = section + 0.06 * z_B
    P = np.concatenate([section] * 6 + [band] * 4)
    ids = np.repeat(np.arange(10), len(section))
    fooled = estimate_drift(P, X_BK, template.points, template.normals)
    kept = estimate_drift(P, X_BK, template.points, template.normals, frame_ids=ids)
    assert fooled.magnitude > 0.004
    assert kept.magnitude < 0.0015 and (kept.n_frames_used, kept.n_frames) == (6, 10)
    shift = 0.012 * z_B
    moved = estimate_drift(
        np.concatenate([section + shift] * 8),
        X_BK,
        template.points,
        template.normals,
        frame_ids=np.repeat(np.arange(8), len(section)),
    )
    assert moved.n_frames_used == 8
    np.testing.assert_allclose(moved.drift_B, shift, atol=0.002)


def test_kidney_in_view_counts_the_registered_surface_in_the_image(template):
    geometry = ProbeGeometry.from_config(ImagingConfig())
    shape_B = X_BK.multiply(template.points.T).T
    R_KP = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    over = X_BK.multiply(RigidTransform(RotationMatrix(R_KP), [0.0, 0.0, 0.06]))
    assert kidney_in_view(shape_B, over, geometry, 0.003) > 50
    # The same view 120 mm along the kidney's long axis (past its pole), and turned so the
    # image plane lies beside the kidney (30 mm off along its y): nothing to compare.
    past = X_BK.multiply(RigidTransform(RotationMatrix(R_KP), [0.12, 0.0, 0.06]))
    beside = X_BK.multiply(RigidTransform(RotationMatrix(R_KP), [0.0, 0.035, 0.06]))
    assert kidney_in_view(shape_B, past, geometry, 0.003) == 0
    assert kidney_in_view(shape_B, beside, geometry, 0.003) == 0


def _run_monitor(
    template,
    shift_B,
    *,
    phase=4,
    motion_allowed=None,
    duration=2.0,
    config=None,
    outlier=None,
    view_offset_K=(0.0, 0.0, 0.0),
):
    """Runs the monitor on synthetic long-axis frames of a kidney displaced by shift_B (m):
    the template's section through its x-z plane, seen by a probe whose image plane is
    that plane, one frame per imaging period."""
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import DiagramBuilder
    from pydrake.systems.primitives import ConstantValueSource, ConstantVectorSource

    imaging = ImagingConfig()
    geometry = ProbeGeometry.from_config(imaging)
    config = config or LocalizationConfig()
    builder = DiagramBuilder()
    monitor = builder.AddSystem(KidneyTrackingMonitor(template, config, imaging, [4]))
    result = IcpResult(
        X_BK=X_BK,
        iterations=1,
        converged=True,
        rms_residual=0.001,
        inlier_fraction=1.0,
        covariance=np.eye(6),
        errors=np.zeros(1),
        max_rotation_steps=np.zeros(1),
    )
    outcome = builder.AddSystem(
        ConstantValueSource(AbstractValue.Make(LocalizationOutcome(result=result, time=0.0)))
    )
    builder.Connect(outcome.get_output_port(), monitor.GetInputPort("localization"))
    builder.Connect(
        builder.AddSystem(ConstantVectorSource([phase])).get_output_port(),
        monitor.GetInputPort("phase"),
    )
    if motion_allowed is not None:
        builder.Connect(
            builder.AddSystem(ConstantVectorSource([motion_allowed])).get_output_port(),
            monitor.GetInputPort("motion_allowed"),
        )
    sim = Simulator(builder.Build())
    mctx = monitor.GetMyContextFromRoot(sim.get_mutable_context())
    # Image plane = the kidney's x-z plane: P's x along K's x, P's z (depth) along -K's z.
    R_KP = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    X_BP = X_BK.multiply(
        RigidTransform(RotationMatrix(R_KP), np.add([0.0, 0.0, 0.06], view_offset_K))
    )
    section = long_axis_slab(template, 0.0015) + np.asarray(shift_B)
    pixels, _ = geometry.B_to_pixel(section, X_BP)
    period = 1.0 / imaging.frame_rate_hz
    for k in range(int(duration / period)):
        px = pixels
        if outlier is not None and outlier(k):
            # A region 60 mm deeper in the image than the kidney's section.
            px = pixels + [0.0, 0.06 / geometry.dz]
        monitor.GetInputPort("boundary_pixels").FixValue(
            mctx, BoundaryPixels(px, k * period, X_BP, k)
        )
        sim.AdvanceTo((k + 1) * period)
    return monitor.state(mctx), monitor.GetOutputPort("kidney_drift").Eval(mctx)[0]


def test_monitor_passes_a_kidney_that_stayed(template):
    state, drift = _run_monitor(template, [0.0, 0.0, 0.0])
    assert state.error == "" and len(state.history) >= 3
    assert drift < 0.002


def test_monitor_reports_a_kidney_that_moved_across(template):
    lateral = X_BK.rotation().matrix()[:, 2] * 0.02  # 20 mm along the kidney's z
    state, drift = _run_monitor(template, lateral)
    assert "from its registered pose" in state.error and "limit 15.0 mm" in state.error
    assert drift == pytest.approx(0.02, abs=0.003)


def test_monitor_is_not_fooled_by_a_few_outlier_frames(template):
    """Two frames in five segment a region 60 mm deeper than the kidney: not motion (the
    trimmed fit alone, without the frame gate, reads 4.8 mm)."""
    state, drift = _run_monitor(template, [0.0, 0.0, 0.0], outlier=lambda k: k % 5 in (1, 3))
    assert state.error == "" and len(state.history) >= 3
    assert drift < 0.001


def test_monitor_skips_views_the_registered_kidney_does_not_cross(template):
    """Past the registered pole (the view 120 mm along the long axis) whatever the
    segmenter marks is not compared: no check, no error (compared, it reads 60 mm)."""
    state, drift = _run_monitor(
        template, [0.0, 0.0, 0.0], view_offset_K=(0.12, 0.0, 0.0), outlier=lambda k: True
    )
    assert state.error == "" and state.frames == () and math.isnan(drift)


def test_monitor_ignores_frames_outside_its_phases_and_breath_holds(template):
    lateral = X_BK.rotation().matrix()[:, 2] * 0.02
    state, drift = _run_monitor(template, lateral, phase=1)  # EXPLORE: not checked
    assert state.error == "" and state.history == () and math.isnan(drift)
    state, _ = _run_monitor(template, lateral, motion_allowed=0.0)  # outside a hold
    assert state.error == "" and state.frames == ()
    off = dataclasses.replace(LocalizationConfig(), tracking_check=False)
    state, _ = _run_monitor(template, lateral, config=off)
    assert state.error == "" and state.history == ()


def _result(rms=0.001):
    return IcpResult(
        X_BK=X_BK,
        iterations=1,
        converged=True,
        rms_residual=rms,
        inlier_fraction=1.0,
        covariance=np.eye(6),
        errors=np.zeros(1),
        max_rotation_steps=np.zeros(1),
    )


def test_judged_drift_allows_the_registrations_axial_uncertainty():
    lim = TrackingLimits(0.015, 0.015, np.array([0.0, 1.0, 0.0]))
    assert judged_drift([0.0, 0.014, 0.0], lim) == 0.0  # within the allowance
    assert judged_drift([0.0, -0.020, 0.0], lim) == pytest.approx(0.005)
    assert judged_drift([0.012, 0.020, 0.0], lim) == pytest.approx(math.hypot(0.012, 0.005))
    # Without an axis the whole drift counts (the plain limit).
    assert judged_drift([0.012, 0.020, 0.0], TrackingLimits(0.015)) == pytest.approx(
        math.hypot(0.012, 0.020)
    )


def test_tracking_limits_follow_the_registration():
    cfg = LocalizationConfig()
    lim = tracking_limits(_result(0.002), cfg)
    assert lim.limit == cfg.tracking_max_drift
    assert lim.axial_allowance == cfg.tracking_axial_allowance
    np.testing.assert_allclose(lim.axis_B, X_BK.rotation().matrix()[:, 0])
    scaled = dataclasses.replace(cfg, tracking_rms_factor=10.0)
    assert tracking_limits(_result(0.002), scaled).limit == pytest.approx(0.020)
    assert tracking_limits(_result(0.001), scaled).limit == cfg.tracking_max_drift
    plain = tracking_limits(None, cfg)
    assert plain.limit == cfg.tracking_max_drift and plain.axis_B is None


def test_tracking_update_judges_with_the_limits():
    cfg = LocalizationConfig(tracking_confirmations=2)
    lim = TrackingLimits(0.015, 0.015, np.array([0.0, 1.0, 0.0]))
    along = DriftEstimate(np.array([0.0, 0.025, 0.0]), 0.001, 100)
    s = tracking_update(
        tracking_update(TrackingState(), 1.0, along, cfg, lim), 1.5, along, cfg, lim
    )
    assert s.error == "" and s.judged_m == pytest.approx(0.010) and s.limit_m == 0.015
    assert s.drift_m == pytest.approx(0.025)  # the apparent drift itself
    across = DriftEstimate(np.array([0.016, 0.025, 0.0]), 0.001, 100)
    s = tracking_update(tracking_update(s, 2.0, across, cfg, lim), 2.5, across, cfg, lim)
    assert "25.0 mm of it along the kidney's long axis, where 15 mm are allowed" in s.error
    assert "judged 18.9 mm" in s.error and "29.7 mm from its registered pose" in s.error
    assert "from its registered pose" in s.error and "limit 15.0 mm" in s.error


def test_each_phase_takes_its_own_reference_for_the_change_check():
    """TRANSIT's slide views another part of the kidney than PIVOT: a still kidney's drift
    changes by 14 mm between them, which is not motion. PIVOT's first checks are its
    reference; a 12 mm change from them on two checks is."""
    cfg = LocalizationConfig(tracking_reference_checks=2, tracking_confirmations=2)
    lim = TrackingLimits(0.015, 0.015, np.array([0.0, 1.0, 0.0]))

    def check(s, t, v_mm, phase):
        return tracking_update(
            s, t, DriftEstimate(np.array(v_mm) * 1e-3, 0.001, 100), cfg, lim, phase=phase
        )

    s = TrackingState()
    for k, v in enumerate([[0, 14, 0], [0, 14.5, 0], [0, 10, 0]]):
        s = check(s, 1.0 + 0.5 * k, v, 3)  # TRANSIT
    for k, v in enumerate([[-3, 0, 0], [-3, 1, 0], [-2, 0, 0], [-3, 0.5, 0]]):
        s = check(s, 3.0 + 0.5 * k, v, 4)  # PIVOT: 14 mm from TRANSIT's reference
    assert s.error == "" and s.change_m < 0.002
    s = check(check(s, 5.0, [-3, 12.5, 0], 4), 5.5, [-3, 13, 0], 4)
    assert "from where the first checks after it saw it" in s.error
    assert cfg.tracking_change_limit == pytest.approx(0.011)
    one = TrackingState()  # one reference for both phases: the view change reads as motion
    for k, v in enumerate([[0, 14, 0], [0, 14.5, 0], [0, 10, 0], [-3, 0, 0], [-3, 1, 0]]):
        one = check(one, 1.0 + 0.5 * k, v, -1)
    assert one.error


def _view(angle_deg, offset_m=0.0):
    """A view turned ``angle_deg`` about B's z from transverse (normal -y_B), the probe
    ``offset_m`` along x_B."""
    a = math.radians(angle_deg)
    return (np.array([math.sin(a), -math.cos(a), 0.0]), np.array([0.48 + offset_m, 0, 0.2]))


def test_same_view_is_the_same_image_plane_and_probe_place():
    assert same_view(_view(0), _view(7.5), 0.138, 0.0075)
    assert not same_view(_view(0), _view(9), 0.138, 0.0075)
    flipped = (-_view(3)[0], _view(3)[1])  # a plane and its flip are one plane
    assert same_view(_view(0), flipped, 0.138, 0.0075)
    assert not same_view(_view(0), _view(0, 0.009), 0.138, 0.0075)
    assert same_view(None, _view(40), 0.138, 0.0075)  # a view not known: any view
    assert same_view((None, None), _view(40), 0.138, 0.0075)


def test_a_window_of_frames_is_viewed_along_its_mean_plane():
    """A fit over the frames of the last second views what they viewed: the mean plane (a
    flipped frame the same plane) and the mean probe place."""
    n, origin = window_view([_view(0), (-_view(20)[0], _view(20)[1]), _view(10, 0.003)])
    assert abs(float(n @ _view(10)[0])) == pytest.approx(1.0, abs=1e-9)
    assert np.allclose(origin, [0.481, 0, 0.2])


def test_the_change_is_judged_against_checks_of_the_same_view():
    """test:9's still scan, TRANSIT turning the probe from transverse to longitudinal about
    p* (15 deg between checks): the drift's long-axis part read 13.6, 12.7, 9.0, 1.6,
    -3.6 mm, a 17.3 mm change from the first two checks that stopped a good scan. Against
    checks of its own view nothing changed; a shift at one view still does."""
    cfg = LocalizationConfig(tracking_reference_checks=2, tracking_confirmations=2)
    assert cfg.tracking_reference_view_angle == pytest.approx(math.atan(7.5 / 54), abs=1e-3)
    lim = TrackingLimits(0.015, 0.015, np.array([0.0, 1.0, 0.0]))
    readings = [[0.7, 13.6, -2.6], [0.1, 12.7, -3.1], [2.0, 9.0, -0.4], [1.0, 1.6, -0.3]]
    readings.append([2.5, -3.6, 1.0])
    turn = [17, 33, 51, 68, 79]  # deg from transverse, as the probe turned

    def check(s, t, v_mm, view, phase=3):
        return tracking_update(
            s,
            t,
            DriftEstimate(np.array(v_mm) * 1e-3, 0.001, 100),
            cfg,
            lim,
            phase=phase,
            view=view,
        )

    plain = turning = TrackingState()
    for k, (v, a) in enumerate(zip(readings, turn)):
        plain = check(plain, 11.2 + 0.5 * k, v, None)  # the former rule: one reference
        turning = check(turning, 11.2 + 0.5 * k, v, _view(a))
    assert "17.3 mm from where the first checks after it saw it" in plain.error
    assert turning.error == "" and math.isnan(turning.change_m)
    # PIVOT at p*, the plane standing still: its first two checks are the reference, and a
    # kidney moved 12 mm along the body shows on the next two of the same view.
    s = turning
    for k, v in enumerate([[8.7, 1.6, 2.6], [7.7, 3.3, 2.1], [8.0, 2.0, 2.4]]):
        s = check(s, 14.0 + 0.5 * k, v, _view(80 + k), phase=4)
    assert s.error == "" and s.change_m < 0.002
    s = check(s, 15.5, [8.0, 14.5, 2.4], _view(96), phase=4)  # another view: not judged
    assert math.isnan(s.change_m) and s.exceed_count == 0
    s = check(s, 16.0, [8.0, 15.0, 2.4], _view(81), phase=4)
    assert s.error == "" and s.exceed_count == 1 and s.change_m > 0.011
    s = check(s, 16.5, [8.0, 15.5, 2.0], _view(110), phase=4)  # not judged: the run holds
    assert s.exceed_count == 1
    s = check(s, 17.0, [8.0, 14.5, 2.4], _view(80), phase=4)
    assert "from where the first checks after it saw it" in s.error


def test_a_change_in_one_breaths_window_is_not_a_shift_one_in_two_is():
    """Gated free breathing: every end-expiration window is a stretch of its own. A change
    over the limit in the reference's stretch (continuous motion) is a shift at once; in a
    later window it must show in two windows (two breaths): one window caught at another
    point of the breath, or fitted over a few frames, is not."""
    assert changed_across_stretches((0, 0), 0)
    assert not changed_across_stretches((3, 3), 0)
    assert not changed_across_stretches((0, 3), 0)
    assert changed_across_stretches((3, 4), 0)
    assert not changed_across_stretches((), 0)
    cfg = LocalizationConfig(tracking_reference_checks=2, tracking_confirmations=2)
    lim = TrackingLimits(0.05, 0.015, np.array([0.0, 1.0, 0.0]))

    def check(s, t, v_mm, segment):
        s = dataclasses.replace(s, segment=segment)
        return tracking_update(
            s, t, DriftEstimate(np.array(v_mm) * 1e-3, 0.001, 100), cfg, lim, phase=4
        )

    s = check(check(TrackingState(), 1.0, [0, 0, 0], 0), 1.5, [0, 0, 0], 0)
    window = check(check(s, 5.0, [0, 16, 0], 3), 5.5, [0, 16, 0], 3)  # one breath's window
    assert window.error == "" and window.change_m > 0.015
    window = check(check(window, 9.0, [0, 0.5, 0], 4), 9.5, [0, 1, 0], 4)  # the next: back
    assert window.error == "" and window.exceed_count == 0
    moved = check(check(window, 13.0, [0, 17, 0], 5), 17.0, [0, 17, 0], 6)  # two breaths
    assert "from where the first checks after it saw it" in moved.error
    still = check(check(s, 2.0, [0, 16, 0], 0), 2.5, [0, 16, 0], 0)  # no gating: at once
    assert "limit 11.0 mm" in still.error


def test_monitor_passes_a_still_kidney_its_template_misplaces_along_the_axis(template):
    """The pivot frames of a kidney longer than the template pull the template along the
    kidney's axis (half the length difference) although nothing moved: not motion."""
    along = X_BK.rotation().matrix()[:, 0] * 0.018
    state, drift = _run_monitor(template, along)
    assert drift == pytest.approx(0.018, abs=0.004)  # the apparent drift ...
    assert state.error == "" and state.judged_m < 0.006  # ... within the allowance
    assert state.limit_m == pytest.approx(0.015)
    plain = dataclasses.replace(LocalizationConfig(), tracking_axial_allowance=0.0)
    state, _ = _run_monitor(template, along, config=plain)  # the former rule: "moved"
    assert "from its registered pose" in state.error


@pytest.mark.parametrize("seed", range(5))
def test_group_medians_are_numpys_medians(seed):
    """One median per group, as np.median gives it: the middle value of an odd count, the
    mean of the two middle values of an even one; groups in any order, ties included."""
    rng = np.random.default_rng(seed)
    n_groups = int(rng.integers(1, 30))
    counts = rng.integers(1, 40, n_groups)
    counts[0], counts[-1] = 1, 2  # a single value and an even pair
    groups = np.repeat(np.arange(n_groups), counts)
    values = rng.normal(size=len(groups))
    values[rng.random(len(values)) < 0.2] = 0.5  # ties
    order = rng.permutation(len(groups))  # groups interleaved
    got = group_medians(values[order], groups[order], n_groups)
    want = np.array([np.median(values[groups == g]) for g in range(n_groups)])
    assert np.array_equal(got, want)
    assert np.count_nonzero(counts % 2) and np.count_nonzero(counts % 2 == 0)


def test_group_medians_need_every_group():
    with pytest.raises(ValueError, match="every group"):
        group_medians(np.ones(3), np.array([0, 0, 2]), 3)


def test_estimate_drift_reuses_neighbours_with_the_kd_trees_answer(
    template, monkeypatch, moving_nearest_doubles
):
    """The drift fit's nearest neighbours come from MovingNearest: the same drift, residual
    and frame count, bit for bit, as fresh kd-tree queries every iteration, with under half
    of the points sent to the tree (the points only slide by the fit's small steps)."""
    from scipy.spatial import cKDTree

    from drake_rus.localization import tracking

    rng = np.random.default_rng(7)
    section = long_axis_slab(template)
    z_B = X_BK.rotation().matrix()[:, 2]
    frames = [
        section + 0.003 * z_B + rng.normal(scale=0.0007, size=section.shape) for _ in range(8)
    ] + [section + 0.05 * z_B] * 2  # two outlier frames
    P = np.concatenate(frames)
    ids = np.repeat(np.arange(len(frames)), len(section))
    tree = cKDTree(template.points)
    Counted, Plain, made = moving_nearest_doubles

    args = (P, X_BK, template.points, template.normals)
    monkeypatch.setattr(tracking, "MovingNearest", Counted)
    fast = estimate_drift(*args, tree=tree, frame_ids=ids)
    calls = made[0].calls
    assert calls >= 10 and made[0].queried < 0.5 * calls * len(P), (calls, made[0].queried)
    monkeypatch.setattr(tracking, "MovingNearest", Plain)
    plain = estimate_drift(*args, tree=tree, frame_ids=ids)
    assert np.array_equal(fast.drift_B, plain.drift_B)
    assert fast.rms_residual == plain.rms_residual
    assert (fast.n_frames_used, fast.n_frames) == (plain.n_frames_used, plain.n_frames) == (8, 10)
    assert fast.magnitude > 0.002


def test_a_latched_error_clears_when_the_kidney_is_localized_again(template):
    """The error that started a re-localization must not meet the new registration: it
    clears as soon as the localizer drops its estimate (in EXPLORE, outside the checked
    phases), and the new registration is checked afresh (the history is kept)."""
    from pydrake.systems.analysis import Simulator

    imaging = ImagingConfig()
    geometry = ProbeGeometry.from_config(imaging)
    monitor = KidneyTrackingMonitor(template, LocalizationConfig(), imaging, [4])
    sim = Simulator(monitor)
    ctx = sim.get_mutable_context()
    R_KP = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    X_BP = X_BK.multiply(RigidTransform(RotationMatrix(R_KP), [0.0, 0.0, 0.06]))
    period = 1.0 / imaging.frame_rate_hz
    k = 0

    def run(outcome, phase, shift_B, seconds):
        nonlocal k
        monitor.GetInputPort("localization").FixValue(ctx, outcome)
        monitor.GetInputPort("phase").FixValue(ctx, [float(phase)])
        section = long_axis_slab(template, 0.0015) + np.asarray(shift_B)
        pixels, _ = geometry.B_to_pixel(section, X_BP)
        for _ in range(int(seconds / period)):
            monitor.GetInputPort("boundary_pixels").FixValue(
                ctx, BoundaryPixels(pixels, k * period, X_BP, k)
            )
            k += 1
            sim.AdvanceTo(k * period)
        return monitor.state(ctx), monitor.GetOutputPort("tracking_error").Eval(ctx)

    first = LocalizationOutcome(result=_result(), time=0.0)
    lateral = X_BK.rotation().matrix()[:, 2] * 0.02
    state, error = run(first, 4, lateral, 2.0)
    assert "from its registered pose" in error
    n_checks = len(state.history)
    state, error = run(LocalizationOutcome(round=1), 1, lateral, 0.2)  # re-exploring
    assert error == "" and state.frames == () and len(state.history) == n_checks
    # Re-registered where the kidney now is: checked afresh, consistent.
    moved = RigidTransform(X_BK.rotation(), X_BK.translation() + lateral)
    second = LocalizationOutcome(result=dataclasses.replace(_result(), X_BK=moved), time=5.0)
    state, error = run(second, 4, lateral, 2.0)
    assert error == "" and state.registered_at == 5.0 and len(state.history) > n_checks


def test_tangential_force_change_looks_back_by_the_lag():
    forces = ((0.0, 0.0, 0.0), (0.05, 0.5, 0.0), (0.10, 1.0, 0.0), (0.15, 3.0, 4.0))
    # Newest (3, 4) against the newest sample at least 0.1 s older: (0.5, 0) at 0.05 s.
    assert tangential_force_change(forces, 0.1) == pytest.approx(math.hypot(2.5, 4.0))
    assert tangential_force_change(forces, 0.15) == pytest.approx(5.0)
    assert math.isnan(tangential_force_change(forces, 0.2))  # nothing that old
    assert math.isnan(tangential_force_change((), 0.1))


def _slip(samples, config, phases=None, period=0.05):
    """slip_update over force samples f_P (3,) one period apart; the final state."""
    s = TrackingState()
    for k, f in enumerate(samples):
        phase = 4 if phases is None else phases[k]
        s = slip_update(s, k * period, f, phase, config, max_gap=2.5 * period)
    return s


def test_slip_update_catches_a_jump_of_the_tangential_force_after_the_settle_time():
    cfg = LocalizationConfig(tracking_slip_force=1.5)
    # The pivot turns the force slowly (0.28 N per 0.1 s; the normal force changes by 3 N,
    # which is not tangential): no slip.
    slow = [(-1.0 + 0.1 * k, -6.0 + 0.1 * k, -9.0 + 0.075 * k) for k in range(40)]
    s = _slip(slow, cfg)
    assert s.error == "" and s.slip_N == pytest.approx(math.hypot(0.2, 0.2))
    # The skin slides under the probe at 1.0 s: friction drags it by 2 N along x_P.
    slid = slow[:20] + [(f[0] + 2.0, f[1], f[2]) for f in slow[20:]]
    s = _slip(slid, cfg)
    assert "slid under the probe" in s.error and "2.2 N within 0.10 s" in s.error
    # The same jump within the settle time of the stretch (the probe's own start): no
    # error, nor when the check is off.
    s = _slip(slid[13:], cfg)  # the jump at 0.35 s
    assert s.error == "" and s.stretch_start == 0.0
    assert _slip(slid, LocalizationConfig()).error == ""
    # A new phase starts a new stretch (its own settle time); so does a gap in the samples
    # (the checks paused outside a breath-hold).
    s = _slip(slid, cfg, phases=[3] * 18 + [4] * 22)
    assert s.error == "" and s.stretch_start == pytest.approx(0.9)
    s = TrackingState()
    for k, f in enumerate(slid):
        t = k * 0.05 + (1.0 if k >= 18 else 0.0)  # no sample between 0.85 and 1.9 s
        s = slip_update(s, t, f, 4, cfg, max_gap=0.125)
    assert s.error == "" and s.stretch_start == pytest.approx(1.9)


def test_the_monitor_reports_a_patient_sliding_under_the_probe(template):
    """The LeafSystem feeds ``probe_force`` to the slip check in the checked phases while
    the scan may move, and reports a slip on ``tracking_error`` at once (no frames
    needed); outside a breath-hold the force is not judged."""
    from pydrake.systems.analysis import Simulator

    imaging = ImagingConfig()
    cfg = LocalizationConfig(tracking_slip_force=1.5)

    def run(allowed, slip_check=True):
        monitor = KidneyTrackingMonitor(template, cfg, imaging, [4], slip_check=slip_check)
        sim = Simulator(monitor)
        ctx = sim.get_mutable_context()
        monitor.GetInputPort("localization").FixValue(
            ctx, LocalizationOutcome(result=_result(), time=0.0)
        )
        monitor.GetInputPort("phase").FixValue(ctx, [4.0])
        monitor.GetInputPort("motion_allowed").FixValue(ctx, [allowed])
        monitor.GetInputPort("boundary_pixels").FixValue(ctx, BoundaryPixels(np.zeros((0, 2))))
        force = monitor.GetInputPort("probe_force")
        force.FixValue(ctx, [0.0, 0.0, 0.0, -0.5, 0.2, -9.0])
        sim.AdvanceTo(1.0)
        quiet = monitor.GetOutputPort("tracking_error").Eval(ctx)
        force.FixValue(ctx, [0.0, 0.0, 0.0, 1.8, 0.2, -9.0])  # dragged along x_P
        sim.AdvanceTo(1.2)
        return quiet, monitor.GetOutputPort("tracking_error").Eval(ctx)

    quiet, slid = run(1.0)
    assert quiet == "" and "slid under the probe: its tangential force changed by 2.3 N" in slid
    assert run(0.0) == ("", "")
    assert run(1.0, slip_check=False) == ("", "")  # gated free breathing: not judged


def test_the_monitor_answers_whether_the_pivots_view_contradicts_the_fit(template):
    """During PIVOT the monitor keeps the pivot frames' boundary points and answers, on
    ``pivot_view``, with the verdict's rule against the explored cloud: stamped with the
    time of the newest frame covered; off without ``pivot_view``."""
    from pydrake.systems.analysis import Simulator

    from drake_rus.imaging.frames import PointCloud
    from drake_rus.localization.pivot_view import PIVOT_VIEW_CONTRADICTS

    imaging = ImagingConfig()
    geometry = ProbeGeometry.from_config(imaging)
    R_KP = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    X_BP = X_BK.multiply(RigidTransform(RotationMatrix(R_KP), [0.0, 0.0, 0.06]))
    period = 1.0 / imaging.frame_rate_hz
    # The explored cloud on the registered template (its residual 0); the pivot's section
    # 2 mm off it across the body (the tracking limit is larger: no tracking error).
    cloud = PointCloud(points=X_BK.multiply(np.asarray(template.points, float).T).T)
    section = long_axis_slab(template, 0.0015) + X_BK.rotation().matrix()[:, 2] * 0.002
    pixels, _ = geometry.B_to_pixel(section, X_BP)

    def run(pivot_view, phase=4, seconds=1.0):
        monitor = KidneyTrackingMonitor(
            template, LocalizationConfig(), imaging, [4], pivot_view=pivot_view, pivot_phase=4
        )
        sim = Simulator(monitor)
        ctx = sim.get_mutable_context()
        monitor.GetInputPort("localization").FixValue(
            ctx, LocalizationOutcome(result=_result(), time=0.0)
        )
        monitor.GetInputPort("phase").FixValue(ctx, [float(phase)])
        monitor.GetInputPort("partial_cloud").FixValue(ctx, cloud)
        for k in range(int(seconds / period)):
            monitor.GetInputPort("boundary_pixels").FixValue(
                ctx, BoundaryPixels(pixels, k * period, X_BP, k)
            )
            sim.AdvanceTo((k + 1) * period)
        state = monitor.state(ctx)
        return state, monitor.GetOutputPort("pivot_view").Eval(ctx)

    # Excess 0: any pivot boundary farther off than the cloud contradicts the fit.
    state, (covered, error) = run((90.0, 0.0, "none"))
    assert state.error == "" and len(state.pivot_points) > 10
    assert error.startswith(PIVOT_VIEW_CONTRADICTS), error
    seen = float(error.split("pivot boundary ")[1].split(" mm")[0])
    assert seen == pytest.approx(2.0, abs=0.5)  # 2 mm, and the pixels' quantization
    assert 0.5 <= covered <= 1.0  # a check every tracking_period (0.5 s), stamped
    # The shipped bound (1.25 x the RMS bound) accepts 2 mm.
    _, (covered, error) = run((90.0, 1.25, "none"))
    assert error == "" and covered >= 0.5
    # Not in PIVOT (TRANSIT), or switched off: no answer.
    state, (covered, _) = run((90.0, 0.0, "none"), phase=3)
    assert math.isnan(covered) and state.pivot_points == ()
    _, (covered, _) = run(None)
    assert math.isnan(covered)
