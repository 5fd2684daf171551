"""The simulated robot, patient and ultrasound machine of a rehearsal, as its own process.

``python -m drake_rus.rehearsal.sim_process --patient test:0 --scenario quick --ready R.json
--log sim_log.json`` builds the simulated station for the virtual patient with the robot at
the planned scan start (``drake_rus.scan.run.PrepareScenario``: the start planner stands in
for the operator placing the probe and choosing the depth preset), then speaks the real
robot's wire protocol of the Drake route and serves the machine's video:

- drake-franka-driver's LCM messages on ``--lcm-url`` (default
  ``udpm://239.255.76.67:7667?ttl=0``): subscribes PANDA_COMMAND (velocity mode; a command
  older than ``--expire-sec``, default drake-franka-driver's 0.1 s, makes the robot hold
  zero velocity), publishes PANDA_STATUS (positions, velocities, external torques in the
  driver's sign, wall-clock utime) every 1 / ``--rate-hz`` s, paced at real time;
- the emulated ultrasound (the station's ``us_image``, at the imaging rate) as MJPEG over
  HTTP on 127.0.0.1 (``http://127.0.0.1:PORT/stream.mjpg``);
- wire faults: ``--latency-ms``, ``--drop-status``, ``--video-delay-ms``,
  ``--freeze-video-at``.

When ready it writes ``--ready`` (JSON: pid, lcm_url, channels, video_url, the depth preset,
the start joints and pose). While running it rewrites ``--live`` (JSON, ~10 Hz: simulated
time, first command time, PIVOT-like seconds, true force). It stops on SIGTERM / SIGINT,
when ``--stop-file`` appears, when ``--parent-pid`` is gone or after ``--max-wall`` s, and
then writes ``--log`` (sim_log.json: command ages, the true kidney pose X_BK in the base
frame, the true contact force peak, the joint velocities at the end, timing, faults, the
per-tick speed trace and command trace).
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import json
import logging
import math
import os
import signal
import sys
import time
from pathlib import Path

import numpy as np
from pydrake.lcm import DrakeLcm

from drake_rus.anatomy import load_patient
from drake_rus.hardware.lcm_sim_driver import DRIVER_EXPIRE_SEC
from drake_rus.io_utils import write_text_atomic
from drake_rus.rehearsal.core import age_statistics, pose_to_json, raise_priority, stall_causes
from drake_rus.rehearsal.sim import (
    BuildRehearsalSim,
    RehearsalSim,
    StatusPublisherThread,
    WireFaults,
)
from drake_rus.rehearsal.status_process import StatusPublisherProcess
from drake_rus.rehearsal.video_process import SliceEmulateRenderer, VideoProcess
from drake_rus.scan.run import PrepareScenario
from drake_rus.scenario import DEFAULT_SCENARIOS_FILE, ApplyOverrides, LoadScenario

LOG = logging.getLogger("drake_rus.rehearsal")

DEFAULT_LCM_URL = "udpm://239.255.76.67:7667?ttl=0"

# The status thread's SCHED_FIFO priority (when permitted): the real robot's statuses come
# from its own real-time controller, not from a process that competes with the scan's.
STATUS_PRIORITY = 10


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m drake_rus.rehearsal.sim_process",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--patient", default="test:0")
    p.add_argument("--scenario", default="default")
    p.add_argument("--scenarios-file", default=str(DEFAULT_SCENARIOS_FILE))
    p.add_argument("--set", dest="overrides", default=None, metavar="YAML")
    p.add_argument("--lcm-url", default=DEFAULT_LCM_URL)
    p.add_argument("--command-channel", default="PANDA_COMMAND")
    p.add_argument("--status-channel", default="PANDA_STATUS")
    p.add_argument(
        "--rate-hz",
        type=float,
        default=200.0,
        help="status rate and simulation tick (Hz; the real driver: 1000)",
    )
    p.add_argument(
        "--expire-sec",
        type=float,
        default=DRIVER_EXPIRE_SEC,
        help="command expiry (s; drake-franka-driver's --expire_sec, default 0.1)",
    )
    p.add_argument(
        "--declared-load",
        action="store_true",
        help="report external torques without the probe's weight (as if the "
        "probe were entered in Desk); default: the weight is in them",
    )
    p.add_argument(
        "--status-priority",
        type=int,
        default=STATUS_PRIORITY,
        help="real-time (SCHED_FIFO) priority of the status publisher, as the robot's own "
        "controller has it, when permitted (root or CAP_SYS_NICE); 0: none",
    )
    p.add_argument("--latency-ms", type=float, default=0.0)
    p.add_argument("--drop-status", type=float, default=0.0)
    p.add_argument("--video-delay-ms", type=float, default=0.0)
    p.add_argument("--freeze-video-at", type=float, default=None)
    p.add_argument("--video-port", type=int, default=0, help="0: any free port")
    p.add_argument("--seed", type=int, default=0, help="seed of the dropped packets")
    p.add_argument("--ready", required=True, help="JSON written when ready")
    p.add_argument("--log", required=True, help="sim_log.json written at the end")
    p.add_argument("--live", default=None, help="JSON rewritten ~10 times a second")
    p.add_argument("--stop-file", default=None)
    p.add_argument("--parent-pid", type=int, default=None)
    p.add_argument(
        "--nice",
        type=int,
        default=0,
        help="scheduling priority of this process and its session (below 0: root)",
    )
    p.add_argument(
        "--max-wall",
        type=float,
        default=900.0,
        help="stop after this many s of wall time whatever happens",
    )
    return p


class StopFlag:
    """Why and when to stop: a signal, the stop file, the parent gone, the wall limit."""

    def __init__(self, stop_file, parent_pid, max_wall):
        self.reason = None
        self.wall = None
        self._stop_file = Path(stop_file) if stop_file else None
        self._parent = parent_pid
        self._deadline = time.monotonic() + float(max_wall)
        self._next_check = 0.0

    def set(self, reason: str) -> None:
        if self.reason is None:
            self.reason, self.wall = reason, time.time()

    def __call__(self) -> bool:
        if self.reason is not None:
            return True
        now = time.monotonic()
        if now >= self._next_check:  # file system and process checks at 20 Hz
            self._next_check = now + 0.05
            if self._stop_file is not None and self._stop_file.exists():
                self.set("stop file")
            elif self._parent is not None and os.getppid() != self._parent:
                self.set("parent process gone")
            elif now >= self._deadline:
                self.set("wall-clock limit")
        return self.reason is not None


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="sim: %(levelname)s %(message)s")
    stop = StopFlag(args.stop_file, args.parent_pid, args.max_wall)
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda signum, frame: stop.set(signal.Signals(signum).name))
    if args.nice:
        print(f"sim: {raise_priority(args.nice)}", flush=True)
    faults = WireFaults(
        command_latency=args.latency_ms * 1e-3,
        status_drop=args.drop_status,
        video_delay=args.video_delay_ms * 1e-3,
        freeze_video_at=args.freeze_video_at,
    )
    t_start = time.time()
    scenario = LoadScenario(
        filename=args.scenarios_file, scenario_name=args.scenario, scenario_text=args.overrides
    )
    scenario = ApplyOverrides(scenario, "{hardware: false}", "rehearsal sim")
    patient = load_patient(
        args.patient, side=scenario.patient.side, posture=scenario.patient.posture, progress=False
    )
    scenario, X_start, plan = PrepareScenario(scenario, patient)
    lcm = DrakeLcm(args.lcm_url)
    # The pictures are sliced, emulated and encoded in a process of their own, from the
    # poses the physics hands over (the station's own functions, model and seed).
    video = VideoProcess(
        SliceEmulateRenderer(scenario.imaging, patient.labels, scenario.random_seed),
        frame_rate_hz=scenario.imaging.frame_rate_hz,
        delay=faults.video_delay,
        port=args.video_port,
    )
    holder = {}
    # The statuses go out from a process of their own on udpm (no interpreter lock shared
    # with the physics), else from a thread: the robot's status rate does not depend on how
    # long a simulation step takes.
    status_options = dict(
        drop_probability=faults.status_drop,
        seed=args.seed,
        realtime_priority=args.status_priority,
    )
    if args.lcm_url.startswith("udpm://"):
        status_thread = StatusPublisherProcess(
            args.lcm_url, args.status_channel, 1.0 / args.rate_hz, **status_options
        )
    else:
        status_thread = StatusPublisherThread(
            lcm, args.status_channel, 1.0 / args.rate_hz, **status_options
        )

    def on_pose(snapshot):
        sim = holder.get("sim")
        t0 = getattr(sim, "t_first_command", None) if sim is not None else None
        if faults.freeze_video_at is not None and t0 is not None:
            if holder.get("frozen"):
                return
            if snapshot.t - t0 >= faults.freeze_video_at:
                holder["frozen"] = True
                video.freeze(snapshot.stamp)
                return
        video.offer(snapshot)

    try:
        diagram, station, wire = BuildRehearsalSim(
            scenario,
            patient,
            lcm,
            faults=faults,
            rate_hz=args.rate_hz,
            expire_sec=args.expire_sec,
            undeclared_load=not args.declared_load,
            seed=args.seed,
            command_channel=args.command_channel,
            status_channel=args.status_channel,
            status_sink=status_thread.offer,
        )
        sim = RehearsalSim(
            diagram,
            station,
            wire,
            lcm,
            rate_hz=args.rate_hz,
            frame_period=1.0 / scenario.imaging.frame_rate_hz,
            command_channel=args.command_channel,
            lcm_url=args.lcm_url,
            status_thread=status_thread,
            plant_period=scenario.contact.time_step,
            on_pose=on_pose,
        )
        holder["sim"] = sim
        sim.prime()
        X_BK_start = sim.kidney_pose()
        ready = {
            "pid": os.getpid(),
            "lcm_url": args.lcm_url,
            "command_channel": args.command_channel,
            "status_channel": args.status_channel,
            "video_url": video.url,
            "depth": float(scenario.imaging.depth),
            "q0": [float(v) for v in scenario.robot.initial_joint_positions],
            "X_BP_start": pose_to_json(X_start),
            "patient": patient.name,
            "start_plan": plan.summary() if plan is not None else None,
            "setup_s": time.time() - t_start,
        }
        write_text_atomic(args.ready, json.dumps(ready, indent=2, default=str) + "\n")
        print(
            f"sim: ready in {ready['setup_s']:.1f} s: LCM {args.lcm_url}, video "
            f"{video.url}, depth {scenario.imaging.depth:g} m",
            flush=True,
        )

        sim.hold(stop)
        # What exists now lives to the end: keep it out of the collector's full passes. And
        # a thread holding the interpreter lock (the video, the wire tap, the stream server)
        # hands it to the physics or the statuses within 1 ms, not 5.
        gc.freeze()
        sys.setswitchinterval(0.001)

        def live():
            if args.live:
                write_text_atomic(
                    args.live,
                    json.dumps(
                        {
                            "wall": time.time(),
                            "sim_t": sim.context.get_time() - sim.t_first_command,
                            "first_command_wall": sim.first_command_wall,
                            "pivot_like_s": sim.pivot_like_s,
                            "force_true_n": sim.force_now,
                            "tip_speed": sim.pivot.tip_speed,
                            "turn_rate": sim.pivot.turn_rate,
                        }
                    ),
                )

        stats = sim.run(stop, every=live) if not stop() else sim.stats
    finally:
        status_thread.close()
        video_stats = video.close()
        if "sim" in holder:
            holder["sim"].close()
    log = sim_log(args, scenario, faults, sim, stats, stop, video.url, X_BK_start, video_stats)
    write_text_atomic(args.log, json.dumps(log, indent=1, default=_json_default) + "\n")
    c = log["commands"]["age_ms"]
    print(
        f"sim: stopped ({stop.reason}); {log['commands']['count']} commands, age median "
        f"{_fmt(c['median_ms'])} ms, max {_fmt(c['max_ms'])} ms; real-time margin "
        f"{_fmt(log['realtime']['margin'])}x, max lag {1e3 * stats.max_lag_s:.1f} ms",
        flush=True,
    )
    return 0


def _fmt(x):
    return "n/a" if x is None else f"{x:.2f}"


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    return str(o)


def sequence_gaps(arrivals) -> int | None:
    """Messages missing between consecutive sequence numbers of each sender."""
    by_sender: dict = {}
    for a in arrivals:
        if a[4] < 0:
            return None
        by_sender.setdefault(a[3], []).append(a[4])
    return int(
        sum(max(0, b - a - 1) for seqs in by_sender.values() for a, b in zip(seqs[:-1], seqs[1:]))
    )


def sim_log(args, scenario, faults, sim, stats, stop, video_url, X_BK_start, video) -> dict:
    """sim_log.json's content; ``video``: the video process's statistics."""
    expiry = sim.wire.expiry
    arrivals = list(sim.arrivals)
    arrival_ages = [a[0] - a[1] * 1e-6 for a in arrivals]
    applied_ages = [now - utime * 1e-6 for now, utime, _, _ in expiry.log]
    X_BK = sim.kidney_pose()
    return {
        "patient": args.patient,
        "scenario": args.scenario,
        "depth": float(scenario.imaging.depth),
        "stop": {"reason": stop.reason, "wall": stop.wall},
        "first_command_wall": sim.first_command_wall,
        "commands": {
            "count": len(arrivals),
            # Messages a sender published that never arrived (gaps in LCM's per-sender
            # sequence numbers; None without a wire tap): 0 means every command was logged.
            "sequence_gaps": sequence_gaps(arrivals),
            "senders": sorted({a[3] for a in arrivals}),
            # Distinct commands the driver's subscriber handed on (it keeps the newest).
            "applied": len(expiry.log),
            "stale_when_applied": sum(1 for *_, fresh in expiry.log if not fresh),
            # now - utime when each command arrived at the driver (the wire's age) ...
            "age_ms": age_statistics(arrival_ages),
            # ... and when it reached the robot (plus the injected latency).
            "age_at_robot_ms": age_statistics(applied_ages),
            "expire_sec": args.expire_sec,
        },
        "X_BK_true": pose_to_json(X_BK),
        "X_BK_true_start": pose_to_json(X_BK_start),
        "force_true_peak_n": sim.force_peak,
        "force_true_peak_sim_s": (
            sim.force_peak_time - (sim.t_first_command or 0.0)
            if math.isfinite(sim.force_peak_time)
            else None
        ),
        "joint_velocity_end": sim.joint_velocity().tolist(),
        "applied_command_end": sim.applied_command().tolist(),
        "realtime": stats.as_dict(),
        "status": {
            "published": sim.status_thread.published,
            "dropped": sim.status_thread.dropped,
            "rate_hz": args.rate_hz,
            # Gaps between successive statuses on the wire (ms): the robot's status rate.
            "gaps_ms": sim.status_thread.gaps_ms(),
            "scheduling": sim.status_thread.scheduling,
            # Gaps of more than two periods and what ran meanwhile in this process.
            "stalls": stall_causes(
                sim.status_thread.times,
                2.0 / args.rate_hz,
                {
                    # Before the first command: the robot rests, nothing steps.
                    "hold": [(sim.status_thread.times[0], stats.starts[0])]
                    if sim.status_thread.times and stats.starts
                    else [],
                    "gc": stats.gc_spans,
                    "frame_tick": stats.spans("frame"),
                    "plant_tick": stats.spans("plant"),
                    "wire_tick": stats.spans("wire"),
                    "picture": video.get("spans", []),
                },
            ),
        },
        "video": {
            # Poses handed to the video process; pictures it sliced, emulated and encoded,
            # skipped (a newer pose came first), the time each took and its age when shown
            # (ms from the robot being at its pose).
            "poses": sim.frames,
            **{k: v for k, v in video.items() if k not in ("spans", "rendered")},
            "url": video_url,
        },
        "faults": dataclasses.asdict(faults),
        "undeclared_load": not args.declared_load,
        # Per command reaching the robot: wall time s, utime s, max |v| (rad/s), fresh.
        "command_trace": [
            [round(now, 6), round(utime * 1e-6, 6), float(np.abs(v).max()), bool(fresh)]
            for now, utime, v, fresh in expiry.log
        ],
        # Per command arriving at the driver: wall time s, utime s, max |v| (rad/s).
        "arrival_trace": [[round(a[0], 6), round(a[1] * 1e-6, 6), a[2]] for a in arrivals],
        # Per truth sample (sim s since the first command, tip speed m/s, turn rate rad/s,
        # true force N, PIVOT-like s).
        "motion_trace": [
            [round(t - (sim.t_first_command or 0.0), 4)]
            + [None if not math.isfinite(x) else round(x, 5) for x in rest]
            for t, *rest in sim.motion
        ],
        # Per simulation tick: wall time s, max |joint velocity|, max |applied command|.
        "speed_trace": [[round(t, 6), round(v, 7), round(c, 7)] for t, v, c in sim.speeds],
    }


if __name__ == "__main__":
    sys.exit(main())
