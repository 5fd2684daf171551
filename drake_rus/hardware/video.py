"""Video of the ultrasound machine for the hardware station: capture thread, probe pose
history, diagram clock, video latency.

Timing model (docs/hardware_bringup.md, "Video timing")
------------------------------------------------------
Everything is stamped on one clock, ``time.monotonic()`` (s):

- the capture thread (:class:`FrameCapture`) reads the source as fast as it delivers
  pictures (a device or a stream: ``read()`` blocks until the next picture, so none queue up
  in OpenCV's buffer; a video file: replayed at its own frame rate in real time), and keeps
  only the newest picture with its *capture time* (the monotonic time ``read()`` returned)
  and a frame counter;
- the frame grabber (``systems.FrameGrabber``) records, at every control tick, the monotonic
  time and the diagram time (a :class:`DiagramClock`), and the probe pose ``X_BP`` (our FK
  of the joints the station read) stamped with the monotonic time those joints were
  measured (franky: when libfranka's state was read; LCM: the status's arrival less its
  wall-clock age from ``utime``): a :class:`PoseHistory`;
- the picture shows the tissue as it was ``video_latency`` s before its capture time (scan
  conversion, video output, capture card, decoding; plus whatever constant lag the robot
  state's stamp still has). So a frame's probe pose is the history at
  ``capture_time - video_latency`` (translation linear, rotation slerp) and its
  ``UsFrame.time`` is the *diagram* time of that same instant, from the clock map (linear
  between the two ticks around it; slope 1 outside). ``UsFrame.frame_index`` is the capture
  counter: gaps are frames the grabber never saw.

The latency is measured by :func:`estimate_video_latency`: the probe moves sinusoidally over
a point target; the lag that best aligns the target's image position with the probe's
recorded position is the latency (``drake-rus hardware calibrate-latency``).
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import os
import re
import threading
import time
import urllib.parse
from typing import Callable

import numpy as np
from pydrake.common.eigen_geometry import Quaternion
from pydrake.math import RigidTransform, RotationMatrix

from drake_rus.extras import require

LOG = logging.getLogger("drake_rus.hardware")

__all__ = [
    "URL_SCHEMES",
    "VideoSourceSpec",
    "parse_video_source",
    "open_video_capture",
    "CapturedFrame",
    "CaptureStats",
    "FrameCapture",
    "SyntheticVideo",
    "quaternion_slerp",
    "interpolate_pose",
    "monotonic_to_diagram_time",
    "PoseHistory",
    "DiagramClock",
    "LatencyEstimate",
    "estimate_video_latency",
    "motion_signal",
]

VIDEO_FIELD = "hardware_interface.video_source"
# URL schemes OpenCV's FFmpeg back-end reads as a live stream.
URL_SCHEMES = ("http", "https", "rtsp", "rtsps", "rtp", "rtmp", "udp", "tcp")


# --- sources ---------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class VideoSourceSpec:
    """A parsed video source: ``kind`` "device" (``value`` an int index), "file" (a path)
    or "url"."""

    kind: str
    value: object

    @property
    def live(self) -> bool:
        """Devices and streams deliver at their own pace; files are paced here."""
        return self.kind != "file"


def parse_video_source(text: str, field: str = VIDEO_FIELD) -> VideoSourceSpec:
    """``"0"`` -> device 0; ``"scheme://..."`` -> a URL (scheme in :data:`URL_SCHEMES`, with a
    host); anything else -> a video file that must exist. A device path (``/dev/video0``,
    present or not) is refused with the index to give instead. Raises ValueError naming
    ``field``."""
    source = str(text).strip()
    if not source:
        raise ValueError(f"field '{field}': empty video source")
    if source.isdigit():
        return VideoSourceSpec("device", int(source))
    if "://" in source:
        parts = urllib.parse.urlsplit(source)
        scheme = parts.scheme.lower()
        if scheme not in URL_SCHEMES:
            raise ValueError(
                f"field '{field}': unsupported URL scheme {parts.scheme!r} in "
                f"{source!r}; use one of {', '.join(URL_SCHEMES)}, a capture "
                f"device index or a video file path"
            )
        try:
            host, port = parts.hostname, parts.port
        except ValueError as e:
            raise ValueError(f"field '{field}': bad URL {source!r}: {e}") from None
        if not host:
            raise ValueError(f"field '{field}': URL {source!r} names no host")
        del port
        return VideoSourceSpec("url", source)
    others = f"a stream URL ({', '.join(URL_SCHEMES)}) or a video file path"
    if source.startswith("/dev/"):
        # OpenCV opens V4L2 devices by index; /dev/v4l/by-id/... links resolve to /dev/videoN.
        video = re.fullmatch(r"/dev/video(\d+)", os.path.realpath(source))
        index = f"'{video.group(1)}' for {source}" if video else "N for /dev/videoN"
        raise ValueError(
            f"field '{field}': {source!r} is a device path; give a capture device index "
            f"({index}), {others}"
        )
    if not os.path.isfile(source):
        raise ValueError(
            f"field '{field}': video file not found: {source} (the source is a capture "
            f"device index, {others})"
        )
    return VideoSourceSpec("file", source)


def open_video_capture(spec: VideoSourceSpec, field: str = VIDEO_FIELD):
    """An opened ``cv2.VideoCapture`` for ``spec`` (raises ValueError naming ``field``).
    Devices get a one-picture driver buffer where the back-end allows it."""
    cv2 = require("cv2", "the ultrasound video capture (hardware_interface.video_source)")
    if spec.kind == "device":
        cap = cv2.VideoCapture(int(spec.value))
        if not cap.isOpened():
            raise ValueError(f"field '{field}': cannot open capture device {spec.value}")
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
        return cap
    if spec.kind == "url":
        cap = cv2.VideoCapture(str(spec.value), cv2.CAP_FFMPEG)
        if not cap.isOpened():
            raise ValueError(f"field '{field}': OpenCV cannot open the stream {spec.value}")
        return cap
    cap = cv2.VideoCapture(str(spec.value))
    if not cap.isOpened():
        raise ValueError(f"field '{field}': OpenCV cannot read the video file {spec.value}")
    return cap


@dataclasses.dataclass(frozen=True)
class CapturedFrame:
    """A picture as delivered by the capture thread: ``image`` (after ``process``),
    ``capture_time`` (s, monotonic, when the source delivered it), ``counter`` (0 for the
    first picture delivered, +1 for each one after; never reset) and, if kept, the raw
    ``picture``."""

    image: np.ndarray
    capture_time: float
    counter: int
    picture: np.ndarray | None = None


@dataclasses.dataclass(frozen=True)
class CaptureStats:
    """Frames delivered, read failures, frame rate over the last ~2 s (Hz), age of the
    newest frame (s), whether the thread runs, whether a file ended, the last error."""

    frames: int
    failures: int
    frame_rate_hz: float
    age: float
    running: bool
    ended: bool
    error: str | None


class FrameCapture:
    """A thread that drains a video source and keeps only its newest picture.

    ``source``: a source string (:func:`parse_video_source`) or an object with OpenCV's
    ``read()`` / ``release()`` (e.g. :class:`SyntheticVideo`, paced by itself like a device).
    ``process(picture) -> image`` runs in the thread (crop, grey, map to the probe grid).
    A video file is replayed at its own frame rate (``CAP_PROP_FPS``; ``fallback_fps`` if the
    file has none) in real time, looped if ``loop``. A device or stream that fails is
    re-opened after ``reopen_after`` s of failures. The first picture is read (and processed)
    in the constructor, so a bad source or crop fails at once (ValueError naming the field).
    """

    def __init__(
        self,
        source,
        *,
        process: Callable | None = None,
        loop: bool = True,
        keep_raw: bool = False,
        fallback_fps: float = 20.0,
        reopen_after: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
        field: str = VIDEO_FIELD,
        start: bool = True,
    ):
        self._process = process if process is not None else (lambda p: p)
        self._loop = bool(loop)
        self._keep_raw = bool(keep_raw)
        self._clock = clock
        self._field = field
        self._reopen_after = float(reopen_after)
        if isinstance(source, str):
            self.spec = parse_video_source(source, field)
            self._cap = open_video_capture(self.spec, field)
        else:
            self.spec = VideoSourceSpec("object", type(source).__name__)
            self._cap = source
        self.file_fps = float("nan")
        if self.spec.kind == "file":
            cv2 = require("cv2", "the ultrasound video capture (hardware_interface.video_source)")
            fps = float(self._cap.get(cv2.CAP_PROP_FPS) or 0.0)
            self.file_fps = (
                fps if math.isfinite(fps) and 0.5 <= fps <= 1000.0 else float(fallback_fps)
            )
        ok, picture = self._cap.read()
        read_time = self._clock()  # the capture time: before processing, which takes a while
        if not ok or picture is None:
            self._cap.release()
            raise ValueError(f"field '{field}': no picture from {self.spec.value}")
        try:
            self._process(picture)
        except ValueError:
            self._cap.release()
            raise
        except Exception as e:
            self._cap.release()
            raise ValueError(
                f"field '{field}': cannot process a picture from "
                f"{self.spec.value}: {type(e).__name__}: {e}"
            ) from None
        if self.spec.kind == "file":
            self._rewind()
        self._first = None if self.spec.kind == "file" else (picture, read_time)
        self._lock = threading.Condition()
        self._latest: CapturedFrame | None = None
        self._counter = 0
        self._failures = 0
        self._times = collections.deque(maxlen=128)
        self._ended = False
        self._error: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="drake_rus_video", daemon=True)
        if start:
            self._thread.start()

    # --- the thread -----------------------------------------------------------------
    def _rewind(self):
        cv2 = require("cv2", "the ultrasound video capture (hardware_interface.video_source)")
        self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)

    def _publish(self, picture, capture_time: float) -> None:
        try:
            image = self._process(picture)
        except Exception as e:  # a bad picture: count it, keep the previous frame
            with self._lock:
                self._failures += 1
                if self._error is None:
                    LOG.error("video: cannot process a picture: %s: %s", type(e).__name__, e)
                self._error = f"{type(e).__name__}: {e}"
            return
        image = np.asarray(image)
        image.flags.writeable = False
        frame = CapturedFrame(
            image, float(capture_time), self._counter, picture if self._keep_raw else None
        )
        with self._lock:
            self._latest = frame
            self._counter += 1
            self._times.append(frame.capture_time)
            self._lock.notify_all()

    def _run(self):
        try:
            if self.spec.kind == "file":
                self._run_file()
            else:
                self._run_live()
        except Exception as e:  # never let the thread die silently
            LOG.error("video thread: %s: %s", type(e).__name__, e)
            with self._lock:
                self._error = f"{type(e).__name__}: {e}"
        finally:
            with self._lock:
                self._lock.notify_all()

    def _run_file(self):
        period = 1.0 / self.file_fps
        start = self._clock()
        k = 0
        while not self._stop.is_set():
            ok, picture = self._cap.read()
            if not ok:
                if not self._loop:
                    with self._lock:
                        self._ended = True
                    return
                self._rewind()
                ok, picture = self._cap.read()
                if not ok:
                    with self._lock:
                        self._failures += 1
                        self._ended = True
                        self._error = f"cannot rewind the video file {self.spec.value}"
                    return
            due = start + k * period
            delay = due - self._clock()
            if delay > 0 and self._stop.wait(delay):
                return
            if delay < -period:  # fell behind (a loaded machine): skip ahead
                start += -delay
            self._publish(picture, self._clock())
            k += 1

    def _run_live(self):
        if self._first is not None:
            picture, t = self._first
            self._first = None
            self._publish(picture, t)
        failing_since = None
        while not self._stop.is_set():
            ok, picture = self._cap.read()
            now = self._clock()
            if ok and picture is not None:
                failing_since = None
                self._publish(picture, now)
                continue
            with self._lock:
                self._failures += 1
            failing_since = now if failing_since is None else failing_since
            if self.spec.kind in ("device", "url") and now - failing_since > self._reopen_after:
                LOG.warning(
                    "video: no picture from %s for %.1f s: re-opening",
                    self.spec.value,
                    now - failing_since,
                )
                try:
                    self._cap.release()
                    self._cap = open_video_capture(self.spec, self._field)
                except ValueError as e:
                    with self._lock:
                        self._error = str(e)
                failing_since = self._clock()
            self._stop.wait(0.01)

    # --- the caller's side ----------------------------------------------------------
    def latest(self) -> CapturedFrame | None:
        """The newest frame (None before the first). Never blocks on the source."""
        with self._lock:
            return self._latest

    def wait_for(self, after_counter: int = -1, timeout: float = 1.0) -> CapturedFrame | None:
        """Blocks (at most ``timeout`` s) until a frame with counter > ``after_counter``
        exists; returns it, or None. For tools and tests, never for the control loop."""
        deadline = time.monotonic() + timeout
        with self._lock:
            while self._latest is None or self._latest.counter <= after_counter:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self._ended or not self._thread.is_alive():
                    break
                self._lock.wait(remaining)
            f = self._latest
        return f if f is not None and f.counter > after_counter else None

    def stats(self, now: float | None = None) -> CaptureStats:
        now = self._clock() if now is None else now
        with self._lock:
            times = [t for t in self._times if t >= now - 2.0]
            rate = (
                (len(times) - 1) / (times[-1] - times[0])
                if len(times) >= 3 and times[-1] > times[0]
                else 0.0
            )
            age = now - self._latest.capture_time if self._latest is not None else math.inf
            return CaptureStats(
                self._counter,
                self._failures,
                rate,
                age,
                self._thread.is_alive(),
                self._ended,
                self._error,
            )

    def close(self) -> None:
        """Stops the thread and releases the source (idempotent)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2.0)
        if self._thread.is_alive():
            # Still blocked in the source's read(): releasing under it could crash; the
            # daemon thread ends with the process.
            LOG.error("video: the capture thread is blocked in read(); source not released")
            return
        cap, self._cap = self._cap, None
        if cap is not None:
            try:
                cap.release()
            except Exception as e:
                LOG.error("video: release: %s", e)

    def __del__(self):
        try:
            self._stop.set()
        except Exception:
            pass


class SyntheticVideo:
    """A video source that draws its pictures (tests, rehearsal): ``read()`` waits for the
    next frame time ``t_k = start + k / frame_rate_hz`` (like a device) and returns
    ``render(t_k - latency)``: the scene as it was ``latency`` s before the picture is
    delivered (s, monotonic clock)."""

    def __init__(
        self,
        render: Callable[[float], np.ndarray],
        frame_rate_hz: float = 30.0,
        latency: float = 0.0,
        clock: Callable[[], float] = time.monotonic,
    ):
        self._render = render
        self._period = 1.0 / float(frame_rate_hz)
        self.latency = float(latency)
        self._clock = clock
        self._start = None
        self._k = 0
        self._released = threading.Event()

    def read(self):
        if self._released.is_set():
            return False, None
        now = self._clock()
        if self._start is None:
            self._start = now
        due = self._start + self._k * self._period
        if due < now - self._period:  # fell behind: the next slot from now
            self._k = int(math.ceil((now - self._start) / self._period))
            due = self._start + self._k * self._period
        if due > now and self._released.wait(due - now):
            return False, None
        self._k += 1
        return True, self._render(due - self.latency)

    def get(self, prop):
        return 0.0

    def set(self, prop, value):
        return False

    def release(self):
        self._released.set()


# --- pose interpolation and the diagram clock (pure) -------------------------------------
def quaternion_slerp(q0, q1, s: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions (w, x, y, z) at s in [0, 1], along
    the shorter arc."""
    q0 = np.asarray(q0, float)
    q1 = np.asarray(q1, float)
    d = float(q0 @ q1)
    if d < 0.0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + s * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = math.acos(min(d, 1.0))
    sin_theta = math.sin(theta)
    return (math.sin((1.0 - s) * theta) * q0 + math.sin(s * theta) * q1) / sin_theta


def interpolate_pose(times, translations, quaternions, t: float):
    """The pose at ``t`` from samples at increasing ``times`` (N,): translation (N, 3)
    linear, rotation (N, 4 quaternions w, x, y, z) slerp. Outside the samples the nearest
    one is returned. Returns (p (3,), q (4,), where) with ``where`` one of "inside",
    "before", "after"."""
    times = np.asarray(times, float)
    p = np.asarray(translations, float)
    q = np.asarray(quaternions, float)
    n = times.shape[0]
    if n == 0:
        raise ValueError("interpolate_pose: no samples")
    if t <= times[0]:
        return p[0].copy(), q[0].copy(), "inside" if t == times[0] else "before"
    if t >= times[-1]:
        return p[-1].copy(), q[-1].copy(), "inside" if t == times[-1] else "after"
    i = int(np.searchsorted(times, t, side="right")) - 1
    dt = times[i + 1] - times[i]
    s = (t - times[i]) / dt if dt > 0 else 0.0
    return (p[i] + s * (p[i + 1] - p[i]), quaternion_slerp(q[i], q[i + 1], s), "inside")


def monotonic_to_diagram_time(monotonic, diagram, m: float) -> float:
    """The diagram time at monotonic time ``m`` (s), from tick records (monotonic (N,),
    diagram (N,), both increasing): linear between the two ticks around ``m``; beyond the
    records the clocks are taken to run at the same rate (slope 1)."""
    mono = np.asarray(monotonic, float)
    diag = np.asarray(diagram, float)
    if mono.size == 0:
        raise ValueError("monotonic_to_diagram_time: no tick records")
    if m <= mono[0]:
        return float(diag[0] - (mono[0] - m))
    if m >= mono[-1]:
        return float(diag[-1] + (m - mono[-1]))
    return float(np.interp(m, mono, diag))


class _Ring:
    """Fixed-capacity ring buffer of rows (time first), appended with increasing time."""

    def __init__(self, capacity: int, width: int):
        self._data = np.full((max(int(capacity), 2), width), np.nan)
        self._n = 0
        self._head = 0  # next row to write

    def __len__(self):
        return self._n

    def append(self, row) -> bool:
        if self._n and row[0] <= self._data[(self._head - 1) % len(self._data), 0]:
            return False  # not newer than the last sample: ignored
        self._data[self._head] = row
        self._head = (self._head + 1) % len(self._data)
        self._n = min(self._n + 1, len(self._data))
        return True

    def ordered(self) -> np.ndarray:
        if self._n < len(self._data):
            return self._data[: self._n].copy()
        return np.roll(self._data, -self._head, axis=0)

    def last(self) -> np.ndarray | None:
        return self._data[(self._head - 1) % len(self._data)].copy() if self._n else None


class PoseHistory:
    """Ring buffer of (monotonic time s, X_BP) filled every control period;
    :meth:`pose_at` interpolates (translation linear, rotation slerp)."""

    def __init__(self, duration: float, rate_hz: float):
        self._ring = _Ring(int(math.ceil(duration * rate_hz)) + 2, 8)

    def __len__(self):
        return len(self._ring)

    def append(self, t: float, X_BP: RigidTransform) -> bool:
        """Adds a sample; one not newer than the last is ignored (returns False)."""
        q = X_BP.rotation().ToQuaternion()
        return self._ring.append(
            np.concatenate([[t], X_BP.translation(), [q.w(), q.x(), q.y(), q.z()]])
        )

    def span(self) -> tuple[float, float]:
        rows = self._ring.ordered()
        return (float(rows[0, 0]), float(rows[-1, 0])) if len(rows) else (math.nan, math.nan)

    def samples(self):
        """(times (N,), translations (N, 3), quaternions (N, 4)) in time order."""
        rows = self._ring.ordered()
        return rows[:, 0], rows[:, 1:4], rows[:, 4:8]

    def pose_at(self, t: float) -> tuple[RigidTransform, str]:
        """The pose at monotonic time ``t`` and "inside", "before" (older than the history:
        the oldest pose), "after" (the newest) or "empty" (identity)."""
        if not len(self._ring):
            return RigidTransform(), "empty"
        p, q, where = interpolate_pose(*self.samples(), t)
        R = RotationMatrix(Quaternion(q / np.linalg.norm(q)))
        return RigidTransform(R, p), where


class DiagramClock:
    """Tick records (diagram time, monotonic time) of the last ``duration`` s; maps a
    monotonic instant to diagram time (:func:`monotonic_to_diagram_time`)."""

    def __init__(self, duration: float, rate_hz: float):
        self._ring = _Ring(int(math.ceil(duration * rate_hz)) + 2, 2)

    def record(self, diagram_time: float, monotonic_time: float) -> None:
        self._ring.append([monotonic_time, diagram_time])

    def __len__(self):
        return len(self._ring)

    def to_diagram(self, m: float) -> float:
        rows = self._ring.ordered()
        if not len(rows):
            return math.nan
        return monotonic_to_diagram_time(rows[:, 0], rows[:, 1], m)


# --- video latency ---------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class LatencyEstimate:
    """``latency`` (s): the picture captured at time t shows the probe pose of t - latency;
    ``correlation``: the normalised correlation of image and probe motion at that lag (its
    sign says whether the image moves with or against the probe); ``frames`` used; the
    correlation curve ``lags`` (s) -> ``scores``."""

    latency: float
    correlation: float
    frames: int
    lags: np.ndarray
    scores: np.ndarray


def motion_signal(values) -> np.ndarray:
    """A 1-D motion signal from samples: (N,) as is; (N, k) projected on their principal
    direction; a sequence of RigidTransforms by their translations."""
    if len(values) and isinstance(values[0], RigidTransform):
        values = np.array([X.translation() for X in values])
    a = np.asarray(values, float)
    if a.ndim == 1:
        return a.copy()
    if a.ndim != 2:
        raise ValueError(f"motion_signal: expected (N,) or (N, k) samples, got {a.shape}")
    ok = np.all(np.isfinite(a), axis=1)
    out = np.full(a.shape[0], np.nan)
    if ok.sum() < 2:
        return out
    centred = a[ok] - a[ok].mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    out[ok] = centred @ vt[0]
    return out


def estimate_video_latency(
    pose_times,
    poses,
    frame_times,
    frame_signal,
    *,
    max_latency: float = 0.5,
    resolution: float = 0.001,
    min_correlation: float = 0.9,
    min_frames: int = 20,
) -> LatencyEstimate:
    """The video latency from a recording of the probe moving over a point target.

    Args:
        pose_times: (N,) monotonic times (s) of the probe poses (increasing).
        poses: the probe's motion: (N,) positions, (N, k) translations or N RigidTransforms.
        frame_times: (M,) capture times (s, same clock) of the frames.
        frame_signal: the target's image position per frame: (M,) or (M, 2) pixels; NaN
            where the target was not found.
        max_latency: the largest lag tried (s). The motion's period must exceed twice it
            (a sinusoid repeats itself after one period).
        resolution: lag step (s); the peak is refined by a parabola through its neighbours.
        min_correlation: below this best |correlation| the estimate is refused.

    Cross-correlates the image motion with the probe motion delayed by each candidate lag
    (the probe signal is interpolated at ``frame_times - lag``; the pose rate is usually
    10x the frame rate) and returns the lag of the largest |normalised correlation|.
    Raises ValueError with what went wrong (too few frames, no motion, poor correlation,
    peak at the end of the range, ambiguous peaks).
    """
    pt = np.asarray(pose_times, float).ravel()
    ps = motion_signal(poses)
    ft = np.asarray(frame_times, float).ravel()
    fs = motion_signal(frame_signal)
    if pt.shape[0] != ps.shape[0] or pt.shape[0] < 4:
        raise ValueError(
            f"estimate_video_latency: {pt.shape[0]} pose times for "
            f"{ps.shape[0]} poses (need matching arrays of at least 4)"
        )
    if ft.shape[0] != fs.shape[0]:
        raise ValueError(
            f"estimate_video_latency: {ft.shape[0]} frame times for "
            f"{fs.shape[0]} frame signal values"
        )
    if not (max_latency > 0 and resolution > 0):
        raise ValueError("estimate_video_latency: max_latency and resolution must be > 0")
    if np.any(np.diff(pt) <= 0):
        order = np.argsort(pt)
        pt, ps = pt[order], ps[order]
        keep = np.concatenate([[True], np.diff(pt) > 0])
        pt, ps = pt[keep], ps[keep]
    found = np.isfinite(fs) & np.isfinite(ft)
    usable = found & (ft - max_latency >= pt[0]) & (ft <= pt[-1])
    n = int(usable.sum())
    if n < min_frames:
        raise ValueError(
            f"estimate_video_latency: only {n} frames with the target found inside the pose "
            f"recording (less max_latency {max_latency:g} s at its start); need "
            f"{min_frames}: record longer, or check that the target is in view "
            f"({int(found.sum())} of {len(fs)} frames found it)"
        )
    ft, fs = ft[usable], fs[usable]
    moving = ps[(pt >= ft[0] - max_latency) & (pt <= ft[-1])]
    if not np.all(np.isfinite(ps)) or np.ptp(moving) <= 1e-9:
        raise ValueError("estimate_video_latency: the probe did not move during the frames")
    if np.std(fs) <= 1e-9:
        raise ValueError("estimate_video_latency: the target did not move in the images")
    f0 = (fs - fs.mean()) / np.std(fs)
    lags = np.arange(0.0, max_latency + 0.5 * resolution, resolution)
    scores = np.empty_like(lags)
    for i, lag in enumerate(lags):
        x = np.interp(ft - lag, pt, ps)
        sd = np.std(x)
        scores[i] = float(np.mean((x - x.mean()) / sd * f0)) if sd > 0 else 0.0
    magnitude = np.abs(scores)
    k = int(np.argmax(magnitude))
    best = float(scores[k])
    if abs(best) < min_correlation:
        raise ValueError(
            f"estimate_video_latency: the image motion does not follow the probe motion "
            f"(best |correlation| {abs(best):.2f} < {min_correlation:g} at a lag of "
            f"{1e3 * lags[k]:.0f} ms): is the target found in every frame, and did the probe "
            f"move across the image plane?"
        )
    if k == len(lags) - 1 and len(lags) > 2:
        raise ValueError(
            f"estimate_video_latency: the best lag is at the end of the range "
            f"({max_latency:g} s): raise max_latency"
        )
    # Another local maximum almost as good, far from this one: a period too short.
    frame_gap = np.median(np.diff(ft)) if len(ft) > 1 else resolution
    for j in range(1, len(lags) - 1):
        if (
            abs(j - k) * resolution > 2 * frame_gap
            and magnitude[j] >= magnitude[j - 1]
            and magnitude[j] >= magnitude[j + 1]
            and magnitude[j] > magnitude[k] - 0.02
            and np.sign(scores[j]) == np.sign(best)
        ):
            raise ValueError(
                f"estimate_video_latency: ambiguous: lags {1e3 * lags[k]:.0f} ms and "
                f"{1e3 * lags[j]:.0f} ms fit equally well; use a motion period longer than "
                f"twice max_latency"
            )
    latency = float(lags[k])
    if 0 < k < len(lags) - 1:
        a, b, c = magnitude[k - 1], magnitude[k], magnitude[k + 1]
        denom = a - 2 * b + c
        if denom < 0:
            latency += float(np.clip(0.5 * (a - c) / denom, -0.5, 0.5) * resolution)
    return LatencyEstimate(latency, best, n, lags, scores)
