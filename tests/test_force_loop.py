"""The reduced force-loop model (drake_rus.control.force_loop): analytic limits, known stable
and unstable gains, the margin of the configured gains over the contact stiffness range, and
the force statistics the summaries report."""

import json
import math

import numpy as np
import pytest

from drake_rus.control import force_loop as fl
from drake_rus.control.config import ControllerConfig

# The FR3 with the probe at the demo's held pose (q of the press demo at 5 s), reflected to
# the tip along a by fl.reflect_to_tip with the scenario's driver gains (numbers rounded).
HELD = fl.AxialArm(mass=6.84, stiffness=12730.0, damping=499.0)
FREE = fl.AxialArm(mass=4.70, stiffness=5460.0, damping=218.0)
TAU = 2 * fl.SAP_DEFAULT_RELAXATION_TIME
STIFFNESSES = [100.0, 300.0, 1e3, 3e3, 1e4, 3e4, 1e5, 1e6, math.inf]


def test_rigid_limit_matches_the_closed_form_polynomial():
    # k = inf, no filter, controller period = plant step h: the tip stays put and
    # F = K x_d + D v_d, so u+ = -g F, v_d+ = u, x_d+ = x_d + h v_d gives
    # z^3 - z^2 + g D z + g (K h - D) = 0 (plus the decaying contact mode tau / (h + tau)).
    g, h = 0.004, 0.01
    law = fl.ForceLaw(gain=g, period=h)
    z = fl.closed_loop_poles(HELD, law, math.inf, TAU, h)
    K, D = HELD.stiffness, HELD.damping
    expected = np.roots([1.0, -1.0, g * D, g * (K * h - D)])
    got = z[np.abs(z) > 1e-9]
    for root in list(expected) + [TAU / (h + TAU)]:
        assert np.min(np.abs(got - root)) < 1e-9
    assert np.max(np.abs(expected)) > 1.0  # this gain is unstable on a rigid contact


def test_soft_contact_pole_is_the_series_stiffness_integrator():
    # A soft contact and a small gain: the slowest pole is the integrator through the contact
    # in series with the driver's stiffness, z = 1 - g T k K / (k + K).
    g, k, T = 2e-4, 200.0, 0.01
    for arm in (HELD, FREE):
        for h in (0.01, 0.001):
            z = fl.closed_loop_poles(arm, fl.ForceLaw(g, period=T), k, TAU, h)[0]
            k_series = k * arm.stiffness / (k + arm.stiffness)
            assert abs(z.imag) < 1e-9
            assert abs((1.0 - z.real) / (g * T * k_series) - 1.0) < 0.02


def test_the_old_press_law_is_unstable_where_the_station_oscillated():
    # The press driver before issue 32: v = 0.004 (F_des - F), no filter. The station, with
    # the probe stuck to the skin (effective stiffness ~1e4 N/m), oscillated at about 22 Hz
    # at the 10 ms step and at 50 Hz (the controller's Nyquist rate) at 1 ms.
    old = fl.ForceLaw(gain=0.004)
    z10 = fl.closed_loop_poles(HELD, old, 1e4, TAU, 0.01)[0]
    z1 = fl.closed_loop_poles(HELD, old, 1e4, TAU, 0.001)[0]
    assert abs(z10) > 1.0 and 20.0 < fl.pole_frequency_hz(z10, 0.01) < 25.0
    assert abs(z1) > 1.0 and fl.pole_frequency_hz(z1, 0.01) > 49.0
    # ... and stable on the soft normal contact alone (1.6 kN/m on the placeholder torso).
    assert fl.spectral_radius(HELD, old, 1600.0, TAU, 0.01) < 1.0
    # The scan's gains before issue 32 (K_d1 5e-5, 5 Hz): unstable on a rigid contact.
    assert fl.gain_margin(HELD, fl.ForceLaw(0.006, 5e-5, 5.0), math.inf, TAU, 0.001) == 0.0


def test_configured_gains_are_stable_with_margin_over_every_stiffness():
    law = fl.ForceLaw.from_config(ControllerConfig())
    for arm in (HELD, FREE):
        for h in (0.01, 0.001):
            for k in STIFFNESSES:
                assert fl.gain_margin(arm, law, k, TAU, h) >= fl.REQUIRED_GAIN_MARGIN, (arm, h, k)
                assert fl.damping_ratio(arm, law, k, TAU, h) >= fl.REQUIRED_DAMPING_RATIO


def test_gain_margin_brackets_the_stability_boundary():
    law = fl.ForceLaw(0.006, 1e-5, 3.0)
    gm = fl.gain_margin(HELD, law, math.inf, TAU, 0.01)
    assert 1.0 < gm < 100.0
    assert fl.spectral_radius(HELD, law.scaled(gm * 0.99), math.inf, TAU, 0.01) < 1.0
    assert fl.spectral_radius(HELD, law.scaled(gm * 1.01), math.inf, TAU, 0.01) > 1.0
    assert fl.gain_margin(HELD, fl.ForceLaw(0.004), math.inf, TAU, 0.01) == 0.0


def test_filter_and_derivative_follow_eq_6():
    # A step of force error seen by one period of the law: u = K_p3 e + K_d1 de/dt on the
    # filtered error, from a state at rest.
    law = fl.ForceLaw(0.006, 2e-5, 3.0, period=0.01)
    A = fl.closed_loop_matrix(HELD, law, math.inf, TAU, 0.01)
    # A unit of filter state (F_f = 1 N above the equilibrium) with the error state
    # consistent (e_prev = -1): the filter decays by (1 - alpha), the command follows.
    x = np.zeros(len(fl.STATE))
    x[fl.STATE.index("F_f")], x[fl.STATE.index("e_prev")] = 1.0, -1.0
    y = A @ x
    a = law.alpha
    assert y[fl.STATE.index("F_f")] == pytest.approx(1.0 - a)
    e_new = -(1.0 - a)
    assert y[fl.STATE.index("u")] == pytest.approx(0.006 * e_new + 2e-5 * (e_new + 1.0) / 0.01)


def test_reflect_to_tip_held_is_heavier_and_stiffer_than_free():
    rng = np.random.default_rng(3)
    J = rng.normal(size=(6, 7))
    B = rng.normal(size=(7, 7))
    M = B @ B.T + 7 * np.eye(7)
    Kp, Kd = np.full(7, 800.0), np.full(7, 30.0)
    a = np.array([0.0, 0.0, 1.0])
    held = fl.reflect_to_tip(M, J, Kp, Kd, a, held=True)
    free = fl.reflect_to_tip(M, J, Kp, Kd, a, held=False)
    assert held.mass > free.mass > 0 and held.stiffness > free.stiffness > 0
    # Decoupled (J = identity on the first six joints, M diagonal): both are the joint's own.
    J6 = np.hstack([np.eye(6), np.zeros((6, 1))])
    M6 = np.diag([1, 2, 3, 4, 5, 6, 7.0])
    for held_flag in (True, False):
        arm = fl.reflect_to_tip(M6, J6, Kp, Kd, a, held=held_flag)
        assert arm.mass == pytest.approx(6.0) and arm.stiffness == pytest.approx(800.0)
        assert arm.damping == pytest.approx(30.0)


def test_period_must_be_whole_plant_steps():
    with pytest.raises(ValueError, match="whole number"):
        fl.closed_loop_matrix(HELD, fl.ForceLaw(0.004, period=0.01), 1e3, TAU, 0.003)


def test_stiffness_at_force_reads_the_slope():
    x = np.array([0.0, 1e-3, 2e-3, 3e-3])
    F = np.array([0.0, 2.0, 5.0, 9.0])
    assert fl.stiffness_at_force(x, F, 4.0) == pytest.approx(3000.0)
    assert fl.stiffness_at_force(x, F, 9.0) == pytest.approx(4000.0)
    with pytest.raises(ValueError, match="force"):
        fl.stiffness_at_force(x, F, 12.0)
    with pytest.raises(ValueError, match="increasing"):
        fl.stiffness_at_force(x[::-1], F, 4.0)


def test_force_statistics_ripple_and_settled():
    t = np.arange(0.0, 20.0, 0.01)
    steady = 9.0 + 0.001 * np.sin(2 * np.pi * 3 * t)
    s = fl.force_statistics(t, steady, 9.0, window=5.0)
    assert s["settled"] and s["mean_n"] == pytest.approx(9.0, abs=1e-3)
    assert s["ripple_n"] == pytest.approx(0.001 / math.sqrt(2), rel=0.02)
    # A 22 Hz oscillation of 2 N peak to peak about the right mean is not settled.
    osc = 9.0 + 1.0 * np.sin(2 * np.pi * 22 * t)
    s = fl.force_statistics(t, osc, 9.0, window=5.0)
    assert not s["settled"] and s["mean_n"] == pytest.approx(9.0, abs=0.01)
    assert s["ripple_n"] == pytest.approx(1 / math.sqrt(2), rel=0.02)
    assert s["peak_to_peak_n"] == pytest.approx(2.0, rel=0.02)
    # Off the target is not settled either.
    assert not fl.force_statistics(t, steady - 0.5, 9.0, window=5.0)["settled"]
    # A window with no samples.
    empty = fl.force_statistics(t[:0], steady[:0], 9.0, window=5.0)
    assert empty["mean_n"] is None and not empty["settled"]


def test_step_response_metrics_say_none_for_a_response_that_never_happens():
    """The controller notebook's step metrics: a good response gives its times; a force
    still oscillating at the tilt, an error never below 1 deg, no touch give None, never the
    0 s (or the window's length) the notebook's test would take for a pass."""
    t = np.arange(0.0, 5.5, 0.01)
    landing = np.where(t > 2.6, 9.0 + 3.0 * np.exp(-(t - 2.6) / 0.1), 0.0)
    decay = np.where(t >= 4.0, 20.0 * np.exp(-(t - 4.0) / 0.2), 0.1)
    good = fl.step_response_metrics(t, landing, decay, 9.0, 4.0)
    assert good["touch_s"] == pytest.approx(2.61)
    assert 0.05 < good["force_settling_s"] < 0.2
    assert good["force_final_n"] == pytest.approx(9.0, abs=1e-3)
    assert good["tilt_below_1deg_s"] == pytest.approx(0.2 * math.log(20.0), abs=0.011)
    oscillating = np.where(t > 2.6, 9.0 + 2.0 * np.sin(20.0 * t), 0.0)
    bad = fl.step_response_metrics(t, oscillating, np.where(t >= 4.0, 20.0, 0.1), 9.0, 4.0)
    assert bad["touch_s"] == pytest.approx(2.61)
    assert bad["force_settling_s"] is None
    assert bad["tilt_below_1deg_s"] is None and bad["tilt_final_deg"] == 20.0
    never = fl.step_response_metrics(t, np.zeros_like(t), decay, 9.0, 4.0)
    assert never["touch_s"] is None and never["force_settling_s"] is None


def test_phase_force_statistics_and_the_scan_summary_force_block():
    import types

    from drake_rus.scan.metrics import _force_block

    t = np.arange(0.0, 10.0, 0.01)
    F = np.where(t <= 4.0 + 1e-9, 9.0 + 0.05 * np.sin(2 * np.pi * 2 * t), 8.0)
    F[(t >= 2.0) & (t < 2.5)] = 20.0  # the landing, skipped in EXPLORE
    phases = [
        ("APPROACH", 0.0, 2.0),
        ("EXPLORE", 2.0, 4.0),
        ("LOCALIZE", 4.0, 5.0),
        ("PIVOT", 5.0, 9.0),
    ]
    stats = fl.phase_force_statistics(t, F, phases)
    assert set(stats) == {"EXPLORE", "LOCALIZE", "PIVOT"}
    assert stats["EXPLORE"]["mean_n"] == pytest.approx(9.0, abs=0.01)
    assert stats["EXPLORE"]["ripple_n"] == pytest.approx(0.05 / math.sqrt(2), rel=0.05)
    assert stats["PIVOT"] == {"mean_n": pytest.approx(8.0), "ripple_n": pytest.approx(0.0)}
    # The summary's block reads the true force (simulation) when there is one ...
    wrench = np.zeros((6, t.size))
    wrench[5] = -F
    result = types.SimpleNamespace(
        logs={"force_true": (t, wrench), "force": (t, np.zeros((1, t.size)))}, phases=phases
    )
    block = _force_block(result)
    assert block["source"] == "true contact force" and block["log_period_s"] == pytest.approx(0.01)
    assert block["EXPLORE"]["mean_n"] == pytest.approx(9.0, abs=0.01)
    # ... else the estimated, filtered force (hardware).
    result.logs.pop("force_true")
    block = _force_block(result)
    assert block["source"].startswith("estimated") and block["PIVOT"]["mean_n"] == 0.0


# ----------------------------------------------------------------------------- diagrams
# The 60 s holds at 10 ms and 1 ms over the stiffness range are `python -m benchmarks
# force_loop --hold 60` (docs/force_loop.md); here the shortest runs that show the same: a
# settled hold, then the linearized one-period map of the held diagram with every pole
# inside the unit circle (the hold stays still however long it lasts).


@pytest.mark.parametrize("modulus, h", [(5e4, 0.01), (1e6, 0.01), (2e5, 0.001)])
def test_press_diagram_settles_and_its_hold_is_linearly_stable(modulus, h):
    from pydrake.systems.analysis import Simulator

    from benchmarks.force_loop import _poles, period_map
    from drake_rus.closed_loop import PressDiagram
    from drake_rus.scenario import LoadScenario

    scenario = LoadScenario(
        scenario_text=f"{{contact: {{hydroelastic_modulus: {modulus}, time_step: {h}}}}}"
    )
    press = PressDiagram(scenario)
    sim = Simulator(press.diagram)
    sim.Initialize()
    sim.AdvanceTo(10.0 + h / 2)  # just after a controller update (period_map's cut)
    t, F = press.true_force(sim.get_context())
    stats = fl.force_statistics(t, F, 9.0, window=4.0)
    assert stats["settled"] and stats["ripple_n"] <= 0.1, stats
    J = period_map(press.diagram, sim.get_context().Clone(), 0.01)
    poles = _poles(np.linalg.eigvals(J), 0.01)
    assert poles["largest_pole"]["abs"] < 1.0, poles


def test_press_diagram_holds_still_for_60_s_at_10_ms():
    from benchmarks.force_loop import press_hold
    from drake_rus.scenario import LoadScenario

    stats = press_hold(LoadScenario(), 60.0, window=50.0)  # settled within 10 s
    assert stats["settled"] and stats["ripple_n"] <= 0.1 and stats["peak_to_peak_n"] <= 0.01


def test_scan_controller_holds_still_at_test0_start():
    from benchmarks.force_loop import scan_controller_hold
    from drake_rus.scenario import LoadScenario

    stats = scan_controller_hold(LoadScenario(), "test:0", 6.0, window=2.0)
    assert stats["settled"] and stats["ripple_n"] < 0.01, stats


def test_benchmark_json_is_strict_with_a_law_without_filter(monkeypatch, capsys, tmp_path):
    """The design table's first candidate has no force filter (cut-off inf): its rows and
    the last line were written as ``Infinity``, which is not JSON; now null."""
    from benchmarks import force_loop as bench

    monkeypatch.setattr(bench, "scan_arms", lambda scenario: [])
    monkeypatch.setattr(bench, "plot_margins", lambda *a, **k: {})
    assert bench.main(["--plot", str(tmp_path / "margins.png")]) == 0
    lines = capsys.readouterr().out.strip().splitlines()

    def refuse(constant):
        raise ValueError(f"not JSON: {constant}")

    docs = [json.loads(line, parse_constant=refuse) for line in lines]
    table = docs[-1]["design_table"]
    assert table[0]["cutoff_hz"] is None and table[0] == docs[0]
    assert len(table) == len(docs) - 1
