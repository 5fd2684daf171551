"""``drake-rus demo``: the simulated station pressing the probe into the patient's body
(``PressDiagram``: station + the minimal ``drake_rus.control.press.PressDriver``).

Writes to ``--out``: ``press.html`` (standalone Meshcat recording), ``force.png`` (estimated
and true contact force over time), ``summary.json`` (the force over the last 5 s: mean,
ripple as RMS about the mean, and whether it settled within +-0.1 N of the desired force;
the estimate's error there; rates). The press driver runs the scan's force law with the
scenario's gains (docs/force_loop.md).
"""

import argparse
import time
from pathlib import Path

import matplotlib
import numpy as np
from pydrake.systems.analysis import Simulator

from drake_rus import interrupts
from drake_rus.cli import (
    EXIT_STATUS_HELP,
    MakeMeshcat,
    add_scenario_arguments,
    load_scenario_from_args,
)
from drake_rus.closed_loop import PressDiagram
from drake_rus.control.force_loop import SETTLING_BAND_N, force_statistics
from drake_rus.io_utils import (
    MB,
    check_output_file,
    dumps_strict,
    output_dir,
    save_figure,
    write_text_atomic,
)
from drake_rus.progress import AdvanceWithProgress, SaveMeshcatRecording
from drake_rus.provenance import Provenance

# About what the demo's Meshcat recording takes on disk (bytes): 2.5 MB for the default 6 s
# (30 frames a second), so 0.5 MB per simulated second with a margin, at least 20 MB.
DEMO_RECORDING_BYTES = 20 * MB
DEMO_RECORDING_BYTES_PER_S = MB // 2
# The longest demo (simulated s): the recording keeps every frame in memory and on disk
# (0.4-0.5 MB a second: 300 MB at this bound) and the force logs grow with it; a hold of
# 60 s (the breath-hold protocol's) fits ten times over. Longer holds: a study.
DEMO_MAX_DURATION = 600.0
# The summary's force statistics cover the last HOLD_WINDOW_S of the run (at most half of it).
HOLD_WINDOW_S = 5.0
FORCE_DEFINITION = (
    "true contact force F_z over the last window_s of the run, every plant "
    "step: mean; ripple = RMS about the mean (standard deviation, as the "
    "scan's force statistics); settled = every sample within desired +- "
    "settling_band_n"
)


def add_commands(subparsers) -> None:
    p = subparsers.add_parser(
        "demo",
        help="the simulated station pressing the probe into the body (Meshcat + plot)",
        description=__doc__,
        epilog=EXIT_STATUS_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_scenario_arguments(p)
    p.add_argument(
        "--out",
        default="runs/press",
        help="output directory (default runs/press; make demo's scan writes runs/demo)",
    )
    p.add_argument(
        "--duration",
        type=float,
        default=20.0,
        help=f"simulated time in s (default 20: landing, settling and a hold; at "
        f"most {DEMO_MAX_DURATION:g}: the recording grows by about 0.5 MB a "
        "second)",
    )
    p.add_argument(
        "--force",
        type=float,
        default=None,
        help="desired contact force in N (default: the scenario's controller force)",
    )
    p.add_argument(
        "--meshcat", action="store_true", help="live Meshcat in the browser, simulated at real time"
    )
    p.add_argument(
        "--record",
        default=None,
        help="where to save the Meshcat recording (default OUT/press.html)",
    )
    p.set_defaults(func=run_demo, outputs={"out": "dir", "record": "file:.html"})


def plot_force(times, F_est, F_true, desired, path: Path, window=None) -> None:
    """Estimated and true F_z over time; ``window`` (start, end s) shades the hold the
    summary's force statistics cover."""
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.6), dpi=110)
    ax.plot(times, F_true, label="true (plant contact results)", lw=2.2, color="tab:gray")
    ax.plot(
        times,
        F_est,
        label="estimated from external joint torques",
        lw=1.2,
        color="tab:blue",
        ls="--",
    )
    ax.axhline(desired, color="tab:red", lw=0.8, ls=":", label=f"desired {desired:.1f} N")
    if window is not None:
        ax.axvspan(
            window[0],
            window[1],
            color="tab:green",
            alpha=0.12,
            lw=0,
            label="window of the summary's force statistics",
        )
    ax.set_xlabel("time (s)")
    ax.set_ylabel("contact force $F_z$ (N)")
    ax.set_title("Probe pressing into the patient's body")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)


def demo_recording_bytes(duration: float) -> int:
    """About what the demo's recording of ``duration`` simulated s takes on disk (bytes)."""
    return max(DEMO_RECORDING_BYTES, int(DEMO_RECORDING_BYTES_PER_S * duration))


def run_demo(args) -> int:
    if args.duration > DEMO_MAX_DURATION:
        raise ValueError(
            f"--duration: expected at most {DEMO_MAX_DURATION:g} s, got "
            f"{args.duration:g} (the Meshcat recording keeps every frame, about "
            f"0.5 MB per simulated s; a longer hold belongs in a study)"
        )
    scenario = load_scenario_from_args(args)
    desired = scenario.controller.desired_force if args.force is None else args.force
    if not (0 < desired <= scenario.safety.force_ceiling):
        raise ValueError(
            f"--force: expected 0 < F <= the force ceiling "
            f"{scenario.safety.force_ceiling} N, got {desired}"
        )
    recording = demo_recording_bytes(args.duration)
    need = 2 * MB + (0 if args.record else recording)
    if args.record:
        check_output_file(args.record, "--record", need_bytes=recording, suffixes=(".html",))
    provenance = Provenance(
        scenario,
        scenario_name=args.scenario,
        scenarios_file=args.scenarios_file,
        overrides=args.overrides,
        argv=getattr(args, "argv", None),
    )
    provenance["command"] = "demo"
    provenance["arguments"] = {"duration": args.duration, "force": args.force}
    with output_dir(
        args.out, "--out", need_bytes=need, what="demo", argv=getattr(args, "argv", None)
    ) as out:
        try:
            return _demo(args, scenario, desired, out, provenance)
        except BaseException as e:
            if not (isinstance(e, KeyboardInterrupt) or interrupts.pending() is not None):
                raise
            return _demo_interrupted(args, out, provenance, e)


def _demo_interrupted(args, out: Path, provenance: dict, exc: BaseException) -> int:
    """A signal during the demo: an INTERRUPTED summary.json; the exit status (130, 143)."""
    reason = (
        f"interrupted by {interrupts.signal_text(interrupts.signal_of(exc))}; the "
        "outputs are partial"
    )
    with interrupts.deferred(reraise=False):
        path = write_text_atomic(
            out / "summary.json",
            dumps_strict(
                {
                    "status": "INTERRUPTED",
                    "reason": reason,
                    "scenario": args.scenario,
                    "provenance": provenance,
                },
                indent=2,
            )
            + "\n",
        )
    print(f"INTERRUPTED: {reason}; wrote {path}", flush=True)
    return interrupts.exit_status(exc)


def _demo(args, scenario, desired: float, out: Path, provenance: dict | None = None) -> int:
    meshcat = MakeMeshcat()
    if args.meshcat:
        print(f"Meshcat: {meshcat.web_url()}", flush=True)
    press = PressDiagram(scenario, meshcat=meshcat, desired_force=desired)
    simulator = Simulator(press.diagram)
    if args.meshcat:
        simulator.set_target_realtime_rate(1.0)
    simulator.Initialize()
    meshcat.StartRecording(frames_per_second=30.0)
    start = time.perf_counter()
    AdvanceWithProgress(simulator, args.duration, desc="pressing")
    wall = time.perf_counter() - start
    record = Path(args.record) if args.record else out / "press.html"
    SaveMeshcatRecording(meshcat, record)

    times, F_est, F_true = press.logs(simulator.get_context())
    t_true, F_true_all = press.true_force(simulator.get_context())
    window = min(HOLD_WINDOW_S, args.duration / 2)
    force = force_statistics(t_true, F_true_all, desired, window)
    plot_force(
        times, F_est, F_true, desired, out / "force.png", window=(t_true[-1] - window, t_true[-1])
    )
    contact = F_true > 1.0
    held = times >= times[-1] - window
    summary = {
        "scenario": args.scenario,
        "contact_model": scenario.contact.model,
        "desired_force_n": desired,
        "force": {**force, "settling_band_n": SETTLING_BAND_N, "definition": FORCE_DEFINITION},
        "force_estimated_mean_n": float(np.mean(F_est[held])),
        "estimate_error_mean_n": float(
            np.mean(np.abs(F_est[held & contact] - F_true[held & contact]))
        )
        if (held & contact).any()
        else None,
        "first_contact_s": float(times[np.argmax(contact)]) if contact.any() else None,
        "sim_s": args.duration,
        "wall_s": wall,
        "realtime_rate": args.duration / wall,
        "recording": str(record),
        "force_plot": str(out / "force.png"),
    }
    summary.update(status="DONE", provenance=provenance)
    write_text_atomic(out / "summary.json", dumps_strict(summary, indent=2) + "\n")
    state = (
        "settled"
        if force["settled"]
        else f"NOT settled (off by up to {force['max_error_n']:.2f} N)"
    )
    print(
        f"force over the last {window:g} s: mean {force['mean_n']:.3f} N, ripple "
        f"{force['ripple_n']:.2g} N RMS ({force['peak_to_peak_n']:.2g} N peak to peak), "
        f"{state}; desired {desired:.1f} +- {SETTLING_BAND_N:g} N; estimated mean "
        f"{summary['force_estimated_mean_n']:.3f} N; "
        f"{summary['realtime_rate']:.1f}x real time"
    )
    print(f"wrote {record}, {out / 'force.png'}, {out / 'summary.json'}")
    return 0
