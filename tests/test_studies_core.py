"""Study bookkeeping and statistics on constructed results, the runner's resume, and one tiny
real study through the CLI (Dask, one worker) whose output the paper notebook reads."""

import json
from pathlib import Path

import nbformat
import nrrd
import numpy as np
import pytest
from nbclient import NotebookClient

from drake_rus import batch
from drake_rus.cli import main
from drake_rus.experiments import analysis, keys, specs
from drake_rus.experiments import results as study_results

NOTEBOOK = Path(__file__).resolve().parent.parent / "notebooks" / "reproduce_paper.ipynb"


def test_expand_patients():
    assert specs.expand_patients("test:0-2") == ["test:0", "test:1", "test:2"]
    assert specs.expand_patients("seed:7, train:3,test:1-1") == ["seed:7", "train:3", "test:1"]
    assert specs.expand_patients("../shared/anatomy/body") == ["../shared/anatomy/body"]
    for bad in ("test:3-1", "bogus", ""):
        with pytest.raises(ValueError, match="--patients"):
            specs.expand_patients(bad)


def test_tasks_and_run_ids_are_unique_and_deterministic():
    o = specs.StudyOptions()
    tasks = (
        specs.er_sweep_tasks(["test:0", "test:1"], o)
        + specs.starts_tasks(["test:0"], o, 0.6)
        + specs.efficiency_tasks(["seed:5", "../x/y"], o, 0.6)
    )
    ids = [keys.run_id(t) for t in tasks]
    assert len(set(ids)) == len(ids) == 22 + 5 + 2
    # ER in units of the patient's kidney length (the default) is "erk"; of L_m "er".
    assert "er-sweep__test-0__erk060" in ids and "starts__test-0__erk060__s4" in ids
    fixed = specs.er_sweep_tasks(["test:0"], specs.StudyOptions(er_unit="fixed"), [0.6])
    assert keys.run_id(fixed[0]) == "er-sweep__test-0__er060"
    assert all("/" not in i and ":" not in i for i in ids)
    assert len(specs.ER_GRID) == 11 and specs.ER_GRID[0] == 0.0 and specs.ER_GRID[-1] == 1.0


def _er_results(rng, n=12):
    """ER sweep results whose errors converge from ER 0.6 on (below: larger errors)."""
    out = []
    for k in range(n):
        base_t, base_r = rng.uniform(2, 6), rng.uniform(2, 6)
        for er in specs.ER_GRID:
            bump = 0.0 if er >= 0.6 else 30.0 * (0.6 - er)
            # Below ER 1: +-0.2 alternating over patients (zero mean difference at ER >=
            # 0.6, so those p-values are exactly 1; no chance significance).
            wobble = 0.0 if er == 1.0 else 0.2 * (-1) ** k
            out.append(
                {
                    "patient": f"test:{k}",
                    "er": er,
                    "e_trans_mm": base_t + bump + wobble,
                    "e_rot_x_deg": base_r + bump - wobble,
                    "registration_ms": 10.0,
                    "points": 100,
                }
            )
    return out


def test_er_sweep_critical_er_and_paired_tests():
    an = analysis.analyze_er_sweep(_er_results(np.random.default_rng(0)))
    assert an["critical_er"] == pytest.approx(0.6)
    rows = {r["er"]: r for r in an["rows"]}
    assert rows[1.0]["p_e_trans"] == 1.0
    assert rows[0.3]["p_e_trans"] < 0.05 and rows[0.3]["p_e_rot_x"] < 0.05
    assert rows[0.0]["e_trans_mm_mean"] > rows[1.0]["e_trans_mm_mean"] + 10


def test_er_sweep_critical_er_needs_every_larger_er_to_agree():
    res = _er_results(np.random.default_rng(1))
    for r in res:  # ER 0.8 is worse than 100%: the critical ER is 0.9
        if r["er"] == 0.8:
            r["e_trans_mm"] += 10 + float(np.random.default_rng(len(r["patient"])).normal())
    an = analysis.analyze_er_sweep(res, rule="strict")
    assert an["critical_er"] == pytest.approx(0.9)
    assert an["first_not_significant_er"] == pytest.approx(0.6)
    # The paper's rule (the default): the smallest ER that passes.
    paper = analysis.analyze_er_sweep(res)
    assert paper["rule"] == "paper" and paper["critical_er"] == pytest.approx(0.6)
    assert paper["critical_er_strict_rule"] == pytest.approx(0.9)


def test_starts_bonferroni():
    rng = np.random.default_rng(2)
    res = [
        {
            "patient": f"test:{k}",
            "start": s,
            "er": 0.6,
            "e_trans_mm": 4 + rng.normal(0, 1) + (5.0 if s == 4 else 0.0),
            "e_rot_x_deg": 4 + rng.normal(0, 1),
        }
        for k in range(15)
        for s in range(5)
    ]
    an = analysis.analyze_starts(res)
    assert an["bonferroni_threshold"] == pytest.approx(0.005)
    assert len(an["tests"]) == 10
    sig = [(t["start_a"], t["start_b"]) for t in an["tests"] if t["significant_e_trans_mm"]]
    assert sig and all(4 in pair for pair in sig)
    assert not any(t["significant_e_rot_x_deg"] for t in an["tests"])
    assert an["any_significant"]


def _eff_result(patient, n_op, n_nop):
    def entry(n, step):
        V = np.minimum(1.0, np.arange(1, n + 1) / n)
        return {
            "n": n,
            "eps_mm": (n - 1) * step,
            "V": 1.0,
            "curve_V": V.tolist(),
            "curve_eps_mm": (np.arange(n) * step).tolist(),
            "volume_error_pct": 2.0,
            "n_full": n,
            "eps_full_mm": (n - 1) * step,
            "V_full": 1.0,
            "volume_ml": 100.0,
        }

    return {
        "patient": patient,
        "e_trans_mm": 3.0,
        "e_rot_x_deg": 3.0,
        "true_volume_ml": 98.0,
        "strategies": {
            "OP": entry(n_op, 0.75),
            "GT-OP": entry(n_op - 5, 0.75),
            "NOP": entry(n_nop, 0.75),
            "SL": entry(400, 0.25),
        },
    }


def test_efficiency_reductions_and_mean_curves():
    res = [_eff_result(f"test:{k}", 100 + k, 200 + 3 * k) for k in range(6)]
    an = analysis.analyze_efficiency(res)
    c = {
        (x["comparison"], x["metric"]): x
        for x in an["comparisons"]
        if x["definition"] == "pole_to_pole"
    }
    nop = c[("OP vs NOP", "n")]
    assert nop["reduction_mean"] == pytest.approx(np.mean([100 + 2 * k for k in range(6)]))
    assert nop["op_lower_count"] == 6 and nop["significant"]
    assert c[("OP vs GT-OP", "n")]["reduction_mean"] == pytest.approx(-5)
    assert an["bonferroni_threshold"] == pytest.approx(0.05 / 6)
    assert an["summary"]["OP"]["within_5pct"] == 6
    grid = np.array([1.0, 50.0, 500.0])
    V = analysis.mean_curve(res, "OP", "n", grid)
    assert V[-1] == pytest.approx(1.0) and 0.4 < V[1] < 0.55


def test_figure_groups_split_runs_as_the_study_tables_do(tmp_path):
    """The paper notebook's figures: one group per mode and template and, for starts, per
    ER; runs without a localization left out and counted; mixed settings named, not drawn."""

    def run(run_id, er, mode="kinematic", template=None, e_trans=1.0, segmenter="oracle"):
        task = {"study": "starts", "mode": mode, "template": template, "segmenter": segmenter}
        return {
            "run_id": run_id,
            "task": task,
            "patient": "test:0",
            "er": er,
            "start": 0,
            "e_trans_mm": e_trans,
            "e_rot_x_deg": 1.0,
        }

    runs = [
        run("a", 0.6),
        run("b", 0.8),
        run("c", 0.6, mode="closed-loop", e_trans=None),
        run("d", 0.6, mode="closed-loop"),
        run("e", 0.6, template="real"),
        run("f", 0.6, template="real", segmenter="unet"),
    ]
    (tmp_path / "runs").mkdir()
    for r in runs:
        (tmp_path / "runs" / f"{r['run_id']}.json").write_text(json.dumps(r))
    groups = study_results.figure_groups(tmp_path, "starts")
    got = [(g["label"], g["folder"], [r["run_id"] for r in g["runs"]]) for g in groups]
    assert got == [
        ("kinematic, ER 60%", "er060", ["a"]),
        ("kinematic, ER 80%", "er080", ["b"]),
        ("kinematic, template real, ER 60%", "template-real", []),
        ("closed loop, ER 60%", "closed-loop", ["d"]),
    ]
    assert groups[3]["left_out"] == 1 and groups[3]["settings"]["mode"] == "closed-loop"
    assert "segmenter" in groups[2]["error"]
    assert study_results.figure_groups(tmp_path, "er-sweep") == []


def test_runner_writes_each_run_and_resumes(tmp_path):
    calls = []

    def fake(task):
        calls.append(task.patient)
        if task.patient == "test:2":
            raise RuntimeError("boom")
        return {"run_id": keys.run_id(task), "task": task.to_dict(), "value": len(calls)}

    tasks = specs.er_sweep_tasks(
        ["test:0", "test:1", "test:2"], specs.StudyOptions(er_unit="fixed"), [0.5]
    )
    status = batch.run_tasks(tasks, fake, tmp_path, keys.run_id, workers=0, progress=False)
    assert status["done"] == 2 and status["failed"][0][0] == "er-sweep__test-2__er050"
    assert "boom" in status["failed"][0][1]
    assert sorted(p.name for p in (tmp_path / "runs").iterdir()) == [
        "er-sweep__test-0__er050.json",
        "er-sweep__test-1__er050.json",
    ]
    # Resume: only the failed run is tried again.
    calls.clear()
    status = batch.run_tasks(tasks, fake, tmp_path, keys.run_id, workers=0, progress=False)
    assert calls == ["test:2"] and status["skipped"] == 2
    assert len(study_results.load_study_results(tmp_path, "er-sweep")) == 2


@pytest.fixture(scope="module")
def tiny_paper(tmp_path_factory):
    """A real (tiny) paper study through the CLI: one patient, two ERs, two starts, the
    efficiency sweeps, run on an embedded Dask cluster of one worker."""
    out = tmp_path_factory.mktemp("paper")
    code = main(
        [
            "study",
            "paper",
            "--patients",
            "test:2",
            "--ers",
            "0.6,1",
            "--starts",
            "2",
            "--out",
            str(out),
            "--workers",
            "1",
            "--no-progress",
            "--recon-spacing",
            "0.002",
            "--set",
            "{localization: {max_points: 1500}}",
            "--closed-loop",
            "1",
        ]
    )
    return code, out


def test_tiny_paper_study_outputs(tiny_paper):
    code, out = tiny_paper
    assert code == 0
    for name in (
        "report.md",
        "fig7d_er_sweep.png",
        "fig9d_starts.png",
        "fig10_efficiency.png",
        "er_sweep_table.csv",
        "starts_tests.csv",
        "efficiency_runs.csv",
        "study_paper.json",
    ):
        assert (out / name).stat().st_size > 0, name
    assert len(list((out / "runs").glob("*.json"))) == 2 + 2 + 1 + 1
    meta = json.loads((out / "study_paper.json").read_text())
    assert meta["mode"].startswith("kinematic") and meta["failed_runs"] == []
    # The closed-loop check: one dynamic scan beside its kinematic twin.
    closed = study_results.load_study_results(out, "closed-loop")
    assert len(closed) == 1 and closed[0]["closed_loop"]["status"] == "DONE"
    assert closed[0]["closed_loop"]["V"] > 0.9 and closed[0]["kinematic"]["V"] > 0.9
    assert (out / "closed_loop.csv").stat().st_size > 0
    eff = study_results.load_study_results(out, "efficiency")[0]
    s = eff["strategies"]
    assert s["GT-OP"]["V"] > 0.9 and s["GT-OP"]["n"] < s["NOP"]["n"]
    assert abs(s["GT-OP"]["volume_error_pct"]) < 5.0
    assert sorted(s["GT-OP"]["nrrd"]) == [
        "test-2__GT-OP__kidney_mask.nrrd",
        "test-2__GT-OP__kidney_probability.nrrd",
    ]
    mask, header = nrrd.read(str(out / "volumes" / "test-2__GT-OP__kidney_mask.nrrd"))
    ml = mask.sum() * float(np.prod(np.diag(header["space directions"]))) / 1000.0
    assert ml == pytest.approx(s["GT-OP"]["volume_ml"], rel=1e-6)
    report = (out / "report.md").read_text()
    assert "kinematic" in report and "8.73" in report and "| OP |" in report
    assert "| test:2 | closed-loop | DONE |" in report


def test_study_resumes_without_rerunning(tiny_paper):
    code, out = tiny_paper
    stamps = {p: p.stat().st_mtime_ns for p in (out / "runs").glob("*.json")}
    # The same settings (the reconstruction grid only changes efficiency runs): nothing
    # runs again, and the starts run at the er-sweep's critical ER.
    assert (
        main(
            [
                "study",
                "starts",
                "--patients",
                "test:2",
                "--starts",
                "2",
                "--out",
                str(out),
                "--workers",
                "0",
                "--no-progress",
                "--set",
                "{localization: {max_points: 1500}}",
            ]
        )
        == 0
    )
    assert {p: p.stat().st_mtime_ns for p in (out / "runs").glob("*.json")} == stamps


def test_reproduce_paper_notebook_runs_on_the_tiny_study(tiny_paper, tmp_path, monkeypatch):
    _, out = tiny_paper
    monkeypatch.setenv("DRAKE_RUS_STUDY_DIR", str(out))
    monkeypatch.setenv("DRAKE_RUS_FIG_DIR", str(tmp_path))
    monkeypatch.setenv("MPLBACKEND", "Agg")
    nb = nbformat.read(NOTEBOOK, as_version=4)
    NotebookClient(
        nb,
        timeout=300,
        kernel_name="python3",
        resources={"metadata": {"path": str(NOTEBOOK.parent)}},
    ).execute()
    for name in ("fig7d_er_sweep.png", "fig9d_starts.png", "fig10_efficiency.png"):
        assert (tmp_path / name).stat().st_size > 0
    text = "".join(
        o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
    )
    assert "OP vs NOP" in text
    # Each comparison names its definition of the costs (the same pair is tested under
    # three) and the strategy its count is of.
    lines = [ln for ln in text.splitlines() if " vs " in ln and "reduction" in ln]
    assert lines and all(
        ln.split()[0] in ("pole_to_pole", "whole_pivot", "at_V0.9") for ln in lines
    )
    assert {ln.split()[0] for ln in lines} == {"pole_to_pole", "whole_pivot", "at_V0.9"}
    assert all("OP-PE lower on" in ln for ln in lines if "OP-PE vs OP" in ln)


def test_cli_errors_are_named(capsys):
    assert main(["study", "er-sweep", "--patients", "nonsense", "--workers", "0"]) == 2
    assert "--patients" in capsys.readouterr().err
    assert (
        main(["study", "er-sweep", "--patients", "test:0", "--ers", "0.5,2", "--workers", "0"]) == 2
    )
    assert "--ers" in capsys.readouterr().err
