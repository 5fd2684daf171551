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
