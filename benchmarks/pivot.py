"""Pivot strategies compared closed loop (``python -m benchmarks pivot [--patients test:0-14]``).

Runs the product's default scan (default scenario) on each patient once per pivot strategy
(``controller.pivot_strategy``: ``two_leg``, the seed's, and ``predicted_end``, beyond the
seed: pre-tilt in TRANSIT to the end the registered template predicts, then one sweep) and
prints, per patient and as means: the whole pivot's eps and n (``eps_whole_pivot_mm``,
``n_whole_pivot``: every PIVOT frame), pole to pole eps and n (``eps_mm``, ``n_frames``),
V and V over the whole pivot, E_trans and the status; then one JSON line.

The scan diagram feeds the supervisor the template and the probe's fan
(``drake_rus.scan.diagram.PivotModelFor``). The pre-tilt's own window path (TRANSIT frames after
arrival at p*)
is reported too (``eps_pretilt_mm``), since it is not a PIVOT frame.
"""

import argparse
import math
import sys

import numpy as np

from benchmarks._scan_rows import argument_error, distinct, scan_row
from drake_rus.control.supervisor import Phase
from drake_rus.experiments.specs import expand_patients
from drake_rus.io_utils import dumps_strict
from drake_rus.localization.localize import load_registration_template
from drake_rus.metrics.sweep import cumulative_eps
from drake_rus.scenario import LoadScenario

STRATEGIES = ("two_leg", "predicted_end")
FIELDS = (
    "eps_whole_pivot_mm",
    "n_whole_pivot",
    "eps_mm",
    "n_frames",
    "volume_ratio",
    "volume_ratio_whole_pivot",
    "e_trans_mm",
)


def _pretilt_eps_mm(result, depth) -> float:
    """Window path (mm) of the pre-tilt: the TRANSIT frames after the last one pointing
    straight down (within 0.03 rad of r3*)."""
    frames = [f for f in result.frames if f.phase == Phase.TRANSIT]
    down = [k for k, f in enumerate(frames) if f.X_BP.rotation().matrix()[2, 2] <= -math.cos(0.03)]
    if not down:
        return 0.0
    poses = [f.X_BP for f in frames[down[-1] :]]
    return float(cumulative_eps(poses, depth)[-1] * 1e3) if len(poses) > 1 else 0.0


def run_one(spec, strategy, scenario, template, max_sim_time) -> dict:
    def fill(row, result, summary, s):
        row.update({k: summary.get(k) for k in FIELDS})
        row["eps_pretilt_mm"] = _pretilt_eps_mm(result, s.imaging.depth)

    return scan_row(
        {"patient": spec, "strategy": strategy},
        spec,
        scenario,
        "{controller: {pivot_strategy: %s}}" % strategy,
        template,
        max_sim_time,
        fill=fill,
    )


def _f(v, spec):
    return "-" if v is None else format(v, spec)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks pivot", description=__doc__)
    parser.add_argument("--patients", default="test:0-4")
    parser.add_argument(
        "--strategies",
        nargs="+",
        default=list(STRATEGIES),
        choices=STRATEGIES,
        help="pivot strategies to compare (default: all; a repeated one counts once)",
    )
    parser.add_argument("--scenario", default="default")
    parser.add_argument("--set", dest="overrides", default=None, help="YAML overrides")
    parser.add_argument("--max-sim-time", type=float, default=150.0)
    args = parser.parse_args(argv)
    args.strategies = distinct(args.strategies)
    error = argument_error(args)
    if error:
        print(error, file=sys.stderr)
        return 2
    try:
        specs = expand_patients(args.patients)
    except ValueError as e:  # the message names --patients
        print(e, file=sys.stderr)
        return 2
    scenario = LoadScenario(scenario_name=args.scenario, scenario_text=args.overrides)
    template = load_registration_template(scenario.localization.template)
    rows = []
    for spec in specs:
        for strategy in args.strategies:
            row = run_one(spec, strategy, scenario, template, args.max_sim_time)
            rows.append(row)
            print(
                f"# {spec} {strategy}: {row['status']} eps_whole "
                f"{_f(row.get('eps_whole_pivot_mm'), '.1f')} mm, n_whole "
                f"{row.get('n_whole_pivot')}, V {_f(row.get('volume_ratio'), '.3f')} "
                f"({row['wall_s']} s) {row.get('reason', '')}",
                flush=True,
            )
    head = (
        f"{'patient':9s} {'strategy':14s} {'status':7s} {'eps_whole':>9s} {'n_whole':>7s} "
        f"{'eps_p2p':>8s} {'n_p2p':>5s} {'V':>6s} {'V_whole':>7s} {'E_trans':>7s} "
        f"{'pretilt':>7s}"
    )
    print(head)
    for r in rows:
        print(
            f"{r['patient']:9s} {r['strategy']:14s} {r['status']:7s} "
            f"{_f(r.get('eps_whole_pivot_mm'), '9.1f')} {_f(r.get('n_whole_pivot'), '7d')} "
            f"{_f(r.get('eps_mm'), '8.1f')} {_f(r.get('n_frames'), '5d')} "
            f"{_f(r.get('volume_ratio'), '6.3f')} "
            f"{_f(r.get('volume_ratio_whole_pivot'), '7.3f')} "
            f"{_f(r.get('e_trans_mm'), '7.2f')} {_f(r.get('eps_pretilt_mm'), '7.1f')}"
        )
    # Means over the patients where every strategy finished (DONE).
    done = {r["patient"] for r in rows}
    for strategy in args.strategies:
        done &= {r["patient"] for r in rows if r["strategy"] == strategy and r["status"] == "DONE"}
    means = {}
    for strategy in args.strategies:
        sel = [r for r in rows if r["strategy"] == strategy and r["patient"] in done]
        means[strategy] = {
            k: (float(np.mean([r[k] for r in sel])) if sel else None)
            for k in FIELDS + ("eps_pretilt_mm",)
        }
        m = means[strategy]
        print(
            f"{'mean':9s} {strategy:14s} {len(sel):>3d} ok  "
            f"{_f(m['eps_whole_pivot_mm'], '9.1f')} {_f(m['n_whole_pivot'], '7.1f')} "
            f"{_f(m['eps_mm'], '8.1f')} {_f(m['n_frames'], '5.1f')} "
            f"{_f(m['volume_ratio'], '6.3f')} {_f(m['volume_ratio_whole_pivot'], '7.3f')} "
            f"{_f(m['e_trans_mm'], '7.2f')} {_f(m['eps_pretilt_mm'], '7.1f')}"
        )
    reduction = None
    if all(means.get(s, {}).get("eps_whole_pivot_mm") for s in STRATEGIES):
        reduction = 1 - (
            means["predicted_end"]["eps_whole_pivot_mm"] / means["two_leg"]["eps_whole_pivot_mm"]
        )
        print(
            f"whole-pivot eps reduction (predicted_end vs two_leg, {len(done)} patients): "
            f"{reduction:.1%}"
        )
    print(
        dumps_strict(
            {
                "scans": [
                    {
                        k: r.get(k)
                        for k in (
                            "patient",
                            "strategy",
                            "status",
                            "reason",
                            *FIELDS,
                            "eps_pretilt_mm",
                            "wall_s",
                        )
                    }
                    for r in rows
                ],
                "means": means,
                "patients_all_done": sorted(done),
                "eps_whole_pivot_reduction": reduction,
                "errors": sum(r["status"] == "ERROR" for r in rows),
            }
        )
    )
    return 0
