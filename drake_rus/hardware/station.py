"""The hardware station: the simulated station's ports, on a real FR3 and ultrasound machine.

``MakeHardwareStation(scenario, meshcat=None)`` returns a :class:`HardwareStation` (a Diagram)
exporting what the simulated station (``drake_rus.station.MakeSimStation``) exports, so the
controller and safety layer are built the
same way on both (docs/design.md):

The ports (name, size, unit, frame, which station) are listed once, in
``drake_rus.station_interface.STATION_PORTS``; the station checks itself against them when
built. Here ``us_image`` comes from the frame grabber: the newest picture of a capture
thread, mapped onto the probe's image grid by the image calibration, stamped with the probe
pose and the diagram time of its acquisition instant (``video.py``); the hardware-only
``commanded_velocity`` is what went to the robot after the client-side guard and
``robot_ok`` turns 0 once the robot or its connection failed.

Backends (``scenario.hardware_interface.backend``):

- ``franky``: franky-control (libfranka 0.21) in joint-velocity mode; the 1 kHz loop stays in
  the library, we send targets at ``command_rate_hz``;
- ``lcm``: drake-franka-driver through Drake's ``PandaCommandSender`` /
  ``PandaStatusReceiver`` over ``LcmInterfaceSystem``, channels PANDA_COMMAND / PANDA_STATUS,
  velocity mode, commands stamped with wall-clock microseconds, the driver's external torque
  sign flipped to Drake's and (``lcm_compensate_load``) the probe's weight removed, since
  the driver cannot declare a load.

Safety on hardware, in addition to the safety layer: the client-side guard (velocity and
acceleration limits below the robot's, zero on dry run or fault), a command watchdog (no fresh
command -> zero velocity), and :class:`HardwareSession` / :func:`RunHardware`, which end every
run (normal end, Ctrl-C, any exception, a lost connection) with a zero-velocity command.
"""

from __future__ import annotations

import logging
import signal
import threading

import numpy as np
from pydrake.systems.framework import Diagram, DiagramBuilder
from pydrake.systems.primitives import PassThrough

from drake_rus.config_schema import ScenarioError
from drake_rus.control.config import SafetyConfig
from drake_rus.hardware.config import HardwareConfig
from drake_rus.hardware.franky_backend import FrankyBackend, HardwareFault
from drake_rus.hardware.image_calibration import (
    ImageToProbeMap,
    load_image_calibration,
    preset_for_depth,
)
from drake_rus.hardware.lcm_backend import AddLcmBackend, LcmBackend, wait_for_panda_status
from drake_rus.hardware.systems import (
    CommandGuard,
    FrameGrabber,
    FrankaRobotInterface,
    ProbeLoadTorque,
)
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.pacing import RealtimePacer
from drake_rus.robot import NUM_JOINTS, MakeControlPlant, ProbeForceEstimator, ProbePoseFromJoints
from drake_rus.station_interface import CheckStationPorts

LOG = logging.getLogger("drake_rus.hardware")

__all__ = [
    "MakeHardwareStation",
    "HardwareStation",
    "HardwareSession",
    "RunHardware",
    "HardwareFault",
    "LcmBackend",
    "wait_for_panda_status",
    "picture_processing",
]
# LcmBackend and wait_for_panda_status live in drake_rus.hardware.lcm_backend (re-exported
# here for the station's users), as FrankyBackend lives in franky_backend.


class HardwareStation(Diagram):
    """The hardware station Diagram, with handles on its backend for a clean stop and on its
    frame grabber (``grabber``: pose history, diagram clock, tick times, video stats);
    ``realtime_lag`` (s): how far behind the wall clock a run on it may fall before it is
    stopped (the scenario's ``safety.realtime_lag``; :func:`RunHardware`)."""

    def __init__(
        self,
        builder: DiagramBuilder,
        backend,
        grabber: FrameGrabber,
        config,
        realtime_lag: float = SafetyConfig().realtime_lag,
    ):
        super().__init__()
        builder.BuildInto(self)
        self.backend = backend
        self.grabber = grabber
        self.hardware_config = config
        self.realtime_lag = float(realtime_lag)

    @property
    def period(self) -> float:
        """Its fastest periodic rate's period (s): commands sent, state and frames read
        every 1 / ``command_rate_hz``; a live run is paced at it."""
        return 1.0 / float(self.hardware_config.command_rate_hz)

    def stop(self) -> None:
        """Zero velocity now (never raises)."""
        try:
            self.backend.stop()
        except Exception as e:
            LOG.error("stop: %s: %s", type(e).__name__, e)

    def close(self) -> None:
        """Stops the robot, releases the robot connection and the frame grabber."""
        try:
            self.backend.close()
        finally:
            self.grabber.release()


def _check_rates(scenario) -> None:
    # Sending targets at a whole multiple of the controller's rate (the default 200 Hz for a
    # 100 Hz controller) re-sends every command on time; slower is refused by the scenario
    # (drake_rus.config_schema.CROSS_FIELD_RULES); another ratio jitters: warn.
    cfg = scenario.hardware_interface
    ratio = cfg.command_rate_hz / scenario.controller.rate_hz
    if abs(ratio - round(ratio)) > 1e-6 or round(ratio) < 1:
        LOG.warning(
            "hardware_interface.command_rate_hz (%g Hz) is not a whole multiple of "
            "controller.rate_hz (%g Hz)",
            cfg.command_rate_hz,
            scenario.controller.rate_hz,
        )


def picture_processing(scenario):
    """The grabbed picture -> ``us_image`` map for the scenario: with
    ``hardware_interface.image_calibration``, the metric :class:`ImageToProbeMap` of the
    entry for ``imaging.depth``; without, None (the grabber then crops ``video_crop`` and
    stretches to the image size, which is not metric: logged)."""
    cfg = scenario.hardware_interface
    if not cfg.image_calibration.strip():
        if cfg.video_source.strip():
            LOG.warning(
                "hardware_interface.image_calibration is empty: frames are the crop "
                "stretched to the image size, not metric (docs/hardware_bringup.md, "
                "step 3a)"
            )
        return None
    path = cfg.image_calibration.strip()
    cal = load_image_calibration(path)
    preset = preset_for_depth(cal, scenario.imaging.depth, source=path)
    return ImageToProbeMap(cal, preset, ProbeGeometry.from_config(scenario.imaging))


def MakeHardwareStation(
    scenario,
    meshcat=None,
    *,
    lcm=None,
    lcm_idle=None,
    name: str = "station",
    video=None,
    keep_raw_pictures: bool = False,
) -> HardwareStation:
    """The station on the real robot (``scenario.hardware: true``); see the module doc.

    Connects at once (raises HardwareFault naming the field when the robot or the driver
    cannot be reached, ScenarioError / ValueError for a bad video source, crop or image
    calibration). ``lcm``: a DrakeLcm to use instead of ``hardware_interface.lcm_url``
    (tests: ``memq://``); ``lcm_idle()``: called while waiting for the driver's first
    statuses (a simulated driver stepped in the same thread). ``video``: a source (string,
    or an object with ``read()`` such as ``video.SyntheticVideo``) instead of
    ``hardware_interface.video_source``; ``keep_raw_pictures``: the capture thread also keeps
    the unprocessed picture (calibration tools). ``meshcat`` is accepted for symmetry with
    the sim station (unused).
    """
    cfg: HardwareConfig = scenario.hardware_interface
    _check_rates(scenario)
    rate = float(cfg.command_rate_hz)
    control_plant, tip_frame = MakeControlPlant(scenario.robot, scenario.probe)
    control_plant.set_name("control_plant")
    builder = DiagramBuilder()

    command = builder.AddNamedSystem("joint_velocity_command", PassThrough(NUM_JOINTS))
    guard = builder.AddNamedSystem("command_guard", CommandGuard(cfg, rate))
    builder.Connect(command.get_output_port(), guard.GetInputPort("joint_velocity_command"))

    # Grabber first: a bad video source, crop or calibration fails before we touch the robot.
    image_shape = (scenario.imaging.image_height_px, scenario.imaging.image_width_px)
    grabber = FrameGrabber(
        cfg,
        image_shape,
        rate,
        process=picture_processing(scenario),
        source=video,
        keep_raw=keep_raw_pictures,
    )
    probe = scenario.probe
    try:
        if cfg.backend == "franky":
            backend = FrankyBackend(
                cfg, load=(probe.mass, list(probe.p_FCm), np.diag(probe.inertia_diagonal))
            )
            robot = builder.AddNamedSystem("franka", FrankaRobotInterface(backend, rate))
            builder.Connect(
                guard.GetOutputPort("joint_velocity_sent"),
                robot.GetInputPort("joint_velocity_sent"),
            )
            builder.Connect(robot.GetOutputPort("robot_ok"), guard.GetInputPort("robot_ok"))
            q_port = robot.GetOutputPort("joint_position")
            v_port = robot.GetOutputPort("joint_velocity")
            tau_port = robot.GetOutputPort("tau_external")
            sent_port = robot.GetOutputPort("commanded_velocity")
            ok_port = robot.GetOutputPort("robot_ok")
            time_port = robot.GetOutputPort("state_time")
        elif cfg.backend == "lcm":
            load_torque = (
                ProbeLoadTorque(control_plant, probe.mass, probe.p_FCm)
                if cfg.lcm_compensate_load
                else None
            )
            backend = LcmBackend(cfg, lcm, lcm_idle, load_torque=load_torque)
            q_port, v_port, tau_port, sent_port, ok_port, time_port = AddLcmBackend(
                builder, backend, guard, rate, control_plant, probe
            )
        else:
            raise ScenarioError(
                f"field 'hardware_interface.backend': unknown backend {cfg.backend!r}"
            )
    except BaseException:
        grabber.release()
        raise

    builder.AddNamedSystem("frame_grabber", grabber)
    fk = builder.AddNamedSystem("probe_pose", ProbePoseFromJoints(control_plant, tip_frame))
    builder.Connect(q_port, fk.get_input_port(0))
    builder.Connect(fk.get_output_port(), grabber.GetInputPort("X_BP"))
    builder.Connect(time_port, grabber.GetInputPort("state_time"))
    estimator = builder.AddNamedSystem(
        "probe_force_estimator", ProbeForceEstimator(control_plant, tip_frame)
    )
    builder.Connect(q_port, estimator.get_input_port(0))
    builder.Connect(tau_port, estimator.get_input_port(1))

    builder.ExportInput(command.get_input_port(), "joint_velocity_command")
    builder.ExportOutput(q_port, "joint_position")
    builder.ExportOutput(v_port, "joint_velocity")
    builder.ExportOutput(fk.get_output_port(), "X_BP")
    builder.ExportOutput(tau_port, "tau_external")
    builder.ExportOutput(estimator.get_output_port(), "probe_force")
    builder.ExportOutput(grabber.GetOutputPort("us_image"), "us_image")
    builder.ExportOutput(sent_port, "commanded_velocity")
    builder.ExportOutput(ok_port, "robot_ok")
    station = HardwareStation(builder, backend, grabber, cfg, scenario.safety.realtime_lag)
    station.set_name(name)
    try:
        CheckStationPorts(station, "hardware")
    except BaseException:
        station.close()
        raise
    return station


class HardwareSession:
    """``with HardwareSession(station):`` ends in a zero-velocity command however the block
    ends (normal exit, any exception, Ctrl-C / SIGTERM, which become KeyboardInterrupt).
    ``close=True`` also releases the robot and the grabber on exit."""

    def __init__(self, station: HardwareStation, close: bool = False):
        self.station = station
        self._close = close
        self._previous = {}

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():

            def interrupt(signum, frame):
                raise KeyboardInterrupt(f"signal {signum}")

            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, interrupt)
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is not None:
            LOG.error("hardware run ended by %s: %s: zero velocity", exc_type.__name__, exc)
        try:
            if self._close:
                self.station.close()
            else:
                self.station.stop()
        finally:
            for sig, handler in self._previous.items():
                signal.signal(sig, handler)
            self._previous.clear()
        return False


def RunHardware(
    simulator,
    station: HardwareStation,
    duration: float,
    *,
    check_period: float = 0.05,
    realtime_rate: float = 1.0,
    on_step=None,
    until=None,
    max_lag: float | None = None,
) -> float:
    """Advances ``simulator`` (whose diagram contains ``station``) by ``duration`` s inside
    a :class:`HardwareSession`, in chunks of ``check_period`` s, calling ``on_step()`` after
    each and ending early when ``until()`` returns True; raises HardwareFault as soon as the
    station's ``robot_ok`` drops (the command is zero by then). Returns the end time.

    ``realtime_rate`` 1 (a live robot): paced tick by tick at the station's period
    (:class:`drake_rus.pacing.RealtimePacer`: no racing through ticks after a stall), and
    stopped with HardwareFault (zero velocity) when the loop falls more than ``max_lag`` s
    (default: the station's ``realtime_lag``, the scenario's ``safety.realtime_lag``) behind
    the wall clock, as a live scan is. 0: as fast
    as possible (a simulated driver stepped by ``on_step``); other rates: Drake's own
    pacing, for simulated drivers only."""
    if not realtime_rate >= 0.0:
        raise ValueError(f"RunHardware: realtime_rate must be >= 0, got {realtime_rate}")
    root = simulator.get_context()
    station_context = station.GetMyContextFromRoot(root)
    ok_port = station.GetOutputPort("robot_ok")
    t_end = root.get_time() + duration
    pacer = None
    if realtime_rate == 1.0:
        simulator.set_target_realtime_rate(0.0)  # the pacer keeps time, tick by tick
        lag = station.realtime_lag if max_lag is None else float(max_lag)
        pacer = RealtimePacer(simulator, station.period, lag)
    else:
        simulator.set_target_realtime_rate(realtime_rate)
    with HardwareSession(station):
        while root.get_time() < t_end - 1e-12:
            target = min(t_end, root.get_time() + check_period)
            if pacer is None:
                simulator.AdvanceTo(target)
            else:
                pacer.advance_to(target)
                if pacer.overload is not None:
                    raise HardwareFault(
                        f"run stopped at t = {root.get_time():.3f} s: overloaded: {pacer.overload}"
                    )
            if on_step is not None:
                on_step()
            if ok_port.Eval(station_context)[0] < 0.5:
                fault = getattr(station.backend, "fault", None) or "robot state lost"
                raise HardwareFault(f"hardware fault at t = {root.get_time():.3f} s: {fault}")
            if until is not None and until():
                break
    return root.get_time()
