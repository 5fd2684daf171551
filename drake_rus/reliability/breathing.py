"""Localisation under breathing: the same scans with breathing off, breathing with every
exploration frame used, and breathing with exploration frames gated to breath-holds.

The kidney moves craniocaudally by d(t) (``patient.motion.breathing``); holds are at
end-expiration (within ``hold_reproducibility``), which is also the reference pose the
error is measured against. Gating (``gate_exploration``) makes the point-cloud accumulator
keep only frames acquired during a hold, so the registration sees a still kidney.

Each run's task holds every parameter that changes it (patient, condition, amplitude, rate,
hold period and duration, scenario and its resolved YAML's SHA-256, seed, time limit), and a
rerun reuses a stored run only when its task is the same (:mod:`drake_rus.batch`): a run
with ``--rate 15`` never takes one stored by ``--rate 10``.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
from pathlib import Path

import numpy as np
from pydrake.common.yaml import yaml_dump_typed
from tqdm import tqdm

from drake_rus.anatomy.motion import BreathingConfig
from drake_rus.io_utils import save_figure, write_text_atomic
from drake_rus.provenance import Provenance
from drake_rus.reliability.campaign import run_campaign
from drake_rus.scenario import DEFAULT_SCENARIOS_FILE, LoadScenario

CONDITIONS = {
    "no_breathing": "{}",
    "breathing_ungated": "{patient: {motion: {breathing: {enabled: true, amplitude: %(a).4f, "
    "rate_per_min: %(r).1f, hold_period: %(p).1f, hold_duration: %(h).1f, "
    "gate_exploration: false}}}}",
    "breathing_gated": "{patient: {motion: {breathing: {enabled: true, amplitude: %(a).4f, "
    "rate_per_min: %(r).1f, hold_period: %(p).1f, hold_duration: %(h).1f, "
    "gate_exploration: true}}}}",
}


def _bounds(name: str) -> tuple[float | None, float | None]:
    """(min, max) of a BreathingConfig field (its schema metadata)."""
    f = next(f for f in dataclasses.fields(BreathingConfig) if f.name == name)
    return f.metadata.get("min"), f.metadata.get("max")


def check_breathing_arguments(
    amplitude: float, rate_per_min: float, hold_period: float, hold_duration: float
) -> None:
    """Raises ValueError naming the command-line argument unless the breathing parameters
    can exist: amplitude and rate within the scenario schema's ranges
    (``patient.motion.breathing``), a positive hold period and a hold shorter than it
    (the gated condition explores only during holds)."""
    lo, hi = _bounds("amplitude")
    if not (math.isfinite(amplitude) and max(lo, 0.0) < amplitude <= hi):
        raise ValueError(f"--amplitude: expected 0 < amplitude <= {hi:g} m, got {amplitude}")
    lo, hi = _bounds("rate_per_min")
    if not (math.isfinite(rate_per_min) and lo <= rate_per_min <= hi):
        raise ValueError(
            f"--rate: expected {lo:g}-{hi:g} breaths/min "
            f"(patient.motion.breathing.rate_per_min), got {rate_per_min}"
        )
    if not (math.isfinite(hold_period) and hold_period > 0):
        raise ValueError(f"--hold-period: expected a positive time in s, got {hold_period}")
    if not (math.isfinite(hold_duration) and 0 < hold_duration < hold_period):
        raise ValueError(
            f"--hold-duration: expected 0 < duration < --hold-period "
            f"({hold_period:g} s), got {hold_duration}"
        )


def _scenario_sha256(scenario: str, overrides: str) -> str:
    """SHA-256 of the resolved scenario (YAML) a breathing run loads."""
    sc = LoadScenario(
        filename=DEFAULT_SCENARIOS_FILE, scenario_name=scenario, scenario_text=overrides
    )
    return hashlib.sha256(yaml_dump_typed(sc).encode()).hexdigest()


def breathing_tasks(
    patients: list[str],
    *,
    amplitude=0.010,
    rate_per_min=15.0,
    hold_period=8.0,
    hold_duration=4.0,
    scenario="quick",
    max_sim_time=60.0,
) -> list[dict]:
    """Three runs per patient (:data:`CONDITIONS`), each task with every parameter that
    changes it, its resolved scenario's SHA-256 included (so a stored run is reused only
    with the same parameters)."""
    params = {"a": amplitude, "r": rate_per_min, "p": hold_period, "h": hold_duration}
    digests = {name: _scenario_sha256(scenario, text % params) for name, text in CONDITIONS.items()}
    tasks = []
    for i, spec in enumerate(patients):
        for name, text in CONDITIONS.items():
            tasks.append(
                {
                    "run_id": f"{spec.replace(':', '')}_{name}",
                    "index": i,
                    "fault": name,
                    "patient": spec,
                    "scenario": scenario,
                    "scenarios_file": None,
                    "overrides": text % params,
                    "amplitude": float(amplitude),
                    "rate_per_min": float(rate_per_min),
                    "hold_period": float(hold_period),
                    "hold_duration": float(hold_duration),
                    "scenario_sha256": digests[name],
                    "random_seed": i,
                    "max_sim_time": max_sim_time,
                }
            )
    return tasks


def compare(results: list[dict]) -> dict:
    """Per condition: runs, DONE count, translation errors (mm), their mean and maximum, and
    how far each patient's error moved from its no-breathing error (|delta E_trans|, mm: a
    lower bound of how far breathing moved the estimate)."""
    baseline = {
        r["patient"]: r["e_trans_mm"]
        for r in results
        if r["fault"] == "no_breathing" and r.get("e_trans_mm") is not None
    }
    out = {}
    for name in CONDITIONS:
        rs = [r for r in results if r["fault"] == name]
        errs = [r["e_trans_mm"] for r in rs if r.get("e_trans_mm") is not None]
        change = [
            abs(r["e_trans_mm"] - baseline[r["patient"]])
            for r in rs
            if r.get("e_trans_mm") is not None and r["patient"] in baseline
        ]
        out[name] = {
            "runs": len(rs),
            "done": sum(r["status"] == "DONE" for r in rs),
            "e_trans_mm": errs,
            "mean_e_trans_mm": float(np.mean(errs)) if errs else None,
            "max_e_trans_mm": float(np.max(errs)) if errs else None,
            "mean_abs_change_mm": float(np.mean(change)) if change else None,
            "max_abs_change_mm": float(np.max(change)) if change else None,
        }
    return out


def plot_comparison(results: list[dict], path) -> Path:
    """breathing.png: E_trans per patient under each condition (filled: DONE, open: ABORT)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    patients = sorted({r["patient"] for r in results}, key=lambda p: (len(p), p))
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for k, name in enumerate(CONDITIONS):
        for r in results:
            if r["fault"] != name or r.get("e_trans_mm") is None:
                continue
            x = patients.index(r["patient"]) + (k - 1) * 0.22
            done = r["status"] == "DONE"
            ax.scatter(
                x, r["e_trans_mm"], s=40, color=f"C{k}", facecolors=f"C{k}" if done else "none"
            )
    ax.set_xticks(range(len(patients)), patients)
    ax.set_ylabel("localisation error E_trans (mm)")
    ax.set_title(
        "Localisation with breathing: off / all frames / breath-hold gated\n"
        "(open markers: the scan ended in ABORT)"
    )
    ax.legend(
        [Line2D([], [], ls="", marker="o", color=f"C{k}") for k in range(len(CONDITIONS))],
        list(CONDITIONS),
        fontsize=8,
    )
    ax.grid(axis="y", alpha=0.3)
    return save_figure(fig, path)


def add_commands(subparsers) -> None:
    p = subparsers.add_parser(
        "breathing",
        help="localisation error with breathing off / on / gated to breath-holds",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--patients",
        default="test:0,test:1",
        help="comma-separated patient specs (default test:0,test:1)",
    )
    p.add_argument("--out", required=True, help="output directory (resumable)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument(
        "--amplitude", type=float, default=0.010, help="craniocaudal amplitude in m (default 0.010)"
    )
    p.add_argument("--rate", type=float, default=15.0, help="breaths/min (default 15)")
    p.add_argument(
        "--hold-period",
        type=float,
        default=8.0,
        help="a breath-hold starts every this many s (default 8)",
    )
    p.add_argument(
        "--hold-duration", type=float, default=4.0, help="breath-hold length in s (default 4)"
    )
    p.set_defaults(func=run_breathing_command)


def run_breathing_command(args) -> int:
    patients = [s.strip() for s in args.patients.split(",") if s.strip()]
    if not patients:
        raise ValueError("--patients: expected at least one patient spec")
    check_breathing_arguments(args.amplitude, args.rate, args.hold_period, args.hold_duration)
    if args.workers < 0:
        raise ValueError(f"--workers: expected 0 or more, got {args.workers}")
    tasks = breathing_tasks(
        patients,
        amplitude=args.amplitude,
        rate_per_min=args.rate,
        hold_period=args.hold_period,
        hold_duration=args.hold_duration,
    )
    results = run_campaign(
        tasks,
        args.out,
        workers=args.workers,
        progress=lambda r: tqdm.write(
            f"{r['run_id']}: {r['status']} e_trans {r.get('e_trans_mm')}"
        ),
    )
    table = compare(results)
    # The parameters as the runs themselves record them (their tasks).
    ran = {
        k: sorted({r["task"].get(k) for r in results if "task" in r}, key=str)
        for k in ("amplitude", "rate_per_min", "hold_period", "hold_duration")
    }
    write_text_atomic(
        Path(args.out) / "breathing.json",
        json.dumps(
            {
                "conditions": table,
                "amplitude_m": args.amplitude,
                "rate_per_min": args.rate,
                "hold_period_s": args.hold_period,
                "hold_duration_s": args.hold_duration,
                "patients": patients,
                "runs_recorded": ran,
                "provenance": Provenance(
                    LoadScenario(
                        filename=DEFAULT_SCENARIOS_FILE, scenario_name=tasks[0]["scenario"]
                    ),
                    scenario_name=tasks[0]["scenario"],
                    scenarios_file=str(DEFAULT_SCENARIOS_FILE),
                    overrides="per run: each run's task.overrides",
                    seeds={t["run_id"]: t["random_seed"] for t in tasks},
                ),
            },
            indent=1,
        ),
    )
    if results:
        plot_comparison(results, Path(args.out) / "breathing.png")
    print(
        f"{'condition':<20} {'runs':>4} {'DONE':>4} {'mean E_trans [mm]':>18} "
        f"{'mean/max |dE| vs off [mm]':>26}  per patient"
    )
    for name, row in table.items():
        mean = "-" if row["mean_e_trans_mm"] is None else f"{row['mean_e_trans_mm']:.2f}"
        change = (
            "-"
            if row["mean_abs_change_mm"] is None
            else f"{row['mean_abs_change_mm']:.2f} / {row['max_abs_change_mm']:.2f}"
        )
        print(
            f"{name:<20} {row['runs']:>4} {row['done']:>4} {mean:>18} {change:>26}  "
            f"{[round(e, 2) for e in row['e_trans_mm']]}"
        )
    print(json.dumps({k: v["mean_e_trans_mm"] for k, v in table.items()}))
    return 0
