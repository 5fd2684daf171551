"""``drake-rus rehearse``: software-in-the-loop rehearsal of a hardware scan.

Starts the simulated robot, patient and ultrasound machine in a separate process
(``python -m drake_rus.rehearsal.sim_process``), which speaks the real robot's wire protocol
of the Drake route (drake-franka-driver's PANDA_COMMAND / PANDA_STATUS over LCM UDP
multicast, velocity mode, the driver's command expiry) and serves the emulated ultrasound as
an MJPEG stream on 127.0.0.1, then runs the UNCHANGED hardware scan in this process against
it (``hardware: true``, backend lcm, ``video_source`` the stream, not a dry run) and
compares its kidney estimate with the simulation's truth. Wire faults: --latency-ms,
--drop-status, --video-delay-ms, --freeze-video-at.

Networking: nothing talks to any address but the loopback. The video binds 127.0.0.1; LCM
multicast with ttl=0 stays on the host, and to keep it off every interface the rehearsal
runs in a private network namespace with only the loopback, multicast routed over it:

    unshare -n bash -c 'ip link set lo up && ip route add 224.0.0.0/4 dev lo \\
        && drake-rus rehearse ...'

With --netns auto (default) the command does this by itself when run as root and not yet
isolated; --netns no runs where it is (multicast then uses the host's multicast route,
still with ttl=0).

Writes to --out: the scan's outputs (summary.json, clouds, plots), sim_log.json (the
simulated side: command ages, true kidney pose, true force peak, joint velocities at the
end, timing), rehearsal.json (E_trans, E_rot,x against the truth, both sides' real-time
margins) and sim.out (the simulated side's messages).
"""

from __future__ import annotations

import argparse
import os
import sys

from drake_rus import interrupts
from drake_rus.cli import EXIT_STATUS_HELP, add_scenario_arguments
from drake_rus.extras import require
from drake_rus.rehearsal.core import loopback_only, netns_argv
from drake_rus.rehearsal.run import RehearsalOptions, RunRehearsal, SimProcessError
from drake_rus.rehearsal.sim_process import DEFAULT_LCM_URL

NETNS_ENV = "DRAKE_RUS_REHEARSAL_NETNS"


def add_commands(subparsers) -> None:
    p = subparsers.add_parser(
        "rehearse",
        help="software-in-the-loop rehearsal of a hardware scan (sim process on "
        "the real wire protocol)",
        description=__doc__,
        epilog=EXIT_STATUS_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_scenario_arguments(p)
    p.add_argument(
        "--patient",
        default="test:0",
        help="virtual patient for the simulated side (default test:0)",
    )
    p.add_argument("--out", default="runs/rehearsal", help="output directory")
    p.add_argument(
        "--latency-ms", type=float, default=0.0, help="added command latency at the robot (ms)"
    )
    p.add_argument(
        "--drop-status", type=float, default=0.0, help="probability of dropping each status packet"
    )
    p.add_argument(
        "--video-delay-ms", type=float, default=0.0, help="delay of the video output (ms)"
    )
    p.add_argument(
        "--freeze-video-at",
        type=float,
        default=None,
        metavar="T",
        help="freeze the picture T s after the robot's first command (the stream "
        "keeps flowing, like the machine's freeze key)",
    )
    p.add_argument(
        "--expire-sec",
        type=float,
        default=None,
        help="the simulated driver's command expiry (s; default drake-franka-driver's 0.1)",
    )
    p.add_argument(
        "--status-rate-hz",
        type=float,
        default=200.0,
        help="status rate and simulation tick of the simulated driver (Hz)",
    )
    p.add_argument(
        "--declared-load",
        action="store_true",
        help="the probe is entered in Desk: the robot's torques exclude its weight "
        "(the scan side then sets lcm_compensate_load: false)",
    )
    p.add_argument("--lcm-url", default=DEFAULT_LCM_URL)
    p.add_argument("--seed", type=int, default=0, help="seed of the dropped packets")
    p.add_argument(
        "--max-sim-time", type=float, default=150.0, help="give up after this much scan time (s)"
    )
    p.add_argument(
        "--nice",
        type=int,
        default=0,
        help="scheduling priority of both processes and their sessions (-20..19; "
        "below 0 needs root): on a shared machine whose other sessions keep "
        "the cores busy, e.g. -5 keeps the rehearsal at real time",
    )
    p.add_argument(
        "--cpu-load",
        type=int,
        default=0,
        metavar="N",
        help="a stress rehearsal: N busy processes beside the scan (each spinning on a "
        "core, in its own session like another program); an overloaded computer must end "
        "the scan at zero velocity with the overload named",
    )
    p.add_argument(
        "--netns",
        choices=["auto", "yes", "no"],
        default="auto",
        help="run in a private network namespace (see above; default auto)",
    )
    p.set_defaults(func=run_rehearse_command)


def _argv(args) -> list[str]:
    """The command line that reproduces ``args`` (for the re-exec in a namespace)."""
    argv = [
        "rehearse",
        "--scenario",
        args.scenario,
        "--scenarios-file",
        args.scenarios_file,
        "--patient",
        args.patient,
        "--out",
        args.out,
        "--latency-ms",
        repr(args.latency_ms),
        "--drop-status",
        repr(args.drop_status),
        "--video-delay-ms",
        repr(args.video_delay_ms),
        "--status-rate-hz",
        repr(args.status_rate_hz),
        "--lcm-url",
        args.lcm_url,
        "--seed",
        str(args.seed),
        "--max-sim-time",
        repr(args.max_sim_time),
        "--nice",
        str(args.nice),
        "--cpu-load",
        str(args.cpu_load),
        "--netns",
        "no",
    ]
    if args.overrides:
        argv += ["--set", args.overrides]
    if args.freeze_video_at is not None:
        argv += ["--freeze-video-at", repr(args.freeze_video_at)]
    if args.expire_sec is not None:
        argv += ["--expire-sec", repr(args.expire_sec)]
    if args.declared_load:
        argv += ["--declared-load"]
    return argv


def _reexec_in_netns(args) -> None:
    """Replaces this process by the same command in a private network namespace."""
    os.environ[NETNS_ENV] = "1"
    argv = netns_argv([sys.executable, "-m", "drake_rus.cli", *_argv(args)])
    print("rehearse: re-running in a private network namespace (loopback only)", flush=True)
    os.execvp(argv[0], argv)


def run_rehearse_command(args) -> int:
    require("cv2", "rehearse (the simulated ultrasound machine's video stream)")
    options = RehearsalOptions(
        patient=args.patient,
        scenario=args.scenario,
        scenarios_file=args.scenarios_file,
        overrides=args.overrides,
        latency_ms=args.latency_ms,
        drop_status=args.drop_status,
        video_delay_ms=args.video_delay_ms,
        freeze_video_at=args.freeze_video_at,
        expire_sec=args.expire_sec,
        rate_hz=args.status_rate_hz,
        lcm_url=args.lcm_url,
        declared_load=args.declared_load,
        seed=args.seed,
        max_sim_time=args.max_sim_time,
        nice=args.nice,
        cpu_load=args.cpu_load,
    )
    isolated = loopback_only()
    if not isolated and os.environ.get(NETNS_ENV) != "1":
        if args.netns == "yes" or (args.netns == "auto" and os.geteuid() == 0):
            _reexec_in_netns(args)  # does not return
        if args.netns == "auto":
            print(
                "rehearse: not root, running without a private network namespace (LCM "
                "multicast stays on this host with ttl=0; see --help)",
                file=sys.stderr,
            )
    # SIGTERM ends the command like Ctrl-C (drake_rus.interrupts, installed by drake-rus):
    # the scan's session stops the robot and the simulated side is stopped on the way out.
    try:
        report = RunRehearsal(options, args.out)
    except SimProcessError as e:
        print(f"drake-rus rehearse: error: {e}", file=sys.stderr)
        return 2
    cmd = report["commands_at_sim"]["age_ms"]
    rt = report["realtime"]

    def f(x, digits=2, scale=1.0):
        return "n/a" if x is None else f"{scale * x:.{digits}f}"

    loop = rt["scan"].get("loop") or {"lag_ms": {}, "compute_ms": {}}
    sim_loop = rt["sim"].get("loop") or {"lag_ms": {}}
    gaps = report["status_packets"].get("gaps_ms") or {}
    print(
        f"{report['status']}{': ' + report['reason'] if report['status'] != 'DONE' else ''}"
        f" | E_trans {f(report['e_trans_mm'])} mm, E_rot,x {f(report['e_rot_x_deg'])} deg"
        f" | commands at the robot: {cmd['count']} (lost "
        f"{report['commands_at_sim']['sequence_gaps']}), age median {f(cmd['median_ms'])} "
        f"ms, max {f(cmd['max_ms'])} ms | scan loop: lag p99 {f(loop['lag_ms'].get('p99'), 1)}"
        f" ms, max {f(loop['lag_ms'].get('max'), 1)} ms, compute p99 "
        f"{f(loop['compute_ms'].get('p99'), 1)} ms | simulated robot: lag max "
        f"{f(sim_loop['lag_ms'].get('max'), 1)} ms, statuses up to {f(gaps.get('max'), 1)} ms "
        f"apart"
    )
    lag = rt["sim"]["max_lag_s"]
    if lag > 0.1:
        print(
            f"rehearse: warning: the simulated robot fell up to {lag:.2f} s behind the wall "
            f"clock ({rt['sim']['late_ticks']} of {rt['sim']['ticks']} ticks late): its "
            f"physics lagged the commands, the rehearsal was less faithful (a busy machine? "
            f"see --nice)",
            file=sys.stderr,
        )
    print(f"wrote {os.path.join(args.out, 'rehearsal.json')}")
    if report["status"] == "INTERRUPTED":
        return interrupts.exit_status()
    return 0 if report["status"] == "DONE" else 1
