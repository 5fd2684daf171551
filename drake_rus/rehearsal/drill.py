"""Stop drill: the operator stops the scan mid-PIVOT; how fast is the robot still?

``RunStopDrill(options, out)`` starts the simulated robot and patient
(:class:`drake_rus.rehearsal.run.SimProcess`), runs the real command ``drake-rus scan`` on
the hardware scenario against it as a separate process, waits until the simulated robot
sees PIVOT-like motion (in contact, the tip still, the probe turning; ``pivot_after`` s of
it), sends the scan process SIGTERM (what ``systemctl stop``, ``kill`` or a supervisor
sends; Ctrl-C is the same path) and measures at the simulated robot: the first zero
command after the signal, when the applied command became zero for good, and when the
joints came to rest. Writes ``stop_drill.json``.

``python -m drake_rus.rehearsal.drill --out DIR [--scenario hardware --patient test:0 ...]``;
run it inside the rehearsal's network namespace (see ``drake-rus rehearse --help``).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import yaml

from drake_rus.config_schema import ScenarioError
from drake_rus.extras import MissingExtra, require
from drake_rus.io_utils import write_text_atomic
from drake_rus.rehearsal.core import loopback_only, raise_priority, scan_overrides, stop_reaction
from drake_rus.rehearsal.run import RehearsalOptions, SimProcess, SimProcessError
from drake_rus.scenario import DEFAULT_SCENARIOS_FILE, LoadScenario

__all__ = ["RunStopDrill", "merge_overrides"]


def merge_overrides(*texts) -> str:
    """One YAML mapping (as JSON) from several override mappings, later ones winning
    (nested mappings merged)."""

    def merge(a: dict, b: dict) -> dict:
        out = dict(a)
        for k, v in b.items():
            out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
        return out

    result: dict = {}
    for text in texts:
        if text:
            node = yaml.safe_load(text)
            if not isinstance(node, dict):
                raise ValueError(f"overrides: expected a mapping, got {text!r}")
            result = merge(result, node)
    return json.dumps(result)


def RunStopDrill(
    options: RehearsalOptions,
    out,
    *,
    pivot_after: float = 1.0,
    wait_limit: float = 120.0,
    after_signal: float = 1.0,
) -> dict:
    """The stop drill (module doc). Returns (and writes to ``out``/stop_drill.json) the
    signal's wall time, the scan's exit code, the PIVOT-like state when signalled and
    :func:`drake_rus.rehearsal.core.stop_reaction` at the simulated robot."""
    require("cv2", "the stop drill (the rehearsal's ultrasound video stream)")
    # The scenario and its overrides checked before any process starts or anything is
    # written: ScenarioError naming the field, not the simulated robot's traceback.
    LoadScenario(
        filename=options.scenarios_file,
        scenario_name=options.scenario,
        scenario_text=options.overrides,
    )
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    report: dict = {"network_isolated": loopback_only(), "pivot_after_s": pivot_after}
    if options.nice:
        report["priority"] = raise_priority(options.nice)
    scan = None
    scan_out = open(out / "scan.out", "wb")
    try:
        with SimProcess(out, options) as sim:
            ready = sim.start()
            overrides = merge_overrides(
                options.overrides, scan_overrides(ready, compensate_load=not options.declared_load)
            )
            argv = [
                sys.executable,
                "-m",
                "drake_rus.cli",
                "scan",
                "--scenario",
                options.scenario,
                "--scenarios-file",
                str(options.scenarios_file),
                "--set",
                overrides,
                "--no-record",
                "--out",
                str(out / "scan"),
                "--max-sim-time",
                repr(float(options.max_sim_time)),
            ]
            # In this session (its scheduling group, see raise_priority); signalled by pid.
            scan = subprocess.Popen(
                argv, stdout=scan_out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL
            )
            deadline = time.monotonic() + wait_limit
            live = None
            while time.monotonic() < deadline:
                if scan.poll() is not None:
                    raise SimProcessError(
                        f"the scan ended (code {scan.returncode}) before "
                        f"the robot pivoted:\n{_tail(out / 'scan.out')}\n"
                        f"{sim_lateness(sim.stop())}"
                    )
                if not sim.alive():
                    raise SimProcessError(f"the simulated robot died:\n{sim.tail()}")
                live = sim.live()
                if live is not None and live.get("pivot_like_s", 0.0) >= pivot_after:
                    break
                time.sleep(0.02)
            else:
                raise SimProcessError(
                    f"no PIVOT-like motion within {wait_limit:g} s (last live state {live})"
                )
            t_signal = time.time()
            scan.send_signal(signal.SIGTERM)
            try:
                code = scan.wait(15.0)
            except subprocess.TimeoutExpired:
                code = None
            time.sleep(after_signal)  # let the robot settle, on the record
            log = sim.stop()
        if log is None:
            raise SimProcessError(f"the simulated robot wrote no log:\n{sim.tail()}")
    finally:
        if scan is not None and scan.poll() is None:
            scan.kill()
            scan.wait(5.0)
        scan_out.close()
    commands = [(a[0], a[2]) for a in log["arrival_trace"]]
    reaction = stop_reaction(t_signal, commands, log["speed_trace"])
    report.update(
        {
            "signal_wall": t_signal,
            "scan_exit_code": code,
            "scan_time_at_signal_s": live.get("sim_t"),
            "live_at_signal": live,
            "reaction_s": reaction,
            "commands_at_sim": log["commands"],
            "joint_velocity_end_at_sim": log["joint_velocity_end"],
            "realtime_sim": log["realtime"],
        }
    )
    write_text_atomic(out / "stop_drill.json", json.dumps(report, indent=2) + "\n")
    return report


def sim_lateness(log: dict | None) -> str:
    """One line on how late the simulated robot's process ran (from its ``log``), so that a
    scan stopped on a stale robot state shows whether the simulator or the scan fell behind."""
    if not log:
        return "the simulated robot wrote no log"
    lag = (log.get("realtime") or {}).get("max_lag_s")
    gap = ((log.get("status") or {}).get("gaps_ms") or {}).get("max")
    lag_text = "unknown" if lag is None else f"{1e3 * float(lag):.0f} ms"
    gap_text = "unknown" if gap is None else f"{float(gap):.0f} ms"
    return (
        f"the simulated robot's process fell at most {lag_text} behind the wall clock; "
        f"its statuses came at most {gap_text} apart"
    )


def _tail(path: Path, lines: int = 20) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return ""


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m drake_rus.rehearsal.drill",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", required=True)
    p.add_argument("--patient", default="test:0")
    p.add_argument(
        "--scenario",
        default="hardware",
        help="the scan's scenario (default: hardware, as `drake-rus rehearse`)",
    )
    p.add_argument("--scenarios-file", default=str(DEFAULT_SCENARIOS_FILE))
    p.add_argument("--set", dest="overrides", default=None)
    p.add_argument(
        "--pivot-after",
        type=float,
        default=1.0,
        help="seconds of PIVOT-like motion before the signal",
    )
    p.add_argument("--nice", type=int, default=0)
    p.add_argument("--max-sim-time", type=float, default=60.0)
    args = p.parse_args(argv)
    options = RehearsalOptions(
        patient=args.patient,
        scenario=args.scenario,
        scenarios_file=args.scenarios_file,
        overrides=args.overrides,
        nice=args.nice,
        max_sim_time=args.max_sim_time,
    )
    try:
        report = RunStopDrill(options, args.out, pivot_after=args.pivot_after)
    except (SimProcessError, MissingExtra, ScenarioError) as e:
        print(f"stop drill: error: {e}", file=sys.stderr)
        return 2
    r = report["reaction_s"]

    def ms(x):
        return "never" if x is None else f"{1e3 * x:.1f} ms"

    rest = ", ".join(f"|v| < {k} rad/s {ms(v)}" for k, v in r["at_rest"].items())
    print(
        f"stop drill: SIGTERM at scan time {report['scan_time_at_signal_s']:.2f} s "
        f"(PIVOT-like for {report['live_at_signal']['pivot_like_s']:.2f} s, joints at "
        f"{r['speed_at_signal']:.3f} rad/s); scan exit code {report['scan_exit_code']}; at "
        f"the robot after the signal: first zero command {ms(r['first_zero_command'])}, "
        f"applied command zero {ms(r['command_zero'])}, {rest}"
    )
    return 0


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(main())
