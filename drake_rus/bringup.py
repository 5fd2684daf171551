"""Hardware bring-up procedures (docs/hardware_bringup.md) as a library: the checks of each
step, the scripted free-space motion, live read-outs, pivot and latency calibrations. The
``drake-rus hardware`` command (``drake_rus.hardware.cli``) is a thin front end over these;
the end-to-end tests call them directly.

The scripted motion runs the unchanged controller and safety layer on the hardware station
with the supervisor and force control off: at ``t_orientation`` the desired probe
orientation turns by ``angle`` about the base x axis, at ``t_slide`` the desired tip position
moves ``slide`` m along the base y axis.

It sits beside ``closed_loop`` (the station with the controller), above both stations: in
``drake_rus/hardware/`` it would close an import cycle between that folder and the closed
loop.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time

import numpy as np
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.analysis import Simulator

from drake_rus.closed_loop import BuildClosedLoop
from drake_rus.hardware.core import load_declaration, period_statistics
from drake_rus.hardware.image_calibration import find_point_target
from drake_rus.hardware.station import RunHardware
from drake_rus.hardware.systems import ProbeLoadTorque
from drake_rus.hardware.video import estimate_video_latency
from drake_rus.robot import MakeControlPlant

__all__ = [
    "ScriptedMotion",
    "MotionResult",
    "BuildHardwareClosedLoop",
    "RunScriptedMotion",
    "Readout",
    "motion_failures",
    "LatencyCalibration",
    "RunLatencyCalibration",
    "CheckStation",
    "RecordPivot",
    "pivot_failures",
    "image_fit_failures",
    "timing_report",
    "video_checks",
    "load_check",
    "push_checks",
    "APPROACH_TOLERANCE_DEG",
    "TIP_TOLERANCE_M",
]

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


# Step 3a: image calibration residuals (mm) and skew (deg).
IMAGE_RMS_MM = 0.5
IMAGE_MAX_MM = 1.0
IMAGE_SKEW_DEG = 1.0


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
    return BuildClosedLoop(
        scenario_for_motion(scenario), station=station, use_supervisor=False, log_period=None
    )


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
        out.append(
            f"tip x-y error {1e3 * result.position_error_xy:.2f} mm >= "
            f"{1e3 * TIP_TOLERANCE_M:.1f} mm"
        )
    if motion is not None and motion.settle_angle > 0 and result.end_time >= motion.duration:
        out.append(f"did not settle within {motion.duration:g} s")
    return out


def RunScriptedMotion(
    loop,
    station,
    motion: ScriptedMotion,
    *,
    realtime_rate: float = 1.0,
    check_period: float = 0.05,
    on_step=None,
    context_out: dict | None = None,
) -> MotionResult:
    """Runs ``motion`` on the closed loop (from :func:`BuildHardwareClosedLoop`) inside a
    hardware session (zero velocity at the end, on any exception or fault). ``on_step()``
    runs after every ``check_period`` s; ``context_out["root"]`` receives the root
    context."""
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
        return (
            np.arccos(np.clip(a @ a_target, -1, 1)) < motion.settle_angle
            and np.linalg.norm(X.translation()[:2] - p_target) < motion.settle_distance
        )

    simulator.Initialize()
    end = RunHardware(
        simulator,
        station,
        motion.duration,
        check_period=check_period,
        realtime_rate=realtime_rate,
        on_step=step,
        until=settled,
    )
    safety_ctx = loop.parts.safety.GetMyContextFromRoot(root)
    events = loop.parts.safety.GetOutputPort("safety_events").Eval(safety_ctx)
    frame = station.GetOutputPort("us_image").Eval(st_ctx)
    return MotionResult(
        X0,
        RigidTransform(station.GetOutputPort("X_BP").Eval(st_ctx)),
        a_target,
        o_target,
        p_target,
        q0,
        np.array(station.GetOutputPort("joint_position").Eval(st_ctx)),
        tuple(events),
        int(frame.frame_index) + 1,
        end,
    )


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
        sample = {
            "wall": time.monotonic() - self._start,
            "t": ctx.get_time(),
            "q": q,
            "f": F[3:6].copy(),
            "p_BP": X.translation().copy(),
            "fps": math.nan,
            "age": math.nan,
        }
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
        video = (
            f"video {sample['fps']:5.1f} fps, age {1e3 * sample['age']:4.0f} ms"
            if math.isfinite(sample["age"])
            else "no video"
        )
        print(
            f"{self.prefix}t={sample['t']:6.2f} s  q=["
            + " ".join(f"{v:+.3f}" for v in sample["q"])
            + "] rad  f=["
            + " ".join(f"{v:+5.1f}" for v in sample["f"])
            + f"] N |f|="
            f"{np.linalg.norm(sample['f']):4.1f} N  {video}",
            file=self.out,
            flush=True,
        )


def timing_report(station, config) -> tuple[str, list[str]]:
    """The control loop's tick timing (wall clock) and the watchdog checks on it."""
    ticks = list(station.grabber.tick_times)[5:]  # skip the start-up ticks
    st = period_statistics(ticks)
    if not st["count"]:
        return "control loop: no ticks", []
    line = (
        f"control loop: {st['count']} periods, mean {1e3 * st['mean']:.2f} ms, p99 "
        f"{1e3 * st['p99']:.1f} ms, p99.9 {1e3 * st['p999']:.1f} ms, max "
        f"{1e3 * st['max']:.1f} ms (command_timeout {1e3 * config.command_timeout:.0f} ms, "
        f"status_timeout {1e3 * config.status_timeout:.0f} ms)"
    )
    failures = []
    if st["max"] > config.command_timeout:
        failures.append(
            f"the control loop stalled {1e3 * st['max']:.0f} ms, longer than "
            f"hardware_interface.command_timeout ({1e3 * config.command_timeout:.0f}"
            f" ms): commands would expire mid-motion (raise it, or use the "
            f"real-time PC)"
        )
    return line, failures


def status_age_report(station, config) -> tuple[str | None, list[str]]:
    """The LCM route's clock check (docs/hardware_bringup.md, "Clock synchronisation"):
    the wall-clock age of the robot's statuses at arrival (this PC's wall clock minus the
    driver's ``utime``: the transport delay plus the offset between the two clocks). A
    median beyond a third of ``command_timeout`` either way fails: the driver judges our
    commands' freshness by the same two clocks, so an offset that large eats the command
    expiry's margin (client ahead: stale commands look fresh; behind: every command
    expires). (None, []) on the franky route, which has no wall-clock stamps."""
    if config.backend != "lcm":
        return None, []
    ages = np.asarray(station.GetSubsystemByName("panda_status_latch").status_ages, float)
    if not ages.size:
        return "robot status age: no status arrived", ["no robot status arrived during the check"]
    median = float(np.median(ages))
    bound = config.command_timeout / 3.0
    line = (
        f"robot status age at arrival: median {1e3 * median:.1f} ms, min "
        f"{1e3 * ages.min():.1f} ms, max {1e3 * ages.max():.1f} ms (this PC's wall clock minus "
        f"the driver's; within +-{1e3 * bound:.0f} ms, a third of command_timeout)"
    )
    failures = []
    if abs(median) > bound:
        failures.append(
            f"the robot's statuses arrive {1e3 * median:.0f} ms old by this PC's wall clock: "
            f"its clock and the driver's differ by more than a third of "
            f"hardware_interface.command_timeout ({1e3 * config.command_timeout:.0f} ms); "
            f"synchronise them (PTP or chrony) or run the client on the driver's PC"
        )
    return line, failures


def video_checks(scenario, station, readout: Readout) -> list[str]:
    capture = station.grabber.capture
    if capture is None:
        return []
    stats = capture.stats()
    failures = []
    print(
        f"video: {stats.frames} frames, {stats.frame_rate_hz:.1f} fps, newest "
        f"{1e3 * stats.age:.0f} ms old, {stats.failures} read failures, video_latency "
        f"{1e3 * station.grabber.video_latency:.0f} ms"
    )
    want = FRAME_RATE_FRACTION * scenario.imaging.frame_rate_hz
    if stats.frame_rate_hz < want:
        failures.append(
            f"video frame rate {stats.frame_rate_hz:.1f} fps < {want:.0f} fps "
            f"({FRAME_RATE_FRACTION:.0%} of imaging.frame_rate_hz)"
        )
    age = stats.age + station.grabber.video_latency
    if age > scenario.safety.image_timeout:
        failures.append(
            f"frames are {1e3 * age:.0f} ms old (age + video_latency) > "
            f"safety.image_timeout {1e3 * scenario.safety.image_timeout:.0f} ms: "
            f"the stale-image watchdog would stop the robot"
        )
    if stats.error:
        failures.append(f"video: {stats.error}")
    return failures


def load_check(scenario, station) -> list[str]:
    """LCM route: do the driver's torques at rest carry the probe's weight?"""
    backend = station.backend
    if not hasattr(backend, "rest_tau"):
        return []
    plant, _ = MakeControlPlant(scenario.robot, scenario.probe)
    load = ProbeLoadTorque(plant, scenario.probe.mass, scenario.probe.p_FCm)(backend.rest_q)
    verdict = load_declaration(backend.rest_tau, load)
    compensate = scenario.hardware_interface.lcm_compensate_load
    print(
        f"probe load: the external torques at rest look {verdict} (the probe's weight is "
        f"{np.linalg.norm(load):.2f} N m in joint space; lcm_compensate_load: "
        f"{str(compensate).lower()})"
    )
    if verdict == "undeclared" and not compensate:
        return [
            "the robot does not know the probe's weight: enter the probe holder in Desk "
            "as the end effector, or set hardware_interface.lcm_compensate_load: true"
        ]
    if verdict == "declared" and compensate:
        return [
            "the probe's weight is removed twice (Desk knows it and "
            "lcm_compensate_load is true): set lcm_compensate_load: false"
        ]
    return []


def push_checks(readout: Readout, rest: float) -> list[str]:
    """Guide step 4: hands off for ``rest`` s (force below REST_FORCE_N), then a push on the
    probe face gives f_z < 0."""
    failures = []
    quiet = [np.linalg.norm(f) for w, _, f in readout.forces if w <= rest]
    if quiet:
        worst = float(np.max(quiet))
        print(f"push test: |probe_force| at rest (first {rest:g} s) up to {worst:.2f} N")
        if worst > REST_FORCE_N:
            failures.append(
                f"probe_force at rest {worst:.2f} N > {REST_FORCE_N:g} N (check "
                f"the probe's mass / centre of mass, set_load or "
                f"lcm_compensate_load, tau_external_bias_duration)"
            )
    pushes = [
        (np.linalg.norm(f), f)
        for w, _, f in readout.forces
        if w > rest and np.linalg.norm(f) >= PUSH_FORCE_N
    ]
    if pushes:
        _, f = max(pushes, key=lambda x: x[0])
        print(f"push test: strongest push f = [{f[0]:+.1f} {f[1]:+.1f} {f[2]:+.1f}] N")
        if f[2] >= 0:
            failures.append(
                f"a push on the probe face gave f_z = {f[2]:+.1f} N >= 0: the "
                f"external torque sign is wrong (or the push was not along the "
                f"probe's axis)"
            )
    else:
        print(f"push test: no push seen (|f| < {PUSH_FORCE_N:g} N after the first {rest:g} s)")
    return failures


def CheckStation(
    scenario,
    station,
    *,
    dry_run: bool = True,
    duration: float = 2.0,
    rest: float = 1.0,
    readout_hz: float = 4.0,
) -> list[str]:
    """The bring-up check of docs/hardware_bringup.md on a connected ``station``: read-outs,
    the probe-load check, and either a dry run of ``duration`` s (the push test after
    ``rest`` s hands off, video and loop-timing checks) or, with ``dry_run`` False, the
    scripted free-space motion. Prints what it measures; returns the missed checks (empty:
    all passed)."""

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

        print(
            f"FR3 collision thresholds (contact / collision): joints "
            f"{fmt(thresholds['lower_torque'])} / {fmt(thresholds['upper_torque'])} N m, "
            f"wrench {fmt(thresholds['lower_force'])} / {fmt(thresholds['upper_force'])} "
            f"(N, N m)"
        )
    failures = load_check(scenario, station)
    if dry_run:
        simulator = Simulator(station)
        sc = station.GetMyContextFromRoot(simulator.get_context())
        station.get_input_port().FixValue(sc, np.zeros(7))
        readout = Readout(station, sc, readout_hz)
        if duration > rest:
            print(
                f"hands off the probe for {rest:g} s, then push its face along its axis (push test)"
            )
        simulator.Initialize()
        RunHardware(simulator, station, duration, on_step=readout.step)
        F = station.GetOutputPort("probe_force").Eval(sc)
        frame = station.GetOutputPort("us_image").Eval(sc)
        print(f"probe_force = {np.array2string(np.asarray(F), precision=2)} (N m, N)")
        print(f"frames grabbed: {frame.frame_index + 1} in {duration:g} s")
        failures += push_checks(readout, rest)
        failures += video_checks(scenario, station, readout)
        line, timing = timing_report(station, cfg)
        print(line)
        failures += timing
        line, clock = status_age_report(station, cfg)
        if line is not None:
            print(line)
        failures += clock
        print("dry run: no motion was commanded")
        return failures
    loop = BuildHardwareClosedLoop(scenario, station)
    motion = ScriptedMotion(duration=15.0, settle_angle=math.radians(0.5), settle_distance=1.5e-3)
    holder = {}

    def on_step():
        if "readout" not in holder:
            holder["readout"] = Readout(
                station, station.GetMyContextFromRoot(holder["root"]), readout_hz
            )
        holder["readout"].step()

    result = RunScriptedMotion(loop, station, motion, on_step=on_step, context_out=holder)
    print(
        f"approach error {math.degrees(result.approach_error):.2f} deg, tip x-y error "
        f"{1e3 * result.position_error_xy:.1f} mm, safety events: "
        f"{[e.reason for e in result.safety_events] or 'none'}"
    )
    failures += motion_failures(result, motion)
    if "readout" in holder:
        failures += video_checks(scenario, station, holder["readout"])
    line, timing = timing_report(station, cfg)
    print(line)
    line, clock = status_age_report(station, cfg)
    if line is not None:
        print(line)
    return failures + timing + clock


def pivot_failures(cal) -> list[str]:
    """The guide's checks of a pivot calibration (step 2) that ``cal`` missed."""
    failures = []
    if cal.rms > PIVOT_RMS_M:
        failures.append(f"RMS residual {1e3 * cal.rms:.2f} mm > {1e3 * PIVOT_RMS_M:.1f} mm")
    if cal.residuals.max() > PIVOT_MAX_M:
        worst = np.argsort(cal.residuals)[::-1][:3]
        failures.append(
            f"largest residual {1e3 * cal.residuals.max():.2f} mm > "
            f"{1e3 * PIVOT_MAX_M:.1f} mm (samples {list(map(int, worst))}: the tip "
            f"left the divot?)"
        )
    return failures


def image_fit_failures(fit) -> list[str]:
    """The guide's checks of an image calibration fit (step 3a) that ``fit`` missed."""
    failures = []
    if fit.rms_mm > IMAGE_RMS_MM:
        failures.append(f"RMS residual {fit.rms_mm:.2f} mm > {IMAGE_RMS_MM} mm")
    if fit.max_residual_mm > IMAGE_MAX_MM:
        failures.append(f"largest residual {fit.max_residual_mm:.2f} mm > {IMAGE_MAX_MM} mm")
    if abs(fit.skew_deg) > IMAGE_SKEW_DEG:
        failures.append(
            f"picture axes skewed by {fit.skew_deg:+.2f} deg (> {IMAGE_SKEW_DEG:g} deg)"
        )
    return failures


def RecordPivot(station, duration: float, rate_hz: float, readout_hz: float = 4.0):
    """Records the joint positions (rad, ``rate_hz`` samples a second) for ``duration`` s
    while the operator pivots the probe tip in a divot, with live read-outs; zero velocity
    throughout. Returns (N, 7)."""
    simulator = Simulator(station)
    sc = station.GetMyContextFromRoot(simulator.get_context())
    station.get_input_port().FixValue(sc, np.zeros(7))
    readout = Readout(station, sc, readout_hz)
    recorded, next_t = [], [0.0]

    def step():
        readout.step()
        if time.monotonic() >= next_t[0]:
            next_t[0] = time.monotonic() + 1.0 / rate_hz
            recorded.append(np.array(station.GetOutputPort("joint_position").Eval(sc)))

    simulator.Initialize()
    RunHardware(simulator, station, duration, on_step=step)
    return np.array(recorded)


@dataclasses.dataclass
class LatencyCalibration:
    """The latency estimate and its raw data: pose times (s, monotonic), tip positions
    (m), frame capture times (s), target image positions (px, NaN where not found)."""

    estimate: object
    pose_times: np.ndarray
    positions: np.ndarray
    frame_times: np.ndarray
    targets: np.ndarray


def RunLatencyCalibration(
    loop,
    station,
    *,
    amplitude: float = 0.01,
    period: float = 2.0,
    cycles: float = 4.0,
    max_latency: float = 0.5,
    realtime_rate: float = 1.0,
    check_period: float = 0.05,
    on_step=None,
    min_contrast: float = 30.0,
    context_out: dict | None = None,
) -> LatencyCalibration:
    """Moves the probe tip sinusoidally (``amplitude`` m, ``period`` s, ``cycles``) along
    its array direction projected on the base x-y plane, through the closed loop from
    :func:`BuildHardwareClosedLoop` (orientation held, force control off), records the
    station's pose history and every grabbed frame, finds the point target in each frame
    and estimates the video latency (``video.estimate_video_latency``; raises ValueError
    when it cannot). ``context_out["root"]`` receives the root context."""
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
        raise ValueError(
            "calibrate-latency: the probe's array is not horizontal enough to "
            "slide along it; tilt the probe towards vertical"
        )
    d = d / np.linalg.norm(d)
    p0 = X0.translation()[:2].copy()
    grabber.pose_log, grabber.frame_log = [], []
    t_start = 0.5  # let the loop settle first

    def step():
        t = root.get_time()
        s = math.sin(2 * math.pi * (t - t_start) / period) if t >= t_start else 0.0
        loop.reference_value(root, "P_des").SetFromVector(p0 + amplitude * s * d)
        if on_step is not None:
            on_step()

    try:
        simulator.Initialize()
        RunHardware(
            simulator,
            station,
            t_start + cycles * period,
            check_period=check_period,
            realtime_rate=realtime_rate,
            on_step=step,
        )
        poses, frames = grabber.pose_log, grabber.frame_log
    finally:
        grabber.pose_log, grabber.frame_log = None, None
    pose_times = np.array([m for m, _ in poses])
    positions = np.array([X.translation() for _, X in poses])
    frame_times = np.array([m for m, _ in frames])
    targets = np.array(
        [
            find_point_target(f.image, min_contrast=min_contrast) or (math.nan, math.nan)
            for _, f in frames
        ],
        float,
    ).reshape(-1, 2)
    estimate = estimate_video_latency(
        pose_times, positions, frame_times, targets, max_latency=max_latency
    )
    return LatencyCalibration(estimate, pose_times, positions, frame_times, targets)
