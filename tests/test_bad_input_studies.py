"""Bad-input corpus, studies (issue 32): each case exits with status 2 and one line naming
the argument and the expected form, and writes nothing to the output folder."""

import pytest

from drake_rus.cli import main


def _run(argv, capsys):
    code = main(argv)
    return code, capsys.readouterr().err


ERS_CASES = [
    ("empty", ""),  # was: the default grid, "critical ER 0%"
    ("only_commas", ",,"),
    ("no_reference", "0.5"),  # was: 0.5 made the reference, "critical ER 50%"
    ("no_reference_grid", "0,0.3,0.6,0.9"),
    ("nan", "nan,1"),
    ("inf", "0.5,inf,1"),
    ("negative", "-0.1,1"),
    ("above_one", "0.5,1,1.2"),
    ("words", "half,1"),
]


@pytest.mark.parametrize("study", ["er-sweep", "paper"])
@pytest.mark.parametrize("case,ers", ERS_CASES, ids=[c[0] for c in ERS_CASES])
def test_ers_must_be_a_grid_with_the_reference(tmp_path, capsys, study, case, ers):
    out = tmp_path / "study"
    code, err = _run(
        [
            "study",
            study,
            "--patients",
            "test:0",
            f"--ers={ers}",
            "--out",
            str(out),
            "--workers",
            "0",
            "--no-progress",
        ],
        capsys,
    )
    assert code == 2, err
    assert err.startswith("drake-rus study: error: --ers: expected a non-empty comma list")
    assert "includes the reference 1" in err and err.count("\n") == 1, err
    assert not out.exists()


MARGIN_CASES = [
    ("zero_mm", ["--margin-mm", "0"], "--margin-mm"),
    ("negative_mm", ["--margin-mm", "-5"], "--margin-mm"),
    ("nan_deg", ["--margin-deg", "nan"], "--margin-deg"),
    ("inf_deg", ["--margin-deg", "inf"], "--margin-deg"),
]


@pytest.mark.parametrize("case,args,flag", MARGIN_CASES, ids=[c[0] for c in MARGIN_CASES])
def test_equivalence_margin_must_be_positive(tmp_path, capsys, case, args, flag):
    out = tmp_path / "study"
    code, err = _run(
        ["study", "er-sweep", "--patients", "test:0", "--out", str(out), *args], capsys
    )
    assert code == 2 and f"error: {flag}: expected a positive margin" in err, err
    assert err.count("\n") == 1 and not out.exists()


def test_closed_loop_count_must_not_be_negative(tmp_path, capsys):
    out = tmp_path / "study"
    code, err = _run(
        ["study", "paper", "--patients", "test:0", "--out", str(out), "--closed-loop", "-1"],
        capsys,
    )
    assert code == 2 and "error: --closed-loop: expected 0 or more patients" in err, err
    assert err.count("\n") == 1 and not out.exists()


BREATHING_CASES = [
    ("unknown_condition", ["--conditions", "still,apnea"], "--conditions"),
    ("no_condition", ["--conditions", ","], "--conditions"),
    ("negative_workers", ["--workers", "-1"], "--workers"),
    ("max_sim_time_zero", ["--max-sim-time", "0"], "--max-sim-time"),
    ("max_sim_time_nan", ["--max-sim-time", "nan"], "--max-sim-time"),
    ("max_sim_time_inf", ["--max-sim-time", "inf"], "--max-sim-time"),
    ("max_sim_time_negative", ["--max-sim-time", "-5"], "--max-sim-time"),
]


@pytest.mark.parametrize("case,args,flag", BREATHING_CASES, ids=[c[0] for c in BREATHING_CASES])
def test_breathing_parameters_must_exist(tmp_path, capsys, case, args, flag):
    out = tmp_path / "breathing"
    code, err = _run(
        ["breathing", "--patients", "test:0", "--out", str(out), "--workers", "0", *args], capsys
    )
    assert code == 2, err
    assert err.startswith(f"drake-rus breathing: error: {flag}: expected"), err
    assert err.count("\n") == 1 and not out.exists()


def test_negative_workers_named(tmp_path, capsys):
    out = tmp_path / "study"
    code, err = _run(
        ["study", "er-sweep", "--patients", "test:0", "--workers", "-3", "--out", str(out)], capsys
    )
    assert code == 2 and "--workers" in err and not out.exists()
