"""Statistics of the seed's section III studies on finished run results (plain dicts).

- :func:`analyze_er_sweep` (III-C, Fig. 7d): per exploration ratio, paired t-tests
  (``scipy.stats.ttest_rel``) of E_trans and E_rot,x against ER 100%. Critical ER
  (:func:`critical_er`), rule ``paper`` (default, the seed's IV-A): the smallest ER at which
  neither error differs significantly from ER 100% (p > 0.05); rule ``strict`` (ours, an
  option): the smallest ER from which on EVERY larger ER passes too (guards against a lucky
  low ER).
- :func:`analyze_starts` (III-D, Fig. 9d): pairwise paired t-tests of the random starts
  over patients with Bonferroni correction (5 starts, 10 pairs: p < 0.005).
- :func:`analyze_template` (beyond the paper): errors against the template's distance from
  the patient for template variants (mean, scaled, single kidney, leave-one-out, another
  population's template), generated patients and real bodies apart.
- :func:`analyze_efficiency` (III-E, Fig. 10): totals per strategy pole to pole (the
  paper's), over the whole pivot and at matched coverage (n and eps to reach V = 0.9), OP
  against the paper's other strategies (paired, Bonferroni over each definition's
  comparisons), OP-PE (beyond the paper: the predicted-end pivot) against OP, how often the
  tilt cap ended a pivot leg, reconstructed kidney volume errors;
  :func:`mean_curve` averages V against n or eps over patients.

:data:`PAPER` holds the seed paper's numbers the report puts beside ours.
"""

from __future__ import annotations

import re

import numpy as np
from scipy.stats import ttest_rel

# Strategies of the efficiency study, in table order: the paper's four (III-E), then ours
# beyond it (OP-PE: OP's pivot pose with the predicted_end pivot instead of the two-leg one).
PAPER_STRATEGIES = ("OP", "GT-OP", "NOP", "SL")
BEYOND_PAPER_STRATEGIES = ("OP-PE",)
STRATEGY_ORDER = PAPER_STRATEGIES + BEYOND_PAPER_STRATEGIES
# A beyond-the-paper strategy is compared with the paper's strategy it replaces.
COMPARED_WITH = {"OP-PE": "OP"}
# The seed paper's numbers.
PAPER = {
    "er_sweep": {"critical_er": 0.6, "p_e_trans_at_60": 0.0744, "p_e_rot_at_60": 0.3523,
                 "e_trans_mm_at_60": (10.81, 7.08), "e_rot_x_deg_at_60": (11.58, 7.61)},
    "localization": {"e_trans_mm": (8.73, 6.93), "e_rot_x_deg": (12.86, 20.86)},
    "starts": "no significant difference between the five starts (10 paired t-tests, "
              "Bonferroni p > 0.005) in either error",
    "efficiency": {"eps_reduction_vs_SL_mm": (1.71, 29.62),
                   "eps_reduction_vs_NOP_mm": (24.66, 21.50),
                   "eps_extra_vs_GT_OP_mm": (11.71, 12.60)},
    "volume_loa": "+-18% limits of agreement, freehand 3-D US vs MRI (Bakker 1999)",
}


def paired_p(a, b) -> float:
    """Two-sided paired t-test p-value; 1.0 when the differences are all zero."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    if len(a) < 2:
        return float("nan")
    d = a - b
    if np.allclose(d, d[0]) and np.allclose(d, 0):
        return 1.0
    p = float(ttest_rel(a, b).pvalue)
    return 1.0 if not np.isfinite(p) else p


def mean_sd(v) -> tuple[float, float]:
    """Mean and sample SD (ddof = 1; 0 for one value) of the values that are not None."""
    v = np.asarray([x for x in v if x is not None], float)
    if len(v) == 0:
        return float("nan"), float("nan")
    return float(v.mean()), float(v.std(ddof=1)) if len(v) > 1 else 0.0


CRITICAL_ER_RULES = {
    "paper": "the smallest ER at which neither E_trans nor E_rot,x differs from ER 100% "
             "(paired t-test, p > alpha): the seed's rule (IV-A)",
    "strict": "the smallest ER from which on every ER (it and all larger) differs from ER "
              "100% in neither error (p > alpha): ours, stricter",
}


def _passes(row: dict, alpha: float) -> bool:
    """Neither error significantly different from the reference (NaN p: too few to test)."""
    return all(not np.isfinite(row[k]) or row[k] > alpha for k in ("p_e_trans", "p_e_rot_x"))


def critical_er(rows: list[dict], alpha: float = 0.05, rule: str = "paper") -> float:
    """The critical ER of rows (``er``, ``p_e_trans``, ``p_e_rot_x``; any order) under
    ``rule`` (:data:`CRITICAL_ER_RULES`); the largest ER (the reference) when none passes."""
    if rule not in CRITICAL_ER_RULES:
        raise ValueError(f"critical-ER rule: expected one of {', '.join(CRITICAL_ER_RULES)}, "
                         f"got {rule!r}")
    rows = sorted(rows, key=lambda r: r["er"])
    if not rows:
        raise ValueError("critical ER: no rows")
    if rule == "paper":
        return next((r["er"] for r in rows if _passes(r, alpha)), rows[-1]["er"])
    critical = rows[-1]["er"]
    for row in reversed(rows):
        if not _passes(row, alpha):
            break
        critical = row["er"]
    return critical


def analyze_er_sweep(results: list[dict], alpha: float = 0.05, rule: str = "paper") -> dict:
    """Per ER: mean/SD of both errors, paired p-values against ER 100%; the critical ER under
    ``rule`` ("paper" or "strict", :func:`critical_er`) and under both rules."""
    by = {}
    for r in results:
        by.setdefault(round(r["er"], 3), {})[r["patient"]] = r
    ers = sorted(by)
    if not ers:
        raise ValueError("er-sweep: no results")
    ref_er = max(ers)
    ref = by[ref_er]
    rows = []
    for er in ers:
        common = sorted(set(by[er]) & set(ref))
        et = [by[er][p]["e_trans_mm"] for p in common]
        erx = [by[er][p]["e_rot_x_deg"] for p in common]
        rows.append({
            "er": er, "n": len(common),
            "e_trans_mm_mean": mean_sd(et)[0], "e_trans_mm_sd": mean_sd(et)[1],
            "e_rot_x_deg_mean": mean_sd(erx)[0], "e_rot_x_deg_sd": mean_sd(erx)[1],
            "p_e_trans": paired_p(et, [ref[p]["e_trans_mm"] for p in common]),
            "p_e_rot_x": paired_p(erx, [ref[p]["e_rot_x_deg"] for p in common]),
            "registration_ms_mean": mean_sd([by[er][p]["registration_ms"] for p in common])[0],
            "points_mean": mean_sd([by[er][p]["points"] for p in common])[0],
        })
    both = {k: critical_er(rows, alpha, k) for k in CRITICAL_ER_RULES}
    units = sorted({str(r.get("er_unit", "fixed")) for r in results})
    lengths = [r["kidney_length_mm"] for r in results if r.get("kidney_length_mm") is not None]
    return {"rows": rows, "critical_er": both[rule], "rule": rule,
            "rule_text": CRITICAL_ER_RULES[rule],
            "critical_er_paper_rule": both["paper"], "critical_er_strict_rule": both["strict"],
            "first_not_significant_er": both["paper"], "reference_er": ref_er, "alpha": alpha,
            "er_unit": units[0] if len(units) == 1 else units,
            "kidney_length_mm": (mean_sd(lengths), float(min(lengths)), float(max(lengths)))
            if lengths else None}


def analyze_starts(results: list[dict], alpha: float = 0.05) -> dict:
    """Pairwise paired t-tests between starts over patients, Bonferroni-corrected."""
    by = {}
    for r in results:
        by.setdefault(int(r["start"]), {})[r["patient"]] = r
    starts = sorted(by)
    pairs = [(a, b) for i, a in enumerate(starts) for b in starts[i + 1:]]
    m = max(1, len(pairs))
    tests = []
    for a, b in pairs:
        common = sorted(set(by[a]) & set(by[b]))
        row = {"start_a": a, "start_b": b, "n": len(common)}
        for key in ("e_trans_mm", "e_rot_x_deg"):
            p = paired_p([by[a][q][key] for q in common], [by[b][q][key] for q in common])
            row[f"p_{key}"] = p
            row[f"significant_{key}"] = bool(p < alpha / m)
        tests.append(row)
    per_start = []
    for s in starts:
        vals = list(by[s].values())
        per_start.append({"start": s, "n": len(vals),
                          "e_trans_mm_mean": mean_sd([v["e_trans_mm"] for v in vals])[0],
                          "e_trans_mm_sd": mean_sd([v["e_trans_mm"] for v in vals])[1],
                          "e_rot_x_deg_mean": mean_sd([v["e_rot_x_deg"] for v in vals])[0],
                          "e_rot_x_deg_sd": mean_sd([v["e_rot_x_deg"] for v in vals])[1]})
    allv = [r for r in results]
    return {"per_start": per_start, "tests": tests, "bonferroni_threshold": alpha / m,
            "any_significant": any(t["significant_e_trans_mm"] or t["significant_e_rot_x_deg"]
                                   for t in tests),
            "e_trans_mm": mean_sd([r["e_trans_mm"] for r in allv]),
            "e_rot_x_deg": mean_sd([r["e_rot_x_deg"] for r in allv])}


# Metric keys of a strategy entry per definition (module ``drake_rus.metrics.sweep``).
EFFICIENCY_DEFINITIONS = {
    "pole_to_pole": ("n", "eps_mm"),
    "whole_pivot": ("n_whole_pivot", "eps_whole_pivot_mm"),
}


def _entry_value(e: dict, key: str):
    """A strategy entry's value; the whole pivot's under its old name (``*_full``) in runs
    written before the definitions were named."""
    old = {"n_whole_pivot": "n_full", "eps_whole_pivot_mm": "eps_full_mm",
           "V_whole_pivot": "V_full"}
    return e.get(key, e.get(old.get(key, key)))


def _at(e: dict, target: str, key: str, field: str):
    r = (e.get(key) or {}).get(target)
    return None if r is None else r[field]


def analyze_efficiency(results: list[dict], alpha: float = 0.05, V_target: float = 0.9) -> dict:
    """Totals per strategy pole to pole (the paper's) and over the whole pivot, n and eps to
    reach ``V_target`` (matched coverage; patients that never reach it are left out of that
    comparison), OP against the others (paired, Bonferroni over each definition's
    comparisons), tilt-cap counts, volume errors."""
    results = sorted(results, key=lambda r: r["patient"])
    tgt = f"{V_target:g}"
    keys = ("n", "eps_mm", "V", "n_whole_pivot", "eps_whole_pivot_mm", "V_whole_pivot",
            "n_at_V", "eps_at_V_mm", "n_at_V_whole_pivot", "eps_at_V_whole_pivot_mm",
            "volume_error_pct")
    # The strategies every run has (a study may have run only some), in the report's order.
    order = [s for s in STRATEGY_ORDER if results and all(s in r["strategies"] for r in results)]
    per = {s: {k: [] for k in keys} | {"tilt_cap_legs": []} for s in order}
    for r in results:
        for s in order:
            e = r["strategies"][s]
            for k in ("n", "eps_mm", "V", "n_whole_pivot", "eps_whole_pivot_mm",
                      "V_whole_pivot", "volume_error_pct"):
                per[s][k].append(_entry_value(e, k))
            per[s]["n_at_V"].append(_at(e, tgt, "at_V", "n"))
            per[s]["eps_at_V_mm"].append(_at(e, tgt, "at_V", "eps_mm"))
            per[s]["n_at_V_whole_pivot"].append(_at(e, tgt, "at_V_whole_pivot", "n"))
            per[s]["eps_at_V_whole_pivot_mm"].append(_at(e, tgt, "at_V_whole_pivot", "eps_mm"))
            per[s]["tilt_cap_legs"].append(list(e.get("tilt_cap_legs") or []))
    summary = {}
    for s in order:
        summary[s] = {k: mean_sd(per[s][k]) for k in keys}
        ve = [abs(x) for x in per[s]["volume_error_pct"] if x is not None]
        summary[s]["abs_volume_error_pct"] = mean_sd(ve)
        summary[s]["within_5pct"] = int(sum(x <= 5 for x in ve))
        summary[s]["reached_V"] = int(sum(x is not None for x in per[s]["n_at_V"]))
        summary[s]["tilt_cap_patients"] = int(sum(bool(x) for x in per[s]["tilt_cap_legs"]))
        summary[s]["tilt_cap_leg_counts"] = {
            str(leg): int(sum(leg in x for x in per[s]["tilt_cap_legs"])) for leg in (1, 2)}
    # The paper's family: OP against the paper's other strategies (Bonferroni over them);
    # beyond it, each of ours against the strategy it replaces (its own family).
    others = [s for s in order if s != "OP" and s in PAPER_STRATEGIES] if "OP" in order else []
    pairs_of = [("OP", s, max(1, 2 * len(others))) for s in others]
    pairs_of += [(s, COMPARED_WITH[s], 2) for s in order
                 if s in BEYOND_PAPER_STRATEGIES and COMPARED_WITH[s] in order]
    m = max(1, 2 * len(others))
    families = dict(EFFICIENCY_DEFINITIONS)
    families[f"at_V{tgt}"] = ("n_at_V", "eps_at_V_mm")
    comparisons = []
    for definition, metric_keys in families.items():
        for ours, s, m_family in pairs_of:
            for key in metric_keys:
                pairs = [(a, b) for a, b in zip(per[ours][key], per[s][key])
                         if a is not None and b is not None]
                a = np.asarray([x for x, _ in pairs], float)
                b = np.asarray([y for _, y in pairs], float)
                p = paired_p(a, b)
                comparisons.append({
                    "definition": definition, "comparison": f"{ours} vs {s}",
                    "metric": "n" if key.startswith("n") else "eps_mm",
                    "reduction_mean": float(np.mean(b - a)) if len(a) else float("nan"),
                    "reduction_sd": float(np.std(b - a, ddof=1)) if len(a) > 1 else 0.0,
                    # how often the first-named strategy was lower (OP in the paper's pairs)
                    "op_lower_count": int(np.sum(a < b)), "patients": int(len(a)),
                    "p": p, "bonferroni_threshold": alpha / m_family,
                    "significant": bool(np.isfinite(p) and p < alpha / m_family)})
    return {"per_patient": per, "summary": summary, "comparisons": comparisons,
            "bonferroni_threshold": alpha / m, "V_target": V_target,
            "patients": [r["patient"] for r in results]}


DISTANCE_BINS_MM = (0.0, 3.0, 4.0, 5.0, 7.0, float("inf"))


def template_group(r: dict) -> str:
    """The group of a template-study run in the tables: ``generated`` (the virtual patients,
    ``seed:N``/``train:K``/``test:K``) or the real body's folder or file name; ``, decubitus``
    appended for left-lateral-decubitus runs."""
    spec = str(r["patient"])
    kind = r.get("patient_kind") or ("generated" if re.fullmatch(r"(test|train|seed):\d+", spec)
                                     else "real")
    name = "generated" if kind == "generated" else spec.rstrip("/").split("/")[-1]
    return name + (", decubitus" if r.get("posture") == "left_lateral_decubitus" else "")


def _trend(results: list[dict]) -> dict:
    d = np.asarray([r["template_distance_mm"] for r in results], float)
    trend = {}
    for key in ("e_trans_mm", "e_rot_x_deg"):
        y = np.asarray([r[key] for r in results], float)
        if len(d) > 2 and np.ptp(d) > 0 and np.ptp(y) > 0:
            fit = np.polyfit(d, y, 1)
            trend[key] = {"r": float(np.corrcoef(d, y)[0, 1]), "slope_per_mm": float(fit[0]),
                          "intercept": float(fit[1]), "runs": int(len(d))}
        else:
            trend[key] = {"r": float("nan"), "slope_per_mm": float("nan"),
                          "intercept": float("nan"), "runs": int(len(d))}
    return trend


def analyze_template(results: list[dict]) -> dict:
    """Template-mismatch study: per patient group (:func:`template_group`: the generated
    patients together, each real body on its own) and template variant the template's
    distance from the patients' kidneys and both errors (mean, SD), paired t-tests of each
    variant's errors against the mean template's on the same patients; the Pearson
    correlation and least-squares line of each error against the template distance over the
    generated patients' runs (``trend``) and over all runs (``trend_all``); the errors in
    bins of template distance (``bins``, all runs)."""
    groups = {}
    for r in results:
        groups.setdefault(template_group(r), {}).setdefault(r["template_variant"], {})[
            r["patient"]] = r
    rows = []
    for g in sorted(groups, key=lambda g: (g != "generated", g)):
        by = groups[g]
        ref = by.get("mean", {})
        for v in sorted(by, key=_variant_order):
            runs = by[v]
            vals = list(runs.values())
            common = sorted(set(runs) & set(ref))
            row = {"group": g, "variant": v, "n": len(vals)}
            for key in ("template_distance_mm", "e_trans_mm", "e_rot_x_deg"):
                row[f"{key}_mean"], row[f"{key}_sd"] = mean_sd([x[key] for x in vals])
            for key in ("e_trans_mm", "e_rot_x_deg"):
                row[f"p_{key}_vs_mean"] = (paired_p([runs[q][key] for q in common],
                                                    [ref[q][key] for q in common])
                                           if v != "mean" else float("nan"))
            ext = [x.get("template_extent_mm") for x in vals if x.get("template_extent_mm")]
            row["template_length_mm"] = float(ext[0][0]) if ext else float("nan")
            rows.append(row)
    generated = [r for r in results if template_group(r).startswith("generated")]
    bins = []
    d = np.asarray([r["template_distance_mm"] for r in results], float)
    for lo, hi in zip(DISTANCE_BINS_MM[:-1], DISTANCE_BINS_MM[1:]):
        sel = [r for r, x in zip(results, d) if lo <= x < hi]
        if not sel:
            continue
        b = {"from_mm": lo, "to_mm": hi, "n": len(sel),
             "real_runs": sum(1 for r in sel if not template_group(r).startswith("generated"))}
        for key in ("template_distance_mm", "e_trans_mm", "e_rot_x_deg"):
            b[f"{key}_mean"], b[f"{key}_sd"] = mean_sd([r[key] for r in sel])
        bins.append(b)
    return {"rows": rows, "trend": _trend(generated or results), "trend_all": _trend(results),
            "bins": bins, "groups": list(dict.fromkeys(r["group"] for r in rows)),
            "patients": sorted({r["patient"] for r in results}),
            "er": sorted({r["er"] for r in results})}


def _variant_order(v: str):
    """mean first, then the scaled, single, leave-one-out and population templates."""
    order = ("mean", "scale-", "single:", "loo", "population:")
    k = next((i for i, p in enumerate(order) if v.startswith(p)), len(order))
    return (k, v)


def mean_curve(results: list[dict], strategy: str, x_key: str, grid: np.ndarray) -> np.ndarray:
    """Mean over patients of V as a function of n (x_key "n") or eps (mm, "eps"), each
    patient's curve held at its final V past its end."""
    curves = []
    for r in results:
        e = r["strategies"][strategy]
        V = np.asarray(e["curve_V"], float)
        if len(V) == 0:
            curves.append(np.zeros_like(grid))
            continue
        x = np.arange(1, len(V) + 1, dtype=float) if x_key == "n" else np.asarray(
            e["curve_eps_mm"], float)
        curves.append(np.interp(grid, x, V, left=0.0, right=V[-1]))
    return np.mean(curves, axis=0) if curves else np.zeros_like(grid)

