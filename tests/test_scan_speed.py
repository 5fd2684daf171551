"""The pieces behind the scan's speed (issue 16): the event that ends the scan, the force
trace statistics of the step validation and the benchmark's profile summary. Speed itself is
measured by ``python -m benchmarks scan``, never asserted here."""

import sys
import types

import numpy as np
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource

from drake_rus.control.supervisor import Phase
from drake_rus.paths import REPO_ROOT
from drake_rus.scan.diagram import ScanTerminator
from drake_rus.scan.truth import force_trace_stats

if str(REPO_ROOT) not in sys.path:  # benchmarks/ lives next to the package, not in it
    sys.path.insert(0, str(REPO_ROOT))
from benchmarks.scan import PLANT, summarise_profile  # noqa: E402


def _run_with_phase(phase, enabled=True, until=1.0):
    builder = DiagramBuilder()
    source = builder.AddSystem(ConstantVectorSource([float(phase)]))
    terminator = builder.AddSystem(ScanTerminator((Phase.DONE, Phase.ABORT), 0.01))
    terminator.enabled = enabled
    builder.Connect(source.get_output_port(), terminator.get_input_port(0))
    simulator = Simulator(builder.Build())
    status = simulator.AdvanceTo(until)
    return simulator.get_context().get_time(), status


def test_terminator_ends_the_simulation_on_a_terminal_phase():
    t, status = _run_with_phase(Phase.DONE)
    assert t < 0.05 and "scan finished" in status.FormatMessage()
    t, _ = _run_with_phase(Phase.ABORT)
    assert t < 0.05


def test_terminator_lets_other_phases_and_a_disabled_terminator_run_on():
    assert _run_with_phase(Phase.PIVOT)[0] == 1.0
    assert _run_with_phase(Phase.DONE, enabled=False)[0] == 1.0


def test_force_trace_stats_per_phase_and_landing_peak():
    t = np.arange(0.0, 10.0, 0.005)
    F = np.full_like(t, 9.0)
    F[(t > 1.0) & (t < 1.2)] = 11.0  # landing overshoot
    F[(t >= 6.0)] += 0.1 * np.sin(2 * np.pi * 3 * t[t >= 6.0])  # pivot ripple
    wrench = np.zeros((6, len(t)))
    wrench[5] = -F
    result = types.SimpleNamespace(
        logs={"force_true": (t, wrench)},
        phases=[
            ("APPROACH", 0.0, 1.0),
            ("EXPLORE", 1.0, 5.0),
            ("LOCALIZE", 5.0, 6.0),
            ("PIVOT", 6.0, 10.0),
            ("DONE", 10.0, 10.0),
        ],
    )
    stats = force_trace_stats(result)
    assert stats["landing_peak_n"] == 11.0
    assert abs(stats["explore_mean_n"] - 9.0) < 1e-9 and stats["explore_ripple_n"] < 1e-9
    assert abs(stats["pivot_mean_n"] - 9.0) < 1e-3
    assert abs(stats["pivot_ripple_n"] - 0.1 / np.sqrt(2)) < 1e-3
    assert force_trace_stats(types.SimpleNamespace(logs={}, phases=[]))["pivot_mean_n"] is None


def test_profile_summary_attributes_samples_to_systems_and_the_plant(tmp_path):
    raw = tmp_path / "raw.txt"
    loop = "main;drake::systems::Simulator<double>::AdvanceTo"
    raw.write_text(
        "\n".join(
            [
                f"{loop};SafetyLayer._update (x.py:1);Segmenter._result (y.py:2) 6",
                f"{loop};SafetyLayer._update (x.py:1) 2",
                f"{loop};ProbeForceEstimator._calc (s.py:3);"
                "drake::multibody::internal::SapDriver<double>::CalcContactSolverResults 3",
                f"{loop};drake::systems::VectorLogSink<double>::WriteToLog 1",
                "main;import_stuff 50",
            ]
        )
        + "\n"
    )
    out = summarise_profile(raw, {"SafetyLayer", "Segmenter", "ProbeForceEstimator"})
    assert out["loop_samples"] == 12
    shares = out["share_percent"]
    assert shares["Segmenter"] == 50.0 and shares["SafetyLayer"] == round(200 / 12, 1)
    assert shares[PLANT] == 25.0
    assert "ProbeForceEstimator" not in shares


def test_benchmark_repeat_reports_every_run_and_the_median(monkeypatch, capsys):
    import json

    import benchmarks.scan as bench

    rates = iter([5.0, 7.0, 6.0])

    def fake_run_one(scenario, patient):
        rate = next(rates)
        return {"rtf_scan": rate, "rtf_scan_cpu": rate, "scan_cpu_s": 29.0 / rate}

    monkeypatch.setattr(bench, "run_one", fake_run_one)
    assert bench.main(["--no-profile", "--no-reference", "--repeat", "3"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["rtf_scan_cpu_runs"] == [5.0, 7.0, 6.0] and out["rtf_scan_cpu_median"] == 6.0
    assert out["rtf_scan_cpu"] == 5.0  # the first run's full record stays
    assert out["scan_cpu_s_median"] == round(29.0 / 6.0, 3)
