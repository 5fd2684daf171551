"""Issue 17: progress that tells the truth, Ctrl-C leaves a partial summary, repeated scans
reuse the patient cache."""

import json

import pytest

from drake_rus.cli import main
from drake_rus.progress import AdvanceWithProgress


class _FakeContext:
    def __init__(self):
        self.t = 0.0

    def get_time(self):
        return self.t


class _FakeSimulator:
    def __init__(self):
        self.context = _FakeContext()

    def get_context(self):
        return self.context

    def AdvanceTo(self, t):
        self.context.t = t


def _phases(schedule):
    """on_step returning the phase of the schedule [(start time, name), ...]."""

    def label(context):
        name = schedule[0][1]
        for start, n in schedule:
            if context.get_time() >= start - 1e-9:
                name = n
        return name

    return label


def test_one_log_line_per_phase_when_not_a_terminal(capsys):
    sim = _FakeSimulator()
    schedule = [(0.0, "APPROACH"), (1.0, "EXPLORE"), (5.0, "LOCALIZE"), (6.0, "DONE")]
    AdvanceWithProgress(
        sim,
        150.0,
        desc="scan",
        step=0.25,
        on_step=_phases(schedule),
        should_stop=lambda c: c.get_time() >= 6.0,
        expected=20.0,
    )
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("scan: ")]
    assert [ln.split()[1] for ln in lines] == ["APPROACH", "EXPLORE", "LOCALIZE", "DONE"]
    assert "at 1.0 sim s" in lines[1]
    assert sim.context.t == pytest.approx(6.0)  # stopped early, not at the 150 s cap


def test_no_log_lines_when_disabled(capsys):
    AdvanceWithProgress(_FakeSimulator(), 2.0, step=0.5, disable=True, on_step=lambda c: "EXPLORE")
    assert capsys.readouterr().err == ""


def test_bar_counts_towards_the_expected_length(monkeypatch):
    """The bar's total is the expected scan length, stretched (never past 100 %) when the
    run is longer, and the finished run ends at 100 %."""
    import drake_rus.progress as progress

    bars = []
    real = progress.tqdm

    class Spy(real):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            self.totals = [self.total]
            self.postfixes = []
            bars.append(self)

        def update(self, n=1):
            self.totals.append(self.total)
            assert self.n + n <= self.total + 1e-6
            return super().update(n)

        def set_postfix_str(self, s="", refresh=True):
            self.postfixes.append(s)
            return super().set_postfix_str(s, refresh)

    monkeypatch.setattr(progress, "tqdm", Spy)
    monkeypatch.setattr(progress, "stderr_is_terminal", lambda: True)
    sim = _FakeSimulator()
    AdvanceWithProgress(
        sim,
        150.0,
        step=0.5,
        on_step=lambda c: "PIVOT",
        should_stop=lambda c: c.get_time() >= 30.0,
        expected=20.0,
        disable=False,
    )
    bar = bars[0]
    assert bar.totals[0] == pytest.approx(20.0)  # not the 150 s cap
    assert max(bar.totals) < 150.0
    assert bar.n == pytest.approx(bar.total) == pytest.approx(30.0)
    assert "PIVOT" in bar.postfixes
    assert "{postfix}" in bar.bar_format


def test_expected_scan_time_is_a_scan_not_the_cap():
    from drake_rus.scan.run import ExpectedScanTime
    from drake_rus.scenario import LoadScenario

    default = ExpectedScanTime(LoadScenario())
    quick = ExpectedScanTime(LoadScenario(scenario_name="quick"))
    assert 15.0 < quick < default < 40.0  # README: test:0 takes 23.4 simulated s


@pytest.mark.slow
def test_scan_logs_one_line_per_phase_when_stderr_is_not_a_terminal(tmp_path, capsys):
    """A short scan with stderr captured (not a terminal): one 'scan: PHASE at ...' line per
    phase the scan went through, no progress bars (no carriage returns)."""
    out = tmp_path / "scan"
    code = main(
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
            "3",
        ]
    )
    err = capsys.readouterr().err
    summary = json.loads((out / "summary.json").read_text())
    assert code == 1 and summary["status"] == "TIMEOUT", summary["reason"]
    phases = []
    for p in summary["phases"]:
        if not phases or phases[-1] != p["phase"]:
            phases.append(p["phase"])
    lines = [ln for ln in err.splitlines() if ln.startswith("scan: ")]
    assert [ln.split()[1] for ln in lines] == phases[: len(lines)]
    assert len(lines) == len([p for p in phases if p != "TIMEOUT"]) >= 2, err
    assert "\r" not in err
    assert not (out / ".drake-rus.lock").exists()


@pytest.mark.slow
def test_ctrl_c_leaves_a_partial_summary(tmp_path, capsys, monkeypatch):
    """Ctrl-C during the simulation: summary.json with status INTERRUPTED, exit 130, the
    output folder unlocked."""
    import drake_rus.scan.run as run

    real = run.AdvanceWithProgress

    def interrupted_at_1s(simulator, t_final, **kwargs):
        def stop(context):
            if context.get_time() >= 1.0:
                raise KeyboardInterrupt
            return kwargs["should_stop"](context)

        return real(simulator, t_final, **{**kwargs, "should_stop": stop})

    monkeypatch.setattr(run, "AdvanceWithProgress", interrupted_at_1s)
    out = tmp_path / "scan"
    code = main(
        ["scan", "--patient", "test:1", "--scenario", "quick", "--out", str(out), "--no-record"]
    )
    assert code == 130
    text = (out / "summary.json").read_text()
    summary = json.loads(text)  # strict JSON: no NaN
    assert "NaN" not in text
    assert summary["status"] == "INTERRUPTED" and "Ctrl-C" in summary["reason"]
    assert summary["sim_s"] == pytest.approx(1.0, abs=0.3)
    assert sorted(p.name for p in out.iterdir()) == ["summary.json"]


def test_repeated_loads_use_the_patient_cache(monkeypatch):
    """The scan loads its patient through the cache: the second load builds nothing."""
    from drake_rus.anatomy import cohort
    from drake_rus.anatomy.cli import load_patient_for

    calls = []
    real = cohort.generate_patient

    def counting(*a, **k):
        calls.append(a)
        return real(*a, **k)

    monkeypatch.setattr(cohort, "generate_patient", counting)
    first = load_patient_for("seed:424242", voxel_size=0.004, progress=False)
    n = len(calls)
    second = load_patient_for("seed:424242", voxel_size=0.004, progress=False)
    assert len(calls) == n
    assert second.X_PtK.IsExactlyEqualTo(first.X_PtK)
