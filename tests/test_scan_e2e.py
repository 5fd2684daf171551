"""End to end: `drake-rus scan` on a test patient in the closed-loop simulation."""

import json

import pytest

from drake_rus.cli import main as cli_main
from drake_rus.control.supervisor import Phase
from drake_rus.scan import PhaseIs


def test_phase_is():
    system = PhaseIs(Phase.EXPLORE)
    context = system.CreateDefaultContext()
    for phase, expected in ((0, 0.0), (1, 1.0), (2, 0.0)):
        system.get_input_port(0).FixValue(context, [phase])
        assert system.get_output_port(0).Eval(context)[0] == expected


@pytest.mark.slow
def test_scan_on_a_test_patient(tmp_path):
    out = tmp_path / "scan"
    code = cli_main(
        [
            "scan",
            "--patient",
            "test:1",
            "--scenario",
            "quick",
            "--out",
            str(out),
            "--no-record",
            "--max-sim-time",
            "90",
        ]
    )
    summary = json.loads((out / "summary.json").read_text())
    assert code == 0, summary
    assert summary["status"] == "DONE", summary["reason"]
    assert summary["volume_ratio"] > 0.9
    phases = [p["phase"] for p in summary["phases"]]
    for name in ("EXPLORE", "LOCALIZE", "TRANSIT", "PIVOT", "DONE"):
        assert name in phases
    assert phases.index("EXPLORE") < phases.index("LOCALIZE") < phases.index("PIVOT")
    # The localization produced an estimate in the kidney's neighbourhood.
    assert summary["e_trans_mm"] < 30 and summary["e_rot_x_deg"] < 30
    assert summary["peak_force_n"] < 20.0
    # The kidney-length estimates that ended EXPLORE (exploration_length: estimated): one a
    # second once 40 mm are explored, the travel growing, the last a kidney-sized length.
    checks = summary["kidney_length_checks"]
    assert len(checks) >= 1 and checks[0]["travel_mm"] >= 40.0 - 1e-6
    assert all(
        b["travel_mm"] > a["travel_mm"] and b["time_s"] > a["time_s"]
        for a, b in zip(checks, checks[1:])
    )
    lengths = [c["length_mm"] for c in checks if c["length_mm"] is not None]
    assert lengths and 70.0 < lengths[-1] < 160.0
    assert "kidney_length_checks" in summary["metric_definitions"]
    # The start planner chose a window and a depth preset, and the image depth followed it.
    start = summary["start"]
    assert start["planner"] == "window" and start["windows_feasible"] >= 1
    assert summary["image_depth_m"] == start["depth_preset_m"]
    assert start["depth_preset_m"] * 1000 >= start["needed_depth_mm"]
    assert start["placement_error_mm"] == pytest.approx(5.0)
    for name in (
        "partial_cloud.ply",
        "registered_template.ply",
        "registration.png",
        "coverage.png",
        "traces.png",
        "pivot_frames.png",
        "start_plan.png",
    ):
        assert (out / name).stat().st_size > 0, name


def test_scan_bad_input_is_a_clear_error(tmp_path, capsys):
    assert (
        cli_main(["scan", "--patient", "test:0", "--out", str(tmp_path), "--max-sim-time", "-1"])
        == 2
    )
    assert "--max-sim-time" in capsys.readouterr().err
    assert (
        cli_main(
            [
                "scan",
                "--patient",
                "test:0",
                "--out",
                str(tmp_path),
                "--set",
                "{localization: {method: magic}}",
            ]
        )
        == 2
    )
    assert "'localization.method'" in capsys.readouterr().err
    assert not (tmp_path / "summary.json").exists()


def test_predicted_end_pivot_through_the_cli(tmp_path):
    """controller.pivot_strategy predicted_end reaches the scan diagram's supervisor (the
    template and fan on its pivot_model input): the pivot is one sweep, not two legs."""
    out = tmp_path / "scan"
    code = cli_main(
        [
            "scan",
            "--patient",
            "test:1",
            "--scenario",
            "quick",
            "--out",
            str(out),
            "--no-record",
            "--max-sim-time",
            "90",
            "--set",
            "{controller: {pivot_strategy: predicted_end}}",
        ]
    )
    summary = json.loads((out / "summary.json").read_text())
    assert code == 0 and summary["status"] == "DONE", summary["reason"]
    assert summary["pivot"]["legs"] == 1 and summary["volume_ratio"] > 0.9


@pytest.mark.slow
def test_scan_save_frames_writes_a_folder_that_imports_again(tmp_path):
    """``scan --save-frames``: every frame of the scan (here its first 2 s), with the
    segmenter's mask, pose and time, in the annotated-frames layout that fine-tuning reads."""
    import numpy as np

    from drake_rus.imaging.annotated import read_annotated_frames
    from drake_rus.scenario import Scenario

    out, frames_dir = tmp_path / "scan", tmp_path / "frames"
    cli_main(
        [
            "scan",
            "--patient",
            "test:0",
            "--out",
            str(out),
            "--no-record",
            "--max-sim-time",
            "2",
            "--save-frames",
            str(frames_dir),
        ]
    )
    summary = json.loads((out / "summary.json").read_text())
    imaging = Scenario().imaging
    frames = read_annotated_frames(frames_dir, (imaging.image_height_px, imaging.image_width_px))
    rate = imaging.frame_rate_hz
    assert abs(len(frames.names) - (2.0 * rate + 1)) <= 2  # every frame, at the frame rate
    assert frames.names == sorted(frames.names)
    np.testing.assert_allclose(frames.depth, summary["image_depth_m"])
    times = np.array([float(r["time_s"]) for r in frames.rows])
    np.testing.assert_allclose(np.diff(times), 1.0 / rate, atol=1e-6)
    assert {r["phase"] for r in frames.rows} <= {"APPROACH", "EXPLORE"}
    # A mask is the kidney flag: no mask pixel in a frame marked kidney-free.
    for mask, kidney in zip(frames.masks, frames.kidney):
        assert kidney or not mask.any()
    # The probe pose is recorded (unit quaternion, a position in front of the robot).
    q = np.array([[float(r[f"q_BP_{c}"]) for c in "wxyz"] for r in frames.rows])
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-5)
