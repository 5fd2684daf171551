"""Perception beside the control loop: where the scan's slow steps run and when their
results count.

The scan's perception steps (segmenting a frame, fitting the kidney's length, registering
the explored cloud, the tracking fits) are plain functions (``imaging/``,
``localization/``). The thin systems that host them hand each call to an *executor* and
take the result when it is ready, so the control loop never waits for them:

- :meth:`Executor.submit` ``(lane, fn, *args, t=now, kind=...)`` -> a :class:`Ticket`
  (immutable: it may sit in a Drake Context's abstract state);
- :meth:`Executor.poll` ``(ticket, t)`` -> :class:`Done` (the value, when it was asked for
  and how long it took) or None while it is not ready; an exception raised by ``fn`` is
  raised here, where the result would have been used.

Two executors, chosen by the run (``perception.execution``; ``auto``: worker when the run
is paced at real time, inline otherwise):

- :class:`InlineExecutor` (simulation, tests, studies): ``fn`` runs at once in the caller,
  and its result is *ready* ``latency`` s of diagram time after it was asked for (a
  deterministic latency model per lane; 0 = at once). Reproducible to the bit.
- :class:`WorkerExecutor` (live runs): each lane is a worker *process* (``spawn``, at a
  lower priority than the loop) fed through queues by this process's feeder threads, its
  results collected by a receiver thread; ``poll`` only looks them up. A process, not a
  thread: the Python ICP holds the interpreter lock between its numpy calls, and a worker
  thread holding it makes every one of the control loop's Python callbacks wait up to the
  switch interval (5 ms); a process below the loop's priority takes only the CPU the loop
  leaves. Functions and arguments must pickle (module-level functions); large constant
  objects are installed once per lane with :meth:`share` and passed as the returned
  :class:`Shared` handle. A result that does not pickle is the job's error
  (:class:`WorkerError`, raised by ``poll``), not a job that never ends.

Lanes: ``frames`` (segmentation, at the imaging frame rate) and ``fits`` (registration,
length, adaptive and tracking fits), so a 400 ms fit never delays a frame.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import multiprocessing
import os
import pickle
import queue
import signal
import threading
import time
import traceback
from typing import Callable

__all__ = [
    "LANES",
    "Ticket",
    "Done",
    "Shared",
    "JobRecord",
    "Executor",
    "InlineExecutor",
    "WorkerExecutor",
    "WorkerError",
    "MakeExecutor",
    "execution_mode",
]

LANES = ("frames", "fits")


class WorkerError(RuntimeError):
    """A perception worker process failed (died, or could not start)."""


@dataclasses.dataclass(frozen=True)
class Ticket:
    """A submitted call: its lane, kind (what it computes, for the records), id and the
    diagram time ``t_request`` (s) it was asked for. Inline tickets carry their result."""

    lane: str
    kind: str
    job_id: int
    t_request: float
    # Inline only: (value, exception, compute s) and the diagram time it is ready.
    _inline: tuple | None = dataclasses.field(default=None, repr=False, compare=False)
    ready_at: float = math.nan

    def __deepcopy__(self, memo):  # immutable: Drake's state clones may share it
        return self

    def __copy__(self):
        return self


@dataclasses.dataclass(frozen=True)
class Done:
    """A result: ``value``, the diagram times (s) it was asked for (``t_request``) and
    taken (``t_applied``), and the wall time (s) its computation took (``compute_s``)."""

    value: object
    t_request: float
    t_applied: float
    compute_s: float


@dataclasses.dataclass(frozen=True)
class Shared:
    """A constant object installed once in a worker lane (:meth:`Executor.share`)."""

    key: int
    lane: str


@dataclasses.dataclass(frozen=True)
class JobRecord:
    """One result taken: kind, lane, diagram times asked and taken (s), compute time (s)
    and the wall time (s) from submit to the result being taken."""

    kind: str
    lane: str
    t_request: float
    t_applied: float
    compute_s: float
    wall_s: float


class Executor:
    """The interface (see the module doc). ``mode``: "inline" or "worker"."""

    mode = "inline"

    def __init__(self):
        self.records: list[JobRecord] = []
        self._ids = itertools.count()

    def share(self, lane: str, factory: Callable, *args):
        raise NotImplementedError

    def submit(self, lane: str, fn: Callable, *args, t: float, kind: str = "") -> Ticket:
        raise NotImplementedError

    def poll(self, ticket: Ticket, t: float) -> Done | None:
        raise NotImplementedError

    def warm_up(self, timeout: float = 120.0) -> None:
        """Blocks until every lane can take work (workers started, shared objects built)."""

    def close(self) -> None:
        pass

    def statistics(self) -> dict:
        """Per kind: count, compute time and latency (diagram s from asked to taken), p50
        and max (ms)."""
        out = {}
        kinds = sorted({r.kind for r in self.records})
        for kind in kinds:
            rs = [r for r in self.records if r.kind == kind]
            compute = sorted(r.compute_s for r in rs)
            latency = sorted(r.t_applied - r.t_request for r in rs)
            out[kind] = {
                "count": len(rs),
                "lane": rs[0].lane,
                "compute_ms_p50": 1e3 * compute[len(compute) // 2],
                "compute_ms_max": 1e3 * compute[-1],
                "latency_ms_p50": 1e3 * latency[len(latency) // 2],
                "latency_ms_max": 1e3 * latency[-1],
            }
        return out

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def _check_lane(self, lane: str) -> None:
        if lane not in LANES:
            raise ValueError(f"executor: unknown lane {lane!r}; expected one of {LANES}")


class InlineExecutor(Executor):
    """Runs every call at once, here; its result is ready ``latency[lane]`` s (diagram time)
    after it was asked for (a float: the same for every lane)."""

    mode = "inline"

    def __init__(self, latency: dict | float = 0.0):
        super().__init__()
        if not isinstance(latency, dict):
            latency = {lane: float(latency) for lane in LANES}
        for lane, value in latency.items():
            self._check_lane(lane)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"executor: latency of lane {lane!r} must be >= 0 s, got {value}")
        self.latency = {lane: float(latency.get(lane, 0.0)) for lane in LANES}

    def share(self, lane: str, factory: Callable, *args):
        self._check_lane(lane)
        return factory(*args)

    def submit(self, lane: str, fn: Callable, *args, t: float, kind: str = "") -> Ticket:
        self._check_lane(lane)
        start = time.perf_counter()
        value, error = None, None
        try:
            value = fn(*args)
        except Exception as e:  # raised where the result is used (poll)
            error = e
        compute = time.perf_counter() - start
        return Ticket(
            lane,
            kind or getattr(fn, "__name__", "job"),
            next(self._ids),
            float(t),
            (value, error, compute),
            float(t) + self.latency[lane],
        )

    def poll(self, ticket: Ticket, t: float) -> Done | None:
        if t < ticket.ready_at - 1e-9:
            return None
        value, error, compute = ticket._inline
        if error is not None:
            raise error
        self.records.append(
            JobRecord(ticket.kind, ticket.lane, ticket.t_request, float(t), compute, compute)
        )
        return Done(value, ticket.t_request, float(t), compute)


def _resolve(args, shared):
    out = []
    for a in args:
        if isinstance(a, Shared):
            value = shared[a.key]
            if isinstance(value, _FailedShare):
                raise value.error
            out.append(value)
        else:
            out.append(a)
    return out


class _FailedShare:
    def __init__(self, error):
        self.error = error


def _portable(error: BaseException) -> BaseException:
    """``error`` if it pickles, else a RuntimeError with its text and traceback."""
    import pickle

    try:
        pickle.loads(pickle.dumps(error))
        return error
    except Exception:
        text = "".join(traceback.format_exception(type(error), error, error.__traceback__))
        return RuntimeError(f"{type(error).__name__}: {error}\n{text}")


def _message(kind: str, key: int, fn: Callable, args: tuple) -> bytes:
    """A share or a job for a worker, pickled now, in the caller's thread. A queue pickles
    what it is given later, in its feeder thread: an argument the caller changes meanwhile
    (a ProbeGeometry filling its cached properties, a growing buffer) would then be sent as
    it is at that later moment, or fail to pickle ("dictionary changed size during
    iteration") and be dropped without a word, so a job would find no shared object."""
    try:
        return pickle.dumps((kind, key, fn, args), protocol=pickle.HIGHEST_PROTOCOL)
    except Exception as e:
        name = getattr(fn, "__name__", repr(fn))
        raise WorkerError(f"a perception {kind} ({name}) cannot be sent to its worker: {e}") from e


def _worker_main(jobs, results, lane: str, nice: int, parent: int) -> None:
    """A lane's worker process: installs shared objects, runs jobs, sends results; ends on
    None or when its parent is gone. Ctrl-C is its parent's to handle (which then closes
    it), not a traceback here."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if nice:
        try:
            os.nice(int(nice))
        except OSError:
            pass
    shared: dict = {}
    while True:
        try:
            msg = jobs.get(timeout=0.5)
        except queue.Empty:
            if os.getppid() != parent:
                return
            continue
        if msg is None:
            return
        if isinstance(msg, bytes):  # a share or a job, pickled by the caller (_message)
            msg = pickle.loads(msg)
        if msg[0] == "share":
            _, key, factory, args = msg
            try:
                shared[key] = factory(*args)
            except Exception as e:
                shared[key] = _FailedShare(_portable(e))
            continue
        if msg[0] == "ping":
            results.put(("pong", msg[1], None, 0.0, None))
            continue
        _, job_id, fn, args = msg
        start = time.perf_counter()
        try:
            value, error = fn(*_resolve(args, shared)), None
        except Exception as e:
            value, error = None, _portable(e)
        results.put(_done(job_id, value, time.perf_counter() - start, error, fn))


def _done(job_id: int, value, compute: float, error, fn: Callable) -> bytes:
    """A job's result for the caller, pickled now, in the worker (see :func:`_message`: the
    queue's feeder thread would drop a value that does not pickle without a word, and the
    job would never be done). Such a value is the job's error instead, raised by ``poll``."""
    try:
        return pickle.dumps(
            ("done", job_id, value, compute, error), protocol=pickle.HIGHEST_PROTOCOL
        )
    except Exception as e:
        name = getattr(fn, "__name__", repr(fn))
        error = WorkerError(
            f"the result of a perception job ({name}) cannot be sent back from its worker: "
            f"{type(e).__name__}: {e}"
        )
        return pickle.dumps(("done", job_id, None, compute, error))


class _Lane:
    """One worker process with its job and result queues and a receiver thread."""

    def __init__(self, name: str, nice: int):
        ctx = multiprocessing.get_context("spawn")
        self.name = name
        self.jobs = ctx.Queue()
        self.results = ctx.Queue()
        self.done: dict[int, tuple] = {}
        self.lock = threading.Lock()
        self.pongs: set = set()
        self.failure: str | None = None
        self.process = ctx.Process(
            target=_worker_main,
            args=(self.jobs, self.results, name, nice, os.getpid()),
            name=f"drake_rus_perception_{name}",
            daemon=True,
        )
        self.process.start()
        self._stop = threading.Event()
        self.thread = threading.Thread(
            target=self._receive, name=f"drake_rus_perception_{name}_rx", daemon=True
        )
        self.thread.start()

    def _receive(self):
        while not self._stop.is_set():
            try:
                msg = self.results.get(timeout=0.2)
                if isinstance(msg, bytes):  # a job's result, pickled by the worker (_done)
                    msg = pickle.loads(msg)
                kind, job_id, value, compute, error = msg
            except queue.Empty:
                if not self.process.is_alive():
                    self.failure = (
                        f"the perception worker '{self.name}' ended (exit code "
                        f"{self.process.exitcode})"
                    )
                    return
                continue
            except (EOFError, OSError):
                return
            with self.lock:
                if kind == "pong":
                    self.pongs.add(job_id)
                else:
                    self.done[job_id] = (value, error, compute, time.perf_counter())

    def close(self, timeout: float = 5.0):
        self._stop.set()
        try:
            self.jobs.put(None)
        except (OSError, ValueError):
            pass
        self.process.join(timeout)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join(2.0)
        self.thread.join(1.0)
        for q in (self.jobs, self.results):
            q.close()
            q.cancel_join_thread()


class WorkerExecutor(Executor):
    """Runs calls in one worker process per lane (see the module doc), at ``nice`` (added
    to this process's; the control loop keeps the CPU it needs): one value, or one per lane
    (a dict)."""

    mode = "worker"

    def __init__(self, nice: int | dict = 10, lanes=LANES):
        super().__init__()
        if not isinstance(nice, dict):
            nice = {lane: int(nice) for lane in lanes}
        self.nice = {lane: int(nice.get(lane, 0)) for lane in lanes}
        self._lanes = {name: _Lane(name, self.nice[name]) for name in lanes}
        self._submitted: dict[int, float] = {}
        self._keys = itertools.count()
        self._closed = False

    def _lane(self, name: str) -> _Lane:
        self._check_lane(name)
        lane = self._lanes[name]
        if lane.failure is not None:
            raise WorkerError(lane.failure)
        return lane

    def share(self, lane: str, factory: Callable, *args) -> Shared:
        handle = Shared(next(self._keys), lane)
        self._lane(lane).jobs.put(_message("share", handle.key, factory, args))
        return handle

    def submit(self, lane: str, fn: Callable, *args, t: float, kind: str = "") -> Ticket:
        job_id = next(self._ids)
        self._submitted[job_id] = time.perf_counter()
        self._lane(lane).jobs.put(_message("job", job_id, fn, args))
        return Ticket(lane, kind or getattr(fn, "__name__", "job"), job_id, float(t))

    def poll(self, ticket: Ticket, t: float) -> Done | None:
        lane = self._lane(ticket.lane)
        with lane.lock:
            got = lane.done.pop(ticket.job_id, None)
        if got is None:
            return None
        value, error, compute, arrived = got
        if error is not None:
            raise error
        asked = self._submitted.pop(ticket.job_id, arrived)
        self.records.append(
            JobRecord(
                ticket.kind, ticket.lane, ticket.t_request, float(t), compute, arrived - asked
            )
        )
        return Done(value, ticket.t_request, float(t), compute)

    def warm_up(self, timeout: float = 120.0) -> None:
        deadline = time.monotonic() + timeout
        tokens = {}
        for name, lane in self._lanes.items():
            tokens[name] = next(self._ids)
            lane.jobs.put(("ping", tokens[name]))
        for name, lane in self._lanes.items():
            while True:
                if lane.failure is not None:
                    raise WorkerError(lane.failure)
                with lane.lock:
                    if tokens[name] in lane.pongs:
                        break
                if time.monotonic() > deadline:
                    raise WorkerError(
                        f"the perception worker '{name}' did not start within {timeout:g} s"
                    )
                time.sleep(0.01)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for lane in self._lanes.values():
            lane.close()


def execution_mode(setting: str, paced: bool) -> str:
    """The executor for ``perception.execution`` = ``setting`` in a run that is (``paced``)
    or is not paced at real time: "inline" or "worker" (``auto``: worker when paced)."""
    if setting == "auto":
        return "worker" if paced else "inline"
    if setting not in ("inline", "worker"):
        raise ValueError(
            f"perception.execution: expected 'auto', 'inline' or 'worker', got {setting!r}"
        )
    return setting


def MakeExecutor(config, paced: bool) -> Executor:
    """The executor a run with ``config`` (the scenario's ``perception`` section) uses;
    ``paced``: the run keeps pace with the wall clock (a live station)."""
    if execution_mode(config.execution, paced) == "worker":
        return WorkerExecutor(nice={"frames": config.segmentation_nice, "fits": config.fit_nice})
    return InlineExecutor({"frames": config.segmentation_latency, "fits": config.fit_latency})
