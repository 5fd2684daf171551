"""Finished study runs: loading them (:func:`load_study_results`), matching them to the tasks
that made them (:func:`results_of`) and the settings they share (:func:`settings_of`).

Every run records its task, its settings key, the inputs digest and a provenance record, so
tables and reports take their labels from the runs (:func:`settings_of`), never from the
command line, and refuse to put runs of different settings in one table
(:class:`MixedSettingsError`). A run's result is a plain dict (its JSON file); its ``task``
the dict :meth:`~drake_rus.experiments.specs.StudyTask.to_dict` wrote, read here as
recorded (an older run may lack a field).
"""

from __future__ import annotations

from drake_rus import batch
from drake_rus.experiments.keys import run_id, task_key, template_tag
from drake_rus.experiments.specs import StudyTask, patient_kind

# What a table's runs must share (per-run fields, e.g. the patient, ER, start, template
# variant, may differ): the task's settings, the template asked for, the patients' kind
# (generated, ct, real: tables group them apart) and the inputs digest. The template study
# lays patients in their own postures and groups the kinds itself: its runs share the
# inputs digest within each posture (the digest covers the resolved scenario, posture
# included); the efficiency study's runs share their reconstruction grid too.
SETTINGS = (
    "mode",
    "segmenter",
    "method",
    "er_unit",
    "voxel",
    "seed",
    "scenario",
    "overrides",
    "posture",
    "template",
    "patient_kind",
    "inputs_sha256",
)
SETTINGS_PER_RUN = {"template": ("posture", "patient_kind")}
SETTINGS_PER_POSTURE = {"template": ("inputs_sha256",)}
SETTINGS_OF_STUDY = {"efficiency": ("recon_spacing",)}


def load_study_results(out_dir, study: str | None = None) -> list[dict]:
    """All finished run results under ``out_dir/runs`` (optionally of one study)."""
    if study is None:
        return batch.load_results(out_dir)
    return batch.load_results(out_dir, lambda r: r["task"]["study"] == study)


def column_of(result: dict) -> tuple[str, str]:
    """(mode, template tag) of a run: the column it belongs to in the side-by-side report
    (``kinematic`` or ``closed-loop``; "" for the generated template,
    :func:`~drake_rus.experiments.keys.template_tag`)."""
    task = result.get("task") or {}
    return task.get("mode", "kinematic"), template_tag(task.get("template"))


def usable_runs(results: list[dict], study: str = "") -> list[dict]:
    """Runs with a localization (a closed-loop scan that stopped before it has none); for
    the efficiency study, closed-loop runs whose scans all finished (DONE: the run's own
    scan and each strategy's; a scan that stopped before or during its sweep has no
    comparable sweep)."""
    return [
        r
        for r in results
        if r.get("e_trans_mm") is not None
        and (
            study != "efficiency"
            or (
                r.get("status", "DONE") == "DONE"
                and all(
                    e.get("status", "DONE") == "DONE" for e in (r.get("strategies") or {}).values()
                )
            )
        )
    ]


def figure_groups(out_dir, study: str) -> list[dict]:
    """The runs of ``study`` in the study folder ``out_dir`` split as the study's own tables
    split them, one figure each (notebooks/reproduce_paper.ipynb): per column (mode and
    template, :func:`column_of`; both modes' and several templates' runs share a folder)
    and, for the starts and efficiency studies, per ER. Each group: ``mode``, ``template``
    (the tag), ``er`` (None for the ER sweep), ``label`` (for people), ``folder`` (where its
    figures go below the figure folder: "" for the kinematic runs on the generated template,
    else as the study writes its tables: ``closed-loop``, ``template-real``..., then ``erNNN``
    where a column holds several ERs), ``runs`` (those :func:`usable_runs` keeps),
    ``left_out`` (how many it does not), ``settings`` (:func:`settings_of`) and
    ``template_info`` (the runs' template record); or, where the runs mix settings,
    ``error`` (the :class:`MixedSettingsError` message) and no runs. The kinematic runs on
    the generated template first."""
    columns = {}
    for r in load_study_results(out_dir, study):
        er = None if study == "er-sweep" else round(float(r["er"]), 3)
        columns.setdefault(column_of(r), {}).setdefault(er, []).append(r)
    groups = []
    for (mode, tag), by_er in sorted(
        columns.items(), key=lambda kv: (kv[0][0] != "kinematic", kv[0][1])
    ):
        column = "closed-loop" if mode == "closed-loop" else ""
        if tag:
            column = "/".join(filter(None, (column, f"template-{tag[len('tpl-') :]}")))
        for er, runs in sorted(by_er.items(), key=lambda kv: kv[0] or 0.0):
            ok = usable_runs(runs, study)
            label = ("closed loop" if mode == "closed-loop" else "kinematic") + (
                f", template {tag[len('tpl-') :]}" if tag else ""
            )
            group = {
                "mode": mode,
                "template": tag,
                "er": er,
                "label": label + ("" if er is None else f", ER {er * 100:.0f}%"),
                "folder": "/".join(
                    filter(None, (column, f"er{round(er * 100):03d}" if len(by_er) > 1 else ""))
                ),
                "runs": ok,
                "left_out": len(runs) - len(ok),
                "template_info": next(
                    (r["template"] for r in ok if isinstance(r.get("template"), dict)), None
                ),
            }
            try:
                group["settings"] = settings_of(ok, f"{study} ({group['label']})", study)
            except MixedSettingsError as e:
                group.update(runs=[], error=str(e))
            groups.append(group)
    return groups


def results_of(results: list[dict], tasks: list[StudyTask]) -> list[dict]:
    """The results made by exactly ``tasks`` (same run id and settings key; OUT may hold
    other runs)."""
    wanted = {run_id(t): task_key(t) for t in tasks}
    return [
        r
        for r in results
        if wanted.get(r.get("run_id")) is not None and r.get("task_key") == wanted[r["run_id"]]
    ]


class MixedSettingsError(ValueError):
    """Runs of different settings were to go into one table."""


def run_settings(result: dict) -> dict:
    """The settings a run was made with, from its own record (its task and the inputs
    digest it recorded; None where an older run recorded none)."""
    task = result.get("task") or {}
    out = {k: task.get(k) for k in SETTINGS if k not in ("inputs_sha256", "patient_kind")}
    out["mode"] = task.get("mode", "kinematic")
    out["patient_kind"] = result.get("patient_kind") or patient_kind(
        result.get("patient", task.get("patient", ""))
    )
    out["inputs_sha256"] = result.get("inputs_sha256")
    return out


def settings_of(results: list[dict], what: str = "these runs", study: str = "") -> dict:
    """The settings the ``results`` share (:func:`run_settings`); raises
    :class:`MixedSettingsError` naming each setting that differs and how many runs have each
    value, so a table never mixes them under one label."""
    skip = SETTINGS_PER_RUN.get(study, ())
    per_posture = SETTINGS_PER_POSTURE.get(study, ())
    values = {}
    for r in results:
        settings = run_settings(r) | {
            k: (r.get("task") or {}).get(k) for k in SETTINGS_OF_STUDY.get(study, ())
        }
        for k, v in settings.items():
            if k in per_posture:
                # One value per posture (the digest covers the posture the run lay in).
                k, v = f"{k} ({settings.get('posture') or 'scenario posture'})", v
            if k not in skip:
                values.setdefault(k, {}).setdefault(repr(v), [v, 0])[1] += 1
    mixed = {k: vs for k, vs in values.items() if len(vs) > 1}
    if mixed:
        raise MixedSettingsError(
            f"{what}: runs of different settings would share one table ("
            + "; ".join(
                f"{k}: " + ", ".join(f"{v[0]!r} ({v[1]} runs)" for v in vs.values())
                for k, vs in mixed.items()
            )
            + "); run each setting into its own --out folder"
        )
    out = {
        k: next(iter(vs.values()))[0]
        for k, vs in values.items()
        if k.partition(" (")[0] not in per_posture
    }
    for k in per_posture:
        # The template study's digest: one per posture ({posture: digest} when several).
        each = {
            name.partition(" (")[2].rstrip(")"): next(iter(vs.values()))[0]
            for name, vs in values.items()
            if name.partition(" (")[0] == k
        }
        out[k] = next(iter(each.values())) if len(each) == 1 else dict(sorted(each.items()))
    return out
