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
- :class:`FrameGrabber`: OpenCV VideoCapture (device or file) -> cropped grey ``us_image``.
"""

from __future__ import annotations

import logging
import math
import os
import time

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import EventStatus, LeafSystem

from drake_rus.hardware.config import HardwareConfig
from drake_rus.hardware.core import (
    check_crop, crop_image, external_torque_to_drake, fit_image, guard_command, to_grey,
    wall_clock_utime, watchdog_expired)
from drake_rus.hardware.franky_backend import HardwareFault
from drake_rus.imaging.frames import UsFrame
from drake_rus.robot.model import NUM_JOINTS

LOG = logging.getLogger("drake_rus.hardware")


class CommandGuard(LeafSystem):
    """Client-side command limits (``core.guard_command``).

    Inputs: ``joint_velocity_command`` (7, rad/s, from the safety layer); ``robot_ok`` (1;
    0 latches a stop). Output ``joint_velocity_sent`` (7, rad/s): the guarded command for
    this period (direct feedthrough: limits against the previous period's command, kept in
    state and updated every 1 / ``rate_hz`` s). ``stopped`` (1): the latch.
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
        self.DeclareStateOutputPort("stopped", self._stopped)

    def _guarded(self, context) -> tuple[np.ndarray, bool]:
        stopped = context.get_discrete_state(self._stopped).get_value()[0] > 0.5
        ok = (not self._ok.HasValue(context)) or self._ok.Eval(context)[0] > 0.5
        stopped = stopped or not ok
        desired = (self._cmd.Eval(context) if self._cmd.HasValue(context)
                   else np.zeros(NUM_JOINTS))
        v = guard_command(desired, context.get_discrete_state(self._prev).get_value(),
                          self._dt, self._v_max, self._a_max,
                          enabled=not (self._dry_run or stopped))
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
    ``commanded_velocity`` (7, rad/s: what was sent), ``robot_ok`` (1).
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
        self.DeclarePeriodicUnrestrictedUpdateEvent(1.0 / float(rate_hz), 0.0, self._update)
        self.DeclareStateOutputPort("joint_position", self._q)
        self.DeclareStateOutputPort("joint_velocity", self._v)
        self.DeclareStateOutputPort("tau_external", self._tau)
        self.DeclareStateOutputPort("commanded_velocity", self._sent)
        self.DeclareStateOutputPort("robot_ok", self._ok)

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
                trace.append((r.robot_time, r.q, np.asarray(sent, float).copy()))
        except HardwareFault:
            ds.get_mutable_vector(self._sent).SetZero()
            ds.get_mutable_vector(self._ok).SetFromVector([0.0])
            return EventStatus.Succeeded()
        ds.get_mutable_vector(self._q).SetFromVector(r.q)
        ds.get_mutable_vector(self._v).SetFromVector(r.v)
        ds.get_mutable_vector(self._tau).SetFromVector(r.tau_external)
        ds.get_mutable_vector(self._sent).SetFromVector(sent)
        return EventStatus.Succeeded()


class _StatusRecord:
    """The newest status as bytes, its utime (us) and wall-clock arrival (s, monotonic)."""

    __slots__ = ("data", "utime", "arrival", "ok")

    def __init__(self, data: bytes, utime: int, arrival: float, ok: bool = True):
        self.data, self.utime, self.arrival, self.ok = data, utime, arrival, ok


class PandaStatusLatch(LeafSystem):
    """Newest ``lcmt_panda_status`` and the robot-state watchdog (LCM backend).

    Input ``lcmt_panda_status_in`` (C++ lcmt_panda_status, from an LcmSubscriberSystem).
    Outputs ``lcmt_panda_status`` (the newest status; before any arrives in the simulation,
    the one read when connecting) for ``PandaStatusReceiver``; ``robot_ok`` (1): 0, latched,
    once no new status (new ``utime``) arrived for ``status_timeout`` s of wall-clock time.
    ``status_utime`` (1, s): the newest status stamp.
    """

    def __init__(self, first_status_bytes: bytes, status_timeout: float, rate_hz: float):
        super().__init__()
        import drake
        import pydrake.systems.lcm as lcm_systems
        self._msg_type = drake.lcmt_panda_status
        self._serializer = lcm_systems._Serializer_[drake.lcmt_panda_status]()
        self._timeout = float(status_timeout)
        first = self._msg_type.decode(first_status_bytes)
        model = self._serializer.CreateDefaultValue()
        self._in = self.DeclareAbstractInputPort("lcmt_panda_status_in", model)
        self._record = self.DeclareAbstractState(AbstractValue.Make(
            _StatusRecord(first_status_bytes, int(first.utime), math.nan)))
        self.DeclarePeriodicUnrestrictedUpdateEvent(1.0 / float(rate_hz), 0.0, self._update)
        self.DeclareAbstractOutputPort(
            "lcmt_panda_status", lambda: self._serializer.CreateDefaultValue(), self._calc,
            prerequisites_of_calc={self.abstract_state_ticket(self._record)})
        self.DeclareVectorOutputPort(
            "robot_ok", 1, lambda c, o: o.SetFromVector([float(self._rec(c).ok)]),
            prerequisites_of_calc={self.abstract_state_ticket(self._record)})
        self.DeclareVectorOutputPort(
            "status_utime", 1, lambda c, o: o.SetFromVector([self._rec(c).utime * 1e-6]),
            prerequisites_of_calc={self.abstract_state_ticket(self._record)})

    def _rec(self, context) -> _StatusRecord:
        return context.get_abstract_state(self._record).get_value()

    def _calc(self, context, output):
        self._serializer.Deserialize(self._rec(context).data, output)

    def _update(self, context, state):
        rec = self._rec(context)
        now = time.monotonic()
        arrival = now if math.isnan(rec.arrival) else rec.arrival   # watchdog starts now
        data, utime = rec.data, rec.utime
        if self._in.HasValue(context):
            raw = self._serializer.Serialize(self._in.EvalAbstract(context))
            msg = self._msg_type.decode(raw)
            if msg.num_joints == NUM_JOINTS and int(msg.utime) != rec.utime:
                data, utime, arrival = raw, int(msg.utime), now
        ok = rec.ok and not watchdog_expired(now, arrival, self._timeout)
        if rec.ok and not ok:
            LOG.error("robot state lost: no new lcmt_panda_status for %.3f s", now - arrival)
        state.get_mutable_abstract_state(self._record).set_value(
            _StatusRecord(data, utime, arrival, ok))


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
            f"{name}_in", self._serializer.CreateDefaultValue())
        self.DeclareAbstractOutputPort(
            name, lambda: AbstractValue.Make(self._msg_type()), self._calc,
            prerequisites_of_calc={self.time_ticket(),
                                   self.input_port_ticket(self._in.get_index())})

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
        self.DeclareVectorOutputPort("tau_external", NUM_JOINTS, lambda c, o: o.SetFromVector(
            external_torque_to_drake(self._in.Eval(c)) - self._bias))


def open_video_source(source: str):
    """An opened ``cv2.VideoCapture`` for a device index ("0") or a video file path.
    Raises ValueError naming ``hardware_interface.video_source``."""
    import cv2
    text = str(source).strip()
    field = "hardware_interface.video_source"
    if text.isdigit():
        cap = cv2.VideoCapture(int(text))
        if not cap.isOpened():
            raise ValueError(f"field '{field}': cannot open capture device {text}")
        return cap, False
    if not os.path.isfile(text):
        raise ValueError(f"field '{field}': video file not found: {text}")
    cap = cv2.VideoCapture(text)
    if not cap.isOpened():
        raise ValueError(f"field '{field}': OpenCV cannot read the video file {text}")
    return cap, True


class FrameGrabber(LeafSystem):
    """The ultrasound machine's video through OpenCV, as ``us_image``.

    Every 1 / ``frame_rate_hz`` s grabs the next picture (a device, or a video file replayed
    frame by frame, looped if asked), crops it to ``video_crop``, converts to grey and fits
    it to the probe's image shape (rows, cols). Input ``X_BP`` (RigidTransform): the probe
    pose stamped on the frame. Output ``us_image`` (UsFrame): image, acquisition time (the
    diagram's time), X_BP, frame index. A failed grab keeps the previous frame (its stamp
    ages, and the safety layer's stale-image watchdog stops the robot).
    Without a source, outputs a blank frame stamped NaN (no image stream).
    """

    def __init__(self, config: HardwareConfig, image_shape, frame_rate_hz: float):
        super().__init__()
        self._shape = (int(image_shape[0]), int(image_shape[1]))
        self._crop = list(config.video_crop)
        self._loop = bool(config.video_loop)
        self._cap = None
        self._is_file = False
        self.grab_failures = 0
        empty = UsFrame(np.zeros(self._shape, np.uint8), time=math.nan)
        self._X_BP = self.DeclareAbstractInputPort("X_BP", AbstractValue.Make(RigidTransform()))
        self._frame = self.DeclareAbstractState(AbstractValue.Make(empty))
        if config.video_source.strip():
            self._cap, self._is_file = open_video_source(config.video_source)
            ok, picture = self._cap.read()
            if not ok:
                raise ValueError(f"field 'hardware_interface.video_source': no picture from "
                                 f"{config.video_source}")
            check_crop(self._crop, picture.shape)
            self._rewind()
            period = 1.0 / float(frame_rate_hz)
            self.DeclareInitializationUnrestrictedUpdateEvent(self._grab)
            self.DeclarePeriodicUnrestrictedUpdateEvent(period, period, self._grab)
        self.DeclareAbstractOutputPort(
            "us_image", lambda: AbstractValue.Make(empty),
            lambda c, o: o.set_value(c.get_abstract_state(self._frame).get_value()),
            prerequisites_of_calc={self.abstract_state_ticket(self._frame)})

    def _rewind(self):
        if self._is_file:
            import cv2
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)

    def _read(self):
        ok, picture = self._cap.read()
        if not ok and self._is_file and self._loop:
            self._rewind()
            ok, picture = self._cap.read()
        return picture if ok else None

    def _grab(self, context, state):
        picture = self._read()
        if picture is None:
            self.grab_failures += 1
            return EventStatus.DidNothing()
        image = fit_image(to_grey(crop_image(picture, self._crop)), self._shape)
        previous = context.get_abstract_state(self._frame).get_value()
        X_BP = self._X_BP.Eval(context) if self._X_BP.HasValue(context) else RigidTransform()
        state.get_mutable_abstract_state(self._frame).set_value(UsFrame(
            image=image, time=context.get_time(), X_BP=RigidTransform(X_BP),
            frame_index=previous.frame_index + 1))
        return EventStatus.Succeeded()

    def release(self):
        if self._cap is not None:
            self._cap.release()
            self._cap = None
