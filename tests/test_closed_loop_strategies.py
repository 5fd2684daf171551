"""Closed-loop efficiency strategies (issue 18): GT-OP, NOP and SL as scans on the Drake
diagram. The truth reaches the scan only as scenario values the study computes (a given
pivot pose, a line sweep's start), checked like any scenario; the sweep costs of a line
sweep; the report naming which pose each strategy used. No simulation here (the end-to-end
run is in test_closed_loop_study.py)."""

import dataclasses
import math
import types

import numpy as np
import pytest
from pydrake.math import RigidTransform, RotationMatrix
from test_kinematic_core import synthetic

from drake_rus.config_schema import ScenarioError
from drake_rus.control import supervisor
from drake_rus.control.supervisor import Phase
from drake_rus.experiments import closed_loop_runs, specs
from drake_rus.experiments import kinematic as km
from drake_rus.experiments.report import report_markdown
from drake_rus.scan.diagram import FrameRecord
from drake_rus.scan.metrics import ScanMetrics, Summary, SweepDescription
from drake_rus.scenario import ApplyOverrides, CheckScenario, LoadScenario


def test_every_strategy_has_a_closed_loop_scan_and_unknown_ones_are_named():
    assert specs.check_strategies(["SL", "NOP", "OP", "GT-OP", "OP-PE"], "closed-loop") == (
        "OP",
        "GT-OP",
        "NOP",
        "SL",
        "OP-PE",
    )
    assert specs.default_strategies("closed-loop") == ("OP", "GT-OP", "NOP", "SL")
    with pytest.raises(ValueError, match=r"--strategies: expected .*GT-OP.*\(XY unknown\)"):
        specs.check_strategies(["OP", "XY"], "closed-loop")
    with pytest.raises(ValueError, match="--mode"):
        specs.check_strategies(["OP"], "dynamic")


def test_given_pose_and_line_sweep_are_scenario_values_checked_like_any_other():
    base = LoadScenario()
    assert base.controller.pivot_pose == [] and base.controller.sweep == "pivot"
    ok = ApplyOverrides(base, "{controller: {pivot_pose: [0.5, 0.01, 1.5]}}")
    CheckScenario(ok)
    for text, match in (
        ("{controller: {pivot_pose: [0.5, 0.01]}}", r"controller\.pivot_pose.*\[x \(m\)"),
        (
            "{controller: {pivot_pose: [0.5, 0.01, 1], pivot_strategy: predicted_end}}",
            r"controller\.pivot_pose.*predicted_end",
        ),
        (
            "{controller: {pivot_pose: [0.5, 0.01, 1], sweep: line}}",
            r"controller\.pivot_pose.*line sweep has no pivot",
        ),
        ("{controller: {sweep: raster}}", r"controller\.sweep.*'pivot', 'line'"),
        ("{controller: {line_sweep_max_travel: 0}}", r"controller\.line_sweep_max_travel"),
    ):
        with pytest.raises(ScenarioError, match=match):
            CheckScenario(ApplyOverrides(base, text))


def test_closed_loop_strategy_scans_use_the_twins_poses():
    kp = synthetic(yaw=0.3)
    base = LoadScenario()
    X = kp.X_BK_true
    op = closed_loop_runs.closed_loop_strategy_run(base, "OP", kp, 0.1)
    assert op.scenario == base and op.start_fraction == 0.1  # the run's own scan
    assert op.pose["pivot_pose"] == "registered" and op.pose["pivot_pose_from"] == "registered"
    for name, pose in (
        ("GT-OP", km.optimal_pivot_pose(X.rotation().matrix(), X.translation())),
        ("NOP", km.nop_pose(X.rotation().matrix(), X.translation())),
    ):
        run = closed_loop_runs.closed_loop_strategy_run(base, name, kp, 0.1)
        c = run.scenario.controller
        assert c.pivot_pose == pytest.approx(supervisor.pivot_pose_as_given(*pose))
        assert c.pivot_strategy == "two_leg" and c.sweep == "pivot"
        # The scan turns it back into exactly the twin's pivot pose.
        R, p = supervisor.given_pivot_pose(c.pivot_pose, X.translation()[2])
        np.testing.assert_allclose(R, pose[0], atol=1e-12)
        np.testing.assert_allclose(p, pose[1], atol=1e-12)
        assert run.pose["pivot_pose"] == "given" and run.pose["pivot_pose_from"] == "true"
        assert run.pose["given_pivot_pose"] == c.pivot_pose
        assert run.start_fraction == closed_loop_runs.GIVEN_POSE_START_FRACTION
        # Only the controller's pose changed; the product default is untouched.
        assert run.scenario == dataclasses.replace(
            base,
            controller=dataclasses.replace(
                base.controller, pivot_pose=c.pivot_pose, exploration_ratio=0.0
            ),
        )
    assert LoadScenario().controller.pivot_pose == []
    # GT-OP's array lies along the kidney's long axis, NOP's across it (the plane turned
    # by 90 deg), both tips over the true centroid.
    run = closed_loop_runs.closed_loop_strategy_run
    gt = run(base, "GT-OP", kp).scenario.controller.pivot_pose
    nop = run(base, "NOP", kp).scenario.controller.pivot_pose
    assert gt[2] == pytest.approx(math.pi / 2 + 0.3)
    assert abs(math.remainder(nop[2] - gt[2], math.pi)) == pytest.approx(math.pi / 2)
    assert gt[:2] == nop[:2] == pytest.approx(list(X.translation()[:2]))
    # SL: the line starts where the twin's does and may travel as far.
    sl = closed_loop_runs.closed_loop_strategy_run(base, "SL", kp, 0.1)
    start, travel = km.sl_line(kp, base.controller.scan_direction)
    assert sl.scenario.controller.sweep == "line" and sl.scenario.controller.pivot_pose == []
    assert sl.scenario.controller.start_xy == pytest.approx(list(start))
    assert sl.scenario.controller.line_sweep_max_travel == pytest.approx(travel)
    assert travel == pytest.approx(kp.roi.length_y + 2 * km.SL_MARGIN + km.SL_EXTRA_TRAVEL)
    sign = 1.0 if base.controller.scan_direction == "+y" else -1.0
    assert (start[1] - km.start_xy(kp, 0.0, base.controller.scan_direction)[1]) * sign == (
        pytest.approx(-km.SL_MARGIN)
    )  # beyond the E-ROI's end
    assert not sl.scenario.localization.length_estimation and sl.start_fraction == 0.0
    assert sl.scenario.controller.exploration_ratio == 1.0  # the paper: ER 100%
    assert sl.pose["pivot_pose"] is None
    with pytest.raises(ValueError, match="GT-OP: needs the prepared patient"):
        closed_loop_runs.closed_loop_strategy_run(base, "GT-OP", None)


def test_nop_array_sign_follows_the_exploration_array():
    """Either sign of the kidney's y-axis images the same plane; NOP takes the one along
    base x (the exploration's array), so the probe turns less than 90 deg."""
    for yaw in (0.3, 0.3 + math.pi, -1.2, 2.0):
        R_BK = RotationMatrix.MakeZRotation(yaw).matrix()
        R, p = km.nop_pose(R_BK, [0.5, 0.1, 0.1])
        assert R[0, 0] >= 0
        assert abs(abs(R[:, 0] @ R_BK[:, 1]) - 1) < 1e-12
        assert np.linalg.det(R) == pytest.approx(1.0)


def _line_scan(visible):
    """A recorded line sweep: 10 landing/EXPLORE frames of a 2 mm-step straight line."""
    scenario = dataclasses.replace(
        LoadScenario(), controller=dataclasses.replace(LoadScenario().controller, sweep="line")
    )
    R = RotationMatrix(np.diag([1.0, -1.0, -1.0]))
    frames = [
        FrameRecord(
            0.05 * i,
            i,
            int(Phase.APPROACH if i < 2 else Phase.EXPLORE),
            RigidTransform(R, [0.5, 0.1 - 0.002 * i, 0.2]),
            bool(v),
            9.0,
        )
        for i, v in enumerate(visible)
    ]
    loc = types.SimpleNamespace(result=None, error="", n_points=0, compute_s=0.0)
    return types.SimpleNamespace(
        scenario=scenario,
        frames=frames,
        truth=None,
        X_BK_estimated=None,
        localization=loc,
        logs={"force": (np.zeros(1), np.zeros((1, 1)))},
        status="DONE",
        reason="",
        patient="p",
        wall_s=1.0,
        sim_s=1.0,
        phases=[],
        tracking_drift=(),
        length_checks=(),
        start_plan=None,
        safety_events=[],
    )


def test_scan_metrics_of_a_line_sweep_count_its_exploration_frames():
    visible = [False, False, False, False, True, True, True, True, True, False, False, False]
    m = ScanMetrics(_line_scan(visible))
    assert m["sweep"]["kind"] == "line" and m["sweep"]["pivot_pose"] is None
    assert m["n_whole_pivot"] == 10  # every EXPLORE frame, not APPROACH
    assert m["eps_whole_pivot_mm"] == pytest.approx(9 * 2.0)
    assert m["n_frames"] == 5 and m["eps_mm"] == pytest.approx(4 * 2.0)  # first..last seen
    assert m["pivot"]["legs"] == 0 and m["pivot"]["tilt_cap_legs"] == []
    s = Summary(_line_scan(visible), m)
    assert s["sweep"]["kind"] == "line" and "sweep" in s["metric_definitions"]


def test_sweep_description_says_which_pose_the_pivot_used():
    c = LoadScenario().controller
    d = SweepDescription(c)
    assert d["pivot_pose"] == "registered" and "registered kidney pose" in d["text"]
    d = SweepDescription(dataclasses.replace(c, pivot_pose=[0.5, -0.02, math.pi / 2]))
    assert d["pivot_pose"] == "given" and d["given_pivot_pose"] == [0.5, -0.02, math.pi / 2]
    assert "controller.pivot_pose" in d["text"] and "(500.0, -20.0) mm" in d["text"]
    assert "90.0 deg" in d["text"]


def _entry(n, eps, **kw):
    return {
        "n": n,
        "eps_mm": eps,
        "V": 0.99,
        "n_whole_pivot": n + 40,
        "eps_whole_pivot_mm": eps + 40,
        "V_whole_pivot": 0.99,
        "curve_V": [0.99],
        "curve_eps_mm": [0.0],
        "volume_ml": None,
        "volume_error_pct": None,
        "at_V": {"0.9": {"n": n - 10, "eps_mm": eps - 10}},
    } | kw


def _runs(op_eps, nop_eps, sl_eps, gt_eps):
    return [
        {
            "patient": f"test:{k}",
            "e_trans_mm": 1.0,
            "e_rot_x_deg": 1.0,
            "true_volume_ml": 100.0,
            "status": "DONE",
            "strategies": {
                "OP": _entry(80 + k, op_eps + k, pivot_pose="registered"),
                "GT-OP": _entry(78 + k * k, gt_eps + 0.5 * k * k, pivot_pose="given"),
                "NOP": _entry(170 + 2 * k, nop_eps + 2 * k, pivot_pose="given"),
                "SL": _entry(390 + k * k, sl_eps + 0.5 * k * k, sweep="line"),
            },
        }
        for k in range(4)
    ]


def test_report_puts_all_strategies_beside_the_twin_and_the_paper():
    from drake_rus.experiments.analysis import analyze_efficiency
    from drake_rus.experiments.report import CLOSED_LOOP, KINEMATIC

    cl = analyze_efficiency(_runs(80.0, 160.0, 110.0, 75.0))
    kin = analyze_efficiency(_runs(76.0, 150.0, 108.0, 74.0))
    meta = {
        "patients": cl["patients"],
        "segmenter": "oracle",
        "method": "seed",
        "voxel": 0.002,
        "seed": 0,
        "er": 0.6,
        "er_unit": "kidney",
        "wall_s": 1.0,
        "mode_text": CLOSED_LOOP,
    }
    md = report_markdown(
        meta, None, None, cl, compare={"mode": KINEMATIC, "er": None, "starts": None, "eff": kin}
    )
    for k in ("GT-OP", "NOP", "SL"):
        assert f"| {k} | closed loop | 4 |" in md and f"| {k} | kinematic | 4 |" in md
        assert f"| OP - {k} | pole to pole |" in md
    # The paper's OP - NOP (-24.66 +- 21.50 mm) beside ours: closed loop 80 - 160 - k.
    rows = [line for line in md.splitlines() if line.startswith("| OP - NOP | pole to pole")]
    assert len(rows) == 2  # this mode's section, then the side-by-side one
    assert "-24.66 +- 21.50 | -81.5 +-" in rows[0]
    # Side by side: paper, then the kinematic twin (76 - 150 - k), then the closed loop.
    assert "-24.66 +- 21.50 | -75.5 +-" in rows[1] and rows[1].index("-75.5") < rows[1].index(
        "-81.5"
    )
    assert "no closed-loop scan" not in md and "no closed-loop equivalent" not in md
    assert "`controller.pivot_pose`" in md and "`controller.sweep: line`" in md
    assert "closed loop: the study gives T* of the true pose as controller.pivot_pose" in md
