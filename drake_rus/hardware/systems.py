"""Thin LeafSystems of the hardware station over the pure functions of ``core``.

- :class:`CommandGuard`: the command actually sent (client-side velocity and acceleration
  limits, zero on dry run, fault or non-finite input; a fault latches);
- :class:`FrankaRobotInterface`: franky backend I/O at the command rate (read the robot, send
  the guarded command);
- :class:`PandaStatusLatch`: newest ``lcmt_panda_status`` with its wall-clock arrival,
  the robot-state watchdog (LCM backend);
- :class:`WallClockStamper`: an LCM message (``lcmt_panda_command``) restamped with
  wall-clock microseconds (drake-franka-driver drops commands stamped with simulation time);
- :class:`ExternalTorqueToDrake`: the driver's external torque -> Drake's sign, bias removed;
- :class:`ProbeLoadCompensation`: removes the weight of a probe the robot was not told about
  from the external torques (LCM route: drake-franka-driver cannot declare a load);
- :class:`FrameGrabber`: the capture thread's newest picture (``video.FrameCapture``) as
  ``us_image``, with the probe pose and diagram time of its acquisition instant; never
  blocks.
"""

from __future__ import annotations

import collections
import logging
import math
import time

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import EventStatus, LeafSystem

from drake_rus.hardware.config import HardwareConfig
from drake_rus.hardware.core import (
    crop_image,
    external_torque_to_drake,
    fit_image,
    guard_command,
    to_grey,
    wall_clock_utime,
    watchdog_expired,
    weight_torque,
)
from drake_rus.hardware.franky_backend import HardwareFault
from drake_rus.hardware.video import DiagramClock, FrameCapture, PoseHistory
from drake_rus.imaging.frames import UsFrame
from drake_rus.robot.model import FLANGE_FRAME, NUM_JOINTS

LOG = logging.getLogger("drake_rus.hardware")


class CommandGuard(LeafSystem):
    """Client-side command limits (``core.guard_command``).

    Inputs: ``joint_velocity_command`` (7, rad/s, from the safety layer); ``robot_ok`` (1;
    0 latches a stop). Output ``joint_velocity_sent`` (7, rad/s): the guarded command for
    this period (direct feedthrough: limits against the previous period's command, kept in
    state and updated every 1 / ``rate_hz`` s), for a consumer that reads it in its own
    update at the same tick (the franky route). ``joint_velocity_committed`` (7, rad/s,
    state): the command the latest update stored, for a consumer that runs after the
    updates (a publisher at the same tick, the LCM route): reading ``joint_velocity_sent``
    there would limit against the command just stored and step twice. ``stopped`` (1): the
    latch.
    """

    def __init__(self, config: HardwareConfig, rate_hz: float):
        super().__init__()
        self._dt = 1.0 / float(rate_hz)
        self._v_max = np.asarray(config.max_joint_velocity, float)
        self._a_max = np.asarray(config.max_joint_acceleration, float)
        self._dry_run = bool(config.dry_run)
        self._cmd = self.DeclareVectorInputPort("joint_velocity_command", NUM_JOINTS)
        self._ok = self.DeclareVectorInputPort("robot_ok", 1)
        self._prev = self.DeclareDiscreteState(NUM_JOINTS)
        self._stopped = self.DeclareDiscreteState(1)
        self.DeclarePeriodicDiscreteUpdateEvent(self._dt, 0.0, self._update)
        self.DeclareVectorOutputPort("joint_velocity_sent", NUM_JOINTS, self._calc)
        self.DeclareStateOutputPort("joint_velocity_committed", self._prev)
        self.DeclareStateOutputPort("stopped", self._stopped)

    def _guarded(self, context) -> tuple[np.ndarray, bool]:
        stopped = context.get_discrete_state(self._stopped).get_value()[0] > 0.5
        ok = (not self._ok.HasValue(context)) or self._ok.Eval(context)[0] > 0.5
        stopped = stopped or not ok
        desired = self._cmd.Eval(context) if self._cmd.HasValue(context) else np.zeros(NUM_JOINTS)
        v = guard_command(
            desired,
            context.get_discrete_state(self._prev).get_value(),
            self._dt,
            self._v_max,
            self._a_max,
            enabled=not (self._dry_run or stopped),
        )
        return v, stopped

    def _calc(self, context, output):
        output.SetFromVector(self._guarded(context)[0])

    def _update(self, context, discrete_state):
        v, stopped = self._guarded(context)
        discrete_state.get_mutable_vector(self._prev).SetFromVector(v)
        discrete_state.get_mutable_vector(self._stopped).SetFromVector([float(stopped)])


class FrankaRobotInterface(LeafSystem):
    """The franky backend at the command rate.

    Every 1 / ``rate_hz`` s: reads the robot (joints, external torques in Drake's sign) and
    sends ``joint_velocity_sent``. A libfranka failure latches ``robot_ok`` = 0 and the
    command at zero (the run's session then ends with :class:`HardwareFault`).
    Input ``joint_velocity_sent`` (7, rad/s). Outputs (state, so no algebraic loop):
    ``joint_position`` (7, rad), ``joint_velocity`` (7, rad/s), ``tau_external`` (7, N m),
    ``commanded_velocity`` (7, rad/s: what was sent), ``robot_ok`` (1), ``state_time`` (1,
    s, ``time.monotonic()`` when the joints were read: the probe pose history's stamp).
    """

    def __init__(self, backend, rate_hz: float):
        super().__init__()
        self._backend = backend
        first = backend.read()
        self._in = self.DeclareVectorInputPort("joint_velocity_sent", NUM_JOINTS)
        self._q = self.DeclareDiscreteState(first.q)
        self._v = self.DeclareDiscreteState(first.v)
        self._tau = self.DeclareDiscreteState(first.tau_external)
        self._sent = self.DeclareDiscreteState(NUM_JOINTS)
        self._ok = self.DeclareDiscreteState(np.ones(1))
        self._time = self.DeclareDiscreteState([first.wall_time])
        self.DeclarePeriodicUnrestrictedUpdateEvent(1.0 / float(rate_hz), 0.0, self._update)
        self.DeclareStateOutputPort("joint_position", self._q)
        self.DeclareStateOutputPort("joint_velocity", self._v)
        self.DeclareStateOutputPort("tau_external", self._tau)
        self.DeclareStateOutputPort("commanded_velocity", self._sent)
        self.DeclareStateOutputPort("robot_ok", self._ok)
        self.DeclareStateOutputPort("state_time", self._time)

    @property
    def backend(self):
        return self._backend

    def _update(self, context, state):
        if context.get_discrete_state(self._ok).get_value()[0] < 0.5:
            return EventStatus.DidNothing()
        ds = state.get_mutable_discrete_state()
        try:
            r = self._backend.read()
            v = self._in.Eval(context) if self._in.HasValue(context) else np.zeros(NUM_JOINTS)
            sent = self._backend.send(v)
            trace = getattr(self._backend, "trace", None)
            if trace is not None:
                trace.append((r.robot_time, r.q, np.asarray(sent, float).copy(), r.wall_time))
        except HardwareFault:
            ds.get_mutable_vector(self._sent).SetZero()
            ds.get_mutable_vector(self._ok).SetFromVector([0.0])
            return EventStatus.Succeeded()
        ds.get_mutable_vector(self._q).SetFromVector(r.q)
        ds.get_mutable_vector(self._v).SetFromVector(r.v)
        ds.get_mutable_vector(self._tau).SetFromVector(r.tau_external)
        ds.get_mutable_vector(self._sent).SetFromVector(sent)
        ds.get_mutable_vector(self._time).SetFromVector([r.wall_time])
        return EventStatus.Succeeded()


class _StatusRecord:
    """The newest status as bytes, its utime (us), wall-clock arrival (s, monotonic), the
    watchdog's verdict, the latch's previous tick (s, monotonic), its ticks without news and
    the status's own time on the monotonic clock (s)."""

    __slots__ = ("data", "utime", "arrival", "ok", "last_tick", "quiet_ticks", "state_time")

    def __init__(
        self,
        data: bytes,
        utime: int,
        arrival: float,
        ok: bool = True,
        last_tick: float = math.nan,
        quiet_ticks: int = 0,
        state_time: float = math.nan,
    ):
        self.data, self.utime, self.arrival, self.ok = data, utime, arrival, ok
        self.last_tick, self.quiet_ticks = last_tick, quiet_ticks
        self.state_time = state_time


class PandaStatusLatch(LeafSystem):
    """Newest ``lcmt_panda_status`` and the robot-state watchdog (LCM backend).

    Input ``lcmt_panda_status_in`` (C++ lcmt_panda_status, from an LcmSubscriberSystem).
    Outputs ``lcmt_panda_status`` (the newest status; before any arrives in the simulation,
    the one read when connecting) for ``PandaStatusReceiver``; ``robot_ok`` (1): 0, latched,
    once no new status (new ``utime``) arrived for ``status_timeout`` s of wall-clock time
    *and* for ``min_quiet_ticks`` ticks of this latch after its own last stall (a tick that
    came more than half the timeout after the previous one: our process, not the robot, was
    late; the statuses that arrived meanwhile are pumped before the next tick).
    ``status_utime`` (1, s): the newest status stamp. ``state_time`` (1, s): when that
    status was measured, on this process's monotonic clock (its wall-clock age at arrival,
    from ``utime``, taken off the arrival time; NaN before the first): the probe pose
    history's stamp. ``status_ages`` (attribute, s): the last minute's wall-clock ages of
    new statuses at arrival, unclamped (this PC's wall clock minus the driver's ``utime``:
    the transport delay plus the offset between the two clocks; the bring-up check reads
    them, docs/hardware_bringup.md "Clock synchronisation").
    """

    def __init__(
        self,
        first_status_bytes: bytes,
        status_timeout: float,
        rate_hz: float,
        min_quiet_ticks: int = 3,
    ):
        super().__init__()
        import drake
        import pydrake.systems.lcm as lcm_systems

        self._msg_type = drake.lcmt_panda_status
        self._serializer = lcm_systems._Serializer_[drake.lcmt_panda_status]()
        self._timeout = float(status_timeout)
        self._min_quiet = int(min_quiet_ticks)
        self.status_ages = collections.deque(maxlen=int(60.0 * float(rate_hz)))
        first = self._msg_type.decode(first_status_bytes)
        model = self._serializer.CreateDefaultValue()
        self._in = self.DeclareAbstractInputPort("lcmt_panda_status_in", model)
        self._record = self.DeclareAbstractState(
            AbstractValue.Make(_StatusRecord(first_status_bytes, int(first.utime), math.nan))
        )
        self.DeclarePeriodicUnrestrictedUpdateEvent(1.0 / float(rate_hz), 0.0, self._update)
        self.DeclareAbstractOutputPort(
            "lcmt_panda_status",
            lambda: self._serializer.CreateDefaultValue(),
            self._calc,
            prerequisites_of_calc={self.abstract_state_ticket(self._record)},
        )
        self.DeclareVectorOutputPort(
            "robot_ok",
            1,
            lambda c, o: o.SetFromVector([float(self._rec(c).ok)]),
            prerequisites_of_calc={self.abstract_state_ticket(self._record)},
        )
        self.DeclareVectorOutputPort(
            "status_utime",
            1,
            lambda c, o: o.SetFromVector([self._rec(c).utime * 1e-6]),
            prerequisites_of_calc={self.abstract_state_ticket(self._record)},
        )
        self.DeclareVectorOutputPort(
            "state_time",
            1,
            lambda c, o: o.SetFromVector([self._rec(c).state_time]),
            prerequisites_of_calc={self.abstract_state_ticket(self._record)},
        )

    def _rec(self, context) -> _StatusRecord:
        return context.get_abstract_state(self._record).get_value()

    def _calc(self, context, output):
        self._serializer.Deserialize(self._rec(context).data, output)

    def _update(self, context, state):
        rec = self._rec(context)
        now = time.monotonic()
        arrival = now if math.isnan(rec.arrival) else rec.arrival  # watchdog starts now
        data, utime, state_time = rec.data, rec.utime, rec.state_time
        quiet = rec.quiet_ticks + 1
        if math.isfinite(rec.last_tick) and now - rec.last_tick > 0.5 * self._timeout:
            quiet = 0  # our own stall: the robot gets a few ticks to show it is alive
        if self._in.HasValue(context):
            raw = self._serializer.Serialize(self._in.EvalAbstract(context))
            msg = self._msg_type.decode(raw)
            if msg.num_joints == NUM_JOINTS and int(msg.utime) != rec.utime:
                data, utime, arrival, quiet = raw, int(msg.utime), now, 0
                raw_age = time.time() - utime * 1e-6
                self.status_ages.append(raw_age)
                age = min(max(raw_age, 0.0), 1.0)
                state_time = now - age
        expired = watchdog_expired(now, arrival, self._timeout) and quiet >= self._min_quiet
        ok = rec.ok and not expired
        if rec.ok and not ok:
            LOG.error("robot state lost: no new lcmt_panda_status for %.3f s", now - arrival)
        state.get_mutable_abstract_state(self._record).set_value(
            _StatusRecord(data, utime, arrival, ok, now, quiet, state_time)
        )


class WallClockStamper(LeafSystem):
    """An LCM message from a Drake C++ sender (stamped with simulation time) -> the same
    message as its Python class, stamped with wall-clock microseconds at the moment it is
    evaluated, i.e. when the publisher sends it (drake-franka-driver drops commands stamped
    with simulation time). Input ``<type>_in`` (C++ value), output ``<type>`` (Python)."""

    def __init__(self, lcm_type):
        super().__init__()
        import pydrake.systems.lcm as lcm_systems

        self._msg_type = lcm_type
        self._serializer = lcm_systems._Serializer_[lcm_type]()
        name = lcm_type.__name__
        self._in = self.DeclareAbstractInputPort(
            f"{name}_in", self._serializer.CreateDefaultValue()
        )
        self.DeclareAbstractOutputPort(
            name,
            lambda: AbstractValue.Make(self._msg_type()),
            self._calc,
            prerequisites_of_calc={
                self.time_ticket(),
                self.input_port_ticket(self._in.get_index()),
            },
        )

    def _calc(self, context, output):
        msg = self._msg_type.decode(self._serializer.Serialize(self._in.EvalAbstract(context)))
        msg.utime = wall_clock_utime()
        output.set_value(msg)


def WallClockCommandStamper() -> WallClockStamper:
    """:class:`WallClockStamper` for ``lcmt_panda_command``."""
    import drake

    return WallClockStamper(drake.lcmt_panda_command)


class ExternalTorqueToDrake(LeafSystem):
    """Input ``torque_external`` (7, N m, libfranka / driver sign: robot on environment).
    Output ``tau_external`` (7, N m, Drake's sign: environment on the arm) minus ``bias``."""

    def __init__(self, bias=None):
        super().__init__()
        self._bias = np.zeros(NUM_JOINTS) if bias is None else np.asarray(bias, float)
        self._in = self.DeclareVectorInputPort("torque_external", NUM_JOINTS)
        self.DeclareVectorOutputPort(
            "tau_external",
            NUM_JOINTS,
            lambda c, o: o.SetFromVector(external_torque_to_drake(self._in.Eval(c)) - self._bias),
        )


class ProbeLoadCompensation(LeafSystem):
    """Removes the weight of an undeclared probe from the external joint torques.

    A robot that does not know the probe's mass reports its weight as an external force
    at the probe's centre of mass: Drake's ``tau_external`` (on the arm by the environment)
    carries J_Cm(q)^T m g. Inputs ``joint_position`` (7, rad), ``tau_external`` (7, N m,
    Drake's sign); output ``tau_external`` (7) without it. ``plant``: our FR3 model (its
    gravity field), ``mass`` (kg), ``p_FCm`` (3, m, centre of mass in the flange frame).
    """

    def __init__(self, plant, mass: float, p_FCm):
        super().__init__()
        self._load = ProbeLoadTorque(plant, mass, p_FCm)
        self._q = self.DeclareVectorInputPort("joint_position", NUM_JOINTS)
        self._tau = self.DeclareVectorInputPort("tau_external", NUM_JOINTS)
        self.DeclareVectorOutputPort(
            "tau_external",
            NUM_JOINTS,
            lambda c, o: o.SetFromVector(
                np.asarray(self._tau.Eval(c), float) - self._load(self._q.Eval(c))
            ),
        )


class ProbeLoadTorque:
    """``load(q)``: the generalized force (7, N m, Drake's sign) of a probe of ``mass`` at
    ``p_FCm`` in the flange frame, from our FR3 model's Jacobian and gravity field."""

    def __init__(self, plant, mass: float, p_FCm):
        from pydrake.multibody.tree import JacobianWrtVariable

        self._plant = plant
        self._context = plant.CreateDefaultContext()
        self._flange = plant.GetFrameByName(FLANGE_FRAME)
        self._p = np.asarray(p_FCm, float).reshape(3)
        self._mass = float(mass)
        self._g = np.asarray(plant.gravity_field().gravity_vector(), float)
        self._wrt = JacobianWrtVariable.kV

    def __call__(self, q) -> np.ndarray:
        self._plant.SetPositions(self._context, np.asarray(q, float))
        W = self._plant.world_frame()
        J = self._plant.CalcJacobianTranslationalVelocity(
            self._context, self._wrt, self._flange, self._p, W, W
        )
        return weight_torque(J, self._mass, self._g)


def default_picture_processing(crop, image_shape):
    """picture -> uint8 grey (rows, cols): cropped to ``crop`` and stretched to
    ``image_shape`` (no metric calibration)."""
    shape = (int(image_shape[0]), int(image_shape[1]))
    return lambda picture: fit_image(to_grey(crop_image(picture, crop)), shape)


class FrameGrabber(LeafSystem):
    """The ultrasound machine's video as ``us_image``; never blocks the control loop.

    A capture thread (:class:`~drake_rus.hardware.video.FrameCapture`) drains the source
    (``config.video_source``, or ``source``: a source string or an object with ``read()``)
    and keeps its newest picture, processed by ``process(picture) -> image`` (default: crop
    ``video_crop``, grey, stretch to ``image_shape``; the station passes the metric
    ``ImageToProbeMap`` when there is an image calibration).

    Every 1 / ``rate_hz`` s (the control period) the grabber records the monotonic time,
    the diagram time (``clock``: :class:`~drake_rus.hardware.video.DiagramClock`) and the
    input ``X_BP`` (``history``: :class:`~drake_rus.hardware.video.PoseHistory`), stamped
    with the optional input ``state_time`` (1, s, monotonic: when the robot state behind
    ``X_BP`` was measured; the tick's time when unconnected or NaN); then, if
    the thread holds a picture it has not used, emits it: ``UsFrame(image, time, X_BP,
    frame_index)`` with ``X_BP`` the history at ``capture_time - video_latency`` and
    ``time`` the diagram time of that instant; ``frame_index`` is the capture counter (gaps:
    frames never seen). A picture whose instant is older than the pose history (the first
    ones at start-up) is not used: its pose is unknown. A frozen or unplugged source leaves the
    last frame, whose stamp
    ages: the safety layer's stale-image watchdog stops the robot. Without a source the
    output is a blank frame stamped NaN.

    Logging for tools (None: off): ``pose_log`` gets (monotonic s, X_BP) every tick;
    ``frame_log`` gets (capture time s, UsFrame) for every frame emitted.
    """

    def __init__(
        self,
        config: HardwareConfig,
        image_shape,
        rate_hz: float,
        *,
        process=None,
        source=None,
        keep_raw: bool = False,
    ):
        super().__init__()
        self._shape = (int(image_shape[0]), int(image_shape[1]))
        self._latency = float(config.video_latency)
        self._period = 1.0 / float(rate_hz)
        if self._latency + 0.5 > float(config.pose_history):
            raise ValueError(
                f"field 'hardware_interface.pose_history': {config.pose_history:g}"
                f" s must exceed video_latency ({self._latency:g} s) by 0.5 s"
            )
        self.history = PoseHistory(config.pose_history, rate_hz)
        self.clock = DiagramClock(config.pose_history, rate_hz)
        self.tick_times = collections.deque(maxlen=int(60.0 * rate_hz))
        self.pose_log: list | None = None
        self.frame_log: list | None = None
        self.frames_before_history = 0
        self._skipped = -1
        self.capture: FrameCapture | None = None
        empty = UsFrame(np.zeros(self._shape, np.uint8), time=math.nan)
        self._X_BP = self.DeclareAbstractInputPort("X_BP", AbstractValue.Make(RigidTransform()))
        self._state_time = self.DeclareVectorInputPort("state_time", 1)
        self._frame = self.DeclareAbstractState(AbstractValue.Make(empty))
        if source is None and config.video_source.strip():
            source = config.video_source
        if source is not None:
            if process is None:
                process = default_picture_processing(config.video_crop, self._shape)
            self.capture = FrameCapture(
                source, process=self._checked(process), loop=config.video_loop, keep_raw=keep_raw
            )
        self.DeclareInitializationUnrestrictedUpdateEvent(self._tick)
        self.DeclarePeriodicUnrestrictedUpdateEvent(self._period, 0.0, self._tick)
        self.DeclareAbstractOutputPort(
            "us_image",
            lambda: AbstractValue.Make(empty),
            lambda c, o: o.set_value(c.get_abstract_state(self._frame).get_value()),
            prerequisites_of_calc={self.abstract_state_ticket(self._frame)},
        )

    def _checked(self, process):
        shape = self._shape

        def run(picture):
            image = np.asarray(process(picture))
            if image.shape != shape or image.dtype != np.uint8:
                raise ValueError(
                    f"frame grabber: processed picture is {image.shape} "
                    f"{image.dtype}, expected {shape} uint8"
                )
            return image

        return run

    @property
    def video_latency(self) -> float:
        return self._latency

    def _tick(self, context, state):
        now = time.monotonic()
        self.tick_times.append(now)
        self.clock.record(context.get_time(), now)
        if self._X_BP.HasValue(context):
            X = self._X_BP.Eval(context)
            stamp = now
            if self._state_time.HasValue(context):
                measured = float(self._state_time.Eval(context)[0])
                stamp = measured if math.isfinite(measured) and measured <= now else now
            if self.history.append(stamp, X) and self.pose_log is not None:
                self.pose_log.append((stamp, RigidTransform(X)))
        if self.capture is None:
            return EventStatus.DidNothing()
        newest = self.capture.latest()
        previous = context.get_abstract_state(self._frame).get_value()
        if newest is None or newest.counter <= previous.frame_index:
            return EventStatus.DidNothing()
        instant = newest.capture_time - self._latency
        X_BP, where = self.history.pose_at(instant)
        if where == "before" and instant < self.history.span()[0] - self._period:
            # Older than the pose history (the first pictures at start-up): its pose is
            # unknown, so it is not used.
            if newest.counter != self._skipped:
                self._skipped = newest.counter
                self.frames_before_history += 1
            return EventStatus.DidNothing()
        frame = UsFrame(
            image=newest.image,
            time=self.clock.to_diagram(instant),
            X_BP=X_BP,
            frame_index=newest.counter,
        )
        if self.frame_log is not None:
            self.frame_log.append((newest.capture_time, frame))
        state.get_mutable_abstract_state(self._frame).set_value(frame)
        return EventStatus.Succeeded()

    def tick_gaps(self) -> np.ndarray:
        """Wall-clock gaps (s) between the last minute's control ticks."""
        return np.diff(np.asarray(self.tick_times, float))

    def release(self):
        if self.capture is not None:
            self.capture.close()
            self.capture = None
