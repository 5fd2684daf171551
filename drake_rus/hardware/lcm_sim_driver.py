"""A simulated drake-franka-driver on LCM, for tests and for rehearsing the LCM route.

Built from Drake's own ``PandaCommandReceiver`` / ``PandaStatusSender`` like the driver's
simulation counterpart: it subscribes to PANDA_COMMAND, drops commands whose ``utime`` is not
within ``command_expiry`` s of its wall clock (as drake-franka-driver does, ``--expire_sec``,
default 0.1 s there; a command stamped with simulation time is never used) and then holds
zero velocity, and publishes PANDA_STATUS stamped with wall-clock microseconds, with
``joint_torque_external`` in the driver's sign (robot on environment, the opposite of
Drake's): it publishes ``-tau_external_drake``.

- :func:`AddSimulatedDriverWire`: the driver's wire side around any simulated robot in a
  DiagramBuilder (its joint positions, velocities and Drake-sign external torques in, the
  accepted joint-velocity command out). Wire faults for rehearsals: an added command latency
  (``command_latency`` s: a command reaches the robot that much later) and dropped status
  packets (``status_drop_probability``).
- :class:`SimulatedPandaDriver`: that wire around :class:`SimulatedJoints` (perfect
  velocity tracking) and a constant external torque, for the memq:// tests; the rehearsal
  (``drake_rus.rehearsal``) puts the simulated station with its patient behind the wire.
"""

from __future__ import annotations

import collections
import time
from dataclasses import dataclass

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import Diagram, DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ConstantVectorSource, Gain

from drake_rus.hardware.core import is_command_fresh, wall_clock_utime
from drake_rus.hardware.systems import WallClockStamper
from drake_rus.robot.model import NUM_JOINTS

__all__ = [
    "SimulatedPandaDriver",
    "CommandExpiry",
    "SimulatedJoints",
    "LossyLcmPublisher",
    "StatusSlot",
    "AddSimulatedDriverWire",
    "DriverWire",
    "DRIVER_EXPIRE_SEC",
]

# drake-franka-driver's --expire_sec default (s).
DRIVER_EXPIRE_SEC = 0.1


class CommandExpiry(LeafSystem):
    """Input ``lcmt_panda_command_in`` (C++). Output ``lcmt_panda_command`` (C++): the newest
    command that has reached the robot if its ``utime`` is within ``expiry`` s of the wall
    clock, else a zero-velocity command.

    ``latency`` (s, default 0): a received command reaches the robot only ``latency`` s after
    it arrived (a slow wire; its age at the robot grows by as much). Records every distinct
    command: ``received`` (arrival wall time s, utime us) and ``log`` (wall time s when it
    reached the robot, utime, velocity, fresh then)."""

    def __init__(self, expiry: float, latency: float = 0.0):
        super().__init__()
        import drake
        import pydrake.systems.lcm as lcm_systems

        self._type = drake.lcmt_panda_command
        self._ser = lcm_systems._Serializer_[drake.lcmt_panda_command]()
        self._expiry = float(expiry)
        self._latency = max(float(latency), 0.0)
        self.log: list[tuple[float, int, np.ndarray, bool]] = []
        self.received: list[tuple[float, int]] = []
        self._last_utime = None
        self._pending: collections.deque = collections.deque()  # (arrival, msg)
        self._active = None
        self._in = self.DeclareAbstractInputPort(
            "lcmt_panda_command_in", self._ser.CreateDefaultValue()
        )
        self.DeclareAbstractOutputPort(
            "lcmt_panda_command",
            lambda: self._ser.CreateDefaultValue(),
            self._calc,
            prerequisites_of_calc={
                self.time_ticket(),
                self.input_port_ticket(self._in.get_index()),
            },
        )

    def _calc(self, context, output):
        msg = self._type.decode(self._ser.Serialize(self._in.EvalAbstract(context)))
        now = time.time()
        if msg.num_joint_velocity == NUM_JOINTS and msg.utime != self._last_utime:
            self._last_utime = msg.utime
            self.received.append((now, int(msg.utime)))
            self._pending.append((now, msg))
        while self._pending and self._pending[0][0] + self._latency <= now:
            self._active = self._pending.popleft()[1]
            self.log.append(
                (
                    now,
                    int(self._active.utime),
                    np.array(self._active.joint_velocity),
                    is_command_fresh(self._active.utime, now, self._expiry),
                )
            )
        active = self._active
        if active is None or not is_command_fresh(active.utime, now, self._expiry):
            active = self._type()
            active.utime = wall_clock_utime(now)
            active.control_mode_expected = 2
            active.num_joint_velocity = NUM_JOINTS
            active.joint_velocity = [0.0] * NUM_JOINTS
        self._ser.Deserialize(active.encode(), output)


class SimulatedJoints(LeafSystem):
    """Perfect joint-velocity tracking: q_{k+1} = q_k + dt v_k. Input ``velocity`` (7).
    Outputs ``position`` (7, state), ``velocity_measured`` (7, state: the applied v)."""

    def __init__(self, q0, period: float):
        super().__init__()
        self._dt = float(period)
        self._v_in = self.DeclareVectorInputPort("velocity", NUM_JOINTS)
        self._q = self.DeclareDiscreteState(np.asarray(q0, float))
        self._v = self.DeclareDiscreteState(NUM_JOINTS)
        self.DeclarePeriodicDiscreteUpdateEvent(self._dt, 0.0, self._update)
        self.DeclareStateOutputPort("position", self._q)
        self.DeclareStateOutputPort("velocity_measured", self._v)

    def _update(self, context, ds):
        v = np.asarray(self._v_in.Eval(context), float)
        q = context.get_discrete_state(self._q).get_value()
        ds.get_mutable_vector(self._q).SetFromVector(q + self._dt * v)
        ds.get_mutable_vector(self._v).SetFromVector(v)


class LossyLcmPublisher(LeafSystem):
    """Publishes its input (a Python LCM message, e.g. from :class:`WallClockStamper`, which
    stamps it when evaluated here) on ``channel`` every ``period`` s and on a forced
    publish, dropping each message with probability ``drop_probability`` (a lossy wire;
    seeded by ``seed``). Counts ``published`` and ``dropped``."""

    def __init__(
        self,
        lcm,
        channel: str,
        lcm_type,
        period: float,
        *,
        drop_probability: float = 0.0,
        seed: int = 0,
    ):
        super().__init__()
        if not 0.0 <= drop_probability <= 1.0:
            raise ValueError(
                f"drop_probability: expected a probability in [0, 1], got {drop_probability}"
            )
        self._lcm, self._channel = lcm, channel
        self._p = float(drop_probability)
        self._rng = np.random.default_rng(seed)
        self.published = 0
        self.dropped = 0
        self._in = self.DeclareAbstractInputPort(lcm_type.__name__, AbstractValue.Make(lcm_type()))
        self.DeclarePeriodicPublishEvent(float(period), 0.0, self._publish)
        self.DeclareForcedPublishEvent(self._publish)

    def _publish(self, context):
        if self._p > 0.0 and self._rng.random() < self._p:
            self.dropped += 1
            return
        self._lcm.Publish(self._channel, self._in.Eval(context).encode())
        self.published += 1


class StatusSlot(LeafSystem):
    """Hands its input (a Python LCM message, stamped when evaluated) to ``sink(message)``
    every ``period`` s and on a forced publish: the newest status for a publisher that runs
    beside the simulation (``drake_rus.rehearsal``'s status thread or process), so that the
    status stream keeps its rate while a simulation step takes long."""

    def __init__(self, lcm_type, period: float, sink):
        super().__init__()
        self._sink = sink
        self._in = self.DeclareAbstractInputPort(lcm_type.__name__, AbstractValue.Make(lcm_type()))
        self.DeclarePeriodicPublishEvent(float(period), 0.0, self._publish)
        self.DeclareForcedPublishEvent(self._publish)

    def _publish(self, context):
        self._sink(self._in.Eval(context))


@dataclass
class DriverWire:
    """What :func:`AddSimulatedDriverWire` added: ``velocity`` (the accepted joint-velocity
    command, an OutputPort for the robot's input), the ``expiry`` system (its command logs),
    the ``receiver`` and the status ``publisher`` (its counts; a :class:`StatusSlot` when
    the statuses are published beside the simulation)."""

    velocity: object
    expiry: CommandExpiry
    receiver: object
    publisher: object


def AddSimulatedDriverWire(
    builder: DiagramBuilder,
    lcm,
    *,
    position,
    velocity,
    tau_external_drake,
    rate_hz: float = 200.0,
    command_expiry: float = DRIVER_EXPIRE_SEC,
    command_latency: float = 0.0,
    status_drop_probability: float = 0.0,
    seed: int = 0,
    command_channel: str = "PANDA_COMMAND",
    status_channel: str = "PANDA_STATUS",
    status_sink=None,
) -> DriverWire:
    """Adds drake-franka-driver's wire side (velocity mode) to ``builder`` around a simulated
    robot whose joint ``position`` (7, rad), ``velocity`` (7, rad/s) and
    ``tau_external_drake`` (7, N m, Drake's sign) are OutputPorts in ``builder``: the
    LcmInterfaceSystem on ``lcm`` (add none other), the command subscriber, the expiry (and
    ``command_latency``), Drake's PandaCommandReceiver, and the status every 1 / ``rate_hz``
    s through PandaStatusSender, stamped with wall-clock microseconds, external torque in
    the driver's sign, each status dropped with ``status_drop_probability``. Connect the
    returned ``velocity`` port to the robot's joint-velocity input. ``status_sink(msg)``:
    instead of publishing, hand each status to it (a publisher beside the simulation, which
    then also drops statuses)."""
    import drake
    from pydrake.manipulation import PandaCommandReceiver, PandaControlMode, PandaStatusSender
    from pydrake.systems.lcm import LcmInterfaceSystem, LcmSubscriberSystem

    builder.AddNamedSystem("lcm", LcmInterfaceSystem(lcm))
    sub = builder.AddNamedSystem(
        "command_subscriber",
        LcmSubscriberSystem.Make(
            channel=command_channel,
            lcm_type=drake.lcmt_panda_command,
            lcm=lcm,
            use_cpp_serializer=True,
        ),
    )
    expiry = builder.AddNamedSystem(
        "command_expiry", CommandExpiry(command_expiry, command_latency)
    )
    receiver = builder.AddNamedSystem(
        "command_receiver", PandaCommandReceiver(NUM_JOINTS, PandaControlMode.kVelocity)
    )
    builder.Connect(sub.get_output_port(), expiry.get_input_port())
    builder.Connect(expiry.get_output_port(), receiver.GetInputPort("lcmt_panda_command"))
    builder.Connect(position, receiver.GetInputPort("position_measured"))

    status = builder.AddNamedSystem("status_sender", PandaStatusSender(NUM_JOINTS))
    zero = builder.AddNamedSystem("zero_torque", ConstantVectorSource(np.zeros(NUM_JOINTS)))
    # The driver reports libfranka's sign: the robot's torque on the environment.
    flip = builder.AddNamedSystem("external_torque_to_driver_sign", Gain(-1.0, NUM_JOINTS))
    builder.Connect(tau_external_drake, flip.get_input_port())
    builder.Connect(position, status.GetInputPort("position_measured"))
    builder.Connect(velocity, status.GetInputPort("velocity_measured"))
    builder.Connect(receiver.GetOutputPort("velocity"), status.GetInputPort("velocity_commanded"))
    builder.Connect(zero.get_output_port(), status.GetInputPort("torque_commanded"))
    builder.Connect(flip.get_output_port(), status.GetInputPort("torque_external"))
    stamper = builder.AddNamedSystem(
        "wall_clock_stamper", WallClockStamper(drake.lcmt_panda_status)
    )
    builder.Connect(status.get_output_port(), stamper.get_input_port())
    if status_sink is not None:
        pub = builder.AddNamedSystem(
            "status_publisher", StatusSlot(drake.lcmt_panda_status, 1.0 / rate_hz, status_sink)
        )
    else:
        pub = builder.AddNamedSystem(
            "status_publisher",
            LossyLcmPublisher(
                lcm,
                status_channel,
                drake.lcmt_panda_status,
                1.0 / rate_hz,
                drop_probability=status_drop_probability,
                seed=seed,
            ),
        )
    builder.Connect(stamper.get_output_port(), pub.get_input_port())
    return DriverWire(
        velocity=receiver.GetOutputPort("velocity"), expiry=expiry, receiver=receiver, publisher=pub
    )


class SimulatedPandaDriver(Diagram):
    """The simulated driver on ``lcm`` (see the module doc). Run it with its own Simulator
    next to the station's (both pump the same DrakeLcm). ``q0`` (rad): start positions;
    ``tau_external_drake`` (7, N m, Drake's sign): the external torque to report."""

    def __init__(
        self,
        lcm,
        q0,
        *,
        rate_hz: float = 200.0,
        command_expiry: float = 0.1,
        tau_external_drake=None,
        command_channel: str = "PANDA_COMMAND",
        status_channel: str = "PANDA_STATUS",
        command_latency: float = 0.0,
        status_drop_probability: float = 0.0,
        seed: int = 0,
    ):
        super().__init__()
        b = DiagramBuilder()
        joints = b.AddNamedSystem("joints", SimulatedJoints(q0, 1.0 / rate_hz))
        tau = (
            np.zeros(NUM_JOINTS)
            if tau_external_drake is None
            else np.asarray(tau_external_drake, float)
        )
        self.tau_source = b.AddNamedSystem("external_torque", ConstantVectorSource(tau))
        wire = AddSimulatedDriverWire(
            b,
            lcm,
            position=joints.GetOutputPort("position"),
            velocity=joints.GetOutputPort("velocity_measured"),
            tau_external_drake=self.tau_source.get_output_port(),
            rate_hz=rate_hz,
            command_expiry=command_expiry,
            command_latency=command_latency,
            status_drop_probability=status_drop_probability,
            seed=seed,
            command_channel=command_channel,
            status_channel=status_channel,
        )
        b.Connect(wire.velocity, joints.GetInputPort("velocity"))
        b.ExportOutput(joints.GetOutputPort("position"), "position")
        b.ExportOutput(joints.GetOutputPort("velocity_measured"), "velocity")
        b.BuildInto(self)
        self.expiry = wire.expiry
        self.publisher = wire.publisher
        self.lcm = lcm

    def publish_once(self, context) -> None:
        """Publishes one status now (e.g. before the station connects)."""
        pub = self.GetSubsystemByName("status_publisher")
        pub.ForcedPublish(pub.GetMyContextFromRoot(context))
