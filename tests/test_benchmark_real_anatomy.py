"""``python -m benchmarks real_anatomy``: a scenario or ``--set`` it cannot use is one line
and exit 2, before any patient is loaded or scanned (it once raised a traceback)."""

import json

import pytest

from benchmarks import real_anatomy


@pytest.mark.parametrize(
    "args, word",
    [
        (["--set", "{imaging: {segmenter: foo}}"], "imaging.segmenter"),
        (["--set", "{imaging: ["], "YAML"),
        (["--scenario", "no_such_scenario"], "no_such_scenario"),
    ],
)
def test_bad_scenario_is_one_line_before_any_scan(tmp_path, monkeypatch, capsys, args, word):
    scanned = []
    monkeypatch.setattr(real_anatomy, "run_one", lambda *a, **k: scanned.append(a))
    body = tmp_path / "body"
    body.mkdir()
    assert real_anatomy.main(["--patients", str(body), *args]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert err.startswith("--scenario/--set: ") and word in err
    assert captured.out == ""  # stdout is for the table and the JSON
    assert scanned == []


@pytest.mark.parametrize(
    "argv, word",
    [
        (["pivot", "--set", "{imaging: {segmenter: foo}}"], "imaging.segmenter"),
        (["control", "--scenario", "no_such_scenario"], "no_such_scenario"),
    ],
)
def test_any_benchmark_refuses_a_bad_scenario_in_one_line(capsys, argv, word):
    """The dispatcher turns a scenario error of any benchmark into one line naming the
    benchmark, and exit 2 (several raised a traceback)."""
    from benchmarks.__main__ import main

    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"python -m benchmarks {argv[0]}: ") and word in err
    assert len(err.splitlines()) == 1


def _record_scans(monkeypatch):
    scanned = []

    def fake_run_one(body, posture, *args):
        scanned.append((str(body), posture))
        return {"body": str(body), "posture": posture, "status": "DONE"}

    monkeypatch.setattr(real_anatomy, "run_one", fake_run_one)
    return scanned


def test_fresh_seed_base_moves_the_fresh_patients(tmp_path, monkeypatch, capsys):
    """``--fresh-seed-base N`` scans seeds N.. instead of 5,000,000.., and the JSON says so."""
    scanned = _record_scans(monkeypatch)
    body = tmp_path / "body"
    body.mkdir()
    argv = ["--patients", str(body), "--postures", "supine", "--fresh-seeds", "2"]
    assert real_anatomy.main([*argv, "--fresh-seed-base", "7000000"]) == 0
    assert [b for b, _ in scanned[1:]] == ["seed:7000000", "seed:7000001"]
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["fresh_seed_base"] == 7_000_000 and summary["fresh_seeds"] == 2
    scanned.clear()
    assert real_anatomy.main(argv) == 0
    assert [b for b, _ in scanned[1:]] == ["seed:5000000", "seed:5000001"]


@pytest.mark.parametrize(
    "base, count, word",
    [
        (-1, 3, "non-negative"),
        (2_000_000, 3, "overlap"),  # the test cohort
        (999_999, 2, "overlap"),  # runs into the training cohort
        (3_999_999, 1, "overlap"),  # the last CT-body seed
    ],
)
def test_fresh_seed_base_in_a_cohort_is_one_line(tmp_path, monkeypatch, capsys, base, count, word):
    scanned = _record_scans(monkeypatch)
    body = tmp_path / "body"
    body.mkdir()
    argv = ["--patients", str(body), "--fresh-seeds", str(count)]
    assert real_anatomy.main([*argv, "--fresh-seed-base", str(base)]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert err.startswith("--fresh-seed-base: ") and word in err and len(err.splitlines()) == 1
    assert captured.out == ""
    assert scanned == []


@pytest.mark.parametrize(
    "args, start",
    [
        (["--fresh-seeds", "-1"], "--fresh-seeds: "),
        (["--max-sim-time", "0"], "--max-sim-time: "),
    ],
)
def test_argument_errors_go_to_stderr(tmp_path, monkeypatch, capsys, args, start):
    """The last stdout line is the JSON machines parse: an error is one line on stderr."""
    scanned = _record_scans(monkeypatch)
    body = tmp_path / "body"
    body.mkdir()
    assert real_anatomy.main(["--patients", str(body), *args]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.startswith(start)
    assert len(captured.err.strip().splitlines()) == 1
    assert scanned == []


def test_missing_patients_go_to_stderr(tmp_path, monkeypatch, capsys):
    scanned = _record_scans(monkeypatch)
    assert real_anatomy.main(["--patients", str(tmp_path / "missing")]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.startswith("--patients: not found: ")
    assert scanned == []


def test_fresh_seed_base_just_outside_the_cohorts_is_accepted():
    assert real_anatomy.check_fresh_seed_base(999_998, 2) is None
    assert real_anatomy.check_fresh_seed_base(4_000_000, 30) is None
    assert real_anatomy.check_fresh_seed_base(2_000_000, 0) is None


def test_a_repeated_body_is_scanned_once(tmp_path, monkeypatch, capsys):
    """``--patients A A/ B A`` scanned A three times; a repeated body (the same path,
    written with or without a trailing slash) counts once, in the order first given."""
    scanned = _record_scans(monkeypatch)
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    argv = ["--patients", str(a), f"{a}/", str(b), str(a), "--postures", "supine"]
    assert real_anatomy.main(argv) == 0
    assert scanned == [(str(a), "supine"), (str(b), "supine")]
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert len(summary["scans"]) == 2


def test_a_repeated_posture_is_scanned_once(tmp_path, monkeypatch, capsys):
    """``--postures supine supine`` scanned every body twice and listed both rows; a
    repeated value counts once, as in the commands' list options."""
    scanned = _record_scans(monkeypatch)
    body = tmp_path / "body"
    body.mkdir()
    argv = ["--patients", str(body), "--postures", "supine", "supine", "left_lateral_decubitus"]
    argv += ["--fresh-seeds", "1", "--fresh-postures", "supine", "supine"]
    assert real_anatomy.main(argv) == 0
    assert scanned == [
        (str(body), "supine"),
        (str(body), "left_lateral_decubitus"),
        ("seed:5000000", "supine"),
    ]
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert len(summary["scans"]) == 3 and summary["fresh_seeds"] == 1
