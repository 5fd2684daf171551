"""Bounded study workers (issue 32): --workers capped at the CPUs and memory available, the
embedded Dask cluster on 127.0.0.1 without a dashboard, and Ctrl-C ending the whole study,
workers included, with exit status 130."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from drake_rus import batch

pytestmark = pytest.mark.wallclock

ROOT = Path(__file__).resolve().parent.parent


def test_bound_workers_caps_at_cpus_and_memory(monkeypatch):
    monkeypatch.setattr(batch, "available_cpus", lambda: 4)
    monkeypatch.setattr(batch, "available_memory_bytes", lambda: 64 << 30)
    assert batch.bound_workers(3) == (3, None)
    n, note = batch.bound_workers(100000)
    assert n == 4 and note == "--workers 100000: capped at 4 (4 CPU(s) available)"
    monkeypatch.setattr(batch, "available_memory_bytes", lambda: int(2.5 * (1 << 30)))
    n, note = batch.bound_workers(4)
    assert n == 2 and "capped at 2" in note and "2.5 GB of memory available" in note
    assert batch.bound_workers(0) == (0, None)
    monkeypatch.setattr(batch, "available_memory_bytes", lambda: 1 << 20)
    assert batch.bound_workers(4)[0] == 1  # at least one worker
    with pytest.raises(ValueError, match="--workers: expected 0 or more"):
        batch.bound_workers(-1)
    assert batch.available_cpus() >= 1


def _listening(procs):
    out = []
    for p in procs:
        try:
            conns = p.net_connections(kind="inet")
        except (psutil.Error, AttributeError):
            continue
        out += [c.laddr for c in conns if c.status == psutil.CONN_LISTEN]
    return out


def test_local_cluster_listens_on_localhost_only(tmp_path):
    seen = []

    def look(result):
        me = psutil.Process()
        seen.extend(_listening([me] + me.children(recursive=True)))

    tasks = [{"id": "a"}, {"id": "b"}]
    status = batch.run_tasks(
        tasks, dict, tmp_path, lambda t: t["id"], workers=1, progress=False, on_result=look
    )
    assert status["done"] == 2 and seen
    assert {a.ip for a in seen} == {"127.0.0.1"}, seen
    assert len(batch.load_results(tmp_path)) == 2


# A stand-in for a study run, importable by the Dask workers (a module on PYTHONPATH): the
# first run returns at once, the others take a minute.
SLOW_RUN = """
import time

def run(task):
    if not (task.patient == "test:0" and task.er == 1.0):
        time.sleep(60)
    return {"run_id": f"{task.patient}-{task.er}", "task": task.to_dict(),
            "patient": task.patient, "er": task.er, "e_trans_mm": 1.0,
            "e_rot_x_deg": 1.0}
"""
# The study command with that stand-in (imports under the main guard: the workers import
# this module as their __mp_main__ and need none of it).
STUDY = """
import sys

if __name__ == "__main__":
    import slow_run
    from drake_rus.experiments import cli
    cli.run_task = slow_run.run
    from drake_rus.cli import main
    sys.exit(main(sys.argv[1:]))
"""


def test_ctrl_c_ends_the_study_and_its_workers(tmp_path):
    """The observed case: --workers 100000 (was: 1.5 GB, no worker, alive 30 s after
    Ctrl-C). Now capped with a note; Ctrl-C (SIGINT to the process group, as a terminal
    sends it) while the workers run ends the study with 130 at once and leaves no process
    behind."""
    (tmp_path / "slow_run.py").write_text(SLOW_RUN)
    (tmp_path / "study.py").write_text(STUDY)
    out = tmp_path / "study"
    env = dict(
        os.environ,
        PYTHONPATH=os.pathsep.join([str(tmp_path), str(ROOT), os.environ.get("PYTHONPATH", "")]),
    )
    proc = subprocess.Popen(
        [
            sys.executable,
            str(tmp_path / "study.py"),
            "study",
            "er-sweep",
            "--patients",
            "test:0-2",
            "--ers",
            "0.6,1",
            "--workers",
            "100000",
            "--out",
            str(out),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        cwd=str(tmp_path),
        start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    err_lines, rest = [], ""
    try:
        # Wait until the first run has finished: the workers are up and busy.
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            line = proc.stderr.readline()
            if not line:
                break
            err_lines.append(line)
            if "er-sweep: run 1/" in line:
                break
        assert any("run 1/" in x for x in err_lines), "".join(err_lines)
        workers = psutil.Process(proc.pid).children(recursive=True)
        assert workers
        os.killpg(proc.pid, signal.SIGINT)
        _, rest = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    stderr = "".join(err_lines) + (rest or "")
    assert proc.returncode == 130, stderr
    assert "drake-rus study: interrupted" in stderr
    cap = [x for x in err_lines if x.startswith("--workers 100000: capped at")]
    assert len(cap) == 1 and ("CPU" in cap[0] or "memory" in cap[0]), stderr
    time.sleep(0.5)
    alive = [p.pid for p in workers if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
    assert alive == [], alive
    assert "Traceback" not in stderr, stderr
    runs = sorted((out / "runs").glob("*.json"))
    assert [p.name for p in runs] == ["er-sweep__test-0__erk100.json"]
    assert json.loads(runs[0].read_text())["e_trans_mm"] == 1.0  # a whole file
