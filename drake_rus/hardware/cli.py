"""``drake-rus hardware``: bring-up commands for the real robot and ultrasound machine
(docs/hardware_bringup.md).

    drake-rus hardware check --dry-run --set "{hardware_interface: {robot_ip: 172.16.0.2}}"

- ``check``: connect, read; live read-outs (joints, contact force, video rate and age) at a
  few Hz; the push test in a dry run; with ``--no-dry-run`` a short scripted motion in free
  space. Exit 0: every check of the guide passed; 1: one was missed (named); 2: no
  connection or a bad configuration.
- ``pivot``: live read-outs while the operator pivots the probe tip in a divot, then the
  pivot calibration of the tip (exit 1 above the guide's residuals).
- ``grab``: saves the newest grabbed picture and the joint positions (for calibrate-image).
- ``calibrate-image``: scale and origin of the picture per depth preset from point-target
  pictures (least squares), written to the image calibration file.
- ``calibrate-latency``: moves the probe sinusoidally over a point target and estimates the
  video latency.

The scripted motion (also used by the end-to-end tests) runs the unchanged controller and
safety layer on the hardware station with the supervisor and force control off: at
``t_orientation`` the desired probe orientation turns by ``angle`` about the base x axis, at
``t_slide`` the desired tip position moves ``slide`` m along the base y axis.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path

import numpy as np
from pydrake.common.yaml import yaml_dump_typed
from pydrake.math import RigidTransform, RotationMatrix

from drake_rus.closed_loop import BuildClosedLoop
from drake_rus.config_schema import ScenarioError
from drake_rus.demo import add_scenario_arguments
from drake_rus.hardware.calibration import flange_poses_from_joints, pivot_calibration
from drake_rus.hardware.core import load_declaration, period_statistics
from drake_rus.hardware.image_calibration import (
    ImageCalibration, TargetImage, TargetSet, find_point_target, fit_target_set,
    load_image_calibration, load_target_set, save_image_calibration, with_preset)
from drake_rus.hardware.station import HardwareFault, MakeHardwareStation, RunHardware
from drake_rus.hardware.systems import ProbeLoadTorque
from drake_rus.hardware.video import estimate_video_latency
from drake_rus.robot import MakeControlPlant
from drake_rus.scenario import ApplyOverrides, LoadScenario

__all__ = ["ScriptedMotion", "MotionResult", "BuildHardwareClosedLoop", "RunScriptedMotion",
           "add_commands", "Readout", "motion_failures", "LatencyCalibration",
           "RunLatencyCalibration", "APPROACH_TOLERANCE_DEG", "TIP_TOLERANCE_M"]

# docs/hardware_bringup.md, step 5: after the scripted motion, errors below these.
APPROACH_TOLERANCE_DEG = 0.5
TIP_TOLERANCE_M = 1.5e-3
# Step 4: probe_force with nothing touching the probe; a push must give f_z < 0.
REST_FORCE_N = 1.0
PUSH_FORCE_N = 3.0
# Step 2: pivot calibration residuals (m).
PIVOT_RMS_M = 0.5e-3
PIVOT_MAX_M = 1.0e-3
# Step 3: at least this fraction of imaging.frame_rate_hz.
FRAME_RATE_FRACTION = 0.8


@dataclasses.dataclass
class ScriptedMotion:
    """An orientation step then a slide (s, rad, m), in the base frame. With
    ``settle_angle`` / ``settle_distance`` > 0 the run ends early, after the slide started,
    once the approach vector is within ``settle_angle`` (rad) and the tip within
    ``settle_distance`` (m, base x-y) of their targets; ``duration`` bounds it."""
    t_orientation: float = 0.3
    angle: float = math.radians(5.0)
    t_slide: float = 2.0
    slide: float = 0.02
    duration: float = 5.0
    settle_angle: float = 0.0
    settle_distance: float = 0.0


@dataclasses.dataclass
class MotionResult:
    """What the scripted motion did: start / end tip pose and the targets; joint positions
    (rad) at start and end; the safety layer's events; frames grabbed."""
    X_BP_start: object
    X_BP_end: object
    a_target: np.ndarray
    o_target: np.ndarray
    p_target_xy: np.ndarray
    q_start: np.ndarray
    q_end: np.ndarray
    safety_events: tuple
    frames: int
    end_time: float

    @property
    def approach_error(self) -> float:
        """Angle (rad) between the probe's approach vector and its target."""
        a = self.X_BP_end.rotation().matrix()[:, 2]
        return float(np.arccos(np.clip(a @ self.a_target, -1.0, 1.0)))

    @property
    def orientation_error(self) -> float:
        """Angle (rad) between the probe's x axis and its target."""
        o = self.X_BP_end.rotation().matrix()[:, 0]
        return float(np.arccos(np.clip(o @ self.o_target, -1.0, 1.0)))

    @property
    def position_error_xy(self) -> float:
        """Tip distance (m) from the target in the base x-y plane."""
        return float(np.linalg.norm(self.X_BP_end.translation()[:2] - self.p_target_xy))


def scenario_for_motion(scenario):
    """The scenario with force control off (K_p3 = K_d1 = 0: no motion along a from the
    force loop) for a free-space motion."""
    controller = dataclasses.replace(scenario.controller, K_p3=0.0, K_d1=0.0)
    return dataclasses.replace(scenario, controller=controller)


def BuildHardwareClosedLoop(scenario, station):
    """The controller + safety layer (``BuildClosedLoop``, supervisor off, force control
    off) on ``station``."""
    return BuildClosedLoop(scenario_for_motion(scenario), station=station,
                           use_supervisor=False, log_period=None)


def motion_failures(result: MotionResult, motion: ScriptedMotion | None = None) -> list[str]:
    """The guide's checks of the scripted motion (docs/hardware_bringup.md, step 5) that
    ``result`` missed, each saying which and by how much; empty when all passed."""
    out = []
    if result.safety_events:
        out.append(f"safety events: {', '.join(str(e.reason) for e in result.safety_events)}")
    approach = math.degrees(result.approach_error)
    if approach >= APPROACH_TOLERANCE_DEG:
        out.append(f"approach error {approach:.2f} deg >= {APPROACH_TOLERANCE_DEG} deg")
    if result.position_error_xy >= TIP_TOLERANCE_M:
        out.append(f"tip x-y error {1e3 * result.position_error_xy:.2f} mm >= "
                   f"{1e3 * TIP_TOLERANCE_M:.1f} mm")
    if motion is not None and motion.settle_angle > 0 and result.end_time >= motion.duration:
        out.append(f"did not settle within {motion.duration:g} s")
    return out


def RunScriptedMotion(loop, station, motion: ScriptedMotion, *, realtime_rate: float = 1.0,
                      check_period: float = 0.05, on_step=None,
                      context_out: dict | None = None) -> MotionResult:
    """Runs ``motion`` on the closed loop (from :func:`BuildHardwareClosedLoop`) inside a
    hardware session (zero velocity at the end, on any exception or fault). ``on_step()``
    runs after every ``check_period`` s; ``context_out["root"]`` receives the root
    context."""
    from pydrake.systems.analysis import Simulator


    simulator = Simulator(loop.diagram)
    root = simulator.get_context()
    if context_out is not None:
        context_out["root"] = root
    st_ctx = station.GetMyContextFromRoot(root)
    X0 = RigidTransform(station.GetOutputPort("X_BP").Eval(st_ctx))
    q0 = np.array(station.GetOutputPort("joint_position").Eval(st_ctx))
    R_step = RotationMatrix.MakeXRotation(motion.angle).matrix()
    R0 = X0.rotation().matrix()
    a_target, o_target = R_step @ R0[:, 2], R_step @ R0[:, 0]
    p_target = X0.translation()[:2] + np.array([0.0, motion.slide])
    stage = {"orientation": False, "slide": False}

    def step():
        t = root.get_time()
        if not stage["orientation"] and t >= motion.t_orientation:
            loop.reference_value(root, "a_des").SetFromVector(a_target)
            loop.reference_value(root, "o_des").SetFromVector(o_target)
            stage["orientation"] = True
        if not stage["slide"] and t >= motion.t_slide:
            loop.reference_value(root, "P_des").SetFromVector(p_target)
            stage["slide"] = True
        if on_step is not None:
            on_step()

    def settled():
        if motion.settle_angle <= 0 or not stage["slide"]:
            return False
        X = station.GetOutputPort("X_BP").Eval(st_ctx)
        a = X.rotation().matrix()[:, 2]
        return (np.arccos(np.clip(a @ a_target, -1, 1)) < motion.settle_angle
                and np.linalg.norm(X.translation()[:2] - p_target) < motion.settle_distance)

    simulator.Initialize()
    end = RunHardware(simulator, station, motion.duration, check_period=check_period,
                      realtime_rate=realtime_rate, on_step=step, until=settled)
    safety_ctx = loop.parts.safety.GetMyContextFromRoot(root)
    events = loop.parts.safety.GetOutputPort("safety_events").Eval(safety_ctx)
    frame = station.GetOutputPort("us_image").Eval(st_ctx)
    return MotionResult(X0, RigidTransform(station.GetOutputPort("X_BP").Eval(st_ctx)), a_target, o_target,
                        p_target, q0,
                        np.array(station.GetOutputPort("joint_position").Eval(st_ctx)),
                        tuple(events), int(frame.frame_index) + 1, end)


class Readout:
    """Live read-outs of a hardware station, printed at ``rate_hz`` (wall clock) by
    :meth:`step` (call it often, e.g. as RunHardware's ``on_step``): diagram time, joint
    positions (rad), estimated contact force (N, in P), video frame rate (Hz) and age of the
    newest frame (ms). Keeps every sample it printed in ``samples`` and every force it saw
    in ``forces`` ((wall s, diagram s, f (3,)))."""

    def __init__(self, station, context, rate_hz: float = 4.0, out=None, prefix: str = ""):
        self.station = station
        self.context = context
        self.period = 1.0 / rate_hz if rate_hz > 0 else math.inf
        self.out = out if out is not None else sys.stdout
        self.prefix = prefix
        self.samples: list[dict] = []
        self.forces: list[tuple[float, float, np.ndarray]] = []
        self._next = time.monotonic()
        self._start = time.monotonic()

    def read(self) -> dict:
        st, ctx = self.station, self.context
        q = np.array(st.GetOutputPort("joint_position").Eval(ctx))
        F = np.array(st.GetOutputPort("probe_force").Eval(ctx))
        X = st.GetOutputPort("X_BP").Eval(ctx)
        sample = {"wall": time.monotonic() - self._start, "t": ctx.get_time(), "q": q,
                  "f": F[3:6].copy(), "p_BP": X.translation().copy(),
                  "fps": math.nan, "age": math.nan}
        capture = getattr(st.grabber, "capture", None)
        if capture is not None:
            stats = capture.stats()
            sample["fps"], sample["age"] = stats.frame_rate_hz, stats.age
        return sample

    def step(self):
        now = time.monotonic()
        sample = self.read()
        self.forces.append((sample["wall"], sample["t"], sample["f"]))
        if now < self._next or self.period == math.inf:
            return
        self._next = max(self._next + self.period, now)
        self.samples.append(sample)
        video = (f"video {sample['fps']:5.1f} fps, age {1e3 * sample['age']:4.0f} ms"
                 if math.isfinite(sample["age"]) else "no video")
        print(f"{self.prefix}t={sample['t']:6.2f} s  q=["
              + " ".join(f"{v:+.3f}" for v in sample["q"]) + "] rad  f=["
              + " ".join(f"{v:+5.1f}" for v in sample["f"]) + f"] N |f|="
              f"{np.linalg.norm(sample['f']):4.1f} N  {video}", file=self.out, flush=True)


def _load(args, **hardware) -> object:
    scenario = LoadScenario(filename=args.scenarios_file, scenario_name=args.scenario,
                            scenario_text=args.overrides)
    fields = ", ".join(f"{k}: {v}" for k, v in hardware.items())
    return ApplyOverrides(scenario, "{hardware: true, hardware_interface: {%s}}" % fields)


def _connect(scenario, prog: str, **kwargs):
    try:
        return MakeHardwareStation(scenario, **kwargs)
    except (HardwareFault, ValueError) as e:       # ScenarioError is a ValueError
        print(f"drake-rus hardware {prog}: error: {e}", file=sys.stderr)
        return None


def _timing_report(station, config) -> tuple[str, list[str]]:
    """The control loop's tick timing (wall clock) and the watchdog checks on it."""
    ticks = list(station.grabber.tick_times)[5:]      # skip the start-up ticks
    st = period_statistics(ticks)
    if not st["count"]:
        return "control loop: no ticks", []
    line = (f"control loop: {st['count']} periods, mean {1e3 * st['mean']:.2f} ms, p99 "
            f"{1e3 * st['p99']:.1f} ms, p99.9 {1e3 * st['p999']:.1f} ms, max "
            f"{1e3 * st['max']:.1f} ms (command_timeout {1e3 * config.command_timeout:.0f} ms, "
            f"status_timeout {1e3 * config.status_timeout:.0f} ms)")
    failures = []
    if st["max"] > config.command_timeout:
        failures.append(f"the control loop stalled {1e3 * st['max']:.0f} ms, longer than "
                        f"hardware_interface.command_timeout ({1e3 * config.command_timeout:.0f}"
                        f" ms): commands would expire mid-motion (raise it, or use the "
                        f"real-time PC)")
    return line, failures


def _video_checks(scenario, station, readout: Readout) -> list[str]:
    capture = station.grabber.capture
    if capture is None:
        return []
    stats = capture.stats()
    failures = []
    print(f"video: {stats.frames} frames, {stats.frame_rate_hz:.1f} fps, newest "
          f"{1e3 * stats.age:.0f} ms old, {stats.failures} read failures, video_latency "
          f"{1e3 * station.grabber.video_latency:.0f} ms")
    want = FRAME_RATE_FRACTION * scenario.imaging.frame_rate_hz
    if stats.frame_rate_hz < want:
        failures.append(f"video frame rate {stats.frame_rate_hz:.1f} fps < {want:.0f} fps "
                        f"({FRAME_RATE_FRACTION:.0%} of imaging.frame_rate_hz)")
    age = stats.age + station.grabber.video_latency
    if age > scenario.safety.image_timeout:
        failures.append(f"frames are {1e3 * age:.0f} ms old (age + video_latency) > "
                        f"safety.image_timeout {1e3 * scenario.safety.image_timeout:.0f} ms: "
                        f"the stale-image watchdog would stop the robot")
    if stats.error:
        failures.append(f"video: {stats.error}")
    return failures


def _load_check(scenario, station) -> list[str]:
    """LCM route: do the driver's torques at rest carry the probe's weight?"""
    backend = station.backend
    if not hasattr(backend, "rest_tau"):
        return []
    plant, _ = MakeControlPlant(scenario)
    load = ProbeLoadTorque(plant, scenario.probe.mass, scenario.probe.p_FCm)(backend.rest_q)
    verdict = load_declaration(backend.rest_tau, load)
    compensate = scenario.hardware_interface.lcm_compensate_load
    print(f"probe load: the external torques at rest look {verdict} (the probe's weight is "
          f"{np.linalg.norm(load):.2f} N m in joint space; lcm_compensate_load: "
          f"{str(compensate).lower()})")
    if verdict == "undeclared" and not compensate:
        return ["the robot does not know the probe's weight: enter the probe holder in Desk "
                "as the end effector, or set hardware_interface.lcm_compensate_load: true"]
    if verdict == "declared" and compensate:
        return ["the probe's weight is removed twice (Desk knows it and "
                "lcm_compensate_load is true): set lcm_compensate_load: false"]
    return []


def _push_checks(readout: Readout, rest: float) -> list[str]:
    """Guide step 4: hands off for ``rest`` s (force below REST_FORCE_N), then a push on the
    probe face gives f_z < 0."""
    failures = []
    quiet = [np.linalg.norm(f) for w, _, f in readout.forces if w <= rest]
    if quiet:
        worst = float(np.max(quiet))
        print(f"push test: |probe_force| at rest (first {rest:g} s) up to {worst:.2f} N")
        if worst > REST_FORCE_N:
            failures.append(f"probe_force at rest {worst:.2f} N > {REST_FORCE_N:g} N (check "
                            f"the probe's mass / centre of mass, set_load or "
                            f"lcm_compensate_load, tau_external_bias_duration)")
    pushes = [(np.linalg.norm(f), f) for w, _, f in readout.forces
              if w > rest and np.linalg.norm(f) >= PUSH_FORCE_N]
    if pushes:
        _, f = max(pushes, key=lambda x: x[0])
        print(f"push test: strongest push f = [{f[0]:+.1f} {f[1]:+.1f} {f[2]:+.1f}] N")
        if f[2] >= 0:
            failures.append(f"a push on the probe face gave f_z = {f[2]:+.1f} N >= 0: the "
                            f"external torque sign is wrong (or the push was not along the "
                            f"probe's axis)")
    else:
        print(f"push test: no push seen (|f| < {PUSH_FORCE_N:g} N after the first {rest:g} s)")
    return failures


def _report(prog: str, failures: list[str]) -> int:
    if failures:
        print(f"drake-rus hardware {prog}: FAILED:")
        for f in failures:
            print(f"  - {f}")
        return 1
    print(f"drake-rus hardware {prog}: all checks passed")
    return 0


def add_commands(subparsers) -> None:
    p = subparsers.add_parser(
        "hardware", help="the real robot: connection check, dry run, scripted motion, "
        "calibrations", description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="hardware_command", metavar="HARDWARE_COMMAND")
    sub.required = True

    def common(c, readout=True):
        add_scenario_arguments(c)
        c.add_argument("--recover", action="store_true",
                       help="reset the robot's pending errors at connection (after you "
                       "checked the patient and the probe)")
        if readout:
            c.add_argument("--readout-hz", type=float, default=4.0,
                           help="live read-outs per second (0: none; default 4)")

    c = sub.add_parser("check", help="connect, read joints / torques / images with live "
                       "read-outs and the push test; with --no-dry-run also run the scripted "
                       "free-space motion")
    common(c)
    group = c.add_mutually_exclusive_group()
    group.add_argument("--dry-run", dest="dry_run", action="store_true", default=True,
                       help="read only, never command motion (default)")
    group.add_argument("--no-dry-run", dest="dry_run", action="store_false",
                       help="also run the scripted motion: 5 deg tilt, 2 cm slide, no contact")
    c.add_argument("--duration", type=float, default=2.0,
                   help="seconds of reading in a dry run (default 2; 20-30 for the push test)")
    c.add_argument("--rest", type=float, default=1.0,
                   help="first seconds of a dry run with nothing touching the probe (default 1)")
    c.set_defaults(func=run_check)

    c = sub.add_parser("pivot", help="pivot calibration of the probe tip: live read-outs "
                       "while you pivot the tip in a divot, then the fit")
    common(c)
    c.add_argument("--duration", type=float, default=60.0,
                   help="seconds of recording (default 60)")
    c.add_argument("--rate", type=float, default=10.0,
                   help="joint samples per second recorded (default 10)")
    c.add_argument("--save", default=None, metavar="CSV",
                   help="also write the recorded joint positions (rad) to this file")
    c.set_defaults(func=run_pivot, outputs={"save": "file"})

    c = sub.add_parser("grab", help="save the newest grabbed picture and the joint "
                       "positions, and list them in a target file for calibrate-image")
    common(c, readout=False)
    c.add_argument("--out", default="image_targets", metavar="DIR",
                   help="folder of pictures and targets.yaml (default image_targets)")
    c.add_argument("--p-P", dest="p_P", type=float, nargs=3, default=None,
                   metavar=("X", "Y", "Z"),
                   help="the target's position in the probe frame (m), if known (a jig)")
    c.set_defaults(func=run_grab, outputs={"out": "dir"})

    c = sub.add_parser("calibrate-image", help="fit mm per pixel and the image origin of a "
                       "depth preset to point-target pictures; write the calibration file")
    add_scenario_arguments(c)
    c.add_argument("targets", help="target file (YAML, see `hardware grab`)")
    c.add_argument("--out", required=True, help="image calibration file to write or update")
    c.add_argument("--force", action="store_true",
                   help="write even when the residuals exceed the guide's limits")
    c.set_defaults(func=run_calibrate_image, outputs={"out": "file"})

    c = sub.add_parser("calibrate-latency", help="move the probe sinusoidally over a point "
                       "target (in water or a phantom) and estimate the video latency")
    common(c)
    c.add_argument("--amplitude", type=float, default=0.01,
                   help="motion amplitude along the probe's array (m, default 0.01)")
    c.add_argument("--period", type=float, default=2.0, help="motion period (s, default 2)")
    c.add_argument("--cycles", type=float, default=4.0, help="periods (default 4)")
    c.add_argument("--max-latency", type=float, default=0.5,
                   help="largest latency considered (s, default 0.5)")
    c.set_defaults(func=run_calibrate_latency)


def run_check(args) -> int:
    scenario = _load(args, dry_run="true" if args.dry_run else "false",
                     **({"error_recovery": "at_connect"} if args.recover else {}))
    station = _connect(scenario, "check")
    if station is None:
        return 2
    try:
        return _check(args, scenario, station)
    except HardwareFault as e:
        print(f"drake-rus hardware check: error: {e}", file=sys.stderr)
        return 2
    finally:
        station.close()


def _check(args, scenario, station) -> int:
    from pydrake.systems.analysis import Simulator

    cfg = scenario.hardware_interface
    ctx = station.CreateDefaultContext()
    q = station.GetOutputPort("joint_position").Eval(ctx)
    X = station.GetOutputPort("X_BP").Eval(ctx)
    print(f"connected ({cfg.backend}); q = {np.array2string(np.asarray(q), precision=4)} rad")
    print(f"probe tip p_BP = {np.array2string(X.translation(), precision=4)} m")
    thresholds = getattr(station.backend, "collision_thresholds", None)
    if thresholds is not None:
        def fmt(v):
            return "[" + ", ".join(f"{float(x):g}" for x in v) + "]"
        print(f"FR3 collision thresholds (contact / collision): joints "
              f"{fmt(thresholds['lower_torque'])} / {fmt(thresholds['upper_torque'])} N m, "
              f"wrench {fmt(thresholds['lower_force'])} / {fmt(thresholds['upper_force'])} "
              f"(N, N m)")
    failures = _load_check(scenario, station)
    if args.dry_run:
        simulator = Simulator(station)
        sc = station.GetMyContextFromRoot(simulator.get_context())
        station.get_input_port().FixValue(sc, np.zeros(7))
        readout = Readout(station, sc, args.readout_hz)
        if args.duration > args.rest:
            print(f"hands off the probe for {args.rest:g} s, then push its face along its "
                  f"axis (push test)")
        simulator.Initialize()
        RunHardware(simulator, station, args.duration, on_step=readout.step)
        F = station.GetOutputPort("probe_force").Eval(sc)
        frame = station.GetOutputPort("us_image").Eval(sc)
        print(f"probe_force = {np.array2string(np.asarray(F), precision=2)} (N m, N)")
        print(f"frames grabbed: {frame.frame_index + 1} in {args.duration:g} s")
        failures += _push_checks(readout, args.rest)
        failures += _video_checks(scenario, station, readout)
        line, timing = _timing_report(station, cfg)
        print(line)
        failures += timing
        print("dry run: no motion was commanded")
        return _report("check", failures)
    loop = BuildHardwareClosedLoop(scenario, station)
    motion = ScriptedMotion(duration=15.0, settle_angle=math.radians(0.5),
                            settle_distance=1.5e-3)
    holder = {}

    def on_step():
        if "readout" not in holder:
            holder["readout"] = Readout(station, station.GetMyContextFromRoot(holder["root"]),
                                        args.readout_hz)
        holder["readout"].step()

    result = RunScriptedMotion(loop, station, motion, on_step=on_step, context_out=holder)
    print(f"approach error {math.degrees(result.approach_error):.2f} deg, tip x-y error "
          f"{1e3 * result.position_error_xy:.1f} mm, safety events: "
          f"{[e.reason for e in result.safety_events] or 'none'}")
    failures += motion_failures(result, motion)
    if "readout" in holder:
        failures += _video_checks(scenario, station, holder["readout"])
    line, timing = _timing_report(station, cfg)
    print(line)
    return _report("check", failures + timing)


def run_pivot(args) -> int:
    from pydrake.systems.analysis import Simulator

    scenario = _load(args, dry_run="true",
                     **({"error_recovery": "at_connect"} if args.recover else {}))
    station = _connect(scenario, "pivot")
    if station is None:
        return 2
    try:
        simulator = Simulator(station)
        sc = station.GetMyContextFromRoot(simulator.get_context())
        station.get_input_port().FixValue(sc, np.zeros(7))
        readout = Readout(station, sc, args.readout_hz)
        recorded, next_t = [], [0.0]

        def step():
            readout.step()
            if time.monotonic() >= next_t[0]:
                next_t[0] = time.monotonic() + 1.0 / args.rate
                recorded.append(np.array(station.GetOutputPort("joint_position").Eval(sc)))

        print(f"pivot the probe tip in the divot for {args.duration:g} s: tilt 20-40 deg "
              f"about two different axes, the tip never leaving the divot")
        simulator.Initialize()
        RunHardware(simulator, station, args.duration, on_step=step)
    except HardwareFault as e:
        print(f"drake-rus hardware pivot: error: {e}", file=sys.stderr)
        return 2
    finally:
        station.close()
    q = np.array(recorded)
    if args.save:
        np.savetxt(args.save, q, delimiter=",", header="q1,q2,q3,q4,q5,q6,q7 (rad)")
        print(f"joint positions: {args.save} ({len(q)} samples)")
    try:
        cal = pivot_calibration(*flange_poses_from_joints(scenario, q))
    except ValueError as e:
        print(f"drake-rus hardware pivot: {e}", file=sys.stderr)
        return 1
    print(f"tip in the flange p_FT = {np.array2string(cal.p_FT, precision=5)} m; pivot "
          f"p_BT = {np.array2string(cal.p_BT, precision=4)} m")
    print(f"residuals: RMS {1e3 * cal.rms:.2f} mm, max {1e3 * cal.residuals.max():.2f} mm over "
          f"{len(q)} samples; write p_FT into probe.X_FP.translation")
    failures = []
    if cal.rms > PIVOT_RMS_M:
        failures.append(f"RMS residual {1e3 * cal.rms:.2f} mm > {1e3 * PIVOT_RMS_M:.1f} mm")
    if cal.residuals.max() > PIVOT_MAX_M:
        worst = np.argsort(cal.residuals)[::-1][:3]
        failures.append(f"largest residual {1e3 * cal.residuals.max():.2f} mm > "
                        f"{1e3 * PIVOT_MAX_M:.1f} mm (samples {list(map(int, worst))}: the tip "
                        f"left the divot?)")
    return _report("pivot", failures)


def run_grab(args) -> int:
    scenario = _load(args, dry_run="true",
                     **({"error_recovery": "at_connect"} if args.recover else {}))
    if not scenario.hardware_interface.video_source.strip():
        print("drake-rus hardware grab: error: field 'hardware_interface.video_source' is "
              "empty", file=sys.stderr)
        return 2
    station = _connect(scenario, "grab", keep_raw_pictures=True)
    if station is None:
        return 2
    try:
        import cv2
        frame = station.grabber.capture.wait_for(-1, timeout=5.0)
        if frame is None or frame.picture is None:
            print("drake-rus hardware grab: error: no picture within 5 s", file=sys.stderr)
            return 2
        q = np.array(station.GetOutputPort("joint_position").Eval(
            station.CreateDefaultContext()))
    finally:
        station.close()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    index_file = out / "targets.yaml"
    targets = load_target_set(index_file) if index_file.exists() else TargetSet(
        depth=scenario.imaging.depth, crop=list(scenario.hardware_interface.video_crop))
    name = f"grab_{len(targets.targets):03d}.png"
    cv2.imwrite(str(out / name), frame.picture)
    targets.targets.append(TargetImage(image=name, p_P=list(args.p_P) if args.p_P else [],
                                       q=[] if args.p_P else [float(v) for v in q]))
    index_file.write_text(yaml_dump_typed(targets))
    found = find_point_target(frame.picture, targets.crop, targets.search_radius_px,
                              targets.min_contrast)
    where = (f"target at column {found[0]:.1f}, row {found[1]:.1f}" if found is not None
             else "NO target found: check the crop and the gain")
    print(f"{out / name}: {where}; q = {np.array2string(q, precision=4)} rad; listed in "
          f"{index_file} ({len(targets.targets)} pictures, depth {targets.depth:g} m)")
    return 0 if found is not None else 1


def run_calibrate_image(args) -> int:
    prog = "drake-rus hardware calibrate-image"
    try:
        targets = load_target_set(args.targets)
        scenario = LoadScenario(filename=args.scenarios_file, scenario_name=args.scenario,
                                scenario_text=args.overrides)
        report = fit_target_set(targets, Path(args.targets).parent, scenario)
    except ValueError as e:          # ScenarioError too
        print(f"{prog}: refused: {e}", file=sys.stderr)
        return 2
    fit = report.fit
    print(f"depth {targets.depth:g} m: {fit.mm_per_pixel[0]:.4f} x {fit.mm_per_pixel[1]:.4f} "
          f"mm per pixel; origin (probe-face centre) at column {fit.origin_px[0]:.1f}, row "
          f"{fit.origin_px[1]:.1f}; in-plane angle {fit.angle_deg:+.2f} deg; mirrored: "
          f"{str(fit.mirror_x).lower()}; skew {fit.skew_deg:+.2f} deg")
    for name, px, p, r in zip(report.names, report.pixels, report.p_P, fit.residuals_mm):
        print(f"  {name}: target at ({px[0]:7.1f}, {px[1]:7.1f}) px, p_P = "
              f"({1e3 * p[0]:+7.1f}, {1e3 * p[2]:+7.1f}) mm (x, z): residual {r:.2f} mm")
    print(f"residuals: RMS {fit.rms_mm:.2f} mm, max {fit.max_residual_mm:.2f} mm over "
          f"{len(report.names)} targets")
    failures = []
    if fit.rms_mm > 0.5:
        failures.append(f"RMS residual {fit.rms_mm:.2f} mm > 0.5 mm")
    if fit.max_residual_mm > 1.0:
        failures.append(f"largest residual {fit.max_residual_mm:.2f} mm > 1.0 mm")
    if abs(fit.skew_deg) > 1.0:
        failures.append(f"picture axes skewed by {fit.skew_deg:+.2f} deg (> 1 deg)")
    if len(report.names) < 6:
        print(f"note: {len(report.names)} targets; 6 or more give a check on the fit")
    if failures and not args.force:
        print(f"{prog}: not written ({'; '.join(failures)}); re-take the worst pictures or "
              f"use --force")
        return 1
    out = Path(args.out)
    try:
        cal = load_image_calibration(out) if out.exists() else ImageCalibration()
    except ScenarioError as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 2
    old = cal.X_PI.GetDeterministicValue()
    cal = with_preset(cal, fit.preset(targets.depth, targets.crop), angle_deg=fit.angle_deg,
                      mirror_x=fit.mirror_x)
    if cal.presets and len(cal.presets) > 1:
        new = cal.X_PI.GetDeterministicValue()
        turn = math.degrees(np.arccos(np.clip(
            (np.trace(old.rotation().matrix().T @ new.rotation().matrix()) - 1) / 2, -1, 1)))
        if turn > 1.0:
            print(f"warning: the in-plane angle moved by {turn:.1f} deg from the file's; the "
                  f"other presets were fitted with the old one")
    save_image_calibration(cal, out)
    print(f"wrote {out} (entries for {', '.join(f'{p.depth:g}' for p in cal.presets)} m); "
          f"set hardware_interface.image_calibration: {out}")
    return 1 if failures else 0


@dataclasses.dataclass
class LatencyCalibration:
    """The latency estimate and its raw data: pose times (s, monotonic), tip positions
    (m), frame capture times (s), target image positions (px, NaN where not found)."""
    estimate: object
    pose_times: np.ndarray
    positions: np.ndarray
    frame_times: np.ndarray
    targets: np.ndarray


def RunLatencyCalibration(loop, station, *, amplitude: float = 0.01, period: float = 2.0,
                          cycles: float = 4.0, max_latency: float = 0.5,
                          realtime_rate: float = 1.0, check_period: float = 0.05,
                          on_step=None, min_contrast: float = 30.0,
                          context_out: dict | None = None) -> LatencyCalibration:
    """Moves the probe tip sinusoidally (``amplitude`` m, ``period`` s, ``cycles``) along
    its array direction projected on the base x-y plane, through the closed loop from
    :func:`BuildHardwareClosedLoop` (orientation held, force control off), records the
    station's pose history and every grabbed frame, finds the point target in each frame
    and estimates the video latency (``video.estimate_video_latency``; raises ValueError
    when it cannot). ``context_out["root"]`` receives the root context."""
    from pydrake.systems.analysis import Simulator

    grabber = station.grabber
    if grabber.capture is None:
        raise ValueError("field 'hardware_interface.video_source': no video source")
    simulator = Simulator(loop.diagram)
    root = simulator.get_context()
    if context_out is not None:
        context_out["root"] = root
    st_ctx = station.GetMyContextFromRoot(root)
    X0 = RigidTransform(station.GetOutputPort("X_BP").Eval(st_ctx))
    d = X0.rotation().matrix()[:2, 0]
    if np.linalg.norm(d) < 0.5:
        raise ValueError("calibrate-latency: the probe's array is not horizontal enough to "
                         "slide along it; tilt the probe towards vertical")
    d = d / np.linalg.norm(d)
    p0 = X0.translation()[:2].copy()
    grabber.pose_log, grabber.frame_log = [], []
    t_start = 0.5                                        # let the loop settle first

    def step():
        t = root.get_time()
        s = math.sin(2 * math.pi * (t - t_start) / period) if t >= t_start else 0.0
        loop.reference_value(root, "P_des").SetFromVector(p0 + amplitude * s * d)
        if on_step is not None:
            on_step()

    try:
        simulator.Initialize()
        RunHardware(simulator, station, t_start + cycles * period, check_period=check_period,
                    realtime_rate=realtime_rate, on_step=step)
        poses, frames = grabber.pose_log, grabber.frame_log
    finally:
        grabber.pose_log, grabber.frame_log = None, None
    pose_times = np.array([m for m, _ in poses])
    positions = np.array([X.translation() for _, X in poses])
    frame_times = np.array([m for m, _ in frames])
    targets = np.array([find_point_target(f.image, min_contrast=min_contrast) or
                        (math.nan, math.nan) for _, f in frames], float).reshape(-1, 2)
    estimate = estimate_video_latency(pose_times, positions, frame_times, targets,
                                      max_latency=max_latency)
    return LatencyCalibration(estimate, pose_times, positions, frame_times, targets)


def run_calibrate_latency(args) -> int:
    prog = "calibrate-latency"
    scenario = _load(args, dry_run="false", video_latency=0.0,
                     **({"error_recovery": "at_connect"} if args.recover else {}))
    station = _connect(scenario, prog)
    if station is None:
        return 2
    try:
        loop = BuildHardwareClosedLoop(scenario, station)
        print(f"moving the probe {1e3 * args.amplitude:g} mm each way along its array, "
              f"period {args.period:g} s, {args.cycles:g} periods, over the point target")
        holder = {}

        def on_step():
            if "readout" not in holder:
                holder["readout"] = Readout(
                    station, station.GetMyContextFromRoot(holder["root"]), args.readout_hz)
            holder["readout"].step()

        result = RunLatencyCalibration(loop, station, amplitude=args.amplitude,
                                       period=args.period, cycles=args.cycles,
                                       max_latency=args.max_latency, on_step=on_step,
                                       context_out=holder)
    except ValueError as e:
        print(f"drake-rus hardware {prog}: refused: {e}", file=sys.stderr)
        return 1
    except HardwareFault as e:
        print(f"drake-rus hardware {prog}: error: {e}", file=sys.stderr)
        return 2
    finally:
        station.close()
    est = result.estimate
    print(f"video latency {1e3 * est.latency:.1f} ms (correlation {est.correlation:+.3f}, "
          f"{est.frames} frames)")
    print(f"set hardware_interface.video_latency: {est.latency:.3f}")
    return 0
