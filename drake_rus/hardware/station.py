"""The hardware station: the simulated station's ports, on a real FR3 and ultrasound machine.

``MakeHardwareStation(scenario, meshcat=None)`` returns a :class:`HardwareStation` (a Diagram)
exporting what the simulated station (``drake_rus.station.MakeSimStation``) exports, so the controller and safety layer are built the
same way on both (docs/design.md):

- input ``joint_velocity_command`` (7, rad/s);
- outputs ``joint_position`` (7, rad), ``joint_velocity`` (7, rad/s), ``X_BP`` (abstract
  RigidTransform, our FR3 model's FK with the scenario's probe calibration),
  ``tau_external`` (7, N m, Drake's sign: on the arm by the environment), ``probe_force``
  (6, through the same ``ProbeForceEstimator`` as in simulation), ``us_image`` (abstract
  UsFrame from the frame grabber: the newest picture of a capture thread, mapped onto the
  probe's image grid by the image calibration, stamped with the probe pose and the diagram
  time of its acquisition instant, see ``video.py``);
- hardware only: ``commanded_velocity`` (7, rad/s: what went to the robot after the
  client-side guard), ``robot_ok`` (1: 0 once the robot or its connection failed).

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
import time

import numpy as np
from pydrake.systems.framework import Diagram, DiagramBuilder
from pydrake.systems.primitives import PassThrough

from drake_rus.config_schema import ScenarioError
from drake_rus.hardware.config import HardwareConfig
from drake_rus.hardware.core import external_torque_to_drake, wall_clock_utime
from drake_rus.hardware.franky_backend import FrankyBackend, HardwareFault
from drake_rus.hardware.image_calibration import (
    ImageToProbeMap, load_image_calibration, preset_for_depth)
from drake_rus.hardware.systems import (
    CommandGuard, ExternalTorqueToDrake, FrameGrabber, FrankaRobotInterface, PandaStatusLatch,
    ProbeLoadCompensation, ProbeLoadTorque, WallClockCommandStamper)
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.robot import (
    NUM_JOINTS, MakeControlPlant, ProbeForceEstimator, ProbePoseFromJoints)

LOG = logging.getLogger("drake_rus.hardware")

__all__ = ["MakeHardwareStation", "HardwareStation", "HardwareSession", "RunHardware",
           "HardwareFault", "LcmBackend", "wait_for_panda_status", "picture_processing"]


def wait_for_panda_status(lcm, channel: str, timeout: float, *, count: int = 1,
                          duration: float = 0.0, idle=None) -> list[bytes]:
    """Pumps ``lcm`` until ``count`` lcmt_panda_status messages arrived on ``channel`` and
    ``duration`` s passed (or raises HardwareFault after ``timeout`` s). ``idle()``, if
    given, is called between pumps (e.g. to step a simulated driver in the same thread).
    Returns the raw messages."""
    received: list[bytes] = []
    active = [True]

    def handler(data: bytes):
        if active[0]:       # the raw subscription outlives this call: stop collecting
            received.append(bytes(data))

    lcm.Subscribe(channel, handler)
    start = time.monotonic()
    while len(received) < count or time.monotonic() - start < duration:
        if time.monotonic() - start > timeout:
            active[0] = False
            raise HardwareFault(
                f"field 'hardware_interface.lcm_status_channel': no lcmt_panda_status on "
                f"{channel!r} within {timeout:g} s (hardware_interface.connect_timeout); is "
                f"drake-franka-driver running and is hardware_interface.lcm_url right?")
        if idle is not None:
            idle()
        lcm.HandleSubscriptions(0 if idle is not None else 10)
    active[0] = False
    return received


class LcmBackend:
    """The LCM side of a hardware station: the DrakeLcm, its channels, the clean stop."""

    def __init__(self, config: HardwareConfig, lcm=None, idle=None, load_torque=None):
        """``load_torque(q)``: the undeclared probe's weight as joint torques (Drake's
        sign), removed before the start-up bias is estimated (None: no compensation)."""
        from pydrake.lcm import DrakeLcm
        self.config = config
        self.dry_run = bool(config.dry_run)
        if lcm is None:
            try:
                lcm = DrakeLcm(config.lcm_url)
            except Exception as e:
                raise ScenarioError(f"field 'hardware_interface.lcm_url': cannot open "
                                    f"{config.lcm_url!r}: {e}") from None
        self.lcm = lcm
        statuses = wait_for_panda_status(
            lcm, config.lcm_status_channel, config.connect_timeout,
            duration=config.tau_external_bias_duration, idle=idle)
        import drake
        decoded = [drake.lcmt_panda_status.decode(b) for b in statuses]
        decoded = [m for m in decoded if m.num_joints == NUM_JOINTS]
        if not decoded:
            raise HardwareFault(f"field 'hardware_interface.lcm_status_channel': statuses on "
                                f"{config.lcm_status_channel!r} are not for a 7-joint arm")
        self.first_status = decoded[-1].encode()
        self.tau_bias = np.zeros(NUM_JOINTS)
        self.load_torque = load_torque
        # At rest, before any bias or load is removed (for the load check).
        self.rest_q = np.mean([m.joint_position for m in decoded], axis=0)
        self.rest_tau = np.mean([external_torque_to_drake(m.joint_torque_external)
                                 for m in decoded], axis=0)
        if config.tau_external_bias_duration > 0.0:
            self.tau_bias = np.mean([
                external_torque_to_drake(m.joint_torque_external)
                - (load_torque(m.joint_position) if load_torque is not None else 0.0)
                for m in decoded], axis=0)
        self.fault = None

    def publish_zero(self, repeats: int = 3) -> None:
        """Publishes zero-velocity commands stamped with wall-clock microseconds (never in
        a dry run: a dry run commands nothing)."""
        if self.dry_run:
            return
        import drake
        for _ in range(repeats):
            msg = drake.lcmt_panda_command()
            msg.utime = wall_clock_utime()
            msg.control_mode_expected = 2   # PandaControlMode.kVelocity
            msg.num_joint_position = 0
            msg.joint_position = []
            msg.num_joint_velocity = NUM_JOINTS
            msg.joint_velocity = [0.0] * NUM_JOINTS
            msg.num_joint_torque = 0
            msg.joint_torque = []
            self.lcm.Publish(self.config.lcm_command_channel, msg.encode())

    def stop(self) -> None:
        try:
            self.publish_zero()
        except Exception as e:  # never raise from a stop
            LOG.error("stop: %s: %s", type(e).__name__, e)

    def close(self) -> None:
        self.stop()


class HardwareStation(Diagram):
    """The hardware station Diagram, with handles on its backend for a clean stop and on its
    frame grabber (``grabber``: pose history, diagram clock, tick times, video stats)."""

    def __init__(self, builder: DiagramBuilder, backend, grabber: FrameGrabber, config):
        super().__init__()
        builder.BuildInto(self)
        self.backend = backend
        self.grabber = grabber
        self.hardware_config = config

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
        LOG.warning("hardware_interface.command_rate_hz (%g Hz) is not a whole multiple of "
                    "controller.rate_hz (%g Hz)", cfg.command_rate_hz,
                    scenario.controller.rate_hz)


def picture_processing(scenario):
    """The grabbed picture -> ``us_image`` map for the scenario: with
    ``hardware_interface.image_calibration``, the metric :class:`ImageToProbeMap` of the
    entry for ``imaging.depth``; without, None (the grabber then crops ``video_crop`` and
    stretches to the image size, which is not metric: logged)."""
    cfg = scenario.hardware_interface
    if not cfg.image_calibration.strip():
        if cfg.video_source.strip():
            LOG.warning("hardware_interface.image_calibration is empty: frames are the crop "
                        "stretched to the image size, not metric (docs/hardware_bringup.md, "
                        "step 3a)")
        return None
    path = cfg.image_calibration.strip()
    cal = load_image_calibration(path)
    preset = preset_for_depth(cal, scenario.imaging.depth, source=path)
    return ImageToProbeMap(cal, preset, ProbeGeometry.from_config(scenario.imaging))


def MakeHardwareStation(scenario, meshcat=None, *, lcm=None, lcm_idle=None,
                        name: str = "station", video=None,
                        keep_raw_pictures: bool = False) -> HardwareStation:
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
    control_plant, tip_frame = MakeControlPlant(scenario)
    control_plant.set_name("control_plant")
    builder = DiagramBuilder()

    command = builder.AddNamedSystem("joint_velocity_command", PassThrough(NUM_JOINTS))
    guard = builder.AddNamedSystem("command_guard", CommandGuard(cfg, rate))
    builder.Connect(command.get_output_port(), guard.GetInputPort("joint_velocity_command"))

    # Grabber first: a bad video source, crop or calibration fails before we touch the robot.
    image_shape = (scenario.imaging.image_height_px, scenario.imaging.image_width_px)
    grabber = FrameGrabber(cfg, image_shape, rate, process=picture_processing(scenario),
                           source=video, keep_raw=keep_raw_pictures)
    probe = scenario.probe
    try:
        if cfg.backend == "franky":
            backend = FrankyBackend(cfg, load=(probe.mass, list(probe.p_FCm),
                                               np.diag(probe.inertia_diagonal)))
            robot = builder.AddNamedSystem("franka", FrankaRobotInterface(backend, rate))
            builder.Connect(guard.GetOutputPort("joint_velocity_sent"),
                            robot.GetInputPort("joint_velocity_sent"))
            builder.Connect(robot.GetOutputPort("robot_ok"), guard.GetInputPort("robot_ok"))
            q_port = robot.GetOutputPort("joint_position")
            v_port = robot.GetOutputPort("joint_velocity")
            tau_port = robot.GetOutputPort("tau_external")
            sent_port = robot.GetOutputPort("commanded_velocity")
            ok_port = robot.GetOutputPort("robot_ok")
            time_port = robot.GetOutputPort("state_time")
        elif cfg.backend == "lcm":
            load_torque = (ProbeLoadTorque(control_plant, probe.mass, probe.p_FCm)
                           if cfg.lcm_compensate_load else None)
            backend = LcmBackend(cfg, lcm, lcm_idle, load_torque=load_torque)
            q_port, v_port, tau_port, sent_port, ok_port, time_port = _add_lcm_backend(
                builder, backend, guard, rate, control_plant, probe)
        else:
            raise ScenarioError(f"field 'hardware_interface.backend': unknown backend "
                                f"{cfg.backend!r}")
    except BaseException:
        grabber.release()
        raise

    builder.AddNamedSystem("frame_grabber", grabber)
    fk = builder.AddNamedSystem("probe_pose", ProbePoseFromJoints(control_plant, tip_frame))
    builder.Connect(q_port, fk.get_input_port(0))
    builder.Connect(fk.get_output_port(), grabber.GetInputPort("X_BP"))
    builder.Connect(time_port, grabber.GetInputPort("state_time"))
    estimator = builder.AddNamedSystem(
        "probe_force_estimator", ProbeForceEstimator(control_plant, tip_frame))
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
    station = HardwareStation(builder, backend, grabber, cfg)
    station.set_name(name)
    return station


def _add_lcm_backend(builder, backend: LcmBackend, guard, rate, control_plant, probe):
    import drake
    from pydrake.manipulation import (PandaCommandSender, PandaControlMode,
                                      PandaStatusReceiver)
    from pydrake.systems.lcm import LcmInterfaceSystem, LcmPublisherSystem, LcmSubscriberSystem

    cfg = backend.config
    builder.AddNamedSystem("lcm", LcmInterfaceSystem(backend.lcm))
    sub = builder.AddNamedSystem("panda_status_subscriber", LcmSubscriberSystem.Make(
        channel=cfg.lcm_status_channel, lcm_type=drake.lcmt_panda_status, lcm=backend.lcm,
        use_cpp_serializer=True))
    latch = builder.AddNamedSystem(
        "panda_status_latch", PandaStatusLatch(backend.first_status, cfg.status_timeout, rate))
    receiver = builder.AddNamedSystem("panda_status_receiver", PandaStatusReceiver(NUM_JOINTS))
    builder.Connect(sub.get_output_port(), latch.GetInputPort("lcmt_panda_status_in"))
    builder.Connect(latch.GetOutputPort("lcmt_panda_status"), receiver.get_input_port())
    builder.Connect(latch.GetOutputPort("robot_ok"), guard.GetInputPort("robot_ok"))
    torque = builder.AddNamedSystem("external_torque_to_drake",
                                    ExternalTorqueToDrake(backend.tau_bias))
    builder.Connect(receiver.get_torque_external_output_port(), torque.get_input_port())
    tau_port = torque.get_output_port()
    if backend.load_torque is not None:
        # drake-franka-driver cannot declare the probe's load: remove its weight here.
        load = builder.AddNamedSystem("probe_load_compensation", ProbeLoadCompensation(
            control_plant, probe.mass, probe.p_FCm))
        builder.Connect(receiver.get_position_measured_output_port(),
                        load.GetInputPort("joint_position"))
        builder.Connect(tau_port, load.GetInputPort("tau_external"))
        tau_port = load.GetOutputPort("tau_external")

    sender = builder.AddNamedSystem(
        "panda_command_sender", PandaCommandSender(NUM_JOINTS, PandaControlMode.kVelocity))
    builder.Connect(guard.GetOutputPort("joint_velocity_sent"), sender.get_input_port())
    if not backend.dry_run:
        # A dry run publishes nothing: the driver never receives a command.
        stamper = builder.AddNamedSystem("wall_clock_stamper", WallClockCommandStamper())
        builder.Connect(sender.get_output_port(), stamper.get_input_port())
        publisher = builder.AddNamedSystem("panda_command_publisher", LcmPublisherSystem.Make(
            channel=cfg.lcm_command_channel, lcm_type=drake.lcmt_panda_command,
            lcm=backend.lcm, publish_period=1.0 / rate, use_cpp_serializer=False))
        builder.Connect(stamper.get_output_port(), publisher.get_input_port())
    return (receiver.get_position_measured_output_port(),
            receiver.get_velocity_measured_output_port(), tau_port,
            guard.GetOutputPort("joint_velocity_sent"), latch.GetOutputPort("robot_ok"),
            latch.GetOutputPort("state_time"))


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


def RunHardware(simulator, station: HardwareStation, duration: float, *,
                check_period: float = 0.05, realtime_rate: float = 1.0,
                on_step=None, until=None) -> float:
    """Advances ``simulator`` (whose diagram contains ``station``) by ``duration`` s at
    ``realtime_rate`` (0: as fast as possible) inside a :class:`HardwareSession`, in
    chunks of ``check_period`` s, calling ``on_step()`` after each and ending early when
    ``until()`` returns True; raises HardwareFault as soon as the station's ``robot_ok``
    drops (the command is zero by then). Returns the end time."""
    simulator.set_target_realtime_rate(realtime_rate)
    root = simulator.get_context()
    station_context = station.GetMyContextFromRoot(root)
    ok_port = station.GetOutputPort("robot_ok")
    t_end = root.get_time() + duration
    with HardwareSession(station):
        while root.get_time() < t_end - 1e-12:
            simulator.AdvanceTo(min(t_end, root.get_time() + check_period))
            if on_step is not None:
                on_step()
            if ok_port.Eval(station_context)[0] < 0.5:
                fault = getattr(station.backend, "fault", None) or "robot state lost"
                raise HardwareFault(f"hardware fault at t = {root.get_time():.3f} s: {fault}")
            if until is not None and until():
                break
    return root.get_time()
