"""Localisation under breathing: the same scans with breathing off, breathing with every
exploration frame used, and breathing with exploration frames gated to breath-holds.

The kidney moves craniocaudally by d(t) (``patient.motion.breathing``); holds are at
end-expiration (within ``hold_reproducibility``), which is also the reference pose the
error is measured against. Gating (``gate_exploration``) makes the point-cloud accumulator
keep only frames acquired during a hold, so the registration sees a still kidney.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from tqdm import tqdm

from drake_rus.io_utils import save_figure, write_text_atomic
from drake_rus.reliability.campaign import run_campaign

CONDITIONS = {
    "no_breathing": "{}",
    "breathing_ungated": "{patient: {motion: {breathing: {enabled: true, amplitude: %(a).4f, "
                         "rate_per_min: %(r).1f, hold_period: %(p).1f, hold_duration: %(h).1f, "
                         "gate_exploration: false}}}}",
    "breathing_gated": "{patient: {motion: {breathing: {enabled: true, amplitude: %(a).4f, "
                       "rate_per_min: %(r).1f, hold_period: %(p).1f, hold_duration: %(h).1f, "
                       "gate_exploration: true}}}}",
}


def breathing_tasks(patients: list[str], *, amplitude=0.010, rate_per_min=15.0,
                    hold_period=8.0, hold_duration=4.0, scenario="quick",
                    max_sim_time=60.0) -> list[dict]:
    params = {"a": amplitude, "r": rate_per_min, "p": hold_period, "h": hold_duration}
    tasks = []
    for i, spec in enumerate(patients):
        for name, text in CONDITIONS.items():
            tasks.append({"run_id": f"{spec.replace(':', '')}_{name}", "index": i,
                          "fault": name, "patient": spec, "scenario": scenario,
                          "scenarios_file": None, "overrides": text % params,
                          "random_seed": i, "max_sim_time": max_sim_time})
    return tasks


def compare(results: list[dict]) -> dict:
    """Per condition: runs, DONE count, translation errors (mm), their mean and maximum, and
    how far each patient's error moved from its no-breathing error (|delta E_trans|, mm: a
    lower bound of how far breathing moved the estimate)."""
    baseline = {r["patient"]: r["e_trans_mm"] for r in results
                if r["fault"] == "no_breathing" and r.get("e_trans_mm") is not None}
    out = {}
    for name in CONDITIONS:
        rs = [r for r in results if r["fault"] == name]
        errs = [r["e_trans_mm"] for r in rs if r.get("e_trans_mm") is not None]
        change = [abs(r["e_trans_mm"] - baseline[r["patient"]]) for r in rs
                  if r.get("e_trans_mm") is not None and r["patient"] in baseline]
        out[name] = {"runs": len(rs), "done": sum(r["status"] == "DONE" for r in rs),
                     "e_trans_mm": errs,
                     "mean_e_trans_mm": float(np.mean(errs)) if errs else None,
                     "max_e_trans_mm": float(np.max(errs)) if errs else None,
                     "mean_abs_change_mm": float(np.mean(change)) if change else None,
                     "max_abs_change_mm": float(np.max(change)) if change else None}
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
            ax.scatter(x, r["e_trans_mm"], s=40, color=f"C{k}",
                       facecolors=f"C{k}" if done else "none")
    ax.set_xticks(range(len(patients)), patients)
    ax.set_ylabel("localisation error E_trans (mm)")
    ax.set_title("Localisation with breathing: off / all frames / breath-hold gated\n"
                 "(open markers: the scan ended in ABORT)")
    ax.legend([Line2D([], [], ls="", marker="o", color=f"C{k}") for k in range(len(CONDITIONS))],
              list(CONDITIONS), fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    return save_figure(fig, path)


def add_commands(subparsers) -> None:
    p = subparsers.add_parser(
        "breathing", help="localisation error with breathing off / on / gated to breath-holds",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--patients", default="test:0,test:1",
                   help="comma-separated patient specs (default test:0,test:1)")
    p.add_argument("--out", required=True, help="output directory (resumable)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--amplitude", type=float, default=0.010,
                   help="craniocaudal amplitude in m (default 0.010)")
    p.add_argument("--rate", type=float, default=15.0, help="breaths/min (default 15)")
    p.add_argument("--hold-period", type=float, default=8.0,
                   help="a breath-hold starts every this many s (default 8)")
    p.add_argument("--hold-duration", type=float, default=4.0,
                   help="breath-hold length in s (default 4)")
    p.set_defaults(func=run_breathing_command)


def run_breathing_command(args) -> int:
    patients = [s.strip() for s in args.patients.split(",") if s.strip()]
    if not patients:
        raise ValueError("--patients: expected at least one patient spec")
    if not 0.0 < args.amplitude <= 0.03:
        raise ValueError(f"--amplitude: expected 0 < amplitude <= 0.03 m, got {args.amplitude}")
    if args.workers < 0:
        raise ValueError(f"--workers: expected 0 or more, got {args.workers}")
    tasks = breathing_tasks(patients, amplitude=args.amplitude, rate_per_min=args.rate,
                            hold_period=args.hold_period, hold_duration=args.hold_duration)
    results = run_campaign(tasks, args.out, workers=args.workers,
                           progress=lambda r: tqdm.write(f"{r['run_id']}: {r['status']} "
                                                         f"e_trans {r.get('e_trans_mm')}"))
    table = compare(results)
    write_text_atomic(Path(args.out) / "breathing.json", json.dumps(
        {"conditions": table, "amplitude_m": args.amplitude, "rate_per_min": args.rate,
         "hold_period_s": args.hold_period, "hold_duration_s": args.hold_duration,
         "patients": patients}, indent=1))
    if results:
        plot_comparison(results, Path(args.out) / "breathing.png")
    print(f"{'condition':<20} {'runs':>4} {'DONE':>4} {'mean E_trans [mm]':>18} "
          f"{'mean/max |dE| vs off [mm]':>26}  per patient")
    for name, row in table.items():
        mean = "-" if row["mean_e_trans_mm"] is None else f"{row['mean_e_trans_mm']:.2f}"
        change = ("-" if row["mean_abs_change_mm"] is None else
                  f"{row['mean_abs_change_mm']:.2f} / {row['max_abs_change_mm']:.2f}")
        print(f"{name:<20} {row['runs']:>4} {row['done']:>4} {mean:>18} {change:>26}  "
              f"{[round(e, 2) for e in row['e_trans_mm']]}")
    print(json.dumps({k: v["mean_e_trans_mm"] for k, v in table.items()}))
    return 0
