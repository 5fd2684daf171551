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
from pydrake.geometry import Meshcat, MeshcatParams
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource, LogVectorOutput

from drake_rus import interrupts
from drake_rus.cli import EXIT_STATUS_HELP
from drake_rus.config_schema import check_nesting_depth
from drake_rus.control.force_loop import SETTLING_BAND_N, force_statistics
from drake_rus.control.press import PressDriver
from drake_rus.io_utils import (MB, check_output_file, dumps_strict, output_dir, save_figure,
                                write_text_atomic)
from drake_rus.progress import AdvanceWithProgress, SaveMeshcatRecording
from drake_rus.provenance import Provenance
from drake_rus.robot import MakeControlPlant
from drake_rus.scenario import DEFAULT_SCENARIOS_FILE, LoadScenario
from drake_rus.stations import MakeStation

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
FORCE_DEFINITION = ("true contact force F_z over the last window_s of the run, every plant "
                    "step: mean; ripple = RMS about the mean (standard deviation, as the "
                    "scan's force statistics); settled = every sample within desired +- "
                    "settling_band_n")


def add_commands(subparsers) -> None:
    p = subparsers.add_parser(
        "demo", help="the simulated station pressing the probe into the body (Meshcat + plot)",
        description=__doc__, epilog=EXIT_STATUS_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scenario_arguments(p)
    p.add_argument("--out", default="runs/demo", help="output directory (default runs/demo)")
    p.add_argument("--duration", type=float, default=20.0,
                   help=f"simulated time in s (default 20: landing, settling and a hold; at "
                        f"most {DEMO_MAX_DURATION:g}: the recording grows by about 0.5 MB a "
                        "second)")
    p.add_argument("--force", type=float, default=None,
                   help="desired contact force in N (default: the scenario's controller force)")
    p.add_argument("--meshcat", action="store_true",
                   help="live Meshcat in the browser, simulated at real time")
    p.add_argument("--record", default=None,
                   help="where to save the Meshcat recording (default OUT/press.html)")
    p.set_defaults(func=run_demo, outputs={"out": "dir", "record": "file:.html"})


def add_scenario_arguments(parser) -> None:
    """--scenario / --scenarios-file / --set, shared by every command that builds a station."""
    parser.add_argument("--scenario", default="default", help="scenario name (default 'default')")
    parser.add_argument("--scenarios-file", default=str(DEFAULT_SCENARIOS_FILE),
                        help="YAML file of named scenarios")
    parser.add_argument("--set", dest="overrides", default=None, metavar="YAML",
                        help="YAML overrides, e.g. \"{contact: {model: point}}\"")


def load_scenario_from_args(args):
    check_nesting_depth(args.overrides, "--set")
    return LoadScenario(filename=args.scenarios_file, scenario_name=args.scenario,
                        scenario_text=args.overrides)


# The address every server of drake-rus listens on: the loopback only (Meshcat, the
# rehearsal's video stream; `make notebooks` starts JupyterLab on it too).
LOOPBACK = "127.0.0.1"


def MakeMeshcat(port: int | None = None):
    """A Meshcat server listening on the loopback only (127.0.0.1; Drake's default "*" is
    every interface, and "localhost" may resolve to an IPv6 or another address)."""
    params = MeshcatParams()
    params.host = LOOPBACK
    if port is not None:
        params.port = port
    return Meshcat(params)


def plot_force(times, F_est, F_true, desired, path: Path, window=None) -> None:
    """Estimated and true F_z over time; ``window`` (start, end s) shades the hold the
    summary's force statistics cover."""
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 3.6), dpi=110)
    ax.plot(times, F_true, label="true (plant contact results)", lw=2.2, color="tab:gray")
    ax.plot(times, F_est, label="estimated from external joint torques", lw=1.2,
            color="tab:blue", ls="--")
    ax.axhline(desired, color="tab:red", lw=0.8, ls=":", label=f"desired {desired:.1f} N")
    if window is not None:
        ax.axvspan(window[0], window[1], color="tab:green", alpha=0.12, lw=0,
                   label="window of the summary's force statistics")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("contact force $F_z$ (N)")
    ax.set_title("Probe pressing into the patient's body")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)


class PressDiagram:
    """Station + PressDriver (+ loggers of the estimated and true probe wrench).

    The true wrench is logged at every plant step (cheap: the station samples it there), so
    an oscillation of the force loop, up to the controller's Nyquist rate, cannot alias
    into a false steady value; the estimate at every controller period (``log_period``
    overrides both)."""

    def __init__(self, scenario, meshcat=None, desired_force: float | None = None,
                 log_period: float | None = None, patient=None, drive: bool = True,
                 hold_orientation: bool = True):
        builder = DiagramBuilder()
        self.station = builder.AddNamedSystem(
            "station", MakeStation(scenario, meshcat=meshcat, patient=patient))
        if drive:
            control_plant, tip_frame = MakeControlPlant(scenario)
            self.driver = builder.AddNamedSystem(
                "press_driver", PressDriver(control_plant, tip_frame, scenario.controller,
                                            desired_force, hold_orientation=hold_orientation))
            builder.Connect(self.station.GetOutputPort("joint_position"),
                            self.driver.get_input_port(0))
            builder.Connect(self.station.GetOutputPort("probe_force"),
                            self.driver.get_input_port(1))
            builder.Connect(self.driver.get_output_port(),
                            self.station.GetInputPort("joint_velocity_command"))
        else:
            self.driver = builder.AddNamedSystem("zero_command", ConstantVectorSource(np.zeros(7)))
            builder.Connect(self.driver.get_output_port(),
                            self.station.GetInputPort("joint_velocity_command"))
        self.force_log = LogVectorOutput(
            self.station.GetOutputPort("probe_force"), builder,
            log_period or 1.0 / scenario.controller.rate_hz)
        self.truth_log = LogVectorOutput(
            self.station.GetOutputPort("probe_contact_wrench_true"), builder,
            log_period or scenario.contact.time_step)
        self.diagram = builder.Build()
        self.diagram.set_name("press_demo")

    def logs(self, root_context):
        """(times (N,), estimated F_z (N,), true F_z (N,)) in s and N, at the estimate's
        log times."""
        est = self.force_log.FindLog(root_context)
        t_true, F_true = self.true_force(root_context)
        t = est.sample_times()
        i = np.clip(np.searchsorted(t_true, t - 1e-9), 0, max(len(t_true) - 1, 0))
        return t, -est.data()[5], F_true[i] if len(t_true) else np.zeros(len(t))

    def true_force(self, root_context):
        """(times (N,), true F_z (N,)) in s and N, at every plant step."""
        tru = self.truth_log.FindLog(root_context)
        return tru.sample_times(), -tru.data()[5]


def demo_recording_bytes(duration: float) -> int:
    """About what the demo's recording of ``duration`` simulated s takes on disk (bytes)."""
    return max(DEMO_RECORDING_BYTES, int(DEMO_RECORDING_BYTES_PER_S * duration))


def run_demo(args) -> int:
    if args.duration > DEMO_MAX_DURATION:
        raise ValueError(f"--duration: expected at most {DEMO_MAX_DURATION:g} s, got "
                         f"{args.duration:g} (the Meshcat recording keeps every frame, about "
                         f"0.5 MB per simulated s; a longer hold belongs in a study)")
    scenario = load_scenario_from_args(args)
    desired = scenario.controller.desired_force if args.force is None else args.force
    if not (0 < desired <= scenario.safety.force_ceiling):
        raise ValueError(f"--force: expected 0 < F <= the force ceiling "
                         f"{scenario.safety.force_ceiling} N, got {desired}")
    recording = demo_recording_bytes(args.duration)
    need = 2 * MB + (0 if args.record else recording)
    if args.record:
        check_output_file(args.record, "--record", need_bytes=recording, suffixes=(".html",))
    provenance = Provenance(scenario, scenario_name=args.scenario,
                            scenarios_file=args.scenarios_file, overrides=args.overrides,
                            argv=getattr(args, "argv", None))
    provenance["command"] = "demo"
    provenance["arguments"] = {"duration": args.duration, "force": args.force}
    with output_dir(args.out, "--out", need_bytes=need, what="demo",
                    argv=getattr(args, "argv", None)) as out:
        try:
            return _demo(args, scenario, desired, out, provenance)
        except BaseException as e:
            if not (isinstance(e, KeyboardInterrupt) or interrupts.pending() is not None):
                raise
            return _demo_interrupted(args, out, provenance, e)


def _demo_interrupted(args, out: Path, provenance: dict, exc: BaseException) -> int:
    """A signal during the demo: an INTERRUPTED summary.json; the exit status (130, 143)."""
    reason = (f"interrupted by {interrupts.signal_text(interrupts.signal_of(exc))}; the "
              "outputs are partial")
    with interrupts.deferred(reraise=False):
        path = write_text_atomic(out / "summary.json", dumps_strict(
            {"status": "INTERRUPTED", "reason": reason, "scenario": args.scenario,
             "provenance": provenance}, indent=2) + "\n")
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
    plot_force(times, F_est, F_true, desired, out / "force.png", window=(t_true[-1] - window,
                                                                        t_true[-1]))
    contact = F_true > 1.0
    held = times >= times[-1] - window
    summary = {
        "scenario": args.scenario,
        "contact_model": scenario.contact.model,
        "desired_force_n": desired,
        "force": {**force, "settling_band_n": SETTLING_BAND_N,
                  "definition": FORCE_DEFINITION},
        "force_estimated_mean_n": float(np.mean(F_est[held])),
        "estimate_error_mean_n": float(np.mean(np.abs(F_est[held & contact]
                                                      - F_true[held & contact])))
        if (held & contact).any() else None,
        "first_contact_s": float(times[np.argmax(contact)]) if contact.any() else None,
        "sim_s": args.duration,
        "wall_s": wall,
        "realtime_rate": args.duration / wall,
        "recording": str(record),
        "force_plot": str(out / "force.png"),
    }
    summary.update(status="DONE", provenance=provenance)
    write_text_atomic(out / "summary.json", dumps_strict(summary, indent=2) + "\n")
    state = ("settled" if force["settled"] else
             f"NOT settled (off by up to {force['max_error_n']:.2f} N)")
    print(f"force over the last {window:g} s: mean {force['mean_n']:.3f} N, ripple "
          f"{force['ripple_n']:.2g} N RMS ({force['peak_to_peak_n']:.2g} N peak to peak), "
          f"{state}; desired {desired:.1f} +- {SETTLING_BAND_N:g} N; estimated mean "
          f"{summary['force_estimated_mean_n']:.3f} N; "
          f"{summary['realtime_rate']:.1f}x real time")
    print(f"wrote {record}, {out / 'force.png'}, {out / 'summary.json'}")
    return 0
