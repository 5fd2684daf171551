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

from drake_rus.control.force_loop import SETTLING_BAND_N, force_statistics
from drake_rus.control.press import PressDriver
from drake_rus.io_utils import (MB, check_output_file, dumps_strict, output_dir, save_figure,
                                write_text_atomic)
from drake_rus.progress import AdvanceWithProgress, SaveMeshcatRecording
from drake_rus.robot import MakeControlPlant
from drake_rus.scenario import DEFAULT_SCENARIOS_FILE, LoadScenario
from drake_rus.stations import MakeStation

# About what the demo's Meshcat recording takes on disk (bytes).
DEMO_RECORDING_BYTES = 20 * MB
# The summary's force statistics cover the last HOLD_WINDOW_S of the run (at most half of it).
HOLD_WINDOW_S = 5.0
FORCE_DEFINITION = ("true contact force F_z over the last window_s of the run, every plant "
                    "step: mean; ripple = RMS about the mean (standard deviation, as the "
                    "scan's force statistics); settled = every sample within desired +- "
                    "settling_band_n")


def add_commands(subparsers) -> None:
    p = subparsers.add_parser(
        "demo", help="the simulated station pressing the probe into the body (Meshcat + plot)",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scenario_arguments(p)
    p.add_argument("--out", default="runs/demo", help="output directory (default runs/demo)")
    p.add_argument("--duration", type=float, default=20.0,
                   help="simulated time in s (default 20: landing, settling and a hold)")
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
    return LoadScenario(filename=args.scenarios_file, scenario_name=args.scenario,
                        scenario_text=args.overrides)


def MakeMeshcat(port: int | None = None):
    """A Meshcat server on localhost (no other network)."""
    params = MeshcatParams()
    params.host = "localhost"
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


def run_demo(args) -> int:
    scenario = load_scenario_from_args(args)
    desired = scenario.controller.desired_force if args.force is None else args.force
    if not (0 < desired <= scenario.safety.force_ceiling):
        raise ValueError(f"--force: expected 0 < F <= the force ceiling "
                         f"{scenario.safety.force_ceiling} N, got {desired}")
    need = 2 * MB + (0 if args.record else DEMO_RECORDING_BYTES)
    if args.record:
        check_output_file(args.record, "--record", need_bytes=DEMO_RECORDING_BYTES,
                          suffixes=(".html",))
    with output_dir(args.out, "--out", need_bytes=need, what="demo") as out:
        return _demo(args, scenario, desired, out)


def _demo(args, scenario, desired: float, out: Path) -> int:
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
