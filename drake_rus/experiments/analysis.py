"""Statistics of the seed's section III studies on finished run results (plain dicts).

- :func:`analyze_er_sweep` (III-C, Fig. 7d): per exploration ratio, paired t-tests
  (``scipy.stats.ttest_rel``) of E_trans and E_rot,x against ER 100%. Critical ER
  (:func:`critical_er`), rule ``paper`` (default, the seed's IV-A): the smallest ER at which
  neither error differs significantly from ER 100% (p > 0.05); rule ``strict`` (ours, an
  option): the smallest ER from which on EVERY larger ER passes too (guards against a lucky
  low ER). Beside it, what a reader needs to weigh it (issue 27): the ER-100% floor, the
  paired effect size (Cohen's d_z, :func:`cohens_dz`) and the test's power
  (:func:`paired_t_power`, noncentral t) at each ER, equivalence to ER 100% within a clinical
  margin (:func:`tost_paired`, two one-sided paired t-tests) and the sample size below which
  the critical ER is weakly supported (:func:`minimum_patients`, from a power calculation).
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

import functools
import math
import re

import numpy as np
from scipy import stats
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
    "er_sweep": {
        "critical_er": 0.6,
        "p_e_trans_at_60": 0.0744,
        "p_e_rot_at_60": 0.3523,
        "e_trans_mm_at_60": (10.81, 7.08),
        "e_rot_x_deg_at_60": (11.58, 7.61),
    },
    "localization": {"e_trans_mm": (8.73, 6.93), "e_rot_x_deg": (12.86, 20.86)},
    "starts": "no significant difference between the five starts (10 paired t-tests, "
    "Bonferroni p > 0.005) in either error",
    "efficiency": {
        "eps_reduction_vs_SL_mm": (1.71, 29.62),
        "eps_reduction_vs_NOP_mm": (24.66, 21.50),
        "eps_extra_vs_GT_OP_mm": (11.71, 12.60),
    },
    "volume_loa": "+-18% limits of agreement, freehand 3-D US vs MRI (Bakker 1999)",
}
# The paper's ER study: 15 simulated patients, paired t-tests at alpha 0.05 (III-C, IV-A).
PAPER_PATIENTS = 15
ALPHA = 0.05
# The two errors of the ER sweep: (result key, unit, default clinical equivalence margin).
# +-5 mm / +-5 deg: the margin the report states (a CLI option, --margin-mm/--margin-deg).
ERRORS = (("e_trans_mm", "mm", 5.0), ("e_rot_x_deg", "deg", 5.0))
DEFAULT_MARGINS = {k: m for k, _, m in ERRORS}
# The minimum sample size of the ER study: the smallest n at which a two-sided paired t-test
# at ALPHA has MIN_N_POWER power to detect a large paired effect, Cohen's d_z = MIN_N_EFFECT
# (15 patients: the paper's own number). Below it, "no significant difference" is weak
# evidence (it would miss even a large effect more often than 1 time in 5).
MIN_N_EFFECT = 0.8
MIN_N_POWER = 0.8


def paired_p(a, b) -> float:
    """Two-sided paired t-test p-value; 1.0 when the differences are all zero; NaN for fewer
    than two pairs or a non-finite difference (a missing error is not "no difference")."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    if len(a) < 2:
        return float("nan")
    d = a - b
    if not np.all(np.isfinite(d)):
        return float("nan")
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


# ------------------------------------------------------------------------------- power
def cohens_dz(differences) -> float:
    """Cohen's d_z of paired differences: their mean over their SD (ddof 1). NaN for fewer
    than two or a non-finite difference; with zero SD, 0 (all differences zero) or +-inf."""
    d = np.asarray(differences, float)
    if len(d) < 2 or not np.all(np.isfinite(d)):
        return float("nan")
    sd = float(d.std(ddof=1))
    mean = float(d.mean())
    if sd == 0 or not np.isfinite(sd):
        return 0.0 if mean == 0 else math.copysign(math.inf, mean)
    return mean / sd


def paired_t_power(d_z: float, n: int, alpha: float = ALPHA) -> float:
    """Power of the two-sided paired t-test at ``alpha`` with ``n`` pairs against a true
    effect ``d_z``: P(|T| > t_(1-alpha/2, n-1)) with T noncentral t, n - 1 degrees of
    freedom, noncentrality d_z sqrt(n). NaN for n < 2 or a NaN effect; 1 for an infinite
    one."""
    if n < 2 or not np.isfinite(alpha) or d_z is None or np.isnan(d_z):
        return float("nan")
    if np.isinf(d_z):
        return 1.0
    df = n - 1
    t_crit = stats.t.isf(alpha / 2, df)
    ncp = abs(float(d_z)) * math.sqrt(n)
    upper = float(stats.nct.sf(t_crit, df, ncp))
    # The far tail, P(T < -t_crit) <= P(Z + ncp < 0) = Phi(-ncp): scipy's noncentral t
    # returns NaN there for large ncp, where it is below that bound anyway.
    lower = float(stats.nct.cdf(-t_crit, df, ncp))
    bound = float(stats.norm.cdf(-ncp))
    lower = min(lower, bound) if np.isfinite(lower) else bound
    if not np.isfinite(upper):
        return float("nan")
    return min(1.0, upper + lower)


def paired_n_for_power(
    d_z: float, power: float = MIN_N_POWER, alpha: float = ALPHA, n_max: int = 100_000
) -> int | None:
    """The smallest number of pairs n >= 2 at which the two-sided paired t-test at ``alpha``
    reaches ``power`` against an effect ``d_z`` (None: not within ``n_max``)."""
    if not (np.isfinite(d_z) and d_z != 0):
        return 2 if np.isinf(d_z) else None
    lo, hi = 2, 2
    while paired_t_power(d_z, hi, alpha) < power:  # power grows with n: bracket, bisect
        if hi >= n_max:
            return None
        lo, hi = hi, min(n_max, hi * 2)
    while lo < hi:
        mid = (lo + hi) // 2
        if paired_t_power(d_z, mid, alpha) >= power:
            hi = mid
        else:
            lo = mid + 1
    return hi


@functools.cache
def minimum_patients(
    effect: float = MIN_N_EFFECT, power: float = MIN_N_POWER, alpha: float = ALPHA
) -> int:
    """The ER study's minimum number of patients (:data:`MIN_N_EFFECT`)."""
    return paired_n_for_power(effect, power, alpha)


def minimum_patients_text() -> str:
    return (
        f"{minimum_patients()} patients: the smallest n at which a two-sided paired "
        f"t-test at alpha {ALPHA:g} has {MIN_N_POWER:.0%} power to detect a large "
        f"paired effect (Cohen's d_z = {MIN_N_EFFECT:g})"
    )


def tost_paired(differences, margin: float, alpha: float = ALPHA) -> dict:
    """Equivalence of paired measurements within +-``margin`` by two one-sided paired
    t-tests (TOST): H0 mean difference <= -margin, and >= +margin. ``p`` is the larger of
    the two one-sided p-values; ``equivalent`` if p < alpha, i.e. the (1 - 2 alpha)
    confidence interval of the mean difference (``ci``) lies inside (-margin, margin)."""
    d = np.asarray(differences, float)
    n = len(d)
    out = {
        "margin": float(margin),
        "n": int(n),
        "p": float("nan"),
        "equivalent": False,
        "ci": (float("nan"), float("nan")),
        "mean": float("nan"),
    }
    if n < 2:
        return out
    mean, sd = float(d.mean()), float(d.std(ddof=1))
    out["mean"] = mean
    if sd == 0:
        inside = -margin < mean < margin
        out.update(p=0.0 if inside else 1.0, equivalent=bool(inside), ci=(mean, mean))
        return out
    se = sd / math.sqrt(n)
    df = n - 1
    p_lower = float(stats.t.sf((mean + margin) / se, df))  # H0: mean <= -margin
    p_upper = float(stats.t.cdf((mean - margin) / se, df))  # H0: mean >= +margin
    half = float(stats.t.isf(alpha, df)) * se
    p = max(p_lower, p_upper)
    out.update(p=p, equivalent=bool(p < alpha), ci=(mean - half, mean + half))
    return out


def d_z_from_p(p: float, n: int) -> float:
    """The paired effect size |d_z| that a two-sided paired t-test with ``n`` pairs turns
    into the p-value ``p``: t_(1-p/2, n-1) / sqrt(n) (e.g. the paper's, from its p)."""
    return float(stats.t.isf(p / 2, n - 1) / math.sqrt(n))


def paper_er_power() -> dict:
    """The paper's ER test at 60% read back through the t distribution: its p-values with
    its 15 patients give the observed |d_z| of each error and the power of its test against
    that effect."""
    out = {}
    for key, p in (
        ("e_trans_mm", PAPER["er_sweep"]["p_e_trans_at_60"]),
        ("e_rot_x_deg", PAPER["er_sweep"]["p_e_rot_at_60"]),
    ):
        d = d_z_from_p(p, PAPER_PATIENTS)
        out[key] = {"p": p, "d_z": d, "power": paired_t_power(d, PAPER_PATIENTS)}
    return out


CRITICAL_ER_RULES = {
    "paper": "the smallest ER at which neither E_trans nor E_rot,x differs from ER 100% "
    "(paired t-test, p > alpha): the seed's rule (IV-A)",
    "strict": "the smallest ER from which on every ER (it and all larger) differs from ER "
    "100% in neither error (p > alpha): ours, stricter",
}
# Both rules (and the equivalence ER) pass over an ER at which a patient localized at ER
# 100% has no localization: a scan that cannot localize is a failure of that ER, not "no
# different" (left out, it once made a sweep whose ER-10% scans mostly failed report a
# critical ER of 10% from the few that did not).
ALL_LOCALIZED_TEXT = (
    "an ER at which a patient localized at ER 100% has no localization cannot be it"
)


def _all_localized(row: dict) -> bool:
    """Every patient with a run at the reference ER has a localization at this ER too
    (``missing``: how many have none; 0 when the row does not say)."""
    return row.get("missing", 0) == 0


def _testable(row: dict) -> bool:
    """At least two paired runs, both p-values (a paired test was possible) and no patient
    without a localization at this ER."""
    return (
        row.get("n", 2) >= 2
        and all(np.isfinite(row[k]) for k in ("p_e_trans", "p_e_rot_x"))
        and _all_localized(row)
    )


def _passes(row: dict, alpha: float) -> bool:
    """Neither error significantly different from the reference (and a test was possible:
    one patient says nothing)."""
    return _testable(row) and all(row[k] > alpha for k in ("p_e_trans", "p_e_rot_x"))


def _smallest(rows: list[dict], ok, rule: str) -> float | None:
    """The smallest ER whose row is ``ok`` (rule "paper") or from which on every row is
    (rule "strict"); None when there is none."""
    rows = sorted(rows, key=lambda r: r["er"])
    if rule == "paper":
        return next((r["er"] for r in rows if ok(r)), None)
    found = None
    for row in reversed(rows):
        if not ok(row):
            break
        found = row["er"]
    return found


def critical_er(rows: list[dict], alpha: float = ALPHA, rule: str = "paper") -> float | None:
    """The critical ER of rows (``er``, ``n``, ``p_e_trans``, ``p_e_rot_x``; any order) under
    ``rule`` (:data:`CRITICAL_ER_RULES`): None when no ER can be tested (fewer than two
    paired runs), else at worst the reference itself."""
    if rule not in CRITICAL_ER_RULES:
        raise ValueError(
            f"critical-ER rule: expected one of {', '.join(CRITICAL_ER_RULES)}, got {rule!r}"
        )
    if not rows:
        raise ValueError("critical ER: no rows")
    return _smallest(rows, lambda r: _passes(r, alpha), rule)


def equivalence_er(rows: list[dict], rule: str = "paper") -> float | None:
    """The smallest ER equivalent to ER 100% in both errors (TOST within the margins, the
    rows' ``equivalent_*``) with every patient localized (as :func:`critical_er`) under
    ``rule``; None if none is."""
    keys = [f"equivalent_{k}" for k, _, _ in ERRORS]
    return _smallest(rows, lambda r: _all_localized(r) and all(r.get(k) for k in keys), rule)


REFERENCE_ER = 1.0


def analyze_er_sweep(
    results: list[dict], alpha: float = ALPHA, rule: str = "paper", margins: dict | None = None
) -> dict:
    """Per ER: mean/SD of both errors, paired p-values against the reference ER 100% (the
    paper's), and per error the paired differences (mean, SD), Cohen's d_z, the power of
    the paired t-test at ``alpha`` against that effect with that n, and equivalence (TOST)
    within ``margins`` ({"e_trans_mm": mm, "e_rot_x_deg": deg}, default +-5 / +-5); the
    critical ER under ``rule`` ("paper" or "strict", :func:`critical_er`) and both rules,
    the equivalence ER likewise, the ER-100% floor, the number of patients against
    :func:`minimum_patients`, and the paper's test read back the same way."""
    margins = dict(DEFAULT_MARGINS, **(margins or {}))
    by = {}
    for r in results:
        by.setdefault(round(r["er"], 3), {})[r["patient"]] = r
    ers = sorted(by)
    if not ers:
        raise ValueError("er-sweep: no results")
    if REFERENCE_ER not in by:
        raise ValueError(
            "er-sweep: no run at the reference ER 100% (every ER is compared "
            "with it); --ers must include 1"
        )
    ref = by[REFERENCE_ER]
    rows = []
    for er in ers:
        common = sorted(set(by[er]) & set(ref))
        et = [by[er][p]["e_trans_mm"] for p in common]
        erx = [by[er][p]["e_rot_x_deg"] for p in common]
        row = {
            "er": er,
            "n": len(common),
            # patients localized at ER 100% but not at this ER (their runs are left out)
            "missing": len(set(ref) - set(by[er])),
            "e_trans_mm_mean": mean_sd(et)[0],
            "e_trans_mm_sd": mean_sd(et)[1],
            "e_rot_x_deg_mean": mean_sd(erx)[0],
            "e_rot_x_deg_sd": mean_sd(erx)[1],
            "p_e_trans": paired_p(et, [ref[p]["e_trans_mm"] for p in common]),
            "p_e_rot_x": paired_p(erx, [ref[p]["e_rot_x_deg"] for p in common]),
            "registration_ms_mean": mean_sd([by[er][p]["registration_ms"] for p in common])[0],
            "points_mean": mean_sd([by[er][p]["points"] for p in common])[0],
        }
        for key, _, _ in ERRORS:
            diff = np.asarray([by[er][p][key] - ref[p][key] for p in common], float)
            dz = cohens_dz(diff)
            tost = tost_paired(diff, margins[key], alpha)
            row.update(
                {
                    f"diff_{key}_mean": mean_sd(diff)[0],
                    f"diff_{key}_sd": mean_sd(diff)[1],
                    f"dz_{key}": dz,
                    f"power_{key}": paired_t_power(dz, len(common), alpha),
                    f"tost_p_{key}": tost["p"],
                    f"equivalent_{key}": tost["equivalent"],
                    f"ci90_{key}_low": tost["ci"][0],
                    f"ci90_{key}_high": tost["ci"][1],
                }
            )
        rows.append(row)
    both = {k: critical_er(rows, alpha, k) for k in CRITICAL_ER_RULES}
    equiv = {k: equivalence_er(rows, k) for k in CRITICAL_ER_RULES}
    units = sorted({str(r.get("er_unit", "fixed")) for r in results})
    lengths = [r["kidney_length_mm"] for r in results if r.get("kidney_length_mm") is not None]
    reference = next(r for r in rows if r["er"] == REFERENCE_ER)
    n = reference["n"]
    minimum = minimum_patients()
    critical = both[rule]
    return {
        "rows": rows,
        "critical_er": critical,
        "rule": rule,
        "rule_text": CRITICAL_ER_RULES[rule],
        "critical_er_paper_rule": both["paper"],
        "critical_er_strict_rule": both["strict"],
        "first_not_significant_er": both["paper"],
        "reference_er": REFERENCE_ER,
        "alpha": alpha,
        "equivalence_er": equiv[rule],
        "equivalence_er_paper_rule": equiv["paper"],
        "equivalence_er_strict_rule": equiv["strict"],
        "margins": margins,
        "floor": {key: mean_sd([ref[p][key] for p in ref]) for key, _, _ in ERRORS},
        "patients": n,
        "paired_runs_per_er": {f"{r['er']:g}": r["n"] for r in rows},
        "min_patients": minimum,
        "min_patients_text": minimum_patients_text(),
        "below_minimum": bool(n < minimum),
        "critical_row": next((r for r in rows if r["er"] == critical), None),
        "paper_power": paper_er_power(),
        "er_unit": units[0] if len(units) == 1 else units,
        "kidney_length_mm": (mean_sd(lengths), float(min(lengths)), float(max(lengths)))
        if lengths
        else None,
    }


def critical_evidence_row(an: dict) -> tuple[dict | None, bool]:
    """(row, below) of the ER whose paired effect and power explain the critical ER: the
    critical ER's own row (``below`` False), or, when the critical ER is the reference
    (ER 100%) itself, whose comparison with itself says nothing, the largest ER below it
    (``below`` True: the ER that differed; a negative d_z there means smaller errors than
    at ER 100%, which the paper's two-sided test counts as a difference too). (None,
    False) without a critical ER."""
    row = an.get("critical_row")
    if row is None:
        return None, False
    ref = an.get("reference_er", 1.0)
    if row["er"] != ref:
        return row, False
    below = [r for r in an.get("rows", ()) if r["er"] < ref and r.get("n", 0) >= 2]
    if not below:
        return None, False
    return max(below, key=lambda r: r["er"]), True


def critical_er_summary(an: dict) -> str:
    """One line for the console: the critical ER with its n, the floor, the effect and
    power there, and the equivalence ER."""

    def pct(er):
        return "not determined" if er is None else f"{er * 100:.0f}%"

    fl = an["floor"]
    m = an["margins"]
    line = (
        f"critical ER {pct(an['critical_er'])} ({an['rule']} rule; n = {an['patients']} "
        f"patients, one paired run each per ER against ER 100%); floor at ER 100%: E_trans "
        f"{fl['e_trans_mm'][0]:.2f} +- {fl['e_trans_mm'][1]:.2f} mm, E_rot,x "
        f"{fl['e_rot_x_deg'][0]:.2f} +- {fl['e_rot_x_deg'][1]:.2f} deg"
    )
    row, below = critical_evidence_row(an)
    if row is not None:
        line += (
            f"; at {pct(row['er'])}{' (the ER below, which fails the rule)' if below else ''}: "
            f"d_z {row['dz_e_trans_mm']:.2f} / "
            f"{row['dz_e_rot_x_deg']:.2f}, power {row['power_e_trans_mm']:.2f} / "
            f"{row['power_e_rot_x_deg']:.2f}"
        )
    line += (
        f"; equivalent to ER 100% within +-{m['e_trans_mm']:g} mm / "
        f"+-{m['e_rot_x_deg']:g} deg (TOST) from ER {pct(an['equivalence_er'])}"
    )
    return line


def sample_size_warning(an: dict) -> str | None:
    """The warning when the ER study has fewer patients than :func:`minimum_patients`."""
    if not an.get("below_minimum"):
        return None
    n = an["patients"]
    reason = (
        "a paired test needs at least 2"
        if n < 2
        else f"its power to detect even a large effect (d_z {MIN_N_EFFECT:g}) is "
        f"{paired_t_power(MIN_N_EFFECT, n):.2f}"
    )
    return (
        f"warning: the critical ER rests on {n} patient(s), below the minimum of "
        f"{an['min_patients']} ({reason}): a 'no significant difference' is weak "
        "evidence here"
    )


def analyze_starts(results: list[dict], alpha: float = 0.05) -> dict:
    """Pairwise paired t-tests between starts over patients, Bonferroni-corrected per error
    (alpha over the number of pairs, for E_trans and E_rot,x each, as the paper tests each
    error on its own; ``tests`` counts both errors' tests)."""
    by = {}
    for r in results:
        by.setdefault(int(r["start"]), {})[r["patient"]] = r
    starts = sorted(by)
    pairs = [(a, b) for i, a in enumerate(starts) for b in starts[i + 1 :]]
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
        per_start.append(
            {
                "start": s,
                "n": len(vals),
                "e_trans_mm_mean": mean_sd([v["e_trans_mm"] for v in vals])[0],
                "e_trans_mm_sd": mean_sd([v["e_trans_mm"] for v in vals])[1],
                "e_rot_x_deg_mean": mean_sd([v["e_rot_x_deg"] for v in vals])[0],
                "e_rot_x_deg_sd": mean_sd([v["e_rot_x_deg"] for v in vals])[1],
            }
        )
    allv = [r for r in results]
    return {
        "per_start": per_start,
        "tests": tests,
        "bonferroni_threshold": alpha / m,
        "any_significant": any(
            t["significant_e_trans_mm"] or t["significant_e_rot_x_deg"] for t in tests
        ),
        "e_trans_mm": mean_sd([r["e_trans_mm"] for r in allv]),
        "e_rot_x_deg": mean_sd([r["e_rot_x_deg"] for r in allv]),
    }


# Metric keys of a strategy entry per definition (module ``drake_rus.metrics.sweep``).
EFFICIENCY_DEFINITIONS = {
    "pole_to_pole": ("n", "eps_mm"),
    "whole_pivot": ("n_whole_pivot", "eps_whole_pivot_mm"),
}


def _entry_value(e: dict, key: str):
    """A strategy entry's value; the whole pivot's under its old name (``*_full``) in runs
    written before the definitions were named."""
    old = {
        "n_whole_pivot": "n_full",
        "eps_whole_pivot_mm": "eps_full_mm",
        "V_whole_pivot": "V_full",
    }
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
    keys = (
        "n",
        "eps_mm",
        "V",
        "n_whole_pivot",
        "eps_whole_pivot_mm",
        "V_whole_pivot",
        "n_at_V",
        "eps_at_V_mm",
        "n_at_V_whole_pivot",
        "eps_at_V_whole_pivot_mm",
        "volume_error_pct",
    )
    # The strategies every run has (a study may have run only some), in the report's order.
    order = [s for s in STRATEGY_ORDER if results and all(s in r["strategies"] for r in results)]
    per = {s: {k: [] for k in keys} | {"tilt_cap_legs": []} for s in order}
    for r in results:
        for s in order:
            e = r["strategies"][s]
            for k in (
                "n",
                "eps_mm",
                "V",
                "n_whole_pivot",
                "eps_whole_pivot_mm",
                "V_whole_pivot",
                "volume_error_pct",
            ):
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
            str(leg): int(sum(leg in x for x in per[s]["tilt_cap_legs"])) for leg in (1, 2)
        }
    # The paper's family: OP against the paper's other strategies (Bonferroni over them);
    # beyond it, each of ours against the strategy it replaces (its own family).
    others = [s for s in order if s != "OP" and s in PAPER_STRATEGIES] if "OP" in order else []
    pairs_of = [("OP", s, max(1, 2 * len(others))) for s in others]
    pairs_of += [
        (s, COMPARED_WITH[s], 2)
        for s in order
        if s in BEYOND_PAPER_STRATEGIES and COMPARED_WITH[s] in order
    ]
    m = max(1, 2 * len(others))
    families = dict(EFFICIENCY_DEFINITIONS)
    families[f"at_V{tgt}"] = ("n_at_V", "eps_at_V_mm")
    comparisons = []
    for definition, metric_keys in families.items():
        for ours, s, m_family in pairs_of:
            for key in metric_keys:
                pairs = [
                    (a, b)
                    for a, b in zip(per[ours][key], per[s][key])
                    if a is not None and b is not None
                ]
                a = np.asarray([x for x, _ in pairs], float)
                b = np.asarray([y for _, y in pairs], float)
                p = paired_p(a, b)
                comparisons.append(
                    {
                        "definition": definition,
                        "comparison": f"{ours} vs {s}",
                        "metric": "n" if key.startswith("n") else "eps_mm",
                        "reduction_mean": float(np.mean(b - a)) if len(a) else float("nan"),
                        "reduction_sd": float(np.std(b - a, ddof=1)) if len(a) > 1 else 0.0,
                        # how often the first-named strategy was lower (OP in the paper's pairs)
                        "op_lower_count": int(np.sum(a < b)),
                        "patients": int(len(a)),
                        "p": p,
                        "bonferroni_threshold": alpha / m_family,
                        "significant": bool(np.isfinite(p) and p < alpha / m_family),
                    }
                )
    return {
        "per_patient": per,
        "summary": summary,
        "comparisons": comparisons,
        "bonferroni_threshold": alpha / m,
        "V_target": V_target,
        "patients": [r["patient"] for r in results],
    }


DISTANCE_BINS_MM = (0.0, 3.0, 4.0, 5.0, 7.0, float("inf"))


# The template study's group of the CT-kidney patients (``ct:``: real CT kidneys in
# generated bodies), all together like the generated patients; each real body is its own.
CT_GROUP = "real CT kidneys"


def template_group(r: dict) -> str:
    """The group of a template-study run in the tables: ``generated`` (the virtual patients,
    ``seed:N``/``train:K``/``test:K``), ``real CT kidneys`` (``ct:`` patients: real CT
    kidneys in generated bodies) or the real body's folder or file name; ``, decubitus``
    appended for left-lateral-decubitus runs."""
    spec = str(r["patient"])
    kind = r.get("patient_kind") or (
        "generated"
        if re.fullmatch(r"(test|train|seed):\d+", spec)
        else "ct"
        if spec.startswith("ct:")
        else "real"
    )
    name = {"generated": "generated", "ct": CT_GROUP}.get(kind) or spec.rstrip("/").split("/")[-1]
    return name + (", decubitus" if r.get("posture") == "left_lateral_decubitus" else "")


def group_kind(group: str) -> str:
    """ "generated", "ct" or "real" of a :func:`template_group` name."""
    if group.startswith("generated"):
        return "generated"
    return "ct" if group.startswith(CT_GROUP) else "real"


def _trend(results: list[dict]) -> dict:
    d = np.asarray([r["template_distance_mm"] for r in results], float)
    trend = {}
    for key in ("e_trans_mm", "e_rot_x_deg"):
        y = np.asarray([r[key] for r in results], float)
        if len(d) > 2 and np.ptp(d) > 0 and np.ptp(y) > 0:
            fit = np.polyfit(d, y, 1)
            trend[key] = {
                "r": float(np.corrcoef(d, y)[0, 1]),
                "slope_per_mm": float(fit[0]),
                "intercept": float(fit[1]),
                "runs": int(len(d)),
            }
        else:
            trend[key] = {
                "r": float("nan"),
                "slope_per_mm": float("nan"),
                "intercept": float("nan"),
                "runs": int(len(d)),
            }
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
            r["patient"]
        ] = r
    rows = []
    for g in sorted(groups, key=lambda g: ({"generated": 0, "ct": 1}.get(group_kind(g), 2), g)):
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
                row[f"p_{key}_vs_mean"] = (
                    paired_p([runs[q][key] for q in common], [ref[q][key] for q in common])
                    if v != "mean"
                    else float("nan")
                )
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
        b = {
            "from_mm": lo,
            "to_mm": hi,
            "n": len(sel),
            "real_runs": sum(1 for r in sel if group_kind(template_group(r)) == "real"),
            "ct_runs": sum(1 for r in sel if group_kind(template_group(r)) == "ct"),
        }
        for key in ("template_distance_mm", "e_trans_mm", "e_rot_x_deg"):
            b[f"{key}_mean"], b[f"{key}_sd"] = mean_sd([r[key] for r in sel])
        bins.append(b)
    return {
        "rows": rows,
        "trend": _trend(generated or results),
        "trend_all": _trend(results),
        "bins": bins,
        "groups": list(dict.fromkeys(r["group"] for r in rows)),
        "patients": sorted({r["patient"] for r in results}),
        "er": sorted({r["er"] for r in results}),
    }


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
        x = (
            np.arange(1, len(V) + 1, dtype=float)
            if x_key == "n"
            else np.asarray(e["curve_eps_mm"], float)
        )
        curves.append(np.interp(grid, x, V, left=0.0, right=V[-1]))
    return np.mean(curves, axis=0) if curves else np.zeros_like(grid)
