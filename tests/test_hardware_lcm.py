"""The LCM backend in-process on ``memq://``: the hardware station against a simulated
drake-franka-driver built from Drake's PandaCommandReceiver / PandaStatusSender.

The driver drops commands whose utime is not within EXPIRY s of its wall clock (like the real
driver), integrates the velocities it accepts and reports libfranka's torque sign. The two
diagrams share one DrakeLcm and are stepped in lockstep in this thread.
"""

import math
import time

import drake
import numpy as np
import pytest
from conftest import hardware_scenario
from pydrake.lcm import DrakeLcm
from pydrake.math import RigidTransform
from pydrake.multibody.tree import JacobianWrtVariable
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import LeafSystem

from drake_rus.bringup import BuildHardwareClosedLoop, RunScriptedMotion, ScriptedMotion
from drake_rus.hardware.lcm_sim_driver import CommandExpiry, SimulatedPandaDriver
from drake_rus.hardware.station import HardwareFault, MakeHardwareStation, RunHardware
from drake_rus.imaging.frames import UsFrame
from drake_rus.robot import MakeControlPlant
from drake_rus.scenario import LoadScenario
from drake_rus.station_interface import ports_of
from drake_rus.stations import MakeStation

EXPIRY = 0.25  # s, the simulated driver's command expiry (generous: shared CPU)
STEP = 0.005  # s, lockstep chunk (one control period at 200 Hz)

pytestmark = [pytest.mark.timeout(300), pytest.mark.wallclock]


def lcm_scenario(**hw):
    fields = {
        "backend": "lcm",
        "dry_run": False,
        "tau_external_bias_duration": 0.0,
        "connect_timeout": 5.0,
        "status_timeout": 0.5,
        # The simulated robot reports no probe weight: as if the probe were entered
        # in Desk (lcm_compensate_load must then be off).
        "lcm_compensate_load": False,
    }
    fields.update(hw)
    return hardware_scenario(fields)


def assert_reached_fresh(log, expiry: float = EXPIRY, stall_share: float = 0.02) -> None:
    """Every command in the driver's ``log`` (wall time s at the robot, utime us, velocity,
    fresh) carries a wall-clock stamp that reached the robot within ``expiry``; a few may
    arrive late only across a stall of this shared-CPU test process (both sides run in
    lockstep in one thread, so a pause between stamping and delivery ages a command by its
    length): at most ``stall_share`` of them, each under 20 expiries old. A stamp in
    simulation time (about 1.7e9 s old) or a command re-sent from the past fails."""
    assert log, "no command reached the robot"
    ages = np.array([t - utime * 1e-6 for t, utime, *_ in log])
    assert np.all(ages > -1e-3) and np.all(ages < 20 * expiry), ages.max()
    late = [age for age, (*_, fresh) in zip(ages, log) if not fresh]
    assert len(late) <= stall_share * len(log), (len(late), len(log), late[:5])
    assert all(age >= expiry for age in late)


class Rig:
    """Station + simulated driver on one memq:// DrakeLcm, and a wire tap on PANDA_COMMAND."""

    def __init__(self, scenario, tau_external_drake=None):
        self.scenario = scenario
        self.lcm = DrakeLcm("memq://")
        self.wire = []  # (wall time s, lcmt_panda_command) as published
        self.lcm.Subscribe(
            "PANDA_COMMAND",
            lambda data: self.wire.append((time.time(), drake.lcmt_panda_command.decode(data))),
        )
        self.q0 = np.asarray(scenario.robot.initial_joint_positions, float)
        self.driver = SimulatedPandaDriver(
            self.lcm, self.q0, command_expiry=EXPIRY, tau_external_drake=tau_external_drake
        )
        self.dsim = Simulator(self.driver)
        self.dsim.Initialize()
        self.station = MakeHardwareStation(scenario, lcm=self.lcm, lcm_idle=self.step_driver)

    def pump(self):
        """Delivers what was published (e.g. the session's final zeros) to the wire tap."""
        self.lcm.HandleSubscriptions(0)
        return self.wire

    def step_driver(self, dt=STEP):
        self.dsim.AdvanceTo(self.dsim.get_context().get_time() + dt)

    def driver_q(self):
        return self.driver.GetOutputPort("position").Eval(self.dsim.get_context())

    def driver_v(self):
        return self.driver.GetOutputPort("velocity").Eval(self.dsim.get_context())


def test_lcm_station_ports_stamps_tracking_and_torque_sign():
    scenario = lcm_scenario()
    # A known wrench on the probe (in P): 6 N pushing back along -z_P and a small torque.
    plant, tip = MakeControlPlant(scenario.robot, scenario.probe)
    pc = plant.CreateDefaultContext()
    q0 = np.asarray(scenario.robot.initial_joint_positions)
    plant.SetPositions(pc, q0)
    W = plant.world_frame()
    J = plant.CalcJacobianSpatialVelocity(pc, JacobianWrtVariable.kV, tip, np.zeros(3), W, W)
    R_WP = tip.CalcPoseInWorld(pc).rotation().matrix()
    F_P = np.array([0.0, 0.1, 0.0, 0.0, 0.0, -6.0])
    F_W = np.concatenate([R_WP @ F_P[:3], R_WP @ F_P[3:]])
    tau_drake = J.T @ F_W
    rig = Rig(scenario, tau_external_drake=tau_drake)
    st = rig.station

    # Same ports and types as the simulated station.
    sim_station = MakeStation(LoadScenario())
    both = [
        p.name
        for p in ports_of("sim", include_optional=False)
        if "hardware" in p.stations and p.direction == "out" and p.size is not None
    ]
    assert both == ["joint_position", "joint_velocity", "tau_external", "probe_force"]
    for name in both:
        assert st.HasOutputPort(name)
        assert st.GetOutputPort(name).size() == sim_station.GetOutputPort(name).size()
    assert st.get_input_port().get_name() == "joint_velocity_command"
    ctx0 = st.CreateDefaultContext()
    assert isinstance(st.GetOutputPort("X_BP").Eval(ctx0), RigidTransform)
    assert isinstance(st.GetOutputPort("us_image").Eval(ctx0), UsFrame)
    np.testing.assert_allclose(st.GetOutputPort("joint_position").Eval(ctx0), q0)

    sim = Simulator(st)
    ctx = st.GetMyContextFromRoot(sim.get_context())
    v_cmd = np.array([0.1, -0.05, 0.0, 0.08, 0.0, 0.0, 0.2])
    st.get_input_port().FixValue(ctx, v_cmd)
    sim.Initialize()
    wall_start = time.time()
    q_driver_start = rig.driver_q().copy()
    RunHardware(sim, st, 1.0, check_period=STEP, realtime_rate=0.0, on_step=rig.step_driver)
    wall_end = time.time()

    # Commands on the wire: wall-clock microseconds, fresh, velocity mode, never rejected.
    cmds = [(t, m) for t, m in rig.wire if t <= wall_end]
    assert len(cmds) >= 150
    for t_rx, m in cmds:
        assert wall_start - 1.0 <= m.utime * 1e-6 <= wall_end
        assert m.control_mode_expected == 2 and m.num_joint_velocity == 7
    assert_reached_fresh(rig.driver.expiry.log)
    # Velocities tracked: the driver applies the command (after the acceleration ramp).
    np.testing.assert_allclose(rig.driver_v(), v_cmd, atol=1e-12)
    np.testing.assert_allclose(st.GetOutputPort("joint_velocity").Eval(ctx), v_cmd, atol=1e-12)
    moved = rig.driver_q() - q_driver_start
    # 1 s at v_cmd, less the ramp (v / a_max / 2 at 2 rad/s^2) and 1-3 periods of latency.
    lag = v_cmd**2 / (2 * 2.0) + 3 * STEP * np.abs(v_cmd)
    assert np.all(np.abs(moved - v_cmd * 1.0) <= lag + 1e-9), (moved, v_cmd)
    np.testing.assert_allclose(
        st.GetOutputPort("joint_position").Eval(ctx),
        rig.driver_q(),
        atol=np.abs(v_cmd).max() * 4 * STEP + 1e-12,
    )  # status latency
    # Torque sign: the driver publishes -tau_drake; the station exports tau_drake, and the
    # probe force estimate recovers the wrench (q moved a little: tolerance).
    np.testing.assert_allclose(st.GetOutputPort("tau_external").Eval(ctx), tau_drake, atol=1e-9)
    F_est = st.GetOutputPort("probe_force").Eval(ctx)
    assert F_est[5] == pytest.approx(-6.0, abs=0.6)
    assert st.GetOutputPort("robot_ok").Eval(ctx)[0] == 1.0
    # After the session: zero velocity on the wire.
    assert rig.pump()[-1][1].joint_velocity == tuple([0.0] * 7)
    print(
        f"\n[lcm] {len(cmds)} commands in {wall_end - wall_start:.2f} s wall; "
        f"max command age at the driver "
        f"{1e3 * max(abs(t - m.utime * 1e-6) for t, m in cmds):.2f} ms; "
        f"joint displacement error {np.abs(moved - v_cmd).max():.2e} rad"
    )


def test_commands_on_the_wire_keep_the_acceleration_limit():
    """The publisher runs after the tick's updates, so it must send the command the guard
    stored: what goes on the wire changes by at most max_joint_acceleration * dt a period,
    ramping and when the desired command reverses every period (the guard's feedthrough,
    read after its update, is limited against the command just stored: two or three steps
    a period)."""
    scenario = lcm_scenario()
    rig = Rig(scenario)
    st = rig.station
    sim = Simulator(st)
    ctx = st.GetMyContextFromRoot(sim.get_context())
    cfg = scenario.hardware_interface
    dt = 1.0 / cfg.command_rate_hz
    sim.Initialize()
    for k in range(40):
        v = np.zeros(7)
        v[0] = 0.5 if k % 2 == 0 else -0.5  # reverses every period
        v[3] = 0.3  # a ramp
        st.get_input_port().FixValue(ctx, v)
        sim.AdvanceTo(sim.get_context().get_time() + dt)
        rig.step_driver(dt)
        rig.pump()
    sent = np.array([m.joint_velocity for _, m in rig.wire if m.num_joint_velocity == 7])
    assert len(sent) >= 40
    steps = np.abs(np.diff(sent, axis=0)).max(axis=0)
    limit = np.asarray(cfg.max_joint_acceleration) * dt
    assert np.all(steps <= limit + 1e-12), (steps, limit)
    assert sent[:, 3].max() > 10 * limit[3]  # it did ramp


def test_simulation_time_stamps_would_be_dropped_by_the_driver():
    """Why the stamper exists: PandaCommandSender stamps context time, which the driver
    (and our simulated one) never accepts."""
    from pydrake.manipulation import PandaCommandSender, PandaControlMode

    sender = PandaCommandSender(7, PandaControlMode.kVelocity)
    sc = sender.CreateDefaultContext()
    sc.SetTime(2.0)
    sender.get_input_port().FixValue(sc, np.full(7, 0.1))
    expiry = CommandExpiry(EXPIRY)
    ec = expiry.CreateDefaultContext()
    expiry.get_input_port().FixValue(ec, sender.get_output_port().EvalAbstract(sc))
    out = expiry.get_output_port().EvalAbstract(ec)
    import pydrake.systems.lcm as L

    msg = drake.lcmt_panda_command.decode(L._Serializer_[drake.lcmt_panda_command]().Serialize(out))
    assert msg.joint_velocity == tuple([0.0] * 7)
    assert expiry.log[-1][1] == 2_000_000 and not expiry.log[-1][3]


def test_lcm_scripted_motion_with_unchanged_controller_and_safety():
    rig = Rig(lcm_scenario())
    loop = BuildHardwareClosedLoop(rig.scenario, rig.station)
    motion = ScriptedMotion(t_orientation=0.2, t_slide=1.2, duration=3.0)
    result = RunScriptedMotion(
        loop, rig.station, motion, realtime_rate=0.0, check_period=STEP, on_step=rig.step_driver
    )
    assert result.safety_events == ()
    assert math.degrees(result.approach_error) < 0.5
    assert math.degrees(result.orientation_error) < 0.5
    assert result.position_error_xy < 1e-3
    dy = result.X_BP_end.translation()[1] - result.X_BP_start.translation()[1]
    assert dy == pytest.approx(0.02, abs=1e-3)
    assert np.abs(result.q_end - result.q_start).max() > 0.02  # the joints moved
    np.testing.assert_allclose(result.q_end, rig.driver_q(), atol=1e-3)
    assert rig.pump()[-1][1].joint_velocity == tuple([0.0] * 7)
    assert_reached_fresh(rig.driver.expiry.log)
    print(
        f"\n[lcm motion] approach error {math.degrees(result.approach_error):.3f} deg, "
        f"x-y error {1e3 * result.position_error_xy:.2f} mm, dy {1e3 * dy:.2f} mm"
    )


def test_stale_command_stops_the_driver():
    """The station stops sending (a frozen process): the driver's newest command ages out
    and it applies zero velocity."""
    rig = Rig(lcm_scenario())
    st = rig.station
    sim = Simulator(st)
    ctx = st.GetMyContextFromRoot(sim.get_context())
    v_cmd = np.array([0.1, 0, 0, 0, 0, 0, 0])
    st.get_input_port().FixValue(ctx, v_cmd)
    sim.Initialize()
    # Lockstep without a session: the station process then "freezes" mid-motion.
    while sim.get_context().get_time() < 0.3:
        sim.AdvanceTo(sim.get_context().get_time() + STEP)
        rig.step_driver()
    assert np.allclose(rig.driver_v(), v_cmd)
    t_last = rig.wire[-1][0]
    stopped_at = None
    while time.time() - t_last < 1.0:
        rig.step_driver()
        if not np.any(rig.driver_v()):
            stopped_at = time.time()
            break
        time.sleep(0.002)
    assert stopped_at is not None, "the driver kept a stale command"
    latency = stopped_at - t_last
    assert latency >= EXPIRY - 0.05  # stamped at publish, tapped a little later
    q_stop = rig.driver_q().copy()
    for _ in range(20):
        rig.step_driver()
    np.testing.assert_array_equal(rig.driver_q(), q_stop)
    print(
        f"\n[lcm stale] driver zeroed the command {1e3 * latency:.1f} ms after the last "
        f"one (expiry {1e3 * EXPIRY:.0f} ms)"
    )


def test_lost_connection_ends_at_zero_command():
    rig = Rig(lcm_scenario(status_timeout=0.3))
    st = rig.station
    sim = Simulator(st)
    ctx = st.GetMyContextFromRoot(sim.get_context())
    st.get_input_port().FixValue(ctx, np.array([0, 0.1, 0, 0, 0, 0, 0]))
    sim.Initialize()
    t_wall = {}

    def step():
        if sim.get_context().get_time() < 0.3:
            rig.step_driver()
        else:
            t_wall.setdefault("lost", time.time())  # the driver stops answering
            time.sleep(0.002)

    with pytest.raises(HardwareFault, match="robot state lost"):
        RunHardware(sim, st, 5.0, check_period=STEP, realtime_rate=0.0, on_step=step)
    detected = time.time()
    assert detected - t_wall["lost"] >= 0.3 - 0.01
    assert st.GetOutputPort("robot_ok").Eval(ctx)[0] == 0.0
    assert not np.any(st.GetOutputPort("commanded_velocity").Eval(ctx))
    # The session's final commands on the wire are zero, stamped with wall-clock time.
    wire = rig.pump()
    assert all(m.joint_velocity == tuple([0.0] * 7) for _, m in wire[-3:])
    assert all(abs(t - m.utime * 1e-6) < EXPIRY for t, m in wire[-3:])
    print(
        f"\n[lcm lost] fault detected {1e3 * (detected - t_wall['lost']):.0f} ms after the "
        f"last status (status_timeout 300 ms)"
    )


class Boom(LeafSystem):
    """Raises ``error`` from a periodic event at ``t``."""

    def __init__(self, t, error):
        super().__init__()
        self._t, self._error = t, error
        self.DeclarePeriodicPublishEvent(0.01, 0.0, self._check)

    def _check(self, context):
        if context.get_time() >= self._t:
            raise self._error


@pytest.mark.parametrize("error", [RuntimeError("controller bug"), KeyboardInterrupt()])
def test_exception_ends_at_zero_command(error):
    rig = Rig(lcm_scenario())
    st = rig.station
    from pydrake.systems.framework import DiagramBuilder

    b = DiagramBuilder()
    b.AddSystem(st)
    b.AddSystem(Boom(0.2, error))
    d = b.Build()
    sim = Simulator(d)
    ctx = st.GetMyContextFromRoot(sim.get_context())
    st.get_input_port().FixValue(ctx, np.array([0, 0, 0, 0, 0.2, 0, 0]))
    sim.Initialize()
    with pytest.raises(type(error)):
        RunHardware(sim, st, 2.0, check_period=STEP, realtime_rate=0.0, on_step=rig.step_driver)
    assert sim.get_context().get_time() < 0.5
    assert rig.pump()[-1][1].joint_velocity == tuple([0.0] * 7)
    assert abs(rig.wire[-1][0] - rig.wire[-1][1].utime * 1e-6) < EXPIRY
    for _ in range(3):
        rig.step_driver()
    assert not np.any(rig.driver_v())


def test_dry_run_publishes_nothing():
    rig = Rig(lcm_scenario(dry_run=True))
    st = rig.station
    sim = Simulator(st)
    ctx = st.GetMyContextFromRoot(sim.get_context())
    st.get_input_port().FixValue(ctx, np.full(7, 0.1))
    sim.Initialize()
    RunHardware(sim, st, 0.2, check_period=STEP, realtime_rate=0.0, on_step=rig.step_driver)
    assert rig.wire == []
    assert not np.any(st.GetOutputPort("commanded_velocity").Eval(ctx))
    np.testing.assert_allclose(rig.driver_q(), rig.q0)
    assert st.GetOutputPort("robot_ok").Eval(ctx)[0] == 1.0


def test_no_driver_is_a_clear_error():
    scenario = lcm_scenario(connect_timeout=0.2)
    with pytest.raises(HardwareFault, match="hardware_interface.lcm_status_channel"):
        MakeHardwareStation(scenario, lcm=DrakeLcm("memq://"))


def test_sigterm_ends_at_zero_command():
    """SIGTERM (or Ctrl-C) during a run: the session turns it into KeyboardInterrupt and
    sends zero velocity."""
    import os
    import signal

    rig = Rig(lcm_scenario())
    st = rig.station
    sim = Simulator(st)
    ctx = st.GetMyContextFromRoot(sim.get_context())
    st.get_input_port().FixValue(ctx, np.array([0, 0, 0.1, 0, 0, 0, 0]))
    sim.Initialize()

    def step():
        rig.step_driver()
        if sim.get_context().get_time() >= 0.2:
            os.kill(os.getpid(), signal.SIGTERM)

    previous = signal.getsignal(signal.SIGTERM)
    with pytest.raises(KeyboardInterrupt):
        RunHardware(sim, st, 2.0, check_period=STEP, realtime_rate=0.0, on_step=step)
    assert signal.getsignal(signal.SIGTERM) is previous  # handler restored
    assert rig.pump()[-1][1].joint_velocity == tuple([0.0] * 7)
    for _ in range(3):
        rig.step_driver()
    assert not np.any(rig.driver_v())
