"""``python -m benchmarks real_anatomy``: a scenario or ``--set`` it cannot use is one line
and exit 2, before any patient is loaded or scanned (it once raised a traceback)."""

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
    out = capsys.readouterr().out.strip()
    assert out.startswith("--scenario/--set: ") and word in out
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
