"""The default scan on real bodies (``python -m benchmarks real_anatomy [--patients DIR ...]``).

Runs the product's default scan (default scenario: start planner, learned segmenter,
registration, pivot) in the closed-loop simulation on every real body given (default: the
Visible Human female in ``../shared/anatomy/hubmap_vh_female``), supine and in left lateral
decubitus, and prints a table and, last, one JSON line: per body and posture the status, the
reason of a stop, E_trans (mm), E_rot,x (deg), V, the depth preset and window the planner
chose; a safety stop on "segmentation lost" says in how many frames of the watchdog's
window the true kidney was in the image (``segmentation_lost_in_view``: a loss, not an
expected absence; the JSON counts them). Every scan also says how its own kidney-visible
decisions agreed with the truth (``segmentation_in_loop``: frames with the kidney in view
it did not see, frames with no kidney in the image it marked one in; summed in the JSON).
Real bodies are never used for training or tuning; this is how we check the generator is
not the world. ``--out DIR`` also writes every scan's outputs (summary, pictures).
``--fresh-seeds K`` also scans K generated patients never seen before (generator seeds
5,000,000 + k, outside the training and test cohorts), supine unless ``--fresh-postures``
says otherwise (``left_lateral_decubitus``, or both): the default scan must keep working on
the generator's own world. Every rule of this project has been read on those same K seeds,
so they are no longer unseen by the people tuning the scan: ``--fresh-seed-base N`` starts
them at N instead (any N whose K seeds miss the reserved cohorts, generator seeds
1,000,000-3,999,999: training, test, CT bodies and population subjects).
"""

import argparse
import sys
from pathlib import Path

from tqdm import tqdm

from benchmarks._scan_rows import (
    argument_error,
    distinct,
    in_loop_line,
    in_loop_totals,
    scan_row,
    scenario_from_args,
)
from drake_rus.anatomy.cohort import TRAIN_OFFSET
from drake_rus.anatomy.ct_patient import CT_BODY_OFFSET
from drake_rus.cli import add_scenario_arguments
from drake_rus.io_utils import dumps_strict
from drake_rus.localization.localize import load_registration_template
from drake_rus.paths import REPO_ROOT

DEFAULT_BODIES = [REPO_ROOT.parent / "shared" / "anatomy" / "hubmap_vh_female"]
FRESH_SEED_BASE = 5_000_000
# Generator seeds the cohorts own: train 1e6 + K, test 2e6 + K, CT bodies and population
# template subjects 3e6 + (0..999,999) (ct_patient.ct_body_seed's modulus).
RESERVED_SEEDS = range(TRAIN_OFFSET, CT_BODY_OFFSET + 1_000_000)
POSTURES = ("supine", "left_lateral_decubitus")


def check_fresh_seed_base(base: int, count: int) -> str | None:
    """None if the ``count`` seeds from ``base`` are fresh generator seeds, else the error
    line (negative, or overlapping the reserved cohorts)."""
    if base < 0:
        return f"--fresh-seed-base: expected a non-negative integer, got {base}"
    if count > 0 and base < RESERVED_SEEDS.stop and base + count > RESERVED_SEEDS.start:
        return (
            f"--fresh-seed-base: seeds {base}..{base + count - 1} overlap the reserved "
            f"cohorts {RESERVED_SEEDS.start}..{RESERVED_SEEDS.stop - 1} (training, test, CT "
            "bodies, population subjects); choose a base outside them"
        )
    return None


def run_one(body, posture: str, scenario, template, out: Path | None, max_sim_time: float) -> dict:
    """One scan of a body (a path, or a spec like ``seed:N``); never raises (a failure is a
    row with its reason)."""
    name = body.name if isinstance(body, Path) else str(body)

    def fill(row, result, summary, s):
        row.update(
            e_trans_mm=summary["e_trans_mm"],
            e_rot_x_deg=summary["e_rot_x_deg"],
            volume_ratio=summary["volume_ratio"],
            n_frames=summary["n_frames"],
            volume_ratio_whole_pivot=summary.get("volume_ratio_whole_pivot"),
            eps_mm=summary["eps_mm"],
            depth_preset_m=summary["image_depth_m"],
            start=summary["start"],
            sim_s=summary["sim_s"],
        )

    return scan_row(
        {"body": name, "posture": posture},
        str(body),
        scenario,
        "{patient: {posture: %s}}" % posture,
        template,
        max_sim_time,
        out=None if out is None else out / f"{name.replace(':', '_')}_{posture}",
        fill=fill,
    )


def _fmt(v, spec):
    return "-" if v is None else format(v, spec)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks real_anatomy", description=__doc__)
    parser.add_argument(
        "--patients",
        nargs="+",
        default=[str(p) for p in DEFAULT_BODIES],
        help="real bodies: patient folders or label maps (a repeated one counts once)",
    )
    parser.add_argument(
        "--postures",
        nargs="+",
        default=list(POSTURES),
        choices=POSTURES,
        help="postures of the real bodies (default: both; a repeated one counts once)",
    )
    add_scenario_arguments(parser)
    parser.add_argument("--max-sim-time", type=float, default=120.0)
    parser.add_argument("--out", default=None, help="also write each scan's outputs here")
    parser.add_argument(
        "--fresh-seeds",
        type=int,
        default=0,
        help="also scan this many never-seen generated patients",
    )
    parser.add_argument(
        "--fresh-seed-base",
        type=int,
        default=FRESH_SEED_BASE,
        help=f"first generator seed of the fresh patients (default {FRESH_SEED_BASE:,}; "
        f"not in the reserved cohorts {RESERVED_SEEDS.start:,}-{RESERVED_SEEDS.stop - 1:,})",
    )
    parser.add_argument(
        "--fresh-postures",
        nargs="+",
        default=["supine"],
        choices=POSTURES,
        help="postures of the fresh generated patients (default: supine; a repeated one "
        "counts once)",
    )
    args = parser.parse_args(argv)
    args.postures, args.fresh_postures = distinct(args.postures), distinct(args.fresh_postures)
    bodies = distinct(Path(p) for p in args.patients)  # body/ and ./body: one body
    missing = [str(p) for p in bodies if not p.exists()]
    if missing:
        print(f"--patients: not found: {', '.join(missing)}", file=sys.stderr)
        return 2
    error = argument_error(args)
    if error:
        print(error, file=sys.stderr)
        return 2
    if args.fresh_seeds < 0:
        print(f"--fresh-seeds: expected 0 or more, got {args.fresh_seeds}", file=sys.stderr)
        return 2
    error = check_fresh_seed_base(args.fresh_seed_base, args.fresh_seeds)
    if error:
        print(error, file=sys.stderr)
        return 2
    scenario, error = scenario_from_args(args)
    if error:
        print(error, file=sys.stderr)
        return 2
    template = load_registration_template(scenario.localization.template)
    out = Path(args.out) if args.out else None
    rows = []
    jobs = [(b, p) for b in bodies for p in args.postures]
    jobs += [
        (f"seed:{args.fresh_seed_base + k}", p)
        for p in args.fresh_postures
        for k in range(args.fresh_seeds)
    ]
    for body, posture in tqdm(jobs, desc="real bodies", unit="scan"):
        row = run_one(body, posture, scenario, template, out, args.max_sim_time)
        rows.append(row)
        tqdm.write(f"{row['body']} {posture}: {row['status']} {row.get('reason', '')}")
    # V: pole to pole (the paper's); V all: over the whole pivot (both legs).
    print(
        f"{'body':28s} {'posture':24s} {'status':7s} {'E_trans mm':>10s} "
        f"{'E_rot,x deg':>11s} {'V':>6s} {'V all':>6s} {'depth':>6s}  reason"
    )
    for r in rows:
        lost = r.get("segmentation_lost_in_view")
        if lost is not None:
            r["reason"] = (
                f"{r.get('reason', '')} [segmentation lost with the kidney in view in "
                f"{lost['frames_in_view']} of {lost['frames']} frames]"
            )
        print(
            f"{r['body']:28s} {r['posture']:24s} {r['status']:7s} "
            f"{_fmt(r.get('e_trans_mm'), '10.2f')} {_fmt(r.get('e_rot_x_deg'), '11.2f')} "
            f"{_fmt(r.get('volume_ratio'), '6.3f')} "
            f"{_fmt(r.get('volume_ratio_whole_pivot'), '6.3f')} "
            f"{_fmt(r.get('depth_preset_m'), '6.2f')}  {r.get('reason', '')}"
        )
    fresh = [r for r in rows if r["body"].startswith("seed:")]
    in_loop = in_loop_totals(rows)
    print(in_loop_line(in_loop))
    print(
        dumps_strict(
            {
                "scans": [
                    {
                        k: r.get(k)
                        for k in (
                            "body",
                            "posture",
                            "status",
                            "reason",
                            "e_trans_mm",
                            "e_rot_x_deg",
                            "volume_ratio",
                            "volume_ratio_whole_pivot",
                            "depth_preset_m",
                            "wall_s",
                            "segmentation_lost_in_view",
                            "segmentation_in_loop",
                        )
                    }
                    for r in rows
                ],
                "fresh_seeds_done": sum(r["status"] == "DONE" for r in fresh),
                "fresh_seeds": len(fresh),
                "fresh_seed_base": args.fresh_seed_base,
                "fresh_seeds_done_by_posture": {
                    p: sum(r["status"] == "DONE" for r in fresh if r["posture"] == p)
                    for p in args.fresh_postures
                },
                "errors": sum(r["status"] == "ERROR" for r in rows),
                # Safety stops on "segmentation lost" while the true kidney was in the image
                # (a loss, not an expected absence): should be none.
                "segmentation_lost_in_view": sum(
                    bool((r.get("segmentation_lost_in_view") or {}).get("in_view")) for r in rows
                ),
                "segmentation_lost": sum(
                    r.get("segmentation_lost_in_view") is not None for r in rows
                ),
                # The scans' own kidney-visible decisions against the truth, summed.
                "segmentation_in_loop": in_loop,
            }
        )
    )
    return 0
