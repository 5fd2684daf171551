"""FrameGrabber: the capture thread's newest picture -> cropped grey us_image frames,
stamped with the diagram time and the probe pose of the acquisition instant (capture time
minus video_latency); it never blocks the diagram; clear errors for a missing file or a bad
crop."""

import math
import time

import numpy as np
import pytest
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem

from drake_rus.hardware.config import HardwareConfig
from drake_rus.hardware.systems import FrameGrabber
from drake_rus.hardware.video import SyntheticVideo

cv2 = pytest.importorskip("cv2", reason="opencv-python-headless is not installed")

pytestmark = [pytest.mark.timeout(120), pytest.mark.wallclock]

SHAPE = (128, 96)  # rows, cols of the probe's image
RATE = 200.0  # the control rate the grabber ticks at


def write_video(path, n, size=(200, 160), levels=None, fps=20.0):
    w, h = size
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    assert writer.isOpened()
    for k in range(n):
        picture = np.full((h, w, 3), 250, np.uint8)
        picture[10:150, 20:180] = levels[k] if levels else 30 + 10 * k
        writer.write(picture)
    writer.release()
    return path


class MovingPose(LeafSystem):
    """X_BP = translation [t, 0, 0] at diagram time t."""

    def __init__(self):
        super().__init__()
        self.DeclareAbstractOutputPort(
            "X_BP",
            lambda: AbstractValue.Make(RigidTransform()),
            lambda c, o: o.set_value(RigidTransform([c.get_time(), 0.0, 0.0])),
        )


def rig(grabber):
    b = DiagramBuilder()
    b.AddSystem(grabber)
    pose = b.AddSystem(MovingPose())
    b.Connect(pose.get_output_port(), grabber.GetInputPort("X_BP"))
    sim = Simulator(b.Build())
    sim.set_target_realtime_rate(1.0)
    return sim, grabber.GetMyContextFromRoot(sim.get_context())


def run_and_collect(sim, grabber, ctx, duration, step=0.005, clock=None):
    """Advances ``sim`` in ``step``s to ``duration``; returns the frames seen (diagram time
    when first seen, UsFrame) and the longest step (wall s). ``clock`` (a list) gets
    (monotonic s, diagram s) after the start and after every step."""
    frames, worst_step = [], 0.0
    sim.Initialize()
    if clock is not None:
        clock.append((time.monotonic(), sim.get_context().get_time()))
    while sim.get_context().get_time() < duration:
        t0 = time.perf_counter()
        sim.AdvanceTo(sim.get_context().get_time() + step)
        worst_step = max(worst_step, time.perf_counter() - t0)
        if clock is not None:
            clock.append((time.monotonic(), sim.get_context().get_time()))
        f = grabber.get_output_port().Eval(ctx)
        if f.valid and (not frames or frames[-1][1].frame_index != f.frame_index):
            frames.append((sim.get_context().get_time(), f))
    return frames, worst_step


class TimedLog(list):
    """A list that also records the monotonic time of each append."""

    def __init__(self):
        super().__init__()
        self.times = []

    def append(self, item):
        self.times.append(time.monotonic())
        super().append(item)


def test_replay_crop_stamp_pose_and_loop(tmp_path):
    """The timing checks hold on a loaded machine too: they compare with this test's own
    record of the wall clock against diagram time, not with a fixed real-time rate."""
    path = write_video(tmp_path / "v.avi", 5)
    latency = 0.08
    cfg = HardwareConfig(
        video_source=str(path),
        video_crop=[20, 10, 160, 140],
        video_loop=True,
        video_latency=latency,
    )
    g = FrameGrabber(cfg, SHAPE, RATE)
    g.frame_log = TimedLog()  # (capture time, frame), and when the grabber emitted it
    published = {}  # capture time -> monotonic time the capture thread published it
    publish = g.capture._publish

    def timed_publish(picture, capture_time):
        publish(picture, capture_time)
        published[float(capture_time)] = time.monotonic()

    g.capture._publish = timed_publish  # from its next picture on
    clock = []
    try:
        sim, ctx = rig(g)
        frames, _ = run_and_collect(sim, g, ctx, 1.2, clock=clock)
        ticks = np.asarray(g.tick_times, float)  # monotonic start of each grabber tick
    finally:
        g.release()
    assert len(frames) >= 15  # 20 fps in real time
    indices = [f.frame_index for _, f in frames]
    assert indices == sorted(indices) and len(set(indices)) == len(indices)
    for t_seen, f in frames:
        assert f.image.shape == SHAPE and f.image.dtype == np.uint8
        assert f.image.max() < 200  # the 250 surround is cropped off
        assert abs(f.image.mean() - (30 + 10 * (f.frame_index % 5))) < 6  # file order, looped
        # The pose is the one of the frame's stamp.
        assert f.X_BP.translation()[0] == pytest.approx(f.time, abs=1e-9)
    # Stamped with the acquisition instant, latency before the capture: the diagram time at
    # monotonic time (capture - latency), bracketed within a step by this test's own records
    # (the ticks before a record's diagram time ran before its wall time, later ones after).
    mono, diag = np.array(clock).T
    step = diag[1] - diag[0]
    emitted = dict(zip((f.frame_index for _, f in g.frame_log), g.frame_log.times))
    checked = 0
    for capture_time, f in g.frame_log:
        instant = capture_time - latency
        before, after = mono <= instant, mono >= instant
        low = (diag[before].max() if before.any() else diag[0]) - step
        high = diag[after].min() + step if after.any() else math.inf
        assert low - 1e-9 <= f.time <= high + 1e-9, (f.frame_index, low, f.time, high)
        # Emitted promptly: at the latest by the first grabber tick that began after the
        # capture thread published the picture.
        if capture_time in published:
            p = published[capture_time]
            first_tick_after = ticks[ticks >= p].min()
            emitting_tick = ticks[ticks <= emitted[f.frame_index]].max()
            assert emitting_tick <= first_tick_after, (f.frame_index, emitting_tick - p)
            checked += 1
    assert len(g.frame_log) >= len(frames) and checked >= len(g.frame_log) - 3


def test_grabber_never_blocks_on_a_slow_source():
    """A source that delivers 4 pictures a second (its read() blocks 250 ms): the diagram's
    5 ms steps stay short, frames arrive as the source delivers them."""
    picture = np.full((60, 80, 3), 90, np.uint8)
    video = SyntheticVideo(lambda t: picture, frame_rate_hz=4.0)
    cfg = HardwareConfig()
    g = FrameGrabber(cfg, SHAPE, RATE, source=video)
    try:
        sim, ctx = rig(g)
        frames, worst = run_and_collect(sim, g, ctx, 1.1)
        stats = g.capture.stats()
    finally:
        g.release()
    assert 3 <= len(frames) <= 6
    assert worst < 0.1, f"a 5 ms step took {worst:.3f} s: the grabber blocked"
    assert stats.frames >= len(frames)
    gaps = g.tick_gaps()
    assert len(gaps) > 100 and np.median(gaps) == pytest.approx(1 / RATE, abs=2e-3)


def test_end_of_file_without_loop_keeps_the_last_frame(tmp_path):
    path = write_video(tmp_path / "v.avi", 2)
    cfg = HardwareConfig(video_source=str(path), video_crop=[20, 10, 160, 140], video_loop=False)
    g = FrameGrabber(cfg, SHAPE, RATE)
    try:
        sim, ctx = rig(g)
        frames, _ = run_and_collect(sim, g, ctx, 0.5)
        assert g.capture.stats().ended
    finally:
        g.release()
    # The last frame keeps its stamp: it ages, and the safety layer's stale-image watchdog
    # stops the robot. (Frame 0 may predate the pose history, which starts with the
    # simulation: then it is not used.)
    assert [f.frame_index for _, f in frames] in ([0, 1], [1])
    last = g.get_output_port().Eval(ctx)
    assert last.frame_index == 1 and sim.get_context().get_time() - last.time > 0.3


def test_no_source_gives_unstamped_blank_frames_and_still_records_poses():
    g = FrameGrabber(HardwareConfig(), SHAPE, RATE)
    sim, ctx = rig(g)
    sim.Initialize()
    sim.AdvanceTo(0.05)
    f = g.get_output_port().Eval(ctx)
    assert not f.valid and math.isnan(f.time) and f.image.shape == SHAPE
    assert len(g.history) >= 10 and len(g.clock) >= 10


def test_clear_errors(tmp_path):
    def make(source, crop=(20, 10, 160, 140)):
        return FrameGrabber(
            HardwareConfig(video_source=str(source), video_crop=list(crop)), SHAPE, RATE
        )

    with pytest.raises(ValueError, match="video file not found: .*missing.avi"):
        make(tmp_path / "missing.avi")
    not_video = tmp_path / "notes.avi"
    not_video.write_text("not a video")
    with pytest.raises(ValueError, match="hardware_interface.video_source"):
        make(not_video)
    path = write_video(tmp_path / "v.avi", 2)
    with pytest.raises(ValueError, match="hardware_interface.video_crop.*200 x 160"):
        make(path, crop=(100, 10, 160, 140))
    with pytest.raises(ValueError, match="unsupported URL scheme"):
        make("smb://server/share/v.avi")
