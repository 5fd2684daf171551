"""The LCM backend of the hardware station: drake-franka-driver through Drake's
``PandaCommandSender`` / ``PandaStatusReceiver`` over LCM (channels PANDA_COMMAND /
PANDA_STATUS, velocity mode), commands stamped with wall-clock microseconds, the driver's
external torque sign flipped to Drake's and (``lcm_compensate_load``) the probe's weight
removed, since the driver cannot declare a load. The franky backend is ``franky_backend``.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from drake_rus.config_schema import ScenarioError
from drake_rus.hardware.config import HardwareConfig
from drake_rus.hardware.core import external_torque_to_drake, wall_clock_utime
from drake_rus.hardware.franky_backend import HardwareFault
from drake_rus.hardware.systems import (
    ExternalTorqueToDrake,
    PandaStatusLatch,
    ProbeLoadCompensation,
    WallClockCommandStamper,
)
from drake_rus.robot import NUM_JOINTS

LOG = logging.getLogger("drake_rus.hardware")

__all__ = ["LcmBackend", "wait_for_panda_status", "AddLcmBackend"]


def wait_for_panda_status(
    lcm, channel: str, timeout: float, *, count: int = 1, duration: float = 0.0, idle=None
) -> list[bytes]:
    """Pumps ``lcm`` until ``count`` lcmt_panda_status messages arrived on ``channel`` and
    ``duration`` s passed (or raises HardwareFault after ``timeout`` s). ``idle()``, if
    given, is called between pumps (e.g. to step a simulated driver in the same thread).
    Returns the raw messages."""
    received: list[bytes] = []
    active = [True]

    def handler(data: bytes):
        if active[0]:  # the raw subscription outlives this call: stop collecting
            received.append(bytes(data))

    lcm.Subscribe(channel, handler)
    start = time.monotonic()
    while len(received) < count or time.monotonic() - start < duration:
        if time.monotonic() - start > timeout:
            active[0] = False
            raise HardwareFault(
                f"field 'hardware_interface.lcm_status_channel': no lcmt_panda_status on "
                f"{channel!r} within {timeout:g} s (hardware_interface.connect_timeout); is "
                f"drake-franka-driver running and is hardware_interface.lcm_url right?"
            )
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
                raise ScenarioError(
                    f"field 'hardware_interface.lcm_url': cannot open {config.lcm_url!r}: {e}"
                ) from None
        self.lcm = lcm
        statuses = wait_for_panda_status(
            lcm,
            config.lcm_status_channel,
            config.connect_timeout,
            duration=config.tau_external_bias_duration,
            idle=idle,
        )
        import drake

        decoded = [drake.lcmt_panda_status.decode(b) for b in statuses]
        decoded = [m for m in decoded if m.num_joints == NUM_JOINTS]
        if not decoded:
            raise HardwareFault(
                f"field 'hardware_interface.lcm_status_channel': statuses on "
                f"{config.lcm_status_channel!r} are not for a 7-joint arm"
            )
        self.first_status = decoded[-1].encode()
        self.tau_bias = np.zeros(NUM_JOINTS)
        self.load_torque = load_torque
        # At rest, before any bias or load is removed (for the load check).
        self.rest_q = np.mean([m.joint_position for m in decoded], axis=0)
        self.rest_tau = np.mean(
            [external_torque_to_drake(m.joint_torque_external) for m in decoded], axis=0
        )
        if config.tau_external_bias_duration > 0.0:
            self.tau_bias = np.mean(
                [
                    external_torque_to_drake(m.joint_torque_external)
                    - (load_torque(m.joint_position) if load_torque is not None else 0.0)
                    for m in decoded
                ],
                axis=0,
            )
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
            msg.control_mode_expected = 2  # PandaControlMode.kVelocity
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


def AddLcmBackend(builder, backend: LcmBackend, guard, rate, control_plant, probe):
    """Adds the LCM route to ``builder``: status subscriber, latch and receiver, the
    external torque in Drake's sign (bias and, with ``load_torque``, the probe's weight
    removed), the command sender and (not in a dry run) the wall-clock stamped publisher.
    Returns the ports (q, v, tau_external, commanded velocity, robot_ok, state time)."""
    import drake
    from pydrake.manipulation import PandaCommandSender, PandaControlMode, PandaStatusReceiver
    from pydrake.systems.lcm import LcmInterfaceSystem, LcmPublisherSystem, LcmSubscriberSystem

    cfg = backend.config
    builder.AddNamedSystem("lcm", LcmInterfaceSystem(backend.lcm))
    sub = builder.AddNamedSystem(
        "panda_status_subscriber",
        LcmSubscriberSystem.Make(
            channel=cfg.lcm_status_channel,
            lcm_type=drake.lcmt_panda_status,
            lcm=backend.lcm,
            use_cpp_serializer=True,
        ),
    )
    latch = builder.AddNamedSystem(
        "panda_status_latch", PandaStatusLatch(backend.first_status, cfg.status_timeout, rate)
    )
    receiver = builder.AddNamedSystem("panda_status_receiver", PandaStatusReceiver(NUM_JOINTS))
    builder.Connect(sub.get_output_port(), latch.GetInputPort("lcmt_panda_status_in"))
    builder.Connect(latch.GetOutputPort("lcmt_panda_status"), receiver.get_input_port())
    builder.Connect(latch.GetOutputPort("robot_ok"), guard.GetInputPort("robot_ok"))
    torque = builder.AddNamedSystem(
        "external_torque_to_drake", ExternalTorqueToDrake(backend.tau_bias)
    )
    builder.Connect(receiver.get_torque_external_output_port(), torque.get_input_port())
    tau_port = torque.get_output_port()
    if backend.load_torque is not None:
        # drake-franka-driver cannot declare the probe's load: remove its weight here.
        load = builder.AddNamedSystem(
            "probe_load_compensation", ProbeLoadCompensation(control_plant, probe.mass, probe.p_FCm)
        )
        builder.Connect(
            receiver.get_position_measured_output_port(), load.GetInputPort("joint_position")
        )
        builder.Connect(tau_port, load.GetInputPort("tau_external"))
        tau_port = load.GetOutputPort("tau_external")

    sender = builder.AddNamedSystem(
        "panda_command_sender", PandaCommandSender(NUM_JOINTS, PandaControlMode.kVelocity)
    )
    # The publisher runs after the tick's updates: it sends the command the guard's update
    # stored, not the guard's feedthrough (which would limit against that stored command).
    builder.Connect(guard.GetOutputPort("joint_velocity_committed"), sender.get_input_port())
    if not backend.dry_run:
        # A dry run publishes nothing: the driver never receives a command.
        stamper = builder.AddNamedSystem("wall_clock_stamper", WallClockCommandStamper())
        builder.Connect(sender.get_output_port(), stamper.get_input_port())
        publisher = builder.AddNamedSystem(
            "panda_command_publisher",
            LcmPublisherSystem.Make(
                channel=cfg.lcm_command_channel,
                lcm_type=drake.lcmt_panda_command,
                lcm=backend.lcm,
                publish_period=1.0 / rate,
                use_cpp_serializer=False,
            ),
        )
        builder.Connect(stamper.get_output_port(), publisher.get_input_port())
    return (
        receiver.get_position_measured_output_port(),
        receiver.get_velocity_measured_output_port(),
        tau_port,
        guard.GetOutputPort("joint_velocity_committed"),
        latch.GetOutputPort("robot_ok"),
        latch.GetOutputPort("state_time"),
    )
