"""The project's one batch runner: independent runs through Dask, one JSON file per run.

A batch is a list of tasks (dicts, or picklable objects with a ``to_dict()`` such as the
studies' typed tasks) and a function ``run(task) -> dict`` (module-level, so that Dask can
pickle it by reference). Each run's result is written atomically to
``OUT/runs/<id>.json`` as it finishes (a process killed while writing leaves at most a
hidden temporary file, which is never read as a run), ``<id>`` given by the caller's id
function, with the
task's settings key (``task_key``: a hash of everything that changes the run, by default the
whole task, :func:`content_key`). An interrupted batch resumes: running it again skips every
task whose file exists AND holds the same key. A stored run whose key differs (the same run
id made with other settings, or by a version that recorded no key) is never reused: it is
moved aside to ``OUT/runs/superseded/<id>__<key>.json`` and run again; a later batch with
those settings again takes it back from there instead of running it.

Runs go to an existing Dask scheduler (``scheduler="tcp://HOST:PORT"``), to an embedded
LocalCluster of ``workers`` single-threaded worker processes (at most as many as the CPUs
and the memory allow, :func:`bound_workers`; listening on 127.0.0.1 only, no dashboard), or,
with ``workers`` = 0, run one after the other in this process. A tqdm bar counts finished
runs. Ctrl-C (or any exception) ends the embedded cluster's worker processes at once.

This module sits low in the package: it knows nothing of studies, campaigns or scans.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import signal
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
from tqdm import tqdm

from drake_rus.io_utils import write_text_atomic

RUNS_DIR = "runs"
SUPERSEDED_DIR = "superseded"
# Memory one embedded worker process may need (bytes): measured peaks of a study worker are
# 0.71 GB (kinematic, three patients in its cache) and 0.84 GB (one closed-loop scan).
WORKER_MEMORY_BYTES = 1 << 30
# The embedded cluster's addresses: this machine only.
LOCAL_HOST = "127.0.0.1"
# How long (s) worker processes get to end after SIGTERM before SIGKILL, on interruption.
STOP_GRACE_S = 2.0


def runs_dir(out_dir) -> Path:
    """Where the per-run JSON files of ``out_dir`` live."""
    return Path(out_dir) / RUNS_DIR


def result_path(out_dir, run_id: str) -> Path:
    """The result file of run ``run_id`` under ``out_dir``."""
    return runs_dir(out_dir) / f"{run_id}.json"


def task_dict(task) -> dict:
    """A task as a dict: itself, or its ``to_dict()`` (a typed task)."""
    return task.to_dict() if hasattr(task, "to_dict") else task


def json_default(o):
    """``json.dumps`` default: numpy scalars and arrays as plain Python values, typed tasks
    as their ``to_dict()``."""
    if dataclasses.is_dataclass(o) and hasattr(o, "to_dict"):
        return o.to_dict()
    if isinstance(o, np.generic):  # numpy scalars: int, float, bool
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def content_key(obj) -> str:
    """SHA-256 (hex) of ``obj`` as canonical JSON (sorted keys, no spaces): the same for
    equal dicts whatever their key order."""
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"), default=json_default)
    return hashlib.sha256(text.encode()).hexdigest()


def save_result(out_dir, run_id: str, result: dict) -> Path:
    """Writes one run's result (atomically) to its file under ``out_dir``."""
    return write_text_atomic(result_path(out_dir, run_id), json.dumps(result, default=json_default))


def load_results(out_dir, where: Callable[[dict], bool] | None = None) -> list[dict]:
    """All finished run results under ``out_dir/runs`` in file-name order (not the
    superseded ones, nor the temporary file, ``.<id>.json.*.json``, of a write a killed
    process left unfinished); with ``where``, only those for which ``where(result)`` is
    true."""
    rows = []
    for p in sorted(runs_dir(out_dir).glob("*.json")):
        if p.name.startswith("."):  # io_utils.atomic_path's temporary file: not a run
            continue
        r = json.loads(p.read_text())
        if where is None or where(r):
            rows.append(r)
    return rows


def _stored_key(path: Path) -> str | None:
    """The settings key a stored result records (None: none, or unreadable)."""
    try:
        key = json.loads(path.read_text()).get("task_key")
    except (OSError, ValueError, AttributeError):
        return None
    return key if isinstance(key, str) else None


def differences(old: dict | None, new: dict, limit: int = 4) -> str:
    """What differs between two task dicts, e.g. "segmenter oracle -> classical"."""
    if not isinstance(old, dict):
        return "no settings recorded"
    keys = [k for k in sorted(set(old) | set(new)) if old.get(k) != new.get(k)]
    text = ", ".join(f"{k} {old.get(k)!r} -> {new.get(k)!r}" for k in keys[:limit])
    return (
        text + (f" (+{len(keys) - limit} more)" if len(keys) > limit else "")
        or "the resolved inputs (scenario or template file contents)"
    )


def superseded_path(out_dir, run_id: str, key: str | None) -> Path:
    """Where a stored run with settings key ``key`` is kept once other settings replace it."""
    return runs_dir(out_dir) / SUPERSEDED_DIR / f"{run_id}__{(key or 'nokey')[:16]}.json"


def plan(
    tasks: list[dict],
    out_dir,
    task_id: Callable[[dict], str],
    task_key: Callable[[dict], str] = content_key,
) -> dict:
    """Which ``tasks`` a batch under ``out_dir`` reuses and which it runs (nothing is moved):
    {"todo": [task], "reused": int, "superseded": [(run_id, what differs)],
    "restorable": [run_id]} (superseded: a stored run of the same id with other settings;
    restorable: one kept under runs/superseded with exactly these settings)."""
    todo, reused, superseded, restorable = [], 0, [], []
    for t in tasks:
        rid, key = task_id(t), task_key(t)
        path = result_path(out_dir, rid)
        if path.exists():
            if _stored_key(path) == key:
                reused += 1
                continue
            try:
                old = json.loads(path.read_text()).get("task")
            except (OSError, ValueError, AttributeError):
                old = None
            superseded.append((rid, differences(old, task_dict(t))))
        if (
            superseded_path(out_dir, rid, key).exists()
            and _stored_key(superseded_path(out_dir, rid, key)) == key
        ):
            restorable.append(rid)
            continue
        todo.append(t)
    return {"todo": todo, "reused": reused, "superseded": superseded, "restorable": restorable}


def _set_aside(out_dir, tasks, task_id, task_key) -> tuple[list[dict], int, list]:
    """Moves stored runs whose key differs to runs/superseded and takes back superseded
    runs with the tasks' keys; returns (tasks still to run, reused, superseded)."""
    p = plan(tasks, out_dir, task_id, task_key)
    for t in tasks:
        rid, key = task_id(t), task_key(t)
        path = result_path(out_dir, rid)
        if any(rid == s for s, _ in p["superseded"]):
            aside = superseded_path(out_dir, rid, _stored_key(path))
            aside.parent.mkdir(parents=True, exist_ok=True)
            os.replace(path, aside)
        if rid in p["restorable"]:
            os.replace(superseded_path(out_dir, rid, key), path)
    return p["todo"], p["reused"] + len(p["restorable"]), p["superseded"]


# ------------------------------------------------------------------------------- workers
def available_cpus() -> int:
    """CPUs this process may run on (its affinity mask, else the machine's count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def available_memory_bytes() -> int | None:
    """Memory available to new processes (bytes; /proc/meminfo's MemAvailable), or None."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def bound_workers(
    requested: int, memory_per_worker: int | None = WORKER_MEMORY_BYTES, arg: str = "--workers"
) -> tuple[int, str | None]:
    """(workers, note): ``requested`` embedded worker processes, capped at the CPUs this
    process may use and at the available memory over ``memory_per_worker`` (bytes; None:
    memory not considered); ``note`` says why when it capped (one line), else None. 0 (run
    in this process) stays 0; a negative count raises ValueError naming ``arg``."""
    requested = int(requested)
    if requested < 0:
        raise ValueError(f"{arg}: expected 0 or more worker processes, got {requested}")
    if requested == 0:
        return 0, None
    cpus = available_cpus()
    cap, why = cpus, f"{cpus} CPU(s) available"
    memory = available_memory_bytes() if memory_per_worker else None
    if memory is not None:
        fit = max(1, int(memory // memory_per_worker))
        if fit < cap:
            cap, why = (
                fit,
                (
                    f"{memory / 2**30:.1f} GB of memory available, about "
                    f"{memory_per_worker / 2**30:.1f} GB per worker"
                ),
            )
    if requested <= cap:
        return requested, None
    return cap, f"{arg} {requested}: capped at {cap} ({why})"


def _descendants() -> list:
    import psutil  # a dependency of distributed

    try:
        return psutil.Process().children(recursive=True)
    except psutil.Error:
        return []


def _stop(processes) -> None:
    """Ends ``processes`` (psutil.Process objects this batch started): SIGTERM, then SIGKILL
    after ``STOP_GRACE_S``."""
    import psutil

    live = []
    for p in processes:
        try:
            p.terminate()
            live.append(p)
        except psutil.Error:
            pass
    _, alive = psutil.wait_procs(live, timeout=STOP_GRACE_S)
    for p in alive:
        try:
            p.kill()
        except psutil.Error:
            pass
    psutil.wait_procs(alive, timeout=STOP_GRACE_S)


def _started_by_us(before: set) -> list:
    """The processes this batch started (descendants new since ``before``), without
    multiprocessing's resource tracker, which ends with this process by itself."""
    out = []
    for p in _descendants():
        if p.pid in before:
            continue
        try:
            if "resource_tracker" in " ".join(p.cmdline()):
                continue
        except Exception:  # noqa: BLE001 - gone or unreadable: still ours
            pass
        out.append(p)
    return out


def dask_setup(worker) -> None:
    """Worker preload (this module, ``preload=["drake_rus.batch"]``): the worker process
    ignores SIGINT, so a Ctrl-C in the terminal (sent to the whole process group) reaches
    only the batch's own process, which ends the workers itself (no tracebacks from them)."""
    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    except ValueError:  # not the main thread: leave it
        pass


# ------------------------------------------------------------------------------- run
def run_tasks(
    tasks: list[dict],
    run: Callable[[dict], dict],
    out_dir,
    task_id: Callable[[dict], str],
    *,
    workers: int = 2,
    scheduler: str | None = None,
    progress: bool = True,
    desc: str = "runs",
    on_result: Callable[[dict], object] | None = None,
    task_key: Callable[[dict], str] = content_key,
    stamp: Callable[[dict], object] | None = None,
    memory_per_worker: int | None = WORKER_MEMORY_BYTES,
) -> dict:
    """Runs the ``tasks`` without a result of the same settings under ``out_dir/runs`` and
    writes each result (atomically, as ``task_id(task)``.json, with ``task_key(task)`` as
    its ``task_key``) as it finishes.

    ``run``: picklable module-level function task -> JSON-ready dict. ``scheduler``:
    address of an existing Dask scheduler; otherwise an embedded LocalCluster of
    ``workers`` single-threaded processes (:func:`bound_workers`; a note on stderr when
    capped), or, with ``workers`` = 0, this process. ``stamp`` may amend each result in this
    process before it is saved; ``on_result`` is called with each saved result (e.g. to
    print a line). A run that raises (or whose worker died) is reported, not retried, and
    the others go on.

    Returns {done, skipped, failed: [(run_id, error)], superseded: [(run_id, what
    differs)]}.
    """
    runs_dir(out_dir).mkdir(parents=True, exist_ok=True)
    todo, skipped, superseded = _set_aside(out_dir, tasks, task_id, task_key)
    failed = []
    bar = tqdm(
        total=len(tasks),
        initial=skipped,
        desc=desc,
        unit="run",
        disable=not progress,
        dynamic_ncols=True,
    )

    def save(task, result):
        result = dict(result)
        result["task_key"] = task_key(task)
        if stamp is not None:
            stamp(result)
        save_result(out_dir, task_id(task), result)
        bar.update(1)
        if on_result is not None:
            on_result(result)

    def status():
        return {
            "done": len(todo) - len(failed),
            "skipped": skipped,
            "failed": failed,
            "superseded": superseded,
        }

    try:
        if not todo:
            return status()
        if scheduler is None and workers == 0:
            for task in todo:
                try:
                    save(task, run(task))
                except Exception as e:  # noqa: BLE001 - report, keep going
                    failed.append((task_id(task), f"{type(e).__name__}: {e}"))
            return status()
        if scheduler is None:
            workers, note = bound_workers(workers, memory_per_worker)
            if note:
                print(note, file=sys.stderr, flush=True)
        _run_on_dask(todo, run, task_id, save, failed, workers=workers, scheduler=scheduler)
        return status()
    finally:
        bar.close()


def _run_on_dask(todo, run, task_id, save, failed, *, workers: int, scheduler: str | None) -> None:
    from distributed import Client, LocalCluster, as_completed  # heavy, optional

    before = {p.pid for p in _descendants()}
    clusters_before = _clusters()
    cluster = client = None
    clean = False
    try:
        if scheduler is None:
            for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
                os.environ.setdefault(var, "1")
            # No dashboard; the scheduler's own HTTP server (health checks) on a free
            # localhost port (Dask's default, 8787, may be taken by another cluster).
            cluster = LocalCluster(
                n_workers=workers,
                threads_per_worker=1,
                processes=True,
                host=LOCAL_HOST,
                dashboard_address=None,
                worker_dashboard_address=None,
                silence_logs=logging.ERROR,
                scheduler_kwargs={"dashboard": False, "dashboard_address": f"{LOCAL_HOST}:0"},
                preload=["drake_rus.batch"],
            )
            client = Client(cluster)
        else:
            client = Client(scheduler)
        # Submitted in task order: a caller listing tasks patient-major makes a worker tend
        # to get the same patient's runs (its caches).
        futures = {client.submit(run, t, pure=False, key=f"run-{task_id(t)}"): t for t in todo}
        for fut in as_completed(futures):
            task = futures[fut]
            try:
                result = fut.result()
            except Exception as e:  # noqa: BLE001
                failed.append((task_id(task), f"{type(e).__name__}: {e}"))
                continue
            save(task, result)
        clean = True
    finally:
        if not clean:
            _interrupted_cleanup(client, cluster, before, clusters_before, local=scheduler is None)
        else:
            for closer in (client, cluster):
                if closer is not None:
                    closer.close(timeout=10)


def _clusters() -> set:
    """Dask's live cluster objects of this process (to forget the batch's own)."""
    try:
        from distributed.deploy.spec import SpecCluster

        return set(SpecCluster._instances)
    except (ImportError, AttributeError):
        return set()


def _forget_cluster(cluster) -> None:
    try:
        from distributed.deploy.spec import SpecCluster

        SpecCluster._instances.discard(cluster)
    except (ImportError, AttributeError):
        pass


def _interrupted_cleanup(client, cluster, before: set, clusters_before: set, local: bool) -> None:
    """After Ctrl-C (or an error) in a Dask batch: a second Ctrl-C is held off while the
    embedded cluster's worker processes are ended at once (not after their runs) and the
    client and cluster closed, with Dask's shutdown chatter (closed connections) kept off
    the console."""
    try:
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    except ValueError:  # not the main thread
        previous = None
    try:
        for name in ("distributed", "tornado", "asyncio"):
            logging.getLogger(name).setLevel(logging.CRITICAL)
        if local:
            _stop(_started_by_us(before))
        for closer in (client, cluster):
            if closer is None:
                continue
            try:
                closer.close(timeout=0.5)
            except Exception:  # noqa: BLE001 - already torn down
                pass
        # Dask's exit handler would close them again and wait up to 10 s for the (dead)
        # workers: they are closed as far as this batch is concerned.
        for c in _clusters() - clusters_before:
            _forget_cluster(c)
        if local:
            _stop(_started_by_us(before))  # a worker the nanny restarted meanwhile
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
