"""``drake-rus study ... --mode closed-loop``: every study run a full closed-loop scan on the
Drake diagram, with the kinematic run's record, and the report naming the mode."""

import json
import math

import pytest

from drake_rus.cli import main
from drake_rus.control import supervisor
from drake_rus.experiments import kinematic as km
from drake_rus.experiments import patients as run_patients
from drake_rus.scenario import LoadScenario


def test_tiny_closed_loop_paper_study(tmp_path, capsys):
    out = tmp_path / "study"
    code = main(
        [
            "study",
            "paper",
            "--patients",
            "test:1",
            "--scenario",
            "quick",
            "--ers",
            "0.6,1",
            "--starts",
            "1",
            "--mode",
            "closed-loop",
            # The oracle (closed loop's default is the learned segmenter): the checks below
            # are of the study's wiring, with exact masks.
            "--segmenter",
            "oracle",
            "--workers",
            "0",
            "--no-progress",
            "--no-nrrd",
            "--out",
            str(out),
        ]
    )
    assert code == 0, capsys.readouterr()
    runs = sorted((out / "runs").glob("*.json"))
    assert len(runs) == 4  # ER 60% and 100%, one start, one efficiency run
    records = [json.loads(p.read_text()) for p in runs]
    assert {r["task"]["study"] for r in records} == {"er-sweep", "starts", "efficiency"}
    for r in records:
        assert r["mode"] == "closed-loop" and r["run_id"].endswith("__cl")
        assert r["status"] == "DONE", r["reason"]
        assert math.isfinite(r["e_trans_mm"]) and math.isfinite(r["e_rot_x_deg"])
        assert math.isfinite(r["sweep"]["V"]) and 0 < r["sweep"]["V"] <= 1
        assert r["sweep"]["n_whole_pivot"] >= r["sweep"]["n"] > 0
    er60 = next(r for r in records if r["run_id"] == "er-sweep__test-1__erk060__cl")
    # ER x the patient's kidney length, as the kinematic twin explores.
    assert abs(er60["explore_travel_mm"] - 0.6 * er60["kidney_length_mm"]) < 5
    eff = next(r for r in records if r["task"]["study"] == "efficiency")
    # The paper's four strategies, each its own closed-loop scan (OP the run's own).
    s = eff["strategies"]
    assert list(s) == ["OP", "GT-OP", "NOP", "SL"]
    for k, e in s.items():
        assert e["status"] == "DONE", (k, e["reason"])
        assert 0.9 < e["V"] <= 1 and e["n_whole_pivot"] >= e["n"] > 0, k
        assert e["eps_whole_pivot_mm"] >= e["eps_mm"] > 0, k
        assert e["at_V"]["0.9"]["n"] <= e["n"], k
        # Reconstructed from the scan's own pole-to-pole masks (V above 0.9: within 15%).
        assert e["volume_ml"] > 0 and abs(e["volume_error_pct"]) < 15, (k, e["volume_note"])
        assert "pole-to-pole masks compounded" in e["volume_note"], k
    assert s["OP"]["scan"] == "the run's own scan" and s["OP"]["pivot_pose"] == "registered"
    assert s["OP"]["e_trans_mm"] == eff["e_trans_mm"]
    # GT-OP and NOP pivoted at the pose the study computed from the truth, nothing else.
    quick = LoadScenario(scenario_name="quick").patient
    kp = run_patients.prepared_patient(
        "test:1", quick.side, quick.posture, 0.002, quick.X_BPt.GetDeterministicValue()
    )
    for k in ("GT-OP", "NOP"):
        assert s[k]["pivot_pose"] == "given" and s[k]["e_trans_mm"] is None  # no registration
        want = supervisor.pivot_pose_as_given(*km.strategy_pivot_pose(k, kp.X_BK_true))
        assert s[k]["given_pivot_pose"] == pytest.approx(want)
        assert s[k]["sim_s"] < s["OP"]["sim_s"]  # no exploration
    # NOP sweeps the transverse planes: more frames and path than the long-axis pivots; SL
    # is a line (no pivot pose), the longest in frames.
    assert s["NOP"]["n"] > 1.4 * s["GT-OP"]["n"] and s["NOP"]["eps_mm"] > s["GT-OP"]["eps_mm"]
    assert s["SL"]["sweep"] == "line" and s["SL"]["pivot_pose"] is None
    assert s["SL"]["n"] > 2 * s["OP"]["n"]
    # Tables, figures and report in OUT/closed-loop, each saying the mode.
    d = out / "closed-loop"
    for name in (
        "fig7d_er_sweep.png",
        "fig9d_starts.png",
        "fig10_efficiency.png",
        "er_sweep.json",
        "efficiency_runs.csv",
        "report.md",
    ):
        assert (d / name).exists(), name
    report = (d / "report.md").read_text()
    assert "mode: closed loop (Drake diagram" in report
    for k in ("OP", "GT-OP", "NOP", "SL"):
        assert f"- **{k}**: " in report
    assert "| OP - NOP | pole to pole | -24.66 +- 21.50 |" in report
    csv = (d / "efficiency_runs.csv").read_text()
    assert csv.count("\n") == 5 and ",given," in csv and ",line," in csv
    assert json.loads((d / "study_paper.json").read_text())["mode"] == "closed-loop"


def test_closed_loop_refuses_unknown_strategies(tmp_path, capsys):
    out = tmp_path / "study"
    code = main(
        [
            "study",
            "efficiency",
            "--patients",
            "test:1",
            "--mode",
            "closed-loop",
            "--strategies",
            "OP,NOPE",
            "--workers",
            "0",
            "--out",
            str(out),
        ]
    )
    err = capsys.readouterr().err
    assert code == 2
    assert "--strategies: expected a comma list of OP, GT-OP, NOP, SL, OP-PE" in err
    assert "(NOPE unknown)" in err
    assert not out.exists()
