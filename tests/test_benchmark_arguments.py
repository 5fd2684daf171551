"""A benchmark's argument it cannot use is one line on stderr naming the option, and exit
status 2, before any patient is loaded or anything is timed (not a traceback from deep
inside the run, nor a silent run of something else)."""

import pytest

from benchmarks.__main__ import main as run_benchmark


def _one_line_error(capsys, argv, option):
    assert run_benchmark(argv) == 2
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert len(err.splitlines()) == 1 and option in err, captured
    assert "Traceback" not in captured.err


@pytest.mark.parametrize(
    "args, option",
    [
        (["--patients", "0"], "--patients"),
        (["--patients", "test:x"], "--patients"),
        (["--patients", "test:3-1"], "--patients"),
        (["--er", "0"], "--er"),
        (["--er", "nan"], "--er"),
        (["--voxel", "-0.002"], "--voxel"),
    ],
)
def test_localization_bad_arguments(capsys, monkeypatch, args, option):
    from benchmarks import localization

    monkeypatch.setattr(localization, "load_patient", lambda *a, **k: pytest.fail("loaded"))
    _one_line_error(capsys, ["localization", *args], option)


@pytest.fixture
def label_map_folder(tmp_path):
    """A KiTS-layout folder of two cases (the files are never read before a build)."""
    for case in ("case_00000", "case_00001"):
        (tmp_path / case).mkdir()
        (tmp_path / case / "segmentation.nii.gz").write_bytes(b"")
    return tmp_path


@pytest.mark.parametrize(
    "args, option",
    [
        (["--policies", "exclude,foo"], "--policies"),
        (["--policies", ","], "--policies"),
        (["--n", "0"], "--n"),
        (["--test", "x/y"], "--test"),
        (["--test", "5-9"], "--test"),  # selects no case: it once built, then failed
    ],
)
def test_real_template_bad_arguments(capsys, monkeypatch, label_map_folder, args, option):
    from benchmarks import real_template

    monkeypatch.setattr(real_template, "ct_template", lambda *a, **k: pytest.fail("built"))
    _one_line_error(capsys, ["real_template", "--cases", str(label_map_folder), *args], option)


def test_real_template_refuses_an_unknown_option(capsys, tmp_path):
    """A misspelt option (``--polices``) was ignored: the run measured the default policy."""
    with pytest.raises(SystemExit) as stop:
        run_benchmark(["real_template", "--cases", str(tmp_path / "none"), "--polices", "mask"])
    assert stop.value.code == 2 and "--polices" in capsys.readouterr().err


def test_real_template_folder_without_label_maps_is_one_line(capsys, tmp_path):
    _one_line_error(capsys, ["real_template", "--cases", str(tmp_path)], "--cases")


@pytest.mark.parametrize(
    "args, option",
    [
        (["--patients", "0"], "--patients"),  # was an IndexError on specs[0]
        (["--frames", "0"], "--frames"),
        (["--iou-frames", "-1"], "--iou-frames"),
        (["--speed-frames", "0"], "--speed-frames"),
        (["--depth-views", "-3"], "--depth-views"),
        (["--onnx-model", "/nonexistent/model.onnx"], "--onnx-model"),
    ],
)
def test_imaging_bad_arguments(capsys, monkeypatch, args, option):
    from drake_rus.imaging.training import evaluation

    monkeypatch.setattr(evaluation, "load_volume", lambda *a, **k: pytest.fail("loaded"))
    _one_line_error(capsys, ["imaging", *args], option)


def test_imaging_refuses_an_unknown_source(capsys):
    """Any --source but 'test' once ran the phantoms."""
    with pytest.raises(SystemExit) as stop:
        run_benchmark(["imaging", "--source", "tset"])
    assert stop.value.code == 2 and "--source" in capsys.readouterr().err


@pytest.mark.parametrize("hold", ["0", "-5", "nan"])
def test_force_loop_hold_must_be_positive(capsys, monkeypatch, hold):
    """``--hold 0`` once read as "no option given" and ran the whole default set
    (stiffness, validation, 60 s holds): tens of minutes."""
    from benchmarks import force_loop

    for step in ("stiffness_range", "validate", "holds"):
        monkeypatch.setattr(force_loop, step, lambda *a, **k: pytest.fail("ran"))
    _one_line_error(capsys, ["force_loop", "--hold", hold], "--hold")


@pytest.mark.parametrize(
    "args, option",
    [
        (["--steps", "0.001,abc"], "--steps"),  # was a float() traceback after the import
        (["--steps", "0.001,0"], "--steps"),
        (["--steps", "-0.01"], "--steps"),
        (["--steps", ""], "--steps"),
        (["--force-log-period", "0"], "--force-log-period"),
        (["--patients", ","], "--patients"),
    ],
)
def test_scan_validate_bad_arguments(capsys, monkeypatch, args, option):
    from benchmarks import scan

    monkeypatch.setattr(scan, "run_one", lambda *a, **k: pytest.fail("scanned"))
    with pytest.raises(SystemExit) as stop:
        run_benchmark(["scan", "--validate", "--no-profile", *args])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and option in err.strip().splitlines()[-1]
    assert "Traceback" not in err


@pytest.mark.parametrize("value", ["0", "-10", "nan"])
def test_scan_benchmarks_refuse_a_max_sim_time_that_is_not_positive(
    capsys, monkeypatch, tmp_path, value
):
    """--max-sim-time 0 started every scan (each after building its patient) and ended it at
    once: a whole run of TIMEOUT rows instead of one line."""
    from benchmarks import pivot, real_anatomy, real_kidneys

    monkeypatch.setattr(pivot, "run_one", lambda *a, **k: pytest.fail("scanned"))
    monkeypatch.setattr(real_kidneys, "scan_case", lambda *a, **k: pytest.fail("scanned"))
    monkeypatch.setattr(real_anatomy, "run_one", lambda *a, **k: pytest.fail("scanned"))
    flag = ["--max-sim-time", value]
    _one_line_error(capsys, ["pivot", "--patients", "test:0", *flag], "--max-sim-time")
    _one_line_error(capsys, ["real_kidneys", "--cases", str(tmp_path), *flag], "--max-sim-time")
    body = tmp_path / "body"
    body.mkdir()
    assert real_anatomy.main(["--patients", str(body), *flag]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("--max-sim-time: ") and len(err.splitlines()) == 1


@pytest.mark.parametrize("name", ["station", "control"])
@pytest.mark.parametrize("value", ["0", "-1"])
def test_rate_benchmarks_refuse_a_duration_that_is_not_positive(capsys, monkeypatch, name, value):
    """--duration 0 divided by a wall time of almost nothing; negative went back in time."""
    import importlib

    bench = importlib.import_module(f"benchmarks.{name}")
    monkeypatch.setattr(bench, "LoadScenario", lambda *a, **k: pytest.fail("built"))
    _one_line_error(capsys, [name, "--duration", value], "--duration")


@pytest.mark.parametrize("patients", ["test:x", "test:4-0", ","])
def test_pivot_bad_patients_is_one_line(capsys, monkeypatch, patients):
    """expand_patients' ValueError (its message names --patients) was a traceback."""
    from benchmarks import pivot

    monkeypatch.setattr(pivot, "run_one", lambda *a, **k: pytest.fail("scanned"))
    _one_line_error(capsys, ["pivot", "--patients", patients], "--patients")


def test_segmenter_finetune_refuses_a_used_out_folder_on_stderr(capsys, tmp_path):
    """The error went to stdout, whose last line is the JSON a machine parses."""
    pytest.importorskip("torch", reason="the train extra (PyTorch) is not installed")
    (tmp_path / "old.txt").write_text("x")
    _one_line_error(capsys, ["segmenter_finetune", "--out", str(tmp_path)], "--out")


def test_pivot_runs_a_repeated_strategy_once(capsys, monkeypatch):
    """``--strategies two_leg two_leg`` ran and listed every patient's scan twice."""
    from benchmarks import pivot

    runs = []

    def fake_run_one(spec, strategy, *args):
        runs.append((spec, strategy))
        row = {k: 1.0 for k in (*pivot.FIELDS, "eps_pretilt_mm")}
        row.update(n_whole_pivot=10, n_frames=10)
        return {"patient": spec, "strategy": strategy, "status": "DONE", "wall_s": 0.0, **row}

    monkeypatch.setattr(pivot, "run_one", fake_run_one)
    monkeypatch.setattr(pivot, "load_registration_template", lambda path: None)
    argv = ["--patients", "test:0", "--strategies", "two_leg", "predicted_end", "two_leg"]
    assert run_benchmark(["pivot", *argv]) == 0
    assert runs == [("test:0", "two_leg"), ("test:0", "predicted_end")]


@pytest.mark.parametrize("seed", ["-200", str(2**64)])
def test_segmenter_finetune_refuses_a_seed_out_of_range(capsys, tmp_path, seed):
    """-200 failed in numpy's generator after the first patient was built; 2**64 in
    PyTorch's after the frames. (A used --out, refused later, keeps the old code fast.)"""
    (tmp_path / "old.txt").write_text("x")
    argv = ["segmenter_finetune", "--out", str(tmp_path), "--seed", seed]
    with pytest.raises(SystemExit) as stop:
        run_benchmark(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert stop.value.code == 2 and "--seed: expected an integer 0-4294967295" in err[-1], err
