"""Bad-input corpus, command line: bad arguments give exit status 2 and one message naming
the argument or field, and nothing is written to the output directory."""

import pytest

from drake_rus.cli import main


def _run(argv, capsys):
    code = main(argv)
    err = capsys.readouterr().err
    return code, err


CAMPAIGN_CASES = [
    ("zero_runs", ["--runs", "0"], ["--runs"]),
    ("negative_runs", ["--runs", "-5"], ["--runs"]),
    ("negative_workers", ["--runs", "2", "--workers", "-1"], ["--workers"]),
    ("nan_time", ["--runs", "2", "--max-sim-time", "nan"], ["--max-sim-time"]),
    ("zero_time", ["--runs", "2", "--max-sim-time", "0"], ["--max-sim-time"]),
    ("negative_seed", ["--runs", "2", "--seed", "-3"], ["--seed"]),
    ("zero_patients", ["--runs", "2", "--patients", "0"], ["--patients"]),
    ("unknown_scenario", ["--runs", "2", "--scenario", "nope"], ["'nope'", "available"]),
]


@pytest.mark.parametrize("case,args,words", CAMPAIGN_CASES, ids=[c[0] for c in CAMPAIGN_CASES])
def test_campaign_bad_arguments(tmp_path, capsys, case, args, words):
    out = tmp_path / "campaign"
    code, err = _run(["campaign", "--out", str(out), *args], capsys)
    assert code == 2
    assert err.startswith("drake-rus campaign: error:")
    for w in words:
        assert w in err, err
    assert not out.exists()


def test_campaign_missing_scenarios_file(tmp_path, capsys):
    code, err = _run(["campaign", "--runs", "1", "--out", str(tmp_path / "c"),
                      "--scenarios-file", str(tmp_path / "none.yaml")], capsys)
    assert code == 2 and "none.yaml" in err and not (tmp_path / "c").exists()


def test_campaign_out_is_a_file(tmp_path, capsys):
    target = tmp_path / "file.txt"
    target.write_text("keep me")
    code, err = _run(["campaign", "--runs", "1", "--out", str(target)], capsys)
    assert code == 2 and "--out" in err and target.read_text() == "keep me"


@pytest.mark.parametrize("argv,word", [
    (["campaign", "--runs", "abc", "--out", "x"], "--runs"),
    (["campaign", "--out", "x"], "--runs"),
    (["campaign", "--runs", "3"], "--out"),
    (["scan", "--seed", "one"], "--seed"),
], ids=["non_integer_runs", "missing_runs", "missing_out", "non_integer_seed"])
def test_argparse_errors_name_the_argument(capsys, argv, word):
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    assert word in capsys.readouterr().err


SCAN_CASES = [
    ("negative_seed", ["--seed", "-1"], ["--seed"]),
    ("zero_time", ["--max-sim-time", "0"], ["--max-sim-time"]),
    ("inf_time", ["--max-sim-time", "inf"], ["--max-sim-time"]),
    ("unknown_scenario", ["--scenario", "nope"], ["'nope'"]),
    ("bad_override", ["--set", "{contact: {time_step: -1}}"], ["contact.time_step"]),
    ("bad_override_yaml", ["--set", "{contact: ["], ["YAML"]),
    ("missing_template", ["--set", "{localization: {template: /nonexistent/t.npz}}"],
     ["localization.template", "t.npz"]),
    ("unknown_patient", ["--patient", "nobody:1", "--no-record"], ["nobody:1"]),
]


@pytest.mark.parametrize("case,args,words", SCAN_CASES, ids=[c[0] for c in SCAN_CASES])
def test_scan_bad_arguments(tmp_path, capsys, case, args, words):
    out = tmp_path / "scan"
    code, err = _run(["scan", "--out", str(out), *args], capsys)
    assert code == 2
    assert err.startswith("drake-rus scan: error:")
    for w in words:
        assert w in err, err
    assert not out.exists()
