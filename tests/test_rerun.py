"""A scan repeated from its summary.json alone gives the same result (issue 32).

``drake-rus scan --rerun DIR/summary.json`` takes the patient, the resolved scenario (with
the --set overrides and --seed in it) and --max-sim-time from the summary's provenance; the
rerun's E_trans, E_rot,x, V and phase times equal the recorded ones exactly. When the
software differs from the recorded run's, one warning line says so and the run goes on.
"""

import json

import pytest

from drake_rus.cli import main


@pytest.mark.slow
def test_a_rerun_repeats_the_scan_exactly(tmp_path, capsys):
    first = tmp_path / "first"
    # A quick scan with an override and a seed, so that the rerun must take both from the
    # summary (neither is given again).
    code = main(
        [
            "scan",
            "--patient",
            "test:0",
            "--scenario",
            "quick",
            "--no-record",
            "--seed",
            "3",
            "--set",
            "{controller: {pivot_rate: 0.25}}",
            "--out",
            str(first),
        ]
    )
    recorded = json.loads((first / "summary.json").read_text())
    assert code == 0 and recorded["status"] == "DONE", recorded["reason"]
    prov = recorded["provenance"]
    assert prov["overrides"] == "{controller: {pivot_rate: 0.25}}"
    assert prov["seeds"]["random_seed"] == 3 and prov["seeds"]["seed_argument"] == 3
    assert prov["seeds"]["patient"] == "test:0"
    assert prov["seeds"]["patient_generator_seed"] is not None
    assert "pivot_rate: 0.25" in prov["scenario_yaml"]
    assert prov["packages"]["drake"] and prov["arguments"]["max_sim_time"] == 150.0
    assert prov["inputs"]["localization.template"]["sha256"]
    capsys.readouterr()

    # The recorded software differs from this one: the rerun warns in one line and runs.
    prov["packages"]["numpy"] = "0.0.1"
    prov["commit"] = "0" * 40
    (first / "summary.json").write_text(json.dumps(recorded, indent=2))
    code = main(["scan", "--rerun", str(first / "summary.json"), "--no-record"])
    err = capsys.readouterr().err
    again = json.loads((first / "rerun" / "summary.json").read_text())
    assert code == 0 and again["status"] == "DONE"
    warnings = [line for line in err.splitlines() if "warning" in line]
    assert len(warnings) == 1 and warnings[0].startswith("drake-rus scan: warning: --rerun:")
    assert "commit 000000000000 -> now" in warnings[0] and "numpy 0.0.1 -> now" in warnings[0]

    for key in (
        "e_trans_mm",
        "e_rot_x_deg",
        "volume_ratio",
        "volume_ratio_whole_pivot",
        "eps_mm",
        "n_frames",
        "sim_s",
        "peak_force_n",
        "frames_total",
    ):
        assert again[key] == recorded[key], key
    assert again["phases"] == recorded["phases"]
    assert again["start"] == recorded["start"]
    assert again["provenance"]["scenario_yaml"] == prov["scenario_yaml"]
    assert again["provenance"]["seeds"] == prov["seeds"]
    assert again["provenance"]["rerun_of"] == str(first / "summary.json")
    assert again["provenance"]["overrides"] == prov["overrides"]
    # The rerun never writes over the run it repeats.
    code = main(["scan", "--rerun", str(first), "--out", str(first), "--no-record"])
    assert code == 2 and "--out: " in capsys.readouterr().err
