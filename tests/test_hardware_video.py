"""Video timing of the hardware station: source parsing, the capture thread (drains a live
source, paces a file, reads an MJPEG stream on 127.0.0.1), pose interpolation, the diagram
clock, and the video latency recovered from a synthetic source with a known latency."""

import http.server
import math
import socketserver
import threading
import time

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix

from drake_rus.hardware.video import (
    DiagramClock,
    FrameCapture,
    PoseHistory,
    SyntheticVideo,
    estimate_video_latency,
    interpolate_pose,
    monotonic_to_diagram_time,
    motion_signal,
    parse_video_source,
    quaternion_slerp,
)

cv2 = pytest.importorskip("cv2", reason="opencv-python-headless is not installed")

pytestmark = [pytest.mark.timeout(120), pytest.mark.wallclock]


# --- pure functions ----------------------------------------------------------------------
def test_parse_video_source(tmp_path):
    assert parse_video_source("0").kind == "device" and parse_video_source(" 2 ").value == 2
    url = parse_video_source("http://127.0.0.1:8080/stream.mjpg")
    assert url.kind == "url" and url.live
    assert parse_video_source("rtsp://10.0.0.5/live").kind == "url"
    f = tmp_path / "v.avi"
    f.write_bytes(b"x")
    assert parse_video_source(str(f)).kind == "file" and not parse_video_source(str(f)).live
    for bad, message in (
        ("ftp://host/v.mjpg", "unsupported URL scheme 'ftp'"),
        ("file:///tmp/v.avi", "unsupported URL scheme 'file'"),
        ("http:///stream", "names no host"),
        ("http://host:99999/x", "bad URL"),
        (str(tmp_path / "missing.avi"), "video file not found"),
        ("", "empty video source"),
        # A device path, present or not (a character device is no file): the index to give.
        ("/dev/video0", r"'/dev/video0' is a device path; give a capture device index \('0'"),
        ("/dev/video17", r"device path; give a capture device index \('17' for /dev/video17"),
        ("/dev/null", r"device path; give a capture device index \(N for /dev/videoN"),
    ):
        with pytest.raises(ValueError, match=f"hardware_interface.video_source.*{message}") as e:
            parse_video_source(bad)
        assert "\n" not in str(e.value)


def test_slerp_and_pose_interpolation():
    R0 = RotationMatrix()
    R1 = RotationMatrix.MakeZRotation(math.radians(90))
    q0 = R0.ToQuaternion().wxyz()
    q1 = R1.ToQuaternion().wxyz()
    half = quaternion_slerp(q0, q1, 0.5)
    from pydrake.common.eigen_geometry import Quaternion

    angle = RollPitchYaw(RotationMatrix(Quaternion(half))).yaw_angle()
    assert math.degrees(angle) == pytest.approx(45.0, abs=1e-9)
    # Shorter arc: q and -q are the same rotation.
    np.testing.assert_allclose(np.abs(quaternion_slerp(q0, -q1, 0.5)), np.abs(half), atol=1e-12)
    times = [0.0, 1.0]
    p = [[0, 0, 0], [1.0, 2.0, 3.0]]
    pp, qq, where = interpolate_pose(times, p, [q0, q1], 0.25)
    np.testing.assert_allclose(pp, [0.25, 0.5, 0.75])
    assert where == "inside"
    assert math.degrees(RollPitchYaw(RotationMatrix(Quaternion(qq))).yaw_angle()) == pytest.approx(
        22.5, abs=1e-9
    )
    assert interpolate_pose(times, p, [q0, q1], -1.0)[2] == "before"
    assert interpolate_pose(times, p, [q0, q1], 2.0)[2] == "after"
    np.testing.assert_allclose(interpolate_pose(times, p, [q0, q1], 2.0)[0], p[1])

    h = PoseHistory(duration=1.0, rate_hz=10.0)  # capacity 12
    assert h.pose_at(0.0)[1] == "empty"
    for k in range(30):  # wraps around
        t = 0.1 * k
        h.append(t, RigidTransform(RotationMatrix.MakeZRotation(0.1 * t), [t, 0, 0]))
    h.append(2.9, RigidTransform())  # not newer: ignored
    assert len(h) == 12
    lo, hi = h.span()
    assert lo == pytest.approx(1.8) and hi == pytest.approx(2.9)
    X, where = h.pose_at(2.345)
    assert where == "inside"
    assert X.translation()[0] == pytest.approx(2.345, abs=1e-9)
    assert RollPitchYaw(X.rotation()).yaw_angle() == pytest.approx(0.2345, abs=1e-7)
    assert h.pose_at(1.0)[1] == "before" and h.pose_at(5.0)[1] == "after"


def test_diagram_clock_mapping():
    mono = [10.0, 10.005, 10.5, 10.5005]  # a 0.5 s stall of our loop
    diag = [1.000, 1.005, 1.010, 1.015]
    assert monotonic_to_diagram_time(mono, diag, 10.0025) == pytest.approx(1.0025)
    assert monotonic_to_diagram_time(mono, diag, 10.25) == pytest.approx(
        1.005 + 0.005 * 0.245 / 0.495
    )
    assert monotonic_to_diagram_time(mono, diag, 9.9) == pytest.approx(0.9)  # slope 1
    assert monotonic_to_diagram_time(mono, diag, 10.6005) == pytest.approx(1.115)
    c = DiagramClock(duration=1.0, rate_hz=100.0)
    assert math.isnan(c.to_diagram(0.0))
    for k in range(500):
        c.record(0.01 * k, 100.0 + 0.01 * k)
    assert c.to_diagram(104.123) == pytest.approx(4.123)
    assert len(c) == 102


def _sinusoid(t, period=1.6, amplitude=0.01):
    return amplitude * np.sin(2 * np.pi * t / period)


def test_estimate_video_latency_on_synthetic_signals():
    rng = np.random.default_rng(0)
    latency = 0.0735
    pose_t = np.arange(0.0, 6.0, 0.005)
    poses = np.stack(
        [0.4 + _sinusoid(pose_t), np.full_like(pose_t, 0.1), np.full_like(pose_t, 0.2)], axis=1
    )
    frame_t = np.arange(0.6, 6.0, 1 / 30) + rng.uniform(0, 0.002, size=162)
    # The image moves against the probe, 2000 px/m, 0.3 px of detection noise; 5 % lost.
    signal = np.stack(
        [80.0 - 2000.0 * _sinusoid(frame_t - latency), 40.0 + rng.normal(0, 0.3, frame_t.size)],
        axis=1,
    )
    signal[:, 0] += rng.normal(0, 0.3, frame_t.size)
    signal[rng.random(frame_t.size) < 0.05] = np.nan
    est = estimate_video_latency(pose_t, poses, frame_t, signal)
    assert est.latency == pytest.approx(latency, abs=0.002)
    assert est.correlation < -0.99  # the image moves the other way
    # RigidTransforms and a 1-D signal work too.
    est2 = estimate_video_latency(pose_t, [RigidTransform(p) for p in poses], frame_t, signal[:, 0])
    assert est2.latency == pytest.approx(latency, abs=0.002)
    print(
        f"\n[latency] synthetic arrays: true {1e3 * latency:.1f} ms, estimated "
        f"{1e3 * est.latency:.2f} ms"
    )


def test_estimate_video_latency_refuses_bad_recordings():
    t = np.arange(0.0, 4.0, 0.005)
    ft = np.arange(0.6, 4.0, 1 / 30)
    moving = _sinusoid(t)
    with pytest.raises(ValueError, match="did not move during the frames"):
        estimate_video_latency(t, np.zeros_like(t), ft, _sinusoid(ft))
    with pytest.raises(ValueError, match="target did not move"):
        estimate_video_latency(t, moving, ft, np.ones_like(ft))
    with pytest.raises(ValueError, match="only 0 frames"):
        estimate_video_latency(t, moving, ft, np.full_like(ft, np.nan))
    noise = np.random.default_rng(1).normal(size=ft.size)
    with pytest.raises(ValueError, match="does not follow the probe motion"):
        estimate_video_latency(t, moving, ft, noise)
    fast = _sinusoid(t, period=0.3)  # repeats within max_latency: ambiguous
    with pytest.raises(ValueError, match="ambiguous|end of the range"):
        estimate_video_latency(t, fast, ft, _sinusoid(ft - 0.05, period=0.3))
    assert motion_signal(np.zeros((3, 2))).shape == (3,)


# --- the capture thread ------------------------------------------------------------------
def _dot_picture(col, row=40.0, shape=(96, 160)):
    rr, cc = np.mgrid[0 : shape[0], 0 : shape[1]]
    img = 20 + 220 * np.exp(-((cc - col) ** 2 + (rr - row) ** 2) / (2 * 2.5**2))
    return np.repeat(img.astype(np.uint8)[:, :, None], 3, axis=2)


def test_capture_thread_drains_a_live_source_and_never_blocks():
    """A source delivering at 30 fps; the reader looks only every 0.2 s and always gets the
    newest picture (never a stale, queued one), without waiting."""
    video = SyntheticVideo(lambda t: _dot_picture(20 + 100 * ((t * 10) % 1.0)), 30.0)
    cap = FrameCapture(video, process=lambda p: p[:, :, 0].copy())
    try:
        first = cap.wait_for(-1, timeout=2.0)
        assert first is not None and first.image.shape == (96, 160)
        for _ in range(3):
            time.sleep(0.2)
            t0 = time.perf_counter()
            f = cap.latest()
            assert time.perf_counter() - t0 < 0.01  # no blocking on the source
            assert time.monotonic() - f.capture_time < 0.1  # the newest, not a queued one
        stats = cap.stats()
        assert stats.frames >= 15 and 20.0 < stats.frame_rate_hz < 36.0
        assert f.counter == stats.frames - 1 or f.counter == stats.frames - 2
    finally:
        cap.close()
    assert not cap.stats().running


def test_first_picture_is_stamped_when_read_returned_not_after_processing():
    """The constructor reads and processes the first picture; its capture time is when
    read() returned, not after the processing (which can take a while: the map to the probe
    grid is built on the first picture)."""
    now = [100.0]

    class OnePicture:
        def __init__(self):
            self.reads = 0

        def read(self):
            self.reads += 1
            if self.reads > 1:
                time.sleep(0.01)
                return False, None
            return True, np.zeros((8, 8), np.uint8)

        def release(self):
            pass

    def slow_process(picture):
        now[0] += 5.0  # the processing takes 5 s on the fake clock
        return picture

    cap = FrameCapture(OnePicture(), process=slow_process, clock=lambda: now[0])
    try:
        first = cap.wait_for(-1, timeout=2.0)
        assert first is not None and first.counter == 0
        assert first.capture_time == 100.0
    finally:
        cap.close()


def test_capture_thread_replays_a_file_at_its_own_rate(tmp_path):
    path = tmp_path / "v.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (64, 48))
    for k in range(10):
        writer.write(np.full((48, 64, 3), 20 * k, np.uint8))
    writer.release()
    cap = FrameCapture(str(path), process=lambda p: p[:, :, 0].copy(), loop=True)
    try:
        assert cap.file_fps == pytest.approx(25.0)
        seen = []
        f = cap.wait_for(-1, 2.0)
        while f is not None and len(seen) < 15:
            seen.append(f)
            f = cap.wait_for(f.counter, 2.0)
        times = np.array([x.capture_time for x in seen])
        assert np.median(np.diff(times)) == pytest.approx(0.04, abs=0.01)  # real time
        levels = [int(round(x.image.mean() / 20)) for x in seen]
        assert levels == [(x.counter % 10) for x in seen]  # looped, in order
    finally:
        cap.close()
    once = FrameCapture(str(path), process=lambda p: p[:, :, 0].copy(), loop=False)
    try:
        deadline = time.monotonic() + 3.0
        while not once.stats().ended and time.monotonic() < deadline:
            time.sleep(0.02)
        assert once.stats().ended and once.latest().counter == 9
    finally:
        once.close()


class _Mjpeg(socketserver.ThreadingMixIn, http.server.HTTPServer):
    daemon_threads = True


def _mjpeg_server(fps=25.0, lifetime=20.0):
    """An MJPEG stream on 127.0.0.1 (an ephemeral port); it stops by itself after
    ``lifetime`` s or when ``stop`` is set."""
    stop = threading.Event()

    class Handler(http.server.BaseHTTPRequestHandler):
        def log_message(self, *args):
            pass

        def do_GET(self):
            self.send_response(200)
            self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
            self.end_headers()
            k, start = 0, time.monotonic()
            try:
                while not stop.is_set() and time.monotonic() - start < lifetime:
                    ok, jpg = cv2.imencode(".jpg", _dot_picture(10 + (k * 7) % 140))
                    data = jpg.tobytes()
                    self.wfile.write(
                        b"--frame\r\nContent-Type: image/jpeg\r\n"
                        b"Content-Length: %d\r\n\r\n" % len(data) + data + b"\r\n"
                    )
                    k += 1
                    stop.wait(max(0.0, start + k / fps - time.monotonic()))
            except (BrokenPipeError, ConnectionResetError):
                pass

    server = _Mjpeg(("127.0.0.1", 0), Handler)
    thread = threading.Thread(
        target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True
    )
    thread.start()
    timer = threading.Timer(lifetime, stop.set)
    timer.daemon = True
    timer.start()

    def shutdown():
        stop.set()
        timer.cancel()
        server.shutdown()
        server.server_close()

    return f"http://127.0.0.1:{server.server_address[1]}/stream.mjpg", shutdown


def test_capture_thread_reads_an_mjpeg_stream_on_loopback():
    url, shutdown = _mjpeg_server()
    try:
        cap = FrameCapture(url, process=lambda p: p[:, :, 0].copy())
        try:
            f = cap.wait_for(-1, 5.0)
            assert f is not None and f.image.shape == (96, 160)
            time.sleep(0.6)
            stats = cap.stats()
            assert stats.frames >= 10 and stats.frame_rate_hz > 15.0
            assert stats.age < 0.2
        finally:
            cap.close()
    finally:
        shutdown()


def test_latency_recovered_from_a_synthetic_source():
    """A dot whose column follows a known probe motion, delivered by a 30 fps source whose
    pictures show the scene LATENCY s late; the poses are sampled at 200 Hz on the same
    clock. The estimate recovers LATENCY within one frame period."""
    latency, fps, period = 0.12, 30.0, 1.2
    t0 = time.monotonic()

    def probe_x(t):  # the probe's position (m) at monotonic time t
        return 0.01 * math.sin(2 * math.pi * (t - t0) / period)

    video = SyntheticVideo(lambda t: _dot_picture(80 - 3000 * probe_x(t)), fps, latency)
    cap = FrameCapture(video, process=lambda p: p[:, :, 0].copy())
    frames, pose_t, poses = [], [], []
    try:
        last = -1
        end = time.monotonic() + 2.5 * period
        while time.monotonic() < end:
            now = time.monotonic()
            pose_t.append(now)
            poses.append(probe_x(now))
            f = cap.latest()
            if f is not None and f.counter > last:
                frames.append(f)
                last = f.counter
            time.sleep(0.005)
    finally:
        cap.close()
    from drake_rus.hardware.image_calibration import find_point_target

    targets = np.array([find_point_target(f.image) for f in frames], float)
    est = estimate_video_latency(pose_t, poses, [f.capture_time for f in frames], targets)
    error = abs(est.latency - latency)
    print(
        f"\n[latency] synthetic source at {fps:g} fps: true {1e3 * latency:.0f} ms, "
        f"estimated {1e3 * est.latency:.1f} ms (error {1e3 * error:.1f} ms, "
        f"{est.frames} frames, correlation {est.correlation:+.3f})"
    )
    assert error < 1.0 / fps
