"""Issue 31: the kidney found again after a pivot leg (the registered template's predicted
section as the tracker's prior) and the "segmentation lost" stop telling an expected absence
from a loss."""

import dataclasses
import math

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix

from drake_rus.control import supervisor
from drake_rus.control.config import ControllerConfig
from drake_rus.control.laws import template_section_area
from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.imaging.segment import (
    KidneyTrack,
    predicted_section,
    track_prior,
    track_settings,
    track_update,
    tracked_component,
)


def ellipsoid_points(a, b, c, n=4000, seed=0):
    """(n, 3) points on the surface of an ellipsoid with semi-axes a, b, c (m) at the origin."""
    u = np.random.default_rng(seed).normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u * [a, b, c]


GEOMETRY = ProbeGeometry.from_config(ImagingConfig())
# A small kidney-like ellipsoid 90 mm below the probe face, long axis along the array.
A, B, C, DEPTH = 0.030, 0.015, 0.012, 0.090


def _surface_B(dy=0.0):
    return ellipsoid_points(A, B, C) + [0.0, dy, DEPTH]


def test_predicted_section_is_the_template_cut_by_the_image_plane():
    X_BP = RigidTransform()  # P = B: the image plane is x-z, y across it
    section = predicted_section(_surface_B(), X_BP, GEOMETRY, slab=0.005)
    area = section.sum() * GEOMETRY.pixel_area
    assert area == pytest.approx(math.pi * A * C, rel=0.1)
    # Its centre lies where the kidney's centre projects.
    v, u = np.nonzero(section)
    p = GEOMETRY.pixel_to_P(np.array([[u.mean(), v.mean()]]))[0]
    np.testing.assert_allclose([p[0], p[2]], [0.0, DEPTH], atol=0.002)
    # The kidney beside the plane (beyond the slab): nothing predicted.
    assert not predicted_section(_surface_B(dy=0.030), X_BP, GEOMETRY, 0.005).any()
    # The same area from the supervisor's point-set version (the pivot model's fan).
    got = template_section_area(
        np.eye(3),
        np.array([0.0, 0.0, DEPTH]),
        ellipsoid_points(A, B, C),
        np.eye(3),
        np.zeros(3),
        probe_radius=GEOMETRY.radius,
        half_angle=GEOMETRY.half_angle,
        depth=GEOMETRY.depth,
        slab_half_width=0.005,
    )
    assert got == pytest.approx(area, rel=0.05)


def _disc(centre_uv, radius_px):
    v, u = np.mgrid[0 : GEOMETRY.height_px, 0 : GEOMETRY.width_px]
    return ((u - centre_uv[0]) ** 2 + (v - centre_uv[1]) ** 2 <= radius_px**2) & GEOMETRY.fan_mask


def _run(sequence, sections, dt=0.05, **kw):
    """The Segmenter's per-frame rule on a sequence of candidate regions: returns, per frame,
    the index of the region taken for the kidney (None: none)."""
    cfg = ImagingConfig()
    track = KidneyTrack()
    taken = []
    for i, (regions, section) in enumerate(zip(sequence, sections)):
        t = i * dt
        prev, age = track_prior(track, t, cfg.track_confirm)
        k = tracked_component(
            regions,
            prev,
            age,
            GEOMETRY,
            max_gap=cfg.track_gap,
            reach=cfg.track_reach,
            min_overlap=cfg.track_min_overlap,
            section=section,
            section_reach=cfg.track_section_reach,
            **kw,
        )
        mask = regions[k] if k is not None else np.zeros(GEOMETRY.image_shape, bool)
        track = track_update(
            track,
            mask,
            k is not None,
            t,
            GEOMETRY,
            **track_settings(cfg),
        )
        taken.append(k)
    return taken


def _pivot_sequence():
    """A pivot leg on synthetic frames: the kidney (a disc) is followed for 1 s while it
    shrinks towards the image's left edge (the leg's end), is gone for 0.5 s, then a small
    hypoechoic blob appears where it left and stays; the kidney re-enters 0.5 s later on the
    image's other side (the return leg sees it from the other side of its pole)."""
    seq, sections, kidney_index = [], [], []
    blob = _disc((60, 110), 6)
    for i in range(20):  # followed, shrinking at the left
        seq.append([_disc((70, 110), 24 - i)])
        kidney_index.append(0)
    for _ in range(10):  # gone past the pivot end
        seq.append([])
        kidney_index.append(None)
    for _ in range(10):  # a blob where it left
        seq.append([blob])
        kidney_index.append(None)
    for i in range(30):  # the kidney re-enters on the right; the blob stays
        seq.append([_disc((175, 120), 8 + i), blob])
        kidney_index.append(0)
    # The registered template: the kidney's section where it is (a little larger, shifted
    # by a registration error of 5 mm), nothing past the pivot end.
    shift = int(round(0.005 / GEOMETRY.dx))
    for i in range(70):
        if i < 20:
            sections.append(_disc((70 + shift, 110), 26 - i))
        elif i < 40:
            sections.append(None)
        else:
            sections.append(_disc((175 + shift, 120), 12 + (i - 40)))
    return seq, sections, kidney_index


def test_track_settings_read_each_tracker_field_of_the_config():
    """Every follower of the kidney (the Segmenter, the kinematic imager, the benchmarks)
    takes the tracker's settings from one place: each field goes to its own argument, and
    the gap decides whether a mask continues the track."""
    cfg = dataclasses.replace(
        ImagingConfig(), track_gap=0.7, track_reach=0.013, track_min_overlap=0.3
    )
    assert track_settings(cfg) == {"max_gap": 0.7, "reach": 0.013, "min_overlap": 0.3}
    disc = _disc((100, 120), 20)
    track = track_update(KidneyTrack(), disc, True, 0.0, GEOMETRY, **track_settings(cfg))
    within = track_update(track, disc, True, 0.5, GEOMETRY, **track_settings(cfg))
    beyond = track_update(track, disc, True, 0.9, GEOMETRY, **track_settings(cfg))
    assert within.since == 0.0  # continued: 0.5 s < track_gap
    assert beyond.since == 0.9  # a new track: 0.9 s > track_gap


def test_the_kidney_is_found_again_after_a_pivot_leg_with_the_template_prior():
    seq, sections, truth = _pivot_sequence()
    # Without the template: the blob that continues the last small section is followed and
    # the re-entering kidney, which does not continue it, is refused for the 2 s track gap.
    without = _run(seq, [None] * len(seq))
    assert without[30] == 0  # the blob taken for the kidney
    assert all(without[i] == 1 for i in range(40, 70))  # ... and followed: kidney missed
    # With it: the kidney is taken from its first frame back in view, the blob never after.
    with_prior = _run(seq, sections)
    assert with_prior[:20] == truth[:20]
    assert all(with_prior[i] == 0 for i in range(40, 70))
    assert all(k is None for k in with_prior[20:30])


def test_a_region_the_template_does_not_put_the_kidney_in_is_not_the_kidney():
    blob = _disc((60, 110), 10)
    section = _disc((180, 120), 20)
    assert (
        tracked_component(
            [blob], None, math.inf, GEOMETRY, max_gap=2.0, reach=0.01, section=section
        )
        is None
    )
    # No prediction (past the template's end, or no registration yet): the largest region.
    assert (
        tracked_component(
            [blob],
            None,
            math.inf,
            GEOMETRY,
            max_gap=2.0,
            reach=0.01,
            section=np.zeros_like(section),
        )
        == 0
    )
    # A region continuing the last mask beyond the template's end is kept.
    last = _disc((62, 110), 10)
    assert (
        tracked_component([blob], last, 0.05, GEOMETRY, max_gap=2.0, reach=0.01, section=section)
        == 0
    )


# ------------------------------------------------------------- expected absence (PIVOT)
def test_absence_expected_rule():
    rule = supervisor.absence_expected
    ref, min_area = 20e-4, 1e-4
    # No registered template: the old rule (after a leg's end, until seen again).
    assert rule(True, math.nan, math.nan, min_area, 0.5)
    assert not rule(False, math.nan, math.nan, min_area, 0.5)
    # The template puts the kidney out of view (past a pivot end): expected, leg end or not.
    assert rule(False, 0.0, ref, min_area, 0.5)
    assert rule(True, 0.5e-4, ref, min_area, 0.5)
    # After a leg's end, while the template's section is small (its overhang at the pole).
    assert rule(True, 0.3 * ref, ref, min_area, 0.5)
    # ... but not once the probe is back over the kidney: not finding it there is a loss.
    assert not rule(True, 0.6 * ref, ref, min_area, 0.5)
    # Anywhere the template puts the kidney in view during a leg: required.
    assert not rule(False, 0.2 * ref, ref, min_area, 0.5)


def _inputs(t, R, p, visible, R_BK, p_BK, model):
    return supervisor.SupervisorInputs(
        t=t,
        R_BP=np.asarray(R),
        p_BP=np.asarray(p, float),
        F_z=9.0,
        kidney_visible=visible,
        c_msk=0.5,
        R_BK=R_BK,
        p_BK=p_BK,
        pivot_model=model,
    )


def _pivot_until(c, visible_rule, t_max=20.0):
    """A PIVOT with a registered template (an ellipsoid kidney 100 mm under the pivot
    point, long axis along the array): returns [(tilt, kidney seen, watchdog armed,
    template section m^2)] per period and the final state."""
    dt = 0.01
    R_BK = RotationMatrix(RollPitchYaw(0.0, 0.0, math.pi / 2)).matrix()  # x_K along base y
    p_BK = np.array([0.55, 0.0, 0.0])
    model = supervisor.PivotModel(points_K=ellipsoid_points(0.050, 0.025, 0.020, n=3000))
    R_star, p_star = supervisor.optimal_pivot_pose(R_BK, p_BK)
    p_tip = np.array([p_star[0], p_star[1], 0.10])
    s = supervisor.SupervisorState(
        phase=supervisor.Phase.TRANSIT,
        a_des=R_star[:, 2].copy(),
        o_des=R_star[:, 0].copy(),
        p_star=p_star,
        initialised=True,
    )
    t = 0.0
    s = supervisor.supervisor_step(s, _inputs(t, R_star, p_tip, True, R_BK, p_BK, model), c, dt)
    assert s.phase == supervisor.Phase.PIVOT
    out = []
    while s.phase == supervisor.Phase.PIVOT and t < t_max:
        t += dt
        R = np.column_stack([s.o_des, np.cross(s.a_des, s.o_des), s.a_des])  # probe follows
        seen = visible_rule(s)
        s = supervisor.supervisor_step(s, _inputs(t, R, p_tip, seen, R_BK, p_BK, model), c, dt)
        if s.phase == supervisor.Phase.PIVOT:
            out.append((s.pivot_angle, seen, supervisor.segmentation_required(s), s.section_area))
    return out, s


def test_the_watchdog_is_armed_where_the_template_puts_the_kidney_in_view():
    c = dataclasses.replace(
        ControllerConfig(), pivot_follow_limit=3.2, pivot_rate=0.1, visibility_debounce=0.15
    )
    # The segmentation sees the kidney on the first leg while the template does (a
    # section of at least 3 cm^2), then never again (a lost kidney).
    lost = {"leg2": False}

    def rule(s):
        if s.pivot_legs_done >= 1:
            lost["leg2"] = True
        return (
            not lost["leg2"] and s.section_area >= 3e-4 if math.isfinite(s.section_area) else True
        )

    rows, s = _pivot_until(c, rule, t_max=8.0)
    reference = s.section_reference
    assert reference > 10e-4  # the long-axis section at the pivot's start
    # Past the first leg's end, while the template's section is small: not required.
    after_end = [r for r in rows if r[0] > 0 and not r[1]]
    assert any(not armed for _, _, armed, _ in after_end)
    # Back over the kidney (the template's section at least half the reference), the kidney
    # not seen: required, so the safety layer's 1 s watchdog stops a scan that lost it.
    back = [armed for angle, seen, armed, area in rows if not seen and area >= 0.5 * reference]
    assert back and all(back)
    # Where the template puts the kidney out of view: never required.
    assert all(not armed for _, _, armed, area in rows if area < 1e-4)


def test_the_benchmark_says_whether_the_kidney_was_in_view_when_segmentation_was_lost():
    from types import SimpleNamespace

    from benchmarks._scan_rows import segmentation_lost_in_view
    from drake_rus.control.safety import SafetyEvent, StopReason
    from drake_rus.scan.diagram import FrameRecord
    from drake_rus.scenario import Scenario

    scenario = Scenario()
    depth = scenario.imaging.depth
    # True kidney voxels (2 mm) of an ellipsoid 90 mm under the probe at the origin.
    g = np.mgrid[-0.03:0.03:0.002, -0.016:0.016:0.002, -0.012:0.012:0.002].reshape(3, -1).T
    inside = ((g / [A, B, C]) ** 2).sum(axis=1) <= 1
    truth = SimpleNamespace(kidney_points_B=g[inside] + [0, 0, DEPTH], voxel_volume=0.002**3)

    def result(dy):
        frames = [
            FrameRecord(t, k, 4, RigidTransform([0.0, dy, 0.0]), False, 9.0)
            for k, t in enumerate(np.arange(0.0, 2.0, 0.05))
        ]
        events = [SafetyEvent(1.9, StopReason.SEGMENTATION_LOST, "kidney invisible")]
        return SimpleNamespace(safety_events=events, truth=truth, frames=frames, scenario=scenario)

    assert depth > DEPTH + C
    seen = segmentation_lost_in_view(result(0.0))
    assert seen["in_view"] and seen["frames"] in (20, 21)  # the last second's frames
    assert seen["frames_in_view"] == seen["frames"]
    away = segmentation_lost_in_view(result(0.05))  # the plane 50 mm beside the kidney
    assert not away["in_view"] and away["frames_in_view"] == 0
    ok = result(0.0)
    ok.safety_events = []
    assert segmentation_lost_in_view(ok) is None


# ------------------------------------------- the prior in every executor mode (Segmenter)
def _two_kidney_like_regions():
    """(config, geometry, frame, surface, left, right): a grey frame with two dark discs,
    the left one larger (the classical segmenter's pick without a prior), and a registered
    surface (a sphere) whose section in the frame is the right one."""
    from drake_rus.imaging.frames import KidneySurface, UsFrame

    cfg = ImagingConfig(segmenter="classical")
    g = ProbeGeometry.from_config(cfg)
    v, u = np.mgrid[0 : g.height_px, 0 : g.width_px]

    def disc(cu, cv, r):
        return ((u - cu) ** 2 + (v - cv) ** 2 <= r * r) & g.fan_mask

    left, right = disc(80, 120, 26), disc(175, 120, 20)
    image = np.where(g.fan_mask, 150, 0).astype(np.uint8)
    image[left | right] = 80
    centre = g.pixel_to_P(np.array([[175.0, 120.0]]))[0]  # X_BP = I: P is B
    surface = KidneySurface(ellipsoid_points(*(3 * [20 * g.dx])) + centre, time=0.0)
    frame = UsFrame(image, time=0.0, X_BP=RigidTransform(), frame_index=0)
    return cfg, g, frame, surface, left, right


def _segment_once(cfg, frame, surface, executor):
    """The Segmenter's mask of ``frame`` (direct, or hosted by ``executor``), with the
    ``kidney_surface`` input given ``surface`` (None: unconnected)."""
    import time

    from pydrake.systems.analysis import Simulator

    from drake_rus.imaging.systems import Segmenter

    seg = Segmenter(cfg, executor=executor, poll_period=0.01)
    if executor is not None and executor.mode == "worker":
        executor.warm_up()
    sim = Simulator(seg)
    ctx = sim.get_mutable_context()
    seg.GetInputPort("us_image").FixValue(ctx, frame)
    if surface is not None:
        seg.GetInputPort("kidney_surface").FixValue(ctx, surface)
    sim.Initialize()
    deadline = time.monotonic() + 120.0  # a bound on a hung worker, not a speed check
    while time.monotonic() < deadline:
        mask = seg.GetOutputPort("kidney_mask").Eval(ctx)
        if mask.frame_index == frame.frame_index:
            return mask.image
        sim.AdvanceTo(ctx.get_time() + 0.01)
        if executor is not None and executor.mode == "worker":
            time.sleep(0.01)
    raise AssertionError("the frame was never segmented")


@pytest.mark.parametrize("mode", ["direct", "inline", "worker"])
def test_the_template_prior_reaches_the_segmentation_wherever_it_runs(mode):
    """The registered surface goes with the frame to where it is segmented (in the loop, an
    inline executor, a worker process): the region the template puts the kidney in is
    taken, not the larger one beside it that is taken without a template."""
    from drake_rus.executor import InlineExecutor, WorkerExecutor

    cfg, g, frame, surface, left, right = _two_kidney_like_regions()
    executors = {
        "direct": lambda: None,
        "inline": lambda: InlineExecutor(0.05),
        "worker": lambda: WorkerExecutor(nice=0, lanes=("frames",)),
    }
    ex = executors[mode]()
    try:
        without = _segment_once(cfg, frame, None, ex)
        with_prior = _segment_once(cfg, frame, surface, ex)
    finally:
        if ex is not None:
            ex.close()
    assert (without & left).sum() > 0.8 * left.sum() and not (without & right).any()
    assert (with_prior & right).sum() > 0.8 * right.sum() and not (with_prior & left).any()


def test_the_classical_segmenter_takes_the_template_section_after_a_frame_without_kidney():
    """After a frame in which no kidney was found, the classical segmenter's previous mask is
    empty: the registered template's section is its prior then, so the region the template
    puts the kidney in is taken, not the larger one beside it."""
    from drake_rus.imaging.frames import UsFrame
    from drake_rus.imaging.systems import make_segmenter_backend, segment_frame

    cfg, g, frame, surface, left, right = _two_kidney_like_regions()
    frame = UsFrame(frame.image, time=0.05, X_BP=frame.X_BP, frame_index=1)
    nothing_seen = UsFrame(np.zeros(g.image_shape, bool), 0.0, frame.X_BP, 0)
    backend = make_segmenter_backend(cfg, g)

    def segment(surface_points):
        mask, _, _ = segment_frame(
            backend,
            g,
            cfg.min_kidney_area,
            frame,
            nothing_seen,
            follows=False,
            uses_prior=True,
            track_confirm=cfg.track_confirm,
            source="us_image",
            surface_points=surface_points,
            slab=0.5 * cfg.elevation_width,
        )
        return mask.image

    without = segment(None)
    with_template = segment(surface.points_B)
    assert (without & left).sum() > 0.8 * left.sum() and not (without & right).any()
    assert (with_template & right).sum() > 0.8 * right.sum()
    assert not (with_template & left).any()
