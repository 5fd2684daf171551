"""Software-in-the-loop rehearsal: the unchanged hardware scan against the simulated robot,
patient and ultrasound machine in another process, over drake-franka-driver's LCM messages
and an MJPEG stream (drake_rus/rehearsal).

The slow tests run inside a private network namespace (``unshare -n``, loopback only,
multicast routed over it): nothing leaves the host. They skip, saying why, only when
``unshare`` is not permitted.

They rehearse the shipped ``hardware`` scenario (its watchdogs, the kidney-length estimate
on, no raised priority), made shorter by the ``quick`` scenario's two differences, and
compare with the same scan in this process on the simulated station. The scan's perception
runs beside its control loop (drake_rus/executor.py), and the simulated robot publishes its
statuses from a process of their own; still, on a shared 2-core CI machine the two
load-sensitive watchdogs (real-time lag, image age) get 1 s (``OVERRIDES``).
"""

import json
import math
import os
import shutil
import subprocess
import sys
import threading
import time

import drake
import numpy as np
import pytest
from pydrake.lcm import DrakeLcm
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.systems.analysis import Simulator

from drake_rus.anatomy import load_patient
from drake_rus.hardware.lcm_sim_driver import DRIVER_EXPIRE_SEC, CommandExpiry, SimulatedPandaDriver
from drake_rus.localization.localize import load_registration_template
from drake_rus.rehearsal.core import (
    NETNS_SETUP,
    PivotDetector,
    age_statistics,
    kidney_errors,
    netns_argv,
    pose_from_json,
    pose_to_json,
    scan_overrides,
    stop_reaction,
)
from drake_rus.rehearsal.drill import merge_overrides, sim_lateness
from drake_rus.rehearsal.mjpeg import FrameBuffer, MjpegServer
from drake_rus.rehearsal.run import CpuLoad
from drake_rus.rehearsal.sim import WireFaults
from drake_rus.rehearsal.sim_process import sequence_gaps
from drake_rus.scan import RunScan, ScanMetrics, Summary
from drake_rus.scenario import LoadScenario

# realtime_lag 1 s, as in tests/test_realtime.py: on a slower 2-core CI machine (an AMD
# EPYC without VNNI, 2026-11-28) the rehearsal's own three processes let the loop's slips add
# up to 0.26 s within a second, past the default 0.25 s, on the last stop's head as well;
# the overload stop itself is tested in tests/test_scan_realtime.py. image_timeout 1 s for the
# same reason: on the CI machine (2026-11-29) the segmentation worker fell 0.351 s behind the
# video in EXPLORE (the `hardware` scenario's limit is 0.35 s) and the SIGTERM drill stopped
# before its signal; that stop is tested in tests/test_realtime.py and
# tests/test_control_safety.py. state_timeout 1 s for the same reason: on a CI machine
# (2026-11-29, its `make test` 14% slower than ours) the simulated robot's process, sharing
# 2 cores with the scan, its segmentation worker and the video process, published the same
# joint positions for 0.15 s in EXPLORE (the `hardware` scenario's limit) and the drill
# stopped before its signal; the simulator's lateness, not the robot's. The stale-state stop
# is tested in tests/test_control_safety.py and tests/test_control_station.py.
OVERRIDES = (
    "{controller: {exploration_ratio: 0.5, pivot_rate: 0.2},"
    " safety: {realtime_lag: 1.0, image_timeout: 1.0, state_timeout: 1.0}}"
)
PATIENT = "test:0"
SCENARIO = "hardware"

pytestmark = [pytest.mark.timeout(600), pytest.mark.wallclock]


# --- fast: pieces -------------------------------------------------------------------------
def test_frame_buffer_delay_and_freeze():
    now = [100.0]
    buf = FrameBuffer(delay=0.1, clock=lambda: now[0])
    assert buf.current() is None
    buf.push(b"a", 100.0)
    buf.push(b"b", 100.05)
    assert buf.current(100.05)[1] == b"a"  # nothing old enough yet: the first
    assert buf.current(100.16)[1] == b"b"
    buf.freeze(100.2)
    assert not buf.push(b"c", 100.3)
    assert buf.current(101.0)[1] == b"b"  # frozen: the last picture, forever
    with pytest.raises(ValueError):
        FrameBuffer(delay=-1)


def test_mjpeg_stream_reads_in_opencv():
    cv2 = pytest.importorskip("cv2")
    buf = FrameBuffer()
    with MjpegServer(buf, frame_rate_hz=20.0) as server:
        assert server.url.startswith("http://127.0.0.1:")
        image = np.zeros((96, 128), np.uint8)
        image[20:40, 30:60] = 200
        server.push(image)
        cap = cv2.VideoCapture(server.url, cv2.CAP_FFMPEG)
        try:
            assert cap.isOpened()
            # 21 frames: FFmpeg's probe on opening may have buffered a few that then read at
            # once (6 frames once read at 43 Hz on a busy machine); over 20 intervals that
            # shows as less than half the pace.
            times = []
            for _ in range(21):
                ok, picture = cap.read()
                assert ok
                times.append(time.monotonic())
            assert picture.shape[:2] == (96, 128)
            grey = picture[:, :, 0].astype(int)
            assert abs(grey[30, 45] - 200) < 8 and grey[80, 100] < 8  # JPEG, lossy
        finally:
            cap.release()
        assert 12.0 < 20 / (times[-1] - times[0]) < 40.0  # paced near 20 Hz
    with pytest.raises(ValueError, match="loopback"):
        MjpegServer(FrameBuffer(), host="0.0.0.0")


def test_command_expiry_latency():
    """A command reaches the robot ``latency`` s after it arrived; a fresh command stays
    in force until it is older than the expiry."""
    import pydrake.systems.lcm as lcm_systems

    ser = lcm_systems._Serializer_[drake.lcmt_panda_command]()
    expiry = CommandExpiry(expiry=0.3, latency=0.05)
    ctx = expiry.CreateDefaultContext()
    msg = drake.lcmt_panda_command()
    msg.utime = int(time.time() * 1e6)
    msg.control_mode_expected = 2
    msg.num_joint_velocity = 7
    msg.joint_velocity = [0.1] * 7
    value = ser.CreateDefaultValue()
    ser.Deserialize(msg.encode(), value)
    expiry.get_input_port().FixValue(ctx, value)

    def out(t):
        ctx.SetTime(t)  # a new time: the output is recomputed
        raw = ser.Serialize(expiry.get_output_port().EvalAbstract(ctx))
        return drake.lcmt_panda_command.decode(raw).joint_velocity

    assert out(0.001) == tuple([0.0] * 7)  # arrived, not yet at the robot
    time.sleep(0.06)
    assert out(0.002) == tuple([0.1] * 7)
    assert len(expiry.received) == 1 and len(expiry.log) == 1
    assert expiry.log[0][0] - expiry.received[0][0] >= 0.05
    assert DRIVER_EXPIRE_SEC == 0.1


def test_simulated_driver_drops_statuses():
    lcm = DrakeLcm("memq://")
    got = []
    lcm.Subscribe("PANDA_STATUS", lambda data: got.append(data))
    driver = SimulatedPandaDriver(lcm, np.zeros(7), status_drop_probability=0.5, seed=3)
    sim = Simulator(driver)
    sim.Initialize()
    sim.AdvanceTo(1.0)
    lcm.HandleSubscriptions(0)
    pub = driver.publisher
    assert pub.published + pub.dropped == 201
    assert 60 < pub.dropped < 140
    assert len(got) >= 1  # memq keeps the newest: at least one arrived


def test_pure_helpers():
    stats = age_statistics([0.001, 0.002, 0.003, math.nan])
    assert stats["count"] == 3 and stats["median_ms"] == pytest.approx(2.0)
    assert stats["max_ms"] == pytest.approx(3.0)
    assert age_statistics([])["median_ms"] is None
    # A stop at t = 10: commands until 9.99, zeros from 10.004; speeds decay.
    commands = [(9.98, 0.2), (9.99, 0.2), (10.004, 0.0), (10.005, 0.0)]
    speeds = [
        (9.995, 0.2, 0.2),
        (10.005, 0.1, 0.0),
        (10.01, 0.005, 0.0),
        (10.05, 0.0005, 0.0),
        (10.06, 0.0002, 0.0),
    ]
    r = stop_reaction(10.0, commands, speeds)
    assert r["last_moving_command"] == pytest.approx(-0.01)
    assert r["first_zero_command"] == pytest.approx(0.004)
    assert r["command_zero"] == pytest.approx(0.005)
    assert r["at_rest"]["0.01"] == pytest.approx(0.01)
    assert r["at_rest"]["0.001"] == pytest.approx(0.05)
    assert r["speed_at_signal"] == pytest.approx(0.2)
    # PIVOT-like: the tip still, turning at 0.2 rad/s, in contact.
    det = PivotDetector()
    for k in range(60):
        t = 0.02 * k
        X = RigidTransform(RollPitchYaw(0.2 * t, 0, 0), [0.5, 0.0, 0.1])
        held = det.update(t, X, 9.0)
    assert held == pytest.approx(1.18, abs=0.03)  # since its first window began
    assert det.update(1.2, RigidTransform([0.5, 0.01, 0.1]), 9.0) == 0.0  # slid: not
    # Sequence gaps per sender.
    arrivals = [(0, 0, 0, "a", 1), (0, 0, 0, "a", 2), (0, 0, 0, "a", 5), (0, 0, 0, "b", 9)]
    assert sequence_gaps(arrivals) == 2
    assert sequence_gaps([(0, 0, 0, "", -1)]) is None
    # The scan side's overrides and merging.
    ready = {
        "lcm_url": "udpm://239.255.76.67:7667?ttl=0",
        "command_channel": "PANDA_COMMAND",
        "status_channel": "PANDA_STATUS",
        "video_url": "http://127.0.0.1:1/stream.mjpg",
        "depth": 0.16,
    }
    o = json.loads(scan_overrides(ready))
    assert o["hardware"] is True and o["imaging"]["depth"] == 0.16
    assert o["hardware_interface"]["backend"] == "lcm"
    assert o["hardware_interface"]["dry_run"] is False
    merged = json.loads(merge_overrides(OVERRIDES, scan_overrides(ready)))
    assert merged["controller"]["pivot_rate"] == 0.2 and merged["hardware"] is True
    X = RigidTransform(RollPitchYaw(0.1, 0.2, 0.3), [0.5, 0.1, 0.2])
    assert pose_from_json(json.loads(json.dumps(pose_to_json(X)))).IsNearlyEqualTo(X, 1e-12)
    e = kidney_errors(RigidTransform([0.503, 0.104, 0.3]), RigidTransform([0.5, 0.1, 0.2]))
    assert e["e_trans_mm"] == pytest.approx(5.0) and e["e_rot_x_deg"] == pytest.approx(0.0)
    with pytest.raises(ValueError):
        WireFaults(status_drop=2.0)
    argv = netns_argv(["python", "-c", "pass"])
    assert argv[:3] == ["unshare", "-n", "bash"] and NETNS_SETUP in argv[4]


# --- slow: end to end in a private network namespace --------------------------------------
def _netns_problem():
    """None if ``unshare -n`` works here, else why not."""
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return "unshare or ip not found"
    try:
        r = subprocess.run(
            ["unshare", "-n", "bash", "-c", NETNS_SETUP], capture_output=True, timeout=30
        )
    except (OSError, subprocess.TimeoutExpired) as e:
        return f"unshare -n failed: {e}"
    if r.returncode != 0:
        return f"unshare -n not permitted: {r.stderr.decode(errors='replace').strip()}"
    return None


def run_isolated(argv, log_path, timeout):
    """``argv`` in a private network namespace (its own session), output to ``log_path``;
    killed after ``timeout`` s (its simulated robot then stops by itself)."""
    problem = _netns_problem()
    if problem:
        pytest.skip(problem)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    with open(log_path, "wb") as log:
        p = subprocess.Popen(
            netns_argv(argv),
            stdout=log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
            env=env,
        )
        try:
            code = p.wait(timeout)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(10)
            raise AssertionError(
                f"{argv[:4]} did not finish in {timeout} s:\n"
                f"{log_path.read_text(errors='replace')[-3000:]}"
            )
    return code, log_path.read_text(errors="replace")


def skip_if_overloaded_by_others(report):
    """A machine that other jobs load beyond twice its CPUs cannot run the rehearsal at real
    time, and the scan must then stop, at zero velocity, naming the overload: that is checked
    and the rest skipped. On a machine that is not (the rehearsal's own processes load 2
    CPUs about 2) an overload stop fails the test like any other."""
    reason = report.get("reason") or ""
    loop = (report.get("realtime") or {}).get("scan", {}).get("loop") or {}
    load = loop.get("load_average") or {}
    if report.get("status") != "ABORT" or "the computer is overloaded" not in reason:
        return
    if not load.get("1min", 0.0) > 2.0 * (load.get("cpus") or 1):
        return
    assert np.abs(report["joint_velocity_end_at_sim"]).max() < 1e-3, reason  # at rest
    pytest.skip(
        f"machine overloaded by other jobs (load average {load['1min']:.1f} on "
        f"{load['cpus']} CPUs): the scan stopped at zero velocity naming it ({reason[:90]})"
    )


@pytest.mark.slow
def test_rehearsal_end_to_end(tmp_path):
    out = tmp_path / "rehearsal"
    t0 = time.monotonic()
    code, text = run_isolated(
        [
            sys.executable,
            "-m",
            "drake_rus.cli",
            "rehearse",
            "--patient",
            PATIENT,
            "--scenario",
            SCENARIO,
            "--set",
            OVERRIDES,
            "--out",
            str(out),
            # 90 s: a scan that doubts its pivot takes a second, whole-kidney look (38.6 s
            # of EXPLORE on a loaded CI machine, 2026-11-29) and still ends DONE.
            "--max-sim-time",
            "90",
        ],
        tmp_path / "rehearse.log",
        timeout=300,
    )
    wall_rehearsal = time.monotonic() - t0
    report = json.loads((out / "rehearsal.json").read_text())
    skip_if_overloaded_by_others(report)
    assert code == 0 and report["status"] == "DONE", (report.get("reason"), text[-3000:])
    assert report["network_isolated"]
    for name in ("summary.json", "sim_log.json", "partial_cloud.ply", "registration.png"):
        assert (out / name).stat().st_size > 0, name
    # The sim side logged every command's age: no gap in the scan's LCM sequence numbers,
    # one age per command, the scan's final zero commands among them.
    cmd = report["commands_at_sim"]
    assert cmd["sequence_gaps"] == 0 and len(cmd["senders"]) == 1
    assert cmd["count"] == cmd["age_ms"]["count"]
    sim_s = report["realtime"]["scan"]["sim_s"]
    assert cmd["count"] >= 0.9 * sim_s * 100  # >= the 100 Hz controller rate
    log = json.loads((out / "sim_log.json").read_text())
    assert [a[2] for a in log["arrival_trace"][-3:]] == [0.0, 0.0, 0.0]
    assert cmd["age_ms"]["max_ms"] < 1e3 * DRIVER_EXPIRE_SEC  # fresh on arrival
    assert np.abs(report["joint_velocity_end_at_sim"]).max() < 1e-3
    # The loop's timing and where perception ran, recorded for every live run.
    loop = report["realtime"]["scan"]["loop"]
    assert loop["ticks"] >= 0.9 * sim_s / (loop["tick_ms"] * 1e-3)
    assert loop["compute_ms"]["p50"] is not None and loop["lag_ms"]["max"] is not None
    assert report["realtime"]["scan"]["perception"]["execution"] == "worker"
    assert report["realtime"]["scan"]["perception"]["jobs"]["length_fit"]["count"] >= 1
    assert report["status_packets"]["gaps_ms"]["p50"] is not None
    assert (out / "loop_timing.png").stat().st_size > 0
    # The same patient's scan in this process on the simulated station, same scenario (and
    # so the same start plan and depth preset).
    scenario = LoadScenario(
        scenario_name=SCENARIO, scenario_text=merge_overrides(OVERRIDES, "{hardware: false}")
    )
    patient = load_patient(
        PATIENT, side=scenario.patient.side, posture=scenario.patient.posture, progress=False
    )
    template = load_registration_template(scenario.localization.template)
    t1 = time.monotonic()
    result = RunScan(scenario, patient, template, max_sim_time=60.0, progress=False)
    wall_inprocess = time.monotonic() - t1
    summary = Summary(result, ScanMetrics(result))
    assert summary["status"] == "DONE", summary["reason"]
    assert summary["image_depth_m"] == pytest.approx(report["depth"])
    assert abs(report["e_trans_mm"] - summary["e_trans_mm"]) <= 3.0, (
        report["e_trans_mm"],
        summary["e_trans_mm"],
    )
    rt = report["realtime"]
    print(
        f"\n[rehearsal] E_trans {report['e_trans_mm']:.2f} mm (in-process "
        f"{summary['e_trans_mm']:.2f} mm), E_rot,x {report['e_rot_x_deg']:.2f} deg "
        f"(in-process {summary['e_rot_x_deg']:.2f} deg); {cmd['count']} commands, age at "
        f"the driver median {cmd['age_ms']['median_ms']:.3f} ms max "
        f"{cmd['age_ms']['max_ms']:.2f} ms, at the robot (next tick) median "
        f"{cmd['age_at_robot_ms']['median_ms']:.2f} ms max "
        f"{cmd['age_at_robot_ms']['max_ms']:.2f} ms; real-time margin: scan "
        f"{rt['scan']['margin']:.2f}x per CPU s (max lag {1e3 * rt['scan']['max_lag_s']:.0f}"
        f" ms, p99 {loop['lag_ms']['p99']:.1f} ms, compute p99 {loop['compute_ms']['p99']:.1f}"
        f" ms), sim {rt['sim']['cpu_margin']:.2f}x per CPU s, {rt['sim']['margin']:.2f}x "
        f"when running (max lag {1e3 * rt['sim']['max_lag_s']:.0f} ms, late ticks "
        f"{rt['sim']['late_ticks']}/{rt['sim']['ticks']}); true force peak "
        f"{report['force_true_peak_n']:.2f} N (estimated {report['force_estimated_peak_n']:.2f}"
        f" N); wall: rehearsal {wall_rehearsal:.0f} s, in-process scan {wall_inprocess:.0f} s"
    )


@pytest.mark.slow
def test_sigterm_mid_pivot_stops_the_robot_within_100_ms(tmp_path):
    out = tmp_path / "drill"
    t0 = time.monotonic()
    code, text = run_isolated(
        [
            sys.executable,
            "-m",
            "drake_rus.rehearsal.drill",
            "--out",
            str(out),
            "--patient",
            PATIENT,
            "--scenario",
            SCENARIO,
            "--set",
            OVERRIDES,
            "--pivot-after",
            "1.0",
        ],
        tmp_path / "drill.log",
        timeout=300,
    )
    wall = time.monotonic() - t0
    if code != 0 and "the computer is overloaded" in text:
        # The scan stopped by itself before the signal: only a machine loaded by other jobs
        # excuses it (see skip_if_overloaded_by_others), and then at zero velocity.
        load, cpus = os.getloadavg()[0], os.cpu_count() or 1
        if load > 2.0 * cpus:
            assert "zero velocity" in text, text[-3000:]  # the session stopped the robot
            pytest.skip(
                f"machine overloaded by other jobs (load average {load:.1f} on {cpus} "
                "CPUs): the scan stopped at zero velocity naming it before the signal"
            )
    assert code == 0, text[-3000:]
    report = json.loads((out / "stop_drill.json").read_text())
    assert report["network_isolated"]
    assert report["live_at_signal"]["pivot_like_s"] >= 1.0  # signalled mid-PIVOT
    assert report["live_at_signal"]["force_true_n"] > 2.0  # in contact
    r = report["reaction_s"]
    assert r["speed_at_signal"] > 0.05  # the robot was moving
    assert r["first_zero_command"] is not None and r["first_zero_command"] < 0.1
    assert r["command_zero"] is not None and r["command_zero"] < 0.1
    # The scan's stop reaches the robot within 100 ms (the two lines above). The robot at
    # rest is the simulated robot's own braking, judged in its own time: its velocity loop
    # brings 0.25 rad/s below 0.01 rad/s in 78-86 ms on an idle machine, and wall time lost
    # by its real-time loop (max_lag_s, up to ~30 ms on a busy 2-core PC) is the simulator's
    # lateness, not the product's.
    sim_lag = report["realtime_sim"]["max_lag_s"]
    assert r["at_rest"]["0.01"] is not None and r["at_rest"]["0.01"] < 0.1 + sim_lag
    assert np.abs(report["joint_velocity_end_at_sim"]).max() < 1e-3
    scan_log = (out / "scan.out").read_text(errors="replace")
    assert "zero velocity" in scan_log  # the session's stop

    def ms(x):
        return "never" if x is None else f"{1e3 * x:.1f} ms"

    print(
        f"\n[stop drill] SIGTERM at scan time {report['scan_time_at_signal_s']:.2f} s, "
        f"PIVOT-like for {report['live_at_signal']['pivot_like_s']:.2f} s, joints at "
        f"{r['speed_at_signal']:.3f} rad/s; last moving command "
        f"{ms(r['last_moving_command'])}, first zero command {ms(r['first_zero_command'])},"
        f" applied command zero {ms(r['command_zero'])}, |v| < 0.01 rad/s "
        f"{ms(r['at_rest']['0.01'])}, |v| < 0.001 rad/s {ms(r['at_rest']['0.001'])} after "
        f"the signal (simulated robot's max lag {ms(sim_lag)}); scan exit code "
        f"{report['scan_exit_code']}; wall {wall:.0f} s"
    )


def test_a_scan_that_ends_early_names_how_late_the_simulated_robot_ran():
    log = {"realtime": {"max_lag_s": 0.162}, "status": {"gaps_ms": {"max": 171.4}}}
    assert sim_lateness(log) == (
        "the simulated robot's process fell at most 162 ms behind the wall clock; "
        "its statuses came at most 171 ms apart"
    )
    assert "unknown" in sim_lateness({"realtime": {}, "status": {}})
    assert sim_lateness(None) == "the simulated robot wrote no log"


def test_stop_drill_refuses_a_bad_override_in_one_line_and_writes_nothing(tmp_path, capsys):
    from drake_rus.rehearsal import drill

    out = tmp_path / "drill"
    code = drill.main(["--out", str(out), "--set", "{safety: {force_ceiling: 1.0}}"])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("stop drill: error: ") and "safety.force_ceiling = 1" in err, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_threads_do_not_leak():
    """The fast tests leave no rehearsal thread behind (servers closed)."""
    names = [t.name for t in threading.enumerate()]
    assert not any(n.startswith("drake_rus_mjpeg") for n in names), names


def test_cpu_load_spins_in_sessions_of_its_own_and_ends():
    """--cpu-load's busy processes: each spins (its CPU time grows) in a session of its own,
    like another program; leaving the context ends them all."""

    def cpu_ticks(pid):
        fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
        return int(fields[11]) + int(fields[12])  # utime + stime

    with CpuLoad(2) as load:
        assert len(load.pids) == 2
        for pid in load.pids:
            assert os.getsid(pid) == pid
        first = {pid: cpu_ticks(pid) for pid in load.pids}
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline and not all(
            cpu_ticks(pid) > first[pid] + 5 for pid in load.pids
        ):
            time.sleep(0.1)
        assert all(cpu_ticks(pid) > first[pid] + 5 for pid in load.pids)
        processes = list(load.processes)
    assert all(p.poll() is not None for p in processes)
