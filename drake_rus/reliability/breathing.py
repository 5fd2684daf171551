"""A patient who breathes and moves: the scan in four conditions per patient (issue 29).

- ``still``: no motion (the reference error of the same patient);
- ``protocol``: the seed's breath-hold protocol (``respiration.mode: breath_hold``) on a
  patient who breathes like a person (``patient.motion.breathing``: 10-20 mm at 12-20
  breaths/min, 2-6 mm of the wall under the probe) and holds when told;
- ``free``: the same breathing without holds, scanned in the end-expiration windows the
  estimator finds (``respiration.mode: gated``);
- ``shift``: a still patient shifting rigidly by 5-20 mm after localization (during TRANSIT
  or PIVOT of a still scan); the scan re-localizes instead of aborting.

Every draw (breathing, shift) is a hash of the patient's index and ``--seed``. Each run's
task holds every parameter that changes it (its overrides, the resolved scenario's SHA-256,
seed, time limit): a rerun reuses a stored run only when its task is the same
(:mod:`drake_rus.batch`). The errors are measured against where the kidney truly was when
the scan imaged it: the true kidney pose moved by the patient's mean true displacement over
the exploration frames that entered the registered cloud (E_trans); with a shift, against
the kidney after the shift too. Outputs: ``breathing.json`` / ``.md`` (per condition and
per run), ``breathing.png`` (E_trans per patient and condition), ``estimator.png`` (the
respiration estimator's hold onsets and ends against the simulation's truth).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
from pathlib import Path

import numpy as np
from pydrake.common.yaml import yaml_dump_typed
from tqdm import tqdm

from drake_rus.control.respiration import HOLDING
from drake_rus.experiments.specs import expand_patients
from drake_rus.io_utils import save_figure, write_text_atomic
from drake_rus.metrics import e_trans_of_offset
from drake_rus.provenance import Provenance
from drake_rus.reliability.campaign import run_campaign
from drake_rus.scenario import DEFAULT_SCENARIOS_FILE, LoadScenario

CONDITIONS = ("still", "protocol", "free", "shift")
# Every condition checks the tracking's change from its first checks and the probe's
# tangential force for a patient sliding under it (both off by default:
# localization/config.py), so a shift along the kidney's long axis is caught too.
TRACKING = "localization: {tracking_reference_checks: 2, tracking_slip_force: 1.6}"
# The ranges drawn per patient.
AMPLITUDE = (0.010, 0.020)  # m, craniocaudal
AP_AMPLITUDE = (0.002, 0.006)  # m, the wall under the probe
RATE = (12.0, 20.0)  # breaths/min
SHIFT = (0.005, 0.020)  # m
SHIFT_TIME = (14.5, 18.0)  # s: TRANSIT or PIVOT of a still quick scan
# E_trans of free breathing within this of the still scan's (mm).
FREE_TOLERANCE_MM = 2.0
# A shift above this (mm) must be noticed.
SHIFT_NOTICE_MM = 5.0


def draw_motion(index: int, seed: int = 0) -> dict:
    """One patient's breathing and shift (module doc), from (seed, index)."""
    rng = np.random.default_rng([int(seed), 29, int(index)])
    direction = rng.normal(size=3)
    direction[2] *= 0.3  # mostly along the bed
    if index % 3 == 0:
        direction = np.array([0.0, 1.0, 0.0])  # along the body: the kidney's long axis
    magnitude = rng.uniform(*SHIFT)
    offset = np.clip(direction / np.linalg.norm(direction) * magnitude, -0.02, 0.02)
    return {
        "amplitude": float(rng.uniform(*AMPLITUDE)),
        "ap_amplitude": float(rng.uniform(*AP_AMPLITUDE)),
        "rate_per_min": float(rng.uniform(*RATE)),
        "shift_offset": [float(v) for v in offset],
        "shift_time": float(rng.uniform(*SHIFT_TIME)),
        "shift_ramp": float(rng.uniform(0.3, 1.0)),
    }


def motion_seed(index: int, seed: int = 0) -> int:
    """``patient.motion.seed`` of patient ``index`` (its breath-to-breath and hold draws)
    under ``--seed``: the index itself for seed 0, so every seed gives other draws."""
    return (int(seed) * 100003 + int(index)) % 2**31


def condition_overrides(condition: str, m: dict, index: int, seed: int = 0) -> str:
    """Scenario YAML overrides of ``condition`` for the motion ``m`` (draw_motion) of
    patient ``index`` under ``--seed`` ``seed``."""
    index = motion_seed(index, seed)
    breathing = "enabled: true, amplitude: %.4f, ap_amplitude: %.4f, rate_per_min: %.2f" % (
        m["amplitude"],
        m["ap_amplitude"],
        m["rate_per_min"],
    )
    if condition == "still":
        return "{%s}" % TRACKING
    if condition == "protocol":
        return (
            "{" + TRACKING + ", respiration: {mode: breath_hold}, "
            "patient: {motion: {seed: %d, breathing: {%s}}}}" % (index, breathing)
        )
    if condition == "free":
        return (
            "{" + TRACKING + ", respiration: {mode: gated}, patient: {motion: {seed: %d, "
            "breathing: {%s, "
            "follows_prompts: false}}}}" % (index, breathing)
        )
    if condition == "shift":
        offset = "[" + ", ".join(f"{v:.5f}" for v in m["shift_offset"]) + "]"
        return (
            "{" + TRACKING + ", patient: {motion: {seed: %d, shift: {enabled: true, "
            "time: %.3f, offset: %s, "
            "ramp: %.3f}}}}" % (index, m["shift_time"], offset, m["shift_ramp"])
        )
    raise ValueError(f"--conditions: unknown condition {condition!r} (one of {CONDITIONS})")


def _scenario_sha256(scenario: str, overrides: str) -> str:
    sc = LoadScenario(
        filename=DEFAULT_SCENARIOS_FILE, scenario_name=scenario, scenario_text=overrides
    )
    return hashlib.sha256(yaml_dump_typed(sc).encode()).hexdigest()


def breathing_tasks(
    patients: list[str],
    conditions=CONDITIONS,
    *,
    scenario: str = "quick",
    seed: int = 0,
    max_sim_time: float = 240.0,
) -> list[dict]:
    """One run per patient and condition, each task with every parameter that changes it."""
    tasks = []
    for i, spec in enumerate(patients):
        m = draw_motion(i, seed)
        for name in conditions:
            text = condition_overrides(name, m, i, seed)
            tasks.append(
                {
                    "run_id": f"{spec.replace(':', '')}_{name}",
                    "index": i,
                    "fault": name,
                    "patient": spec,
                    "scenario": scenario,
                    "scenarios_file": None,
                    "overrides": text,
                    "motion": m,
                    "scenario_sha256": _scenario_sha256(scenario, text),
                    "random_seed": i,
                    "max_sim_time": max_sim_time,
                    "analyse": "drake_rus.reliability.breathing:analyse_run",
                }
            )
    return tasks


# ----------------------------------------------------------------------------- per run
def _log(result, name):
    if name not in result.logs:
        return None, None
    t, data = result.logs[name]
    return np.asarray(t), np.asarray(data)


def _last_exploration(result) -> tuple[float, float]:
    """(start, end) s of the scan's last EXPLORE (a re-localization explores again)."""
    spans = [(a, b) for name, a, b in result.phases if name == "EXPLORE"]
    return spans[-1] if spans else (math.nan, math.nan)


def registration_offset(result) -> np.ndarray:
    """The patient's mean true displacement (m, B) over the exploration frames that entered
    the registered cloud: those of the last EXPLORE acquired while the scan could move."""
    t_off, off = _log(result, "patient_offset_true")
    if t_off is None:
        return np.zeros(3)
    start, end = _last_exploration(result)
    times = np.array([f.time for f in result.frames if start <= f.time <= end])
    t_ok, ok = _log(result, "motion_allowed")
    if t_ok is not None and len(times):
        allowed = np.interp(times, t_ok, ok[0]) > 0.5
        times = times[allowed] if allowed.any() else times
    if not len(times):
        return np.zeros(3)
    return np.array([np.interp(times, t_off, off[k]).mean() for k in range(3)])


def hold_intervals(times, flags) -> list[tuple[float, float]]:
    """[(start, end)] s where ``flags`` (0/1 samples at ``times``) is 1; end NaN for a hold
    still on at the last sample (the scan ended first: it has no end to sense)."""
    flags = np.asarray(flags).reshape(-1) > 0.5
    out, start = [], None
    for t, f in zip(times, flags):
        if f and start is None:
            start = float(t)
        if not f and start is not None:
            out.append((start, float(t)))
            start = None
    if start is not None:
        out.append((start, math.nan))
    return out


def estimator_errors(true_holds, transitions, max_gap: float = 1.5) -> list[dict]:
    """For each true hold (start, end): the estimator's HOLDING onset and end (its
    estimated times and when it decided), matched to the nearest within ``max_gap`` s."""
    onsets = [(w, d) for w, d, a, b in transitions if b == HOLDING]
    ends = [(w, d) for w, d, a, b in transitions if a == HOLDING]
    out = []
    for start, end in true_holds:
        row = {"start": start, "end": end}
        for key, truth, cands in (("onset", start, onsets), ("end", end, ends)):
            if not math.isfinite(truth):
                continue
            best = min(cands, key=lambda c: abs(c[0] - truth), default=None)
            if best is not None and abs(best[0] - truth) <= max_gap:
                row[f"{key}_error_s"] = best[0] - truth
                row[f"{key}_latency_s"] = best[1] - truth
        out.append(row)
    return out


# A hold that ends later than this before the scan's end (s) has no end the scan could sense:
# the estimator decides 0.15-0.35 s after the wall starts to move.
END_MARGIN = 0.5


def sensed_holds(r: dict) -> list[dict]:
    """The run's estimator rows (``estimator_errors``), each hold's end left out (NaN, no
    error) when it came later than END_MARGIN s before the scan ended (``sim_s``): the
    patient let go after DONE, when told to breathe."""
    out = []
    for e in r.get("estimator", []):
        end = e.get("end", math.nan)
        if end is None or not (math.isfinite(end) and end <= r.get("sim_s", math.inf) - END_MARGIN):
            e = {k: v for k, v in e.items() if not k.startswith("end_")} | {"end": math.nan}
        out.append(e)
    return out


def relocalization_triggers(events) -> list[dict]:
    """What started each re-localization of a scan, from the supervisor's events ((time s,
    phase, message), ...): its time (s) and the tracking check's own words (which check
    fired: the drift limit, the drift-change rule or the slip check, and its reading)."""
    out = []
    for t, _, message in events:
        if "re-localizing" in message:
            why = message.split("; re-localizing")[0]
            out.append({"t_s": round(float(t), 2), "why": why.removeprefix("kidney moved: ")})
    return out


def analyse_run(result, scenario, task) -> dict:
    """The study's figures of one finished scan (module doc)."""
    triggers = relocalization_triggers(result.events)
    record: dict = {"relocalizations": len(triggers), "relocalization_triggers": triggers}
    if result.X_BK_estimated is not None and result.truth is not None:
        est = result.X_BK_estimated.translation()
        truth = result.X_BK_true.translation()
        # E_trans as the paper's (x-y; metrics.e_trans_of_offset), the kidney's motion off.
        record["e_trans_mm"] = 1e3 * e_trans_of_offset(est - truth - registration_offset(result))
        record["e_trans_static_mm"] = 1e3 * e_trans_of_offset(est - truth)
        shift = scenario.patient.motion.shift
        if shift.enabled:
            record["e_trans_after_shift_mm"] = 1e3 * e_trans_of_offset(
                est - truth - np.asarray(shift.offset)
            )
    shift = scenario.patient.motion.shift
    if shift.enabled:
        localized = [t for t, name, _ in result.events if name == "TRANSIT"]
        record["shift_mm"] = float(np.linalg.norm(shift.offset) * 1e3)
        record["shift_after_localization"] = bool(localized and shift.time >= localized[0])
        record["shift_started_in_scan"] = bool(shift.time < result.sim_s)
    t_hold, hold = _log(result, "breath_hold")
    if t_hold is not None and result.respiration:
        holds = hold_intervals(t_hold, hold[0])
        record["estimator"] = estimator_errors(holds, result.respiration.get("transitions", ()))
        record["holds_used"] = result.respiration.get("holds", 0)
        record["prompts"] = len(result.respiration.get("prompts", ()))
        # The time line of the first run, for the figure.
        t_lev, lev = _log(result, "respiratory_level_true")
        t_st, st = _log(result, "respiration_state")
        if t_lev is not None and t_st is not None:
            k = slice(None, None, 2)
            record["timeline"] = {
                "t": t_lev[k].round(3).tolist(),
                "level": lev[0][k].round(3).tolist(),
                "hold": hold[0][k].round(0).tolist(),
                "t_state": t_st.round(3).tolist(),
                "state": st[0].round(0).tolist(),
            }
            t_mv, mv = _log(result, "probe_moving")
            if t_mv is not None:
                record["timeline"]["moving"] = np.interp(t_st, t_mv, mv[0]).round(0).tolist()
    return record


# ----------------------------------------------------------------------------- tables
def summarize(results: list[dict]) -> dict:
    """Per condition: runs, DONE, E_trans (mm); free breathing against the still scan of the
    same patient; shifts: re-localized and DONE, noticed; the estimator's onset/end errors."""
    still = {
        r["patient"]: r.get("e_trans_mm")
        for r in results
        if r["fault"] == "still" and r.get("e_trans_mm") is not None
    }
    out = {}
    for name in CONDITIONS:
        rs = [r for r in results if r["fault"] == name]
        if not rs:
            continue
        errs = [r["e_trans_mm"] for r in rs if r.get("e_trans_mm") is not None]
        row = {
            "runs": len(rs),
            "done": sum(r["status"] == "DONE" for r in rs),
            "mean_e_trans_mm": float(np.mean(errs)) if errs else None,
            "max_e_trans_mm": float(np.max(errs)) if errs else None,
            "sim_s_mean": float(np.mean([r["sim_s"] for r in rs if r.get("sim_s")] or [0])),
        }
        if name in ("free", "protocol"):
            within = [
                r
                for r in rs
                if r["status"] == "DONE"
                and r.get("e_trans_mm") is not None
                and r["patient"] in still
                and abs(r["e_trans_mm"] - still[r["patient"]]) <= FREE_TOLERANCE_MM
            ]
            row["done_within_2mm_of_still"] = len(within)
        if name == "shift":
            row["relocalized_done"] = sum(
                r["status"] == "DONE" and r.get("relocalizations", 0) > 0 for r in rs
            )
            row["unnoticed_above_5mm"] = sum(
                bool(
                    r.get("shift_mm", 0) > SHIFT_NOTICE_MM
                    and r.get("shift_started_in_scan")
                    and r.get("relocalizations", 0) == 0
                    and "kidney moved" not in (r.get("reason") or "")
                )
                for r in rs
            )
            # Of those, the ones that ended DONE: a wrong result reported as success (the
            # others stopped on the way: a safety stop, a failed check).
            row["done_unnoticed_above_5mm"] = sum(
                bool(
                    r["status"] == "DONE"
                    and r.get("shift_mm", 0) > SHIFT_NOTICE_MM
                    and r.get("shift_started_in_scan")
                    and r.get("relocalizations", 0) == 0
                )
                for r in rs
            )
            row["shift_before_localization"] = sum(
                not r.get("shift_after_localization", True) for r in rs
            )
        est = [e for r in rs for e in sensed_holds(r)]
        if est:
            for key in ("onset", "end"):
                errs_k = [abs(e[f"{key}_error_s"]) for e in est if f"{key}_error_s" in e]
                lat = [e[f"{key}_latency_s"] for e in est if f"{key}_latency_s" in e]
                row[f"hold_{key}s"] = sum(
                    math.isfinite(e[key if key == "end" else "start"]) for e in est
                )
                row[f"hold_{key}s_found"] = len(errs_k)
                row[f"hold_{key}_within_0.3s"] = sum(e <= 0.3 for e in errs_k)
                row[f"hold_{key}_max_error_s"] = float(max(errs_k)) if errs_k else None
                row[f"hold_{key}_median_latency_s"] = float(np.median(lat)) if lat else None
        out[name] = row
    return out


def _index(r: dict) -> int:
    """The run's patient index (a stored run keeps it in its task)."""
    return int(r.get("index", r.get("task", {}).get("index", 0)))


def table_markdown(results: list[dict], summary: dict) -> str:
    """breathing.md: the summary and the per-run table."""
    lines = [
        "| condition | runs | DONE | mean / max E_trans (mm) | mean sim s | notes |",
        "|---|---|---|---|---|---|",
    ]
    for name, row in summary.items():
        notes = []
        if "done_within_2mm_of_still" in row:
            notes.append(f"DONE within 2 mm of still: {row['done_within_2mm_of_still']}")
        if "relocalized_done" in row:
            notes.append(
                f"re-localized and DONE: {row['relocalized_done']}; unnoticed above 5 mm: "
                f"{row['unnoticed_above_5mm']} (of them DONE: "
                f"{row['done_unnoticed_above_5mm']}); shift before localization: "
                f"{row['shift_before_localization']}"
            )
        if "hold_onsets" in row:
            notes.append(
                f"holds {row['hold_onsets']}: onset within 0.3 s {row['hold_onset_within_0.3s']}"
                f" (max {_fmt(row['hold_onset_max_error_s'], 2)} s); of {row['hold_ends']} "
                f"ending within the scan, end within 0.3 s {row['hold_end_within_0.3s']} "
                f"(max {_fmt(row['hold_end_max_error_s'], 2)} s)"
            )
        lines.append(
            f"| {name} | {row['runs']} | {row['done']} | {_fmt(row['mean_e_trans_mm'])} / "
            f"{_fmt(row['max_e_trans_mm'])} | {row['sim_s_mean']:.0f} | {'; '.join(notes)} |"
        )
    lines += [
        "",
        "| run | status | E_trans (mm) | static E_trans (mm) | re-localizations | shift (mm) | "
        "sim s | reason |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in sorted(results, key=lambda r: (CONDITIONS.index(r["fault"]), _index(r))):
        lines.append(
            f"| {r['run_id']} | {r['status']} | {_fmt(r.get('e_trans_mm'))} | "
            f"{_fmt(r.get('e_trans_static_mm'))} | {r.get('relocalizations', '-')} | "
            f"{_fmt(r.get('shift_mm'))} | {_fmt(r.get('sim_s'), 0)} | "
            f"{_run_reason(r)} |"
        )
    return "\n".join(lines) + "\n"


def _run_reason(r: dict) -> str:
    """The table's reason cell: each re-localization's time and trigger, then the end's
    reason (each cut to fit a table)."""
    parts = [
        f"re-localized at {t['t_s']:.1f} s: {t['why'][:90]}"
        for t in r.get("relocalization_triggers", ())
    ]
    if r.get("reason"):
        parts.append(r["reason"][:120])
    return "; ".join(parts)


def _fmt(v, digits: int = 1) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def plot_comparison(results: list[dict], path) -> Path:
    """breathing.png: E_trans per patient under each condition (filled: DONE, open: not)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    patients = sorted({r["patient"] for r in results}, key=lambda p: (len(p), p))
    present = [c for c in CONDITIONS if any(r["fault"] == c for r in results)]
    fig, ax = plt.subplots(figsize=(9, 4.5))
    for k, name in enumerate(present):
        for r in results:
            if r["fault"] != name or r.get("e_trans_mm") is None:
                continue
            x = patients.index(r["patient"]) + (k - (len(present) - 1) / 2) * 0.18
            done = r["status"] == "DONE"
            ax.scatter(
                x, r["e_trans_mm"], s=40, color=f"C{k}", facecolors=f"C{k}" if done else "none"
            )
    ax.set_xticks(range(len(patients)), patients, rotation=45)
    ax.set_ylabel("E_trans (mm), against the kidney where it was imaged")
    ax.set_title("Still, breath-hold protocol, free breathing (gated), shift after localization")
    ax.legend(
        [Line2D([], [], ls="", marker="o", color=f"C{k}") for k in range(len(present))],
        present,
        fontsize=8,
    )
    ax.grid(axis="y", alpha=0.3)
    return save_figure(fig, path)


def plot_estimator(results: list[dict], path) -> Path | None:
    """estimator.png: one protocol run's true respiratory level and holds with the
    estimator's state and when it took the probe as moving of its own accord, and every
    hold's onset and end error (estimated minus true, s)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = [r for r in results if r.get("estimator")]
    if not runs:
        return None
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(12, 4), gridspec_kw={"width_ratios": [2, 1]})
    line = next((r for r in runs if r.get("timeline") and r["fault"] == "protocol"), None)
    if line is not None:
        tl = line["timeline"]
        ax0.plot(tl["t"], tl["level"], lw=1, label="true respiratory level")
        ax0.fill_between(
            tl["t"],
            0,
            np.asarray(tl["hold"]) * 1.3,
            color="C2",
            alpha=0.2,
            label="true breath-hold",
        )
        st = np.asarray(tl["state"])
        if "moving" in tl:
            ax0.fill_between(
                tl["t_state"],
                -0.25,
                -0.1,
                where=np.asarray(tl["moving"]) > 0.5,
                color="0.4",
                alpha=0.5,
                lw=0,
                label="probe moving by the scan's command (hold kept unless > 3 mm)",
            )
        ax0.plot(
            tl["t_state"],
            np.where(st == 2, 1.4, np.where(st == 3, 0.1, np.nan)),
            "k.",
            ms=2,
            label="estimator: holding (top), end-expiration (bottom)",
        )
        ax0.set_xlabel("time (s)")
        ax0.set_title(f"{line['run_id']}")
        ax0.legend(fontsize=7, loc="upper right")
    for k, key in enumerate(("onset", "end")):
        rows = [e for r in runs for e in sensed_holds(r)]
        errs = [e[f"{key}_error_s"] for e in rows if f"{key}_error_s" in e]
        lat = [e[f"{key}_latency_s"] for e in rows if f"{key}_latency_s" in e]
        ax1.scatter(
            np.full(len(errs), k) - 0.1,
            errs,
            s=12,
            color="C0",
            label="estimated time - true" if k == 0 else None,
        )
        ax1.scatter(
            np.full(len(lat), k) + 0.1,
            lat,
            s=12,
            color="C3",
            marker="x",
            label="decided - true" if k == 0 else None,
        )
    ax1.axhspan(-0.3, 0.3, color="C2", alpha=0.15)
    ax1.set_xticks([0, 1], ["hold onset", "hold end"])
    ax1.set_ylabel("s")
    ax1.legend(fontsize=7)
    ax1.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    return save_figure(fig, path)


# ----------------------------------------------------------------------------- command
def add_commands(subparsers) -> None:
    p = subparsers.add_parser(
        "breathing",
        help="the scan with a breathing and moving patient: protocol, free breathing, shifts",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--patients", default="test:0-9", help="patient specs (default test:0-9)")
    p.add_argument("--out", required=True, help="output directory (resumable)")
    p.add_argument(
        "--conditions",
        default=",".join(CONDITIONS),
        help=f"comma-separated conditions (default {','.join(CONDITIONS)})",
    )
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--seed", type=int, default=0, help="seed of the breathing and shift draws")
    p.add_argument("--max-sim-time", type=float, default=240.0, help="per scan (s)")
    p.set_defaults(func=run_breathing_command)


def run_breathing_command(args) -> int:
    patients = expand_patients(args.patients)
    conditions = [c.strip() for c in args.conditions.split(",") if c.strip()]
    bad = [c for c in conditions if c not in CONDITIONS]
    if bad or not conditions:
        raise ValueError(f"--conditions: expected some of {','.join(CONDITIONS)}, got {bad}")
    if args.workers < 0:
        raise ValueError(f"--workers: expected 0 or more, got {args.workers}")
    if not (math.isfinite(args.max_sim_time) and args.max_sim_time > 0):
        raise ValueError(f"--max-sim-time: expected a positive time, got {args.max_sim_time}")
    tasks = breathing_tasks(patients, conditions, seed=args.seed, max_sim_time=args.max_sim_time)
    results = run_campaign(
        tasks,
        args.out,
        workers=args.workers,
        progress=lambda r: tqdm.write(
            f"{r['run_id']}: {r['status']} e_trans {_fmt(r.get('e_trans_mm'))} mm "
            f"{(r.get('reason') or '')[:100]}"
        ),
    )
    summary = summarize(results)
    out = Path(args.out)
    write_text_atomic(out / "breathing.md", table_markdown(results, summary))
    write_text_atomic(
        out / "breathing.json",
        json.dumps(
            {
                "conditions": summary,
                "patients": patients,
                "seed": args.seed,
                "runs": [{k: v for k, v in r.items() if k != "timeline"} for r in results],
                "provenance": Provenance(
                    LoadScenario(filename=DEFAULT_SCENARIOS_FILE, scenario_name="quick"),
                    scenario_name="quick",
                    scenarios_file=str(DEFAULT_SCENARIOS_FILE),
                    overrides="per run: each run's task.overrides",
                    seeds={t["run_id"]: t["random_seed"] for t in tasks},
                ),
            },
            indent=1,
            default=str,
        ),
    )
    if results:
        plot_comparison(results, out / "breathing.png")
        plot_estimator(results, out / "estimator.png")
    print(table_markdown(results, summary).split("\n\n")[0])
    print(json.dumps({k: {"runs": v["runs"], "done": v["done"]} for k, v in summary.items()}))
    return 0
