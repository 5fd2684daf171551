"""Ctrl-C (SIGINT) and SIGTERM at any moment of a command (issue 32).

Real processes (``python -m drake_rus.cli scan``) get a signal during the start-up imports,
once the output folder is locked (patient, start plan, diagram), during the simulation and
while the outputs are written. Each ends with 128 + the signal (130, 143), leaves no lock
and no temporary file, and where the output folder exists an INTERRUPTED summary.json with
the provenance and the reason naming the signal. The machinery itself
(``drake_rus.interrupts``) is tested in this process.
"""

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from drake_rus import interrupts
from drake_rus.io_utils import LOCK_NAME, atomic_path, staged_files, write_text_atomic

pytestmark = pytest.mark.wallclock

REPO = Path(__file__).resolve().parents[1]
linux_only = pytest.mark.skipif(
    not Path("/proc/self/status").exists(),
    reason="needs /proc to see when the handlers are installed",
)


# ------------------------------------------------------------------------ in this process
def test_a_signal_raises_interrupted_and_names_itself():
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    with interrupts.handling():
        with pytest.raises(interrupts.Interrupted) as caught:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1.0)  # the handler runs at the next bytecode
        assert caught.value.signum == signal.SIGTERM
        assert interrupts.exit_status(caught.value) == 143
        assert interrupts.signal_text(signal.SIGINT) == "SIGINT (Ctrl-C)"
    # Outside the block the previous handlers are back and nothing is pending.
    assert interrupts.pending() is None
    assert {s: signal.getsignal(s) for s in before} == before


def test_a_swallowed_signal_comes_back_at_the_next_check():
    with interrupts.handling():
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1.0)
        except KeyboardInterrupt:
            pass  # a library that swallows it
        with pytest.raises(interrupts.Interrupted):
            interrupts.check()
        assert interrupts.exit_status() == 130


def test_deferred_blocks_hold_the_signal_until_they_end():
    done = []
    with interrupts.handling():
        with pytest.raises(interrupts.Interrupted):
            with interrupts.deferred():
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.2)
                done.append("the whole block ran")
        assert done == ["the whole block ran"]
        with interrupts.deferred(reraise=False):  # cleanup: recorded, not raised
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.2)


def test_an_import_is_a_checkpoint_while_importing(tmp_path, monkeypatch):
    """During the start-up imports a signal is raised at the next import statement, even
    after a library swallowed it once."""
    (tmp_path / "drake_rus_test_mod_a.py").write_text("X = 1\n")
    (tmp_path / "drake_rus_test_mod_b.py").write_text("Y = 2\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with interrupts.handling():
        with pytest.raises(interrupts.Interrupted):
            with interrupts.importing():
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.2)  # the handler only records it here
                try:
                    import drake_rus_test_mod_a  # noqa: F401
                except BaseException:
                    pass  # like trimesh's guarded optional imports
                import drake_rus_test_mod_b  # noqa: F401
    assert "drake_rus_test_mod_b" not in sys.modules


def test_a_signal_while_writing_leaves_no_temporary_file(tmp_path):
    target = tmp_path / "plot.png"
    with interrupts.handling():
        with pytest.raises(interrupts.Interrupted):
            with atomic_path(target) as tmp:
                tmp.write_bytes(b"half a picture")
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(1.0)
    assert list(tmp_path.iterdir()) == []
    write_text_atomic(tmp_path / "a.json", "{}")
    assert [p.name for p in tmp_path.iterdir()] == ["a.json"]


# ------------------------------------------------------------------------ real processes
@pytest.fixture(scope="module")
def cached_patient():
    """test:0 with its label volume in the session's patient cache, so that the processes
    below reach the simulation in a few seconds."""
    from drake_rus.anatomy.cli import load_patient_for

    patient = load_patient_for("test:0", progress=False)
    assert patient.labels is not None
    return "test:0"


class Scan:
    """``python -m drake_rus.cli scan`` in a child process, its stderr lines collected."""

    def __init__(self, out: Path, *extra: str):
        env = dict(
            os.environ,
            PYTHONUNBUFFERED="1",
            PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]),
        )
        self.out = out
        self.process = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "drake_rus.cli",
                "scan",
                "--scenario",
                "quick",
                "--patient",
                "test:0",
                "--no-record",
                "--out",
                str(out),
                *extra,
            ],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=REPO,
        )
        self.err: list[str] = []
        self.out_lines: list[str] = []
        self._readers = [
            threading.Thread(target=self._read, args=(s, lines), daemon=True)
            for s, lines in ((self.process.stderr, self.err), (self.process.stdout, self.out_lines))
        ]
        for r in self._readers:
            r.start()

    @staticmethod
    def _read(stream, lines):
        for line in stream:
            lines.append(line.rstrip("\n"))

    def wait_until(self, ready, what: str, timeout: float = 240.0) -> None:
        deadline = time.monotonic() + timeout
        while not ready():
            if self.process.poll() is not None:
                raise AssertionError(
                    f"the scan ended ({self.process.returncode}) before "
                    f"{what}:\n" + "\n".join(self.err[-20:])
                )
            if time.monotonic() > deadline:
                self.process.kill()
                raise AssertionError(f"no {what} within {timeout} s")
            time.sleep(0.005)

    def handlers_installed(self) -> bool:
        """True once the process catches SIGTERM (drake-rus installed its handlers)."""
        try:
            status = Path(f"/proc/{self.process.pid}/status").read_text()
        except OSError:
            return False
        caught = int(
            next(ln.split()[1] for ln in status.splitlines() if ln.startswith("SigCgt:")), 16
        )
        return bool(caught & (1 << (signal.SIGTERM - 1)))

    def stop_with(self, signum: int) -> int:
        self.process.send_signal(signum)
        try:
            code = self.process.wait(120)
        except subprocess.TimeoutExpired:
            self.process.kill()
            raise
        for r in self._readers:
            r.join(5)
        return code


def _check_left_behind(scan: Scan, signum: int, folder_expected: bool | None) -> dict | None:
    """The exit status, no lock or temporary file; the INTERRUPTED summary if the folder
    exists (returned)."""
    out = scan.out
    if folder_expected is not None:
        assert out.exists() == folder_expected, (folder_expected, scan.err[-5:])
    if not out.exists():
        assert scan.err and scan.err[-1].endswith(
            f"interrupted by {interrupts.signal_text(signum)}"
        ), scan.err
        return None
    hidden = [p.name for p in out.iterdir() if p.name.startswith(".") or p.suffix == ".tmp"]
    assert hidden == [], f"left behind: {hidden}"
    assert not (out / LOCK_NAME).exists()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "INTERRUPTED", summary["reason"]
    assert f"interrupted by {interrupts.signal_text(signum)}" in summary["reason"]
    prov = summary["provenance"]
    assert prov["command"] == "scan" and prov["seeds"]["patient"] == "test:0"
    assert "random_seed" in prov["seeds"] and prov["scenario_yaml"]
    # (a signal between a print's text and its newline joins the two lines)
    assert any("INTERRUPTED: interrupted by" in line for line in scan.out_lines), scan.out_lines
    return summary


@linux_only
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_signal_during_the_start_up_imports(tmp_path, signum):
    """The first moment drake-rus catches signals (the pydrake import follows): the command
    ends with 130/143 and one line, creates no output folder, runs no scan."""
    scan = Scan(tmp_path / "scan")
    scan.wait_until(scan.handlers_installed, "signal handlers")
    assert scan.stop_with(signum) == 128 + signum
    _check_left_behind(scan, signum, folder_expected=False)
    assert not any("Traceback" in line for line in scan.err), scan.err


@linux_only
def test_sigterm_once_the_output_folder_is_locked(tmp_path, cached_patient):
    """SIGTERM while the patient loads and the diagram is built (the lock is taken): an
    INTERRUPTED summary saying no scan ran, the lock gone."""
    scan = Scan(tmp_path / "scan")
    scan.wait_until(lambda: (scan.out / LOCK_NAME).exists(), "lock in --out")
    assert scan.stop_with(signal.SIGTERM) == 143
    summary = _check_left_behind(scan, signal.SIGTERM, folder_expected=True)
    assert summary["stage"].startswith("start-up") and "no scan ran" in summary["reason"]


@linux_only
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_signal_during_the_simulation(tmp_path, cached_patient, signum):
    """A signal during EXPLORE: the partial summary of the scan so far (its phases, the
    simulated time reached), only summary.json in --out."""
    scan = Scan(tmp_path / "scan")
    scan.wait_until(lambda: any(ln.startswith("scan: EXPLORE") for ln in scan.err), "EXPLORE phase")
    assert scan.stop_with(signum) == 128 + signum
    summary = _check_left_behind(scan, signum, folder_expected=True)
    assert summary["sim_s"] >= 1.0 and summary["phases"][0]["phase"] == "APPROACH"
    assert sorted(p.name for p in scan.out.iterdir()) == ["summary.json"]


@linux_only
def test_sigterm_while_the_outputs_are_written(tmp_path, cached_patient):
    """SIGTERM once summary.json is written and the clouds and plots follow (a short
    TIMEOUT scan): no half-written picture, the summary turned INTERRUPTED keeping the
    scan's own status and figures."""
    scan = Scan(tmp_path / "scan", "--max-sim-time", "2")
    scan.wait_until(lambda: (scan.out / "summary.json").exists(), "summary.json")
    assert scan.stop_with(signal.SIGTERM) == 143
    summary = _check_left_behind(scan, signal.SIGTERM, folder_expected=True)
    assert summary["scan_status"] == "TIMEOUT" and "while writing the outputs" in summary["reason"]
    assert summary["phases"] and summary["sim_s"] == pytest.approx(2.0, abs=0.3)


def test_sigterm_during_the_demo_leaves_an_interrupted_summary(tmp_path, capsys, monkeypatch):
    """The demo (no scan): SIGTERM while it presses -> 143, an INTERRUPTED summary with the
    provenance, no recording or plot half-written, no lock."""
    import drake_rus.demo as demo
    from drake_rus.cli import main

    def pressed_then_stopped(simulator, t_final, **kwargs):
        simulator.AdvanceTo(0.02)
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5.0)  # the handler raises here
        raise AssertionError("the signal did not stop the demo")

    monkeypatch.setattr(demo, "AdvanceWithProgress", pressed_then_stopped)
    out = tmp_path / "demo"
    assert main(["demo", "--duration", "0.2", "--out", str(out)]) == 143
    assert sorted(p.name for p in out.iterdir()) == ["summary.json"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "INTERRUPTED" and "interrupted by SIGTERM" in summary["reason"]
    assert summary["provenance"]["command"] == "demo"
    assert summary["provenance"]["arguments"]["duration"] == 0.2
    assert "INTERRUPTED: interrupted by SIGTERM" in capsys.readouterr().out


def test_a_signal_caught_by_the_hardware_session_keeps_its_number():
    """The hardware session raises KeyboardInterrupt('signal 15') from its own handler: the
    command still reports SIGTERM (143), and outside drake-rus's handling nothing sticks."""
    e = KeyboardInterrupt(f"signal {int(signal.SIGTERM)}")
    assert interrupts.signal_of(e) == signal.SIGTERM and interrupts.exit_status(e) == 143
    assert interrupts.exit_status(KeyboardInterrupt()) == 130
    interrupts.note(signal.SIGTERM)  # no handling(): not recorded
    assert interrupts.pending() is None
    interrupts.check()
    with interrupts.handling():
        interrupts.note(signal.SIGTERM)
        assert interrupts.exit_status() == 143
        with pytest.raises(interrupts.Interrupted):
            interrupts.check()
    assert interrupts.pending() is None


@linux_only
def test_sigterm_while_the_lock_is_taken(tmp_path, cached_patient):
    """SIGTERM that arrives while the output folder's lock is being taken (the process
    signals itself at that moment, which a loaded machine once hit by chance): it waits
    until the run can write its INTERRUPTED summary; the folder is not removed."""
    out = tmp_path / "scan"
    code = (
        "import os, signal, sys\n"
        "import drake_rus.io_utils as io\n"
        "take = io._take_lock\n"
        "def signalled(*a, **k):\n"
        "    take(*a, **k)\n"
        "    os.kill(os.getpid(), signal.SIGTERM)\n"
        "io._take_lock = signalled\n"
        "from drake_rus.cli import main\n"
        "sys.exit(main(['scan', '--scenario', 'quick', '--patient', 'test:0', '--no-record',"
        f" '--out', {str(out)!r}]))\n"
    )
    env = dict(
        os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])
    )
    done = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 143, done.stderr[-2000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "INTERRUPTED" and "no scan ran" in summary["reason"]
    assert sorted(p.name for p in out.iterdir()) == ["summary.json"]


def test_staged_files_appear_together_or_not_at_all(tmp_path):
    """A model and its card: both renamed into place on success; on an error the folder
    keeps its old files untouched, and a folder the call made is removed."""
    out = tmp_path / "models"
    with staged_files(out, ".m-") as stage:
        (stage / "m.onnx").write_text("new model")
        (stage / "m.json").write_text("new card")
    assert sorted(p.name for p in out.iterdir()) == ["m.json", "m.onnx"]
    with pytest.raises(RuntimeError):
        with staged_files(out, ".m-") as stage:
            (stage / "m.onnx").write_text("half")
            raise RuntimeError("the check failed")
    assert sorted(p.name for p in out.iterdir()) == ["m.json", "m.onnx"]
    assert (out / "m.onnx").read_text() == "new model"
    fresh = tmp_path / "a" / "b"
    with pytest.raises(RuntimeError):
        with staged_files(fresh, ".m-") as stage:
            raise RuntimeError("boom")
    assert not fresh.exists()
