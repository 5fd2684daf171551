"""Speed of the full closed-loop scan (``python -m benchmarks scan``).

One run reports, for one test patient on one scenario (default: ``default``):

- ``rtf_scan`` (``rtf_scan_cpu``): the scan's simulated time over the wall (process CPU)
  time of its simulation loop;
- ``rtf_free_station``: the simulated station in free motion (a joint-velocity sine, no
  contact, no controller) at the same plant step;
- ``rtf_floor``: the bare-plant floor at the same step: the FR3 with the probe in SAP, its
  joint PD holding a fixed pose, no contact geometry, no Python system. No diagram on this
  plant step can run faster;
- ratios of the scan to both, measured in the same run (the machines are shared: compare
  ratios);
- ``setup_s``: the set-up time in this process (patient from the cache, template, start plan,
  station and diagram build) and, with ``--cli-start``, the time from running
  ``drake-rus scan --patient P`` to its first simulated step (a fresh process);
- ``profile``: the per-system share of the loop (``py-spy`` sampling of a second run in a
  child process, native frames included: the plant step, Drake's framework, every Python
  LeafSystem by class); skipped with ``--no-profile`` or when ``py-spy`` is missing;
- the scan's outcome: status, phases, E_trans, V, and the true contact force (mean and
  ripple in EXPLORE and PIVOT, landing peak);
- with ``--repeat N``, every run's rates (``rtf_scan_runs``, ``rtf_scan_cpu_runs``,
  ``scan_cpu_s_runs``) and their medians: a shared host's speed moves by a third between
  runs minutes apart, so one run is one sample.

``--validate`` instead runs the scan at several plant steps (``--steps``) on several patients
(``--patients``) and compares every step with the first (the reference, 1 ms) against the
tolerances of issue 16: force 9 +- 0.2 N (mean and ripple) in EXPLORE and PIVOT, landing peak
< 12 N, E_trans within 1 mm and V within 0.02 of the reference.

The last line is one JSON object.
"""

import argparse
import collections
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from pydrake.multibody.plant import AddMultibodyPlant
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ConstantVectorSource

from drake_rus.io_utils import dumps_strict
from drake_rus.scenario import ApplyOverrides, LoadScenario

# py-spy's sampling rate for the per-system profile (samples per second).
PROFILE_RATE_HZ = 100

# Issue 16's tolerances.
FORCE_TARGET_N = 9.0
FORCE_TOL_N = 0.2
LANDING_PEAK_MAX_N = 12.0
E_TRANS_TOL_MM = 1.0
V_TOL = 0.02


def floor_rtf(scenario, duration: float = 5.0) -> dict:
    """Real-time rates (over wall and over process CPU time) of the bare plant at the
    scenario's step: FR3 + probe in SAP, joint PD holding the initial pose, no contact
    geometry, no Python systems."""
    from drake_rus.robot import AddFr3AndProbe
    from drake_rus.station import _plant_config

    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlant(_plant_config(scenario), builder)
    parts = AddFr3AndProbe(plant, scenario.robot, scenario.probe)
    plant.Finalize()
    q0 = np.asarray(scenario.robot.initial_joint_positions, dtype=float)
    desired = builder.AddSystem(ConstantVectorSource(np.concatenate([q0, np.zeros(7)])))
    builder.Connect(desired.get_output_port(), plant.get_desired_state_input_port(parts.robot))
    zero = builder.AddSystem(ConstantVectorSource(np.zeros(7)))
    builder.Connect(zero.get_output_port(), plant.get_actuation_input_port(parts.robot))
    simulator = Simulator(builder.Build())
    simulator.Initialize()
    start, cpu = time.perf_counter(), time.process_time()
    simulator.AdvanceTo(duration)
    return {
        "rtf": duration / (time.perf_counter() - start),
        "rtf_cpu": duration / (time.process_time() - cpu),
    }


def free_station_rtf(scenario, duration: float) -> dict:
    """Real-time rates (wall, CPU) of the simulated station in free motion (benchmarks.
    station's joint-velocity sine, no contact, no controller)."""
    from benchmarks.station import _free_run

    cpu = time.process_time()
    out = _free_run(scenario, duration)
    # _free_run times AdvanceTo only; the CPU figure here includes the (small) build.
    out["rtf_cpu"] = duration / (time.process_time() - cpu)
    return out


def _load(patient_name, scenario):
    from drake_rus.anatomy import load_patient
    from drake_rus.localization.localize import load_registration_template

    patient = load_patient(patient_name)
    _ = patient.labels
    return patient, load_registration_template(scenario.localization.template)


def run_one(scenario, patient_name: str) -> dict:
    """One scan: rate, set-up time, outcome, metrics and force-trace statistics."""
    from drake_rus.scan import RunScan, ScanMetrics, Summary
    from drake_rus.scan.truth import force_trace_stats

    start = time.perf_counter()
    patient, template = _load(patient_name, scenario)
    loaded = time.perf_counter()
    result = RunScan(scenario, patient, template, progress=False)
    total = time.perf_counter() - loaded
    summary = Summary(result, ScanMetrics(result))
    out = {
        "patient": patient_name,
        "time_step": scenario.contact.time_step,
        "status": summary["status"],
        "reason": result.reason,
        "scan_sim_s": round(result.sim_s, 3),
        "scan_wall_s": round(result.wall_s, 3),
        "rtf_scan": round(result.sim_s / result.wall_s, 3),
        "scan_cpu_s": round(result.cpu_s, 3),
        "rtf_scan_cpu": round(result.sim_s / result.cpu_s, 3),
        "setup_s": round(loaded - start + total - result.wall_s, 2),
        "phases": {p["phase"]: round(p["duration_s"], 2) for p in summary["phases"]},
        "pivot_frames_pole_to_pole": summary.get("n_frames"),
        "pivot_frames_whole_pivot": summary.get("n_whole_pivot"),
        "volume_ratio": summary["volume_ratio"],
        "e_trans_mm": summary["e_trans_mm"],
        "e_rot_x_deg": summary["e_rot_x_deg"],
    }
    out.update(
        {k: (None if v is None else round(v, 4)) for k, v in force_trace_stats(result).items()}
    )
    return out


def _leaf_system_classes() -> set:
    """Names of the Python LeafSystem classes of drake_rus (for the profile summary)."""
    import drake_rus.scan.diagram  # noqa: F401  (imports the systems)
    import drake_rus.scan.run  # noqa: F401
    import drake_rus.station  # noqa: F401

    names, todo = set(), [LeafSystem]
    while todo:
        cls = todo.pop()
        for sub in cls.__subclasses__():
            if sub.__module__.startswith("drake_rus"):
                names.add(sub.__name__)
            todo.append(sub)
    return names


PLANT = "plant step and contact solves (native)"
_PLANT_FRAMES = (
    "MultibodyPlant<double>::CalcStep",
    "DiscreteUpdateManager",
    "CompliantContactManager",
    "SapDriver",
    "ContactResults",
    "GeometryContactData",
    "ContactSurface",
    "PointPairPenetration",
)


def summarise_profile(raw_path: Path, classes: set) -> dict:
    """Per-system share (%) of the simulation loop from py-spy's raw (collapsed) stacks:
    each sample goes to the innermost of: a MultibodyPlant computation (the plant step and
    its contact solves, wherever triggered) or a drake_rus LeafSystem frame; samples in the
    loop with neither go to Drake's framework (events, caches, loggers, C++ systems)."""
    shares = collections.Counter()
    loop = 0
    name_re = re.compile(r"^([A-Za-z_]\w*)\.")
    for line in raw_path.read_text().splitlines():
        if not line.strip():
            continue
        stack, count = line.rsplit(" ", 1)
        frames = stack.split(";")
        if not any("Simulator<double>::AdvanceTo" in f for f in frames):
            continue
        n = int(count)
        loop += n
        owner = None
        for f in reversed(frames):
            if any(key in f for key in _PLANT_FRAMES):
                # The plant's contact solve, also when a Python system's read of a contact
                # output (unsampled ports) triggered it.
                owner = PLANT
                break
            m = name_re.match(f)
            if m and m.group(1) in classes:
                owner = m.group(1)
                break
        if owner is None:
            owner = "Drake framework (events, caches, C++ systems, loggers)"
        shares[owner] += n
    return {
        "loop_samples": loop,
        "share_percent": {k: round(100.0 * v / max(loop, 1), 1) for k, v in shares.most_common()},
    }


def profile_run(args) -> dict | None:
    """The per-system profile of a second scan, run under py-spy in a child process."""
    spy = shutil.which("py-spy") or str(Path(sys.executable).parent / "py-spy")
    if not Path(spy).exists():
        return {"skipped": "py-spy not installed"}
    with tempfile.TemporaryDirectory() as tmp:
        raw = Path(tmp) / "profile.txt"
        # PROFILE_RATE_HZ samples/s: unwinding native stacks stops the process for
        # milliseconds per sample; at 200/s a scan took 26 min under py-spy on an AMD EPYC
        # host (6.8 s unprofiled); at 100/s it takes about 40 s and gives about 4,000
        # samples in the loop (at 50/s: 10 s, but only 503 samples, shares +-2%).
        cmd = [
            spy,
            "record",
            "--native",
            "-r",
            str(PROFILE_RATE_HZ),
            "-f",
            "raw",
            "-o",
            str(raw),
            "--",
            sys.executable,
            "-m",
            "benchmarks",
            "scan",
            "--patient",
            args.patient,
            "--scenario",
            args.scenario,
            "--set",
            args.set,
            "--no-profile",
            "--no-reference",
        ]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0 or not raw.exists():
            return {"skipped": f"py-spy failed: {proc.stderr.strip()[-300:]}"}
        return summarise_profile(raw, _leaf_system_classes())


def cli_start_time(patient: str, scenario: str, overrides: str) -> dict:
    """Seconds from running ``drake-rus scan --patient P`` to its first simulated step (the
    progress bar's first line on stderr), in a fresh process; the run is then stopped."""
    exe = Path(sys.executable).parent / "drake-rus"
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [str(exe), "scan", "--patient", patient, "--scenario", scenario, "--out", tmp]
        if overrides and overrides != "{}":
            cmd += ["--set", overrides]
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        start = time.perf_counter()
        proc = subprocess.Popen(
            cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env, text=True, bufsize=1
        )
        first = None
        buffer = ""
        while True:
            ch = proc.stderr.read(1)
            if not ch:
                break
            buffer += ch
            # Stepping has begun: tqdm's bar shows the simulated time ("0.25/150"), or, off a
            # terminal, the first phase line ("scan: APPROACH at 0.0 sim s").
            if re.search(r"scan.*\d+\.\d+/\d+|scan: \w+ at [\d.]+ sim s", buffer[-200:]):
                first = time.perf_counter() - start
                break
        proc.kill()
        proc.wait()
    return {
        "cli_first_step_s": None if first is None else round(first, 2),
        "cli_stderr_tail": None if first is not None else buffer[-300:],
    }


def check_against_reference(row: dict, ref: dict) -> dict:
    """Issue 16's tolerances for one run against the 1 ms reference run."""

    def close(value, target, tol):
        return value is not None and abs(value - target) <= tol

    checks = {
        "explore_force": close(row["explore_mean_n"], FORCE_TARGET_N, FORCE_TOL_N)
        and row["explore_ripple_n"] is not None
        and row["explore_ripple_n"] <= FORCE_TOL_N,
        "pivot_force": close(row["pivot_mean_n"], FORCE_TARGET_N, FORCE_TOL_N)
        and row["pivot_ripple_n"] is not None
        and row["pivot_ripple_n"] <= FORCE_TOL_N,
        "landing_peak": row["landing_peak_n"] is not None
        and row["landing_peak_n"] < LANDING_PEAK_MAX_N,
        "e_trans": row["e_trans_mm"] is not None
        and ref["e_trans_mm"] is not None
        and abs(row["e_trans_mm"] - ref["e_trans_mm"]) <= E_TRANS_TOL_MM,
        "volume_ratio": row["volume_ratio"] is not None
        and ref["volume_ratio"] is not None
        and abs(row["volume_ratio"] - ref["volume_ratio"]) <= V_TOL,
        "status": row["status"] == ref["status"],
    }
    checks["all"] = all(checks.values())
    return checks


def parse_steps(text: str) -> list[float]:
    """The plant steps (s) of ``--steps``: comma-separated positive numbers; ValueError
    naming ``--steps`` otherwise."""
    try:
        steps = [float(s) for s in str(text).split(",")]
    except ValueError:
        steps = []
    if not steps or not all(math.isfinite(h) and h > 0.0 for h in steps):
        raise ValueError(
            f"--steps: expected comma-separated positive plant steps in s, got {text!r}"
        )
    return steps


def validate(args, base) -> dict:
    """Every step of ``--steps`` on every patient of ``--patients``, against the first step."""
    from drake_rus.scan import truth

    truth.FORCE_LOG_PERIOD = args.force_log_period  # fine enough for the landing peak
    steps = parse_steps(args.steps)
    rows = []
    verdict = {}
    for patient in args.patients.split(","):
        ref = None
        for step in steps:
            scenario = ApplyOverrides(base, f"{{contact: {{time_step: {step}}}}}")
            row = run_one(scenario, patient)
            row["load"] = os.getloadavg()[0]
            if ref is None:
                ref = row
            row["checks"] = check_against_reference(row, ref)
            if ref is not row:
                row["d_e_trans_mm"] = (
                    None
                    if row["e_trans_mm"] is None or ref["e_trans_mm"] is None
                    else round(row["e_trans_mm"] - ref["e_trans_mm"], 3)
                )
                row["d_volume_ratio"] = (
                    None
                    if row["volume_ratio"] is None or ref["volume_ratio"] is None
                    else round(row["volume_ratio"] - ref["volume_ratio"], 4)
                )
            print(dumps_strict(row), flush=True)
            rows.append(row)
            verdict.setdefault(step, []).append(row["checks"]["all"])
    return {
        "validate": rows,
        "steps_passing_all_patients": [s for s, ok in verdict.items() if all(ok)],
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks scan")
    parser.add_argument("--patient", default="test:0")
    parser.add_argument("--scenario", default="default")
    parser.add_argument("--set", default="{}", help="scenario overrides (YAML mapping)")
    parser.add_argument(
        "--no-profile",
        action="store_true",
        help="skip the per-system profile (a second run under py-spy)",
    )
    parser.add_argument(
        "--no-reference", action="store_true", help="skip the floor and free-station reference runs"
    )
    parser.add_argument(
        "--cli-start",
        action="store_true",
        help="also time `drake-rus scan` to its first simulated step",
    )
    parser.add_argument(
        "--validate",
        action="store_true",
        help="compare plant steps (--steps) on --patients with the first",
    )
    parser.add_argument("--steps", default="0.001,0.002,0.005,0.01")
    parser.add_argument("--patients", default="test:0,test:1,test:2")
    parser.add_argument("--force-log-period", type=float, default=0.005)
    parser.add_argument(
        "--repeat",
        type=int,
        default=1,
        help="run the scan this many times; report every run's rates and "
        "their median (the host's speed drifts between runs)",
    )
    args = parser.parse_args(argv)
    if args.repeat < 1:
        parser.error(f"--repeat: expected a whole number >= 1, got {args.repeat}")
    if not (math.isfinite(args.force_log_period) and args.force_log_period > 0.0):
        parser.error(f"--force-log-period: expected a positive number, got {args.force_log_period}")
    try:
        parse_steps(args.steps)
    except ValueError as e:
        parser.error(str(e))
    if not [p for p in args.patients.split(",") if p.strip()]:
        parser.error(f"--patients: expected comma-separated patient specs, got {args.patients!r}")
    base = ApplyOverrides(LoadScenario(scenario_name=args.scenario), args.set)
    load_before = os.getloadavg()
    if args.validate:
        out = validate(args, base)
        out["load_before"] = [round(x, 2) for x in load_before]
        out["load_after"] = [round(x, 2) for x in os.getloadavg()]
        print(dumps_strict(out))
        return 0
    out = {"scenario": args.scenario, "overrides": args.set, "time_step": base.contact.time_step}
    if not args.no_reference:
        floor = floor_rtf(base, 20.0)
        free = free_station_rtf(base, 20.0)
        out.update(
            {
                "rtf_floor": round(floor["rtf"], 3),
                "rtf_floor_cpu": round(floor["rtf_cpu"], 3),
                "rtf_free_station": round(free["rtf"], 3),
                "rtf_free_station_cpu": round(free["rtf_cpu"], 3),
            }
        )
    scan = run_one(base, args.patient)
    out.update(scan)
    if args.repeat > 1:
        runs = [scan] + [run_one(base, args.patient) for _ in range(args.repeat - 1)]
        for key in ("rtf_scan", "rtf_scan_cpu", "scan_cpu_s"):
            out[f"{key}_runs"] = [r[key] for r in runs]
            out[f"{key}_median"] = round(float(np.median(out[f"{key}_runs"])), 3)
    if not args.no_reference:
        out["ratio_scan_to_floor"] = round(scan["rtf_scan"] / out["rtf_floor"], 3)
        out["ratio_scan_to_floor_cpu"] = round(scan["rtf_scan_cpu"] / out["rtf_floor_cpu"], 3)
        out["ratio_scan_to_free_station"] = round(scan["rtf_scan"] / out["rtf_free_station"], 3)
    if args.cli_start:
        out.update(cli_start_time(args.patient, args.scenario, args.set))
    if not args.no_profile:
        out["profile"] = profile_run(args)
    out["load_before"] = [round(x, 2) for x in load_before]
    out["load_after"] = [round(x, 2) for x in os.getloadavg()]
    print(dumps_strict(out))
    return 0
