"""The kinematic twin's predicted-end pivot (OP-PE, issue 18) on the synthetic ellipsoid
kidney, and the closed-loop study's rules for runs the product would refuse (ER below the
product's exploration minimum, ER 0, random starts where the kidney is not visible)."""

import dataclasses
import math
import types

import numpy as np
import pytest
from pydrake.math import RigidTransform
from test_kinematic_core import CTRL, IMG, SEMI, synthetic

from drake_rus.control import supervisor
from drake_rus.control.supervisor import Phase
from drake_rus.experiments import closed_loop_runs, kinematic_runs, specs
from drake_rus.experiments import kinematic as km
from drake_rus.experiments import patients as run_patients
from drake_rus.experiments.analysis import analyze_efficiency
from drake_rus.localization.config import LocalizationConfig
from drake_rus.metrics.core import e_trans
from drake_rus.scenario import LoadScenario


def ellipsoid_points_K(n=4000):
    """The synthetic kidney's surface in its canonical frame K (x_k along its long axis)."""
    k = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * k / n)
    th = math.pi * (1 + 5**0.5) * k
    u = np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], axis=1)
    return u * np.array([SEMI[1], SEMI[0], SEMI[2]])


def model():
    return km.pivot_model_for(types.SimpleNamespace(points=ellipsoid_points_K()), IMG)


def _entry(kp, sweep):
    return kinematic_runs.sweep_entry(kp, sweep, km.ProbeGeometry.from_config(IMG), CTRL)


def test_predicted_end_sweep_starts_at_the_predicted_end_and_costs_less():
    kp = synthetic()
    X = kp.X_BK_true
    R, p = km.optimal_pivot_pose(X.rotation().matrix(), X.translation())
    imager = km.Imager(kp, IMG)
    pe = km.strategy_sweep(kp, imager, "OP-PE", CTRL, X, pivot_model=model())
    two = km.strategy_sweep(kp, imager, "OP", CTRL, X)
    tip = [p[0], p[1], kp.skin(p[0], p[1])]
    ends = supervisor.predict_pivot_ends(
        model(), X.rotation().matrix(), X.translation(), tip, R[:, 2], R[:, 0], CTRL.max_pivot_tilt
    )
    info = pe.info
    assert info["predicted_ends"] == pytest.approx(list(ends))
    # A symmetric kidney: equal ends, the tie goes to +; no margin by default.
    assert ends[0] == pytest.approx(-ends[1], abs=math.radians(0.3)) and ends[0] > 0.1
    side, target = supervisor.pretilt_plan(ends, CTRL.pivot_end_margin, CTRL.max_pivot_tilt)
    assert info["pretilt_target"] == pytest.approx(target)
    assert side == 1.0 and target == pytest.approx(ends[0])
    # The kidney was already out of the image at the predicted end (one check frame), and
    # the one sweep starts there, one frame's tilt towards the other side.
    step = CTRL.pivot_rate / IMG.frame_rate_hz
    assert info["pretilt_check_frames"] == 1 and info["pretilt_end"] == pytest.approx(target)
    assert pe.angles[0] == pytest.approx(target - step)
    assert np.all(np.diff(pe.angles) < 0) and set(pe.leg) == {2}
    assert pe.angles[-1] < 0 and not pe.visible[-1]
    # One pass instead of out and back: the whole pivot is far cheaper at the same coverage.
    e_pe, e_two = _entry(kp, pe), _entry(kp, two)
    assert e_pe["n_whole_pivot"] < 0.85 * e_two["n_whole_pivot"]
    assert e_pe["eps_whole_pivot_mm"] < 0.85 * e_two["eps_whole_pivot_mm"]
    assert e_pe["V"] >= e_two["V"] - 0.01 and e_pe["V"] > 0.95
    assert abs(e_pe["n"] - e_two["n"]) <= 3  # pole to pole: the same span
    # The pre-tilt moves the image unrecorded: its window path is reported apart.
    assert info["eps_pretilt"] > 0


def test_the_twin_and_the_controller_share_one_prediction(monkeypatch):
    assert km.predict_pivot_ends is supervisor.predict_pivot_ends
    assert km.pretilt_plan is supervisor.pretilt_plan
    assert km.pivot_end_allowed is supervisor.pivot_end_allowed
    calls = []
    real = supervisor.pivot_end_angles

    def spy(*args, **kw):
        calls.append(kw["max_angle"])
        return real(*args, **kw)

    monkeypatch.setattr(supervisor, "pivot_end_angles", spy)
    kp = synthetic()
    X = kp.X_BK_true
    R, p = km.optimal_pivot_pose(X.rotation().matrix(), X.translation())
    sweep = km.predicted_end_sweep(kp, km.Imager(kp, IMG), R, p[:2], X, model(), CTRL)
    assert len(calls) == 1
    # The supervisor's TRANSIT prediction for the same pose and tip gives the same ends.
    s = supervisor.SupervisorState(a_des=R[:, 2].copy(), o_des=R[:, 0].copy())
    tip = np.array([p[0], p[1], kp.skin(p[0], p[1])])
    u = supervisor.SupervisorInputs(
        t=0.0,
        R_BP=R,
        p_BP=tip,
        F_z=9.0,
        kidney_visible=True,
        c_msk=0.5,
        R_BK=X.rotation().matrix(),
        p_BK=X.translation(),
    )
    ends = supervisor.predicted_pivot_ends(s, model(), u, tip, CTRL)
    assert len(calls) == 2
    assert list(ends) == pytest.approx(sweep.info["predicted_ends"], abs=1e-12)


def test_pivot_end_rule_is_the_two_leg_rule_without_predicted_ends():
    allowed = supervisor.pivot_end_allowed
    assert allowed(0.1, 1.0, 0) and allowed(-0.1, 1.0, 0)  # leg 1: anywhere
    assert allowed(-0.1, -1.0, 1) and not allowed(0.1, -1.0, 1)  # leg 2: past the start
    ends = (0.3, -0.4)
    assert not allowed(-0.25, -1.0, 1, ends, 0.1)  # short of -0.4 + 0.1
    assert allowed(-0.31, -1.0, 1, ends, 0.1)


def test_op_pe_needs_a_model_and_runs_in_both_modes():
    kp = synthetic()
    with pytest.raises(ValueError, match="OP-PE: needs pivot_model"):
        km.strategy_sweep(kp, km.Imager(kp, IMG), "OP-PE", CTRL, kp.X_BK_true)
    assert "OP-PE" in specs.default_strategies("kinematic")
    assert "OP-PE" not in specs.default_strategies("closed-loop")  # a scan more, on request
    assert specs.check_strategies(["OP-PE", "OP"], "closed-loop") == ("OP", "OP-PE")
    # Closed loop, OP-PE is the scan with the controller's predicted_end pivot.
    base = LoadScenario()
    assert base.controller.pivot_strategy == "two_leg"
    sc = closed_loop_runs.closed_loop_strategy_scenario(base, "OP-PE")
    assert sc.controller.pivot_strategy == "predicted_end"
    assert sc.controller == dataclasses.replace(base.controller, pivot_strategy="predicted_end")
    assert closed_loop_runs.closed_loop_strategy_scenario(sc, "OP").controller == base.controller


def test_op_pe_is_compared_with_op_outside_the_papers_family():
    def entry(n, eps):
        return {
            "n": n,
            "eps_mm": eps,
            "V": 1.0,
            "n_whole_pivot": n + 40,
            "eps_whole_pivot_mm": eps + 40,
            "V_whole_pivot": 1.0,
            "curve_V": [1.0],
            "curve_eps_mm": [0.0],
            "volume_error_pct": None,
        }

    res = [
        {
            "patient": f"test:{k}",
            "e_trans_mm": 1.0,
            "e_rot_x_deg": 1.0,
            "true_volume_ml": 100.0,
            "strategies": {
                "OP": entry(90 + k, 80.0 + k),
                "NOP": entry(180 + 2 * k, 160.0),
                "OP-PE": dict(
                    entry(90 + k, 80.0 + k),
                    n_whole_pivot=95 + 2 * k,
                    eps_whole_pivot_mm=85.0 + 2 * k,
                ),
            },
        }
        for k in range(5)
    ]
    an = analyze_efficiency(res)
    assert an["bonferroni_threshold"] == pytest.approx(0.05 / 2)  # OP vs NOP only
    c = {(x["comparison"], x["definition"], x["metric"]): x for x in an["comparisons"]}
    whole = c[("OP-PE vs OP", "whole_pivot", "eps_mm")]
    assert whole["reduction_mean"] == pytest.approx(np.mean([35.0 - k for k in range(5)]))
    assert whole["op_lower_count"] == 5 and whole["bonferroni_threshold"] == 0.025
    assert ("OP vs OP-PE", "whole_pivot", "eps_mm") not in c


# ------------------------------------------------------------- the closed-loop study's rules
def test_study_relaxes_the_product_minimums_only_below_them():
    product = LocalizationConfig()
    assert product.min_exploration_travel == pytest.approx(0.015)
    cfg, note = closed_loop_runs.study_localization(product, 0.1, 0.009)
    assert cfg.min_exploration_travel == 0.0 and cfg.min_inlier_fraction == 0.0
    assert cfg.min_cloud_spread == 0.0
    assert cfg.max_rms_residual >= 1.0 and cfg.max_centroid_offset >= 1.0
    assert "below the product's minimum 15 mm" in note
    assert product.min_exploration_travel == pytest.approx(0.015)  # untouched
    assert closed_loop_runs.study_localization(product, 0.2, 0.018) == (product, "")
    # ER 0: nothing to register.
    assert closed_loop_runs.study_localization(product, 0.0, 0.0) == (product, "")


def test_closed_loop_setup_changes_the_study_scenario_not_the_default():
    kp = synthetic()
    base = LoadScenario()
    task = specs.StudyTask(mode="closed-loop", study="er-sweep", patient="synthetic", er=0.1)
    scenario, sf, xo, notes = closed_loop_runs.closed_loop_setup(task, kp, base)
    assert scenario.localization.min_exploration_travel == 0.0 and notes["study_relaxation"]
    assert base.localization.min_exploration_travel == pytest.approx(0.015)
    assert LoadScenario().localization.min_exploration_travel == pytest.approx(0.015)
    scenario, *_, notes = closed_loop_runs.closed_loop_setup(
        dataclasses.replace(task, er=0.6), kp, base
    )
    assert scenario.localization == dataclasses.replace(base.localization, method="seed")
    assert notes["study_relaxation"] == ""


def test_random_starts_are_redrawn_until_the_kidney_is_visible():
    kp = synthetic()
    task = specs.StudyTask(study="starts", patient="synthetic", er=0.6, start=2)
    first = run_patients.random_start(task, kp, CTRL)
    assert run_patients.random_start(task, kp, CTRL) == first  # deterministic
    seen = []

    def visible(xy):
        seen.append(tuple(xy))
        return len(seen) > 3

    sf, xo, rejected = run_patients.visible_random_start(task, kp, CTRL, visible)
    assert rejected == 3 and (sf, xo) != first
    np.testing.assert_allclose(seen[-1], km.start_xy(kp, sf, CTRL.scan_direction, xo))
    assert run_patients.random_start(task, kp, CTRL, lambda xy: True) == first
    with pytest.raises(ValueError, match="not visible at any of 5"):
        run_patients.visible_random_start(task, kp, CTRL, lambda xy: False, max_draws=5)


def test_random_starts_at_er_100_have_room_to_see_the_kidney():
    """At ER 100% the travel leaves no room: the starts may lie up to START_MIN_ROOM into
    the E-ROI, where the pole is in view (every draw failed on real CT kidneys whose
    critical ER came out 100%)."""
    kp = synthetic()
    task = specs.StudyTask(study="starts", patient="synthetic", er=1.0, start=0)
    starts = [
        run_patients.random_start(dataclasses.replace(task, start=k), kp, CTRL) for k in range(5)
    ]
    assert all(0 <= sf <= run_patients.START_MIN_ROOM for sf, _ in starts)
    assert len({sf for sf, _ in starts}) == 5
    visible = run_patients.start_visibility(kp, km.Imager(kp, IMG))
    sf, _, _ = run_patients.visible_random_start(task, kp, CTRL, visible)
    assert 0 < sf <= run_patients.START_MIN_ROOM
    # With room to spare the rule is the paper's: the whole travel fits.
    sf, _ = run_patients.random_start(dataclasses.replace(task, er=0.6), kp, CTRL)
    assert 0 <= sf <= 0.4 + 1e-9


def test_start_visibility_on_the_synthetic_kidney():
    kp = synthetic()
    imager = km.Imager(kp, IMG)
    visible = run_patients.start_visibility(kp, imager)
    centre = kp.X_BK_true.translation()
    assert visible(centre[:2])
    assert not visible([centre[0], centre[1] + SEMI[1] + 0.001])  # just past the pole
    assert not visible([centre[0] + 0.12, centre[1]])  # beside the kidney
    # Within 2 mm of the pole: visible at the point but not all around it.
    assert not visible([centre[0], centre[1] + SEMI[1] - 0.001])
    assert imager.frame_index == 0  # counter restored


def test_er0_is_the_initial_alignment_in_both_modes():
    kp = synthetic()
    xy = kp.X_BK_true.translation()[:2] + [0.0, 0.03]
    pose = RigidTransform(km.R_B_TRANSVERSE, [xy[0], xy[1], kp.skin(*xy)])
    scan = types.SimpleNamespace(
        status="ABORT",
        reason="localization failed: none",
        frames=[
            types.SimpleNamespace(phase=int(Phase.APPROACH), X_BP=RigidTransform()),
            types.SimpleNamespace(phase=int(Phase.EXPLORE), X_BP=pose),
        ],
    )
    rec = closed_loop_runs.initial_alignment_record(kp, scan, [0.0, 0.0])
    X0 = km.heuristic_pose(kp, xy)
    assert rec["e_trans_mm"] == pytest.approx(e_trans(X0, kp.X_BK_true) * 1e3)
    assert rec["localization_note"].startswith("ER 0: initial alignment only")
    # No frames at all: at the start.
    rec = closed_loop_runs.initial_alignment_record(
        kp, types.SimpleNamespace(status="ABORT", reason="", frames=[]), xy
    )
    assert rec["e_trans_mm"] == pytest.approx(e_trans(X0, kp.X_BK_true) * 1e3)
    # The twin at ER 0: the initial alignment even when the start frame saw the kidney.
    P = kp.kidney_points_B[:200]
    loc = km.localize_cloud(kp, P, None, LocalizationConfig(), xy, min_points=math.inf)
    assert loc.result is None and loc.X_BK.IsExactlyEqualTo(X0)


def test_a_rejected_registration_is_measured_but_not_swept():
    from drake_rus.experiments.results import usable_runs as _usable

    kp = synthetic()
    X = RigidTransform(kp.X_BK_true.rotation(), kp.X_BK_true.translation() + [0.0, 0.004, 0.0])
    loc = types.SimpleNamespace(
        rejected=types.SimpleNamespace(X_BK=X),
        error="registration rejected: only 18% of the explored points",
    )
    rec = closed_loop_runs.rejected_registration_record(kp, loc)
    assert rec["e_trans_mm"] == pytest.approx(4.0, abs=1e-9)
    assert "the paper has no acceptance check" in rec["localization_note"]
    runs = [
        {"run_id": "a", "status": "ABORT", "e_trans_mm": 4.0},
        {"run_id": "b", "status": "DONE", "e_trans_mm": 2.0},
        {"run_id": "c", "status": "ABORT", "e_trans_mm": None},
        {"run_id": "d", "e_trans_mm": 3.0},
    ]  # kinematic: no status
    assert [r["run_id"] for r in _usable(runs, "er-sweep")] == ["a", "b", "d"]
    assert [r["run_id"] for r in _usable(runs, "efficiency")] == ["b", "d"]


def test_report_lists_the_runs_left_out():
    from drake_rus.experiments.report import report_markdown

    meta = {
        "patients": ["test:0"],
        "segmenter": "oracle",
        "method": "seed",
        "voxel": 0.002,
        "seed": 0,
        "er": 0.6,
        "wall_s": 1.0,
        "runs_without_localization": {
            "er-sweep": ["er-sweep__test-0__erk010__cl: ABORT localization failed"]
        },
    }
    md = report_markdown(meta, None, None, None)
    assert (
        "- Runs left out of the analysis (no localization; efficiency: a scan that did "
        "not finish): er-sweep: er-sweep__test-0__erk010__cl: ABORT localization "
        "failed."
    ) in md
    assert "Runs left out" not in report_markdown(
        dict(meta, runs_without_localization={}), None, None, None
    )
    assert "drawn again until the kidney is visible" in md  # the study's start rule
