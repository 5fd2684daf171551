"""Pacing a live run at real time, tick by tick, and measuring every tick.

A live run (a station that drives a real robot: the scan, and the bring-up steps through
``hardware.station.RunHardware``) advances its diagram one *tick* at a time
(``tick`` s, the fastest periodic rate of the loop: the station's command rate): it sleeps
until the tick is due on the wall clock, advances the diagram through it and records

- ``compute``: wall time (s) the tick took (station I/O, control, safety, supervisor, and
  taking perception results; the perception itself runs beside, ``drake_rus.executor``);
- ``lag``: how late (s) the tick started after it was due.

A tick that starts up to ``catch_up`` s late (default 20 ms: four ticks at 200 Hz) is caught
up by running the next ticks at once. Beyond that the diagram does not race to catch up (a
burst of ticks faster than real time would see the robot's state stand still in diagram
time: the safety layer's stale-state watchdog, 50 ms of diagram time, would stop a robot
that moved, and the controller would command from stale readings): the schedule *slips*
by the lateness, so the diagram's time keeps pace with the wall clock after a stall, and
the slip is recorded. The
run is stopped as *overloaded* (``RealtimePacer.overload``: the reason) when one tick
starts more than ``max_lag`` s late or the slips of the last second add up to more than
``max_lag`` (the loop ran slower than real time). ``loop_statistics`` summarises a run
(p50, p99, p99.9 and max of both, in ms) for summary.json and rehearsal.json.
"""

from __future__ import annotations

import collections
import gc
import math
import os
import time

import numpy as np

__all__ = [
    "RealtimePacer",
    "GcPauses",
    "gc_statistics",
    "loop_statistics",
    "load_average",
    "percentiles_ms",
]


def load_average() -> dict:
    """The machine's load averages (1, 5, 15 min) and its number of CPUs."""
    try:
        one, five, fifteen = os.getloadavg()
    except OSError:
        one = five = fifteen = math.nan
    return {"1min": one, "5min": five, "15min": fifteen, "cpus": os.cpu_count()}


def percentiles_ms(values) -> dict:
    """p50, p99, p99.9 and max (ms) of ``values`` (s); None for each when empty."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {"p50": None, "p99": None, "p999": None, "max": None}
    p = np.percentile(v, [50, 99, 99.9])
    return {
        "p50": float(1e3 * p[0]),
        "p99": float(1e3 * p[1]),
        "p999": float(1e3 * p[2]),
        "max": float(1e3 * v.max()),
    }


def loop_statistics(tick: float, compute, lag, slips=(), load=None) -> dict:
    """summary.json's ``loop_timing``: the tick (ms), the number of ticks, the percentiles
    of the per-tick compute time and lag (ms), the ticks whose compute exceeded the tick,
    the slips (count and total, s) and the load average (when given)."""
    compute = np.asarray(compute, float)
    slips = np.asarray(slips, float)
    out = {
        "tick_ms": 1e3 * float(tick),
        "ticks": int(compute.size),
        "compute_ms": percentiles_ms(compute),
        "lag_ms": percentiles_ms(lag),
        "overruns": int(np.count_nonzero(compute > tick)),
        "slips": int(slips.size),
        "slip_total_s": float(slips.sum()) if slips.size else 0.0,
    }
    if load is not None:
        out["load_average"] = load
    return out


class RealtimePacer:
    """Advances ``simulator`` at real time in ticks of ``tick`` s (see the module doc),
    stopping it as overloaded beyond ``max_lag`` s. ``clock`` and ``sleep`` are the wall
    clock (s) and a sleep (tests pass fakes)."""

    def __init__(
        self,
        simulator,
        tick: float,
        max_lag: float,
        *,
        clock=time.perf_counter,
        sleep=time.sleep,
        window: float = 1.0,
        catch_up: float = 0.02,
    ):
        if not (tick > 0.0 and max_lag > 0.0):
            raise ValueError(
                f"RealtimePacer: tick and max_lag must be > 0 s, got {tick}, {max_lag}"
            )
        self.simulator = simulator
        self.tick = float(tick)
        self.max_lag = float(max_lag)
        self._clock, self._sleep = clock, sleep
        self.window = float(window)
        self.catch_up = max(float(catch_up), self.tick)
        self.times: list[float] = []  # diagram time at each tick's start (s)
        self.compute: list[float] = []
        self.lag: list[float] = []
        self.slips: list[float] = []
        self._recent_slips: collections.deque = collections.deque()  # (wall s, slip s)
        self.overload: str | None = None
        self._origin = None  # (wall s, diagram s) of the schedule

    def _due(self, t: float) -> float:
        wall0, t0 = self._origin
        return wall0 + (t - t0)

    def advance_to(self, t_final: float) -> None:
        """Ticks until the diagram reaches ``t_final`` (s) or the run is overloaded."""
        context = self.simulator.get_context()
        if self._origin is None:
            self._origin = (self._clock(), context.get_time())
        while self.overload is None and context.get_time() < t_final - 1e-12:
            t = context.get_time()
            due = self._due(t)
            now = self._clock()
            if now < due:
                self._sleep(due - now)
                now = self._clock()
            lag = now - due
            if lag > self.max_lag:
                self.lag.append(lag)
                self.overload = (
                    f"a control tick started {1e3 * lag:.0f} ms late, behind real time by "
                    f"more than safety.realtime_lag {self.max_lag:g} s"
                )
                return
            if lag > self.catch_up:
                # Too late to catch up: slip the schedule instead of racing.
                wall0, t0 = self._origin
                self._origin = (wall0 + lag, t0)
                self.slips.append(lag)
                self._recent_slips.append((now, lag))
                while self._recent_slips and self._recent_slips[0][0] < now - self.window:
                    self._recent_slips.popleft()
                recent = sum(s for _, s in self._recent_slips)
                if recent > self.max_lag:
                    self.lag.append(lag)
                    self.overload = (
                        f"the loop fell {1e3 * recent:.0f} ms behind real time within "
                        f"{self.window:g} s (more than safety.realtime_lag {self.max_lag:g} s)"
                    )
                    return
            self.simulator.AdvanceTo(min(t_final, t + self.tick))
            self.times.append(t)
            self.lag.append(lag)
            self.compute.append(self._clock() - now)

    def statistics(self, load=None) -> dict:
        return loop_statistics(self.tick, self.compute, self.lag, self.slips, load)

    def trace(self) -> dict:
        """The per-tick record: diagram time (s), compute (s) and lag (s) of every tick."""
        return {
            "t": np.asarray(self.times, float),
            "compute": np.asarray(self.compute, float),
            "lag": np.asarray(self.lag[: len(self.times)], float),
        }


class GcPauses:
    """``with GcPauses(pauses):`` appends (generation, pause s) of every garbage collection
    in the block to ``pauses`` (a stall of every thread: the collector holds the
    interpreter lock); with ``spans``, also appends its (start, end) on ``time.monotonic()``
    (s) there."""

    def __init__(self, pauses: list, spans: list | None = None):
        self.pauses = pauses
        self.spans = spans
        self._start = None
        self._start_monotonic = None

    def _callback(self, phase, info):
        if phase == "start":
            self._start = time.perf_counter()
            self._start_monotonic = time.monotonic()
        elif self._start is not None:
            self.pauses.append((info.get("generation"), time.perf_counter() - self._start))
            if self.spans is not None:
                self.spans.append((self._start_monotonic, time.monotonic()))
            self._start = None

    def __enter__(self):
        gc.callbacks.append(self._callback)
        return self

    def __exit__(self, *exc):
        gc.callbacks.remove(self._callback)
        return False


def gc_statistics(pauses) -> dict:
    """Count and longest pause (ms) of the collections, and how many were full (gen 2)."""
    return {
        "collections": len(pauses),
        "full": sum(1 for g, _ in pauses if g == 2),
        "max_ms": 1e3 * max((p for _, p in pauses), default=0.0),
    }
