"""Running a rehearsal: the simulated robot and patient in their own process, the unchanged
hardware scan in this one.

:class:`SimProcess` starts ``python -m drake_rus.rehearsal.sim_process`` and always stops it
(SIGTERM, then SIGKILL after a bounded wait; the child also stops by itself when this
process is gone). :func:`RunRehearsal` runs the scan with ``hardware: true`` on the LCM
route against it (``drake_rus.scan.RunScan(..., patient=None)``: paced at real time, inside
the zero-velocity session, from the robot's current pose), writes the scan outputs and
``rehearsal.json`` (the scan's kidney estimate against the simulation's truth).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from drake_rus import interrupts
from drake_rus.extras import require
from drake_rus.io_utils import write_text_atomic
from drake_rus.localization.localize import load_registration_template
from drake_rus.provenance import Provenance
from drake_rus.rehearsal.core import (
    kidney_errors,
    loopback_only,
    pose_from_json,
    raise_priority,
    scan_overrides,
)
from drake_rus.rehearsal.sim_process import DEFAULT_LCM_URL
from drake_rus.scan.metrics import ScanMetrics, Summary
from drake_rus.scan.report import WriteScanOutputs
from drake_rus.scan.run import RunScan
from drake_rus.scenario import DEFAULT_SCENARIOS_FILE, ApplyOverrides, LoadScenario
from drake_rus.stations import MakeStation

__all__ = [
    "RehearsalOptions",
    "SimProcess",
    "SimProcessError",
    "RunRehearsal",
    "CpuLoad",
    "scan_scenario",
]


# Status rates (Hz) the simulated driver accepts: it ticks the simulation at this rate; the
# scan side stops the robot when no status arrives for hardware_interface.status_timeout
# (0.25 s by default, 2.5 ticks at 10 Hz); above 10 kHz a tick (0.1 ms) is shorter than
# the simulation can keep up with.
STATUS_RATE_HZ = (10.0, 10000.0)


# At most this many busy processes beside a stress rehearsal.
MAX_CPU_LOAD = 64

# A busy process: spins until told to stop or its parent (the rehearsal) is gone.
BUSY_LOOP = (
    "import os, sys\n"
    "parent = int(sys.argv[1])\n"
    "while os.getppid() == parent:\n"
    "    for _ in range(100000):\n"
    "        pass\n"
)


class CpuLoad:
    """``n`` busy processes (each spinning on a core), each in its own session like another
    program on the computer; they end with :meth:`stop` (SIGTERM, then SIGKILL) or by
    themselves when this process is gone. A context manager."""

    def __init__(self, n: int):
        self.processes: list[subprocess.Popen] = []
        try:
            for _ in range(int(n)):
                self.processes.append(
                    subprocess.Popen(
                        [sys.executable, "-c", BUSY_LOOP, str(os.getpid())],
                        stdin=subprocess.DEVNULL,
                        stdout=subprocess.DEVNULL,
                        stderr=subprocess.DEVNULL,
                        start_new_session=True,
                    )
                )
        except BaseException:
            self.stop()
            raise

    @property
    def pids(self) -> list[int]:
        return [p.pid for p in self.processes]

    def stop(self) -> None:
        for p in self.processes:
            if p.poll() is None:
                p.terminate()
        for p in self.processes:
            try:
                p.wait(5.0)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5.0)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()
        return False


class SimProcessError(RuntimeError):
    """The simulated robot's process failed to start or died."""


@dataclasses.dataclass
class RehearsalOptions:
    """What to rehearse (see ``drake-rus rehearse --help``)."""

    patient: str = "test:0"
    scenario: str = "default"
    scenarios_file: str = str(DEFAULT_SCENARIOS_FILE)
    overrides: str | None = None
    latency_ms: float = 0.0
    drop_status: float = 0.0
    video_delay_ms: float = 0.0
    freeze_video_at: float | None = None
    expire_sec: float | None = None
    rate_hz: float = 200.0
    lcm_url: str = DEFAULT_LCM_URL
    declared_load: bool = False
    seed: int = 0
    max_sim_time: float = 150.0
    ready_timeout: float = 300.0
    # Scheduling priority of both processes (and their sessions); below 0 needs root.
    nice: int = 0
    # Busy processes started beside the scan (a stress rehearsal: an overloaded computer).
    cpu_load: int = 0

    def __post_init__(self):
        for name in ("latency_ms", "video_delay_ms"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(
                    f"--{name.replace('_', '-')}: expected a non-negative time, got {v}"
                )
        if not 0.0 <= self.drop_status <= 1.0:
            raise ValueError(
                f"--drop-status: expected a probability in [0, 1], got {self.drop_status}"
            )
        if self.freeze_video_at is not None and not self.freeze_video_at >= 0:
            raise ValueError(
                f"--freeze-video-at: expected a time >= 0 s, got {self.freeze_video_at}"
            )
        if self.expire_sec is not None and not (
            math.isfinite(self.expire_sec) and self.expire_sec >= 0
        ):
            raise ValueError(f"--expire-sec: expected a non-negative time, got {self.expire_sec}")
        lo, hi = STATUS_RATE_HZ
        if not (math.isfinite(self.rate_hz) and lo <= self.rate_hz <= hi):
            raise ValueError(
                f"--status-rate-hz: expected a status rate of {lo:g}-{hi:g} Hz "
                f"(the real driver: 1000), got {self.rate_hz:g}"
            )
        if not (self.max_sim_time > 0):
            raise ValueError(f"--max-sim-time: expected a positive time, got {self.max_sim_time}")
        if not (isinstance(self.cpu_load, int) and 0 <= self.cpu_load <= MAX_CPU_LOAD):
            raise ValueError(
                f"--cpu-load: expected a number of busy processes, 0-{MAX_CPU_LOAD}, "
                f"got {self.cpu_load}"
            )


class SimProcess:
    """The simulated robot, patient and ultrasound machine in a child process, writing into
    ``workdir`` (``sim_ready.json``, ``sim_live.json``, ``sim_log.json``, ``sim.out``).
    Use as a context manager: the child is stopped on every exit."""

    def __init__(self, workdir, options: RehearsalOptions):
        self.dir = Path(workdir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.options = options
        self.ready_path = self.dir / "sim_ready.json"
        self.live_path = self.dir / "sim_live.json"
        self.log_path = self.dir / "sim_log.json"
        self.stop_path = self.dir / "sim.stop"
        self.out_path = self.dir / "sim.out"
        self.process: subprocess.Popen | None = None
        self.ready: dict | None = None
        self.log: dict | None = None

    def argv(self) -> list[str]:
        o = self.options
        argv = [
            sys.executable,
            "-m",
            "drake_rus.rehearsal.sim_process",
            "--patient",
            o.patient,
            "--scenario",
            o.scenario,
            "--scenarios-file",
            str(o.scenarios_file),
            "--lcm-url",
            o.lcm_url,
            "--rate-hz",
            repr(float(o.rate_hz)),
            "--latency-ms",
            repr(float(o.latency_ms)),
            "--drop-status",
            repr(float(o.drop_status)),
            "--video-delay-ms",
            repr(float(o.video_delay_ms)),
            "--seed",
            str(o.seed),
            "--ready",
            str(self.ready_path),
            "--log",
            str(self.log_path),
            "--live",
            str(self.live_path),
            "--stop-file",
            str(self.stop_path),
            "--parent-pid",
            str(os.getpid()),
            "--max-wall",
            repr(float(o.ready_timeout + 3 * o.max_sim_time + 120.0)),
        ]
        if o.overrides:
            argv += ["--set", o.overrides]
        if o.freeze_video_at is not None:
            argv += ["--freeze-video-at", repr(float(o.freeze_video_at))]
        if o.expire_sec is not None:
            argv += ["--expire-sec", repr(float(o.expire_sec))]
        if o.declared_load:
            argv += ["--declared-load"]
        if o.nice:
            argv += ["--nice", str(int(o.nice))]
        return argv

    def start(self) -> dict:
        """Starts the child and waits (bounded by ``ready_timeout``) until it is ready;
        returns what it announced (``sim_ready.json``)."""
        for path in (self.ready_path, self.live_path, self.log_path, self.stop_path):
            path.unlink(missing_ok=True)
        out = open(self.out_path, "wb")
        try:
            # Its own session: the terminal's Ctrl-C reaches only this process, which stops
            # the scan at zero velocity first and then the child.
            self.process = subprocess.Popen(
                self.argv(),
                stdout=out,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                start_new_session=True,
            )
        finally:
            out.close()
        deadline = time.monotonic() + self.options.ready_timeout
        while not self.ready_path.exists():
            if self.process.poll() is not None:
                raise SimProcessError(
                    f"the simulated robot's process ended with code "
                    f"{self.process.returncode} before it was ready:\n"
                    f"{self.tail()}"
                )
            if time.monotonic() > deadline:
                raise SimProcessError(
                    f"the simulated robot was not ready within "
                    f"{self.options.ready_timeout:g} s:\n{self.tail()}"
                )
            time.sleep(0.05)
        self.ready = json.loads(self.ready_path.read_text())
        return self.ready

    def live(self) -> dict | None:
        """The child's live status (simulated time, PIVOT-like seconds, ...), if any."""
        try:
            return json.loads(self.live_path.read_text())
        except (OSError, ValueError):
            return None

    def alive(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def tail(self, lines: int = 20) -> str:
        try:
            return "\n".join(self.out_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return ""

    def stop(self, timeout: float = 20.0) -> dict | None:
        """Stops the child (stop file and SIGTERM; SIGKILL after ``timeout`` s) and returns
        its log (None if it wrote none). Never raises; idempotent."""
        p = self.process
        if p is not None and p.poll() is None:
            try:
                self.stop_path.touch()
                p.send_signal(signal.SIGTERM)
                p.wait(timeout)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5.0)
            except Exception:
                p.kill()
        if self.log is None and self.log_path.exists():
            try:
                self.log = json.loads(self.log_path.read_text())
            except ValueError:
                self.log = None
        return self.log

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()
        return False


def scan_scenario(options: RehearsalOptions, ready: dict):
    """The scan side's scenario: the rehearsal's scenario on the hardware station, LCM route,
    at the depth preset the simulated machine runs (as the operator sets it)."""
    scenario = LoadScenario(
        filename=options.scenarios_file,
        scenario_name=options.scenario,
        scenario_text=options.overrides,
    )
    return ApplyOverrides(
        scenario,
        scan_overrides(ready, compensate_load=not options.declared_load),
        "rehearsal scan side",
    )


def RunRehearsal(options: RehearsalOptions, out, *, progress: bool | None = None) -> dict:
    """Runs the rehearsal (module doc); writes ``out``/rehearsal.json and returns it. Raises
    MissingExtra (nothing written) without OpenCV, which the video stream needs."""
    require("cv2", "the rehearsal (its ultrasound video stream)")
    out = Path(out)
    provenance = rehearsal_provenance(options)  # a bad scenario fails before any output
    out.mkdir(parents=True, exist_ok=True)
    report: dict = {
        "patient": options.patient,
        "scenario": options.scenario,
        "faults": {
            "latency_ms": options.latency_ms,
            "drop_status": options.drop_status,
            "video_delay_ms": options.video_delay_ms,
            "freeze_video_at": options.freeze_video_at,
        },
        "network_isolated": loopback_only(),
        "lcm_url": options.lcm_url,
    }
    report["provenance"] = provenance
    if options.nice:
        report["priority"] = raise_priority(options.nice)
    sim = SimProcess(out, options)
    try:
        return _rehearse(options, out, report, sim, progress)
    except BaseException as e:  # leave a record of what went wrong
        with interrupts.deferred(reraise=False):
            if isinstance(e, KeyboardInterrupt) or interrupts.pending() is not None:
                report.update(
                    {
                        "status": "INTERRUPTED",
                        "reason": "interrupted by "
                        f"{interrupts.signal_text(interrupts.signal_of(e))}",
                    }
                )
            else:
                report.update({"status": "ERROR", "reason": f"{type(e).__name__}: {e}"})
            report["sim_tail"] = sim.tail()
            write_text_atomic(
                out / "rehearsal.json", json.dumps(report, indent=2, default=str) + "\n"
            )
        raise
    finally:
        sim.stop()


def rehearsal_provenance(options: RehearsalOptions, argv=None) -> dict:
    """rehearsal.json's ``provenance`` (see drake_rus.provenance): the rehearsal's scenario as
    resolved, its options and seeds (the simulated side's patient and dropped packets)."""
    scenario = LoadScenario(
        filename=options.scenarios_file,
        scenario_name=options.scenario,
        scenario_text=options.overrides,
    )
    record = Provenance(
        scenario,
        scenario_name=options.scenario,
        scenarios_file=options.scenarios_file,
        overrides=options.overrides,
        seeds={"patient": options.patient, "status_drop_seed": options.seed},
        argv=argv,
    )
    record["command"] = "rehearse"
    record["arguments"] = dataclasses.asdict(options)
    return record


def robot_side_overload(reason: str, log: dict, scenario) -> str:
    """The scan's stop ``reason``, with the simulated robot's own overload named when the
    stop is the robot's state going stale (the safety layer's stale state, the station's
    lost robot) while the simulated robot's process fell behind the wall clock by more than
    the watchdog allows: on this computer, not on a robot, the cause."""
    if not reason or not any(
        cue in reason for cue in ("stale robot state", "robot fault", "robot state lost")
    ):
        return reason
    rt = log.get("realtime", {})
    lag = float(rt.get("max_lag_s") or 0.0)
    gap = (log.get("status", {}).get("gaps_ms") or {}).get("max") or 0.0
    limit = min(scenario.safety.state_timeout, scenario.hardware_interface.status_timeout)
    if max(lag, 1e-3 * gap) <= limit:
        return reason
    return (
        f"{reason}; the simulated robot's process fell {1e3 * lag:.0f} ms behind the wall "
        f"clock (statuses up to {gap:.0f} ms apart): the computer is overloaded"
    )


def _max_lag_s(timing: dict | None) -> float | None:
    """The scan loop's largest lag (s) from its loop timing, if any."""
    if not timing or timing["lag_ms"]["max"] is None:
        return None
    return timing["lag_ms"]["max"] * 1e-3


def _rehearse(options, out: Path, report: dict, sim: SimProcess, progress) -> dict:
    """RunRehearsal's body (the caller stops ``sim`` whatever happens)."""
    ready = sim.start()
    print(
        f"rehearse: simulated robot ready (pid {ready['pid']}): LCM {ready['lcm_url']}, "
        f"video {ready['video_url']}, depth preset {ready['depth']:g} m",
        flush=True,
    )
    scenario = scan_scenario(options, ready)
    template = load_registration_template(scenario.localization.template)
    stations = []

    def make_station(scenario, **kwargs):  # MakeStation, keeping a handle to close it
        stations.append(MakeStation(scenario, **kwargs))
        return stations[-1]

    cpu0 = time.process_time()
    try:
        with CpuLoad(options.cpu_load) as load:
            if options.cpu_load:
                report["cpu_load"] = {"processes": options.cpu_load, "pids": load.pids}
                print(
                    f"rehearse: {options.cpu_load} busy processes beside the scan "
                    f"(pids {', '.join(map(str, load.pids))})",
                    flush=True,
                )
            result = RunScan(
                scenario,
                None,
                template,
                make_station=make_station,
                max_sim_time=options.max_sim_time,
                progress=progress,
            )
    finally:
        cpu = time.process_time() - cpu0
        for station in stations:  # the robot connection and the video thread
            station.close()
    metrics = ScanMetrics(result)
    summary = Summary(result, metrics, provenance=report.get("provenance"))
    written = WriteScanOutputs(result, metrics, summary, out)
    log = sim.stop()
    if log is None:
        raise SimProcessError(f"the simulated robot wrote no log:\n{sim.tail()}")
    X_true = pose_from_json(log["X_BK_true"])
    errors = kidney_errors(result.X_BK_estimated, X_true)
    report.update(
        {
            "status": result.status,
            "reason": robot_side_overload(result.reason, log, scenario),
            **errors,
            "X_BK_estimated": (
                None
                if result.X_BK_estimated is None
                else {
                    "translation": result.X_BK_estimated.translation().tolist(),
                    "rotation": result.X_BK_estimated.rotation().matrix().tolist(),
                }
            ),
            "X_BK_true": log["X_BK_true"],
            "kidney_moved_mm": 1e3
            * float(
                sum(
                    (a - b) ** 2
                    for a, b in zip(
                        log["X_BK_true"]["translation"], log["X_BK_true_start"]["translation"]
                    )
                )
                ** 0.5
            ),
            "depth": ready["depth"],
            "phases": summary["phases"],
            "force_true_peak_n": log["force_true_peak_n"],
            "force_estimated_peak_n": summary["peak_force_n"],
            "safety_events": summary["safety_events"],
            "commands_at_sim": log["commands"],
            "joint_velocity_end_at_sim": log["joint_velocity_end"],
            "status_packets": log["status"],
            "video": log["video"],
            "realtime": {
                "scan": {
                    "sim_s": result.sim_s,
                    "wall_s": result.wall_s,
                    "cpu_s": cpu,
                    "margin": result.sim_s / cpu if cpu > 0 else None,
                    "max_lag_s": _max_lag_s(result.loop_timing),
                    # Per-tick compute time and lag (ms), slips, load average.
                    "loop": result.loop_timing,
                    "perception": result.perception,
                },
                "sim": log["realtime"],
            },
            "outputs": [str(p) for p in written] + [str(sim.log_path)],
        }
    )
    write_text_atomic(out / "rehearsal.json", json.dumps(report, indent=2, default=str) + "\n")
    return report
