"""Real-time rate of the simulated station (``python -m benchmarks station``).

Three runs of the same scenario in one process, each ``--duration`` simulated seconds:
- ``rtf_hydroelastic``: the probe pressed into the soft body at 9 N, hydroelastic contact;
- ``rtf_point``: the same with point contact;
- ``rtf_free``: free motion (a joint-velocity sine, no contact), the reference.
Also prints, for each contact run, over the hold (the last half of the run, after the
landing): the contact-force accuracy (mean |estimated - true| F_z), the true force's ripple
(RMS about the mean, every plant step) and whether it settled within +-0.1 N of the desired
force; and the settings used. (Before issue 32 the error was taken over the whole contact,
while the press loop oscillated: 0.32 N.) ``--sweep`` also times a grid of resolution hints.
The last line is one JSON object.
"""

import argparse
import sys
import time

import numpy as np
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import Sine

from benchmarks._scan_rows import argument_error
from drake_rus.closed_loop import PressDiagram
from drake_rus.control.force_loop import force_statistics
from drake_rus.io_utils import dumps_strict
from drake_rus.scenario import ApplyOverrides, LoadScenario
from drake_rus.stations import MakeStation


def _press_run(scenario, duration: float) -> dict:
    """The press diagram for ``duration`` s: real-time rate, and over the hold (the last
    half of the run, after the landing): the estimate's mean error |F_est - F_true| and the
    true force's mean and ripple (RMS about the mean, every plant step)."""
    press = PressDiagram(scenario)
    simulator = Simulator(press.diagram)
    simulator.Initialize()
    start = time.perf_counter()
    simulator.AdvanceTo(duration)
    wall = time.perf_counter() - start
    t, F_est, F_true = press.logs(simulator.get_context())
    contact = F_true > 1.0
    hold = contact & (t >= duration / 2)
    error = float(np.mean(np.abs(F_est[hold] - F_true[hold]))) if hold.any() else None
    t_true, F_all = press.true_force(simulator.get_context())
    stats = force_statistics(t_true, F_all, scenario.controller.desired_force, duration / 2)
    return {
        "rtf": duration / wall,
        "force_error_n": error,
        "final_force_n": float(F_true[-1]),
        "contact_fraction": float(contact.mean()),
        "hold_mean_n": stats["mean_n"],
        "hold_ripple_n": stats["ripple_n"],
        "settled": stats["settled"],
    }


def _free_run(scenario, duration: float) -> dict:
    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(scenario))
    amplitude = np.array([0.3, 0.2, 0.3, 0.2, 0.4, 0.3, 0.5])
    sine = builder.AddSystem(Sine(amplitude, np.full(7, 1.5), np.zeros(7)))
    builder.Connect(sine.get_output_port(0), station.GetInputPort("joint_velocity_command"))
    diagram = builder.Build()
    simulator = Simulator(diagram)
    simulator.Initialize()
    start = time.perf_counter()
    simulator.AdvanceTo(duration)
    return {"rtf": duration / (time.perf_counter() - start)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks station")
    parser.add_argument("--duration", type=float, default=10.0, help="simulated seconds per run")
    parser.add_argument("--scenario", default="default")
    parser.add_argument(
        "--sweep", action="store_true", help="also time a grid of patient/probe resolution hints"
    )
    args = parser.parse_args(argv)
    error = argument_error(args)
    if error:
        print(error, file=sys.stderr)
        return 2
    scenario = LoadScenario(scenario_name=args.scenario)
    hydro = _press_run(ApplyOverrides(scenario, "{contact: {model: hydroelastic}}"), args.duration)
    point = _press_run(ApplyOverrides(scenario, "{contact: {model: point}}"), args.duration)
    free = _free_run(scenario, args.duration)
    result = {
        "rtf_hydroelastic": round(hydro["rtf"], 2),
        "rtf_point": round(point["rtf"], 2),
        "rtf_free": round(free["rtf"], 2),
        "ratio_hydroelastic_to_free": round(hydro["rtf"] / free["rtf"], 3),
        "ratio_point_to_free": round(point["rtf"] / free["rtf"], 3),
        "force_error_hydroelastic_n": hydro["force_error_n"],
        "force_error_point_n": point["force_error_n"],
        "final_force_hydroelastic_n": round(hydro["final_force_n"], 3),
        "final_force_point_n": round(point["final_force_n"], 3),
        "hold_ripple_hydroelastic_n": hydro["hold_ripple_n"],
        "hold_ripple_point_n": point["hold_ripple_n"],
        "settled_hydroelastic": hydro["settled"],
        "settled_point": point["settled"],
        "patient_resolution_hint_m": scenario.contact.patient_resolution_hint,
        "probe_resolution_hint_m": scenario.contact.probe_resolution_hint,
        "discrete_contact_approximation": scenario.contact.discrete_contact_approximation,
        "duration_s": args.duration,
    }
    if args.sweep:
        sweep = []
        for patient_hint in (0.03, 0.06, 0.1):
            for probe_hint in (0.01, 0.02, 0.03):
                s = ApplyOverrides(
                    scenario,
                    "{contact: {model: hydroelastic, "
                    f"patient_resolution_hint: {patient_hint}, "
                    f"probe_resolution_hint: {probe_hint}}}}}",
                )
                r = _press_run(s, min(args.duration, 5.0))
                row = {
                    "patient_hint": patient_hint,
                    "probe_hint": probe_hint,
                    "rtf": round(r["rtf"], 2),
                    "ratio_to_free": round(r["rtf"] / free["rtf"], 3),
                    "force_error_n": r["force_error_n"],
                }
                print(dumps_strict(row), flush=True)
                sweep.append(row)
        result["sweep"] = sweep
    print(dumps_strict(result))
    return 0
