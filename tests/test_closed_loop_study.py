"""``drake-rus study ... --mode closed-loop``: every study run a full closed-loop scan on the
Drake diagram, with the kinematic run's record, and the report naming the mode."""

import json
import math

from drake_rus.cli import main


def test_tiny_closed_loop_paper_study(tmp_path, capsys):
    out = tmp_path / "study"
    code = main(["study", "paper", "--patients", "test:1", "--scenario", "quick",
                 "--ers", "0.6,1", "--starts", "1", "--mode", "closed-loop", "--workers", "0",
                 "--no-progress", "--no-nrrd", "--out", str(out)])
    assert code == 0, capsys.readouterr()
    runs = sorted((out / "runs").glob("*.json"))
    assert len(runs) == 4   # ER 60% and 100%, one start, one efficiency run
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
    assert list(eff["strategies"]) == ["OP"]
    assert math.isfinite(eff["strategies"]["OP"]["V"])
    # Tables, figures and report in OUT/closed-loop, each saying the mode.
    d = out / "closed-loop"
    for name in ("fig7d_er_sweep.png", "fig9d_starts.png", "fig10_efficiency.png",
                 "er_sweep.json", "efficiency_runs.csv", "report.md"):
        assert (d / name).exists(), name
    report = (d / "report.md").read_text()
    assert "mode: closed loop (Drake diagram" in report
    assert json.loads((d / "study_paper.json").read_text())["mode"] == "closed-loop"


def test_closed_loop_refuses_strategies_it_has_not(tmp_path, capsys):
    out = tmp_path / "study"
    code = main(["study", "efficiency", "--patients", "test:1", "--mode", "closed-loop",
                 "--strategies", "OP,NOP", "--workers", "0", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2
    assert "--strategies: NOP has no closed-loop equivalent" in err
    assert not out.exists()
