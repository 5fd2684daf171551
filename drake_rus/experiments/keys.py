"""A study run's identity: its file name (:func:`run_id`), its settings key
(:func:`task_key`), the inputs it resolves (:func:`task_scenario`, :func:`inputs_digest`)
and its provenance record (:func:`run_provenance`).

Resume: a run's settings key covers its whole task (:class:`~.specs.StudyTask`: study,
patient, ER, start, segmenter, method, voxel, seed, ER unit, mode, posture, scenario name,
overrides, strategies, template variant, the template asked for...) and the resolved inputs
(:func:`inputs_digest`: the resolved scenario's YAML and the bytes of the registration
template file it names); a stored run is reused only with the same key
(:mod:`drake_rus.batch`). Closed-loop runs have their own run ids (suffix ``__cl``), and so
have runs with another template than the generated one (``__tpl-real``...), so both modes'
and both templates' runs can share an output directory.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import re
import warnings
from pathlib import Path

from pydrake.common.yaml import yaml_dump_typed

from drake_rus import batch
from drake_rus.experiments.specs import POSTURES, StudyTask
from drake_rus.paths import REPO_ROOT
from drake_rus.provenance import Provenance
from drake_rus.scenario import DEFAULT_SCENARIOS_FILE, LoadScenario
from drake_rus.template.ct import TemplateSplitWarning, is_template_spec, resolve_template
from drake_rus.template.io import DEFAULT_TEMPLATE_PATH

# Task fields that do not change a run's numbers: where its NRRD volumes go, and where the
# scenarios file and the template file lie (their resolved contents are keyed instead,
# :func:`inputs_digest`).
UNKEYED_FIELDS = ("export_dir", "scenarios_file", "template_file")
# Fields only some studies read (the reconstruction grid: the efficiency study's volumes).
STUDY_FIELDS = {"recon_spacing": ("efficiency",)}


def run_id(task: StudyTask) -> str:
    """File-name-safe unique name of a run."""
    patient = re.sub(r"[^A-Za-z0-9]+", "-", str(task.patient)).strip("-")
    # "erk": ER in units of the patient's kidney length; "er": of L_m (the runs before
    # ER units existed were all L_m).
    unit = "erk" if task.er_unit == "kidney" else "er"
    parts = [task.study, patient, f"{unit}{int(round(task.er * 100)):03d}"]
    if task.study == "closed-loop":
        parts.append(f"f{int(round(task.start_fraction * 100)):03d}")
    if task.study == "starts":
        parts.append(f"s{task.start}")
    if task.study == "template":
        parts.append("t-" + re.sub(r"[^A-Za-z0-9.+]+", "-", task.template_variant))
    if task.posture == "left_lateral_decubitus":
        parts.append("lld")
    tag = template_tag(task.template)
    if tag:
        parts.append(tag)
    if task.mode == "closed-loop" and task.study != "closed-loop":
        parts.append("cl")
    return "__".join(parts)


def template_tag(spec: str | None) -> str:
    """The run-id part of a run's template (``StudyTask.template``): "" for the scenario's
    or the generated template, ``tpl-real`` for ``real``, else ``tpl-`` with the spec's
    name and a short hash of the whole spec (``real:DIR``, a file), so runs with different
    templates never share a name."""
    if spec is None or str(spec).strip() in ("", "generated"):
        return ""
    text = str(spec).strip()
    if text == "real":
        return "tpl-real"
    name = "real" if text.startswith("real:") else Path(text).stem
    name = re.sub(r"[^A-Za-z0-9]+", "-", name).strip("-")[:24] or "file"
    return f"tpl-{name}-{hashlib.sha256(text.encode()).hexdigest()[:8]}"


# ------------------------------------------------------------------------------- inputs
@functools.lru_cache(maxsize=4)
def study_scenario(name, filename, overrides):
    """The named scenario with its overrides (cached per process)."""
    return LoadScenario(
        filename=filename or DEFAULT_SCENARIOS_FILE, scenario_name=name, scenario_text=overrides
    )


def with_posture(scenario, posture: str | None):
    """``scenario`` with the patient laid in ``posture`` (None: unchanged)."""
    if posture is None or posture == scenario.patient.posture:
        return scenario
    if posture not in POSTURES:
        raise ValueError(f"posture: expected one of {', '.join(POSTURES)}, got {posture!r}")
    return dataclasses.replace(
        scenario, patient=dataclasses.replace(scenario.patient, posture=posture)
    )


def with_template(scenario, template_file: str | None):
    """``scenario`` with ``localization.template`` set to ``template_file`` (None:
    unchanged)."""
    if template_file is None or template_file == scenario.localization.template:
        return scenario
    return dataclasses.replace(
        scenario,
        localization=dataclasses.replace(scenario.localization, template=str(template_file)),
    )


def task_scenario(task: StudyTask):
    """The scenario a study run starts from: its named scenario, overrides, posture and
    template (``StudyTask.template_file``, resolved by the study command)."""
    return with_template(
        with_posture(
            study_scenario(task.scenario, task.scenarios_file, task.overrides), task.posture
        ),
        task.template_file,
    )


def template_file(path) -> Path:
    """The registration template file a scenario's ``localization.template`` names (the
    symbolic ``generated``, ``real``, ``real:DIR`` resolved by
    :func:`drake_rus.template.ct.resolve_template`: ``real`` built on first use)."""
    if path is None:
        return Path(DEFAULT_TEMPLATE_PATH)
    if is_template_spec(path):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", TemplateSplitWarning)
            return Path(resolve_template(path))
    return Path(path) if str(path).startswith("/") else REPO_ROOT / path


def _file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    except OSError as e:
        return f"unreadable {path}: {e.strerror or e}"
    return h.hexdigest()


@functools.lru_cache(maxsize=32)
def inputs_digest(
    scenario: str,
    scenarios_file: str | None,
    overrides: str | None,
    posture: str | None,
    template: str | None = None,
) -> str:
    """SHA-256 (hex) of what a study run reads besides its task: the resolved scenario (its
    YAML, with the overrides and the task's posture; its template path stated as the
    scenario's, so where a template file lies does not change the digest) and the bytes
    of the registration template file it reads (``template``, the task's resolved file,
    else the one the scenario names). Two runs with equal tasks and digests are the same
    run."""
    sc = with_posture(study_scenario(scenario, scenarios_file, overrides), posture)
    h = hashlib.sha256(yaml_dump_typed(sc).encode())
    h.update(_file_sha256(template_file(template or sc.localization.template)).encode())
    return h.hexdigest()


def task_inputs_digest(task: StudyTask) -> str:
    return inputs_digest(
        task.scenario, task.scenarios_file, task.overrides, task.posture, task.template_file
    )


# ------------------------------------------------------------------------------- the key
def task_key(task: StudyTask) -> str:
    """The settings key of a study run: SHA-256 of its task (:meth:`StudyTask.to_dict`,
    without :data:`UNKEYED_FIELDS`, and without the :data:`STUDY_FIELDS` its study does not
    read) and :func:`inputs_digest`. A stored run is reused only with the same key."""
    keyed = {
        k: v
        for k, v in task.to_dict().items()
        if k not in UNKEYED_FIELDS and task.study in STUDY_FIELDS.get(k, (task.study,))
    }
    keyed["inputs_sha256"] = task_inputs_digest(task)
    return batch.content_key(keyed)


def run_provenance(task: StudyTask, scenario=None) -> dict:
    """The :func:`~drake_rus.provenance.Provenance` record of a study run (resolved scenario
    with the task's posture, its name, file and overrides, every seed the run draws from)."""
    if scenario is None:
        scenario = task_scenario(task)
    seeds = {"study_seed": int(task.seed), "patient": str(task.patient)}
    if int(task.start) >= 0:
        seeds["start"] = int(task.start)
    return Provenance(
        scenario,
        scenario_name=task.scenario,
        scenarios_file=task.scenarios_file or str(DEFAULT_SCENARIOS_FILE),
        overrides=task.overrides,
        seeds=seeds,
    )
