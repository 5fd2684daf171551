"""The rehearsal's ultrasound machine as its own process: pictures rendered off the robot.

The simulated robot's physics thread only takes a :class:`PoseSnapshot` at each imaging
instant (the probe pose X_BP, the label volume's pose X_BV, the frame index, and the wall
time the robot was at that pose) and hands it to :class:`VideoProcess`. The process slices
the label volume at that pose, emulates the picture (:class:`SliceEmulateRenderer`: the
station's own slice sensor and emulator functions, model and seed, so the same picture the
station's ``us_image`` gives), JPEG-encodes it and serves it as the MJPEG stream
(``drake_rus.rehearsal.mjpeg``) stamped with the snapshot's wall time: a picture shows the
pose it was rendered at, and it becomes visible when it is ready (its render time is the
machine's video latency). Only the newest snapshot waits; one overtaken is skipped.

Why a process: a thread beside the physics shares the interpreter lock, so the rendering's
Python steps (and the collector, and a thread descheduled while holding the lock) stall the
robot's status stream. In its own process the pictures cost the robot a pipe write per frame.
"""

from __future__ import annotations

import dataclasses
import gc
import logging
import multiprocessing
import os
import time

import numpy as np
from pydrake.math import RigidTransform

from drake_rus.imaging.emulator import EmulatorModel, emulate
from drake_rus.imaging.emulator import warm_up as warm_emulator
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.imaging.slicing import slice_volume
from drake_rus.imaging.slicing import warm_up as warm_slicer
from drake_rus.pacing import percentiles_ms
from drake_rus.rehearsal.core import await_ready, stop_process
from drake_rus.rehearsal.mjpeg import FrameBuffer, MjpegServer

LOG = logging.getLogger("drake_rus.rehearsal")

__all__ = ["PoseSnapshot", "SliceEmulateRenderer", "VideoProcess", "VIDEO_NICE"]

# Niceness of the video process: below the robot's (a late picture is the machine's video
# latency, a late status a robot gone quiet).
VIDEO_NICE = 5


@dataclasses.dataclass(frozen=True)
class PoseSnapshot:
    """What a picture is rendered from: ``frame_index``, simulated time ``t`` (s), ``stamp``
    (wall-clock s, ``time.time()``, when the robot was at this pose: the picture's time
    stamp), ``X_BP`` and ``X_BV`` (4x4 homogeneous matrices, m: the probe tip and the label
    volume's grid in the robot base)."""

    frame_index: int
    t: float
    stamp: float
    X_BP: np.ndarray
    X_BV: np.ndarray


class SliceEmulateRenderer:
    """``renderer(X_BP, X_BV, frame_index)`` -> uint8 grey picture: slices ``volume`` at the
    probe pose and emulates it (the station's ``SliceSensor`` and ``UltrasoundEmulator``
    with the scenario's ``imaging`` ``config`` and speckle ``seed``). Picklable (it is sent
    to the video process); ``warm()`` compiles the kernels there."""

    def __init__(self, config, volume, seed: int):
        self.config, self.volume, self.seed = config, volume, int(seed)
        self._ready = None

    def __getstate__(self):
        return {"config": self.config, "volume": self.volume, "seed": self.seed}

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._ready = None

    def warm(self) -> None:
        geometry = ProbeGeometry.from_config(self.config)
        model = EmulatorModel.from_config(self.config)
        planes, combine = int(self.config.elevation_planes), self.config.elevation_combine
        warm_slicer(geometry, self.volume, planes, combine)
        warm_emulator(model, self.seed)
        self._ready = (geometry, model, planes, combine)

    def __call__(self, X_BP, X_BV, frame_index: int) -> np.ndarray:
        if self._ready is None:
            self.warm()
        geometry, model, planes, combine = self._ready
        labels = slice_volume(
            geometry,
            self.volume,
            RigidTransform(np.asarray(X_BV, float)),
            RigidTransform(np.asarray(X_BP, float)),
            planes,
            combine,
        )
        return emulate(labels, model, self.seed, int(frame_index))


class VideoProcess:
    """Renders :class:`PoseSnapshot` s in a process of its own and serves them as MJPEG on
    127.0.0.1 (``url``). ``renderer``: a picklable ``(X_BP, X_BV, frame_index) -> picture``
    (optionally with ``warm()``, called in the process before it reports ready);
    ``delay`` (s): the stream shows each picture that much later (a fault);
    ``offer(snapshot)`` (a pipe write, never waits for a picture), ``freeze(wall)``,
    ``close()`` -> the process's statistics (also ``stats``)."""

    def __init__(
        self,
        renderer,
        *,
        frame_rate_hz: float,
        delay: float = 0.0,
        port: int = 0,
        quality: int = 90,
        nice: int = VIDEO_NICE,
        timeout: float = 120.0,
    ):
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._process = ctx.Process(
            target=_video_main,
            args=(child, renderer, float(frame_rate_hz), float(delay), int(port), quality, nice),
            name="drake_rus_video",
            daemon=True,
        )
        self._process.start()
        child.close()
        self.stats: dict | None = None
        self.offered = 0
        self.port = int(await_ready(self._process, self._conn, timeout, "video"))

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/stream.mjpg"

    @property
    def pid(self) -> int | None:
        return self._process.pid

    def offer(self, snapshot: PoseSnapshot) -> None:
        if self.stats is None:
            self._conn.send(("pose", snapshot))
            self.offered += 1

    def freeze(self, wall: float) -> None:
        if self.stats is None:
            self._conn.send(("freeze", float(wall)))

    def close(self, timeout: float = 5.0) -> dict:
        if self.stats is not None:
            return self.stats
        self.stats = {}
        try:
            self._conn.send(("stop", None))
            if self._conn.poll(timeout):
                kind, value = self._conn.recv()
                if kind == "stats":
                    self.stats = value
        except (EOFError, OSError, BrokenPipeError):
            pass
        self._process.join(timeout)
        self._kill()
        self._conn.close()
        return self.stats

    def _kill(self) -> None:
        stop_process(self._process)


def _video_main(conn, renderer, frame_rate_hz, delay, port, quality, nice) -> None:
    """The video process: see :class:`VideoProcess`."""
    try:
        os.nice(int(nice))
    except (AttributeError, OSError):
        pass
    try:
        if hasattr(renderer, "warm"):
            renderer.warm()
        server = MjpegServer(
            FrameBuffer(delay), frame_rate_hz=frame_rate_hz, port=port, quality=quality
        )
    except Exception as e:
        conn.send(("error", f"{type(e).__name__}: {e}"))
        return
    gc.collect()
    gc.freeze()  # what the process imported stays out of the collector's passes
    conn.send(("ready", server.port))
    shown = skipped = 0
    spans: list = []  # (start, end) monotonic s per picture
    rendered: list = []  # (frame_index, stamp) per picture pushed
    ages: list = []  # wall s from the pose to the picture being available
    pending = None
    stop = False
    try:
        while not stop:
            timeout = 0.0 if pending is not None else 0.5
            while conn.poll(timeout):
                timeout = 0.0
                try:
                    kind, value = conn.recv()
                except EOFError:  # the robot's process is gone
                    stop = True
                    break
                if kind == "pose":
                    if pending is not None:
                        skipped += 1
                    pending = value
                elif kind == "freeze":
                    server.buffer.freeze(value)
                elif kind == "stop":
                    stop = True
                    break
            if stop or pending is None:
                continue
            snapshot, pending = pending, None
            start = time.monotonic()
            try:
                image = renderer(snapshot.X_BP, snapshot.X_BV, snapshot.frame_index)
                if server.push(image, snapshot.stamp):
                    rendered.append((int(snapshot.frame_index), float(snapshot.stamp)))
                    ages.append(time.time() - snapshot.stamp)
            except Exception as e:  # a picture lost must not stop the video
                LOG.error("video: %s: %s", type(e).__name__, e)
            end = time.monotonic()
            spans.append((start, end))
            shown += 1
    finally:
        server.close()
        stats = {
            "emulated": shown,
            "skipped": skipped,
            "emulation_ms": percentiles_ms([b - a for a, b in spans]),
            "age_when_shown_ms": percentiles_ms(ages),
            "pictures": server.buffer.pushed,
            "parts_sent": server.sent,
            "clients": server.clients,
            "frozen_at_wall": server.buffer.frozen_at,
            "spans": spans,
            "rendered": rendered,
        }
        try:
            conn.send(("stats", stats))
        except (OSError, BrokenPipeError):
            pass
