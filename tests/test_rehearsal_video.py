"""The rehearsal's simulated robot keeps its status rate whatever its pictures cost.

The physics thread only takes pose snapshots; the pictures are sliced, emulated and encoded
in a process of their own (drake_rus/rehearsal/video_process.py). Live tests on ``memq://``
with the real rehearsal diagram (test:0's station behind the driver's wire).
"""

from __future__ import annotations

import multiprocessing
import time
import urllib.request

import numpy as np
import pytest
from pydrake.lcm import DrakeLcm

from drake_rus.anatomy import load_patient
from drake_rus.rehearsal.core import await_ready, stall_causes
from drake_rus.rehearsal.sim import (
    BuildRehearsalSim,
    RehearsalSim,
    StatusPublisherThread,
    WireFaults,
)
from drake_rus.rehearsal.video_process import SliceEmulateRenderer, VideoProcess
from drake_rus.scan.run import PrepareScenario
from drake_rus.scenario import ApplyOverrides, LoadScenario
from drake_rus.station import MakeSimStation

pytestmark = pytest.mark.wallclock

RATE_HZ = 200.0
RENDER_S = 0.2  # the slow renderer's time per picture


class SlowRenderer:
    """A picture that takes ``seconds`` of busy Python (it holds its interpreter's lock
    throughout) and shows its frame index as its grey level."""

    def __init__(self, seconds: float, shape=(64, 48)):
        self.seconds, self.shape = float(seconds), shape

    def __call__(self, X_BP, X_BV, frame_index):
        end = time.perf_counter() + self.seconds
        while time.perf_counter() < end:
            pass
        return np.full(self.shape, (10 * int(frame_index)) % 250, np.uint8)


@pytest.fixture(scope="module")
def prepared():
    scenario = ApplyOverrides(LoadScenario(scenario_name="hardware"), "{hardware: false}", "test")
    patient = load_patient(
        "test:0", side=scenario.patient.side, posture=scenario.patient.posture, progress=False
    )
    scenario, _, _ = PrepareScenario(scenario, patient)
    return scenario, patient


def test_renderer_makes_the_stations_picture_at_the_same_pose(prepared):
    """The video process's picture of a pose is the station's own us_image there."""
    scenario, patient = prepared
    from pydrake.systems.analysis import Simulator

    station = MakeSimStation(scenario, patient=patient)
    sim = Simulator(station)
    sim.Initialize()  # the sensor's first frame (index 0) at the start pose
    context = station.GetMyContextFromRoot(sim.get_context())
    frame = station.GetOutputPort("us_image").Eval(context)
    sensor = station.GetSubsystemByName("slice_sensor")
    X_BV = sensor.volume_pose(sensor.GetMyContextFromRoot(sim.get_context()))
    assert frame.valid and frame.frame_index == 0
    renderer = SliceEmulateRenderer(scenario.imaging, patient.labels, scenario.random_seed)
    image = renderer(frame.X_BP.GetAsMatrix4(), X_BV.GetAsMatrix4(), frame.frame_index)
    assert image.shape == frame.image.shape
    np.testing.assert_array_equal(image, frame.image)
    # 3 cm deeper along the beam (P's z) the fan is in the patient: another picture.
    X = frame.X_BP.GetAsMatrix4().copy()
    X[:3, 3] += X[:3, 2] * 0.03
    deeper = renderer(X, X_BV.GetAsMatrix4(), 0)
    assert np.count_nonzero(deeper) > np.count_nonzero(image) + 1000


def test_a_slow_renderer_does_not_delay_the_robots_statuses(prepared):
    """Pictures taking 200 ms each: the physics keeps its ticks and the statuses their rate
    (>= 80 % of each over about 1 s), and every picture carries the wall time of the pose
    it was rendered from."""
    scenario, patient = prepared
    lcm = DrakeLcm("memq://")
    status = StatusPublisherThread(lcm, "PANDA_STATUS", 1.0 / RATE_HZ)
    video = VideoProcess(SlowRenderer(RENDER_S), frame_rate_hz=scenario.imaging.frame_rate_hz)
    offered = {}

    def on_pose(snapshot):
        offered[snapshot.frame_index] = snapshot
        video.offer(snapshot)

    try:
        diagram, station, wire = BuildRehearsalSim(
            scenario, patient, lcm, faults=WireFaults(), status_sink=status.offer
        )
        sim = RehearsalSim(
            diagram,
            station,
            wire,
            lcm,
            rate_hz=RATE_HZ,
            frame_period=1.0 / scenario.imaging.frame_rate_hz,
            status_thread=status,
            plant_period=scenario.contact.time_step,
            on_pose=on_pose,
        )
        sim.prime()
        # The stream serves the first picture (rendered from the start pose).
        with urllib.request.urlopen(video.url.replace("stream.mjpg", "frame.jpg"), timeout=10):
            pass
        t_start = time.monotonic()
        stats = sim.run(lambda: time.monotonic() - t_start >= 1.0)
        t_end = time.monotonic()
        status.close()
        sim.close()
    finally:
        status.close()
        video_stats = video.close()
    window = t_end - t_start
    expected = window * RATE_HZ
    # The physics kept its ticks, and the statuses went out at their rate meanwhile.
    assert stats.ticks >= 0.8 * expected, (stats.ticks, expected)
    sent = [t for t in status.times if t_start <= t <= t_end]
    assert len(sent) >= 0.8 * expected, (len(sent), expected, status.gaps_ms())
    # A picture's whole render time never showed as a status stall.
    assert stall_causes(sent, 0.5 * RENDER_S, {})["stalls"] == 0
    # A pose every frame period; the renderer took only the newest of those waiting.
    frames = 1 + window * scenario.imaging.frame_rate_hz
    assert sim.frames >= 0.8 * frames
    rendered = video_stats["rendered"]
    assert 2 <= len(rendered) <= 2 + window / RENDER_S
    assert video_stats["skipped"] >= 1
    assert min(video_stats["emulation_ms"]["p50"], video_stats["emulation_ms"]["max"]) >= (
        0.9e3 * RENDER_S
    )
    # Every picture is stamped with the wall time of the pose it was rendered from.
    for index, stamp in rendered:
        assert stamp == offered[index].stamp
    indices = [i for i, _ in rendered]
    assert indices == sorted(indices) and indices[0] == 0


def test_stall_causes_names_what_overlapped_each_gap():
    times = [0.000, 0.005, 0.010, 0.040, 0.045, 0.050, 0.100, 0.105]  # gaps 30 ms, 50 ms
    activities = {
        "gc": [(0.012, 0.013)],  # inside the first gap
        "picture": [(0.050, 0.055), (0.060, 0.080)],  # inside the second
        "tick": [(0.001, 0.004), (0.101, 0.104)],  # in no gap
    }
    report = stall_causes(times, 0.010, activities)
    assert report["stalls"] == 2
    assert report["by_cause"] == {"gc": 1, "picture": 1, "tick": 0, "none": 0}
    assert [w["gap_ms"] for w in report["worst"]] == [50.0, 30.0]
    assert report["worst"][0]["during"] == ["picture"]
    assert report["busy_fraction"]["picture"] == pytest.approx(0.025 / 0.105)
    assert stall_causes(times, 0.010, {})["by_cause"] == {"none": 2}
    assert stall_causes([1.0], 0.010, {"gc": []})["stalls"] == 0


def test_status_slot_hands_over_the_newest_status_with_its_send_time():
    import multiprocessing

    import drake

    from drake_rus.rehearsal.status_process import SlotWriter, read_slot, set_utime

    slot = multiprocessing.get_context("spawn").RawArray("B", 16 + 1024)
    assert read_slot(slot) is None  # nothing offered yet
    writer = SlotWriter(slot)
    for k in range(3):
        msg = drake.lcmt_panda_status()
        msg.utime, msg.num_joints = 5, 7
        msg.joint_position = [0.1 * k] * 7
        for name in (
            "joint_position_desired",
            "joint_velocity",
            "joint_velocity_desired",
            "joint_acceleration_desired",
            "joint_torque",
            "joint_torque_desired",
            "joint_torque_external",
        ):
            setattr(msg, name, [0.0] * 7)
        writer.write(msg.encode())
    got = drake.lcmt_panda_status.decode(set_utime(read_slot(slot), 1234567))
    assert got.utime == 1234567 and list(got.joint_position) == [0.2] * 7  # the newest
    with pytest.raises(ValueError, match="room for 1024"):
        writer.write(bytes(2000))


def _send_and_wait(conn, message, wait_s):
    if message is not None:
        conn.send(message)
    time.sleep(wait_s)


@pytest.mark.parametrize(
    "message, expected",
    [
        (("ready", 8123), None),
        (("error", "port in use"), "the probe process failed: port in use"),
        (None, "the probe process was not ready within 0.5 s"),
    ],
)
def test_await_ready_returns_the_value_or_stops_the_process(message, expected):
    """A helper process's handshake (the video and status processes share it): the value
    of its "ready", else the process is stopped and the error names it."""
    ctx = multiprocessing.get_context("spawn")
    parent, child = ctx.Pipe()
    process = ctx.Process(target=_send_and_wait, args=(child, message, 30.0), daemon=True)
    process.start()
    try:
        if expected is None:
            assert await_ready(process, parent, 30.0, "probe") == 8123
        else:
            with pytest.raises(RuntimeError, match=expected):
                await_ready(process, parent, 0.5 if message is None else 30.0, "probe")
            process.join(5.0)
            assert not process.is_alive()
    finally:
        if process.is_alive():
            process.terminate()
            process.join(2.0)
