"""The default scan on real CT kidneys (``python -m benchmarks real_kidneys --cases DIR
[--limit N] [--template generated|real] [--side right|left] [--workers N] [--offset K]
[--scenario NAME] [--set YAML] [--out DIR]``).

For every case under DIR (KiTS layout: ``DIR/case_*/segmentation.nii.gz``, labels 0
background, 1 kidney, 2 tumour; cases in sorted order, the first ``--limit`` after
skipping ``--offset``), a patient
carrying that case's kidney (``ct:CASE#SIDE``: the real kidney with its tumour in a generated
body, :mod:`drake_rus.anatomy.ct_patient`; the right kidney by default) is scanned by the
product's default closed-loop scan (default scenario: start planner, learned segmenter,
registration, pivot; the scanned side is the kidney's side, so nothing is mirrored). A case
whose kidney cannot be used (missing, cut by the field of view, a frame the anatomy cannot
establish) is skipped with its reason, before any scan; so is one whose kidney fits none of
the generated bodies tried (a very large tumour:
:class:`~drake_rus.anatomy.ct_patient.CtKidneyDoesNotFit`), when its patient is built.

``--template real`` builds (or reads from the cache) the template of real kidneys of the
same folder without any of the benchmarked cases
(:func:`drake_rus.template.ct.resolve_template`'s exclusion) and says which cases built it.

``--scenario NAME`` and ``--set YAML`` choose and change the scenario of every scan (as
for ``drake-rus scan``), for example ``--set "{imaging: {segmenter: oracle}}"`` to measure
what the learned segmenter costs: the JSON keeps both (``scenario``, ``overrides``). The
template is ``--template``'s; ``localization.template`` in ``--set`` is refused.

Prints one line per case as it finishes, a table (one row per case in case order: status,
reason, E_trans, E_rot,x, V, tumour volume) and, last, one JSON line::

    {"n", "done", "skipped", "e_trans_mm": {"mean", "max"}, "e_rot_x_deg": {"mean", "max"},
     "volume_ratio": {"mean", "min"}, "rows": [...], ...}

``n`` counts the cases looked at (skipped ones included) and ``done`` the DONE scans
among them: a skipped case counts as not done ("DONE on 28 of 30" means 28 of the 30
cases attempted). The error statistics are over the DONE scans (``null`` when there is
none). Scans run in ``--workers`` processes (default: 2,
capped at the CPUs and memory available; 0 runs them in this process); each scan is
deterministic, and rows come out in case order whatever the workers' timing. Ctrl-C, or a
worker that dies, ends the run with the table and JSON of the scans finished so far (the
others NOT RUN, ``interrupted`` saying why) and exit status 1.
"""

import argparse
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from multiprocessing import get_context
from pathlib import Path

import numpy as np
from tqdm import tqdm

from benchmarks._scan_rows import argument_error, in_loop_totals, scenario_from_args
from drake_rus.anatomy.cache import file_digest
from drake_rus.anatomy.ct_kidney import import_ct_kidneys, read_label_grid, select_kidney
from drake_rus.batch import bound_workers
from drake_rus.cli import add_scenario_arguments
from drake_rus.io_utils import dumps_strict
from drake_rus.provenance import Provenance
from drake_rus.scenario import DEFAULT_SCENARIOS_FILE, LoadScenario
from drake_rus.template.ct import CtTemplateError, find_label_maps, resolve_template
from drake_rus.template.io import load_template

SIDES = ("right", "left")
TEMPLATES = ("generated", "real")
ROW_KEYS = (
    "case",
    "status",
    "reason",
    "e_trans_mm",
    "e_rot_x_deg",
    "volume_ratio",
    "tumour_ml",
    "parenchyma_ml",
    "rms_residual_mm",
    "wall_s",
    "exploration",
    "second_look",
    "segmentation_in_loop",
)


def check_template_field(scenario, base) -> str | None:
    """The error when ``--set`` moved ``localization.template`` (``scenario`` against the
    same named scenario without the overrides, ``base``): ``--template`` decides it."""
    if scenario.localization.template != base.localization.template:
        return (
            "--set: localization.template: the template is --template's "
            f"({'|'.join(TEMPLATES)}), not a scenario field here"
        )
    return None


def find_cases(ct_dir: Path, limit: int | None, offset: int = 0) -> list[tuple[str, Path]]:
    """(case name, label map) of the KiTS-layout folder, sorted; from the ``offset``-th,
    the first ``limit``."""
    maps = find_label_maps(ct_dir)[offset:]
    return maps[:limit] if limit else maps


def kidney_of_case(path: Path, side: str) -> dict:
    """The ``side`` kidney of a label map: ``{"parenchyma_ml", "tumour_ml"}``, or
    ``{"skip": why}`` when it cannot be used (unreadable, no frame, missing, cut)."""
    try:
        k = select_kidney(import_ct_kidneys(read_label_grid(path)), side)
    except (ValueError, OSError) as e:
        return {"skip": str(e)}
    return {"parenchyma_ml": round(k.parenchyma_ml, 1), "tumour_ml": round(k.tumour_ml, 1)}


def scan_case(job: dict) -> dict:
    """Scans one case (``job``: case, spec, side, template path, max_sim_time, out); never
    raises (a failure is a row with status ERROR and its reason)."""
    from benchmarks._scan_rows import scan_row
    from drake_rus.anatomy.ct_patient import CtKidneyDoesNotFit
    from drake_rus.localization.localize import load_registration_template

    def fill(row, result, summary, s):
        loc = summary.get("localization") or {}
        row.update(
            e_trans_mm=summary["e_trans_mm"],
            e_rot_x_deg=summary["e_rot_x_deg"],
            volume_ratio=summary["volume_ratio"],
            rms_residual_mm=loc.get("rms_residual_mm"),
            sim_s=summary["sim_s"],
            exploration=summary.get("exploration"),
        )
        if summary.get("second_look"):
            row["second_look"] = summary["second_look"]

    row = {"case": job["case"], "tumour_ml": job["tumour_ml"], "parenchyma_ml": job["par_ml"]}
    try:
        template = load_registration_template(job["template"])
    except (OSError, ValueError) as e:
        row.update(status="ERROR", reason=f"template: {e}", wall_s=0.0)
        return row
    return scan_row(
        row,
        job["spec"],
        LoadScenario(
            filename=job.get("scenarios_file") or DEFAULT_SCENARIOS_FILE,
            scenario_name=job.get("scenario", "default"),
            scenario_text=job.get("overrides"),
        ),
        "{patient: {side: %s}}" % job["side"],
        template,
        job["max_sim_time"],
        out=None if job["out"] is None else Path(job["out"]) / job["case"],
        fill=fill,
        progress=False,
        skip=(CtKidneyDoesNotFit,),
    )


def _stat(values, how) -> dict | None:
    v = np.asarray([x for x in values if x is not None], float)
    if len(v) == 0:
        return None
    return {"mean": round(float(v.mean()), 3), how: round(float(getattr(v, how)()), 3)}


def summarise(rows: list[dict]) -> dict:
    """The JSON totals of the rows (error statistics over the DONE scans)."""
    done = [r for r in rows if r["status"] == "DONE"]
    statuses: dict = {}
    for r in rows:
        statuses[r["status"]] = statuses.get(r["status"], 0) + 1
    return {
        "n": len(rows),
        "done": len(done),
        "skipped": statuses.get("SKIPPED", 0),
        "statuses": statuses,
        "e_trans_mm": _stat([r.get("e_trans_mm") for r in done], "max"),
        "e_rot_x_deg": _stat([r.get("e_rot_x_deg") for r in done], "max"),
        "volume_ratio": _stat([r.get("volume_ratio") for r in done], "min"),
        "tracebacks": sum("traceback" in r for r in rows),
        # The scans' own kidney-visible decisions against the truth, summed.
        "segmentation_in_loop": in_loop_totals(rows),
    }


def _plain(o):
    return o.item() if isinstance(o, np.generic) else str(o)


def _round(v):
    return round(float(v), 3) if isinstance(v, (float, np.floating)) else v


def _fmt(v, spec):
    if v is None:
        width = spec.split(".")[0]
        return format("-", f">{width}") if width else "-"
    return format(v, spec)


def print_table(rows, file=sys.stdout) -> None:
    print(
        f"{'case':12s} {'status':10s} {'E_trans mm':>10s} {'E_rot,x deg':>11s} {'V':>6s} "
        f"{'tumour mL':>9s}  reason",
        file=file,
    )
    for r in rows:
        print(
            f"{r['case']:12s} {r['status']:10s} {_fmt(r.get('e_trans_mm'), '10.2f')} "
            f"{_fmt(r.get('e_rot_x_deg'), '11.2f')} {_fmt(r.get('volume_ratio'), '6.3f')} "
            f"{_fmt(r.get('tumour_ml'), '9.1f')}  {r.get('reason') or ''}"
            + (" [second look: whole kidney]" if r.get("second_look") else ""),
            file=file,
        )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks real_kidneys",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--cases", required=True, help="folder DIR/case_*/segmentation.nii.gz")
    parser.add_argument("--limit", type=int, default=None, help="the first N cases")
    parser.add_argument(
        "--offset", type=int, default=0, help="skip the first K cases (held-out runs)"
    )
    parser.add_argument("--template", default="generated", choices=TEMPLATES)
    parser.add_argument("--side", default="right", choices=SIDES)
    parser.add_argument("--workers", type=int, default=2, help="scan processes (0: this one)")
    parser.add_argument("--max-sim-time", type=float, default=120.0)
    parser.add_argument("--out", default=None, help="also write each scan's outputs here")
    add_scenario_arguments(parser)
    args = parser.parse_args(argv)
    ct_dir = Path(args.cases).expanduser().resolve()
    error = argument_error(args)
    if error:
        print(error, file=sys.stderr)
        return 2
    if args.limit is not None and args.limit < 1:
        print(f"--limit: expected 1 or more cases, got {args.limit}", file=sys.stderr)
        return 2
    if args.offset < 0:
        print(f"--offset: expected 0 or more cases, got {args.offset}", file=sys.stderr)
        return 2
    scenario, error = scenario_from_args(args)
    if scenario is not None and args.overrides:
        base = LoadScenario(filename=args.scenarios_file, scenario_name=args.scenario)
        error = check_template_field(scenario, base)
    if error:
        print(error, file=sys.stderr)
        return 2
    try:
        workers, note = bound_workers(args.workers)
    except ValueError as e:
        print(str(e), file=sys.stderr)
        return 2
    if note:
        print(note, file=sys.stderr)
    try:
        cases = find_cases(ct_dir, args.limit, args.offset)
    except CtTemplateError as e:
        print(f"--cases: {e}", file=sys.stderr)
        return 2
    if not cases:
        print(f"--offset: {args.offset} skips every case of {ct_dir}", file=sys.stderr)
        return 2
    t0 = time.time()
    template_info = {"spec": args.template}
    if args.template == "real":
        names = [c for c, _ in cases]
        try:
            path = resolve_template(
                f"real:{ct_dir}", exclude_cases=names, log=lambda s: print(s, flush=True)
            )
        except (CtTemplateError, ValueError) as e:
            print(f"--template real: {e}", file=sys.stderr)
            return 2
        meta = load_template(path).meta
        template_info.update(path=str(path), cases=meta.get("cases", []))
        print(
            f"template: {len(meta.get('subjects_used', []))} {meta.get('side')} kidneys of "
            f"{', '.join(meta.get('cases', []))} (none of the {len(names)} benchmarked cases)",
            flush=True,
        )
    else:
        path = resolve_template("generated")
        template_info["path"] = str(path)
    # A template rebuilt elsewhere may differ: its digest tells two runs' templates apart.
    template_info["sha256"] = file_digest(path)
    rows: list = [None] * len(cases)
    jobs = []
    for i, (case, seg) in tqdm(
        list(enumerate(cases)), desc="reading kidneys", unit="case", leave=False
    ):
        k = kidney_of_case(seg, args.side)
        if "skip" in k:
            rows[i] = {"case": case, "status": "SKIPPED", "reason": k["skip"]}
            tqdm.write(f"{case}: SKIPPED {k['skip']}")
            continue
        jobs.append(
            {
                "i": i,
                "case": case,
                "spec": f"ct:{seg.parent if seg.name.startswith('segmentation') else seg}"
                f"#{args.side}",
                "side": args.side,
                "template": str(path),
                "tumour_ml": k["tumour_ml"],
                "par_ml": k["parenchyma_ml"],
                "max_sim_time": args.max_sim_time,
                "out": args.out,
                "scenarios_file": args.scenarios_file,
                "scenario": args.scenario,
                "overrides": args.overrides,
            }
        )
    bar = tqdm(total=len(jobs), desc="scans", unit="scan")

    def done(job, row):
        rows[job["i"]] = row
        bar.update(1)
        e = row.get("e_trans_mm")
        tqdm.write(
            f"{row['case']}: {row['status']} "
            + (
                f"E_trans {e:.2f} mm, E_rot,x {row.get('e_rot_x_deg'):.2f} deg, "
                f"V {row.get('volume_ratio')} "
                if e is not None
                else ""
            )
            + f"{row.get('reason') or ''} ({row['wall_s']} s)"
        )

    # Ctrl-C or a dead worker ends the run with the rows it has, not a traceback that
    # loses them: the missing cases are NOT RUN and the exit status is 1.
    interrupted = None
    try:
        if workers == 0 or len(jobs) <= 1:
            for job in jobs:
                done(job, scan_case(job))
        else:
            pool = ProcessPoolExecutor(
                max_workers=min(workers, len(jobs)), mp_context=get_context("spawn")
            )
            try:
                futures = {pool.submit(scan_case, job): job for job in jobs}
                for f in as_completed(futures):
                    done(futures[f], f.result())
            except BaseException:
                pool.shutdown(wait=False, cancel_futures=True)  # do not wait for the rest
                raise
            pool.shutdown()
    except KeyboardInterrupt:
        interrupted = "interrupted (Ctrl-C) before this case's scan ended"
    except BrokenProcessPool as e:
        interrupted = f"a scan worker died before this case's scan ended ({e})"
    bar.close()
    for i, r in enumerate(rows):
        if r is None:
            rows[i] = {"case": cases[i][0], "status": "NOT RUN", "reason": interrupted}
    print()
    print_table(rows)
    for r in rows:
        if "traceback" in r:
            print(f"{r['case']}: {r['traceback']}", file=sys.stderr)
    doc = summarise(rows)
    doc.update(
        cases_dir=str(ct_dir),
        side=args.side,
        template=template_info,
        scenario=args.scenario,
        overrides=args.overrides,
        workers=workers,
        interrupted=interrupted,
        wall_s=round(time.time() - t0, 1),
        # What produced the rows: package versions, commit, Python, platform, command line.
        provenance=Provenance(argv=list(sys.argv if argv is None else argv)),
        rows=[{k: _round(r[k]) for k in ROW_KEYS if k in r} for r in rows],
    )
    print(dumps_strict(doc, default=_plain))
    return 0 if interrupted is None else 1


if __name__ == "__main__":
    raise SystemExit(main())
