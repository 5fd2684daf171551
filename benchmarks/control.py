"""Closed-loop real-time rate of station + controller during exploration
(``python -m benchmarks control``).

Runs the scan supervisor through APPROACH into EXPLORE, then times ``--duration`` simulated
seconds of exploration (5 mm/s slide under 9 N force control, mask centring in the loop).
By default the station renders emulated images of the virtual patient ``test:0`` (slice
sensor + ultrasound emulator at 20 Hz) and the scenario's segmenter closes the loop; with
``--patient none`` the geometric kidney view stands in for image + segmenter on the
placeholder torso. Patient generation and diagram build are not timed. Also times the station alone
pressed by the minimal press driver as the reference measured in the same run.
The last line is one JSON object.
"""

import argparse
import math
import sys
import time

from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.systems.analysis import Simulator

from benchmarks._scan_rows import argument_error
from drake_rus.closed_loop import BuildClosedLoop, BuildClosedLoopOnPatient
from drake_rus.control import supervisor
from drake_rus.control.synthetic_view import GeometricKidneyView
from drake_rus.io_utils import dumps_strict
from drake_rus.scenario import ApplyOverrides, LoadScenario


def _closed_loop(scenario, patient: str | None):
    """(closed loop, scenario used)."""
    if patient:
        return BuildClosedLoopOnPatient(scenario, patient, log_period=0.05)
    X_BK = RigidTransform(RollPitchYaw(0.1, 0.0, math.radians(105.0)), [0.595, -0.035, 0.035])
    view = GeometricKidneyView(
        X_BK, [0.055, 0.03, 0.025], frame_rate_hz=scenario.imaging.frame_rate_hz
    )
    return BuildClosedLoop(scenario, kidney_view=view, log_period=0.05), scenario


def _station_alone_rtf(scenario, duration: float) -> float | None:
    """Reference measured in the same run: the station pressed and held by the lead's
    minimal C++-light press driver (drake_rus.control.press), no scan controller."""
    try:
        from drake_rus.closed_loop import PressDiagram
    except ImportError:
        return None
    press = PressDiagram(scenario)
    sim = Simulator(press.diagram)
    sim.AdvanceTo(2.0)
    start = time.perf_counter()
    sim.AdvanceTo(2.0 + duration)
    return duration / (time.perf_counter() - start)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks control")
    parser.add_argument(
        "--duration", type=float, default=5.0, help="simulated seconds of exploration to time"
    )
    parser.add_argument("--scenario", default="default")
    parser.add_argument(
        "--patient",
        default="test:0",
        help="virtual patient spec for emulated images + the scenario's "
        "segmenter (default test:0); 'none' = placeholder torso with the "
        "geometric kidney view",
    )
    parser.add_argument("--rate-hz", type=float, default=None, help="controller rate override")
    parser.add_argument("--contact", choices=["hydroelastic", "point"], default=None)
    parser.add_argument(
        "--no-reference", action="store_true", help="skip the station-alone reference run"
    )
    args = parser.parse_args(argv)
    error = argument_error(args)
    if error:
        print(error, file=sys.stderr)
        return 2
    if args.patient in ("none", ""):
        args.patient = None

    scenario = LoadScenario(scenario_name=args.scenario)
    # The default joint pose hovers about 0.1 m above the placeholder torso: allow that
    # approach (the patient variant starts 0.22 m above the kidney and allows its own).
    overrides = ["exploration_ratio: 1.0", "approach_max_travel: 0.2"]
    if args.rate_hz:
        overrides.append(f"rate_hz: {args.rate_hz}")
    scenario = ApplyOverrides(scenario, "{controller: {%s}}" % ", ".join(overrides))
    if args.contact:
        scenario = ApplyOverrides(scenario, "{contact: {model: %s}}" % args.contact)
    if args.patient:
        scenario = ApplyOverrides(scenario, "{patient: {source: '%s'}}" % args.patient)

    t0 = time.perf_counter()
    cl, scenario = _closed_loop(scenario, args.patient)
    build_s = time.perf_counter() - t0
    sim = Simulator(cl.diagram)
    ctx = sim.get_mutable_context()
    sup = cl.parts.supervisor
    sup_ctx = sup.GetMyContextFromRoot(ctx)
    t_wall0 = time.perf_counter()
    while sup.state(sup_ctx).phase == supervisor.Phase.APPROACH and ctx.get_time() < 20.0:
        sim.AdvanceTo(ctx.get_time() + 0.1)
    approach_wall = time.perf_counter() - t_wall0
    phase = sup.state(sup_ctx).phase
    t_start = ctx.get_time()
    start = time.perf_counter()
    sim.AdvanceTo(t_start + args.duration)
    wall = time.perf_counter() - start
    state = sup.state(sup_ctx)
    safety = cl.parts.safety.safety_state(cl.parts.safety.GetMyContextFromRoot(ctx))
    figures = {}
    if "phase" in cl.loggers:
        phase_log = cl.loggers["phase"].FindLog(ctx)
        m = (phase_log.sample_times() >= t_start + 1.0) & (
            phase_log.data()[0] == float(supervisor.Phase.EXPLORE)
        )
        F = -cl.loggers["probe_force"].FindLog(ctx).data()[5][m]
        c = cl.loggers["mask_centroid"].FindLog(ctx).data()[0][m]
        vis = cl.loggers["kidney_visible"].FindLog(ctx).data()[0][m]
        if m.any():
            figures = {
                "force_min_n": round(float(F.min()), 3),
                "force_max_n": round(float(F.max()), 3),
                "centroid_min": round(float(c.min()), 3),
                "centroid_max": round(float(c.max()), 3),
                "kidney_visible_fraction": round(float(vis.mean()), 3),
            }
    reference = None if args.no_reference else _station_alone_rtf(scenario, args.duration)
    result = {
        "rtf_exploration": round(args.duration / wall, 3),
        "rtf_station_press_reference": None if reference is None else round(reference, 3),
        "explored_m": round(state.travel, 4),
        "phase_at_start": phase.name,
        "phase_at_end": state.phase.name,
        "exploration_figures_after_1s": figures,
        "safety_stops": [e.reason for e in safety.events],
        "supervisor_events": [f"{t:.2f} {name}: {msg}" for t, name, msg in state.events],
        "controller_rate_hz": scenario.controller.rate_hz,
        "contact_model": scenario.contact.model,
        "images": "emulated + " + scenario.imaging.segmenter
        if args.patient
        else "geometric kidney view",
        "approach_wall_s": round(approach_wall, 2),
        "build_s": round(build_s, 2),
        "duration_s": args.duration,
    }
    print(
        f"exploration: {args.duration} s simulated in {wall:.2f} s wall "
        f"(real-time factor {args.duration / wall:.2f})"
    )
    print(dumps_strict(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
