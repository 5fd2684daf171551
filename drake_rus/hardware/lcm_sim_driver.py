"""A simulated drake-franka-driver on LCM, for tests and for rehearsing the LCM route.

Built from Drake's own ``PandaCommandReceiver`` / ``PandaStatusSender`` like the driver's
simulation counterpart: it subscribes to PANDA_COMMAND, drops commands whose ``utime`` is not
within ``command_expiry`` s of its wall clock (as drake-franka-driver does; a command stamped
with simulation time is never used), integrates the commanded joint velocities (perfect
velocity tracking) and publishes PANDA_STATUS stamped with wall-clock microseconds, with
``joint_torque_external`` in the driver's sign (robot on environment, the opposite of
Drake's): it publishes ``-tau_external_drake``.
"""

from __future__ import annotations

import time

import numpy as np
from pydrake.systems.framework import Diagram, DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ConstantVectorSource

from drake_rus.hardware.core import is_command_fresh, wall_clock_utime
from drake_rus.hardware.systems import WallClockStamper
from drake_rus.robot.model import NUM_JOINTS

__all__ = ["SimulatedPandaDriver", "CommandExpiry", "SimulatedJoints"]



class CommandExpiry(LeafSystem):
    """Input ``lcmt_panda_command_in`` (C++). Output ``lcmt_panda_command`` (C++): the input
    if its ``utime`` is within ``expiry`` s of the wall clock, else a zero-velocity command.
    Records every distinct command seen (``log``: wall time s, utime, velocity, fresh)."""

    def __init__(self, expiry: float):
        super().__init__()
        import drake
        import pydrake.systems.lcm as lcm_systems
        self._type = drake.lcmt_panda_command
        self._ser = lcm_systems._Serializer_[drake.lcmt_panda_command]()
        self._expiry = float(expiry)
        self.log: list[tuple[float, int, np.ndarray, bool]] = []
        self._last_utime = None
        self._in = self.DeclareAbstractInputPort("lcmt_panda_command_in",
                                                 self._ser.CreateDefaultValue())
        self.DeclareAbstractOutputPort(
            "lcmt_panda_command", lambda: self._ser.CreateDefaultValue(), self._calc,
            prerequisites_of_calc={self.time_ticket(),
                                   self.input_port_ticket(self._in.get_index())})

    def _calc(self, context, output):
        raw = self._ser.Serialize(self._in.EvalAbstract(context))
        msg = self._type.decode(raw)
        now = time.time()
        fresh = msg.num_joint_velocity == NUM_JOINTS and is_command_fresh(
            msg.utime, now, self._expiry)
        if msg.num_joint_velocity == NUM_JOINTS and msg.utime != self._last_utime:
            self._last_utime = msg.utime
            self.log.append((now, int(msg.utime), np.array(msg.joint_velocity), fresh))
        if not fresh:
            msg = self._type()
            msg.utime = wall_clock_utime(now)
            msg.control_mode_expected = 2
            msg.num_joint_velocity = NUM_JOINTS
            msg.joint_velocity = [0.0] * NUM_JOINTS
            raw = msg.encode()
        self._ser.Deserialize(raw, output)


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


class SimulatedPandaDriver(Diagram):
    """The simulated driver on ``lcm`` (see the module doc). Run it with its own Simulator
    next to the station's (both pump the same DrakeLcm). ``q0`` (rad): start positions;
    ``tau_external_drake`` (7, N m, Drake's sign): the external torque to report."""

    def __init__(self, lcm, q0, *, rate_hz: float = 200.0, command_expiry: float = 0.1,
                 tau_external_drake=None, command_channel: str = "PANDA_COMMAND",
                 status_channel: str = "PANDA_STATUS"):
        super().__init__()
        import drake
        from pydrake.manipulation import (PandaCommandReceiver, PandaControlMode,
                                          PandaStatusSender)
        from pydrake.systems.lcm import (LcmInterfaceSystem, LcmPublisherSystem,
                                         LcmSubscriberSystem)
        b = DiagramBuilder()
        b.AddNamedSystem("lcm", LcmInterfaceSystem(lcm))
        sub = b.AddNamedSystem("command_subscriber", LcmSubscriberSystem.Make(
            channel=command_channel, lcm_type=drake.lcmt_panda_command, lcm=lcm,
            use_cpp_serializer=True))
        self.expiry = b.AddNamedSystem("command_expiry", CommandExpiry(command_expiry))
        receiver = b.AddNamedSystem(
            "command_receiver", PandaCommandReceiver(NUM_JOINTS, PandaControlMode.kVelocity))
        joints = b.AddNamedSystem("joints", SimulatedJoints(q0, 1.0 / rate_hz))
        b.Connect(sub.get_output_port(), self.expiry.get_input_port())
        b.Connect(self.expiry.get_output_port(), receiver.GetInputPort("lcmt_panda_command"))
        b.Connect(joints.GetOutputPort("position"), receiver.GetInputPort("position_measured"))
        b.Connect(receiver.GetOutputPort("velocity"), joints.GetInputPort("velocity"))

        status = b.AddNamedSystem("status_sender", PandaStatusSender(NUM_JOINTS))
        tau = np.zeros(NUM_JOINTS) if tau_external_drake is None else np.asarray(
            tau_external_drake, float)
        zero = b.AddNamedSystem("zero_torque", ConstantVectorSource(np.zeros(NUM_JOINTS)))
        # The driver reports libfranka's sign: the robot's torque on the environment.
        self.tau_source = b.AddNamedSystem("external_torque", ConstantVectorSource(-tau))
        b.Connect(joints.GetOutputPort("position"), status.GetInputPort("position_measured"))
        b.Connect(joints.GetOutputPort("velocity_measured"),
                  status.GetInputPort("velocity_measured"))
        b.Connect(receiver.GetOutputPort("velocity"), status.GetInputPort("velocity_commanded"))
        b.Connect(zero.get_output_port(), status.GetInputPort("torque_commanded"))
        b.Connect(self.tau_source.get_output_port(), status.GetInputPort("torque_external"))
        stamper = b.AddNamedSystem("wall_clock_stamper", WallClockStamper(drake.lcmt_panda_status))
        b.Connect(status.get_output_port(), stamper.get_input_port())
        pub = b.AddNamedSystem("status_publisher", LcmPublisherSystem.Make(
            channel=status_channel, lcm_type=drake.lcmt_panda_status, lcm=lcm,
            publish_period=1.0 / rate_hz, use_cpp_serializer=False))
        b.Connect(stamper.get_output_port(), pub.get_input_port())
        b.ExportOutput(joints.GetOutputPort("position"), "position")
        b.ExportOutput(joints.GetOutputPort("velocity_measured"), "velocity")
        b.BuildInto(self)
        self.lcm = lcm

    def publish_once(self, context) -> None:
        """Publishes one status now (e.g. before the station connects)."""
        pub = self.GetSubsystemByName("status_publisher")
        pub.ForcedPublish(pub.GetMyContextFromRoot(context))
