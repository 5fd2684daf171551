"""The start planner (drake_rus.scan.planning.PlanStart): an acoustic window like a
sonographer's, on synthetic bodies whose answer is known."""

import types

import numpy as np
import pytest
import trimesh
from pydrake.math import RigidTransform

from drake_rus.anatomy.labels import Label, LabelVolume
from drake_rus.imaging.config import ImagingConfig
from drake_rus.scan.config import StartConfig
from drake_rus.scan.planning import PlanStart, StartPlanError, probe_rotation

VOXEL = 0.002


def box_body(kidney_depth=0.09, blocker=None, size=(0.30, 0.30, 0.24), rib_y=None):
    """A box torso (x across, y along the body, z up; bed at z = 0) with an ellipsoidal
    kidney ``kidney_depth`` below the top skin, and optionally a bar of ``blocker`` label
    (bone or gas) 20-30 mm under the skin straight above the kidney, 30 mm wide across the
    body and as long as the kidney, or a rib: a bone bar across the whole body 20-30 mm
    under the skin over ``rib_y`` = (y_min, y_max) (m). Patient frame = B."""
    sx, sy, sz = size
    skin = trimesh.creation.box(extents=size)
    skin.apply_translation([0.0, 0.0, sz / 2])
    kidney = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    kidney.apply_scale([0.025, 0.05, 0.02])
    center = np.array([0.0, 0.0, sz - kidney_depth])
    kidney.apply_translation(center)
    shape = np.round(np.array(size) / VOXEL).astype(int)
    labels = np.full(shape, Label.SOFT_TISSUE, np.uint8)
    X_PtV = RigidTransform([-sx / 2, -sy / 2, 0.0])
    idx = np.indices(shape).reshape(3, -1).T
    p = idx * VOXEL + X_PtV.translation()
    inside = (((p - center) / [0.025, 0.05, 0.02]) ** 2).sum(axis=1) <= 1.0
    labels.reshape(-1)[inside] = Label.KIDNEY_CORTEX
    if blocker is not None:
        slab = (
            (np.abs(p[:, 0]) < 0.015)
            & (np.abs(p[:, 1]) < 0.07)
            & (p[:, 2] > sz - 0.03)
            & (p[:, 2] < sz - 0.02)
        )
        labels.reshape(-1)[slab] = blocker
    if rib_y is not None:
        rib = (
            (p[:, 1] >= rib_y[0])
            & (p[:, 1] <= rib_y[1])
            & (p[:, 2] > sz - 0.03)
            & (p[:, 2] < sz - 0.02)
        )
        labels.reshape(-1)[rib] = Label.BONE
    return types.SimpleNamespace(
        skin_mesh=skin, kidney_mesh=kidney, side="right", labels=LabelVolume(labels, VOXEL, X_PtV)
    )


X_BPT = RigidTransform([0.55, 0.0, 0.0])


def test_clear_body_gets_the_vertical_window_and_the_shallowest_preset():
    plan = PlanStart(
        box_body(0.09),
        X_BPT,
        ImagingConfig(),
        StartConfig(placement_error=0.0, placement_error_angle_deg=0.0),
    )
    assert plan.window.tilt_deg == 0.0
    np.testing.assert_allclose(plan.window.approach_B, [0, 0, -1], atol=1e-12)
    # Kidney far side 0.09 + 0.02 m below the skin, + 10 mm margin -> the 150 mm preset.
    assert plan.window.needed_depth == pytest.approx(0.12, abs=0.004)
    assert plan.depth_preset == 0.15
    # The start hovers 15 mm above the top skin, over the kidney's superior part.
    p = plan.X_start.translation()
    assert p[2] == pytest.approx(0.24 + 0.015, abs=1e-6)
    assert 0.0 < p[1] < 0.05 and abs(p[0] - 0.55) < 1e-6
    deeper = PlanStart(box_body(0.15), X_BPT, ImagingConfig(), StartConfig())
    assert deeper.depth_preset == 0.20


@pytest.mark.parametrize("blocker", [Label.BONE, Label.GAS])
def test_bone_or_gas_in_the_straight_path_moves_the_window(blocker):
    clear = PlanStart(box_body(blocker=None), X_BPT, ImagingConfig(), StartConfig())
    blocked = PlanStart(box_body(blocker=blocker), X_BPT, ImagingConfig(), StartConfig())
    assert clear.window.tilt_deg == 0.0
    assert abs(blocked.window.tilt_deg) > 0.0
    vertical = [c for c in blocked.candidates if c.tilt_deg == 0.0][0]
    assert not vertical.feasible and "bone or gas" in vertical.reason
    assert len(vertical.blockers_B) > 0
    assert blocked.window.blocked_fraction <= StartConfig().max_blocked_fraction


def test_a_rib_across_the_sweep_moves_the_start_past_it():
    """The kidney spans y in [-0.05, 0.05]; a "-y" scan starts near y = 0.04. A rib across
    the body at y in [0.020, 0.028] shadows the sweep 12 mm after that start: the planner
    starts past the rib (every tilt meets it), where the whole sweep is clear."""
    cfg = StartConfig(placement_error=0.0, placement_error_angle_deg=0.0, max_start_shift=0.3)
    clear = PlanStart(box_body(), X_BPT, ImagingConfig(), cfg, exploration_ratio=0.5)
    assert clear.window.start_fraction == pytest.approx(0.1)
    assert clear.window.clear_length == pytest.approx(clear.window.sweep_length)
    ribbed = PlanStart(
        box_body(rib_y=(0.020, 0.028)), X_BPT, ImagingConfig(), cfg, exploration_ratio=0.5
    )
    w = ribbed.window
    assert w.start_fraction > 0.1 + 1e-9
    assert ribbed.X_start.translation()[1] < 0.020  # past the rib, scanning -y
    assert w.clear_length == pytest.approx(w.sweep_length) and w.sweep_shadowed == 0.0
    s = ribbed.summary()
    assert s["sweep_clear_mm"] == s["sweep_checked_mm"] > 0
    # The first start's sweep meets the rib: it is clear for less than the minimum.
    first = evaluate_first_start(box_body(rib_y=(0.020, 0.028)), cfg)
    assert first.clear_length < cfg.min_clear_sweep and "shadows the kidney" in first.warning
    assert first.feasible and not ribbed.window.warning
    # No later start allowed: the planner still gives the window, with the warning said.
    stuck = PlanStart(
        box_body(rib_y=(0.020, 0.028)),
        X_BPT,
        ImagingConfig(),
        StartConfig(placement_error=0.0, placement_error_angle_deg=0.0, max_start_shift=0.0),
        exploration_ratio=0.5,
    )
    assert stuck.window.start_fraction == pytest.approx(0.1)
    assert stuck.window.clear_length < cfg.min_clear_sweep
    assert "10 mm into the sweep" in stuck.summary()["warning"]


def test_a_long_exploration_still_gets_a_start_past_the_rib():
    """ER 0.7 (the default): the rib at 22-30% of the kidney from its superior end needs a
    start at 35%. Its sweep would end at 105% of the kidney; it runs to the far pole (95%
    checked), still covering the paper's 60% (start.min_sweep_fraction), so it is tried and
    taken. Requiring the whole ER inside 95% (min_sweep_fraction = ER, the old rule) leaves
    no start past 25%: the window keeps the rib in its sweep, with the warning said."""
    base = dict(placement_error=0.0, placement_error_angle_deg=0.0, max_start_shift=0.3)
    body = box_body(rib_y=(0.020, 0.028))
    plan = PlanStart(body, X_BPT, ImagingConfig(), StartConfig(**base), exploration_ratio=0.7)
    w = plan.window
    assert w.start_fraction == pytest.approx(0.35) and not w.warning
    assert plan.X_start.translation()[1] < 0.020  # past the rib
    assert w.sweep_length == pytest.approx(0.06, abs=0.003)  # 35% -> 95% of 100 mm
    assert w.clear_length == pytest.approx(w.sweep_length)
    old = PlanStart(
        body,
        X_BPT,
        ImagingConfig(),
        StartConfig(**base, min_sweep_fraction=0.7),
        exploration_ratio=0.7,
    )
    assert old.window.start_fraction < 0.3 and old.window.warning


def test_a_short_clipped_sweep_is_not_preferred_for_being_short():
    """A later start's sweep, cut at the far pole, is clear more easily than an earlier
    start's full one. With "covered" meaning min_sweep_fraction of the kidney (60 mm of a
    100 mm kidney here), a vertical window clear for 65 of its 70 mm ranks before a tilted
    late start clear for its whole 60 mm (longest clear sweep); without it (the whole sweep
    must be clear) the late start would win for being short."""
    from drake_rus.scan.planning import WindowCandidate, window_rank

    def window(tilt, start, sweep, clear, covered):
        return WindowCandidate(
            tilt,
            np.array([0.0, 0.0, -1.0]),
            np.zeros((3, 3)),
            0.12,
            0.0,
            False,
            np.zeros((0, 3)),
            0.15,
            start_fraction=start,
            sweep_length=sweep,
            clear_length=clear,
            covered_length=covered,
        )

    early = window(0.0, 0.10, 0.070, 0.065, 0.060)
    late = window(20.0, 0.35, 0.060, 0.060, 0.060)
    assert window_rank(early, 0.15) < window_rank(late, 0.15)
    early.covered_length = late.covered_length = 0.0  # the whole sweep must be clear
    assert window_rank(late, 0.15) < window_rank(early, 0.15)
    # The evaluated windows carry it: on a clear body the earliest start, covered at 60 mm.
    cfg = StartConfig(placement_error=0.0, placement_error_angle_deg=0.0, max_start_shift=0.3)
    plan = PlanStart(box_body(), X_BPT, ImagingConfig(), cfg, exploration_ratio=0.7)
    assert plan.window.start_fraction == pytest.approx(0.1)
    assert plan.window.covered_length == pytest.approx(0.06, abs=0.003)


def evaluate_first_start(body, cfg):
    from drake_rus.scan.planning import evaluate_windows

    superior_B = X_BPT.rotation().matrix()[:, 1]
    kidney_B = X_BPT.multiply(np.asarray(body.kidney_mesh.vertices).T).T
    return evaluate_windows(
        body,
        X_BPT,
        ImagingConfig(),
        cfg,
        0.0,
        superior_B,
        kidney_B,
        X_BPT @ body.labels.X_PtV,
        exploration_ratio=0.5,
    )[0]


def test_unreachable_windows_are_refused_with_a_clear_message():
    with pytest.raises(StartPlanError, match="cannot reach"):
        PlanStart(box_body(), X_BPT, ImagingConfig(), StartConfig(), reachable=lambda X: False)
    # Only tilted windows reachable: the planner takes one of them.
    plan = PlanStart(
        box_body(),
        X_BPT,
        ImagingConfig(),
        StartConfig(),
        reachable=lambda X: X.rotation().matrix()[2, 2] > -0.999,
    )
    assert abs(plan.window.tilt_deg) > 0.0


def test_a_kidney_deeper_than_every_preset_is_refused():
    imaging = ImagingConfig(depth_presets=[0.10, 0.15])
    with pytest.raises(StartPlanError, match="deepest preset 150 mm"):
        PlanStart(box_body(0.15), X_BPT, imaging, StartConfig(max_tilt_deg=0.0))


def test_placement_error_has_the_configured_size_and_is_seeded():
    cfg = StartConfig(placement_error=0.005, placement_error_angle_deg=3.0)
    a = PlanStart(box_body(), X_BPT, ImagingConfig(), cfg, seed=1)
    b = PlanStart(box_body(), X_BPT, ImagingConfig(), cfg, seed=1)
    c = PlanStart(box_body(), X_BPT, ImagingConfig(), cfg, seed=2)
    offset = a.X_start.translation() - a.X_planned.translation()
    assert np.linalg.norm(offset) == pytest.approx(0.005)
    assert abs(offset @ a.window.approach_B) < 1e-9  # across the beam
    angle = a.X_start.rotation().inverse().multiply(a.X_planned.rotation()).ToAngleAxis().angle()
    assert angle == pytest.approx(np.radians(3.0))
    np.testing.assert_allclose(a.X_start.GetAsMatrix4(), b.X_start.GetAsMatrix4())
    assert not np.allclose(a.X_start.translation(), c.X_start.translation())
    s = a.summary()
    assert s["placement_error_mm"] == pytest.approx(5.0) and s["depth_preset_m"] == 0.15


def test_probe_rotation_is_a_transverse_view():
    R = probe_rotation([0.0, 0.0, -1.0], [0.0, 1.0, 0.0]).matrix()
    np.testing.assert_allclose(R, np.diag([1.0, -1.0, -1.0]), atol=1e-12)
    tilted = probe_rotation([0.5, 0.0, -np.sqrt(0.75)], [0.0, 1.0, 0.0]).matrix()
    assert abs(tilted[:, 0] @ [0, 1, 0]) < 1e-12  # the array stays across the body
    assert np.linalg.det(tilted) == pytest.approx(1.0)


def test_fan_rays_leave_the_curved_face_across_its_width():
    from drake_rus.scan.planning import fan_rays

    skin = np.array([0.5, 0.0, 0.2])
    origins, dirs = fan_rays(skin, [0, 0, -1], [1, 0, 0], 0.05, 40.0, n_rays=9)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0)
    np.testing.assert_allclose(origins[4], skin, atol=1e-12)  # central ray
    np.testing.assert_allclose(dirs[4], [0, 0, -1], atol=1e-12)
    apex = skin + np.array([0, 0, 0.05])
    np.testing.assert_allclose(np.linalg.norm(origins - apex, axis=1), 0.05)
    # The edge rays leave the face 50 mm x sin(20 deg) = 17.1 mm either side of its centre.
    assert origins[0, 0] - skin[0] == pytest.approx(-0.05 * np.sin(np.radians(20)))
    assert origins[-1, 0] - skin[0] == pytest.approx(0.05 * np.sin(np.radians(20)))


def test_a_bar_under_one_side_of_the_face_blocks_those_rays_only():
    """Bone 20-30 mm under the skin only at x > 0.008 (body frame = B): the rays leaving the
    face's +x side cross it, the central ray and the -x side do not."""
    from drake_rus.scan.planning import check_view

    body = box_body()
    lab = body.labels.labels
    p = np.indices(lab.shape).reshape(3, -1).T * VOXEL + body.labels.X_PtV.translation()
    bar = (p[:, 0] > 0.008) & (p[:, 2] > 0.24 - 0.03) & (p[:, 2] < 0.24 - 0.02)
    lab.reshape(-1)[bar] = Label.BONE
    X_BV = X_BPT @ body.labels.X_PtV
    kidney_B = X_BPT.multiply(np.asarray(body.kidney_mesh.vertices).T).T
    v = check_view(
        body.labels,
        X_BV,
        np.array([0.55, 0.0, 0.24]),
        np.array([0.0, 0, -1]),
        np.array([1.0, 0, 0]),
        ImagingConfig(),
        kidney_B,
        0.0,
    )
    assert v.rays_to_kidney > 0 and not v.central_blocked
    assert 0 < v.blocked_rays < v.rays_to_kidney
    assert np.all(v.blockers_B[:, 0] > 0.55 + 0.008 - VOXEL)
    assert v.needed_depth == pytest.approx(0.09 + 0.02, abs=0.003)


def test_vertical_depth_preset_ignores_shadows_but_not_depth():
    """The kinematic twin's depth: the preset holding the kidney under a vertical probe,
    also where bone over the kidney makes the vertical window unusable for a scan."""
    from drake_rus.scan.planning import vertical_depth_preset

    cfg = StartConfig(max_tilt_deg=0.0)
    blocked = box_body(blocker=Label.BONE)
    with pytest.raises(StartPlanError, match="bone or gas"):
        PlanStart(blocked, X_BPT, ImagingConfig(), cfg)
    assert vertical_depth_preset(blocked, X_BPT, ImagingConfig(), cfg) == 0.15
    assert vertical_depth_preset(box_body(0.15), X_BPT, ImagingConfig(), cfg) == 0.20
    with pytest.raises(StartPlanError, match="deepest preset 150 mm"):
        vertical_depth_preset(box_body(0.15), X_BPT, ImagingConfig(depth_presets=[0.1, 0.15]), cfg)


def test_the_scan_starts_in_the_posture_closest_to_the_scenarios_posture():
    """``robot.initial_joint_positions`` chooses among the postures that put the probe at the
    planned start pose (the arm's redundancy, here the elbow's split between joints 1 and
    3); before, the scan always started closest to the default and ignored the field."""
    from drake_rus.anatomy import load_patient
    from drake_rus.robot.kinematics import TipKinematics
    from drake_rus.robot.model import MakeControlPlant
    from drake_rus.scan.run import PrepareScenario
    from drake_rus.scenario import ApplyOverrides, LoadScenario

    patient = load_patient("test:0", progress=False)
    default, X_start, _ = PrepareScenario(LoadScenario(scenario_name="quick"), patient)
    split = ApplyOverrides(
        LoadScenario(scenario_name="quick"),
        "{robot: {initial_joint_positions: [0.5, 0.15, -0.5, -2.0, 0.0, 2.15, 0.785]}}",
        "test",
    )
    split, X_start_split, _ = PrepareScenario(split, patient)
    q_default = np.array(default.robot.initial_joint_positions)
    q_split = np.array(split.robot.initial_joint_positions)
    assert abs(q_default[0]) < 0.15 and abs(q_default[2]) < 0.15  # the default's elbow
    assert abs(q_split[0] - 0.5) < 0.15 and abs(q_split[2] + 0.5) < 0.15  # the scenario's
    assert X_start_split.IsNearlyEqualTo(X_start, 1e-9)  # the same start pose ...
    kin = TipKinematics(*MakeControlPlant(split.robot, split.probe))
    assert kin.pose(q_split).IsNearlyEqualTo(X_start, 2e-3)  # ... reached by both
