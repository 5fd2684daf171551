"""Tables (CSV), figures (PNG) and ``report.md`` of the seed's section III studies.

``write_*_outputs(out_dir, results)`` analyse a study's finished run results
(:mod:`drake_rus.experiments.analysis`) and write its tables, figure and analysis JSON to
``out_dir``; :func:`report_markdown` puts our numbers beside the seed paper's.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from drake_rus.batch import json_default
from drake_rus.experiments.analysis import (
    PAPER, STRATEGY_ORDER, analyze_efficiency, analyze_er_sweep, analyze_starts, mean_curve)
from drake_rus.io_utils import save_figure, write_text_atomic
from drake_rus.tables import write_csv_atomic

MODE_NOTE = "kinematic mode (planned probe poses, no robot dynamics)"


def plot_er_sweep(analysis: dict, path) -> Path:
    """Fig. 7d: E_trans and E_rot,x against ER, mean +- SD across patients."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    rows = analysis["rows"]
    er = np.array([r["er"] for r in rows]) * 100
    fig, axes = plt.subplots(2, 1, figsize=(6, 6), sharex=True)
    for ax, key, unit, paper in ((axes[0], "e_trans_mm", "mm", PAPER["er_sweep"]["e_trans_mm_at_60"]),
                                 (axes[1], "e_rot_x_deg", "deg",
                                  PAPER["er_sweep"]["e_rot_x_deg_at_60"])):
        m = np.array([r[f"{key}_mean"] for r in rows])
        s = np.array([r[f"{key}_sd"] for r in rows])
        ax.plot(er, m, "o-", label="ours (mean)")
        ax.fill_between(er, m - s, m + s, alpha=0.25, label="+- SD")
        ax.errorbar([60], [paper[0]], yerr=[paper[1]], fmt="s", color="k", capsize=4,
                    label="seed paper at ER 60%")
        ax.axvline(analysis["critical_er"] * 100, color="g", ls="--",
                   label=f"critical ER {analysis['critical_er'] * 100:.0f}%")
        ax.set_ylabel(f"{'E_trans' if unit == 'mm' else 'E_rot,x'} ({unit})")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    axes[1].set_xlabel("exploration ratio ER (%)")
    fig.suptitle(f"Localization vs exploration ratio (Fig. 7d), {MODE_NOTE}", fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_starts(results: list[dict], analysis: dict, path) -> Path:
    """Fig. 9d: box plots of both errors per random start."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    starts = [r["start"] for r in analysis["per_start"]]
    fig, axes = plt.subplots(2, 1, figsize=(6, 6), sharex=True)
    for ax, key, label in ((axes[0], "e_trans_mm", "E_trans (mm)"),
                           (axes[1], "e_rot_x_deg", "E_rot,x (deg)")):
        data = [[r[key] for r in results if r["start"] == s] for s in starts]
        ax.boxplot(data, tick_labels=[f"start {s + 1}" for s in starts])
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    er = results[0]["er"] if results else float("nan")
    fig.suptitle(f"Random exploration starts at ER {er * 100:.0f}% (Fig. 9d), {MODE_NOTE}; "
                 f"Bonferroni p < {analysis['bonferroni_threshold']:.4f}", fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path)


COLORS = {"OP": "tab:red", "GT-OP": "tab:green", "NOP": "tab:blue", "SL": "tab:orange"}


def plot_efficiency(results: list[dict], analysis: dict, path) -> Path:
    """Fig. 10e-h (+ volume error): mean V against n and eps, box plots of totals."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(2, 3, figsize=(13, 7.5))
    per = analysis["per_patient"]
    n_max = max([max(per[s]["n"]) for s in STRATEGY_ORDER if per[s]["n"]] + [2])
    e_max = max([max(per[s]["eps_mm"]) for s in STRATEGY_ORDER if per[s]["eps_mm"]] + [1.0])
    n_grid = np.linspace(1, n_max, 200)
    e_grid = np.linspace(0, e_max, 200)
    for s in STRATEGY_ORDER:
        axes[0, 0].plot(n_grid, mean_curve(results, s, "n", n_grid), color=COLORS[s], label=s)
        axes[0, 1].plot(e_grid, mean_curve(results, s, "eps", e_grid), color=COLORS[s], label=s)
    axes[0, 0].set(xlabel="US frame count n", ylabel="volume ratio V (mean)",
                   title="(e) V vs n")
    axes[0, 1].set(xlabel="imaging-window path length eps (mm)", ylabel="V (mean)",
                   title="(f) V vs eps")
    axes[0, 0].legend()
    for ax, key, label, title in ((axes[1, 0], "n", "total frames n", "(g) total n"),
                                  (axes[1, 1], "eps_mm", "total eps (mm)", "(h) total eps")):
        ax.boxplot([per[s][key] for s in STRATEGY_ORDER], tick_labels=list(STRATEGY_ORDER))
        ax.set_ylabel(label)
        ax.set_title(title)
    vol = [[v for v in per[s]["volume_error_pct"] if v is not None] for s in STRATEGY_ORDER]
    axes[1, 2].boxplot(vol, tick_labels=list(STRATEGY_ORDER))
    axes[1, 2].axhspan(-5, 5, color="g", alpha=0.1, label="+-5%")
    axes[1, 2].set(ylabel="reconstructed - true volume (%)", title="kidney volume error")
    axes[1, 2].legend(fontsize=7)
    # Per patient: OP's totals against NOP's and SL's.
    ax = axes[0, 2]
    x = np.arange(len(analysis["patients"]))
    for s in STRATEGY_ORDER:
        ax.plot(x, per[s]["eps_mm"], "o-", color=COLORS[s], label=s, ms=3)
    ax.set(xlabel="patient", ylabel="total eps (mm)", title="eps per patient")
    ax.set_xticks(x)
    ax.set_xticklabels([p.split(":")[-1] for p in analysis["patients"]], fontsize=7)
    for a in axes.ravel():
        a.grid(alpha=0.3)
    fig.suptitle(f"Sweep efficiency by strategy (Fig. 10e-h), pole to pole, {MODE_NOTE}",
                 fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path)


def write_er_sweep_outputs(out_dir, results) -> dict:
    out = Path(out_dir)
    analysis = analyze_er_sweep(results)
    write_csv_atomic(out / "er_sweep_runs.csv", [_flat(r) for r in results])
    write_csv_atomic(out / "er_sweep_table.csv", analysis["rows"])
    plot_er_sweep(analysis, out / "fig7d_er_sweep.png")
    write_text_atomic(out / "er_sweep.json", json.dumps(analysis, default=json_default, indent=1))
    return analysis


def write_starts_outputs(out_dir, results) -> dict:
    out = Path(out_dir)
    analysis = analyze_starts(results)
    write_csv_atomic(out / "starts_runs.csv", [_flat(r) for r in results])
    write_csv_atomic(out / "starts_tests.csv", analysis["tests"])
    plot_starts(results, analysis, out / "fig9d_starts.png")
    write_text_atomic(out / "starts.json", json.dumps(analysis, default=json_default, indent=1))
    return analysis


def write_efficiency_outputs(out_dir, results) -> dict:
    out = Path(out_dir)
    analysis = analyze_efficiency(results)
    rows = []
    for r in results:
        for s in STRATEGY_ORDER:
            e = r["strategies"][s]
            rows.append({"patient": r["patient"], "strategy": s, "n": e["n"],
                         "eps_mm": e["eps_mm"], "V": e["V"], "n_full": e["n_full"],
                         "eps_full_mm": e["eps_full_mm"], "volume_ml": e["volume_ml"],
                         "true_volume_ml": r["true_volume_ml"],
                         "volume_error_pct": e["volume_error_pct"],
                         "e_trans_mm": r["e_trans_mm"], "e_rot_x_deg": r["e_rot_x_deg"]})
    write_csv_atomic(out / "efficiency_runs.csv", rows)
    write_csv_atomic(out / "efficiency_tests.csv", analysis["comparisons"])
    plot_efficiency(results, analysis, out / "fig10_efficiency.png")
    write_text_atomic(out / "efficiency.json",
                      json.dumps({k: v for k, v in analysis.items() if k != "per_patient"},
                                 default=json_default, indent=1))
    return analysis


def _flat(r: dict) -> dict:
    keys = ("patient", "er", "start", "start_fraction", "x_offset_mm", "explore_frames",
            "explore_travel_mm", "points", "e_trans_mm", "e_rot_x_deg", "registration_ms",
            "iterations", "wall_s")
    return {k: r.get(k) for k in keys}


# ------------------------------------------------------------------------------- report
def _where(i: dict) -> str:
    if i.get("scheduler"):
        return f"Dask scheduler {i['scheduler']}"
    if not i.get("workers"):
        return "in one process"
    return f"embedded LocalCluster, {i['workers']} worker(s)"


def _runs(i: dict) -> str:
    if i.get("runs_done") is None:
        return "all runs; "
    return f"{i['runs_done']} runs run, {i['runs_skipped']} skipped; "


def _p(x):
    """A p-value: 4 decimals, or scientific notation below 1e-4."""
    if x is None or not np.isfinite(x):
        return "n/a"
    return f"{x:.4f}" if x >= 1e-4 else f"{x:.1e}"


def _f(x, nd=2):
    return "n/a" if x is None or (isinstance(x, float) and not np.isfinite(x)) else f"{x:.{nd}f}"


def report_markdown(meta: dict, er: dict | None, starts: dict | None, eff: dict | None,
                    closed: list | None = None) -> str:
    """report.md: our numbers beside the seed paper's for each table and figure."""
    L = ["# drake-rus studies: the seed paper's section III on our virtual cohort", "",
         f"- Patients: {', '.join(meta['patients'])} ({len(meta['patients'])})",
         f"- Mode: **{MODE_NOTE}** for every run of the tables and figures; "
         + (f"{len(closed)} closed-loop dynamic scan(s) only in the closed-loop check."
            if closed else "no closed-loop dynamic runs."),
         f"- Segmenter: {meta['segmenter']}; localization method: `{meta['method']}`; "
         f"label voxel {meta['voxel'] * 1e3:.0f} mm; study seed {meta['seed']}.",
         f"- Starts and efficiency ran at ER {meta.get('er', float('nan')) * 100:.0f}% (the "
         f"critical ER of this sweep when it ran).", "- Wall time per invocation (resumed "
         "invocations skip finished runs): " + "; ".join(
             f"{i['wall_s']:.0f} s ({_runs(i)}{_where(i)}; stages "
             + ", ".join(f"{k} {v:.0f} s" for k, v in (i.get("stage_wall_s") or {}).items())
             + ")"
             for i in meta.get("invocations", [meta])), ""]
    if er is not None:
        p = PAPER["er_sweep"]
        L += ["## Exploration ratio vs localization (Fig. 7d, `fig7d_er_sweep.png`)", "",
              "| ER | E_trans (mm) | E_rot,x (deg) | p (E_trans vs 100%) | p (E_rot,x vs 100%) |",
              "|---|---|---|---|---|"]
        for r in er["rows"]:
            L.append(f"| {r['er'] * 100:.0f}% | {_f(r['e_trans_mm_mean'])} +- "
                     f"{_f(r['e_trans_mm_sd'])} | {_f(r['e_rot_x_deg_mean'])} +- "
                     f"{_f(r['e_rot_x_deg_sd'])} | {_p(r['p_e_trans'])} | "
                     f"{_p(r['p_e_rot_x'])} |")
        row60 = next((r for r in er["rows"] if abs(r["er"] - 0.6) < 1e-6), None)
        L += ["", f"Critical ER (smallest ER from which on no ER differs from 100% at p > 0.05 "
              f"in either error): **ours {er['critical_er'] * 100:.0f}%**, paper "
              f"{p['critical_er'] * 100:.0f}% (p = {p['p_e_trans_at_60']} and "
              f"{p['p_e_rot_at_60']} at 60%). First ER with both p > 0.05: "
              f"{er['first_not_significant_er'] * 100:.0f}%."]
        if row60:
            L.append(f"At ER 60%: ours {_f(row60['e_trans_mm_mean'])} +- "
                     f"{_f(row60['e_trans_mm_sd'])} mm, {_f(row60['e_rot_x_deg_mean'])} +- "
                     f"{_f(row60['e_rot_x_deg_sd'])} deg; paper {p['e_trans_mm_at_60'][0]} +- "
                     f"{p['e_trans_mm_at_60'][1]} mm, {p['e_rot_x_deg_at_60'][0]} +- "
                     f"{p['e_rot_x_deg_at_60'][1]} deg.")
        L.append("")
    if starts is not None:
        pl = PAPER["localization"]
        L += ["## Random exploration starts (Fig. 9d, `fig9d_starts.png`)", "",
              f"All runs: E_trans {_f(starts['e_trans_mm'][0])} +- {_f(starts['e_trans_mm'][1])}"
              f" mm, E_rot,x {_f(starts['e_rot_x_deg'][0])} +- {_f(starts['e_rot_x_deg'][1])} "
              f"deg (paper, 15 patients x 5 starts: {pl['e_trans_mm'][0]} +- "
              f"{pl['e_trans_mm'][1]} mm, {pl['e_rot_x_deg'][0]} +- {pl['e_rot_x_deg'][1]} deg).",
              "", "| start | E_trans (mm) | E_rot,x (deg) |", "|---|---|---|"]
        for r in starts["per_start"]:
            L.append(f"| {r['start'] + 1} | {_f(r['e_trans_mm_mean'])} +- {_f(r['e_trans_mm_sd'])}"
                     f" | {_f(r['e_rot_x_deg_mean'])} +- {_f(r['e_rot_x_deg_sd'])} |")
        n_sig = sum(t["significant_e_trans_mm"] + t["significant_e_rot_x_deg"]
                    for t in starts["tests"])
        pmin = min([min(t["p_e_trans_mm"], t["p_e_rot_x_deg"]) for t in starts["tests"]]
                   or [float("nan")])
        L += ["", f"Pairwise paired t-tests ({len(starts['tests'])} pairs x 2 errors, "
              f"Bonferroni threshold p < {starts['bonferroni_threshold']:.4f}): "
              f"**{n_sig} significant** (smallest p = {_p(pmin)}). Paper: "
              f"{PAPER['starts']}.", ""]
    if eff is not None:
        s = eff["summary"]
        pe = PAPER["efficiency"]
        L += ["## Sweep efficiency (Fig. 10, `fig10_efficiency.png`)", "",
              "Pole to pole (from the first to the last frame showing the kidney; for a pivot, "
              "its second leg, which runs from one pole to the other).", "",
              "| strategy | n | eps (mm) | V | volume error (%) | abs volume error (%) |",
              "|---|---|---|---|---|---|"]
        for k in STRATEGY_ORDER:
            L.append(f"| {k} | {_f(s[k]['n'][0], 1)} +- {_f(s[k]['n'][1], 1)} | "
                     f"{_f(s[k]['eps_mm'][0], 1)} +- {_f(s[k]['eps_mm'][1], 1)} | "
                     f"{_f(s[k]['V'][0], 3)} | {_f(s[k]['volume_error_pct'][0])} +- "
                     f"{_f(s[k]['volume_error_pct'][1])} | "
                     f"{_f(s[k]['abs_volume_error_pct'][0])} (within 5%: "
                     f"{s[k]['within_5pct']}/{len(eff['patients'])}) |")
        L += ["", "| comparison | metric | reduction by OP (mean +- SD) | OP lower on | p | "
              "significant (Bonferroni) |", "|---|---|---|---|---|---|"]
        for c in eff["comparisons"]:
            unit = " mm" if c["metric"] == "eps_mm" else " frames"
            L.append(f"| {c['comparison']} | {c['metric']} | {_f(c['reduction_mean'], 1)} +- "
                     f"{_f(c['reduction_sd'], 1)}{unit} | {c['op_lower_count']}/{c['patients']} | "
                     f"{_p(c['p'])} | {c['significant']} |")
        L += ["", f"Paper (simulation, 15 patients): OP reduced eps by {pe['eps_reduction_vs_SL_mm'][0]}"
              f" +- {pe['eps_reduction_vs_SL_mm'][1]} mm against SL and by "
              f"{pe['eps_reduction_vs_NOP_mm'][0]} +- {pe['eps_reduction_vs_NOP_mm'][1]} mm "
              f"against NOP; localization error cost {pe['eps_extra_vs_GT_OP_mm'][0]} +- "
              f"{pe['eps_extra_vs_GT_OP_mm'][1]} mm against GT-OP. Volume: "
              f"{PAPER['volume_loa']}; our target: GT-OP within 5%.", ""]
    if closed:
        L += ["## Closed-loop check (a few dynamic scans beside their kinematic twins)", "",
              "Same patient, start (10% into the E-ROI), ER, segmenter and localization; "
              "n, eps and V over both pivot legs (as the scan's `ScanMetrics` counts them).", "",
              "| patient | mode | status | E_trans (mm) | E_rot,x (deg) | n | eps (mm) | V | "
              "wall (s) |", "|---|---|---|---|---|---|---|---|---|"]
        for r in closed:
            c, k = r["closed_loop"], r["kinematic"]
            L.append(f"| {r['patient']} | closed-loop | {c['status']} | {_f(c['e_trans_mm'])} | "
                     f"{_f(c['e_rot_x_deg'])} | {c['n']} | {_f(c['eps_mm'], 1)} | "
                     f"{_f(c['V'], 3)} | {_f(c['wall_s'], 0)} (sim {_f(c['sim_s'], 1)} s) |")
            L.append(f"| {r['patient']} | kinematic | - | {_f(k['e_trans_mm'])} | "
                     f"{_f(k['e_rot_x_deg'])} | {k['n']} | {_f(k['eps_mm'], 1)} | "
                     f"{_f(k['V'], 3)} | {_f(k['wall_s'], 0)} |")
        L.append("")
    L += ["## Method notes", "",
          "- Kinematic runs place the probe exactly where the controller laws ask (eq. 17 "
          "exploration, eq. 20-23 pivot), tip on the skin surface; no contact dynamics, "
          "tracking error or tissue compression.",
          "- Exploration starts at the E-ROI's superior end (ER sweep, efficiency) or at a "
          "seeded random point inside the E-ROI (starts). ER 0% uses the initial alignment "
          "alone (heuristic rotation, centroid under the start point).",
          "- NOP uses the true kidney pose (the in-vivo NOP was expert-placed); OP the "
          "registered pose; SL is the exploration controller over the whole kidney.",
          "- V (eq. 25): fraction of the true kidney's 2 mm voxels inside the fan and the "
          "elevational slab of at least one frame (`drake_rus/metrics/core.py`).",
          "- Kidney volume: masks compounded at 1 mm (nearest-pixel, fan clipping, hole "
          "filling), threshold 0.5, against the kidney mesh's volume.", ""]
    return "\n".join(L)


def write_closed_loop_outputs(out_dir, results) -> Path:
    """closed_loop.csv: each closed-loop scan beside its kinematic twin."""
    rows = []
    for r in results:
        for mode in ("closed_loop", "kinematic"):
            e = r[mode]
            rows.append({"patient": r["patient"], "mode": mode, "er": r["er"],
                         "status": e.get("status", ""), "e_trans_mm": e["e_trans_mm"],
                         "e_rot_x_deg": e["e_rot_x_deg"], "n": e["n"], "eps_mm": e["eps_mm"],
                         "V": e["V"], "wall_s": e["wall_s"], "sim_s": e.get("sim_s")})
    return write_csv_atomic(Path(out_dir) / "closed_loop.csv", rows)
