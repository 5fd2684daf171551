"""FrameGrabber: OpenCV video replay -> cropped grey us_image frames, stamped with the
diagram's time and the probe pose; clear errors for a missing file, a bad crop."""

import math

import numpy as np
import pytest
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator

from drake_rus.hardware.config import HardwareConfig
from drake_rus.hardware.systems import FrameGrabber

cv2 = pytest.importorskip("cv2", reason="opencv-python-headless is not installed")

SHAPE = (128, 96)       # rows, cols of the probe's image


def write_video(path, n, size=(200, 160), levels=None):
    w, h = size
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 20.0, (w, h))
    assert writer.isOpened()
    for k in range(n):
        picture = np.full((h, w, 3), 250, np.uint8)
        picture[10:150, 20:180] = levels[k] if levels else 30 + 10 * k
        writer.write(picture)
    writer.release()
    return path


def grabber(source, crop=(20, 10, 160, 140), loop=True, rate=20.0):
    cfg = HardwareConfig(video_source=str(source), video_crop=list(crop), video_loop=loop)
    return FrameGrabber(cfg, SHAPE, rate)


def test_replay_crop_stamp_and_loop(tmp_path):
    path = write_video(tmp_path / "v.avi", 5)
    g = grabber(path)
    sim = Simulator(g)
    ctx = sim.get_context()
    X = RigidTransform([0.5, 0.1, 0.2])
    g.get_input_port().FixValue(ctx, X)
    frames = []
    sim.Initialize()
    for k in range(8):
        sim.AdvanceTo(k * 0.05 + 1e-9)
        f = g.get_output_port().Eval(ctx)
        frames.append(f)
    for k, f in enumerate(frames):
        assert f.frame_index == k
        assert f.time == pytest.approx(0.05 * k, abs=1e-12)
        assert f.image.shape == SHAPE and f.image.dtype == np.uint8
        assert f.image.max() < 200                       # the 250 surround is cropped off
        assert abs(f.image.mean() - (30 + 10 * (k % 5))) < 6   # replay order, looped
        np.testing.assert_allclose(f.X_BP.translation(), X.translation())
    g.release()


def test_end_of_file_without_loop_keeps_the_last_frame(tmp_path):
    path = write_video(tmp_path / "v.avi", 2)
    g = grabber(path, loop=False)
    sim = Simulator(g)
    ctx = sim.get_context()
    g.get_input_port().FixValue(ctx, RigidTransform())
    sim.Initialize()
    sim.AdvanceTo(0.3)
    f = g.get_output_port().Eval(ctx)
    # The last frame keeps its stamp: it ages, and the safety layer's stale-image watchdog
    # stops the robot.
    assert f.frame_index == 1 and f.time == pytest.approx(0.05)
    assert g.grab_failures >= 4


def test_no_source_gives_unstamped_blank_frames():
    g = FrameGrabber(HardwareConfig(), SHAPE, 20.0)
    f = g.get_output_port().Eval(g.CreateDefaultContext())
    assert not f.valid and math.isnan(f.time) and f.image.shape == SHAPE


def test_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="video file not found: .*missing.avi"):
        grabber(tmp_path / "missing.avi")
    not_video = tmp_path / "notes.avi"
    not_video.write_text("not a video")
    with pytest.raises(ValueError, match="hardware_interface.video_source"):
        grabber(not_video)
    path = write_video(tmp_path / "v.avi", 2)
    with pytest.raises(ValueError, match="hardware_interface.video_crop.*200 x 160"):
        grabber(path, crop=(100, 10, 160, 140))
