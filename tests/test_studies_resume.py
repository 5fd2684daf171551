"""Study resume keyed on every setting that changes a run, labels from the runs themselves,
and provenance in every run (issue 32 "Studies that mislabel", "Not reproducible")."""

import dataclasses
import json
import math
from pathlib import Path

import pytest

from drake_rus import batch
from drake_rus.cli import main
from drake_rus.experiments import cli as study_cli
from drake_rus.experiments import keys, specs
from drake_rus.experiments import results as study_results
from drake_rus.experiments.tasks import run_task
from drake_rus.reliability import breathing
from drake_rus.scenario import DEFAULT_SCENARIOS_FILE


# ------------------------------------------------------------------------------- the key
def _task(**kw):
    return specs.er_sweep_tasks(["test:0"], specs.StudyOptions(**kw), [0.6])[0]


@pytest.mark.parametrize(
    "change",
    [
        {"segmenter": "classical"},
        {"method": "deformable"},
        {"seed": 1},
        {"voxel": 0.003},
        {"er_unit": "fixed"},
        {"mode": "closed-loop"},
        {"scenario": "quick"},
        {"overrides": "{localization: {max_points: 1500}}"},
        {"posture": "left_lateral_decubitus"},
    ],
)
def test_every_setting_changes_the_key_but_not_the_run_id(change):
    base, other = _task(), _task(**change)
    assert keys.task_key(base) != keys.task_key(other)
    if "mode" not in change and "er_unit" not in change and "posture" not in change:
        assert keys.run_id(base) == keys.run_id(other)  # same file name: the key decides


def test_key_covers_resolved_inputs_not_paths(tmp_path):
    base = _task()
    # The same scenarios file elsewhere: the same run (paths are not keyed, contents are).
    copy = tmp_path / "same.yaml"
    copy.write_text(Path(DEFAULT_SCENARIOS_FILE).read_text())
    assert keys.task_key(base) == keys.task_key(dataclasses.replace(base, scenarios_file=str(copy)))
    # Its contents changed (a default the run reads): another run.
    changed = tmp_path / "changed.yaml"
    text = Path(DEFAULT_SCENARIOS_FILE).read_text()
    assert "default: {}\n" in text
    changed.write_text(text.replace("default: {}\n", "default: {random_seed: 7}\n", 1))
    assert keys.task_key(base) != keys.task_key(
        dataclasses.replace(base, scenarios_file=str(changed))
    )
    # Where NRRD volumes go does not change a run; the reconstruction grid changes only
    # efficiency runs.
    o = specs.StudyOptions()
    eff = specs.efficiency_tasks(["test:0"], o, 0.6, "/tmp/a")[0]
    assert keys.task_key(eff) == keys.task_key(dataclasses.replace(eff, export_dir="/elsewhere"))
    assert keys.task_key(eff) != keys.task_key(dataclasses.replace(eff, recon_spacing=0.002))
    assert keys.task_key(base) == keys.task_key(dataclasses.replace(base, recon_spacing=0.002))


def test_template_file_contents_are_keyed(tmp_path):
    base = _task()
    src = keys.template_file(None)
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    a.write_bytes(src.read_bytes())
    b.write_bytes(src.read_bytes() + b"\0")
    ka = keys.task_key(dataclasses.replace(base, overrides=f"{{localization: {{template: {a}}}}}"))
    kb = keys.task_key(dataclasses.replace(base, overrides=f"{{localization: {{template: {b}}}}}"))
    assert ka != kb


# ------------------------------------------------------------------------------- batch
def test_batch_sets_aside_other_settings_and_takes_them_back(tmp_path):
    calls = []

    def fake(task):
        calls.append(task.segmenter)
        return {"run_id": keys.run_id(task), "task": task.to_dict(), "value": task.segmenter}

    oracle = specs.er_sweep_tasks(["test:0", "test:1"], specs.StudyOptions(), [0.6])
    classical = specs.er_sweep_tasks(
        ["test:0", "test:1"], specs.StudyOptions(segmenter="classical"), [0.6]
    )
    kw = dict(workers=0, progress=False, task_key=keys.task_key)
    assert batch.run_tasks(oracle, fake, tmp_path, keys.run_id, **kw)["done"] == 2
    status = batch.run_tasks(classical, fake, tmp_path, keys.run_id, **kw)
    assert status["done"] == 2 and status["skipped"] == 0
    assert len(status["superseded"]) == 2
    assert "segmenter 'oracle' -> 'classical'" in status["superseded"][0][1]
    assert {r["value"] for r in batch.load_results(tmp_path)} == {"classical"}
    assert len(list((tmp_path / "runs" / "superseded").glob("*.json"))) == 2
    # Back to the first settings: taken back from runs/superseded, nothing runs.
    calls.clear()
    status = batch.run_tasks(oracle, fake, tmp_path, keys.run_id, **kw)
    assert calls == [] and status["skipped"] == 2
    assert {r["value"] for r in batch.load_results(tmp_path)} == {"oracle"}
    assert all(
        r["task_key"] == keys.task_key(specs.StudyTask.from_dict(r["task"]))
        for r in batch.load_results(tmp_path)
    )


def test_a_killed_write_leaves_no_run(tmp_path):
    """A process killed while a result was written (SIGKILL, the OOM killer) leaves the
    atomic writer's temporary file in OUT/runs: half-written, or whole but not renamed.
    Neither is a run: loading must neither fail on it nor count a run twice."""
    task = _task()
    rid = keys.run_id(task)
    batch.save_result(tmp_path, rid, {"run_id": rid, "task": task.to_dict()})
    runs = tmp_path / "runs"
    (runs / f".{rid}.json.k1lled0.json").write_text('{"run_id": "' + rid + '", "ta')
    (runs / f".{rid}.json.n0tm0ved.json").write_text(json.dumps({"run_id": rid}))
    assert [r["run_id"] for r in batch.load_results(tmp_path)] == [rid]


def test_a_stored_run_without_a_key_is_not_reused(tmp_path):
    task = _task()
    batch.save_result(
        tmp_path, keys.run_id(task), {"run_id": keys.run_id(task), "task": task.to_dict()}
    )
    plan = batch.plan([task], tmp_path, keys.run_id, keys.task_key)
    assert len(plan["todo"]) == 1 and plan["superseded"]


def test_breathing_runs_are_keyed_on_their_parameters(tmp_path):
    """--seed 0 then --seed 1 (other breathing and shift draws): the second never takes
    the first's runs."""
    conditions = ("protocol", "free", "shift")
    first = breathing.breathing_tasks(["test:0"], conditions, seed=0)
    second = breathing.breathing_tasks(["test:0"], conditions, seed=1)
    assert [t["run_id"] for t in first] == [t["run_id"] for t in second]
    assert all(a["motion"] != b["motion"] for a, b in zip(first, second))
    ran = []

    def fake(task):
        ran.append(task["run_id"])
        return {"run_id": task["run_id"], "task": task, "motion": task["motion"]}

    ident = lambda t: t["run_id"]  # noqa: E731
    batch.run_tasks(first, fake, tmp_path, ident, workers=0, progress=False)
    ran.clear()
    status = batch.run_tasks(second, fake, tmp_path, ident, workers=0, progress=False)
    assert len(ran) == 3 and len(status["superseded"]) == 3
    assert [r["motion"] for r in batch.load_results(tmp_path)] == [t["motion"] for t in second]


# ------------------------------------------------------------------------------- labels
def test_settings_of_refuses_a_mix():
    a = {"task": _task().to_dict(), "inputs_sha256": "x"}
    b = {"task": _task(segmenter="classical").to_dict(), "inputs_sha256": "x"}
    assert study_results.settings_of([a, a])["segmenter"] == "oracle"
    with pytest.raises(
        study_results.MixedSettingsError,
        match=r"segmenter: 'oracle' \(2 runs\), 'classical' \(1 runs\)",
    ):
        study_results.settings_of([a, a, b], "er-sweep")


def _fake_run(calls):
    """A stand-in for run_task (workers 0 runs it in this process): errors that depend on
    the task's segmenter, ER and patient, and the record a real run carries."""

    def run(task):
        calls.append(keys.run_id(task))
        k = int(task.patient.split(":")[1])
        bump = 10.0 if task.segmenter == "classical" else 0.0
        e = 1.0 + 0.1 * k + bump + (6.0 + 0.7 * k) * (1.0 - task.er)
        return {
            "run_id": keys.run_id(task),
            "task": task.to_dict(),
            "mode": "kinematic",
            "patient": task.patient,
            "er": task.er,
            "start": task.start,
            "er_unit": task.er_unit,
            "kidney_length_mm": 110.0,
            "points": 100,
            "e_trans_mm": e,
            "e_rot_x_deg": e + 0.5,
            "registration_ms": 1.0,
            "inputs_sha256": keys.task_inputs_digest(task),
        }

    return run


def test_rerun_with_other_settings_runs_again_and_labels_from_runs(tmp_path, capsys, monkeypatch):
    """The observed case: er-sweep with oracle/seed, then --segmenter classical --method
    deformable. Before: "4 already done", labelled classical/deformable. Now: all run again,
    labelled by the runs; back to oracle/seed: nothing runs."""
    calls = []
    monkeypatch.setattr(study_cli, "run_task", _fake_run(calls))
    out = tmp_path / "sweep"
    argv = [
        "study",
        "er-sweep",
        "--patients",
        "test:0-2",
        "--ers",
        "0.6,1",
        "--workers",
        "0",
        "--no-progress",
        "--out",
        str(out),
    ]
    assert main(argv) == 0
    capsys.readouterr()
    calls.clear()
    assert main(argv + ["--segmenter", "classical", "--method", "deformable"]) == 0
    err = capsys.readouterr().err
    assert len(calls) == 6
    assert "6 runs, 0 already done with these settings, 6 to run" in err
    assert "6 stored run(s) of the same name were made with other settings" in err
    runs = batch.load_results(out)
    assert {(r["task"]["segmenter"], r["task"]["method"]) for r in runs} == {
        ("classical", "deformable")
    }
    saved = json.loads((out / "er_sweep.json").read_text())
    assert saved["settings"]["segmenter"] == "classical"
    assert saved["floor"]["e_trans_mm"][0] > 10  # the classical runs' values
    meta = json.loads((out / "study_er-sweep.json").read_text())
    assert meta["settings_from"] == "runs" and meta["method"] == "deformable"
    assert len(meta["invocations"]) == 1  # a new history for new settings
    report = (out / "report.md").read_text()
    assert "Segmenter: `classical`" in report and "`deformable`" in report
    assert "ER-100% floor (n = 3)" in report and "TOST" in report
    calls.clear()
    assert main(argv) == 0
    assert calls == [] and "6 already done with these settings" in capsys.readouterr().err


def test_critical_er_of_other_settings_is_not_used(tmp_path, capsys, monkeypatch):
    calls = []
    monkeypatch.setattr(study_cli, "run_task", _fake_run(calls))
    out = tmp_path / "sweep"
    assert (
        main(
            [
                "study",
                "er-sweep",
                "--patients",
                "test:0-3",
                "--ers",
                "0.6,0.9,1",
                "--segmenter",
                "classical",
                "--workers",
                "0",
                "--no-progress",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    capsys.readouterr()
    classical = study_cli._expected_settings(specs.StudyOptions(segmenter="classical"))
    oracle = study_cli._expected_settings(specs.StudyOptions())
    found = json.loads((out / "er_sweep.json").read_text())["critical_er"]
    assert study_cli._critical_er(out, classical) == found
    assert study_cli._critical_er(out, oracle) == study_cli.DEFAULT_ER
    assert "made with other settings" in capsys.readouterr().err


def test_other_mode_side_by_side_only_of_one_setting(tmp_path, capsys, monkeypatch):
    calls = []
    monkeypatch.setattr(study_cli, "run_task", _fake_run(calls))
    out = tmp_path / "both"
    common = [
        "study",
        "er-sweep",
        "--ers",
        "0.6,1",
        "--mode",
        "closed-loop",
        "--workers",
        "0",
        "--no-progress",
        "--out",
        str(out),
    ]
    # Closed loop segments with the learned segmenter unless asked otherwise.
    assert main(common + ["--patients", "test:0-2"]) == 0
    assert main(common + ["--patients", "test:3-5", "--segmenter", "classical"]) == 0
    records = [json.loads(p.read_text()) for p in (out / "runs").glob("*.json")]
    assert sorted(r["task"]["segmenter"] for r in records) == ["classical"] * 6 + ["onnx"] * 6
    capsys.readouterr()
    patients = [f"test:{k}" for k in range(6)]

    def columns(**options):
        settings = study_cli._expected_settings(specs.StudyOptions(**options))
        return study_cli._other_columns(
            out, patients, "kinematic", None, "paper", settings=settings
        )

    # The kinematic oracle study is put beside the closed loop's default (learned)
    # segmenter; a classical one beside the classical closed loop.
    (got,) = columns()
    assert got["settings"]["segmenter"] == "onnx" and got["er"]["patients"] == 3
    assert got["mode"] == study_cli.CLOSED_LOOP and got["template"] == ""
    (got,) = columns(segmenter="classical")
    assert got["settings"]["segmenter"] == "classical"
    # Other settings than any the closed loop holds, and two of them: none is picked.
    assert columns(method="deformable") == []
    assert "2 different settings" in capsys.readouterr().err


# ------------------------------------------------------------------------------- provenance
def test_a_run_records_its_provenance_and_repeats_from_its_record():
    task = specs.er_sweep_tasks(["test:0"], specs.StudyOptions(), [1.0])[0]
    r = run_task(task)
    p = r["provenance"]
    assert "scenario_yaml" in p and "localization" in p["scenario_yaml"]
    assert p["seeds"]["study_seed"] == 0 and p["seeds"]["patient"] == "test:0"
    assert "random_seed" in p["seeds"] and p["packages"]["numpy"]
    assert "commit" in p and p["scenario_name"] == "default"
    assert r["inputs_sha256"] == keys.task_inputs_digest(task)
    # The record's own task, through JSON.
    again = run_task(specs.StudyTask.from_dict(json.loads(json.dumps(r["task"]))))
    assert again["e_trans_mm"] == r["e_trans_mm"] and math.isfinite(r["e_trans_mm"])
    assert again["e_rot_x_deg"] == r["e_rot_x_deg"]
