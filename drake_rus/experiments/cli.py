"""``drake-rus study er-sweep|starts|efficiency|paper``: the seed's section III studies.

Every run is kinematic (planned probe poses, no robot dynamics; the fast twin, default) or,
with ``--mode closed-loop``, a full closed-loop scan on the Drake diagram (same run record;
tables, figures and report in OUT/closed-loop, runs in OUT/runs beside the kinematic ones,
and ``paper``'s report puts both modes side by side when both are in OUT). Runs go through
Dask:
an embedded LocalCluster of ``--workers`` processes by default (at most as many as the CPUs
and memory allow; on 127.0.0.1, no dashboard), or ``--scheduler tcp://HOST:PORT``. Ctrl-C
ends the study and its workers (exit 130). Each run's result is written to OUT/runs/ as it
finishes, with its settings key and provenance; running the same command again resumes
(finished runs with the same settings are skipped; a run of the same name made with other
settings is set aside under OUT/runs/superseded and run again). Tables and reports take
their labels from the runs. Tables (CSV), figures (PNG) and,
for ``paper``, ``efficiency`` and ``template``, ``report.md`` go to OUT (OUT/closed-loop);
with both modes' runs in OUT, ``paper``'s and ``efficiency``'s put them side by side.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
import warnings
from pathlib import Path

from drake_rus import batch
from drake_rus.batch import bound_workers, run_tasks
from drake_rus.cli import add_scenario_arguments
from drake_rus.experiments.analysis import (
    DEFAULT_MARGINS,
    STRATEGY_ORDER,
    analyze_efficiency,
    analyze_er_sweep,
    analyze_starts,
    critical_er_summary,
    sample_size_warning,
)
from drake_rus.experiments.ct_cohort import (
    ct_case_path,
    expand_ct_cohorts,
    template_cases_of_patients,
)
from drake_rus.experiments.keys import (
    run_id,
    task_inputs_digest,
    task_key,
    template_file,
    template_tag,
)
from drake_rus.experiments.report import (
    CLOSED_LOOP,
    KINEMATIC,
    figure_note,
    report_markdown,
    write_closed_loop_outputs,
    write_efficiency_outputs,
    write_er_sweep_outputs,
    write_starts_outputs,
    write_template_outputs,
)
from drake_rus.experiments.results import (
    column_of,
    load_study_results,
    results_of,
    run_settings,
    settings_of,
    usable_runs,
)
from drake_rus.experiments.specs import (
    DEFAULT_SEGMENTER,
    ER_GRID,
    MODES,
    PATIENT_KINDS,
    POSTURES,
    TEMPLATE_VARIANTS,
    StudyOptions,
    check_strategies,
    closed_loop_tasks,
    ct_selection,
    default_strategies,
    efficiency_tasks,
    er_sweep_tasks,
    expand_patients,
    patient_kind,
    population_of_variant,
    split_posture,
    starts_tasks,
    template_tasks,
)
from drake_rus.experiments.tasks import run_task
from drake_rus.experiments.templates import template_info
from drake_rus.io_utils import MB, dumps_strict, output_dir, write_text_atomic
from drake_rus.progress import stderr_is_terminal
from drake_rus.provenance import Provenance
from drake_rus.scenario import LoadScenario
from drake_rus.template.ct import (
    CtTemplateError,
    TemplateSplitWarning,
    is_template_spec,
    resolve_template,
)
from drake_rus.template.io import DEFAULT_TEMPLATE_PATH, load_template
from drake_rus.template.population import population_template

# About what a study writes (bytes): per-run JSON, tables, figures, NRRD volumes.
STUDY_OUTPUT_BYTES = 50 * MB


def add_commands(subparsers) -> None:
    p = subparsers.add_parser(
        "study",
        help="the seed paper's studies (kinematic or closed loop, Dask)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = p.add_subparsers(dest="study", metavar="STUDY")
    sub.required = True
    helps = {
        "er-sweep": "localization error vs exploration ratio 0..100% (Fig. 7d)",
        "starts": "five random exploration starts at the critical ER (Fig. 9d)",
        "efficiency": "OP, GT-OP, NOP, SL sweeps: V vs n and eps (Fig. 10), volumes "
        "(kinematic); OP-PE (the predicted-end pivot, beyond the paper); "
        "report.md",
        "paper": "all of the above into one report directory with report.md",
        "template": "localization with mismatched templates (mean, scaled, single "
        "kidney, leave-one-out, another population's) against the "
        "template's distance, generated patients and real bodies",
    }
    for name, text in helps.items():
        # argparse %-formats help strings (not descriptions): escape the "%" of "100%".
        q = sub.add_parser(name, help=text.replace("%", "%%"), description=text)
        add_scenario_arguments(q)
        q.add_argument(
            "--patients",
            default="test:0-14",
            help="comma (or semicolon) list: test:0-14, seed:100-120, train:3, "
            "ct:PATH[#OPTIONS] (a real CT kidney in a generated body), ct:DIR:0-14 "
            "(those cases of a folder of CT label maps; cases without a usable kidney "
            "left out with their reason), ct:DIR:first15 (the first 15 usable cases "
            "that did not build the template), or patient paths (default test:0-14); a "
            "ct: spec's own commas (ct:PATH#left,body=7) do not separate; "
            "study template: each optionally with @decubitus or @supine",
        )
        q.add_argument(
            "--out", default=f"reports/{name}", help=f"output directory (default reports/{name})"
        )
        q.add_argument(
            "--workers",
            type=int,
            default=2,
            help="Dask worker processes of the embedded cluster (default 2; 0 = "
            "run in this process; capped at the CPUs available and at about "
            "1 GB of free memory per worker)",
        )
        q.add_argument(
            "--scheduler",
            default=None,
            help="address of an existing Dask scheduler, e.g. tcp://host:8786",
        )
        q.add_argument(
            "--segmenter",
            default=None,
            choices=["oracle", "classical", "onnx"],
            help="segmentation of the frames (default: oracle in kinematic mode, the "
            "label volume's kidney labels, as the seed's simulation; onnx in closed-loop "
            "mode, the product's learned segmenter, as the seed's system used its "
            "network); the oracle is labelled as such in every table and figure",
        )
        q.add_argument(
            "--template",
            default=None,
            help="registration template: generated (the shipped template of 20 generated "
            "kidneys), real (20 real CT kidneys of ../shared/anatomy/kits19, built once "
            "into the cache without the patients' cases), real:DIR, or a template .npz "
            "(default: the scenario's localization.template, the generated one); runs "
            "with another template than the generated one have their own ids (__tpl-real) "
            "and outputs (OUT/template-real), and the reports put the templates OUT "
            "holds side by side",
        )
        q.add_argument(
            "--allow-template-cases",
            action="store_true",
            help="run patients whose CT case helped build the template anyway (refused "
            "by default: scoring them is not a test on unseen kidneys); the report says "
            "which",
        )
        q.add_argument(
            "--method",
            default="seed",
            choices=["seed", "deformable"],
            help="localization method (default seed, the paper's)",
        )
        q.add_argument("--seed", type=int, default=0, help="study seed (random starts)")
        q.add_argument(
            "--mode",
            default="kinematic",
            choices=list(MODES),
            help="kinematic: the fast twin (planned probe poses, default); "
            "closed-loop: every run a full closed-loop scan on the Drake "
            "diagram (outputs in OUT/closed-loop)",
        )
        q.add_argument(
            "--er-unit",
            default="kidney",
            choices=["kidney", "fixed"],
            help="what ER multiplies: the patient's kidney length (default, the "
            "paper's simulation) or the fixed L_m = 100 mm (its in-vivo rule)",
        )
        if name in ("er-sweep", "paper"):
            q.add_argument(
                "--critical-er-rule",
                default="paper",
                choices=["paper", "strict"],
                help="critical ER: the smallest ER not significantly different "
                "from 100%% (paper, default) or the smallest from which on "
                "every larger ER is not either (strict)",
            )
        q.add_argument(
            "--voxel",
            type=float,
            default=0.002,
            help="label-volume voxel size in m (default 0.002)",
        )
        if name in ("efficiency", "paper"):
            q.add_argument(
                "--recon-spacing",
                type=float,
                default=0.001,
                help="voxel size (m) of the kidney volume reconstruction (default 0.001)",
            )
            q.add_argument(
                "--strategies",
                default=None,
                help="comma list of OP, GT-OP, NOP, SL and OP-PE (OP's pose with "
                "the predicted_end pivot, beyond the paper) (default all in "
                "kinematic mode; the paper's four in closed-loop mode, one "
                "scan each: GT-OP and NOP pivot at a pose the study gives "
                "the scan, SL is the scan's line sweep)",
            )
            q.add_argument(
                "--no-nrrd",
                action="store_true",
                help="do not export the OP/GT-OP reconstructions to OUT/volumes as NRRD",
            )
        if name in ("er-sweep", "paper"):
            q.add_argument(
                "--ers",
                default=None,
                help="comma list of exploration ratios in [0, 1], including the "
                "reference 1 (ER 100%%, which every ER is compared with) "
                "(default 0,0.1,...,1)",
            )
            q.add_argument(
                "--margin-mm",
                type=float,
                default=DEFAULT_MARGINS["e_trans_mm"],
                help="clinical equivalence margin of E_trans against ER 100%% in "
                "mm, for the equivalence test (TOST) beside the critical ER "
                "(default %(default)g)",
            )
            q.add_argument(
                "--margin-deg",
                type=float,
                default=DEFAULT_MARGINS["e_rot_x_deg"],
                help="the same for E_rot,x in degrees (default %(default)g)",
            )
        if name == "template":
            q.add_argument(
                "--variants",
                default=",".join(TEMPLATE_VARIANTS),
                help="comma list of template variants: mean, scale-S, single:K, "
                "loo (training patients only), population:NAME[:N] (a "
                "template built from N (default 20) generated kidneys of "
                "another population, cached: NAME base, short, long, slim "
                "or length+Xsd) (default %(default)s)",
            )
            q.add_argument(
                "--posture",
                default=None,
                choices=list(POSTURES),
                help="lay every patient supine or in left lateral decubitus "
                "(default: the scenario's; decubitus runs' ids end in __lld)",
            )
        if name in ("starts", "efficiency", "template"):
            q.add_argument(
                "--er",
                type=float,
                default=None,
                help="exploration ratio (default: the critical ER found by an "
                "er-sweep in OUT, else 0.6)",
            )
        if name in ("starts", "paper"):
            q.add_argument("--starts", type=int, default=5, help="random starts (default 5)")
        if name == "paper":
            q.add_argument(
                "--closed-loop",
                type=int,
                default=3,
                help="closed-loop dynamic scans (first N patients, at the "
                "scenario's ER) beside their kinematic twins (default 3; 0 "
                "skips)",
            )
        q.add_argument("--no-progress", action="store_true", help="no progress bar")
        q.set_defaults(func=run_study_command, outputs={"out": "dir"})


ERS_EXPECTED = (
    "a non-empty comma list of exploration ratios in [0, 1] that includes the "
    "reference 1 (ER 100%, which every ER is compared with), e.g. 0,0.3,0.6,1"
)


def _ers(text):
    """The ER grid of ``--ers`` (None: the default 0, 0.1, ..., 1), sorted; raises ValueError
    naming ``--ers`` unless it is a non-empty list of finite numbers in [0, 1] with 1."""
    if text is None:
        return list(ER_GRID)
    try:
        ers = sorted({round(float(x), 4) for x in str(text).split(",") if x.strip()})
    except ValueError:
        raise ValueError(f"--ers: expected {ERS_EXPECTED}, got {text!r}") from None
    if not ers or not all(math.isfinite(x) and 0 <= x <= 1 for x in ers) or ers[-1] != 1:
        raise ValueError(f"--ers: expected {ERS_EXPECTED}, got {text!r}")
    return ers


def _margins(args) -> dict:
    """The clinical equivalence margins of ``--margin-mm`` / ``--margin-deg``."""
    out = {}
    for key, flag in (("e_trans_mm", "margin_mm"), ("e_rot_x_deg", "margin_deg")):
        v = getattr(args, flag, DEFAULT_MARGINS[key])
        if not (math.isfinite(v) and v > 0):
            unit = "mm" if key == "e_trans_mm" else "deg"
            raise ValueError(
                f"--{flag.replace('_', '-')}: expected a positive margin in {unit}, got {v}"
            )
        out[key] = float(v)
    return out


def _options(args):
    if not args.voxel > 0:
        raise ValueError(f"--voxel: expected a positive size in m, got {args.voxel}")
    recon = float(getattr(args, "recon_spacing", 0.001))
    if not recon > 0:
        raise ValueError(f"--recon-spacing: expected a positive size in m, got {recon}")
    mode = getattr(args, "mode", "kinematic")
    return StudyOptions(
        scenario=args.scenario,
        scenarios_file=args.scenarios_file,
        overrides=args.overrides,
        segmenter=args.segmenter or DEFAULT_SEGMENTER[mode],
        method=args.method,
        voxel=float(args.voxel),
        seed=int(args.seed),
        recon_spacing=recon,
        er_unit=getattr(args, "er_unit", "kidney"),
        mode=mode,
        posture=getattr(args, "posture", None),
    )


def _is_shipped(value) -> bool:
    """True when a template value names the shipped template of generated kidneys."""
    if value is None or str(value).strip() in ("", "generated"):
        return True
    if is_template_spec(value):
        return False
    try:
        return template_file(value).resolve() == DEFAULT_TEMPLATE_PATH.resolve()
    except OSError:
        return False


def _resolve_study_template(spec, patients, log):
    """The file of template ``spec`` for these patients (a ``real`` template is built
    without their cases), with a one-line error naming ``--template``."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", TemplateSplitWarning)
            path = resolve_template(
                spec, exclude_cases=[str(p) for p in patients if ct_case_path(p)], log=log
            )
    except CtTemplateError as e:
        raise ValueError(f"--template: {e.detail if e.field == 'template' else e}") from None
    if not Path(path).is_file():
        raise ValueError(
            f"--template: {path}: no such template file (expected generated, real, "
            "real:DIR or a template .npz)"
        )
    return Path(path)


def patients_and_template(args, patients, scenario, options):
    """The study's patients (``ct:DIR:SELECTION`` cohorts expanded,
    :func:`~drake_rus.experiments.ct_cohort.expand_ct_cohorts`) and ``options`` with its
    template resolved to a file (``--template``, else the scenario's; None while it is the
    shipped one, so runs keep their ids and keys), and what the report says about them
    (``{"ct_cases_left_out", "template_cases"}``). Refuses (ValueError naming
    ``--patients`` / ``--template``) patients of several kinds in one paper study, and
    patients whose CT case built the template unless ``--allow-template-cases``."""

    def say(line):
        print(line, file=sys.stderr, flush=True)

    spec = args.template if args.template is not None else scenario.localization.template
    shipped = _is_shipped(spec) and _is_shipped(scenario.localization.template)
    note = {"ct_cases_left_out": [], "template_cases": []}
    built = []
    real = is_template_spec(spec) and str(spec).startswith("real")
    if not shipped and not real and any(ct_selection(split_posture(p)[0]) for p in patients):
        # firstN passes by the cases that built a template file; a real template is built
        # without the patients' cases anyway.
        built = template_info(None, str(_resolve_study_template(spec, [], say)))["cases"]
    patients, left_out = expand_ct_cohorts(
        patients, scenario.patient.side, template_cases=built, log=say
    )
    note["ct_cases_left_out"] = left_out
    if args.study != "template":
        kinds = {}
        for p in patients:
            kinds.setdefault(patient_kind(p), []).append(p)
        if len(kinds) > 1:
            raise ValueError(
                "--patients: the paper's studies compare patients of one kind, got "
                + ", ".join(f"{len(v)} {PATIENT_KINDS[k]}" for k, v in kinds.items())
                + "; run each kind into its own --out (study template groups them apart)"
            )
    if shipped:
        return patients, options, note
    path = _resolve_study_template(spec, patients, say)
    lines = template_cases_of_patients(path, patients)
    if lines and not args.allow_template_cases:
        raise ValueError(
            f"--template: {len(lines)} patient(s) helped build the template ({lines[0]}); "
            "leave them out (ct:DIR:firstN passes them by), use --template real (built "
            "without them), or --allow-template-cases"
        )
    for line in lines:
        say(f"warning: {line}")
    note["template_cases"] = lines
    options = dataclasses.replace(options, template=str(spec), template_file=str(path))
    return patients, options, note


def _strategies(args, mode):
    text = getattr(args, "strategies", None)
    if not text:
        return default_strategies(mode)
    return check_strategies(text.split(","), mode)


def _dest(out: Path, mode: str, tag: str = "") -> Path:
    """Where a mode's tables, figures and report go: OUT (kinematic) or OUT/closed-loop, and
    for another template than the generated one (``tag``,
    :func:`~drake_rus.experiments.keys.template_tag`) its own folder below
    (``template-real``)."""
    dest = out / "closed-loop" if mode == "closed-loop" else out
    return dest / f"template-{tag[len('tpl-') :]}" if tag else dest


def _mode_dir(out: Path, mode: str, tag: str = "") -> Path:
    """:func:`_dest`, made."""
    dest = _dest(out, mode, tag)
    dest.mkdir(parents=True, exist_ok=True)
    return dest


def _without(settings: dict, *keys) -> dict:
    return {k: v for k, v in settings.items() if k not in keys}


# Settings in which the columns of the side-by-side report differ: the mode, the template
# (whose bytes the inputs digest covers) and the segmenter (whose default is the mode's).
COLUMN_FREE = ("mode", "template", "inputs_sha256", "segmenter")


def _other_columns(
    out: Path,
    patients,
    mode: str,
    template: str | None,
    rule: str,
    study: str = "paper",
    er: float | None = None,
    settings: dict | None = None,
    margins: dict | None = None,
) -> list[dict]:
    """The other columns of the side-by-side report: every (mode, template) of OUT's runs of
    these patients but this study's, each with its analyses {"mode", "template", "er",
    "starts", "eff", "settings"} (None for a study it lacks). A column's starts and
    efficiency runs are those at the ER its own ``study`` (else its paper study) used,
    else at ``er``. Runs of one setting only (:func:`settings_of`): those with this
    invocation's ``settings`` (but the mode, template and segmenter; the same segmenter
    first, then the column mode's default) if OUT holds them, else the only setting the
    column holds; with several and none of them this one's, that study is left out, with a
    message."""
    wanted = set(patients)
    this = (mode, template_tag(template))
    by_column = {}
    for name in ("er-sweep", "starts", "efficiency"):
        for r in load_study_results(out, name):
            if r["patient"] in wanted and column_of(r) != this:
                by_column.setdefault(column_of(r), {}).setdefault(name, []).append(r)
    mine = None if settings is None else _without(settings, *COLUMN_FREE)
    columns = []
    for (col_mode, tag), studies in sorted(
        by_column.items(), key=lambda kv: (kv[0][0] != "kinematic", kv[0][1])
    ):
        col_er = er
        col_dir = _dest(out, col_mode, tag)
        for name in dict.fromkeys((study, "paper")):
            meta_path = col_dir / f"study_{name}.json"
            if meta_path.exists():
                col_er = json.loads(meta_path.read_text()).get("er", col_er)
                break
        found, labels = {}, None
        for name, key in (("er-sweep", "er"), ("starts", "starts"), ("efficiency", "eff")):
            rs = usable_runs(
                [
                    r
                    for r in studies.get(name, [])
                    if name == "er-sweep" or (col_er is not None and abs(r["er"] - col_er) < 1e-6)
                ],
                name,
            )
            groups = {}
            for r in rs:
                groups.setdefault(
                    repr(sorted(_without(run_settings(r), "mode", "inputs_sha256").items())), []
                ).append(r)
            pick = None
            if mine is not None:
                same = [
                    g for g in groups.values() if _without(run_settings(g[0]), *COLUMN_FREE) == mine
                ]
                seg = [
                    g for g in same if run_settings(g[0])["segmenter"] == settings.get("segmenter")
                ]
                dflt = [
                    g
                    for g in same
                    if run_settings(g[0])["segmenter"] == DEFAULT_SEGMENTER[col_mode]
                ]
                pick = (seg or dflt or [None])[0] if len(seg) <= 1 else None
            if pick is None and len(groups) == 1:
                pick = next(iter(groups.values()))
            if pick is None:
                if groups:
                    print(
                        f"{name}: the {col_mode} runs in {out} "
                        f"{'with template ' + tag if tag else ''} were made with "
                        f"{len(groups)} different settings, none of them this study's: not "
                        "put side by side",
                        file=sys.stderr,
                        flush=True,
                    )
                continue
            try:
                labels = settings_of(pick, f"{col_mode} {name}")
                if name == "er-sweep":
                    found[key] = analyze_er_sweep(pick, rule=rule, margins=margins)
                elif name == "starts":
                    found[key] = analyze_starts(pick)
                else:
                    found[key] = analyze_efficiency(pick)
            except (ValueError, KeyError, ZeroDivisionError):
                continue
            found.setdefault("template_info", pick[0].get("template"))
            found.setdefault("status", {})[name] = _status_counts(pick)
        if not found or "er" not in found and "starts" not in found and "eff" not in found:
            continue
        columns.append(
            dict(
                found,
                mode=CLOSED_LOOP if col_mode == "closed-loop" else KINEMATIC,
                template=tag,
                settings=labels,
            )
        )
    return columns


def _status_counts(results) -> dict:
    """How many of a study's closed-loop scans ended in each status ({} for kinematic
    runs, which have none)."""
    out = {}
    for r in results:
        if r.get("status"):
            out[r["status"]] = out.get(r["status"], 0) + 1
    return dict(sorted(out.items(), key=lambda kv: (kv[0] != "DONE", kv[0])))


# The ER of starts, efficiency and template runs when no er-sweep of the same settings says
# otherwise: the paper's critical ER.
DEFAULT_ER = 0.6


# Settings an er-sweep may differ in from the study that takes its critical ER: the
# reconstruction grid (efficiency only) and the posture field (the resolved scenario, in
# inputs_sha256, holds the posture the runs were laid in).
CRITICAL_ER_FREE = ("recon_spacing", "posture")


def _critical_er(out: Path, settings: dict, default: float = DEFAULT_ER) -> float:
    """The critical ER of the er-sweep in ``out`` (its er_sweep.json) if that sweep was made
    with ``settings`` (but :data:`CRITICAL_ER_FREE`), else ``default`` (with a message
    saying why)."""
    path = out / "er_sweep.json"
    if not path.exists():
        return default
    try:
        saved = json.loads(path.read_text())
    except ValueError:
        saved = {}
    if not isinstance(saved.get("settings"), dict) or (
        _without(saved["settings"], *CRITICAL_ER_FREE) != _without(settings, *CRITICAL_ER_FREE)
    ):
        print(
            f"{path} was made with other settings (or records none): its critical ER is "
            f"not used; ER {default * 100:.0f}% (the paper's critical ER)",
            file=sys.stderr,
            flush=True,
        )
        return default
    if saved.get("critical_er") is None:
        print(
            f"{path}: its critical ER was not determined; ER {default * 100:.0f}% (the "
            "paper's critical ER)",
            file=sys.stderr,
            flush=True,
        )
        return default
    return float(saved["critical_er"])


def _expected_settings(options, patients=("test:0",)) -> dict:
    """The settings runs of ``options`` on ``patients`` (the first one's kind) record
    (:func:`run_settings`)."""
    patient = split_posture(str(list(patients)[0]))[0]
    task = er_sweep_tasks([patient], options, [1.0])[0]
    return run_settings({"task": task.to_dict(), "inputs_sha256": task_inputs_digest(task)})


def run_study_command(args) -> int:
    try:
        patients = expand_patients(args.patients)
    except ValueError as e:
        text = str(e)
        raise ValueError(text if text.startswith("--patients") else f"--patients: {text}") from None
    if args.study != "template" and any("@" in p for p in patients):
        raise ValueError(
            "--patients: a posture suffix (@decubitus, @supine) is only read by "
            "study template; use --scenario decubitus for the other studies"
        )
    options = _options(args)
    # Fail early (in this process) on a bad scenario or template, not in every worker, and
    # on every argument before the output folder is made.
    scenario = LoadScenario(
        filename=args.scenarios_file, scenario_name=args.scenario, scenario_text=args.overrides
    )
    patients, options, cohort = patients_and_template(args, patients, scenario, options)
    if args.study == "template":
        # Every run's posture in its record and run id (decubitus runs end in __lld).
        options = dataclasses.replace(options, posture=options.posture or scenario.patient.posture)
    margins = None
    if args.study in ("er-sweep", "paper"):
        _ers(args.ers)
        margins = _margins(args)
    if args.study in ("efficiency", "paper"):
        _strategies(args, options.mode)
    if args.study == "template":
        try:
            template_tasks(
                [], options, 0.6, [v.strip() for v in args.variants.split(",") if v.strip()]
            )
        except ValueError as e:
            raise ValueError(f"--variants: {e}") from None
    er = getattr(args, "er", None)
    if er is not None and not (math.isfinite(er) and 0 <= er <= 1):
        raise ValueError(f"--er: expected a value in [0, 1], got {er}")
    workers, note = (args.workers, None) if args.scheduler else bound_workers(args.workers)
    if note:
        print(note, file=sys.stderr, flush=True)
    with output_dir(
        args.out, "--out", need_bytes=STUDY_OUTPUT_BYTES, what=f"study {args.study}"
    ) as out:
        return _study(args, patients, options, out, workers, margins, scenario, cohort)


def _study(
    args,
    patients,
    options,
    out: Path,
    workers: int,
    margins: dict | None,
    scenario,
    cohort: dict | None = None,
) -> int:
    terminal = stderr_is_terminal()
    run = dict(
        workers=workers, scheduler=args.scheduler, progress=not args.no_progress and terminal
    )
    t0 = time.perf_counter()
    failed = []
    er_an = starts_an = eff_an = None
    mode = options.mode
    mode_text = CLOSED_LOOP if mode == "closed-loop" else KINEMATIC
    dest = _mode_dir(out, mode, template_tag(options.template))
    unusable = {}
    used = []  # every run a table below was made from: the report's labels
    study_argv = list(sys.argv)

    def note_of(results, labels):
        """A figure's second title line: segmenter, template, patients' kind."""
        info = next((r["template"] for r in results if isinstance(r.get("template"), dict)), None)
        return figure_note(
            labels,
            info
            or template_info(
                options.template, options.template_file or scenario.localization.template
            ),
        )

    def usable(study, results):
        ok = usable_runs(results, study)
        if len(ok) < len(results):
            kept = {r["run_id"] for r in ok}
            unusable[study] = [
                f"{r['run_id']}: {r.get('status', '?')} {r.get('reason', '')}"
                + "".join(
                    f"; {k} {e.get('status')} {e.get('reason', '')}"
                    for k, e in (r.get("strategies") or {}).items()
                    if e.get("status", "DONE") != "DONE"
                )
                for r in results
                if r["run_id"] not in kept
            ]
            print(
                f"{study}: {len(results) - len(ok)} run(s) without a localization"
                + (" or a finished scan" if study == "efficiency" else "")
                + " left out of the analysis",
                file=sys.stderr,
                flush=True,
            )
        return ok

    def runs_of(study, tasks):
        """This invocation's runs of ``study`` (same ids and settings keys), all of one
        setting (:func:`settings_of` refuses a mix)."""
        results = results_of(load_study_results(out, study), tasks)
        settings_of(results, f"study {study}", study)
        used.extend(results)
        return results

    counts = {"done": 0, "skipped": 0, "superseded": 0}

    def stamp(result):
        # The worker's own command line means nothing: the study's does.
        if isinstance(result.get("provenance"), dict):
            result["provenance"]["argv"] = study_argv

    def go(tasks, desc):
        plan = batch.plan(tasks, out, run_id, task_key)
        todo = len(plan["todo"])
        where = args.scheduler or (f"{workers} workers" if workers else "this process")
        print(
            f"{desc}: {len(tasks)} runs, {len(tasks) - todo} already done with these "
            f"settings, {todo} to run on {where}",
            file=sys.stderr,
            flush=True,
        )
        if plan["superseded"]:
            rid, what = plan["superseded"][0]
            print(
                f"{desc}: {len(plan['superseded'])} stored run(s) of the same name were made "
                f"with other settings (e.g. {rid}: {what}): set aside under "
                f"{batch.runs_dir(out) / batch.SUPERSEDED_DIR} and run again",
                file=sys.stderr,
                flush=True,
            )
        finished = [0]

        def line(result):
            # Per-run progress as lines when the bar is off (a log file) or not wanted.
            finished[0] += 1
            if not run["progress"] and not args.no_progress:
                print(
                    f"{desc}: run {finished[0]}/{todo} {result.get('run_id', '')} "
                    f"({time.perf_counter() - t0:.0f} s)",
                    file=sys.stderr,
                    flush=True,
                )

        status = run_tasks(
            tasks,
            run_task,
            out,
            run_id,
            desc=desc,
            on_result=line,
            task_key=task_key,
            stamp=stamp,
            **run,
        )
        counts["done"] += status["done"]
        counts["skipped"] += status["skipped"]
        counts["superseded"] += len(status["superseded"])
        failed.extend(status["failed"])
        for rid, err in status["failed"]:
            print(f"run {rid} failed: {err}", flush=True)
        return status

    ran = {}
    if args.study in ("er-sweep", "paper"):
        tasks = er_sweep_tasks(patients, options, _ers(args.ers))
        t = time.perf_counter()
        go(tasks, "er-sweep")
        ran["er-sweep"] = time.perf_counter() - t
        results = usable("er-sweep", runs_of("er-sweep", tasks))
        er_labels = _labels(results, options, "er-sweep", patients)
        er_an = write_er_sweep_outputs(
            dest,
            results,
            rule=args.critical_er_rule,
            mode=mode_text,
            margins=margins,
            settings=er_labels,
            note=note_of(results, er_labels),
        )
        print(f"er-sweep: {critical_er_summary(er_an)} ({len(results)} runs)", flush=True)
        warning = sample_size_warning(er_an)
        if warning:
            print(f"er-sweep: {warning}", file=sys.stderr, flush=True)
    er = getattr(args, "er", None)
    if er is None:
        if er_an is None:
            er = _critical_er(dest, _expected_settings(options, patients))
        elif er_an["critical_er"] is None:
            er = DEFAULT_ER
            if args.study != "er-sweep":
                print(
                    f"er-sweep: the critical ER was not determined; the other studies run "
                    f"at ER {er * 100:.0f}% (the paper's critical ER)",
                    file=sys.stderr,
                    flush=True,
                )
        else:
            er = er_an["critical_er"]
    if args.study in ("starts", "paper"):
        tasks = starts_tasks(patients, options, er, args.starts)
        t = time.perf_counter()
        go(tasks, "starts")
        ran["starts"] = time.perf_counter() - t
        results = usable("starts", runs_of("starts", tasks))
        if not results:
            print(
                "starts: no run to analyse (every one left out): no starts tables",
                file=sys.stderr,
                flush=True,
            )
        else:
            starts_an = write_starts_outputs(
                dest,
                results,
                mode=mode_text,
                note=note_of(results, _labels(results, options, "starts", patients)),
            )
            print(
                f"starts at ER {er * 100:.0f}%: any significant difference: "
                f"{starts_an['any_significant']}",
                flush=True,
            )
    if args.study in ("efficiency", "paper"):
        export = None if args.no_nrrd else (out / "volumes").resolve()
        tasks = efficiency_tasks(patients, options, er, export, _strategies(args, mode))
        t = time.perf_counter()
        go(tasks, "efficiency")
        ran["efficiency"] = time.perf_counter() - t
        results = usable("efficiency", runs_of("efficiency", tasks))
        if not results:
            print(
                "efficiency: no run to analyse (every one left out): no efficiency tables",
                file=sys.stderr,
                flush=True,
            )
        else:
            eff_an = write_efficiency_outputs(
                dest,
                results,
                mode=mode_text,
                note=note_of(results, _labels(results, options, "efficiency", patients)),
            )
            s = eff_an["summary"]
            print(
                "efficiency (pole to pole): "
                + "; ".join(
                    f"{k} n {s[k]['n'][0]:.0f} eps {s[k]['eps_mm'][0]:.1f} mm V {s[k]['V'][0]:.3f}"
                    for k in STRATEGY_ORDER
                    if k in s
                ),
                flush=True,
            )
    template_an = None
    population_builds = {}
    if args.study == "template":
        variants = [v.strip() for v in args.variants.split(",") if v.strip()]
        tasks = template_tasks(patients, options, er, variants)
        # Population templates: built (or found in the cache) here, once, not in every worker.
        for v in variants:
            pop = population_of_variant(v)
            if pop is not None:
                t = time.perf_counter()
                path = population_template(pop[0], n=pop[1], side=scenario.patient.side)
                population_builds[v] = {
                    "path": str(path),
                    "subjects": pop[1],
                    "wall_s": round(time.perf_counter() - t, 2),
                    "build_s": _build_seconds(path),
                }
                print(
                    f"template {v}: {path} ({population_builds[v]['wall_s']:.1f} s; "
                    f"built in {population_builds[v]['build_s']} s)",
                    file=sys.stderr,
                    flush=True,
                )
        t = time.perf_counter()
        go(tasks, "template")
        ran["template"] = time.perf_counter() - t
        results = usable("template", runs_of("template", tasks))
        template_an = write_template_outputs(
            dest,
            results,
            mode=mode_text,
            note=note_of(results, _labels(results, options, "template", patients)),
        )
        print(
            "template: "
            + "; ".join(
                f"{r['group']} {r['variant']} d {r['template_distance_mm_mean']:.1f} mm, E_trans "
                f"{r['e_trans_mm_mean']:.1f} mm, E_rot,x {r['e_rot_x_deg_mean']:.1f} deg"
                for r in template_an["rows"]
            ),
            flush=True,
        )
    closed = None
    if args.study == "paper" and args.closed_loop > 0 and mode == "kinematic":
        tasks = closed_loop_tasks(
            patients[: args.closed_loop], options, scenario.controller.exploration_ratio
        )
        t = time.perf_counter()
        go(tasks, "closed-loop")
        ran["closed-loop"] = time.perf_counter() - t
        closed = runs_of("closed-loop", tasks)
        write_closed_loop_outputs(dest, closed)
    wall = time.perf_counter() - t0
    labels = _labels(used, options, args.study, patients)
    meta = {
        "study": args.study,
        "patients": patients,
        "segmenter": labels["segmenter"],
        "method": labels["method"],
        "voxel": labels["voxel"],
        "seed": labels["seed"],
        "settings": labels,
        "settings_from": "runs" if used else "command line (no runs)",
        "workers": workers,
        "workers_requested": args.workers,
        "scheduler": args.scheduler,
        "wall_s": wall,
        "stage_wall_s": ran,
        "er": er,
        "er_unit": labels["er_unit"],
        "critical_er_rule": getattr(args, "critical_er_rule", None),
        "equivalence_margins": margins,
        "mode": mode + (" (+ closed-loop check)" if closed else ""),
        "mode_text": mode_text,
        "runs_without_localization": unusable,
        "failed_runs": failed,
        "runs_done": counts["done"],
        "runs_skipped": counts["skipped"],
        "runs_superseded": counts["superseded"],
        "run_commits": sorted(
            {
                f"{(r.get('provenance') or {}).get('commit')}"
                + (" (dirty)" if (r.get("provenance") or {}).get("dirty") else "")
                for r in used
            }
        ),
        "provenance": Provenance(
            scenario,
            scenario_name=args.scenario,
            scenarios_file=args.scenarios_file,
            overrides=args.overrides,
            seeds={"study_seed": options.seed},
            argv=study_argv,
        ),
    }
    kinds = {}
    for p in patients:
        k = patient_kind(p)
        kinds[k] = kinds.get(k, 0) + 1
    meta["patient_kinds"] = {PATIENT_KINDS[k]: n for k, n in kinds.items()}
    meta["template"] = next(
        (r["template"] for r in used if isinstance(r.get("template"), dict)),
        template_info(options.template, options.template_file or scenario.localization.template),
    )
    meta["run_status"] = {}
    for r in used:
        study = (r.get("task") or {}).get("study", "?")
        if r.get("status"):
            meta["run_status"].setdefault(study, []).append(r)
    meta["run_status"] = {k: _status_counts(v) for k, v in meta["run_status"].items()}
    meta["ct_cases_left_out"] = (cohort or {}).get("ct_cases_left_out", [])
    meta["patients_in_template"] = (cohort or {}).get("template_cases", [])
    if args.study == "template":
        meta["posture"] = options.posture + (
            " (per-patient @posture suffixes override)" if any("@" in p for p in patients) else ""
        )
        meta["population_templates"] = population_builds
    # Keep the history of invocations with these settings: a resumed study's wall time
    # covers only what it ran (an invocation with other settings starts a new history).
    meta["settings_sha256"] = batch.content_key(labels)
    meta_path = dest / f"study_{args.study}.json"
    history = []
    if meta_path.exists():
        try:
            old = json.loads(meta_path.read_text())
            if old.get("settings_sha256") == meta["settings_sha256"]:
                history = list(old.get("invocations") or [])
        except (ValueError, AttributeError):
            history = []
    meta["invocations"] = history + [
        {
            k: meta[k]
            for k in ("wall_s", "stage_wall_s", "runs_done", "runs_skipped", "workers", "scheduler")
        }
    ]
    write_text_atomic(meta_path, dumps_strict(meta, indent=1))
    if args.study == "template":
        write_text_atomic(
            dest / "report.md", report_markdown(meta, None, None, None, None, template_an)
        )
        print(f"wrote {dest / 'report.md'}", flush=True)
    if args.study in ("paper", "efficiency", "er-sweep"):
        compare = _other_columns(
            out,
            patients,
            mode,
            options.template,
            getattr(args, "critical_er_rule", "paper"),
            args.study,
            er,
            settings=labels,
            margins=margins,
        )
        write_text_atomic(
            dest / "report.md",
            report_markdown(meta, er_an, starts_an, eff_an, closed, compare=compare),
        )
        print(
            f"wrote {dest / 'report.md'}"
            + (
                f" (with {len(compare)} other mode(s)/template(s) of OUT side by side)"
                if compare
                else ""
            ),
            flush=True,
        )
    print(f"study {args.study}: {wall:.0f} s wall, outputs in {dest}", flush=True)
    return 1 if failed else 0


def _labels(results: list[dict], options, study: str, patients=("test:0",)) -> dict:
    """The settings to label tables and the report with: the runs' own (all of one setting,
    :func:`settings_of`), or, with no runs at all, what the command asked for."""
    if results:
        return settings_of(results, f"study {study}", study)
    return _expected_settings(options, patients)


def _build_seconds(path) -> float | None:
    """The build time a template's metadata records (s), None if it has none: read as
    :func:`~drake_rus.template.io.load_template` reads it, from the .json beside the file
    only when that .json describes this file (not one an earlier build left)."""
    try:
        return load_template(path).meta.get("total_seconds")
    except (OSError, ValueError):
        return None
