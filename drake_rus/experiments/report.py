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
    ALL_LOCALIZED_TEXT,
    CRITICAL_ER_RULES,
    CT_GROUP,
    DEFAULT_MARGINS,
    PAPER,
    PAPER_PATIENTS,
    STRATEGY_ORDER,
    analyze_efficiency,
    analyze_er_sweep,
    analyze_starts,
    analyze_template,
    critical_evidence_row,
    group_kind,
    mean_curve,
    paired_t_power,
    sample_size_warning,
    template_group,
)
from drake_rus.experiments.specs import (
    CLOSED_LOOP_STRATEGY_HOW,
    ER_UNIT_TEXT,
    PATIENT_KINDS,
    SEGMENTER_TEXT,
    STRATEGY_TEXT,
)
from drake_rus.io_utils import save_figure, write_text_atomic
from drake_rus.metrics.sweep import MATCHED_V, POLE_TO_POLE, WHOLE_PIVOT
from drake_rus.tables import write_csv_atomic

MODE_NOTE = "kinematic mode (planned probe poses, no robot dynamics)"
KINEMATIC = "kinematic twin (planned probe poses, no robot dynamics)"
CLOSED_LOOP = "closed loop (Drake diagram: MultibodyPlant, controller, contact)"


def segmenter_label(name) -> str:
    """A segmenter as every table and figure names it: ``oracle`` is said to be the label
    volume's kidney labels, not a segmenter the product ships."""
    return f"`{name}` ({SEGMENTER_TEXT[name]})" if name in SEGMENTER_TEXT else f"`{name}`"


def template_label(meta: dict) -> str:
    """The registration template of a study's runs (their ``template`` record), for
    people."""
    t = meta.get("template") or {}
    return t.get("label") or "generated (the shipped template)"


def figure_note(settings: dict | None, template: dict | None = None) -> str:
    """The second line of a figure's title: segmenter (the oracle named as such),
    template, patients' kind."""
    settings = settings or {}
    seg = settings.get("segmenter")
    parts = []
    if seg:
        parts.append(
            "segmenter: ORACLE (label volume's kidney labels)"
            if seg == "oracle"
            else f"segmenter: {seg}"
        )
    parts.append(f"template: {(template or {}).get('label') or 'generated'}")
    kind = settings.get("patient_kind")
    if kind in PATIENT_KINDS:
        parts.append(f"patients: {PATIENT_KINDS[kind]}")
    return "; ".join(parts)


def provenance(
    meta: dict,
    *,
    mode: str = KINEMATIC,
    definition: str | None = None,
    er_unit: str | None = None,
    extra: str = "",
) -> str:
    """The line under every table and figure of report.md saying what produced it: mode,
    registration method, segmenter (the oracle named as such), template, patients' kind,
    ER unit and (for sweep costs) the metric definition."""
    unit = er_unit or meta.get("er_unit", "fixed")
    parts = [
        f"mode: {mode}",
        f"registration: `{meta.get('method', '?')}`",
        f"segmenter: {segmenter_label(meta.get('segmenter', '?'))}",
        f"template: {template_label(meta)}",
        f"ER unit: {ER_UNIT_TEXT.get(unit, unit)}",
    ]
    kinds = meta.get("patient_kinds")
    if kinds:
        parts.insert(4, "patients: " + ", ".join(f"{k}: {n}" for k, n in kinds.items()))
    if definition:
        parts.append(f"metric: {definition}")
    if extra:
        parts.append(extra)
    return "*Produced by " + "; ".join(parts) + ".*"


def _strategies(analysis: dict) -> list:
    """The strategies an efficiency analysis holds, in the report's order."""
    return [k for k in STRATEGY_ORDER if k in analysis["summary"]]


def plot_er_sweep(analysis: dict, path, mode: str = MODE_NOTE, note: str = "") -> Path:
    """Fig. 7d: E_trans and E_rot,x against ER, mean +- SD across patients."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = analysis["rows"]
    er = np.array([r["er"] for r in rows]) * 100
    fig, axes = plt.subplots(2, 1, figsize=(6, 6), sharex=True)
    for ax, key, unit, paper in (
        (axes[0], "e_trans_mm", "mm", PAPER["er_sweep"]["e_trans_mm_at_60"]),
        (axes[1], "e_rot_x_deg", "deg", PAPER["er_sweep"]["e_rot_x_deg_at_60"]),
    ):
        m = np.array([r[f"{key}_mean"] for r in rows])
        s = np.array([r[f"{key}_sd"] for r in rows])
        ax.plot(er, m, "o-", label="ours (mean)")
        ax.fill_between(er, m - s, m + s, alpha=0.25, label="+- SD")
        ax.errorbar(
            [60],
            [paper[0]],
            yerr=[paper[1]],
            fmt="s",
            color="k",
            capsize=4,
            label="seed paper at ER 60%",
        )
        if analysis["critical_er"] is not None:
            ax.axvline(
                analysis["critical_er"] * 100,
                color="g",
                ls="--",
                label=f"critical ER {analysis['critical_er'] * 100:.0f}% "
                f"({analysis.get('rule', 'strict')} rule, n = "
                f"{analysis.get('patients', '?')})",
            )
        if analysis.get("equivalence_er") is not None:
            margin = (analysis.get("margins") or {}).get(key)
            ax.axvline(
                analysis["equivalence_er"] * 100,
                color="m",
                ls=":",
                label=f"equivalent to ER 100% within +-{margin:g} {unit} (TOST) from "
                f"{analysis['equivalence_er'] * 100:.0f}%",
            )
        ax.set_ylabel(f"{'E_trans' if unit == 'mm' else 'E_rot,x'} ({unit})")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    unit = analysis.get("er_unit")
    axes[1].set_xlabel(
        "exploration ratio ER (% of "
        + (
            "the patient's kidney length"
            if unit == "kidney"
            else "L_m = 100 mm"
            if unit == "fixed"
            else "?"
        )
        + ")"
    )
    fig.suptitle(
        f"Localization vs exploration ratio (Fig. 7d), {mode}" + (f"\n{note}" if note else ""),
        fontsize=8,
    )
    fig.tight_layout()
    return save_figure(fig, path)


def plot_starts(
    results: list[dict], analysis: dict, path, mode: str = MODE_NOTE, note: str = ""
) -> Path:
    """Fig. 9d: box plots of both errors per random start."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    starts = [r["start"] for r in analysis["per_start"]]
    fig, axes = plt.subplots(2, 1, figsize=(6, 6), sharex=True)
    for ax, key, label in (
        (axes[0], "e_trans_mm", "E_trans (mm)"),
        (axes[1], "e_rot_x_deg", "E_rot,x (deg)"),
    ):
        data = [[r[key] for r in results if r["start"] == s] for s in starts]
        ax.boxplot(data, tick_labels=[f"start {s + 1}" for s in starts])
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    er = results[0]["er"] if results else float("nan")
    fig.suptitle(
        f"Random exploration starts at ER {er * 100:.0f}% (Fig. 9d), {mode}; "
        f"Bonferroni p < {analysis['bonferroni_threshold']:.4f}" + (f"\n{note}" if note else ""),
        fontsize=8,
    )
    fig.tight_layout()
    return save_figure(fig, path)


COLORS = {
    "OP": "tab:red",
    "GT-OP": "tab:green",
    "NOP": "tab:blue",
    "SL": "tab:orange",
    "OP-PE": "tab:purple",
}
# The figure's legend: each strategy with the pose its sweep used.
POSE_LABEL = {
    "OP": "registered T*",
    "GT-OP": "true T*",
    "NOP": "true pose, transverse",
    "SL": "line",
    "OP-PE": "registered T*, predicted end",
}


def plot_efficiency(
    results: list[dict], analysis: dict, path, mode: str = MODE_NOTE, note: str = ""
) -> Path:
    """Fig. 10e-h (+ volume error): mean V against n and eps, box plots of totals."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(13, 7.5))
    per = analysis["per_patient"]
    order = _strategies(analysis)
    n_max = max([max(per[s]["n"]) for s in order if per[s]["n"]] + [2])
    e_max = max([max(per[s]["eps_mm"]) for s in order if per[s]["eps_mm"]] + [1.0])
    n_grid = np.linspace(1, n_max, 200)
    e_grid = np.linspace(0, e_max, 200)
    for s in order:
        label = f"{s} ({POSE_LABEL[s]})"
        axes[0, 0].plot(n_grid, mean_curve(results, s, "n", n_grid), color=COLORS[s], label=label)
        axes[0, 1].plot(e_grid, mean_curve(results, s, "eps", e_grid), color=COLORS[s], label=label)
    axes[0, 0].set(xlabel="US frame count n", ylabel="volume ratio V (mean)", title="(e) V vs n")
    axes[0, 1].set(
        xlabel="imaging-window path length eps (mm)", ylabel="V (mean)", title="(f) V vs eps"
    )
    axes[0, 0].legend()
    for ax, key, label, title in (
        (axes[1, 0], "n", "total frames n", "(g) total n"),
        (axes[1, 1], "eps_mm", "total eps (mm)", "(h) total eps"),
    ):
        ax.boxplot([per[s][key] for s in order], tick_labels=order)
        ax.set_ylabel(label)
        ax.set_title(title)
    vol = [[v for v in per[s]["volume_error_pct"] if v is not None] for s in order]
    axes[1, 2].boxplot(vol, tick_labels=order)
    axes[1, 2].axhspan(-5, 5, color="g", alpha=0.1, label="+-5%")
    axes[1, 2].set(ylabel="reconstructed - true volume (%)", title="kidney volume error")
    axes[1, 2].legend(fontsize=7)
    # Per patient: OP's totals against NOP's and SL's.
    ax = axes[0, 2]
    x = np.arange(len(analysis["patients"]))
    for s in order:
        ax.plot(x, per[s]["eps_mm"], "o-", color=COLORS[s], label=s, ms=3)
    ax.set(xlabel="patient", ylabel="total eps (mm)", title="eps per patient")
    ax.set_xticks(x)
    ax.set_xticklabels([p.split(":")[-1] for p in analysis["patients"]], fontsize=7)
    for a in axes.ravel():
        a.grid(alpha=0.3)
    fig.suptitle(
        f"Sweep efficiency by strategy (Fig. 10e-h), pole to pole, {mode}"
        + (f"\n{note}" if note else ""),
        fontsize=9,
    )
    fig.tight_layout()
    return save_figure(fig, path)


def write_er_sweep_outputs(
    out_dir,
    results,
    rule: str = "paper",
    mode: str = KINEMATIC,
    margins: dict | None = None,
    settings: dict | None = None,
    note: str = "",
) -> dict:
    """er_sweep_runs.csv, er_sweep_table.csv (per ER: errors, p-values, paired effect
    sizes, power, equivalence), fig7d_er_sweep.png and er_sweep.json (with ``settings``,
    the runs' own, so a later study knows what the critical ER was found with)."""
    out = Path(out_dir)
    analysis = analyze_er_sweep(results, rule=rule, margins=margins)
    write_csv_atomic(out / "er_sweep_runs.csv", [_flat(r) for r in results])
    write_csv_atomic(out / "er_sweep_table.csv", analysis["rows"])
    analysis["mode"] = mode
    analysis["settings"] = settings
    plot_er_sweep(analysis, out / "fig7d_er_sweep.png", mode, note)
    write_text_atomic(out / "er_sweep.json", json.dumps(analysis, default=json_default, indent=1))
    return analysis


def write_starts_outputs(out_dir, results, mode: str = KINEMATIC, note: str = "") -> dict:
    out = Path(out_dir)
    analysis = analyze_starts(results)
    write_csv_atomic(out / "starts_runs.csv", [_flat(r) for r in results])
    write_csv_atomic(out / "starts_tests.csv", analysis["tests"])
    analysis["mode"] = mode
    plot_starts(results, analysis, out / "fig9d_starts.png", mode, note)
    write_text_atomic(out / "starts.json", json.dumps(analysis, default=json_default, indent=1))
    return analysis


def write_efficiency_outputs(out_dir, results, mode: str = KINEMATIC, note: str = "") -> dict:
    out = Path(out_dir)
    analysis = analyze_efficiency(results)
    analysis["mode"] = mode
    rows = []
    for r in results:
        for s in _strategies(analysis):
            e = r["strategies"][s]
            at = (e.get("at_V") or {}).get(f"{analysis['V_target']:g}") or {}
            at_w = (e.get("at_V_whole_pivot") or {}).get(f"{analysis['V_target']:g}") or {}
            rows.append(
                {
                    "patient": r["patient"],
                    "strategy": s,
                    "n": e["n"],
                    "eps_mm": e["eps_mm"],
                    "V": e["V"],
                    "n_whole_pivot": e.get("n_whole_pivot", e.get("n_full")),
                    "eps_whole_pivot_mm": e.get("eps_whole_pivot_mm", e.get("eps_full_mm")),
                    "V_whole_pivot": e.get("V_whole_pivot", e.get("V_full")),
                    "V_target": analysis["V_target"],
                    "n_at_V": at.get("n"),
                    "eps_at_V_mm": at.get("eps_mm"),
                    "n_at_V_whole_pivot": at_w.get("n"),
                    "eps_at_V_whole_pivot_mm": at_w.get("eps_mm"),
                    "tilt_cap_legs": " ".join(str(x) for x in e.get("tilt_cap_legs") or []),
                    "volume_ml": e["volume_ml"],
                    "sweep": e.get("sweep", "line" if s == "SL" else "pivot"),
                    "pivot_pose_from": e.get("pivot_pose_from"),
                    "pivot_pose": e.get("pivot_pose"),
                    "given_pivot_pose": " ".join(
                        f"{v:.6g}" for v in e.get("given_pivot_pose") or []
                    ),
                    "status": e.get("status", r.get("status", "")),
                    "true_volume_ml": r["true_volume_ml"],
                    "volume_error_pct": e["volume_error_pct"],
                    "e_trans_mm": r["e_trans_mm"],
                    "e_rot_x_deg": r["e_rot_x_deg"],
                }
            )
    write_csv_atomic(out / "efficiency_runs.csv", rows)
    write_csv_atomic(out / "efficiency_tests.csv", analysis["comparisons"])
    plot_efficiency(results, analysis, out / "fig10_efficiency.png", mode, note)
    write_text_atomic(
        out / "efficiency.json",
        json.dumps(
            {k: v for k, v in analysis.items() if k != "per_patient"},
            default=json_default,
            indent=1,
        ),
    )
    return analysis


TEMPLATE_METRICS = (
    "E_trans = x-y distance (base frame) between the registered and the true "
    "kidney canonical-frame origins; E_rot,x = angle between the registered "
    "and the true kidney long axes x_k (drake_rus/metrics/core.py, the "
    "paper's III-B)"
)
TEMPLATE_DISTANCE = (
    "template distance = symmetric mean nearest-point distance between the "
    "template's points and the patient's true kidney surface, both in their "
    "canonical frames (eq. 13-14)"
)
TEMPLATE_VARIANT_TEXT = {
    "mean": "the study's template (the mean of its kidneys, eq. 15: the repository's 20 "
    "generated training kidneys unless the header names another)",
    "scale-": "the mean template scaled by S",
    "single:": "the template's kidney K alone",
    "loo": "leave-one-out mean (training patients only: the mean of the other kidneys)",
    "population:": "a template built the same way from N generated kidneys of another "
    "population (drake_rus/template/population.py; base: other people, same "
    "statistics; short/long: kidney length -1/+1 SD of Glodny 2009, 108.5 +- "
    "12.2 mm; slim: width and thickness -1 SD)",
}


def plot_template(
    results: list[dict], analysis: dict, path, mode: str = KINEMATIC, note: str = ""
) -> Path:
    """E_trans and E_rot,x against the template's distance from the patient, per variant
    (colour) and patient group (marker: generated patients dots, real CT kidneys in
    generated bodies triangles, real bodies stars, in decubitus diamonds), the least-squares
    line over the generated patients, and the paper's localization-study mean +- SD (its
    template vs its test patients)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8))
    variants = list(dict.fromkeys(r["variant"] for r in analysis["rows"]))
    colors = {v: plt.cm.tab10(i % 10) for i, v in enumerate(variants)}
    pl = PAPER["localization"]
    for ax, key, label, paper in (
        (axes[0], "e_trans_mm", "E_trans (mm)", pl["e_trans_mm"]),
        (axes[1], "e_rot_x_deg", "E_rot,x (deg)", pl["e_rot_x_deg"]),
    ):
        for v in variants:
            for g in analysis.get("groups", ["generated"]):
                sel = [r for r in results if r["template_variant"] == v and template_group(r) == g]
                if not sel:
                    continue
                kind = group_kind(g)
                real = kind == "real"
                lld = real and "decubitus" in g
                marker = ("D" if lld else "*") if real else "^" if kind == "ct" else "o"
                ax.plot(
                    [r["template_distance_mm"] for r in sel],
                    [r[key] for r in sel],
                    marker,
                    ms=13 if lld else 11 if real else 6 if kind == "ct" else 4,
                    color=colors[v],
                    mec=colors[v] if lld or not real else "k",
                    mfc="none" if lld or (kind == "ct" and "decubitus" in g) else colors[v],
                    mew=2 if lld else 1,
                    label=v if g == analysis.get("groups", ["generated"])[0] else None,
                )
        t = analysis["trend"][key]
        if np.isfinite(t["slope_per_mm"]):
            d = np.asarray([r["template_distance_mm"] for r in results], float)
            x = np.linspace(0, d.max() * 1.05, 20)
            ax.plot(
                x,
                t["intercept"] + t["slope_per_mm"] * x,
                "-",
                color="0.5",
                lw=1,
                label="fit, generated patients",
            )
        ax.axhline(paper[0], color="k", ls="--", lw=1, label="seed paper (mean +- SD)")
        ax.axhspan(max(0.0, paper[0] - paper[1]), paper[0] + paper[1], color="k", alpha=0.06)
        ax.set(
            xlabel="template distance from the patient's kidney (mm)",
            ylabel=label,
            title=f"generated patients: r = {t['r']:.2f}, slope {t['slope_per_mm']:.2f} per mm",
            xlim=(0, None),
            ylim=(0, None),
        )
        ax.grid(alpha=0.3)
    groups = analysis.get("groups", [])
    kinds = {group_kind(g) for g in groups}
    if "generated" in kinds:
        axes[0].plot([], [], "o", color="0.5", ms=4, label="generated patient")
    if "ct" in kinds:
        axes[0].plot([], [], "^", color="0.5", ms=6, label=f"{PATIENT_KINDS['ct']} (triangle)")
    if "real" in kinds:
        axes[0].plot([], [], "*", color="0.5", mec="k", ms=11, label="real body (supine)")
    if any("decubitus" in g and group_kind(g) == "real" for g in groups):
        axes[0].plot(
            [], [], "D", color="0.5", mfc="none", mew=2, ms=9, label="real body, decubitus"
        )
    axes[0].legend(fontsize=7, ncol=2)
    fig.suptitle(f"Template mismatch, {mode}" + (f"\n{note}" if note else ""), fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path)


def write_template_outputs(out_dir, results, mode: str = KINEMATIC, note: str = "") -> dict:
    out = Path(out_dir)
    analysis = analyze_template(results)
    analysis["mode"] = mode
    write_csv_atomic(
        out / "template_runs.csv",
        [
            dict(
                _flat(r),
                template_variant=r["template_variant"],
                template_distance_mm=r["template_distance_mm"],
                posture=r.get("posture"),
                template_length_mm=(r.get("template_extent_mm") or [None])[0],
                kidney_length_canonical_mm=(r.get("kidney_extent_mm") or [None])[0],
            )
            for r in results
        ],
    )
    write_csv_atomic(out / "template_table.csv", analysis["rows"])
    write_csv_atomic(out / "template_bins.csv", analysis["bins"])
    plot_template(results, analysis, out / "fig_template_mismatch.png", mode, note)
    write_text_atomic(out / "template.json", json.dumps(analysis, default=json_default, indent=1))
    return analysis


def template_markdown(meta: dict, analysis: dict) -> list[str]:
    """The template-mismatch section of report.md: per patient group a table of the
    variants (distance, E_trans, E_rot,x, paired p against the mean template), the errors in
    bins of template distance, the trend lines and the paper's numbers."""
    pl = PAPER["localization"]
    mode = meta.get("mode_text", analysis.get("mode", KINEMATIC))
    variants = list(dict.fromkeys(r["variant"] for r in analysis["rows"]))
    used = [f"`{v}`" for v in TEMPLATE_VARIANT_TEXT if any(x.startswith(v) for x in variants)]
    L = [
        "## Template mismatch (beyond the paper, `fig_template_mismatch.png`)",
        "",
        provenance(
            meta,
            mode=mode,
            extra=f"metrics: {TEMPLATE_METRICS}; {TEMPLATE_DISTANCE}; template "
            "variants: "
            + "; ".join(
                f"{k.rstrip(':-')}: {t}"
                for k, t in TEMPLATE_VARIANT_TEXT.items()
                if f"`{k}`" in used
            ),
        ),
        "",
        f"ER {', '.join(f'{e * 100:.0f}%' for e in analysis['er'])}; posture "
        f"{meta.get('posture') or 'the scenario default'}; patients: "
        f"{', '.join(analysis['patients'])}.",
        "",
    ]
    pops = meta.get("population_templates") or {}
    if pops:
        L += [
            "Population templates (built once, then read from the template cache): "
            + "; ".join(
                f"`{v}` {b['subjects']} subjects, built in {_f(b.get('build_s'), 1)} s"
                for v, b in pops.items()
            )
            + ".",
            "",
        ]
    for g in analysis.get("groups", ["generated"]):
        rows = [r for r in analysis["rows"] if r.get("group", "generated") == g]
        title = {
            "generated": f"Generated patients{g[len('generated') :]}",
            "ct": f"Real CT kidneys in generated bodies{g[len(CT_GROUP) :]}",
        }.get(group_kind(g), f"Real body: {g}")
        L += [
            f"**{title}** ({mode.split(' (')[0]}, registration `{meta.get('method', '?')}`, "
            f"segmenter `{meta.get('segmenter', '?')}`)",
            "",
            "| template | runs | template length (mm) | distance (mm) | E_trans (mm) | "
            "E_rot,x (deg) | p E_trans vs mean | p E_rot,x vs mean |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for r in rows:
            L.append(
                f"| {r['variant']} | {r['n']} | {_f(r.get('template_length_mm'), 1)} | "
                f"{_f(r['template_distance_mm_mean'])} +- "
                f"{_f(r['template_distance_mm_sd'])} | {_f(r['e_trans_mm_mean'])} +- "
                f"{_f(r['e_trans_mm_sd'])} | {_f(r['e_rot_x_deg_mean'])} +- "
                f"{_f(r['e_rot_x_deg_sd'])} | {_p(r['p_e_trans_mm_vs_mean'])} | "
                f"{_p(r['p_e_rot_x_deg_vs_mean'])} |"
            )
        L.append("")
    if analysis.get("bins"):
        L += [
            f"**Errors by template distance** (all runs, {mode.split(' (')[0]})",
            "",
            "| distance bin (mm) | runs (real CT kidneys; real bodies) | distance (mm) | "
            "E_trans (mm) | "
            "E_rot,x (deg) |",
            "|---|---|---|---|---|",
        ]
        for b in analysis["bins"]:
            hi = "" if not np.isfinite(b["to_mm"]) else f"{b['to_mm']:g}"
            L.append(
                f"| {b['from_mm']:g}-{hi} | {b['n']} ({b.get('ct_runs', 0)}; {b['real_runs']}) | "
                f"{_f(b['template_distance_mm_mean'])} | {_f(b['e_trans_mm_mean'])} +- "
                f"{_f(b['e_trans_mm_sd'])} | {_f(b['e_rot_x_deg_mean'])} +- "
                f"{_f(b['e_rot_x_deg_sd'])} |"
            )
        L.append("")
    t, ta = analysis["trend"], analysis.get("trend_all", analysis["trend"])
    L += [
        f"Generated patients' runs: E_trans against distance r = {_f(t['e_trans_mm']['r'])} "
        f"({_f(t['e_trans_mm']['slope_per_mm'])} mm per mm), E_rot,x r = "
        f"{_f(t['e_rot_x_deg']['r'])} ({_f(t['e_rot_x_deg']['slope_per_mm'])} deg per mm); "
        f"all runs: r = {_f(ta['e_trans_mm']['r'])} and {_f(ta['e_rot_x_deg']['r'])}. "
        f"Paper (its template on its 15 simulated test patients, ER 60%, "
        f"`docs/facts/paper.md`): {pl['e_trans_mm'][0]} +- {pl['e_trans_mm'][1]} mm, "
        f"{pl['e_rot_x_deg'][0]} +- {pl['e_rot_x_deg'][1]} deg.",
        "",
    ]
    return L


def _flat(r: dict) -> dict:
    keys = (
        "patient",
        "mode",
        "status",
        "er",
        "er_unit",
        "start",
        "start_fraction",
        "x_offset_mm",
        "explore_frames",
        "explore_travel_mm",
        "kidney_length_mm",
        "points",
        "e_trans_mm",
        "e_rot_x_deg",
        "registration_ms",
        "iterations",
        "sim_s",
        "wall_s",
    )
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


# The paper's OP-vs-other eps differences (OP's eps minus the other's, mm; negative: OP
# shorter), pole to pole, 15 simulated patients (IV-C; docs/facts/paper.md).
PAPER_OP_MINUS = {
    "SL": (
        -PAPER["efficiency"]["eps_reduction_vs_SL_mm"][0],
        PAPER["efficiency"]["eps_reduction_vs_SL_mm"][1],
    ),
    "NOP": (
        -PAPER["efficiency"]["eps_reduction_vs_NOP_mm"][0],
        PAPER["efficiency"]["eps_reduction_vs_NOP_mm"][1],
    ),
    "GT-OP": PAPER["efficiency"]["eps_extra_vs_GT_OP_mm"],
}


def strategy_lines(strategies, mode_text: str) -> list[str]:
    """One bullet per strategy: what it sweeps and which pose its pivot used, and in closed
    loop how the scan got it (the study's wiring)."""
    closed = mode_text.startswith("closed")
    return [
        f"- **{k}**: {STRATEGY_TEXT[k]}"
        + (
            f"; closed loop: {CLOSED_LOOP_STRATEGY_HOW[k]}"
            if closed
            else "; kinematic: planned probe poses"
        )
        + "."
        for k in strategies
    ]


def _op_minus(eff: dict, other: str, definition: str = "pole_to_pole"):
    """The comparison row "OP vs ``other``" (eps) of an efficiency analysis, or None."""
    return next(
        (
            c
            for c in eff.get("comparisons", [])
            if c["comparison"] == f"OP vs {other}"
            and c["metric"] == "eps_mm"
            and c.get("definition", "pole_to_pole") == definition
        ),
        None,
    )


def _op_minus_cell(c) -> str:
    if c is None:
        return "n/a"
    d = -c["reduction_mean"]
    return (
        f"{'n/a' if not np.isfinite(d) else f'{d:+.1f}'} +- {_f(c['reduction_sd'], 1)} "
        f"(OP lower on "
        f"{c['op_lower_count']}/{c['patients']}, p {_p(c['p'])})"
    )


def paper_comparison_table(names: list[str], effs: list[dict]) -> list[str]:
    """OP's eps minus each other paper strategy's, pole to pole (the paper's) and over the
    whole pivot, our modes beside the paper's numbers."""
    others = [k for k in ("GT-OP", "NOP", "SL") if any(k in e["summary"] for e in effs)]
    if not others or not all("OP" in e["summary"] for e in effs):
        return []
    L = [
        "OP's eps minus the other strategy's (mm, mean +- SD over patients; negative: OP "
        "shorter), the paper's comparisons (IV-C):",
        "",
        "| comparison | definition | paper | " + " | ".join(names) + " |",
        "|---|---|---|" + "---|" * len(names),
    ]
    for k in others:
        for definition in ("pole_to_pole", "whole_pivot"):
            pap = PAPER_OP_MINUS.get(k)
            pcell = (
                f"{pap[0]:+.2f} +- {pap[1]:.2f}" if pap and definition == "pole_to_pole" else "-"
            )
            L.append(
                f"| OP - {k} | {definition.replace('_', ' ')} | {pcell} | "
                + " | ".join(_op_minus_cell(_op_minus(e, k, definition)) for e in effs)
                + " |"
            )
    return L + [""]


def _eff_table(L: list, s: dict, n_pat: int, keys: tuple, V_key: str | None, extra=True):
    """Rows of strategy | n | eps | V (| volume) for one metric definition."""
    n_key, e_key = keys
    for k in [k for k in STRATEGY_ORDER if k in s]:
        row = (
            f"| {k} | {_f(s[k][n_key][0], 1)} +- {_f(s[k][n_key][1], 1)} | "
            f"{_f(s[k][e_key][0], 1)} +- {_f(s[k][e_key][1], 1)} |"
        )
        if V_key:
            row += f" {_f(s[k][V_key][0], 3)} |"
        else:
            row += f" {s[k]['reached_V']}/{n_pat} |"
        if extra:
            row += (
                f" {_f(s[k]['volume_error_pct'][0])} +- {_f(s[k]['volume_error_pct'][1])} | "
                f"{_f(s[k]['abs_volume_error_pct'][0])} (within 5%: "
                f"{s[k]['within_5pct']}/{n_pat}) |"
            )
        L.append(row)


DEFAULT_ER_TEXT = "ER 60%, the paper's critical ER,"


def _pct(er) -> str:
    return "not determined" if er is None else f"{er * 100:.0f}%"


def _why_below_fails(row: dict, alpha: float) -> str:
    """Why the ER below a critical ER of 100% fails the rule, for the report: the errors
    that differ (p <= alpha; a negative d_z noted only for those), else the patients not
    localized there, else no test possible."""
    p = {"E_trans": row["p_e_trans"], "E_rot,x": row["p_e_rot_x"]}
    dz = {"E_trans": row["dz_e_trans_mm"], "E_rot,x": row["dz_e_rot_x_deg"]}
    differ = [k for k, v in p.items() if np.isfinite(v) and v <= alpha]
    ps = f"p = {_p(p['E_trans'])} and {_p(p['E_rot,x'])}"
    if differ:
        smaller = [k for k in differ if dz[k] < 0]
        note = (
            f"; a negative d_z in {' and '.join(smaller)}: smaller errors than at ER 100%, a "
            "difference to the paper's two-sided test too"
            if smaller
            else ""
        )
        return f"which differs in {' and '.join(differ)} ({ps}{note})"
    missing = int(row.get("missing", 0) or 0)
    if missing:
        return (
            f"which fails the rule because {missing} patient(s) were not localized there "
            f"({ps} on the others: no significant difference)"
        )
    return f"where no paired test was possible ({ps})"


def critical_er_markdown(er: dict) -> list[str]:
    """The critical ER with what it rests on (issue 27): n against the minimum sample size,
    the ER-100% floor, the paired effect size and power at each ER, equivalence to ER 100%
    within the clinical margins (TOST), and the paper's test read back the same way."""
    p = PAPER["er_sweep"]
    m = er.get("margins") or DEFAULT_MARGINS
    n = er.get("patients")
    fl = er.get("floor") or {}
    alpha = er.get("alpha", 0.05)
    paper_rule = er.get("critical_er_paper_rule", er.get("first_not_significant_er"))
    strict_rule = er.get("critical_er_strict_rule", er["critical_er"])
    L = [
        f"**Critical ER** (rule `{er.get('rule', 'strict')}`): **ours "
        f"{_pct(er['critical_er'])}** (n = {n} patients, one paired run each per ER against "
        f"ER 100%), paper {p['critical_er'] * 100:.0f}% ({PAPER_PATIENTS} patients; p = "
        f"{p['p_e_trans_at_60']} and {p['p_e_rot_at_60']} at 60%). Under the paper's rule "
        f"({CRITICAL_ER_RULES['paper']}): {_pct(paper_rule)}; under ours "
        f"({CRITICAL_ER_RULES['strict']}): {_pct(strict_rule)}. Under both, and for the "
        f"equivalence ER, {ALL_LOCALIZED_TEXT} (a scan that cannot localize fails that ER).",
        "",
    ]
    warning = sample_size_warning(er) if "below_minimum" in er else None
    if warning:
        L += [f"> **{warning[0].upper() + warning[1:]}.**", ""]
    if not fl:
        return L
    L += [
        "What it rests on (the paper's rule compares every ER with ER 100%, so the critical "
        "ER moves with the floor, the spread of the paired differences and n, the test's "
        "power, not only with the method; equivalence asks the clinical question instead: "
        "is the difference within a stated margin?):",
        "",
        f"- ER-100% floor (n = {n}): E_trans {_f(fl['e_trans_mm'][0])} +- "
        f"{_f(fl['e_trans_mm'][1])} mm, E_rot,x {_f(fl['e_rot_x_deg'][0])} +- "
        f"{_f(fl['e_rot_x_deg'][1])} deg (mean +- SD).",
        f"- Equivalence to ER 100% (TOST: two one-sided paired t-tests at alpha {alpha:g}, "
        f"clinical margin +-{m['e_trans_mm']:g} mm / +-{m['e_rot_x_deg']:g} deg, "
        f"`--margin-mm`/`--margin-deg`): both errors equivalent from ER "
        f"**{_pct(er.get('equivalence_er_paper_rule'))}** (the smallest such ER; every ER from "
        f"there on: {_pct(er.get('equivalence_er_strict_rule'))}).",
    ]
    row, below = critical_evidence_row(er)
    if row is not None and n and n >= 2:
        detect = [
            paired_t_power(m[k] / row[f"diff_{k}_sd"], row["n"], alpha)
            if row[f"diff_{k}_sd"] and row[f"diff_{k}_sd"] > 0
            else float("nan")
            for k in ("e_trans_mm", "e_rot_x_deg")
        ]
        where = (
            f"The critical ER is ER 100% itself; at the ER below it, {_pct(row['er'])}, "
            + _why_below_fails(row, alpha)
            if below
            else f"At the critical ER {_pct(row['er'])}"
        )
        L.append(
            f"- {where}: paired effect d_z "
            f"{_f(row['dz_e_trans_mm'])} (E_trans) and {_f(row['dz_e_rot_x_deg'])} "
            f"(E_rot,x), power of the paired t-test against them "
            f"{_f(row['power_e_trans_mm'])} and {_f(row['power_e_rot_x_deg'])}; its power "
            f"to detect a difference as large as the margin (with the SD of the paired "
            f"differences there): {_f(detect[0])} and {_f(detect[1])}."
        )
    pp = er.get("paper_power") or {}
    row60 = next((r for r in er["rows"] if abs(r["er"] - 0.6) < 1e-6), None)
    if pp:
        ours = (
            (
                f"; ours at 60%: d_z {_f(row60['dz_e_trans_mm'])} and "
                f"{_f(row60['dz_e_rot_x_deg'])}, power {_f(row60['power_e_trans_mm'])} and "
                f"{_f(row60['power_e_rot_x_deg'])} (n = {row60['n']})"
            )
            if row60
            else ""
        )
        L.append(
            f"- The paper at ER 60% read back through the t distribution: its p = "
            f"{pp['e_trans_mm']['p']} and {pp['e_rot_x_deg']['p']} with "
            f"{PAPER_PATIENTS} patients are |d_z| {_f(pp['e_trans_mm']['d_z'])} and "
            f"{_f(pp['e_rot_x_deg']['d_z'])}, against which its test had a power of "
            f"{_f(pp['e_trans_mm']['power'])} and {_f(pp['e_rot_x_deg']['power'])}"
            f"{ours}."
        )
    L += [
        f"- Minimum sample size: {er.get('min_patients_text', '')}; this study: {n}.",
        "",
        f"Per ER, paired against ER 100% (difference = ER minus ER 100%, mean +- SD; d_z = "
        f"mean / SD; power of the two-sided paired t-test at alpha {alpha:g} against that "
        f"d_z with that n; TOST p against the margin, **yes** when equivalent):",
        "",
        "| ER | n | dE_trans (mm) | d_z | power | TOST p (+-"
        f"{m['e_trans_mm']:g} mm) | dE_rot,x (deg) | d_z | power | TOST p (+-"
        f"{m['e_rot_x_deg']:g} deg) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in er["rows"]:
        cells = []
        for k in ("e_trans_mm", "e_rot_x_deg"):
            eq = " **yes**" if r.get(f"equivalent_{k}") else ""
            cells.append(
                f"{_f(r[f'diff_{k}_mean'])} +- {_f(r[f'diff_{k}_sd'])} | "
                f"{_f(r[f'dz_{k}'])} | {_f(r[f'power_{k}'])} | "
                f"{_p(r[f'tost_p_{k}'])}{eq}"
            )
        n_cell = f"{r['n']}" + (f" ({r['missing']} not localized)" if r.get("missing") else "")
        L.append(f"| {r['er'] * 100:.0f}% | {n_cell} | " + " | ".join(cells) + " |")
    return L + [""]


def report_markdown(
    meta: dict,
    er: dict | None,
    starts: dict | None,
    eff: dict | None,
    closed: list | None = None,
    template: dict | None = None,
    compare: dict | None = None,
) -> str:
    """report.md: our numbers beside the seed paper's for each table and figure, each with
    the mode, registration method, segmenter, ER unit and metric definition that produced
    it (one section per analysis given). ``compare``: the analyses of the same patients in
    the other modes and templates OUT holds (a list of {"mode", "template_info", "er",
    "starts", "eff", "settings"}), put side by side with these and the paper's."""
    L = header_markdown(meta, er, closed)
    if er is not None:
        L += er_sweep_markdown(meta, er)
    if starts is not None:
        L += starts_markdown(meta, starts)
    if eff is not None:
        L += efficiency_markdown(meta, eff)
    if closed:
        L += closed_loop_check_markdown(meta, closed)
    if compare:
        this = {
            "mode": _report_mode(meta),
            "er": er,
            "starts": starts,
            "eff": eff,
            "settings": meta.get("settings"),
            "template_info": meta.get("template"),
            "status": meta.get("run_status") or {},
        }
        L += compare_markdown(meta, this, compare if isinstance(compare, list) else [compare])
    if template is not None:
        L += template_markdown(meta, template)
    L += method_notes_markdown()
    return "\n".join(L)


def _report_mode(meta: dict) -> str:
    """The mode of the report's runs (every section's unless it says otherwise)."""
    return meta.get("mode_text", KINEMATIC)


def _section_provenance(meta: dict, **kw) -> str:
    """:func:`provenance` in the report's mode unless ``mode`` is given."""
    return provenance(meta, **({"mode": _report_mode(meta)} | kw))


def header_markdown(meta: dict, er: dict | None, closed: list | None) -> list[str]:
    """The report's title and what every table rests on: patients, mode, segmenter and
    registration, ER unit and critical-ER rule, metric definitions, the runs' ER, wall
    times, scenario and inputs digest, and the runs left out."""
    mode = _report_mode(meta)
    unit = meta.get("er_unit", "fixed")
    rule = meta.get("critical_er_rule", (er or {}).get("rule", "paper"))
    kinds = meta.get("patient_kinds") or {}
    L = [
        "# drake-rus studies: the seed paper's section III on "
        + (
            "real CT kidneys in generated bodies"
            if list(kinds) == [PATIENT_KINDS["ct"]]
            else "our virtual cohort"
        ),
        "",
        f"- Patients: {', '.join(meta['patients'])} ({len(meta['patients'])}"
        + ("; " + ", ".join(f"{k}: {n}" for k, n in kinds.items()) if kinds else "")
        + ")",
        f"- Mode: **{mode}** for every run of the tables and figures unless a table "
        "says otherwise; "
        + (
            f"{len(closed)} closed-loop dynamic scan(s) in the closed-loop check."
            if closed
            else "no closed-loop dynamic runs."
        ),
        f"- Segmenter: {segmenter_label(meta['segmenter'])}; registration (localization "
        f"method): `{meta['method']}`; label voxel {meta['voxel'] * 1e3:.0f} mm; study seed "
        f"{meta['seed']}"
        + (" (as the runs themselves record them)" if meta.get("settings_from") == "runs" else "")
        + ".",
        f"- Registration template: {template_label(meta)}"
        + _template_cases_text(meta.get("template") or {})
        + ".",
        f"- ER: {ER_UNIT_TEXT.get(unit, unit)}."
        + (
            f" Critical-ER rule: `{rule}`, {CRITICAL_ER_RULES[rule]}."
            if rule in CRITICAL_ER_RULES
            else ""
        ),
        f"- Sweep costs (eps eq. 24, n, V eq. 25; `drake_rus/metrics/sweep.py`, the same "
        f"functions for the kinematic twin and the closed-loop scan): **{POLE_TO_POLE}**; "
        f"beside it, **{WHOLE_PIVOT}**; {MATCHED_V}.",
        *(
            []
            if meta.get("study") == "er-sweep"
            else [
                f"- Starts, efficiency and template runs ran at ER "
                f"{meta.get('er', float('nan')) * 100:.0f}% (the critical ER of this sweep when "
                f"it ran, unless `--er` was given; {DEFAULT_ER_TEXT} when none was found)."
            ]
        ),
        "- Wall time per invocation (resumed "
        "invocations skip finished runs): "
        + "; ".join(
            f"{i['wall_s']:.0f} s ({_runs(i)}{_where(i)}; stages "
            + ", ".join(f"{k} {v:.0f} s" for k, v in (i.get("stage_wall_s") or {}).items())
            + ")"
            for i in meta.get("invocations", [meta])
        ),
    ]
    settings = meta.get("settings") or {}
    if settings:
        L += [
            f"- Scenario `{settings.get('scenario')}`"
            + (f" with overrides `{settings['overrides']}`" if settings.get("overrides") else "")
            + f"; resolved inputs (scenario YAML and template file) sha256 "
            f"{_digest_text(settings.get('inputs_sha256'))}; runs made by commit(s) "
            + (
                ", ".join(
                    f"`{c[:12]}`" + (" (dirty)" if c.endswith("(dirty)") else "")
                    for c in meta.get("run_commits") or []
                )
                or "n/a"
            )
            + "; each run's record (OUT/runs) holds its task and provenance (resolved "
            "scenario, overrides, seeds, package versions)."
        ]
    run_status = meta.get("run_status") or {}
    if run_status:
        L += [
            "- Closed-loop scans by status: "
            + "; ".join(f"{k} {_status_text(v)}" for k, v in run_status.items())
            + " (a registration the product rejected stops the scan ABORT, its errors are "
            "recorded and analysed, as the paper has no acceptance check)."
        ]
    ct_out = meta.get("ct_cases_left_out") or []
    if ct_out:
        L += [
            f"- CT cases left out of the patient list ({len(ct_out)}): "
            + "; ".join(f"{c['case']} ({c['reason']})" for c in ct_out)
            + "."
        ]
    in_template = meta.get("patients_in_template") or []
    if in_template:
        L += [
            f"- **Warning: {len(in_template)} patient(s) helped build the template** "
            "(`--allow-template-cases`): their errors are not a test on unseen kidneys. "
            + " ".join(in_template)
        ]
    left_out = meta.get("runs_without_localization") or {}
    if left_out:
        L += [
            "- Runs left out of the analysis (no localization; efficiency: a scan that did "
            "not finish): "
            + "; ".join(f"{study}: {', '.join(rs)}" for study, rs in left_out.items() if rs)
            + "."
        ]
    return L + [""]


def _digest_text(digest) -> str:
    """An inputs digest (12 hex digits), or one per posture (the template study)."""
    if isinstance(digest, dict):
        return ", ".join(f"`{str(v)[:12]}` ({k})" for k, v in digest.items())
    return f"`{str(digest)[:12]}`"


def _template_cases_text(t: dict) -> str:
    """Which CT cases built a real template (none of them a patient unless the header
    warns)."""
    cases = t.get("cases") or []
    if not cases:
        return ""
    return (
        f", built from the {len(cases)} CT kidneys of {', '.join(cases)} (sha256 "
        f"`{str(t.get('sha256'))[:12]}`; the patients' cases are not among them unless a "
        "warning below says so)"
    )


def er_sweep_markdown(meta: dict, er: dict) -> list[str]:
    """The ER sweep (Fig. 7d): errors per ER with paired p against ER 100%, the critical ER
    with what it rests on (:func:`critical_er_markdown`) and the paper's ER 60%."""
    p = PAPER["er_sweep"]
    kl = er.get("kidney_length_mm")
    L = [
        "## Exploration ratio vs localization (Fig. 7d, `fig7d_er_sweep.png`)",
        "",
        _section_provenance(
            meta, er_unit=er.get("er_unit") if isinstance(er.get("er_unit"), str) else None
        ),
        "",
    ]
    if kl:
        L += [
            f"Kidney length along the exploration line: {_f(kl[0][0], 1)} +- "
            f"{_f(kl[0][1], 1)} mm ({_f(kl[1], 1)}-{_f(kl[2], 1)} mm); L_m = 100 mm.",
            "",
        ]
    L += [
        "| ER | E_trans (mm) | E_rot,x (deg) | p (E_trans vs 100%) | p (E_rot,x vs 100%) |",
        "|---|---|---|---|---|",
    ]
    for r in er["rows"]:
        L.append(
            f"| {r['er'] * 100:.0f}% | {_f(r['e_trans_mm_mean'])} +- "
            f"{_f(r['e_trans_mm_sd'])} | {_f(r['e_rot_x_deg_mean'])} +- "
            f"{_f(r['e_rot_x_deg_sd'])} | {_p(r['p_e_trans'])} | "
            f"{_p(r['p_e_rot_x'])} |"
        )
    row60 = next((r for r in er["rows"] if abs(r["er"] - 0.6) < 1e-6), None)
    L += [""] + critical_er_markdown(er)
    if row60:
        L.append(
            f"At ER 60%: ours {_f(row60['e_trans_mm_mean'])} +- "
            f"{_f(row60['e_trans_mm_sd'])} mm, {_f(row60['e_rot_x_deg_mean'])} +- "
            f"{_f(row60['e_rot_x_deg_sd'])} deg; paper {p['e_trans_mm_at_60'][0]} +- "
            f"{p['e_trans_mm_at_60'][1]} mm, {p['e_rot_x_deg_at_60'][0]} +- "
            f"{p['e_rot_x_deg_at_60'][1]} deg."
        )
    return L + [""]


def starts_markdown(meta: dict, starts: dict) -> list[str]:
    """The random starts (Fig. 9d): errors over all runs and per start, and the pairwise
    tests against Bonferroni's threshold, beside the paper's."""
    pl = PAPER["localization"]
    L = [
        "## Random exploration starts (Fig. 9d, `fig9d_starts.png`)",
        "",
        _section_provenance(meta),
        "",
        f"All runs: E_trans {_f(starts['e_trans_mm'][0])} +- {_f(starts['e_trans_mm'][1])}"
        f" mm, E_rot,x {_f(starts['e_rot_x_deg'][0])} +- {_f(starts['e_rot_x_deg'][1])} "
        f"deg (paper, 15 patients x 5 starts: {pl['e_trans_mm'][0]} +- "
        f"{pl['e_trans_mm'][1]} mm, {pl['e_rot_x_deg'][0]} +- {pl['e_rot_x_deg'][1]} deg).",
        "",
        "| start | E_trans (mm) | E_rot,x (deg) |",
        "|---|---|---|",
    ]
    for r in starts["per_start"]:
        L.append(
            f"| {r['start'] + 1} | {_f(r['e_trans_mm_mean'])} +- {_f(r['e_trans_mm_sd'])}"
            f" | {_f(r['e_rot_x_deg_mean'])} +- {_f(r['e_rot_x_deg_sd'])} |"
        )
    n_sig = sum(t["significant_e_trans_mm"] + t["significant_e_rot_x_deg"] for t in starts["tests"])
    pmin = min(
        [min(t["p_e_trans_mm"], t["p_e_rot_x_deg"]) for t in starts["tests"]] or [float("nan")]
    )
    return L + [
        "",
        f"Pairwise paired t-tests ({len(starts['tests'])} pairs x 2 errors, "
        f"Bonferroni per error over the {len(starts['tests'])} pairs, p < "
        f"{starts['bonferroni_threshold']:.4f}): "
        f"**{n_sig} significant** (smallest p = {_p(pmin)}). Paper: "
        f"{PAPER['starts']}.",
        "",
    ]


def efficiency_markdown(meta: dict, eff: dict) -> list[str]:
    """The sweep efficiency (Fig. 10): the strategies, their costs pole to pole, over the
    whole pivot and at matched coverage, the tilt cap, the comparisons and the paper's."""
    mode = _report_mode(meta)
    s = eff["summary"]
    pe = PAPER["efficiency"]
    n_pat = len(eff["patients"])
    tgt = eff.get("V_target", 0.9)
    L = [
        "## Sweep efficiency (Fig. 10, `fig10_efficiency.png`)",
        "",
        f"Strategies ({mode.split(' (')[0]}; the same pose definitions in both modes, "
        "`drake_rus/experiments/kinematic.py` `strategy_pivot_pose`, `sl_line`):",
        "",
    ]
    L += strategy_lines(_strategies(eff), mode) + [""]
    poses = (
        "strategy poses as listed above (per run and strategy in "
        "`efficiency_runs.csv`: sweep, pivot_pose_from, pivot_pose); the ER applies to "
        "OP's and OP-PE's exploration only"
    )
    L += [
        _section_provenance(meta, definition=POLE_TO_POLE, extra=poses),
        "",
        "Pole to pole (the paper's eps, n and V):",
        "",
        "| strategy | n | eps (mm) | V | volume error (%) | abs volume error (%) |",
        "|---|---|---|---|---|---|",
    ]
    _eff_table(L, s, n_pat, ("n", "eps_mm"), "V")
    L += [
        "",
        _section_provenance(meta, definition=WHOLE_PIVOT, extra=poses),
        "",
        "Whole pivot (both legs; for SL the whole line), what the robot spends:",
        "",
        "| strategy | n_whole_pivot | eps_whole_pivot (mm) | V_whole_pivot |",
        "|---|---|---|---|",
    ]
    _eff_table(L, s, n_pat, ("n_whole_pivot", "eps_whole_pivot_mm"), "V_whole_pivot", extra=False)
    L += [
        "",
        _section_provenance(meta, definition=f"{MATCHED_V} = {tgt:g}", extra=poses),
        "",
        f"At matched coverage (n and eps, pole to pole, to first reach V = {tgt:g}):",
        "",
        f"| strategy | n to V {tgt:g} | eps to V {tgt:g} (mm) | patients reaching it |",
        "|---|---|---|---|",
    ]
    _eff_table(L, s, n_pat, ("n_at_V", "eps_at_V_mm"), None, extra=False)
    caps = "; ".join(
        f"{k} on {s[k]['tilt_cap_patients']}/{n_pat} patients (leg 1: "
        f"{s[k]['tilt_cap_leg_counts']['1']}, leg 2: {s[k]['tilt_cap_leg_counts']['2']})"
        for k in STRATEGY_ORDER
        if k != "SL" and k in s
    )
    L += [
        "",
        f"Tilt cap (a pivot leg ended at the controller's `max_pivot_tilt` instead of "
        f"where the kidney left the image): {caps}.",
        "",
        'Comparisons "A vs B": the reduction by A (B - A) and how often A was lower; '
        "OP against the paper's other strategies (Bonferroni over those), OP-PE (beyond "
        "the paper: OP's pose, the predicted_end pivot) against OP (its own family).",
        "",
        "| definition | comparison | metric | reduction by A (mean +- SD) | A lower on | "
        "p | significant (Bonferroni) |",
        "|---|---|---|---|---|---|---|",
    ]
    for c in eff["comparisons"]:
        unit_c = " mm" if c["metric"] == "eps_mm" else " frames"
        L.append(
            f"| {c.get('definition', 'pole_to_pole')} | {c['comparison']} | "
            f"{c['metric']} | {_f(c['reduction_mean'], 1)} +- "
            f"{_f(c['reduction_sd'], 1)}{unit_c} | {c['op_lower_count']}/"
            f"{c['patients']} | {_p(c['p'])} | {c['significant']} |"
        )
    L += [""] + paper_comparison_table([_mode_label(mode)], [eff])
    return L + [
        f"Paper (simulation, 15 patients, pole to pole): OP reduced eps by "
        f"{pe['eps_reduction_vs_SL_mm'][0]}"
        f" +- {pe['eps_reduction_vs_SL_mm'][1]} mm against SL and by "
        f"{pe['eps_reduction_vs_NOP_mm'][0]} +- {pe['eps_reduction_vs_NOP_mm'][1]} mm "
        f"against NOP; localization error cost {pe['eps_extra_vs_GT_OP_mm'][0]} +- "
        f"{pe['eps_extra_vs_GT_OP_mm'][1]} mm against GT-OP. Volume: "
        f"{PAPER['volume_loa']}; our target: GT-OP within 5%.",
        "",
    ]


def closed_loop_check_markdown(meta: dict, closed: list) -> list[str]:
    """The paper study's closed-loop check: each dynamic scan beside its kinematic twin."""
    cl_unit = closed[0]["closed_loop"].get("er_unit", "fixed")
    cl_unit_text = (
        "fraction of the kidney length the closed loop estimates from its "
        "explored cloud (controller `exploration_length: estimated`)"
        if cl_unit == "estimated"
        else ER_UNIT_TEXT["fixed"]
    )
    L = [
        "## Closed-loop check (a few dynamic scans beside their kinematic twins)",
        "",
        _section_provenance(
            meta,
            mode=f"{CLOSED_LOOP} and its {KINEMATIC}",
            definition=f"{POLE_TO_POLE} (n, eps, V); {WHOLE_PIVOT} (n_whole, eps_whole, V_whole)",
            extra=f"closed-loop ER: {cl_unit_text}",
        ),
        "",
        "Same patient, start (10% into the E-ROI), ER, segmenter and localization; OP pivot.",
        "",
        "| patient | mode | status | E_trans (mm) | E_rot,x (deg) | n | eps (mm) | V | "
        "n_whole | eps_whole (mm) | V_whole | tilt cap legs | wall (s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in closed:
        for label, c in (("closed-loop", r["closed_loop"]), ("kinematic", r["kinematic"])):
            wall = (
                f"{_f(c['wall_s'], 0)} (sim {_f(c['sim_s'], 1)} s)"
                if "sim_s" in c
                else _f(c["wall_s"], 0)
            )
            caps = " ".join(str(x) for x in c.get("tilt_cap_legs") or []) or "-"
            L.append(
                f"| {r['patient']} | {label} | {c.get('status', '-')} | "
                f"{_f(c['e_trans_mm'])} | {_f(c['e_rot_x_deg'])} | {c['n']} | "
                f"{_f(c['eps_mm'], 1)} | {_f(c['V'], 3)} | "
                f"{c.get('n_whole_pivot', '-')} | {_f(c.get('eps_whole_pivot_mm'), 1)} | "
                f"{_f(c.get('V_whole_pivot'), 3)} | {caps} | {wall} |"
            )
    return L + [""]


def method_notes_markdown() -> list[str]:
    """The report's closing notes: how the runs were made (both modes)."""
    return [
        "## Method notes",
        "",
        "- Kinematic runs place the probe exactly where the controller laws ask (eq. 17 "
        "exploration, eq. 20-23 pivot), tip on the skin surface; no contact dynamics, "
        "tracking error or tissue compression.",
        "- Exploration starts at the E-ROI's superior end (ER sweep, efficiency) or at a "
        "seeded random point inside the E-ROI (starts), drawn again until the kidney is "
        "visible at the start and 2 mm around it (the paper's assumption II-A (i)), in both "
        "modes. ER 0% uses the initial alignment alone (heuristic rotation, centroid under "
        "the start point), in both modes (III-C).",
        "- The kidney length of the ER is the kidney's extent along the exploration line "
        "(base y, the E-ROI's length): ER 100% explores the whole kidney.",
        "- Efficiency strategies, both modes: OP pivots at T* of the registered kidney pose, "
        "GT-OP at T* of the true pose, NOP with the array along the true kidney's y-axis "
        "projected on the horizontal (the sign nearest the exploration's transverse array, "
        "base x), tip over the true centroid (the in-vivo NOP was expert-placed), all with "
        "the paper's two-leg pivot; SL is the exploration controller (eq. 17) from 10 mm "
        "beyond the E-ROI's end until the kidney has left the image; OP-PE (beyond the "
        "paper) OP's pose with the predicted_end pivot.",
        "- V (eq. 25): fraction of the true kidney's 2 mm voxels inside the fan and the "
        "elevational slab of at least one frame (`drake_rus/metrics/core.py`).",
        "- Closed-loop mode (`--mode closed-loop`): each run is a full scan on the Drake "
        "diagram (`RunScan`: approach, exploration, localization, transit, the OP two-leg "
        "pivot) with the run's ER (ER x the patient's kidney length as the controller's "
        "L_m, `exploration_length: fixed`), start, segmenter and registration; its E_trans "
        "and E_rot,x are that scan's. Efficiency: each strategy is its own scan (OP the "
        "run's scan). The scan never reads the simulation truth: GT-OP's and NOP's pivot "
        "poses are computed by the study from the true kidney pose and given to the scan "
        "as a scenario value (`controller.pivot_pose` [x, y, yaw], validated like any "
        "other; the scan then skips exploration and localization: approach over the "
        "kidney's middle, transit to the pose, two-leg pivot), and SL is the scan's "
        "`controller.sweep: line` landing at `controller.start_xy` 10 mm beyond the E-ROI's "
        "end (its costs are its EXPLORE frames'). Every run records per strategy the pose "
        "its pivot used (`pivot_pose`: registered, given; `given_pivot_pose`) and its own "
        "status; a run with any strategy's scan not DONE is left out. OP-PE (the "
        "predicted_end pivot) runs on request. The efficiency scans keep every frame's "
        "kidney mask (`RunScan(keep_sweep_masks=True)`) and reconstruct the kidney from "
        "each strategy's pole-to-pole frames, as the kinematic study does (no NRRD "
        "export in closed-loop mode). Where the product would refuse "
        "what the paper measures, the study's scenario (never the product default) follows "
        "the paper: an exploration planned shorter than the product's "
        "`min_exploration_travel` registers without that minimum and the acceptance checks; "
        "a registration the product rejects stops the scan but its errors are recorded; "
        "runs still without a localization are listed under the run count.",
        "- Kidney volume: masks compounded at 1 mm (nearest-pixel, fan clipping, hole "
        "filling), threshold 0.5, against the kidney mesh's volume.",
        "",
    ]


def _mode_label(text: str) -> str:
    return "closed loop" if text.startswith("closed") else "kinematic"


def _floor_text(er: dict) -> str:
    fl = er.get("floor")
    if not fl:
        return "n/a"
    return (
        f"{_f(fl['e_trans_mm'][0])} +- {_f(fl['e_trans_mm'][1])} mm, "
        f"{_f(fl['e_rot_x_deg'][0])} +- {_f(fl['e_rot_x_deg'][1])} deg"
    )


def _settings_text(settings: dict | None) -> str:
    if not settings:
        return ""
    return (
        f"segmenter `{settings.get('segmenter')}`, registration `{settings.get('method')}`"
        f", scenario `{settings.get('scenario')}`"
    )


def _status_text(counts: dict | None) -> str:
    """Closed-loop scans by status ("DONE 8, ABORT 1"), "-" for kinematic runs."""
    return ", ".join(f"{k} {n}" for k, n in (counts or {}).items()) or "-"


def critical_er_columns(
    names: list[str], ers: list[dict], status: list[dict] | None = None
) -> list[str]:
    """The critical-ER block side by side: per column (and the paper's) the critical ER,
    n, the ER-100% floor, the paired effect size and power at the critical ER, and the
    equivalence ER within the margins."""
    p = PAPER["er_sweep"]
    pp = (ers[0].get("paper_power") or {}) if ers else {}
    m = (ers[0].get("margins") or DEFAULT_MARGINS) if ers else DEFAULT_MARGINS

    def at_critical(e, what):
        row, below = critical_evidence_row(e)
        if row is None:
            return "n/a"
        at = f" (at {_pct(row['er'])}, the ER below)" if below else ""
        return f"{_f(row[f'{what}_e_trans_mm'])} / {_f(row[f'{what}_e_rot_x_deg'])}{at}"

    paper_dz = (
        f"{_f(pp['e_trans_mm']['d_z'])} / {_f(pp['e_rot_x_deg']['d_z'])} (read back from p)"
        if pp
        else "n/a"
    )
    paper_pw = (
        f"{_f(pp['e_trans_mm']['power'])} / {_f(pp['e_rot_x_deg']['power'])}" if pp else "n/a"
    )
    rows = [
        (
            "critical ER (rule of each column's sweep)",
            f"{p['critical_er'] * 100:.0f}%",
            [f"**{_pct(e['critical_er'])}** ({e.get('rule', 'paper')})" for e in ers],
        ),
        ("patients n", f"{PAPER_PATIENTS}", [str(e.get("patients", "?")) for e in ers]),
        ("ER-100% floor (E_trans; E_rot,x)", "not reported", [_floor_text(e) for e in ers]),
        (
            "paired d_z at the critical ER (E_trans / E_rot,x)",
            paper_dz,
            [at_critical(e, "dz") for e in ers],
        ),
        ("power at the critical ER (alpha 0.05)", paper_pw, [at_critical(e, "power") for e in ers]),
        (
            f"equivalence ER (TOST, +-{m['e_trans_mm']:g} mm / +-{m['e_rot_x_deg']:g} deg)",
            "not tested",
            [_pct(e.get("equivalence_er")) for e in ers],
        ),
    ]
    if status and any(status):
        rows.append(
            (
                "closed-loop scans by status (errors of rejected registrations recorded)",
                "-",
                [_status_text(x) for x in status],
            )
        )
    L = [
        "Critical ER and what it rests on, side by side:",
        "",
        "| | paper | " + " | ".join(names) + " |",
        "|---|---|" + "---|" * len(names),
    ]
    L += [f"| {label} | {pap} | " + " | ".join(cells) + " |" for label, pap, cells in rows]
    return L + [""]


def _template_name(col: dict) -> str:
    """A column's template as asked for: generated, real, real:DIR or a file's name."""
    t = str((col.get("template_info") or {}).get("spec") or "generated")
    return Path(t).name if t.endswith(".npz") else t


def _column_names(cols: list[dict]) -> list[str]:
    """The side-by-side columns' names: the mode, and the template and the segmenter where
    the columns differ in them (the oracle named as such)."""
    templates = [_template_name(c) for c in cols]
    segs = [(c.get("settings") or {}).get("segmenter") for c in cols]
    names = []
    for c, t, seg in zip(cols, templates, segs):
        parts = [_mode_label(c["mode"])]
        if len(set(templates)) > 1:
            parts.append(f"{t} template")
        if len(set(segs)) > 1 or seg == "oracle":
            parts.append("ORACLE segmenter" if seg == "oracle" else f"{seg} segmenter")
        names.append(", ".join(parts))
    return names


def compare_markdown(meta: dict, this: dict, others: list[dict]) -> list[str]:
    """The modes and templates OUT holds side by side with the paper: ER sweep (with each
    column's critical ER, floor and equivalence ER), starts, efficiency (OP)."""
    cols = sorted(
        [this, *others],
        key=lambda d: (
            _mode_label(d["mode"]) != "kinematic",
            ((d.get("template_info") or {}).get("spec") or "generated") != "generated",
        ),
    )
    names = _column_names(cols)
    modes = list(dict.fromkeys(_mode_label(c["mode"]) for c in cols))
    templates = list(dict.fromkeys(_template_name(c) for c in cols))
    what = []
    if len(modes) > 1:
        what.append("kinematic twin and closed loop")
    if len(templates) > 1:
        what.append("templates " + " and ".join(templates))
    L = [
        "## Side by side: " + ("; ".join(what) or "segmenters"),
        "",
        provenance(
            meta
            | ({"template": {"label": "each column's (below)"}} if len(templates) > 1 else {})
            | (
                {"segmenter": "each column's (below)"}
                if len({(c.get("settings") or {}).get("segmenter") for c in cols}) > 1
                else {}
            ),
            mode=" and ".join(dict.fromkeys(c["mode"] for c in cols)),
        ),
        "",
        "Columns: "
        + "; ".join(
            f"**{n}**: {_settings_text(c.get('settings'))}, template "
            f"{(c.get('template_info') or {}).get('label') or 'generated'}"
            for n, c in zip(names, cols)
        )
        + ".",
        "",
    ]
    # Each part shows the columns that hold that study (at least two).
    er_names = [n for n, c in zip(names, cols) if c.get("er")]
    ers = [c["er"] for c in cols if c.get("er")]
    if len(ers) >= 2:
        p = PAPER["er_sweep"]
        L += [
            "| ER | paper | "
            + " | ".join(f"{n} E_trans (mm) | {n} E_rot,x (deg)" for n in er_names)
            + " |",
            "|---|---|" + "---|---|" * len(ers),
        ]
        grid = sorted({round(r["er"], 3) for c in ers for r in c["rows"]})
        for g in grid:
            cells = []
            for c in ers:
                r = next((r for r in c["rows"] if abs(r["er"] - g) < 1e-6), None)
                cells.append(
                    "n/a | n/a"
                    if r is None
                    else f"{_f(r['e_trans_mm_mean'])} +- {_f(r['e_trans_mm_sd'])} | "
                    f"{_f(r['e_rot_x_deg_mean'])} +- {_f(r['e_rot_x_deg_sd'])}"
                )
            pap = (
                f"{p['e_trans_mm_at_60'][0]} +- {p['e_trans_mm_at_60'][1]} mm, "
                f"{p['e_rot_x_deg_at_60'][0]} +- {p['e_rot_x_deg_at_60'][1]} deg"
                if abs(g - 0.6) < 1e-6
                else ""
            )
            L.append(f"| {g * 100:.0f}% | {pap} | " + " | ".join(cells) + " |")
        er_status = [(c.get("status") or {}).get("er-sweep") for c in cols if c.get("er")]
        L += [""] + critical_er_columns(er_names, ers, er_status)
    st_names = [n for n, c in zip(names, cols) if c.get("starts")]
    sts = [c["starts"] for c in cols if c.get("starts")]
    if len(sts) >= 2:
        pl = PAPER["localization"]
        L += [
            "Random starts, all runs: paper "
            f"{pl['e_trans_mm'][0]} +- {pl['e_trans_mm'][1]}"
            f" mm, {pl['e_rot_x_deg'][0]} +- {pl['e_rot_x_deg'][1]} deg; "
            + "; ".join(
                f"{n} {_f(c['e_trans_mm'][0])} +- {_f(c['e_trans_mm'][1])} mm, "
                f"{_f(c['e_rot_x_deg'][0])} +- {_f(c['e_rot_x_deg'][1])} deg (any "
                f"significant: {c['any_significant']})"
                for n, c in zip(st_names, sts)
            )
            + ".",
            "",
        ]
    names = [n for n, c in zip(names, cols) if c.get("eff")]
    effs = [c["eff"] for c in cols if c.get("eff")]
    if len(effs) >= 2:
        order = [k for k in STRATEGY_ORDER if any(k in e["summary"] for e in effs)]
        tgt = effs[0].get("V_target", 0.9)
        L += [
            "Efficiency by strategy (mean +- SD over each mode's patients): pole to pole "
            f"(the paper's n, eps, V), the whole pivot (for SL the whole line) and eps to "
            f"first reach V {tgt:g}; `-`: the mode did not run it.",
            "",
            "| strategy | mode | patients | n | eps (mm) | V | n_whole_pivot | "
            f"eps_whole_pivot (mm) | V_whole_pivot | eps to V {tgt:g} (mm) |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for k in order:
            for n, e in zip(names, effs):
                o = e["summary"].get(k)
                if o is None:
                    L.append(f"| {k} | {n} | - | - | - | - | - | - | - | - |")
                    continue
                L.append(
                    f"| {k} | {n} | {len(e['patients'])} | {_f(o['n'][0], 1)} +- "
                    f"{_f(o['n'][1], 1)} | {_f(o['eps_mm'][0], 1)} +- "
                    f"{_f(o['eps_mm'][1], 1)} | {_f(o['V'][0], 3)} | "
                    f"{_f(o['n_whole_pivot'][0], 1)} | "
                    f"{_f(o['eps_whole_pivot_mm'][0], 1)} | {_f(o['V_whole_pivot'][0], 3)} "
                    f"| {_f(o['eps_at_V_mm'][0], 1)} ({o['reached_V']}/"
                    f"{len(e['patients'])}) |"
                )
        L += [""] + strategy_lines(order, CLOSED_LOOP) + [""]
        L += paper_comparison_table(names, effs)
    return L


def write_closed_loop_outputs(out_dir, results) -> Path:
    """closed_loop.csv: each closed-loop scan beside its kinematic twin."""
    rows = []
    for r in results:
        for mode in ("closed_loop", "kinematic"):
            e = r[mode]
            rows.append(
                {
                    "patient": r["patient"],
                    "mode": mode,
                    "er": r["er"],
                    "er_unit": e.get("er_unit", ""),
                    "status": e.get("status", ""),
                    "e_trans_mm": e["e_trans_mm"],
                    "e_rot_x_deg": e["e_rot_x_deg"],
                    "n": e["n"],
                    "eps_mm": e["eps_mm"],
                    "V": e["V"],
                    "n_whole_pivot": e.get("n_whole_pivot"),
                    "eps_whole_pivot_mm": e.get("eps_whole_pivot_mm"),
                    "V_whole_pivot": e.get("V_whole_pivot"),
                    "tilt_cap_legs": " ".join(str(x) for x in e.get("tilt_cap_legs") or []),
                    "wall_s": e["wall_s"],
                    "sim_s": e.get("sim_s"),
                }
            )
    return write_csv_atomic(Path(out_dir) / "closed_loop.csv", rows)
