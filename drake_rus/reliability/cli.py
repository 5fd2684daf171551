"""``drake-rus campaign``: randomised faulty closed-loop scans (see reliability.campaign)."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from drake_rus.localization.localize import load_registration_template
from drake_rus.reliability.breathing import add_commands as add_breathing
from drake_rus.reliability.campaign import __doc__ as doc
from drake_rus.reliability.campaign import (
    fault_table,
    make_tasks,
    outcome_table,
    run_campaign,
    summarize,
    write_outputs,
)
from drake_rus.scenario import DEFAULT_SCENARIOS_FILE, LoadScenario


def add_commands(subparsers) -> None:
    p = subparsers.add_parser(
        "campaign",
        help="reliability campaign: randomised faulty scans, DONE/ABORT + safety",
        description=doc,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--runs", type=int, required=True, help="number of runs N (>= 1)")
    p.add_argument("--out", required=True, help="output directory (resumable)")
    p.add_argument(
        "--workers",
        type=int,
        default=2,
        help="parallel worker processes (0: run in this process; default 2)",
    )
    p.add_argument(
        "--scheduler",
        default=None,
        help="address of a running Dask scheduler to run on (default: local workers)",
    )
    p.add_argument("--seed", type=int, default=0, help="campaign seed (default 0)")
    p.add_argument(
        "--patients",
        type=int,
        default=15,
        help="draw patients from test:0 .. test:K-1 (default 15)",
    )
    p.add_argument("--scenario", default="quick", help="base scenario (default 'quick')")
    p.add_argument("--scenarios-file", default=None, help="YAML file of named scenarios")
    p.add_argument(
        "--max-sim-time",
        type=float,
        default=60.0,
        help="per-run limit of simulated time in s (default 60)",
    )
    p.set_defaults(func=run_campaign_command, outputs={"out": "dir"})
    add_breathing(subparsers)


def _check_args(args) -> None:
    import math

    if args.runs < 1:
        raise ValueError(f"--runs: expected a positive number of runs, got {args.runs}")
    if args.workers < 0:
        raise ValueError(f"--workers: expected 0 or more, got {args.workers}")
    if args.seed < 0:
        raise ValueError(f"--seed: expected a non-negative integer, got {args.seed}")
    if not 1 <= args.patients <= 1_000_000:
        raise ValueError(f"--patients: expected 1 or more, got {args.patients}")
    if not (math.isfinite(args.max_sim_time) and args.max_sim_time > 0):
        raise ValueError(f"--max-sim-time: expected a positive time in s, got {args.max_sim_time}")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out: {out} exists and is not a directory")


def run_campaign_command(args) -> int:

    _check_args(args)
    # Fail fast on a bad scenario or template, before any run starts or anything is written.
    scenario = LoadScenario(
        filename=args.scenarios_file or DEFAULT_SCENARIOS_FILE, scenario_name=args.scenario
    )
    try:
        load_registration_template(scenario.localization.template)
    except FileNotFoundError as e:
        raise FileNotFoundError(f"localization.template: {e}") from None
    tasks = make_tasks(
        args.runs,
        seed=args.seed,
        patients=args.patients,
        scenario=args.scenario,
        scenarios_file=args.scenarios_file,
        max_sim_time=args.max_sim_time,
    )
    start = time.perf_counter()
    done = [0]

    def progress(record):
        from tqdm import tqdm

        done[0] += 1
        tqdm.write(
            f"[{done[0]}] {record['run_id']} {record['patient']}: {record['status']}"
            f" {record.get('exception') or record.get('reason') or ''}"[:160]
        )

    results = run_campaign(
        tasks, args.out, workers=args.workers, progress=progress, scheduler=args.scheduler
    )
    wall = time.perf_counter() - start
    meta = {
        "runs": args.runs,
        "seed": args.seed,
        "scenario": args.scenario,
        "workers": args.workers,
        "max_sim_time": args.max_sim_time,
        "wall_s_this_invocation": round(wall, 1),
        "runs_this_invocation": done[0],
        "force_ceiling_n": scenario.safety.force_ceiling,
    }
    written = write_outputs(args.out, results, meta)
    print(outcome_table(results))
    print(fault_table(results))
    print(f"wrote {', '.join(str(p) for p in written)}; {done[0]} runs in {wall:.0f} s")
    summary = summarize(results)
    print(
        json.dumps(
            {
                k: summary[k]
                for k in ("runs", "done", "abort", "force_violations", "exceptions", "peak_force_n")
            }
        )
    )
    return 0 if summary["force_violations"] == 0 and summary["exceptions"] == 0 else 1
