"""The simulated robot's status stream from a process of its own (LCM over udpm).

:class:`StatusPublisherProcess` has :class:`~drake_rus.rehearsal.sim.StatusPublisherThread`'s
interface: the physics thread ``offer`` s each new status (its encoded bytes go into a
shared-memory slot, a few microseconds, never waiting), and a separate process publishes
the newest one every ``period`` s of the wall clock, its ``utime`` set to the wall clock
when sent. That process shares no interpreter lock with the physics, so a physics thread
holding the lock (a contact solve inside a Python system's evaluation, or the thread
descheduled while it holds it) delays no status: during a physics stall the robot keeps
reporting its last state at its rate, as a real robot's controller would report a robot
that stopped moving (the scan's stale-state watchdog names that).

The slot is a sequence lock: the writer makes the counter odd, writes, makes it even; the
reader retries until it read the same even counter before and after (one writer; x86 and
other total-store-order machines keep the stores in order).
"""

from __future__ import annotations

import gc
import multiprocessing
import struct
import time

import numpy as np
from pydrake.lcm import DrakeLcm

from drake_rus.hardware.core import wall_clock_utime
from drake_rus.pacing import percentiles_ms
from drake_rus.rehearsal.core import await_ready, realtime_scheduling, stop_process

__all__ = ["StatusPublisherProcess", "SlotWriter", "read_slot", "set_utime"]

_HEADER = struct.Struct("<QQ")  # sequence counter, message length
_SEQUENCE = struct.Struct("<Q")
# An lcmt_panda_status is 8 bytes of type hash, then its first field, int64 utime.
_UTIME = struct.Struct(">q")
_UTIME_OFFSET = 8


class SlotWriter:
    """Writes messages (bytes) into ``buffer`` (a writable shared buffer of
    ``16 + capacity`` bytes) under the sequence lock; the only writer."""

    def __init__(self, buffer):
        self._buffer = buffer
        self._capacity = len(memoryview(buffer).cast("B")) - _HEADER.size
        self._sequence = 0

    def write(self, data: bytes) -> None:
        if len(data) > self._capacity:
            raise ValueError(f"status slot: a {len(data)}-byte message, room for {self._capacity}")
        view = memoryview(self._buffer).cast("B")
        self._sequence += 1  # odd: writing
        _SEQUENCE.pack_into(view, 0, self._sequence)
        _SEQUENCE.pack_into(view, 8, len(data))
        view[_HEADER.size : _HEADER.size + len(data)] = data
        self._sequence += 1  # even: done
        _SEQUENCE.pack_into(view, 0, self._sequence)


def read_slot(buffer, tries: int = 100) -> bytes | None:
    """The newest complete message in the slot (None before the first, or if the writer
    kept it busy for ``tries`` reads)."""
    view = memoryview(buffer).cast("B")
    for _ in range(tries):
        before, length = _HEADER.unpack_from(view, 0)
        if before == 0:
            return None
        if before % 2:
            continue
        data = bytes(view[_HEADER.size : _HEADER.size + length])
        if _SEQUENCE.unpack_from(view, 0)[0] == before:
            return data
    return None


def set_utime(data: bytes, utime: int) -> bytes:
    """An encoded lcmt_panda_status with its ``utime`` (us) replaced."""
    out = bytearray(data)
    _UTIME.pack_into(out, _UTIME_OFFSET, int(utime))
    return bytes(out)


class StatusPublisherProcess:
    """Publishes PANDA_STATUS on the LCM ``url`` (udpm://) every ``period`` s from a process
    of its own (see the module doc); the interface of ``StatusPublisherThread``:
    ``offer(msg)``, ``start()``, ``close()``, ``gaps_ms()``, and after ``close()``:
    ``published``, ``dropped``, ``times`` (monotonic s, the machine's one clock, of every
    status sent or dropped), ``scheduling``."""

    def __init__(
        self,
        url: str,
        channel: str,
        period: float,
        *,
        drop_probability: float = 0.0,
        seed: int = 0,
        realtime_priority: int = 0,
        capacity: int = 4096,
    ):
        if not url.startswith("udpm://"):
            raise ValueError(f"StatusPublisherProcess: needs a udpm:// LCM url, got {url!r}")
        ctx = multiprocessing.get_context("spawn")
        self.period = float(period)
        self._slot = ctx.RawArray("B", _HEADER.size + int(capacity))
        self._writer = SlotWriter(self._slot)
        self._conn, child = ctx.Pipe()
        self._process = ctx.Process(
            target=_status_main,
            args=(
                child,
                self._slot,
                url,
                channel,
                self.period,
                float(drop_probability),
                int(seed),
                int(realtime_priority),
            ),
            name="drake_rus_panda_status",
            daemon=True,
        )
        self._child = child
        self.published = 0
        self.dropped = 0
        self.times: list[float] = []
        self.scheduling = "not started"
        self._closed = False

    def offer(self, msg) -> None:
        self._writer.write(msg.encode())

    def start(self, timeout: float = 60.0) -> None:
        if self._process.is_alive() or self._closed:
            return
        self._process.start()
        self._child.close()
        self.scheduling = await_ready(self._process, self._conn, timeout, "status")

    def gaps_ms(self) -> dict:
        t = np.asarray(self.times, float)
        return percentiles_ms(np.diff(t) if t.size > 1 else [])

    def close(self, timeout: float = 5.0) -> None:
        if self._closed:
            return
        self._closed = True
        if self._process.pid is None:  # never started
            return
        try:
            self._conn.send(("stop", None))
            if self._conn.poll(timeout):
                kind, value = self._conn.recv()
                if kind == "stats":
                    self.published, self.dropped = value["published"], value["dropped"]
                    self.times = value["times"]
        except (EOFError, OSError, BrokenPipeError):
            pass
        self._process.join(timeout)
        self._kill()
        self._conn.close()

    def _kill(self) -> None:
        stop_process(self._process)


def _status_main(conn, slot, url, channel, period, drop_probability, seed, priority) -> None:
    """The status process: see :class:`StatusPublisherProcess`."""
    try:
        lcm = DrakeLcm(url)
    except Exception as e:
        conn.send(("error", f"{type(e).__name__}: {e}"))
        return
    scheduling = realtime_scheduling(priority) if priority > 0 else "normal"
    rng = np.random.default_rng(seed)
    published = dropped = 0
    times: list[float] = []
    last = None
    # This process imported what its parent's main module imports: keep all of it out of
    # the collector's passes, or a full collection pauses the statuses for tens of ms.
    gc.collect()
    gc.freeze()
    conn.send(("ready", scheduling))
    due = time.monotonic()
    try:
        while True:
            now = time.monotonic()
            if now < due:
                if conn.poll(due - now):
                    break  # stop (or the robot's process is gone)
                continue
            # The newest status; the last one read while the physics is mid-write.
            data = read_slot(slot, tries=3) or last
            last = data
            if data is not None:
                times.append(now)
                if drop_probability > 0.0 and rng.random() < drop_probability:
                    dropped += 1
                else:
                    lcm.Publish(channel, set_utime(data, wall_clock_utime()))
                    published += 1
            due += period
            if due < now - period:  # fell behind (a stall): do not burst
                due = now + period
    finally:
        try:
            conn.send(("stats", {"published": published, "dropped": dropped, "times": times}))
        except (OSError, BrokenPipeError):
            pass
