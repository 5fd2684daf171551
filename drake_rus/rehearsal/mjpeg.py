"""The ultrasound machine's video output, emulated: an MJPEG stream over HTTP on 127.0.0.1.

:class:`MjpegServer` serves ``/stream.mjpg`` (``multipart/x-mixed-replace``, one JPEG per
part, what network video encoders and many capture boxes serve; OpenCV's
``VideoCapture("http://127.0.0.1:PORT/stream.mjpg")`` reads it) and ``/frame.jpg`` (the
current picture). Like a video output it sends at a fixed frame rate whether or not the
picture changed. Pictures are pushed by the simulation (:meth:`MjpegServer.push`) through a
:class:`FrameBuffer`, which can hold them back (a video delay) or stop taking new ones (a
frozen picture, as when the machine's freeze key is pressed: the stream keeps flowing).

It binds the loopback address only; every loop is bounded by the server's stop event.
"""

from __future__ import annotations

import collections
import http.server
import logging
import threading
import time

import numpy as np

from drake_rus.extras import require

LOG = logging.getLogger("drake_rus.rehearsal")

__all__ = ["FrameBuffer", "MjpegServer", "encode_jpeg", "BOUNDARY"]

BOUNDARY = "drakerusframe"


def encode_jpeg(image: np.ndarray, quality: int = 90) -> bytes:
    """JPEG bytes of a uint8 grey (rows, cols) or BGR picture (OpenCV)."""
    cv2 = require("cv2", "the rehearsal's video stream")
    ok, data = cv2.imencode(
        ".jpg", np.ascontiguousarray(image), [int(cv2.IMWRITE_JPEG_QUALITY), int(quality)]
    )
    if not ok:
        raise ValueError(f"encode_jpeg: OpenCV cannot encode a picture of shape {np.shape(image)}")
    return data.tobytes()


class FrameBuffer:
    """Pictures (JPEG bytes) with the wall-clock time (s, ``clock``) they were pushed.

    ``current(now)`` is the newest picture pushed at least ``delay`` s before ``now`` (the
    first one if none is that old yet: a delayed stream starts with its first picture);
    ``freeze()`` stops taking new pictures (the stream keeps showing the last). Thread-safe.
    """

    def __init__(self, delay: float = 0.0, clock=time.time):
        if not delay >= 0.0:
            raise ValueError(f"video delay: expected a non-negative time in s, got {delay}")
        self.delay = float(delay)
        self._clock = clock
        self._lock = threading.Lock()
        self._frames: collections.deque = collections.deque()  # (stamp, sequence, jpeg)
        self._sequence = 0
        self.frozen_at: float | None = None
        self.pushed = 0

    def push(self, jpeg: bytes, stamp: float | None = None) -> bool:
        """Adds a picture; False (ignored) once frozen."""
        stamp = self._clock() if stamp is None else float(stamp)
        with self._lock:
            if self.frozen_at is not None:
                return False
            self._sequence += 1
            self._frames.append((stamp, self._sequence, jpeg))
            self.pushed += 1
            # Keep what a delayed reader may still need, and the newest.
            while len(self._frames) > 1 and self._frames[1][0] <= stamp - self.delay - 1.0:
                self._frames.popleft()
        return True

    def freeze(self, stamp: float | None = None) -> None:
        with self._lock:
            if self.frozen_at is None:
                self.frozen_at = self._clock() if stamp is None else float(stamp)

    def current(self, now: float | None = None):
        """(sequence, jpeg) of the picture to show at ``now``, or None before the first."""
        now = self._clock() if now is None else float(now)
        with self._lock:
            if not self._frames:
                return None
            chosen = self._frames[0]
            for frame in self._frames:
                if frame[0] <= now - self.delay:
                    chosen = frame
                else:
                    break
            return chosen[1], chosen[2]


class MjpegServer:
    """An MJPEG-over-HTTP video output on ``host`` (127.0.0.1) at ``port`` (0: any free
    port; see ``port`` after construction), sending the buffer's picture every
    1 / ``frame_rate_hz`` s to each client. ``close()`` stops it (idempotent)."""

    def __init__(
        self,
        buffer: FrameBuffer,
        *,
        frame_rate_hz: float = 20.0,
        port: int = 0,
        host: str = "127.0.0.1",
        quality: int = 90,
    ):
        if host != "127.0.0.1":  # "localhost" may resolve to another address
            raise ValueError(
                f"MjpegServer: binds the loopback address 127.0.0.1 only, got {host!r}"
            )
        self.buffer = buffer
        self.quality = int(quality)
        self.period = 1.0 / float(frame_rate_hz)
        self.stop_event = threading.Event()
        self.sent = 0
        self.clients = 0
        server = self

        class Handler(http.server.BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.0"

            def log_message(self, fmt, *args):  # quiet
                LOG.debug("mjpeg %s: " + fmt, self.client_address, *args)

            def do_GET(self):
                path = self.path.split("?")[0]
                if path == "/stream.mjpg":
                    server._serve_stream(self)
                elif path == "/frame.jpg":
                    server._serve_frame(self)
                else:
                    self.send_error(404, "try /stream.mjpg or /frame.jpg")

        self._httpd = http.server.ThreadingHTTPServer((host, int(port)), Handler)
        self._httpd.daemon_threads = True
        self.host = host
        self.port = int(self._httpd.server_address[1])
        self._thread = threading.Thread(
            target=self._httpd.serve_forever,
            kwargs={"poll_interval": 0.1},
            name="drake_rus_mjpeg",
            daemon=True,
        )
        self._thread.start()

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}/stream.mjpg"

    def push(self, image: np.ndarray, stamp: float | None = None) -> bool:
        """Encodes and buffers a picture (grey uint8 or BGR); False once frozen."""
        if self.buffer.frozen_at is not None:
            return False
        return self.buffer.push(encode_jpeg(image, self.quality), stamp)

    def _wait_first(self, timeout: float = 10.0):
        deadline = time.monotonic() + timeout
        while not self.stop_event.is_set() and time.monotonic() < deadline:
            frame = self.buffer.current()
            if frame is not None:
                return frame
            self.stop_event.wait(0.01)
        return None

    def _serve_frame(self, handler) -> None:
        frame = self._wait_first()
        if frame is None:
            handler.send_error(503, "no picture yet")
            return
        handler.send_response(200)
        handler.send_header("Content-Type", "image/jpeg")
        handler.send_header("Content-Length", str(len(frame[1])))
        handler.end_headers()
        handler.wfile.write(frame[1])

    def _serve_stream(self, handler) -> None:
        if self._wait_first() is None:
            handler.send_error(503, "no picture yet")
            return
        handler.send_response(200)
        handler.send_header("Content-Type", f"multipart/x-mixed-replace; boundary={BOUNDARY}")
        handler.send_header("Cache-Control", "no-cache")
        handler.end_headers()
        self.clients += 1
        next_time = time.monotonic()
        try:
            while not self.stop_event.is_set():
                frame = self.buffer.current()
                data = frame[1]
                handler.wfile.write(
                    (
                        f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: "
                        f"{len(data)}\r\n\r\n"
                    ).encode()
                    + data
                    + b"\r\n"
                )
                handler.wfile.flush()
                self.sent += 1
                next_time += self.period
                delay = next_time - time.monotonic()
                if delay < -self.period:  # fell behind: do not burst
                    next_time = time.monotonic()
                elif delay > 0:
                    self.stop_event.wait(delay)
        except (BrokenPipeError, ConnectionResetError, ConnectionAbortedError, OSError):
            pass  # the client went away

    def close(self) -> None:
        if self.stop_event.is_set():
            return
        self.stop_event.set()
        try:
            self._httpd.shutdown()
        finally:
            self._httpd.server_close()
        self._thread.join(2.0)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False
