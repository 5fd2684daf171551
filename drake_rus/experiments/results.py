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
from drake_rus.experiments.keys import run_id, task_key
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
