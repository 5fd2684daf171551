"""Robot-side safety and watchdogs of the hardware station.

- franky route (a fake franky module standing in for franky-control): the FR3's collision
  thresholds are set at connection, below the safety layer's force ceiling; the probe's load
  is declared; a robot with errors pending is refused (operator) or reset (at_connect);
  an unreachable robot is reported after connect_timeout with the time actually spent; the
  command log, the watchdog events and the trace keep only the newest entries, and a
  command that is not 7 velocities is refused in one line before anything is sent;
- LCM route (simulated driver on memq://): the probe's weight, which drake-franka-driver
  cannot declare, is removed when lcm_compensate_load is set, and the check tells which load
  model the torques at rest fit; a stall of our own loop is not taken for a lost robot.
"""

import time
import types

import numpy as np
import pytest
from pydrake.lcm import DrakeLcm
from pydrake.multibody.tree import JacobianWrtVariable
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem

from drake_rus.bringup import load_check as _load_check
from drake_rus.hardware import core, franky_backend
from drake_rus.hardware.config import HardwareConfig
from drake_rus.hardware.franky_backend import FrankyBackend, HardwareFault
from drake_rus.hardware.lcm_sim_driver import SimulatedPandaDriver
from drake_rus.hardware.station import MakeHardwareStation, RunHardware
from drake_rus.hardware.systems import FrankaRobotInterface, ProbeLoadTorque
from drake_rus.robot import MakeControlPlant, estimate_tip_wrench
from drake_rus.scenario import ApplyOverrides, LoadScenario, Scenario

pytestmark = [pytest.mark.timeout(120), pytest.mark.wallclock]


# --- franky route, against a fake franky ---------------------------------------------------
class _Time:
    def to_msec(self):
        return int(time.monotonic() * 1000)


class _Mode:
    def __init__(self, name):
        self.name = name


class _FakeErrors:
    def __init__(self, names=()):
        self._names = list(names)

    def __getstate__(self):
        return tuple(True for _ in self._names) or (False,)


class FakeRobot:
    instances = []
    errors = ()

    def __init__(self, host, realtime_config=None):
        self.host = host
        self.calls = []
        self.relative_dynamics_factor = 1.0
        self.state = types.SimpleNamespace(
            q=np.zeros(7),
            dq=np.zeros(7),
            tau_ext_hat_filtered=np.zeros(7),
            dq_d=np.zeros(7),
            time=_Time(),
            robot_mode=_Mode("Reflex" if FakeRobot.errors else "Idle"),
            current_errors=_FakeErrors(FakeRobot.errors),
        )
        FakeRobot.instances.append(self)

    def set_collision_behavior(self, *args):
        self.calls.append(("set_collision_behavior", [np.asarray(a, float) for a in args]))

    def set_load(self, mass, p, inertia):
        self.calls.append(("set_load", (mass, p, inertia)))

    def recover_from_errors(self):
        self.calls.append(("recover_from_errors", ()))
        self.state.robot_mode = _Mode("Idle")
        self.state.current_errors = _FakeErrors()
        return True

    def poll_motion(self):
        return False

    def move(self, motion, asynchronous=False):
        self.calls.append(("move", motion))

    def join_motion(self, timeout):
        return True


@pytest.fixture
def fake_franky(monkeypatch):
    module = types.SimpleNamespace(
        Robot=FakeRobot,
        RealtimeConfig=types.SimpleNamespace(Ignore=0),
        IncompatibleVersionException=type("Incompatible", (Exception,), {}),
        Duration=lambda ms: ms,
        JointVelocityMotion=lambda v, duration: ("velocity", np.array(v, float), duration),
        JointVelocityStopMotion=lambda: ("stop",),
    )
    monkeypatch.setattr(franky_backend, "_import_franky", lambda: module)
    monkeypatch.setattr(
        franky_backend, "wait_for_port", lambda host, port, timeout: (True, 0.0, "")
    )
    FakeRobot.instances.clear()
    FakeRobot.errors = ()
    yield FakeRobot
    FakeRobot.errors = ()


def _backend(**fields):
    cfg = HardwareConfig(robot_ip="127.0.0.1", tau_external_bias_duration=0.0, **fields)
    return FrankyBackend(cfg, load=(0.55, [0, 0, 0.09], np.diag([2e-3, 2e-3, 4e-4])))


def test_franky_sets_collision_thresholds_below_the_force_ceiling(fake_franky):
    backend = _backend()
    try:
        robot = fake_franky.instances[-1]
        names = [c[0] for c in robot.calls]
        assert names == ["set_collision_behavior", "set_load"]
        lower_tau, upper_tau, lower_f, upper_f = robot.calls[0][1]
        cfg = HardwareConfig()
        np.testing.assert_array_equal(upper_tau, cfg.collision_torque_thresholds)
        np.testing.assert_array_equal(lower_tau, cfg.contact_torque_thresholds)
        np.testing.assert_array_equal(lower_f, cfg.contact_force_thresholds)
        np.testing.assert_array_equal(upper_f, cfg.collision_force_thresholds)
        # The robot's own reflex stops a push on the probe below the safety layer's ceiling,
        # and flags a contact before that.
        ceiling = Scenario().safety.force_ceiling
        assert np.all(upper_f[:3] < ceiling) and np.all(lower_f[:3] < upper_f[:3])
        # Moments at the flange: the collision force at the probe tip, 0.2 m away.
        lever = np.linalg.norm(Scenario().probe.X_FP.GetDeterministicValue().translation())
        assert np.all(upper_f[3:] >= upper_f[:3] * lever)
        assert backend.collision_thresholds is not None
    finally:
        backend.close()
    # Switched off: nothing set (a warning says the robot keeps its old thresholds).
    backend = _backend(set_collision_behavior=False, set_load=False)
    try:
        assert fake_franky.instances[-1].calls == []
    finally:
        backend.close()


def test_collision_threshold_validation():
    ok = core.collision_thresholds(HardwareConfig())
    assert set(ok) == {"lower_torque", "upper_torque", "lower_force", "upper_force"}
    bad = HardwareConfig(contact_force_thresholds=[25.0, 10, 10, 2, 2, 2])
    with pytest.raises(ValueError, match=r"contact_force_thresholds.*entry 0 \(25\)"):
        core.collision_thresholds(bad)
    with pytest.raises(Exception, match="collision_force_thresholds"):
        ApplyOverrides(Scenario(), "{hardware_interface: {collision_force_thresholds: [1, 2]}}")


def test_franky_errors_pending_operator_or_automatic_recovery(fake_franky):
    fake_franky.errors = ("cartesian_reflex",)
    with pytest.raises(HardwareFault, match=r"errors pending \(.*\).*--recover"):
        _backend()
    assert all(c[0] != "recover_from_errors" for c in fake_franky.instances[-1].calls)
    backend = _backend(error_recovery="at_connect")
    try:
        assert fake_franky.instances[-1].calls[0][0] == "recover_from_errors"
    finally:
        backend.close()


def test_franky_command_log_is_bounded_and_a_wrong_length_is_one_line(fake_franky, monkeypatch):
    """The log keeps the newest COMMAND_LOG_LENGTH commands (about 200 a second live); a
    vector that is not 7 velocities is refused before anything is sent, robot not faulted."""
    monkeypatch.setattr(franky_backend, "COMMAND_LOG_LENGTH", 5)
    backend = _backend(dry_run=False, set_collision_behavior=False, set_load=False)
    try:
        robot = fake_franky.instances[-1]
        for i in range(12):
            backend.send(np.full(7, 0.01 * (i + 1)))
        assert len(backend.command_log) == 5
        np.testing.assert_array_equal(backend.command_log[-1][1], np.full(7, 0.12))
        np.testing.assert_array_equal(backend.command_log[0][1], np.full(7, 0.08))
        with pytest.raises(ValueError) as caught:
            backend.send(np.full(6, 0.1))
        message = str(caught.value)
        assert "\n" not in message
        assert "7 joint velocities" in message and "(6,)" in message
        # Nothing of length 6 reached the robot (the watchdog may have sent its zero).
        sent = [c[1][1] for c in robot.calls if c[0] == "move" and c[1][0] == "velocity"]
        assert len(sent) >= 12 and all(v.shape == (7,) for v in sent)
        assert backend.fault is None
    finally:
        backend.close()


def test_franky_watchdog_events_and_trace_are_bounded(fake_franky, monkeypatch):
    """watchdog_events keeps the newest WATCHDOG_EVENTS_LENGTH events and the trace the
    newest TRACE_LENGTH ticks (about 200 a second live): a long run does not fill the
    memory."""
    monkeypatch.setattr(franky_backend, "WATCHDOG_EVENTS_LENGTH", 2)
    monkeypatch.setattr(franky_backend, "TRACE_LENGTH", 5)
    backend = _backend(
        dry_run=False, set_collision_behavior=False, set_load=False, command_timeout=0.02
    )
    try:
        for _ in range(4):  # each command left to go stale: one watchdog event
            backend.send(np.full(7, 0.05))
            deadline = time.monotonic() + 5.0
            while np.any(backend.last_sent) and time.monotonic() < deadline:
                time.sleep(0.005)
            assert not np.any(backend.last_sent), "the watchdog did not zero the command"
        events = list(backend.watchdog_events)
        assert len(events) == 2 and events[0].wall_time < events[1].wall_time

        builder = DiagramBuilder()
        robot = builder.AddSystem(FrankaRobotInterface(backend, 200.0))
        diagram = builder.Build()
        sim = Simulator(diagram)
        robot.get_input_port().FixValue(robot.GetMyContextFromRoot(sim.get_context()), [0] * 7)
        backend.trace = []
        sim.AdvanceTo(0.1)  # 21 ticks at 200 Hz
        trace = list(backend.trace)
        assert len(trace) == 5
        assert [t[3] for t in trace] == sorted(t[3] for t in trace)
        backend.trace = None
        sim.AdvanceTo(0.2)
        assert backend.trace is None
    finally:
        backend.close()


def test_unreachable_robot_reports_the_time_actually_spent():
    """Nothing listens on 127.0.0.3:1337: the fault comes after connect_timeout and says how
    long it took (it used to say "within 10 s" after a minute)."""
    pytest.importorskip("franky", reason="franky-control is not installed")
    cfg = HardwareConfig(robot_ip="127.0.0.3", connect_timeout=0.6)
    start = time.monotonic()
    with pytest.raises(
        HardwareFault,
        match=r"no answer on 127\.0\.0\.3:1337.*after 0\.[67] s "
        r"\(hardware_interface\.connect_timeout 0\.6 s\)",
    ):
        FrankyBackend(cfg)
    assert time.monotonic() - start < 2.0


# --- LCM route -------------------------------------------------------------------------------
def lcm_scenario(**hw):
    fields = {
        "backend": "lcm",
        "dry_run": True,
        "tau_external_bias_duration": 0.0,
        "connect_timeout": 5.0,
        "status_timeout": 0.25,
        "lcm_compensate_load": False,
    }
    fields.update(hw)
    text = ", ".join(
        f"{k}: {str(v).lower() if isinstance(v, bool) else v}" for k, v in fields.items()
    )
    return ApplyOverrides(LoadScenario(), "{hardware: true, hardware_interface: {%s}}" % text)


def _rig(scenario, tau_drake):
    lcm = DrakeLcm("memq://")
    q0 = np.asarray(scenario.robot.initial_joint_positions, float)
    driver = SimulatedPandaDriver(lcm, q0, command_expiry=0.25, tau_external_drake=tau_drake)
    dsim = Simulator(driver)
    dsim.Initialize()

    def step(dt=0.005):
        dsim.AdvanceTo(dsim.get_context().get_time() + dt)

    station = MakeHardwareStation(scenario, lcm=lcm, lcm_idle=step)
    return station, step


@pytest.mark.parametrize("declared_in_desk", [False, True])
def test_lcm_probe_load(declared_in_desk, capsys):
    base = lcm_scenario()
    plant, _ = MakeControlPlant(base.robot, base.probe)
    q0 = np.asarray(base.robot.initial_joint_positions, float)
    weight = ProbeLoadTorque(plant, base.probe.mass, base.probe.p_FCm)(q0)
    # The robot at rest, nothing touching the probe: an FR3 that does not know the probe
    # reports its weight as external torque; one that knows it (Desk) reports nothing.
    tau_robot = np.zeros(7) if declared_in_desk else weight
    forces = {}
    for compensate in (False, True):
        scenario = lcm_scenario(lcm_compensate_load=compensate)
        station, step = _rig(scenario, tau_robot)
        try:
            sim = Simulator(station)
            ctx = station.GetMyContextFromRoot(sim.get_context())
            station.get_input_port().FixValue(ctx, np.zeros(7))
            sim.Initialize()
            RunHardware(sim, station, 0.05, check_period=0.005, realtime_rate=0.0, on_step=step)
            forces[compensate] = np.array(station.GetOutputPort("probe_force").Eval(ctx))[3:]
            failures = _load_check(scenario, station)
        finally:
            station.close()
        out = capsys.readouterr().out
        verdict = "declared" if declared_in_desk else "undeclared"
        assert f"look {verdict}" in out
        if declared_in_desk == compensate:  # Desk knows it and we remove it too, or
            assert failures, out  # nobody accounts for it: both refused
        else:
            assert failures == []
    m_g = base.probe.mass * 9.81
    right = forces[not declared_in_desk]
    wrong = forces[declared_in_desk]
    assert np.linalg.norm(right) < 0.05  # no phantom contact force
    assert np.linalg.norm(wrong) == pytest.approx(m_g, rel=0.05)
    print(
        f"\n[load] declared in Desk: {declared_in_desk}: |f| {np.linalg.norm(right):.3f} N "
        f"with the right setting, {np.linalg.norm(wrong):.2f} N with the wrong one "
        f"(probe weight {m_g:.2f} N)"
    )


def test_unaccounted_weight_reads_as_a_pull():
    """Why the default compensates: a weight nobody accounts for reads as f_z > 0 (a pull
    along the beam) for a probe pointing down, so the force loop would press harder than it
    reads; removed twice it reads as a push (the safe side)."""
    s = Scenario()
    plant, tip = MakeControlPlant(s.robot, s.probe)
    q0 = np.asarray(s.robot.initial_joint_positions, float)
    weight = ProbeLoadTorque(plant, s.probe.mass, s.probe.p_FCm)(q0)
    ctx = plant.CreateDefaultContext()
    plant.SetPositions(ctx, q0)
    W = plant.world_frame()
    J = plant.CalcJacobianSpatialVelocity(ctx, JacobianWrtVariable.kV, tip, np.zeros(3), W, W)
    R = tip.CalcPoseInWorld(ctx).rotation().matrix()
    f_unaccounted = estimate_tip_wrench(J, weight, R)[3:]
    assert f_unaccounted[2] == pytest.approx(s.probe.mass * 9.81, rel=0.02)
    assert HardwareConfig().lcm_compensate_load


def test_load_declaration_verdicts():
    w = np.array([0.0, 3.0, 0.0, -2.0, 0.0, 0.5, 0.0])
    assert core.load_declaration(np.zeros(7) + 0.1, w) == "declared"
    assert core.load_declaration(w + 0.1, w) == "undeclared"
    assert core.load_declaration(0.5 * w, w) == "unclear"
    assert core.load_declaration(w, 0.01 * w) == "unclear"  # too light to tell


class Stall(LeafSystem):
    """Blocks the diagram's thread for ``seconds`` once, at ``t`` (a slow segmentation or
    localization in the same diagram), in the same update as the station's ticks."""

    def __init__(self, t, seconds):
        super().__init__()
        self._t, self._s, self.done = t, seconds, False
        self.DeclarePeriodicUnrestrictedUpdateEvent(0.05, 0.0, self._update)

    def _update(self, context, state):
        if not self.done and context.get_time() >= self._t - 1e-9:
            self.done = True
            time.sleep(self._s)


def _stalled_rig():
    """(station, stall, simulator, station context, driver step): the LCM station on a
    simulated driver, in a diagram whose loop stalls 0.4 s once at t = 0.2 s, initialized
    with a zero command; ``driver_in_real_time()`` steps the driver by the wall time that
    passed (like a separate process publishing meanwhile)."""
    station, step = _rig(lcm_scenario(), np.zeros(7))
    b = DiagramBuilder()
    stall = b.AddSystem(Stall(0.2, 0.4))  # added first: its update runs first
    b.AddSystem(station)
    sim = Simulator(b.Build())
    ctx = station.GetMyContextFromRoot(sim.get_context())
    station.get_input_port().FixValue(ctx, np.zeros(7))
    sim.Initialize()
    last = [time.monotonic()]

    def driver_in_real_time():
        now = time.monotonic()
        while last[0] < now:
            step()
            last[0] += 0.005

    return station, stall, sim, ctx, driver_in_real_time


def test_a_live_run_that_falls_behind_the_wall_clock_stops():
    """RunHardware at real time (the bring-up's motions and read-outs) is paced tick by tick
    like a live scan: a stall longer than safety.realtime_lag stops it with HardwareFault
    (zero velocity, by the session) instead of racing through the missed ticks."""
    station, stall, sim, ctx, driver_in_real_time = _stalled_rig()
    try:
        with pytest.raises(HardwareFault, match="overloaded"):
            RunHardware(
                sim,
                station,
                1.0,
                check_period=0.005,
                realtime_rate=1.0,
                on_step=driver_in_real_time,
                max_lag=0.25,
            )
        assert stall.done
        assert sim.get_context().get_time() < 0.3  # stopped at the stall, not raced through
        with pytest.raises(ValueError, match="realtime_rate"):
            RunHardware(sim, station, 0.1, realtime_rate=-1.0)
    finally:
        station.close()


def test_own_stall_is_not_a_lost_robot():
    """Our loop stalls 0.4 s (longer than status_timeout 0.25 s) while the driver keeps
    publishing: the status latch does not declare the robot lost; a driver that really
    stops is still detected."""
    station, stall, sim, ctx, driver_in_real_time = _stalled_rig()
    try:
        RunHardware(
            sim, station, 0.5, check_period=0.005, realtime_rate=0.0, on_step=driver_in_real_time
        )
        assert stall.done
        assert station.GetOutputPort("robot_ok").Eval(ctx)[0] == 1.0
        gaps = station.grabber.tick_gaps()
        assert gaps.max() > 0.35  # the stall was seen by the station
        # The driver stops for real: detected after status_timeout.
        with pytest.raises(HardwareFault, match="robot state lost"):
            RunHardware(sim, station, 2.0, check_period=0.005, realtime_rate=1.0)
    finally:
        station.close()
