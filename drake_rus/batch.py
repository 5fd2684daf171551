"""The project's one batch runner: independent runs through Dask, one JSON file per run.

A batch is a list of task dicts and a function ``run(task) -> dict`` (module-level, so
that Dask can pickle it by reference). Each run's result is written atomically to
``OUT/runs/<id>.json`` as it finishes, ``<id>`` given by the caller's id function, so an
interrupted batch resumes: running it again skips every task whose file exists.

Runs go to an existing Dask scheduler (``scheduler="tcp://HOST:PORT"``), to an embedded
LocalCluster of ``workers`` single-threaded worker processes, or, with ``workers`` = 0,
run one after the other in this process. A tqdm bar counts finished runs.

This module sits low in the package: it knows nothing of studies, campaigns or scans.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
from tqdm import tqdm

from drake_rus.io_utils import write_text_atomic

RUNS_DIR = "runs"


def runs_dir(out_dir) -> Path:
    """Where the per-run JSON files of ``out_dir`` live."""
    return Path(out_dir) / RUNS_DIR


def result_path(out_dir, run_id: str) -> Path:
    """The result file of run ``run_id`` under ``out_dir``."""
    return runs_dir(out_dir) / f"{run_id}.json"


def json_default(o):
    """``json.dumps`` default: numpy scalars and arrays as plain Python values."""
    if isinstance(o, np.generic):      # numpy scalars: int, float, bool
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def save_result(out_dir, run_id: str, result: dict) -> Path:
    """Writes one run's result (atomically) to its file under ``out_dir``."""
    return write_text_atomic(result_path(out_dir, run_id),
                             json.dumps(result, default=json_default))


def load_results(out_dir, where: Callable[[dict], bool] | None = None) -> list[dict]:
    """All finished run results under ``out_dir/runs`` in file-name order; with ``where``,
    only those for which ``where(result)`` is true."""
    rows = []
    for p in sorted(runs_dir(out_dir).glob("*.json")):
        r = json.loads(p.read_text())
        if where is None or where(r):
            rows.append(r)
    return rows


def run_tasks(tasks: list[dict], run: Callable[[dict], dict], out_dir,
              task_id: Callable[[dict], str], *, workers: int = 2,
              scheduler: str | None = None, progress: bool = True, desc: str = "runs",
              on_result: Callable[[dict], object] | None = None) -> dict:
    """Runs the ``tasks`` without a result under ``out_dir/runs`` and writes each result
    (atomically, as ``task_id(task)``.json) as it finishes.

    ``run``: picklable module-level function task -> JSON-ready dict. ``scheduler``:
    address of an existing Dask scheduler; otherwise an embedded LocalCluster of
    ``workers`` single-threaded processes, or, with ``workers`` = 0, this process.
    ``on_result`` is called with each saved result (e.g. to print a line). A run that
    raises (or whose worker died) is reported, not retried, and the others go on.

    Returns {done, skipped, failed: [(run_id, error)]}.
    """
    todo = [t for t in tasks if not result_path(out_dir, task_id(t)).exists()]
    skipped = len(tasks) - len(todo)
    failed = []
    bar = tqdm(total=len(tasks), initial=skipped, desc=desc, unit="run", disable=not progress,
               dynamic_ncols=True)

    def save(task, result):
        save_result(out_dir, task_id(task), result)
        bar.update(1)
        if on_result is not None:
            on_result(result)

    try:
        if not todo:
            return {"done": 0, "skipped": skipped, "failed": failed}
        if scheduler is None and workers == 0:
            for task in todo:
                try:
                    save(task, run(task))
                except Exception as e:    # noqa: BLE001 - report, keep going
                    failed.append((task_id(task), f"{type(e).__name__}: {e}"))
            return {"done": len(todo) - len(failed), "skipped": skipped, "failed": failed}
        from distributed import Client, LocalCluster, as_completed  # heavy, optional
        cluster = None
        if scheduler is None:
            if workers < 0:
                raise ValueError(f"--workers: expected 0 or more, got {workers}")
            for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
                os.environ.setdefault(var, "1")
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                   dashboard_address=":0", silence_logs=40)
            client = Client(cluster)
        else:
            client = Client(scheduler)
        try:
            # Submitted in task order: a caller listing tasks patient-major makes a worker
            # tend to get the same patient's runs (its caches).
            futures = {client.submit(run, t, pure=False, key=f"run-{task_id(t)}"): t
                       for t in todo}
            for fut in as_completed(futures):
                task = futures[fut]
                try:
                    save(task, fut.result())
                except Exception as e:    # noqa: BLE001
                    failed.append((task_id(task), f"{type(e).__name__}: {e}"))
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
        return {"done": len(todo) - len(failed), "skipped": skipped, "failed": failed}
    finally:
        bar.close()
