"""Statistics of the seed's section III studies on finished run results (plain dicts).

- :func:`analyze_er_sweep` (III-C, Fig. 7d): per exploration ratio, paired t-tests
  (``scipy.stats.ttest_rel``) of E_trans and E_rot,x against ER 100%. Critical ER = the
  smallest ER from which on every ER is not significantly different from 100% (p > 0.05)
  in both errors (the seed: "the smallest ER at which both errors are not significantly
  different"; requiring it for the larger ERs too guards against a lucky low ER).
- :func:`analyze_starts` (III-D, Fig. 9d): pairwise paired t-tests of the random starts
  over patients with Bonferroni correction (5 starts, 10 pairs: p < 0.005).
- :func:`analyze_efficiency` (III-E, Fig. 10): totals per strategy, OP against the others
  (paired, Bonferroni over the comparisons), reconstructed kidney volume errors;
  :func:`mean_curve` averages V against n or eps over patients.

:data:`PAPER` holds the seed paper's numbers the report puts beside ours.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import ttest_rel

# Strategies of the efficiency study, in table order.
STRATEGY_ORDER = ("OP", "GT-OP", "NOP", "SL")
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


def analyze_er_sweep(results: list[dict], alpha: float = 0.05) -> dict:
    """Per ER: mean/SD of both errors, paired p-values against ER 100%; the critical ER."""
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
    critical = ref_er
    for row in reversed(rows):
        ok = (row["p_e_trans"] > alpha or not np.isfinite(row["p_e_trans"])) and \
             (row["p_e_rot_x"] > alpha or not np.isfinite(row["p_e_rot_x"]))
        if not ok:
            break
        critical = row["er"]
    first_ok = next((r["er"] for r in rows if r["p_e_trans"] > alpha and r["p_e_rot_x"] > alpha),
                    ref_er)
    return {"rows": rows, "critical_er": critical, "first_not_significant_er": first_ok,
            "reference_er": ref_er, "alpha": alpha}


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


def analyze_efficiency(results: list[dict], alpha: float = 0.05) -> dict:
    """Totals per strategy, OP against the others (paired, Bonferroni), volume errors."""
    results = sorted(results, key=lambda r: r["patient"])
    per = {s: {"n": [], "eps_mm": [], "V": [], "volume_error_pct": []} for s in STRATEGY_ORDER}
    for r in results:
        for s in STRATEGY_ORDER:
            e = r["strategies"][s]
            per[s]["n"].append(e["n"])
            per[s]["eps_mm"].append(e["eps_mm"])
            per[s]["V"].append(e["V"])
            per[s]["volume_error_pct"].append(e["volume_error_pct"])
    summary = {}
    for s in STRATEGY_ORDER:
        summary[s] = {k: mean_sd(v) for k, v in per[s].items()}
        ve = [abs(x) for x in per[s]["volume_error_pct"] if x is not None]
        summary[s]["abs_volume_error_pct"] = mean_sd(ve)
        summary[s]["within_5pct"] = int(sum(x <= 5 for x in ve))
    others = [s for s in STRATEGY_ORDER if s != "OP"]
    m = 2 * len(others)
    comparisons = []
    for s in others:
        for key in ("n", "eps_mm"):
            a, b = np.asarray(per["OP"][key], float), np.asarray(per[s][key], float)
            p = paired_p(a, b)
            comparisons.append({
                "comparison": f"OP vs {s}", "metric": key,
                "reduction_mean": float(np.mean(b - a)) if len(a) else float("nan"),
                "reduction_sd": float(np.std(b - a, ddof=1)) if len(a) > 1 else 0.0,
                "op_lower_count": int(np.sum(a < b)), "patients": int(len(a)),
                "p": p, "significant": bool(p < alpha / m)})
    return {"per_patient": per, "summary": summary, "comparisons": comparisons,
            "bonferroni_threshold": alpha / m, "patients": [r["patient"] for r in results]}


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

