"""The force loop along the approach axis (``python -m benchmarks force_loop``;
docs/force_loop.md): the figures behind the reduced model of ``drake_rus.control.force_loop``.

- ``--stiffness``: the contact stiffness dF/dx of the probe face on the body at the desired
  force, from the hydroelastic pressure field (no dynamics): the placeholder torso over a
  range of ``contact.hydroelastic_modulus``, generated patients and the Visible Human
  female at the scan's start over the kidney;
- ``--validate``: the one-period map of the press diagram finite-differenced around a held
  equilibrium (its eigenvalues are the closed loop's poles), at the 10 ms and the 1 ms
  step, with the press law before issue 32 (unstable) and the configured law; the reduced
  model's loop transfer fitted to the diagram's (one parameter: the effective contact
  stiffness) and the two sets of poles side by side;
- ``--hold SECONDS``: still holds at the desired force, every sample of the true force:
  the demo's press diagram and the scan's controller at test:0's start, each at 10 ms and
  1 ms (mean, ripple = RMS about the mean, peak to peak, settled);
- ``--plot PATH``: the gain margin and the largest pole against the contact stiffness for
  the laws before and after issue 32 (the worst arm pose of the scans of test:0-2), and the
  design table: candidate gains against the criterion.

Without options: ``--stiffness --validate --hold 60``. The last line is one JSON object
(strict JSON: an infinite value, e.g. the cut-off of a law without a force filter, is
``null``).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time

import numpy as np

from drake_rus.control import force_loop as fl
from drake_rus.io_utils import dumps_strict

# The press law before issue 32: v = 0.004 (F_des - F_z), no filter, no orientation hold.
OLD_PRESS = {"K_p3": 0.004, "K_d1": 0.0, "force_filter_cutoff_hz": 1e9}
# The scan's force gains before issue 32.
OLD_SCAN = {"K_p3": 0.006, "K_d1": 5e-5, "force_filter_cutoff_hz": 5.0}
MODULI = (5e4, 1e5, 2e5, 5e5, 1e6)
PATIENTS = ("test:0", "test:1", "test:2", "test:3", "test:4")
VISIBLE_HUMAN = "../shared/anatomy/hubmap_vh_female"
STIFFNESS_GRID = np.logspace(2, 7, 26)
TAU = 2 * fl.SAP_DEFAULT_RELAXATION_TIME


def _with(scenario, **controller):
    return dataclasses.replace(
        scenario, controller=dataclasses.replace(scenario.controller, **controller)
    )


def _time_step(scenario, h: float):
    return dataclasses.replace(scenario, contact=dataclasses.replace(scenario.contact, time_step=h))


# ----------------------------------------------------------------------------- stiffness
def normal_stiffness(scenario, patient=None, force: float = 9.0, step: float = 2.5e-4) -> dict:
    """dF/dx (N/m) of the probe face pressed along its approach vector into the body, at
    ``force`` (N): the elastic force of the hydroelastic contact surfaces (pressure times
    area, normal to each face), the robot moved along a from the scenario's initial joints
    (above the body) until past ``force``."""
    from pydrake.geometry import HydroelasticContactRepresentation

    from drake_rus.robot import MakeControlPlant, TipKinematics
    from drake_rus.station import MakeSimStation

    station = MakeSimStation(scenario, patient=patient)
    context = station.CreateDefaultContext()
    plant = station.GetSubsystemByName("plant")
    scene_graph = station.GetSubsystemByName("scene_graph")
    plant_context = plant.GetMyMutableContextFromRoot(context)
    sg_context = scene_graph.GetMyContextFromRoot(context)
    tip = TipKinematics(*MakeControlPlant(scenario.robot, scenario.probe))
    q_all = plant.GetPositions(plant_context).copy()
    q = q_all[:7].copy()
    a = tip.pose(q).rotation().matrix()[:, 2]

    def elastic_force(q7) -> float:
        q_all[:7] = q7
        plant.SetPositions(plant_context, q_all)
        query = scene_graph.get_query_output_port().Eval(sg_context)
        F = np.zeros(3)
        # With fallback: the bed and the probe's housing have no hydroelastic properties
        # (point pairs, not counted: only the face presses at the desired force).
        surfaces, _ = query.ComputeContactSurfacesWithFallback(
            HydroelasticContactRepresentation.kPolygon
        )
        for s in surfaces:
            mesh, e = s.poly_mesh_W(), s.poly_e_MN()
            for i in range(mesh.num_faces()):
                F += (
                    e.EvaluateCartesian(i, mesh.element_centroid(i))
                    * mesh.area(i)
                    * mesh.face_normal(i)
                )
        return abs(float(F @ a))

    def moved(q7, dx):
        return q7 + np.linalg.pinv(tip.jacobian(q7)) @ np.concatenate([np.zeros(3), dx * a])

    travel = 0.0
    while elastic_force(q) == 0.0:  # coarse: 2 mm steps to the first contact
        q, travel = moved(q, 2e-3), travel + 2e-3
        if travel > 0.25:
            raise RuntimeError("the probe met no body within 25 cm of travel")
    q = moved(q, -2e-3)
    xs, Fs, x = [], [], 0.0
    while not Fs or Fs[-1] < 1.5 * force:  # fine: ``step`` to past the force
        F = elastic_force(q)
        if F > 0.0:
            xs.append(x)
            Fs.append(F)
        q, x = moved(q, step), x + step
        if x > 0.1:
            raise RuntimeError(f"no {force} N within 10 cm of indentation")
    xs, Fs = np.asarray(xs) - xs[0], np.asarray(Fs)
    k = fl.stiffness_at_force(xs, Fs, force)
    return {
        "stiffness_n_per_m": round(k, 1),
        "indentation_mm_at_force": round(float(np.interp(force, Fs, xs)) * 1e3, 2),
    }


def stiffness_range(scenario, force: float) -> dict:
    from drake_rus.anatomy import load_patient
    from drake_rus.scan.run import PrepareScenario

    out, every = {"placeholder": {}, "patients": {}}, []
    for E in MODULI:
        s = dataclasses.replace(
            scenario, contact=dataclasses.replace(scenario.contact, hydroelastic_modulus=E)
        )
        row = out["placeholder"][f"{E:g}"] = normal_stiffness(s, None, force)
        every.append(row["stiffness_n_per_m"])
        print(dumps_strict({"placeholder_modulus_pa": E, **row}), flush=True)
    for name in PATIENTS + (VISIBLE_HUMAN,):
        try:
            patient = load_patient(name, progress=False)
        except (OSError, ValueError) as e:  # the VH female needs ../shared
            out["patients"][name] = {"error": str(e).splitlines()[0]}
            continue
        s, _, _ = PrepareScenario(scenario, patient)
        row = out["patients"][name] = {}
        for E in (MODULI[0], scenario.contact.hydroelastic_modulus, MODULI[-1]):
            s_E = dataclasses.replace(
                s, contact=dataclasses.replace(s.contact, hydroelastic_modulus=E)
            )
            row[f"{E:g}"] = normal_stiffness(s_E, patient, force)
            every.append(row[f"{E:g}"]["stiffness_n_per_m"])
        print(dumps_strict({"patient": name, **row}), flush=True)
    out["min_n_per_m"], out["max_n_per_m"] = min(every), max(every)
    return out


# ----------------------------------------------------------------------------- validation
def _flat(context) -> np.ndarray:
    s = context.get_discrete_state()
    return np.concatenate([s.get_vector(i).CopyToVector() for i in range(s.num_groups())])


def _set_flat(context, x) -> None:
    s, k = context.get_discrete_state(), 0
    for i in range(s.num_groups()):
        n = s.get_vector(i).size()
        s.get_mutable_vector(i).SetFromVector(x[k : k + n])
        k += n


def _offsets(diagram, context, system, group: int) -> np.ndarray:
    """Indices in the flattened root discrete state of ``system``'s state ``group``."""
    sub = system.GetMyMutableContextFromRoot(context)
    saved = sub.get_discrete_state(group).CopyToVector()
    marker = 1e12 + np.arange(saved.size)
    sub.get_mutable_discrete_state(group).SetFromVector(marker)
    flat = _flat(context)
    sub.get_mutable_discrete_state(group).SetFromVector(saved)
    return np.array([int(np.argmin(np.abs(flat - m))) for m in marker])


def period_map(diagram, context, period: float, eps: float = 1e-7) -> np.ndarray:
    """Jacobian of the map of the diagram's discrete state over one ``period`` from
    ``context`` (central differences; ``context``'s time must lie between event times)."""
    from pydrake.systems.analysis import Simulator

    x0 = _flat(context)
    t0 = context.get_time()

    def step(x):
        c = context.Clone()
        _set_flat(c, x)
        sim = Simulator(diagram, c)
        sim.Initialize()
        sim.AdvanceTo(t0 + period)
        return _flat(sim.get_context())

    J = np.zeros((x0.size, x0.size))
    for j in range(x0.size):
        e = eps * max(1.0, abs(x0[j]))
        xp, xm = x0.copy(), x0.copy()
        xp[j] += e
        xm[j] -= e
        J[:, j] = (step(xp) - step(xm)) / (2 * e)
    return J


def _loop_transfer(J, command: np.ndarray, f: np.ndarray, period: float) -> np.ndarray:
    """L(e^{j 2 pi f T}) of the loop cut at the command (the rows of ``command`` are
    rank one: command = p u)."""
    rest = np.setdiff1d(np.arange(J.shape[0]), command)
    U, s, Vt = np.linalg.svd(J[command])
    p, g = U[:, 0], s[0] * Vt[0]
    A = J[np.ix_(rest, rest)]
    b = J[np.ix_(rest, command)] @ p
    c = g[rest]
    z = np.exp(2j * np.pi * f * period)
    return np.array([c @ np.linalg.solve(zi * np.eye(A.shape[0]) - A, b) / zi for zi in z])


def _arm_at(scenario, q, held=True):
    from drake_rus.robot import MakeControlPlant, TipKinematics

    plant, frame = MakeControlPlant(scenario.robot, scenario.probe)
    tip = TipKinematics(plant, frame)
    c = plant.CreateDefaultContext()
    plant.SetPositions(c, q)
    return fl.reflect_to_tip(
        plant.CalcMassMatrix(c),
        tip.jacobian(q),
        scenario.robot.driver_kp,
        scenario.robot.driver_kd,
        tip.pose(q).rotation().matrix()[:, 2],
        held=held,
    )


def _diagram_gain_margin(J, command, upper: float = 64.0) -> float:
    """The factor on the command's rows (= on K_p3 and K_d1) at which a pole of the
    linearized diagram leaves the unit circle (bisection to 1 %; ``upper`` if none)."""

    def stable(beta):
        Jb = J.copy()
        Jb[command] *= beta
        z = np.linalg.eigvals(Jb)
        return np.max(np.abs(z[np.abs(z - 1.0) > 1e-4])) < 1.0

    if not stable(1.0):
        return 0.0
    if stable(upper):
        return upper
    lo, hi = 1.0, upper
    while hi / lo > 1.01:
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if stable(mid) else (lo, mid)
    return round(lo, 2)


def validate_once(
    scenario, h: float, gains: dict, t: float, hold_orientation: bool = False
) -> dict:
    """The press diagram with ``gains`` at plant step ``h``, linearized over one controller
    period from ``t`` (s; just after a controller update, t = k T + h / 2): its largest
    poles and gain margin; the reduced model with the arm there (held) and the contact
    stiffness fitted to the diagram's loop transfer: its poles and gain margin."""
    from pydrake.systems.analysis import Simulator

    from drake_rus.closed_loop import PressDiagram

    s = _with(_time_step(scenario, h), **gains)
    press = PressDiagram(s, hold_orientation=hold_orientation)
    sim = Simulator(press.diagram)
    sim.Initialize()
    T = 1.0 / s.controller.rate_hz
    sim.AdvanceTo(t)
    tt, F = press.true_force(sim.get_context())
    context = sim.get_context().Clone()
    J = period_map(press.diagram, context, T)
    q = press.station.GetOutputPort("joint_position").Eval(
        press.station.GetMyContextFromRoot(context)
    )
    arm = _arm_at(s, np.asarray(q))
    law = fl.ForceLaw.from_config(s.controller)
    out = {
        "time_step_s": h,
        "linearized_at_s": t,
        "law": gains,
        "hold_orientation": hold_orientation,
        "force_peak_to_peak_last_0.2s_n": float(np.ptp(F[tt >= t - 0.2])),
        "arm_held": {k: round(v, 1) for k, v in dataclasses.asdict(arm).items()},
        "diagram": _poles(np.linalg.eigvals(J), T),
    }
    if hold_orientation:
        return out
    command = _offsets(press.diagram, context, press.driver, 0)
    out["diagram"]["gain_margin"] = _diagram_gain_margin(J, command)
    f = np.linspace(2.0, 0.49 / T, 48)
    L_d = _loop_transfer(J, command, f, T)
    ks = np.logspace(2.5, 6.5, 161)
    errors = [
        float(np.mean(np.abs(np.log(fl.loop_transfer(arm, law, k, TAU, h, f) / L_d)) ** 2))
        for k in ks
    ]
    k_fit = float(ks[int(np.argmin(errors))])
    out["model"] = {
        "fitted_stiffness_n_per_m": round(k_fit),
        "fit_rms_log_error": round(math.sqrt(min(errors)), 3),
        **_poles(fl.closed_loop_poles(arm, law, k_fit, TAU, h), T),
        "gain_margin": round(fl.gain_margin(arm, law, k_fit, TAU, h, upper=64.0), 2),
    }
    return out


def _poles(z, period) -> dict:
    """The largest pole (the integrators no loop closes, |z - 1| < 1e-4, left out) and the
    largest oscillating one."""
    z = np.asarray(z)
    z = z[np.abs(z - 1.0) > 1e-4]
    osc = z[np.abs(z.imag) > 1e-9]
    out = {"largest_pole": _pole(z[np.argmax(np.abs(z))], period)}
    if osc.size:
        out["largest_oscillating_pole"] = _pole(osc[np.argmax(np.abs(osc))], period)
    return out


def _pole(z, period) -> dict:
    return {"abs": round(float(abs(z)), 4), "freq_hz": round(fl.pole_frequency_hz(z, period), 1)}


# Where the press diagram is linearized (s, just after a controller update): with the law
# before issue 32 the probe has just stuck and the oscillation starts; with the configured
# law the hold has settled.
VALIDATION_TIMES = {
    ("old", 0.01): 5.005,
    ("old", 0.001): 5.8005,
    ("configured", 0.01): 10.005,
    ("configured", 0.001): 10.0005,
}


def validate(scenario) -> list:
    rows = []
    for h in (0.01, 0.001):
        for name, gains, hold in (
            ("old", OLD_PRESS, False),
            ("configured", _configured(scenario), False),
            ("configured", _configured(scenario), True),
        ):
            row = validate_once(scenario, h, gains, VALIDATION_TIMES[(name, h)], hold)
            print(dumps_strict(row), flush=True)
            rows.append(row)
    return rows


def _configured(scenario) -> dict:
    c = scenario.controller
    return {"K_p3": c.K_p3, "K_d1": c.K_d1, "force_filter_cutoff_hz": c.force_filter_cutoff_hz}


# ----------------------------------------------------------------------------- holds
def press_hold(scenario, seconds: float, window: float = 10.0) -> dict:
    """The demo's press diagram for ``seconds``: the true force's statistics over the last
    ``window`` s (every plant step)."""
    from pydrake.systems.analysis import Simulator

    from drake_rus.closed_loop import PressDiagram

    press = PressDiagram(scenario)
    sim = Simulator(press.diagram)
    sim.Initialize()
    start = time.perf_counter()
    sim.AdvanceTo(seconds)
    t, F = press.true_force(sim.get_context())
    return {
        "wall_s": round(time.perf_counter() - start, 1),
        **fl.force_statistics(t, F, scenario.controller.desired_force, window),
    }


def scan_controller_hold(scenario, patient_name: str, seconds: float, window: float = 10.0) -> dict:
    """The scan's controller (eq. 1-12 and the safety layer, no supervisor) holding the
    probe still at ``patient_name``'s scan start: the start orientation and tip x, y, the
    desired force; the true force's statistics over the last ``window`` s."""
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.primitives import LogVectorOutput

    from drake_rus.anatomy import load_patient
    from drake_rus.closed_loop import BuildClosedLoop
    from drake_rus.scan.run import PrepareScenario
    from drake_rus.stations import MakeStation

    patient = load_patient(patient_name, progress=False)
    s, _, _ = PrepareScenario(scenario, patient)
    station = MakeStation(s, patient=patient)
    logs = {}

    def log_truth(builder, station_, segmenter):
        logs["true"] = LogVectorOutput(
            station_.GetOutputPort("probe_contact_wrench_true"), builder, s.contact.time_step
        )
        return station_, segmenter, None

    loop = BuildClosedLoop(s, station=station, use_supervisor=False, sensor_hook=log_truth)
    sim = Simulator(loop.diagram)
    sim.Initialize()
    start = time.perf_counter()
    sim.AdvanceTo(seconds)
    log = logs["true"].FindLog(sim.get_context())
    return {
        "wall_s": round(time.perf_counter() - start, 1),
        **fl.force_statistics(
            log.sample_times(), -log.data()[5], s.controller.desired_force, window
        ),
    }


def holds(scenario, seconds: float) -> dict:
    """Still holds of ``seconds``: the press diagram at the lowest, the scenario's and the
    highest modulus of MODULI, and the scan's controller at test:0's start, each at the
    10 ms and the 1 ms step."""
    out = {}
    for h in (0.01, 0.001):
        s = _time_step(scenario, h)
        runs = {
            f"press_E{E:g}": (lambda E=E: press_hold(_modulus(s, E), seconds))
            for E in (MODULI[0], scenario.contact.hydroelastic_modulus, MODULI[-1])
        }
        runs["scan_controller_test0"] = lambda s=s: scan_controller_hold(s, "test:0", seconds)
        for name, run in runs.items():
            key = f"{name}_{h * 1e3:g}ms"
            out[key] = run()
            print(dumps_strict({key: out[key]}), flush=True)
    return out


def _modulus(scenario, E: float):
    return dataclasses.replace(
        scenario, contact=dataclasses.replace(scenario.contact, hydroelastic_modulus=E)
    )


# ----------------------------------------------------------------------------- plot
def scan_arms(scenario, patients=("test:0", "test:1", "test:2"), every: int = 50) -> list:
    """The arm reflected to the tip (held and free) at poses along scans of ``patients``."""
    from drake_rus.anatomy import load_patient
    from drake_rus.localization.localize import load_registration_template
    from drake_rus.scan import RunScan

    template = load_registration_template(scenario.localization.template)
    arms = []
    for name in patients:
        result = RunScan(scenario, load_patient(name, progress=False), template, progress=False)
        for q in result.logs["q"][1].T[::every]:
            arms += [_arm_at(scenario, q, held) for held in (True, False)]
    return arms


def worst_margins(arms, law, stiffnesses, h) -> tuple[np.ndarray, np.ndarray]:
    """Per stiffness: the smallest gain margin and the largest pole over ``arms``."""
    gm = np.array(
        [min(fl.gain_margin(a, law, k, TAU, h, upper=50.0) for a in arms) for k in stiffnesses]
    )
    rho = np.array([max(fl.spectral_radius(a, law, k, TAU, h) for a in arms) for k in stiffnesses])
    return gm, rho


# Candidate gains (K_p3, K_d1, cut-off Hz) of the design table in docs/force_loop.md (the
# configured gains are added when they are not among them).
CANDIDATES = (
    (0.004, 0.0, math.inf),
    (0.006, 5e-5, 5.0),
    (0.006, 0.0, 3.0),
    (0.006, 0.0, 2.0),
    (0.004, 0.0, 2.0),
    (0.003, 0.0, 2.0),
    (0.003, 1e-5, 1.5),
    (0.004, 1e-5, 1.25),
)
DESIGN_STIFFNESSES = (100.0, 300.0, 1e3, 3e3, 1e4, 3e4, 1e5, 1e6, math.inf)
DESIGN_TAUS = (0.02, 0.2, 1.0)


def design_table(arms, candidates=CANDIDATES) -> list:
    """Per candidate law: the worst gain margin and damping ratio over ``arms``, the 10 ms
    and 1 ms steps, DESIGN_STIFFNESSES (the rigid limit included) and DESIGN_TAUS: the
    criterion of docs/force_loop.md (>= REQUIRED_GAIN_MARGIN, >= REQUIRED_DAMPING_RATIO)."""
    rows = []
    for gain, derivative, cutoff in candidates:
        law = fl.ForceLaw(gain, derivative, cutoff)
        gm = zeta = math.inf
        for arm in arms:
            for h in (0.01, 0.001):
                for k in DESIGN_STIFFNESSES:
                    for tau in DESIGN_TAUS:
                        gm = min(gm, fl.gain_margin(arm, law, k, tau, h, upper=50.0))
                        zeta = min(zeta, fl.damping_ratio(arm, law, k, tau, h))
        rows.append(
            {
                "K_p3": gain,
                "K_d1": derivative,
                "cutoff_hz": cutoff,
                "worst_gain_margin": round(gm, 2),
                "worst_damping_ratio": round(zeta, 2),
                "meets_criterion": bool(
                    gm >= fl.REQUIRED_GAIN_MARGIN and zeta >= fl.REQUIRED_DAMPING_RATIO
                ),
            }
        )
        print(dumps_strict(rows[-1]), flush=True)
    return rows


def plot_margins(scenario, arms, path, stiffness_band=None) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from drake_rus.io_utils import save_figure

    laws = {
        "press before issue 32 (0.004, no filter)": fl.ForceLaw(0.004),
        "scan before issue 32 (0.006, 5e-5, 5 Hz)": fl.ForceLaw(0.006, 5e-5, 5.0),
        "configured (both)": fl.ForceLaw.from_config(scenario.controller),
    }
    ks = np.append(STIFFNESS_GRID, math.inf)
    x = np.append(STIFFNESS_GRID, STIFFNESS_GRID[-1] * 3)  # the rigid limit, drawn last
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), dpi=110)
    data = {}
    colours = ["tab:red", "tab:orange", "tab:blue"]
    for (name, law), colour in zip(laws.items(), colours):
        for h, style in ((0.01, "-"), (0.001, "--")):
            gm, rho = worst_margins(arms, law, ks, h)
            label = f"{name}, {h * 1e3:g} ms"
            axes[0].semilogx(x, np.maximum(gm, 1e-2), style, color=colour, label=label)
            axes[1].semilogx(x, rho, style, color=colour, label=label)
            data[label] = {
                "min_gain_margin": round(float(gm.min()), 2),
                "max_pole": round(float(rho.max()), 4),
            }
    for ax in axes:
        if stiffness_band is not None:
            ax.axvspan(
                *stiffness_band,
                color="tab:green",
                alpha=0.12,
                lw=0,
                label="measured normal contact stiffness",
            )
        ax.axvline(x[-1], color="k", lw=0.5)
        ax.set_xlabel("contact stiffness dF/dx (N/m); rightmost: rigid limit")
        ax.grid(alpha=0.3, which="both")
    axes[0].axhline(fl.REQUIRED_GAIN_MARGIN, color="k", ls=":", lw=1, label="required margin")
    axes[0].set_ylabel("gain margin (worst arm pose)")
    axes[0].set_yscale("log")
    axes[0].set_ylim(0.1, 60)
    axes[1].axhline(1.0, color="k", ls=":", lw=1)
    axes[1].set_ylabel("largest closed-loop pole |z| per 10 ms")
    axes[1].set_ylim(0.5, 2.5)
    axes[0].legend(fontsize=6.5, loc="lower left")
    fig.suptitle(
        "Force loop along the approach axis: reduced model, "
        f"{len(arms)} arm poses of the scans of test:0-2"
    )
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    return data


def main(argv=None) -> int:
    from drake_rus.scenario import LoadScenario

    parser = argparse.ArgumentParser(prog="python -m benchmarks force_loop")
    parser.add_argument("--scenario", default="default")
    parser.add_argument("--stiffness", action="store_true")
    parser.add_argument("--validate", action="store_true")
    parser.add_argument("--hold", type=float, default=None, metavar="SECONDS")
    parser.add_argument("--plot", default=None, metavar="PATH")
    args = parser.parse_args(argv)
    if args.hold is not None and not (math.isfinite(args.hold) and args.hold > 0.0):
        print(f"--hold: expected a positive number of seconds, got {args.hold}", file=sys.stderr)
        return 2
    if not (args.stiffness or args.validate or args.hold is not None or args.plot):
        args.stiffness, args.validate, args.hold = True, True, 60.0
    scenario = LoadScenario(scenario_name=args.scenario)
    force = scenario.controller.desired_force
    result = {"law": dataclasses.asdict(fl.ForceLaw.from_config(scenario.controller))}
    if args.stiffness:
        result["stiffness"] = stiffness_range(scenario, force)
    if args.validate:
        result["validate"] = validate(scenario)
    if args.hold is not None:
        result["holds"] = holds(scenario, args.hold)
    if args.plot:
        band = (
            (result["stiffness"]["min_n_per_m"], result["stiffness"]["max_n_per_m"])
            if "stiffness" in result
            else None
        )
        arms = scan_arms(scenario)
        result["plot"] = plot_margins(scenario, arms, args.plot, band)
        configured = fl.ForceLaw.from_config(scenario.controller)
        candidates = CANDIDATES + ((configured.gain, configured.derivative, configured.cutoff_hz),)
        result["design_table"] = design_table(arms, tuple(dict.fromkeys(candidates)))
    print(dumps_strict(result))
    return 0
