"""The reliability campaign: randomised faulty closed-loop scans across the test patients.

Each run draws one fault (round-robin over :data:`CAMPAIGN_FAULTS`, so every type gets its
share) with random timing and size, a test patient and a seed; it runs the full scan with
:func:`~drake_rus.reliability.run.RunFaultyScan` and records DONE or ABORT with a reason,
the peak true contact force, the time above the force ceiling, whether the robot ended at
rest, and any exception. Results are one JSON file per run under ``OUT/runs`` (written
atomically), so an interrupted campaign resumes where it stopped; runs go through the
project's batch runner (:func:`drake_rus.batch.run_tasks`: Dask worker processes, or an
existing Dask scheduler).
"""

from __future__ import annotations

import dataclasses
import importlib
import json
import operator
import time
import traceback
from pathlib import Path

import numpy as np

from drake_rus import batch
from drake_rus.anatomy import load_patient
from drake_rus.anatomy.motion import shift_offset
from drake_rus.io_utils import save_figure, write_text_atomic
from drake_rus.localization.localize import load_registration_template
from drake_rus.metrics import e_trans_of_offset
from drake_rus.reliability.config import FAULT_KINDS
from drake_rus.reliability.run import RunFaultyScan, outcome_reason
from drake_rus.scenario import DEFAULT_SCENARIOS_FILE, LoadScenario
from drake_rus.tables import write_csv_atomic

# Fault types of the campaign: the sensor faults, breathing, a patient shift, and none.
CAMPAIGN_FAULTS = [*FAULT_KINDS, "breathing", "patient_shift"]


def _yaml_list(v) -> str:
    return "[" + ", ".join(f"{float(x):.6g}" for x in v) + "]"


def fault_overrides(kind: str, rng: np.random.Generator, seed: int) -> str:
    """Scenario YAML overrides for one random fault of type ``kind``."""
    start = float(rng.uniform(1.0, 18.0))  # a quick scan lasts ~19 s
    if kind == "none":
        return "{}"
    if kind == "breathing":
        # Half the runs follow the breath-hold protocol (the patient holds when told), the
        # others breathe freely and are scanned at end-expiration (respiration.mode).
        hold = rng.random() < 0.5
        return (
            "{respiration: {mode: %s}, patient: {motion: {seed: %d, breathing: {enabled: true, "
            "amplitude: %.4f, rate_per_min: %.2f, follows_prompts: %s}}}}"
            % (
                "breath_hold" if hold else "gated",
                seed,
                rng.uniform(0.005, 0.020),
                rng.uniform(12.0, 20.0),
                "true" if hold else "false",
            )
        )
    if kind == "patient_shift":
        direction = rng.normal(size=3)
        direction[2] *= 0.3  # mostly along the bed
        offset = direction / np.linalg.norm(direction) * rng.uniform(0.005, 0.02)
        offset = np.clip(offset, -0.02, 0.02)
        return (
            "{patient: {motion: {seed: %d, shift: {enabled: true, time: %.3f, offset: %s, "
            "ramp: %.2f}}}}" % (seed, start, _yaml_list(offset), rng.uniform(0.2, 2.0))
        )
    duration = float(rng.choice([rng.uniform(0.05, 0.5), rng.uniform(0.5, 5.0), 1.0e9]))
    extra = ""
    if kind == "force_spike":
        extra = ", magnitude: %.2f, spike_period: %.3f, spike_width: %.3f" % (
            rng.uniform(10.0, 40.0),
            rng.uniform(0.2, 2.0),
            rng.uniform(0.005, 0.05),
        )
    elif kind == "force_bias":
        extra = ", magnitude: %.2f" % rng.uniform(-6.0, 10.0)
    elif kind == "joint_state_delay":
        extra = ", delay: %.3f" % rng.uniform(0.01, 0.3)
    elif kind in (
        "image_dropout",
        "frozen_image",
        "segmentation_miss",
        "segmentation_false_positive",
        "nan_image",
    ):
        extra = ", probability: %.2f" % rng.choice([rng.uniform(0.05, 0.5), 1.0])
    return "{faults: {seed: %d, sensor: [{kind: %s, start: %.3f, duration: %.4g%s}]}}" % (
        seed,
        kind,
        start,
        duration,
        extra,
    )


def make_tasks(
    n: int,
    *,
    seed: int = 0,
    patients: int = 15,
    scenario: str = "quick",
    scenarios_file: str | None = None,
    max_sim_time: float = 60.0,
) -> list[dict]:
    """``n`` reproducible run descriptions (the same n and seed give the same runs)."""
    tasks = []
    for i in range(n):
        rng = np.random.default_rng([seed, i])
        kind = CAMPAIGN_FAULTS[i % len(CAMPAIGN_FAULTS)]
        run_seed = int(rng.integers(0, 2**31 - 1))
        tasks.append(
            {
                "run_id": f"run{i:04d}_{kind}",
                "index": i,
                "fault": kind,
                "patient": f"test:{int(rng.integers(0, patients))}",
                "scenario": scenario,
                "scenarios_file": scenarios_file,
                "overrides": fault_overrides(kind, rng, run_seed % 100000),
                "random_seed": run_seed % 100000,
                "max_sim_time": max_sim_time,
            }
        )
    return tasks


_CACHE: dict = {}


def _patient(spec: str, side: str, posture: str):
    key = (spec, side, posture)
    if key not in _CACHE:
        _CACHE.clear()  # one patient at a time per worker (memory)
        _CACHE[key] = load_patient(spec, side=side, posture=posture, progress=False)
    return _CACHE[key]


def run_task(task: dict) -> dict:
    """Runs one campaign scan; never raises (an exception is recorded in the result)."""
    start = time.perf_counter()
    record = {
        "task": task,
        "run_id": task["run_id"],
        "fault": task["fault"],
        "patient": task["patient"],
        "status": "EXCEPTION",
        "reason": "",
        "peak_force_n": None,
        "time_above_ceiling_s": None,
        "longest_above_ceiling_s": None,
        "force_violation": None,
        "at_rest": None,
        "sim_s": None,
        "e_trans_mm": None,
        "exception": None,
    }
    try:
        scenario = LoadScenario(
            filename=task["scenarios_file"] or DEFAULT_SCENARIOS_FILE,
            scenario_name=task["scenario"],
            scenario_text=task["overrides"],
        )
        scenario = dataclasses.replace(scenario, random_seed=int(task["random_seed"]))
        template = load_registration_template(scenario.localization.template)
        patient = _patient(task["patient"], scenario.patient.side, scenario.patient.posture)
        result, check = RunFaultyScan(
            scenario, patient, template, max_sim_time=float(task["max_sim_time"])
        )
        record.update(check)
        record.update(
            {
                "status": result.status,
                "reason": outcome_reason(result),
                "sim_s": result.sim_s,
                "scan_wall_s": result.wall_s,
                "e_trans_mm": (
                    None
                    if result.X_BK_estimated is None
                    else 1e3
                    * e_trans_of_offset(
                        result.X_BK_estimated.translation() - result.X_BK_true.translation()
                    )
                ),
                "e_trans_at_localization_mm": error_at_localization_mm(scenario, result),
                "safety_events": [
                    f"{e.time:.3f} s {e.reason}: {e.detail}" for e in result.safety_events
                ],
            }
        )
        if task.get("analyse"):
            # A study's own figures of the run ("module:function"(result, scenario, task)).
            module, _, name = task["analyse"].partition(":")
            record.update(getattr(importlib.import_module(module), name)(result, scenario, task))
    except Exception as e:  # noqa: BLE001 - the campaign counts these
        record["exception"] = f"{type(e).__name__}: {e}"
        record["traceback"] = traceback.format_exc(limit=8)
    record["wall_s"] = time.perf_counter() - start
    return record


def error_at_localization_mm(scenario, result) -> float | None:
    """E_trans (mm) against where the kidney truly was when it was localized: its
    end-expiration pose (where breath-holds put it) moved by the patient shift at the
    estimate's time. Equal to e_trans_mm when the patient does not shift; None without an
    estimate."""
    if result.X_BK_estimated is None:
        return None
    truth = result.X_BK_true.translation() + shift_offset(
        result.localization.time, scenario.patient.motion.shift
    )
    return 1e3 * e_trans_of_offset(result.X_BK_estimated.translation() - truth)


# The id of a campaign run (its result file's name): picklable, unlike a lambda.
task_id = operator.itemgetter("run_id")


def result_path(out_dir, task) -> Path:
    return batch.result_path(out_dir, task_id(task))


def run_campaign(
    tasks: list[dict],
    out_dir,
    *,
    workers: int = 2,
    progress=None,
    scheduler: str | None = None,
    show_bar: bool = True,
) -> list[dict]:
    """Runs the tasks without a result under ``out_dir/runs`` (resumable) through the batch
    runner (:func:`drake_rus.batch.run_tasks`): ``workers`` Dask worker processes, an
    existing Dask ``scheduler``, or (``workers`` = 0) this process. ``progress`` is called
    with each finished record. A run whose worker process died is recorded as an
    exception. Returns all results of ``tasks``."""
    batch.runs_dir(out_dir).mkdir(parents=True, exist_ok=True)
    status = batch.run_tasks(
        tasks,
        run_task,
        out_dir,
        task_id,
        workers=workers,
        scheduler=scheduler,
        progress=show_bar,
        desc="campaign",
        on_result=progress,
    )
    by_id = {t["run_id"]: t for t in tasks}
    for run_id, error in status["failed"]:  # run_task never raises: a dead worker
        task = by_id[run_id]
        record = {
            "task": task,
            "run_id": run_id,
            "fault": task["fault"],
            "patient": task["patient"],
            "status": "EXCEPTION",
            "reason": "",
            "exception": f"worker died: {error}",
        }
        batch.save_result(out_dir, run_id, record)
        if progress:
            progress(record)
    return [
        json.loads(result_path(out_dir, t).read_text())
        for t in tasks
        if result_path(out_dir, t).exists()
    ]


def summarize(results: list[dict]) -> dict:
    """The campaign's headline figures (the command's last output line)."""
    peaks = [r["peak_force_n"] for r in results if r.get("peak_force_n") is not None]
    return {
        "runs": len(results),
        "done": sum(r["status"] == "DONE" for r in results),
        "abort": sum(r["status"] == "ABORT" for r in results),
        "timeout": sum(r["status"] == "TIMEOUT" for r in results),
        "force_violations": sum(bool(r.get("force_violation")) for r in results),
        "exceptions": sum(r["status"] == "EXCEPTION" or bool(r.get("exception")) for r in results),
        "not_at_rest": sum(r.get("at_rest") is False for r in results),
        "aborts_without_reason": sum(
            r["status"] == "ABORT" and not r.get("reason") for r in results
        ),
        "peak_force_n": max(peaks) if peaks else None,
    }


def per_fault(results: list[dict]) -> list[dict]:
    rows = []
    for kind in CAMPAIGN_FAULTS:
        rs = [r for r in results if r["fault"] == kind]
        if rs:
            done = sum(r["status"] == "DONE" for r in rs)
            errs = [
                r.get("e_trans_at_localization_mm", r.get("e_trans_mm"))
                for r in rs
                if r["status"] == "DONE"
            ]
            errs = [e for e in errs if e is not None]
            rows.append(
                {
                    "fault": kind,
                    "runs": len(rs),
                    "done": done,
                    "done_fraction": done / len(rs),
                    "median_e_trans_done_mm": float(np.median(errs)) if errs else None,
                    "abort": sum(r["status"] == "ABORT" for r in rs),
                    "max_peak_force_n": max((r.get("peak_force_n") or 0.0) for r in rs),
                }
            )
    return rows


def fault_table(results: list[dict]) -> str:
    """DONE fraction per fault type, as a plain-text table."""
    lines = [
        f"{'fault':<30} {'runs':>4} {'DONE':>4} {'ABORT':>5} {'other':>5} "
        f"{'DONE frac':>9} {'max peak F [N]':>14} {'median E_trans DONE [mm]':>24}"
    ]
    for f in per_fault(results):
        other = f["runs"] - f["done"] - f["abort"]
        lines.append(
            f"{f['fault']:<30} {f['runs']:>4} {f['done']:>4} {f['abort']:>5} "
            f"{other:>5} {f['done_fraction']:>9.2f} {f['max_peak_force_n']:>14.1f} "
            f"{_fmt(f['median_e_trans_done_mm']):>24}"
        )
    return "\n".join(lines)


def outcome_table(results: list[dict]) -> str:
    """A plain-text table, one row per run."""
    head = (
        f"{'run':<36} {'patient':<8} {'status':<9} {'peak F [N]':>10} {'>ceil [ms]':>10} "
        f"{'rest':>5} {'sim s':>6} {'wall s':>7}  reason / exception"
    )
    lines = [head, "-" * len(head)]
    for r in sorted(results, key=lambda r: r["run_id"]):

        def num(key, scale=1.0, fmt="{:.1f}"):
            v = r.get(key)
            return "-" if v is None else fmt.format(v * scale)

        rest = {True: "yes", False: "NO", None: "-"}[r.get("at_rest")]
        why = r.get("exception") or r.get("reason") or ""
        lines.append(
            f"{r['run_id']:<36} {r['patient']:<8} {r['status']:<9} "
            f"{num('peak_force_n'):>10} {num('time_above_ceiling_s', 1000, '{:.0f}'):>10} "
            f"{rest:>5} {num('sim_s'):>6} {num('wall_s'):>7}  {why[:90]}"
        )
    return "\n".join(lines)


def plot_campaign(results: list[dict], ceiling: float, path) -> Path:
    """campaign.png: outcomes per fault type (stacked DONE / ABORT / other) and the peak
    true contact force of every run against the force ceiling."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = per_fault(results)
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(14, 6))
    fig.subplots_adjust(left=0.16, right=0.98, wspace=0.6, bottom=0.2)
    y = np.arange(len(rows))
    done = np.array([r["done"] for r in rows])
    abort = np.array([r["abort"] for r in rows])
    other = np.array([r["runs"] for r in rows]) - done - abort
    ax1.barh(y, done, color="tab:green", label="DONE")
    ax1.barh(y, abort, left=done, color="tab:orange", label="ABORT (with reason)")
    ax1.barh(y, other, left=done + abort, color="tab:red", label="timeout / exception")
    ax1.set_yticks(y, [r["fault"] for r in rows])
    ax1.invert_yaxis()
    ax1.set_xlabel("runs")
    ax1.set_title("Outcome per fault type")
    ax1.legend(loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=3, fontsize=8)
    index = {r["fault"]: i for i, r in enumerate(rows)}
    for r in results:
        if r.get("peak_force_n") is None or r["fault"] not in index:
            continue
        colour = {"DONE": "tab:green", "ABORT": "tab:orange"}.get(r["status"], "tab:red")
        ax2.scatter(r["peak_force_n"], index[r["fault"]], s=14, color=colour, alpha=0.7)
    ax2.axvline(ceiling, color="k", ls="--", lw=1, label=f"force ceiling {ceiling:.0f} N")
    ax2.set_yticks(y, [r["fault"] for r in rows])
    ax2.invert_yaxis()
    ax2.set_xlabel("peak TRUE contact force per run (N)")
    ax2.set_title("Peak contact force (simulation ground truth, every plant step)")
    ax2.legend(loc="upper center", bbox_to_anchor=(0.5, -0.1), fontsize=8)
    fig.suptitle(f"Reliability campaign: {len(results)} runs")
    return save_figure(fig, path)


def _fmt(v, spec: str = ".1f") -> str:
    return "-" if v is None else format(v, spec)


def write_outputs(out_dir, results: list[dict], meta: dict) -> list[Path]:
    out = Path(out_dir)
    summary = summarize(results)
    faults = per_fault(results)
    keys = [
        "run_id",
        "fault",
        "patient",
        "status",
        "reason",
        "peak_force_n",
        "time_above_ceiling_s",
        "longest_above_ceiling_s",
        "force_violation",
        "at_rest",
        "sim_s",
        "wall_s",
        "e_trans_mm",
        "e_trans_at_localization_mm",
        "exception",
    ]
    rows = sorted(results, key=lambda r: r["run_id"])
    md = [
        "# Reliability campaign",
        "",
        f"{meta}",
        "",
        "## Summary",
        "",
        "```",
        json.dumps(summary, indent=1),
        "```",
        "",
        "## DONE fraction per fault type",
        "",
        "| fault | runs | DONE | ABORT | DONE fraction | max peak F (N) | "
        "median E_trans of DONE runs (mm, vs the kidney at localization) |",
        "|---|---|---|---|---|---|---|",
    ]
    md += [
        f"| {f['fault']} | {f['runs']} | {f['done']} | {f['abort']} | "
        f"{f['done_fraction']:.2f} | {f['max_peak_force_n']:.1f} | "
        f"{_fmt(f['median_e_trans_done_mm'])} |"
        for f in faults
    ]
    md += ["", "## Runs", "", "```", outcome_table(results), "```", ""]
    written = (
        [plot_campaign(results, float(meta.get("force_ceiling_n", 20.0)), out / "campaign.png")]
        if results
        else []
    )
    return written + [
        write_csv_atomic(
            out / "campaign.csv", rows, keys, float_format=None, extrasaction="ignore"
        ),
        write_text_atomic(
            out / "campaign.json",
            json.dumps({"summary": summary, "per_fault": faults, "meta": meta}, indent=1),
        ),
        write_text_atomic(out / "campaign.md", "\n".join(md)),
    ]
