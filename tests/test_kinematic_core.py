"""Kinematic mode on a synthetic box body with an ellipsoidal kidney, and on one patient."""

import dataclasses
import math

import numpy as np
import pytest
import trimesh
from pydrake.math import RigidTransform, RotationMatrix

from drake_rus.anatomy.labels import Label, LabelVolume
from drake_rus.control.config import ControllerConfig
from drake_rus.experiments import kinematic as km
from drake_rus.experiments import kinematic_runs
from drake_rus.experiments import patients as run_patients
from drake_rus.experiments.specs import StudyTask
from drake_rus.imaging.config import ImagingConfig
from drake_rus.localization.config import LocalizationConfig

VOXEL = 0.002
SKIN_Z = 0.20  # body top in Pt (m)
CENTRE = np.array([0.0, 0.0, 0.11])  # kidney centre in Pt: 90 mm under the skin
SEMI = np.array([0.025, 0.055, 0.020])  # semi-axes along x_Pt, y_Pt (long), z_Pt
X_BPT = RigidTransform([0.5, 0.0, 0.0])


class SyntheticPatient:
    """Just what kinematic mode reads of a Patient: a box body, an ellipsoid kidney whose long
    axis lies along y_Pt (rotated by ``yaw`` about z), labels on a 2 mm grid."""

    def __init__(self, yaw: float = 0.0, centre=CENTRE, semi=SEMI):
        self.name, self.side, self.posture = "synthetic", "right", "supine"
        self.centre, self.semi = np.asarray(centre, float), np.asarray(semi, float)
        self.R = RotationMatrix.MakeZRotation(yaw).matrix()
        box = trimesh.creation.box(extents=[0.30, 0.50, SKIN_Z])
        box.apply_translation([0, 0, SKIN_Z / 2])
        self.skin_mesh = box
        sphere = trimesh.creation.icosphere(subdivisions=4)
        sphere.apply_scale(self.semi)
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = self.centre
        sphere.apply_transform(T)
        self.kidney_mesh = sphere
        # Canonical frame: x_k superior (+y_Pt turned by yaw), y_k lateral (-x_Pt for the
        # right kidney, supine), z = x cross y.
        x_k = self.R @ np.array([0.0, 1.0, 0.0])
        y_k = self.R @ np.array([-1.0, 0.0, 0.0])
        self.X_PtK = RigidTransform(
            RotationMatrix(np.column_stack([x_k, y_k, np.cross(x_k, y_k)])), self.centre
        )
        self._labels = None

    def inside(self, p_Pt):
        q = (np.asarray(p_Pt) - self.centre) @ self.R
        return np.sum((q / self.semi) ** 2, axis=1) <= 1.0

    @property
    def labels(self):
        if self._labels is None:
            lo = np.array([-0.15, -0.25, 0.0])
            shape = (150, 250, 100)
            ijk = np.indices(shape).reshape(3, -1).T
            p = lo + ijk * VOXEL
            lab = np.full(len(p), int(Label.SOFT_TISSUE), np.uint8)
            lab[self.inside(p)] = int(Label.KIDNEY_CORTEX)
            self._labels = LabelVolume(lab.reshape(shape), VOXEL, RigidTransform(lo))
        return self._labels

    def X_BK(self, X_BPt):
        return X_BPt.multiply(self.X_PtK)

    def kidney_mask(self, voxel_size=0.001):
        lo = self.centre - self.semi.max() - 2 * voxel_size
        n = int(np.ceil(2 * (self.semi.max() + 2 * voxel_size) / voxel_size)) + 1
        ijk = np.indices((n, n, n)).reshape(3, -1).T
        mask = self.inside(lo + ijk * voxel_size).reshape(n, n, n)
        return mask, RigidTransform(lo)


_CACHE = {}


def synthetic(yaw=0.0):
    if yaw not in _CACHE:
        _CACHE[yaw] = km.prepare_patient(SyntheticPatient(yaw), X_BPT)
    return _CACHE[yaw]


CTRL = ControllerConfig()
IMG = ImagingConfig()


def test_skin_height_map_matches_box_top():
    kp = synthetic()
    assert kp.skin(0.5, 0.0) == pytest.approx(SKIN_Z, abs=1e-9)
    assert kp.skin(0.47, 0.031) == pytest.approx(SKIN_Z, abs=1e-9)
    # Outside the cached grid: the single-ray fallback still finds the body.
    assert kp.skin(0.5, 0.2) == pytest.approx(SKIN_Z, abs=1e-9)


def test_exploration_frames_travel_and_boundary_on_the_kidney():
    kp = synthetic()
    imager = km.Imager(kp, IMG)
    sweep = km.explore(kp, imager, CTRL, exploration_ratio=0.5)
    step = CTRL.scan_speed / IMG.frame_rate_hz
    assert len(sweep.frames) == round(0.5 * CTRL.kidney_length / step) + 1
    assert sweep.travel[-1] == pytest.approx(0.5 * CTRL.kidney_length)
    ys = np.array([X.translation()[1] for X in sweep.poses])
    assert np.all(np.diff(ys) < 0)  # "-y": superior to inferior
    assert ys[0] == pytest.approx(kp.roi.y_max)  # starts at the E-ROI's end
    for X in sweep.poses:  # tip on the skin, pointing down
        assert X.translation()[2] == pytest.approx(SKIN_Z)
        np.testing.assert_allclose(X.rotation().matrix()[:, 2], [0, 0, -1], atol=1e-12)
    P = sweep.point_cloud()
    assert len(P) > 500
    # Boundary points lie on the ellipsoid within about a voxel.
    q = X_BPT.inverse().multiply(P.T).T - CENTRE
    r = np.sqrt(np.sum((q / SEMI) ** 2, axis=1))
    assert np.median(np.abs(r - 1.0)) < VOXEL / SEMI.min()
    # Only the explored half (from the superior pole) is in the cloud.
    assert q[:, 1].min() > -0.01


def test_exploration_recentres_x_with_eq17():
    kp = synthetic()
    imager = km.Imager(kp, IMG)
    off = 0.02
    sweep = km.explore(kp, imager, CTRL, exploration_ratio=0.8, x_offset=off)
    xs = np.array([X.translation()[0] for X in sweep.poses]) - kp.roi.centroid_B[0]
    assert xs[0] == pytest.approx(off)
    assert abs(xs[-1]) < 0.5 * off  # pulled back over the kidney
    assert np.all(np.diff(xs[np.isfinite(xs)]) <= 1e-12)  # monotonically, no overshoot


def test_exploration_stops_after_the_kidney_left_the_image():
    kp = synthetic()
    sweep = km.explore(kp, km.Imager(kp, IMG), CTRL, exploration_ratio=1.0, travel=0.25)
    assert sweep.events and "left the image" in sweep.events[0]
    assert sweep.travel[-1] < 0.2
    assert not sweep.visible[-1]


def test_exploration_ratio_is_checked():
    kp = synthetic()
    with pytest.raises(ValueError, match="exploration_ratio"):
        km.explore(kp, km.Imager(kp, IMG), CTRL, exploration_ratio=1.5)


def test_pivot_sweep_fixed_tip_and_array_eq23():
    kp = synthetic()
    R, p = km.optimal_pivot_pose(kp.X_BK_true.rotation().matrix(), kp.X_BK_true.translation())
    sweep = km.pivot_sweep(
        kp, km.Imager(kp, IMG), R, p[:2], pivot_rate=CTRL.pivot_rate, max_tilt=CTRL.max_pivot_tilt
    )
    step = CTRL.pivot_rate / IMG.frame_rate_hz
    o = R[:, 0]
    for X in sweep.poses:
        np.testing.assert_allclose(X.translation(), [p[0], p[1], SKIN_Z], atol=1e-12)
        np.testing.assert_allclose(X.rotation().matrix()[:, 0], o, atol=1e-9)
    # Each frame turns a about o by the rate times the frame period.
    a = np.array([X.rotation().matrix()[:, 2] for X in sweep.poses])
    turn = np.arccos(np.clip(np.sum(a[1:] * a[:-1], axis=1), -1, 1))
    assert np.allclose(turn[turn > 1e-9], step, atol=1e-6)
    assert np.allclose(np.abs(np.diff(sweep.angles)), step)
    # Two legs, the second one crossing the start; symmetric kidney -> symmetric limits.
    assert set(sweep.leg) == {1, 2}
    end1, end2 = sweep.angles[sweep.leg == 1][-1], sweep.angles[-1]
    assert end1 > 0 > end2
    assert end1 == pytest.approx(-end2, abs=2 * step)
    assert not sweep.visible[-1]


def test_strategies_on_an_elongated_kidney():
    kp = synthetic()
    geometry = km.ProbeGeometry.from_config(IMG)
    imager = km.Imager(kp, IMG)
    res = {}
    for s in km.PAPER_STRATEGIES:  # OP-PE: tests/test_kinematic_predicted_end.py
        sweep = km.strategy_sweep(kp, imager, s, CTRL, kp.X_BK_true).pole_to_pole()
        res[s] = km.sweep_curves(kp, sweep, geometry)
        assert np.all(np.diff(res[s]["V"]) >= 0) and np.all(np.diff(res[s]["eps"]) >= 0)
    # With the true pose, OP is GT-OP.
    assert res["OP"]["n_frames"] == res["GT-OP"]["n_frames"]
    # Long-axis pivoting covers the kidney with fewer frames and less window travel than
    # short-axis pivoting or a straight line.
    assert res["GT-OP"]["V_final"] > 0.95
    assert res["GT-OP"]["n_frames"] < res["NOP"]["n_frames"]
    assert res["GT-OP"]["eps_total"] < res["NOP"]["eps_total"]
    assert res["GT-OP"]["n_frames"] < res["SL"]["n_frames"]
    assert res["SL"]["V_final"] > 0.95


def test_nop_pose_puts_the_array_across_the_kidney():
    R_BK = RotationMatrix.MakeZRotation(0.4).matrix()
    R, p = km.nop_pose(R_BK, [0.5, 0.1, 0.1])
    assert abs(R[:, 0] @ R_BK[:, 0]) < 1e-12
    assert abs(abs(R[:, 0] @ R_BK[:, 1]) - 1) < 1e-12
    np.testing.assert_allclose(R[:, 2], [0, 0, -1])
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_strategy_errors_are_named():
    kp = synthetic()
    with pytest.raises(ValueError, match="OP: needs X_BK_estimated"):
        km.strategy_sweep(kp, km.Imager(kp, IMG), "OP", CTRL)
    with pytest.raises(ValueError, match="strategy"):
        km.strategy_sweep(kp, km.Imager(kp, IMG), "ZIGZAG", CTRL)


def test_localize_cloud_falls_back_to_the_initial_alignment():
    kp = synthetic()
    loc = km.localize_cloud(kp, np.zeros((3, 3)), None, LocalizationConfig(), [0.51, 0.02])
    assert loc.result is None and "initial alignment" in loc.note
    np.testing.assert_allclose(loc.X_BK.translation()[:2], [0.51, 0.02])
    # Heuristic rotation: template x along the body's superior direction (+y_B).
    np.testing.assert_allclose(loc.X_BK.rotation().matrix()[:, 0], [0, 1, 0], atol=1e-12)


def test_classical_segmenter_is_selectable():
    kp = synthetic()
    imager = km.Imager(kp, IMG, "classical", seed=3)
    X = km.tip_pose(kp, km.R_B_TRANSVERSE, *kp.roi.centroid_B[:2])
    frame = imager(X, keep=True)
    assert frame.image is not None and frame.image.dtype == np.uint8
    assert frame.mask.shape == imager.geometry.image_shape


@pytest.fixture(scope="module")
def patient0():
    from drake_rus.anatomy import load_patient

    return km.prepare_patient(load_patient("test:0", voxel_size=0.002, progress=False), X_BPT)


def test_generated_patient_exploration_localization_and_gt_op(patient0):
    from drake_rus.localization.localize import load_registration_template
    from drake_rus.metrics.core import e_rot_x, e_trans

    kp = patient0
    imager = km.Imager(kp, IMG)
    sweep = km.explore(kp, imager, CTRL, exploration_ratio=0.6)
    P = sweep.point_cloud()
    assert sweep.visible.mean() > 0.8 and len(P) > 1000
    cfg = LocalizationConfig(method="seed", max_points=1500)
    loc = km.localize_cloud(
        kp, P, load_registration_template(), cfg, sweep.frames[0].X_BP.translation()[:2]
    )
    # A partial, 60% cloud of a generated kidney on the mean template: the seed reports
    # 8.73 +- 6.93 mm and 12.86 +- 20.86 deg; a generous bound that still catches a failure.
    assert e_trans(loc.X_BK, kp.X_BK_true) < 0.025
    assert math.degrees(e_rot_x(loc.X_BK, kp.X_BK_true)) < 20
    gt = km.strategy_sweep(kp, imager, "GT-OP", CTRL).pole_to_pole()
    curves = km.sweep_curves(kp, gt, imager.geometry)
    assert curves["V_final"] > 0.9


def test_prefix_of_a_long_exploration_is_the_short_exploration():
    kp = synthetic()
    long = km.explore(kp, km.Imager(kp, IMG), CTRL, exploration_ratio=0.8, x_offset=0.01)
    short = km.explore(kp, km.Imager(kp, IMG), CTRL, exploration_ratio=0.3, x_offset=0.01)
    cut = long.prefix(0.3 * CTRL.kidney_length)
    assert len(cut.frames) == len(short.frames)
    for a, b in zip(cut.frames, short.frames):
        np.testing.assert_array_equal(a.X_BP.GetAsMatrix4(), b.X_BP.GetAsMatrix4())
    np.testing.assert_array_equal(cut.point_cloud(), short.point_cloud())


def test_er_in_units_of_the_patients_kidney_length():
    """ER x the kidney's length along the exploration line (the paper's simulation), or x
    L_m (the fixed variant), on an ellipsoid kidney 2 x 55 mm long along y."""
    kp = synthetic()
    length = run_patients.kidney_length(kp)
    assert length == pytest.approx(2 * SEMI[1], abs=0.001)
    assert run_patients.exploration_travel(0.6, "kidney", length, 0.1) == pytest.approx(
        0.6 * length
    )
    assert run_patients.exploration_travel(0.6, "fixed", length, 0.1) == pytest.approx(0.06)
    with pytest.raises(ValueError, match="er_unit"):
        run_patients.exploration_travel(0.6, "inches", length, 0.1)
    step = CTRL.scan_speed / IMG.frame_rate_hz
    imager = km.Imager(kp, IMG)
    for unit, travel in (("kidney", 0.6 * length), ("fixed", 0.06)):
        task = StudyTask(
            study="er-sweep", patient=f"synthetic-{unit}", voxel=VOXEL, er=0.6, er_unit=unit
        )
        sweep = kinematic_runs.exploration(task, kp, imager, CTRL, 0.0, 0.0)
        assert travel - step < sweep.travel[-1] <= travel + 1e-9
    # ER 100% in kidney units explores past the fixed 100 mm: the whole 110 mm kidney.
    task = dataclasses.replace(task, er=1.0, er_unit="kidney", patient="synthetic-full")
    full = kinematic_runs.exploration(task, kp, imager, CTRL, 0.0, 0.0)
    assert full.travel[-1] > CTRL.kidney_length


def test_a_shared_exploration_leaves_the_imager_as_exploring_would():
    """An efficiency run's sweeps (emulated images: the speckle follows the imager's frame
    counter) are the same whether or not its process explored the patient before (an
    er-sweep run of it with --workers 0, or an earlier task on the same Dask worker)."""
    kp = synthetic()
    task = StudyTask(study="er-sweep", patient="synthetic-shared", voxel=VOXEL, er=0.6)
    kinematic_runs._EXPLORATIONS.clear()
    first, again = km.Imager(kp, IMG, "classical"), km.Imager(kp, IMG, "classical")
    kinematic_runs.exploration(task, kp, first, CTRL, 0.0, 0.0)  # explores
    kinematic_runs.exploration(task, kp, again, CTRL, 0.0, 0.0)  # takes the stored one
    assert again.frame_index == first.frame_index > 0
    X = km.tip_pose(kp, km.R_B_TRANSVERSE, *kp.roi.centroid_B[:2])
    np.testing.assert_array_equal(first(X, keep=True).image, again(X, keep=True).image)


def test_kinematic_pivot_and_closed_loop_definitions_agree():
    """The legs found from the poses (what the closed-loop scan does) are the kinematic
    sweep's own legs, so both modes measure pole to pole alike."""
    from drake_rus.metrics import pivot_legs, signed_pivot_angles

    kp = synthetic()
    imager = km.Imager(kp, IMG)
    sweep = km.strategy_sweep(kp, imager, "GT-OP", CTRL)
    angles = signed_pivot_angles([X.rotation() for X in sweep.poses])
    np.testing.assert_allclose(np.abs(angles), np.abs(sweep.angles), atol=1e-9)
    np.testing.assert_array_equal(pivot_legs(angles), sweep.leg)
    entry = kinematic_runs.sweep_entry(kp, sweep, imager.geometry, CTRL)
    curves = km.sweep_curves(kp, sweep.pole_to_pole(), imager.geometry)
    whole = km.sweep_curves(kp, sweep, imager.geometry)
    assert entry["n"] == curves["n_frames"] < entry["n_whole_pivot"] == whole["n_frames"]
    assert entry["eps_mm"] == pytest.approx(curves["eps_total"] * 1e3)
    assert entry["eps_whole_pivot_mm"] == pytest.approx(whole["eps_total"] * 1e3)
    assert entry["V"] == pytest.approx(curves["V_final"])
    at = entry["at_V"]["0.9"]
    assert at is not None and at["n"] <= entry["n"] and at["eps_mm"] <= entry["eps_mm"]
    assert entry["tilt_cap_legs"] == []
    capped_ctrl = dataclasses.replace(CTRL, max_pivot_tilt=0.1)
    capped = kinematic_runs.sweep_entry(
        kp, km.strategy_sweep(kp, imager, "GT-OP", capped_ctrl), imager.geometry, capped_ctrl
    )
    assert capped["tilt_cap_legs"] == [1, 2]
