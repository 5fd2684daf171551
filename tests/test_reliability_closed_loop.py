"""Closed-loop scans with injected faults end safely: ABORT with the right reason, the robot
at rest afterwards, and the true contact force never above the ceiling for > 50 ms.
Short runs only (a fault at 1.5 s of simulated time)."""

import json

import pytest

from drake_rus.reliability.campaign import make_tasks, run_campaign, summarize
from drake_rus.reliability.run import FORCE_VIOLATION_S, ForceWatch, RunFaultyScan, outcome_reason
from drake_rus.scenario import LoadScenario


@pytest.fixture(scope="module")
def patient_and_template():
    from drake_rus.anatomy import load_patient
    from drake_rus.localization.localize import load_registration_template

    scenario = LoadScenario(scenario_name="quick")
    return (
        load_patient("test:0", progress=False),
        load_registration_template(scenario.localization.template),
    )


@pytest.mark.parametrize(
    "fault,words",
    [
        ("{kind: force_spike, start: 1.5, magnitude: 30.0}", ["force ceiling"]),
        ("{kind: image_dropout, start: 1.5}", ["stale image"]),
        ("{kind: nan_pose, start: 1.5, duration: 0.2}", ["non-finite"]),
    ],
    ids=["force_spike", "image_dropout", "nan_pose"],
)
def test_fault_ends_in_a_safe_stop(patient_and_template, fault, words):
    patient, template = patient_and_template
    scenario = LoadScenario(
        scenario_name="quick", scenario_text=f"{{faults: {{sensor: [{fault}]}}}}"
    )
    result, check = RunFaultyScan(scenario, patient, template, max_sim_time=4.0)
    assert result.status == "ABORT"
    reason = outcome_reason(result)
    assert all(w in reason for w in words), reason
    assert result.safety_events[0].time >= 1.5
    assert result.safety_events[0].time < 1.5 + 0.35  # detected within the watchdogs
    assert check["safety_stopped"] and check["at_rest"], check
    assert check["final_command_norm"] == 0.0
    assert not check["force_violation"] and check["peak_force_n"] < 20.0


def test_force_watch_measures_time_above_ceiling():
    w = ForceWatch(ceiling=20.0)
    for k in range(200):
        t = k * 0.001
        w.add(t, 25.0 if 0.050 <= t < 0.090 else 10.0)
    assert w.peak == 25.0
    assert w.longest_above == pytest.approx(0.040, abs=0.0015)
    assert not w.violation
    for k in range(200, 300):
        w.add(k * 0.001, 30.0)
    assert w.longest_above > FORCE_VIOLATION_S and w.violation


def test_campaign_runs_resume_and_summarize(tmp_path):
    tasks = make_tasks(2, seed=4, patients=1, max_sim_time=2.5)
    assert [t["fault"] for t in tasks] == ["none", "image_dropout"]
    assert make_tasks(2, seed=4, patients=1, max_sim_time=2.5) == tasks  # reproducible
    results = run_campaign(tasks[:1], tmp_path, workers=0)
    assert len(results) == 1 and results[0]["exception"] is None
    assert results[0]["status"] == "TIMEOUT" and results[0]["peak_force_n"] > 1.0
    first = (tmp_path / "runs" / f"{tasks[0]['run_id']}.json").read_text()
    # Resuming does not redo a finished run (its file is untouched).
    seen = []
    again = run_campaign(tasks[:1], tmp_path, workers=0, progress=seen.append)
    assert seen == [] and again == results
    assert (tmp_path / "runs" / f"{tasks[0]['run_id']}.json").read_text() == first
    assert json.loads(first)["run_id"] == tasks[0]["run_id"]
    summary = summarize(results)
    assert summary["runs"] == 1 and summary["exceptions"] == 0
    assert summary["force_violations"] == 0
    assert not list((tmp_path / "runs").glob(".*"))  # no temporary files left behind


def test_done_fraction_per_fault_type(tmp_path):
    from drake_rus.reliability.campaign import fault_table, per_fault, write_outputs

    def rec(fault, status, peak):
        return {
            "run_id": f"{fault}{status}{peak}",
            "fault": fault,
            "patient": "test:0",
            "status": status,
            "peak_force_n": peak,
            "reason": "",
            "wall_s": 1.0,
            "e_trans_mm": peak / 2,
            "e_trans_at_localization_mm": peak / 4,
        }

    results = [
        rec("none", "DONE", 9.5),
        rec("none", "DONE", 10.5),
        rec("force_spike", "ABORT", 12.0),
        rec("breathing", "DONE", 9.0),
        rec("breathing", "ABORT", 11.0),
        rec("breathing", "TIMEOUT", 9.9),
    ]
    rows = {r["fault"]: r for r in per_fault(results)}
    assert list(rows) == ["none", "force_spike", "breathing"]  # campaign order
    assert rows["none"]["done_fraction"] == 1.0 and rows["none"]["max_peak_force_n"] == 10.5
    assert rows["force_spike"]["done_fraction"] == 0.0 and rows["force_spike"]["abort"] == 1
    assert rows["breathing"]["done_fraction"] == pytest.approx(1 / 3)
    assert rows["none"]["median_e_trans_done_mm"] == pytest.approx(2.5)  # DONE runs only
    assert rows["force_spike"]["median_e_trans_done_mm"] is None
    table = fault_table(results).splitlines()
    assert len(table) == 4
    assert table[3].split() == ["breathing", "3", "1", "1", "1", "0.33", "11.0", "2.2"]
    written = write_outputs(tmp_path, results, {"force_ceiling_n": 20.0})
    assert sorted(p.name for p in written) == [
        "campaign.csv",
        "campaign.json",
        "campaign.md",
        "campaign.png",
    ]
    assert (tmp_path / "campaign.png").read_bytes()[:4] == b"\x89PNG"
    md = (tmp_path / "campaign.md").read_text()
    assert "| breathing | 3 | 1 | 1 | 0.33 | 11.0 | 2.2 |" in md


def test_respiration_aware_exploration_moves_only_during_breath_holds(patient_and_template):
    """Closed loop, 15 mm breathing with 1.5 s holds every 3.5 s (2 s between holds: one
    breath at 30 breaths/min, the fastest the scenario rules allow): the probe travels along
    the kidney during holds and holds its target (in contact, no watchdog stop) between
    them."""
    import numpy as np

    from drake_rus.anatomy.motion import breath_hold

    patient, template = patient_and_template
    scenario = LoadScenario(
        scenario_name="quick",
        scenario_text=(
            "{patient: {motion: {breathing: {enabled: true, amplitude: 0.015, rate_per_min: 20, "
            "hold_period: 3.5, hold_duration: 1.5, gate_exploration: true}}}}"
        ),
    )
    result, check = RunFaultyScan(scenario, patient, template, max_sim_time=6.5)
    assert result.status == "TIMEOUT" and not result.safety_events, result.safety_events
    explore = [f for f in result.frames if f.phase == 1]  # EXPLORE
    t = np.array([f.time for f in explore])
    y = np.array([f.X_BP.translation()[1] for f in explore])
    speed = np.abs(np.gradient(y, t))
    cfg = scenario.patient.motion.breathing
    inside = np.array([breath_hold(ti - 0.3, cfg) and breath_hold(ti, cfg) for ti in t])
    outside = np.array([not breath_hold(ti - 0.4, cfg) and not breath_hold(ti, cfg) for ti in t])
    assert inside.sum() > 10 and outside.sum() > 10
    v = scenario.controller.scan_speed
    assert np.median(speed[inside]) == pytest.approx(v, rel=0.3)
    # Between holds the target stands still; friction with the breathing skin (up to
    # 16 mm/s) drags the probe at ~1 mm/s against the position loop.
    assert np.median(speed[outside]) < 0.3 * v
    assert min(f.force for f in explore) > 0.5 * scenario.controller.desired_force
    assert not check["force_violation"]


def test_breathing_comparison_table_and_plot(tmp_path):
    from drake_rus.reliability.breathing import breathing_tasks, compare, plot_comparison

    tasks = breathing_tasks(["test:0", "test:1"], amplitude=0.015)
    assert [t["fault"] for t in tasks[:3]] == [
        "no_breathing",
        "breathing_ungated",
        "breathing_gated",
    ]
    assert "gate_exploration: true" in tasks[2]["overrides"]
    assert "gate_exploration: false" in tasks[1]["overrides"]
    assert "amplitude: 0.0150" in tasks[1]["overrides"]
    errors = {
        "no_breathing": (4.0, 6.0),
        "breathing_ungated": (9.0, None),
        "breathing_gated": (5.0, 7.0),
    }
    results = [
        {
            "run_id": t["run_id"],
            "fault": t["fault"],
            "patient": t["patient"],
            "status": "DONE" if errors[t["fault"]][t["index"]] else "ABORT",
            "e_trans_mm": errors[t["fault"]][t["index"]],
        }
        for t in tasks
    ]
    table = compare(results)
    assert table["no_breathing"]["mean_e_trans_mm"] == pytest.approx(5.0)
    assert table["breathing_ungated"]["e_trans_mm"] == [9.0]
    assert table["breathing_ungated"]["done"] == 1
    assert table["breathing_gated"]["max_e_trans_mm"] == 7.0
    assert table["breathing_gated"]["mean_abs_change_mm"] == pytest.approx(1.0)
    assert table["breathing_ungated"]["max_abs_change_mm"] == pytest.approx(5.0)
    assert table["no_breathing"]["max_abs_change_mm"] == 0.0
    assert plot_comparison(results, tmp_path / "b.png").read_bytes()[:4] == b"\x89PNG"
