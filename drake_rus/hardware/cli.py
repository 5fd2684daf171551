"""``drake-rus hardware check``: connect to the robot and the frame grabber, read, and
(only without --dry-run) run a short scripted motion in free space.

    drake-rus hardware check --dry-run --set "{hardware_interface: {robot_ip: 172.16.0.2}}"

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

import numpy as np
from pydrake.math import RigidTransform, RotationMatrix

from drake_rus.closed_loop import BuildClosedLoop
from drake_rus.demo import add_scenario_arguments
from drake_rus.hardware.station import HardwareFault, MakeHardwareStation, RunHardware
from drake_rus.scenario import ApplyOverrides, LoadScenario

__all__ = ["ScriptedMotion", "MotionResult", "BuildHardwareClosedLoop", "RunScriptedMotion",
           "add_commands"]


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


def add_commands(subparsers) -> None:
    p = subparsers.add_parser(
        "hardware", help="the real robot: connection check, dry run, scripted motion",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="hardware_command", metavar="HARDWARE_COMMAND")
    sub.required = True
    c = sub.add_parser("check", help="connect, read joints / torques / images; with "
                       "--no-dry-run also run the scripted free-space motion")
    add_scenario_arguments(c)
    group = c.add_mutually_exclusive_group()
    group.add_argument("--dry-run", dest="dry_run", action="store_true", default=True,
                       help="read only, never command motion (default)")
    group.add_argument("--no-dry-run", dest="dry_run", action="store_false",
                       help="also run the scripted motion: 5 deg tilt, 2 cm slide, no contact")
    c.add_argument("--duration", type=float, default=2.0,
                   help="seconds of reading in a dry run (default 2)")
    c.set_defaults(func=run_check)


def run_check(args) -> int:

    scenario = LoadScenario(filename=args.scenarios_file, scenario_name=args.scenario,
                            scenario_text=args.overrides)
    scenario = ApplyOverrides(scenario, "{hardware: true, hardware_interface: {dry_run: %s}}"
                              % ("true" if args.dry_run else "false"))
    try:
        station = MakeHardwareStation(scenario)
    except HardwareFault as e:
        print(f"drake-rus hardware check: error: {e}", file=sys.stderr)
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

    ctx = station.CreateDefaultContext()
    q = station.GetOutputPort("joint_position").Eval(ctx)
    X = station.GetOutputPort("X_BP").Eval(ctx)
    print(f"connected ({scenario.hardware_interface.backend}); q = "
          f"{np.array2string(np.asarray(q), precision=4)} rad")
    print(f"probe tip p_BP = {np.array2string(X.translation(), precision=4)} m")
    if args.dry_run:
        simulator = Simulator(station)
        station.get_input_port().FixValue(station.GetMyContextFromRoot(
            simulator.get_context()), np.zeros(7))
        simulator.Initialize()
        RunHardware(simulator, station, args.duration)
        sc = station.GetMyContextFromRoot(simulator.get_context())
        F = station.GetOutputPort("probe_force").Eval(sc)
        frame = station.GetOutputPort("us_image").Eval(sc)
        print(f"probe_force = {np.array2string(np.asarray(F), precision=2)} (N m, N)")
        print(f"frames grabbed: {frame.frame_index + 1} in {args.duration:g} s")
        print("dry run: no motion was commanded")
        return 0
    loop = BuildHardwareClosedLoop(scenario, station)
    result = RunScriptedMotion(loop, station, ScriptedMotion(
        duration=15.0, settle_angle=math.radians(0.5), settle_distance=1.5e-3))
    print(f"approach error {math.degrees(result.approach_error):.2f} deg, tip x-y error "
          f"{1e3 * result.position_error_xy:.1f} mm, safety events: "
          f"{[e.reason for e in result.safety_events] or 'none'}")
    return 0 if not result.safety_events else 1

