"""The simulated station: ports, velocity driver, and the probe force estimate."""

import json

import numpy as np
import pytest
from pydrake.math import RigidTransform
from pydrake.multibody.tree import BodyIndex
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource, LogVectorOutput

from drake_rus.cli import main as cli_main
from drake_rus.closed_loop import PressDiagram
from drake_rus.robot import MakeControlPlant, contact_force_along_approach, estimate_tip_wrench
from drake_rus.scenario import LoadScenario
from drake_rus.station_interface import ports_of
from drake_rus.stations import MakeStation

# What both stations export (drake_rus.station_interface, the one list of ports).
STATION_INPUTS = {p.name for p in ports_of("sim", include_optional=False) if p.direction == "in"}
SIM_INPUTS_ALLOWED = {p.name for p in ports_of("sim") if p.direction == "in"}
STATION_OUTPUTS = {
    p.name
    for p in ports_of("sim", include_optional=False)
    if p.direction == "out" and "hardware" in p.stations
}


def test_estimate_tip_wrench_recovers_a_known_wrench():
    rng = np.random.default_rng(3)
    for _ in range(20):
        J = rng.normal(size=(6, 7))
        # A random rotation R_WP.
        Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        R_WP = Q * np.sign(np.linalg.det(Q))
        F_P = rng.normal(size=6) * [0.5, 0.5, 0.5, 5, 5, 20]
        F_W = np.concatenate([R_WP @ F_P[:3], R_WP @ F_P[3:]])
        tau = J.T @ F_W
        np.testing.assert_allclose(estimate_tip_wrench(J, tau, R_WP, damping=1e-9), F_P, atol=1e-6)
    assert contact_force_along_approach([0, 0, 0, 0, 0, -9.0]) == 9.0
    with pytest.raises(ValueError, match="J_WP: expected shape"):
        estimate_tip_wrench(np.zeros((6, 6)), np.zeros(7), np.eye(3))


def test_station_ports_match_design():
    station = MakeStation(LoadScenario())
    inputs = {station.get_input_port(i).get_name() for i in range(station.num_input_ports())}
    outputs = {station.get_output_port(i).get_name() for i in range(station.num_output_ports())}
    # Every input the interface requires; conditional ones (a breathing patient's
    # breath_prompt) only where the interface allows them.
    assert STATION_INPUTS <= inputs <= SIM_INPUTS_ALLOWED
    assert STATION_OUTPUTS <= outputs
    assert station.GetOutputPort("probe_force").size() == 6


def test_control_plant_tip_matches_station():
    scenario = LoadScenario()
    plant, tip = MakeControlPlant(scenario.robot, scenario.probe)
    context = plant.CreateDefaultContext()
    X_BP = tip.CalcPoseInWorld(context)
    station = MakeStation(scenario)
    station_context = station.CreateDefaultContext()
    station.GetInputPort("joint_velocity_command").FixValue(station_context, np.zeros(7))
    X_station = station.GetOutputPort("X_BP").Eval(station_context)
    np.testing.assert_allclose(X_BP.GetAsMatrix4(), X_station.GetAsMatrix4(), atol=1e-12)
    # The probe points down at the start (z_P = -z_B) and sits above the body.
    np.testing.assert_allclose(X_BP.rotation().matrix()[:, 2], [0, 0, -1], atol=1e-6)


def _run_with_command(command, duration, scenario=None):
    scenario = scenario or LoadScenario()
    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(scenario))
    source = builder.AddSystem(ConstantVectorSource(np.asarray(command, dtype=float)))
    builder.Connect(source.get_output_port(), station.GetInputPort("joint_velocity_command"))
    q_log = LogVectorOutput(station.GetOutputPort("joint_position"), builder, 0.01)
    v_log = LogVectorOutput(station.GetOutputPort("joint_velocity"), builder, 0.01)
    diagram = builder.Build()
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    station_context = station.GetMyContextFromRoot(context)
    # Copies: Eval returns a reference into the cache, which the simulation overwrites.
    X0 = RigidTransform(station.GetOutputPort("X_BP").Eval(station_context))
    simulator.AdvanceTo(duration)
    X1 = RigidTransform(station.GetOutputPort("X_BP").Eval(station_context))
    return X0, X1, q_log.FindLog(context), v_log.FindLog(context)


def test_zero_command_holds_the_arm():
    X0, X1, q_log, _ = _run_with_command(np.zeros(7), 2.0)
    drift = np.linalg.norm(X1.translation() - X0.translation())
    assert drift < 1e-3, f"tip drifted {drift * 1000:.3f} mm in 2 s"


def test_zero_command_without_gravity_compensation_sags():
    # The check above means something: without gravity compensation the same arm sags.
    scenario = LoadScenario(scenario_text="{robot: {gravity_compensation: false}}")
    X0, X1, _, _ = _run_with_command(np.zeros(7), 0.5, scenario)
    assert np.linalg.norm(X1.translation() - X0.translation()) > 1e-3


def test_constant_joint_velocity_is_tracked():
    command = np.array([0.10, -0.05, 0.10, 0.10, -0.20, 0.10, 0.30])
    _, _, q_log, v_log = _run_with_command(command, 1.0)
    t = v_log.sample_times()
    steady = t >= 0.4
    v_mean = v_log.data()[:, steady].mean(axis=1)
    np.testing.assert_allclose(v_mean, command, rtol=0.05)
    # And the positions advance at that rate.
    dq = q_log.data()[:, -1] - q_log.data()[:, np.argmax(t >= 0.4)]
    np.testing.assert_allclose(dq / (t[-1] - 0.4), command, rtol=0.05)


def test_command_takes_effect_at_the_next_plant_step():
    """The station holds each command for one plant step (the robot's command latency), so
    a command cannot change the contact solve of the step already under way."""
    scenario = LoadScenario()
    h = scenario.contact.time_step
    command = np.full(7, 0.3)
    station = MakeStation(scenario)
    simulator = Simulator(station)
    context = simulator.get_mutable_context()
    station.GetInputPort("joint_velocity_command").FixValue(context, command)
    v = station.GetOutputPort("joint_velocity")
    simulator.AdvanceTo(h)
    # The first step still ran the initial (zero) command: the arm has not moved.
    assert np.abs(v.Eval(context)).max() < 1e-3
    simulator.AdvanceTo(4 * h)
    assert np.abs(v.Eval(context)).min() > 0.05


@pytest.mark.parametrize("model", ["hydroelastic", "point"])
def test_probe_force_agrees_with_contact_results(model):
    scenario = LoadScenario(scenario_text=f"{{contact: {{model: {model}}}}}")
    press = PressDiagram(scenario, desired_force=9.0)
    simulator = Simulator(press.diagram)
    simulator.AdvanceTo(4.5)
    t, F_est, F_true = press.logs(simulator.get_context())
    assert F_true[t < 1.0].max() == 0.0, "probe must start out of contact"
    steady = t >= 4.0
    assert F_true[steady].min() > 5.0, "probe must be pressing at the end"
    error = np.abs(F_est[steady] - F_true[steady])
    assert np.all(error <= np.maximum(0.05 * F_true[steady], 0.2))
    np.testing.assert_allclose(F_true[-1], 9.0, atol=0.5)


@pytest.mark.parametrize("hardware", [False, True])
def test_make_station_dispatches_on_the_hardware_flag(monkeypatch, hardware):
    """MakeStation builds the simulated station for hardware: false and the hardware station
    for hardware: true, passing the scenario through; nothing else chooses."""
    import drake_rus.stations as stations

    calls = []
    monkeypatch.setattr(
        stations, "MakeSimStation", lambda scenario, **kw: calls.append(("sim", scenario)) or "sim"
    )
    monkeypatch.setattr(
        stations,
        "MakeHardwareStation",
        lambda scenario, **kw: calls.append(("hw", scenario)) or "hw",
    )
    scenario = LoadScenario(scenario_name="hardware" if hardware else "default")
    assert scenario.hardware == hardware
    assert stations.MakeStation(scenario) == ("hw" if hardware else "sim")
    assert calls == [("hw" if hardware else "sim", scenario)]


def test_control_plant_has_no_geometry_the_sim_plant_has():
    """The control plant (FK, Jacobians, gravity) carries no geometry; the simulated
    station's plant has the probe face it presses with."""
    scenario = LoadScenario()
    plant, _ = MakeControlPlant(scenario.robot, scenario.probe)
    assert not plant.geometry_source_is_registered()
    assert all(
        len(plant.GetCollisionGeometriesForBody(plant.get_body(BodyIndex(i)))) == 0
        for i in range(plant.num_bodies())
    )
    sim_plant = MakeStation(scenario).GetSubsystemByName("plant")
    probe = sim_plant.GetBodyByName("probe")
    assert len(sim_plant.GetCollisionGeometriesForBody(probe)) > 0


def test_demo_writes_recording_plot_and_summary(tmp_path):
    out = tmp_path / "demo"
    assert cli_main(["demo", "--out", str(out), "--duration", "3.5"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["first_contact_s"] is not None
    force = summary["force"]
    assert force["mean_n"] > 1.0 and force["window_s"] == pytest.approx(1.75)
    assert abs(force["mean_n"] - summary["force_estimated_mean_n"]) < 0.2
    # 3.5 s is too short to settle (contact at ~2.5 s): the summary must not say it did.
    assert force["settled"] is False and force["max_error_n"] > 0.1
    assert (out / "force.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    html = (out / "press.html").read_text()
    assert "<html" in html.lower() and "meshcat" in html.lower()
    assert len(html) > 10_000


def test_demo_bad_input_is_a_clear_error(tmp_path, capsys):
    assert (
        cli_main(["demo", "--out", str(tmp_path / "x"), "--set", "{contact: {modle: point}}"]) == 2
    )
    assert "field 'contact.modle'" in capsys.readouterr().err
    assert cli_main(["demo", "--out", str(tmp_path / "y"), "--force", "50"]) == 2
    assert "--force" in capsys.readouterr().err
    assert not (tmp_path / "y" / "summary.json").exists()


def test_render_diagram(tmp_path):
    out = tmp_path / "station.svg"
    assert cli_main(["render-diagram", "--out", str(out)]) == 0
    svg = out.read_text()
    assert "<svg" in svg and "plant" in svg and "joint_velocity_command" in svg


def test_render_diagram_default_out_is_beside_the_runs(tmp_path, monkeypatch, capsys):
    """Without --out the picture goes to runs/diagrams/, like the other commands' outputs;
    it went to ./diagrams/, which in the repository is the committed picture --all draws
    (a --depth or --set run there overwrote it with other settings)."""
    monkeypatch.chdir(tmp_path)
    assert cli_main(["render-diagram"]) == 0
    assert (tmp_path / "runs" / "diagrams" / "station.svg").is_file()
    assert not (tmp_path / "diagrams").exists()
    assert "wrote runs/diagrams/station.svg" in capsys.readouterr().out
