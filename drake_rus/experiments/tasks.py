"""One study run, dispatched to its mode: :func:`run_task` is what the batch runner
(:func:`drake_rus.batch.run_tasks`, with :func:`~drake_rus.experiments.keys.run_id` and
:func:`~drake_rus.experiments.keys.task_key`) executes for each
:class:`~drake_rus.experiments.specs.StudyTask`, on a Dask worker or in this process."""

from __future__ import annotations

from drake_rus.experiments.closed_loop_runs import run_closed_loop, run_closed_loop_study
from drake_rus.experiments.keys import run_provenance, task_inputs_digest, task_scenario
from drake_rus.experiments.kinematic_runs import run_kinematic_task
from drake_rus.experiments.specs import StudyTask, check_mode, patient_kind
from drake_rus.experiments.templates import template_info


def run_task(task: StudyTask) -> dict:
    """Executes one run (kinematic, or closed loop with ``mode`` "closed-loop"; the paper
    study's closed-loop check both) and returns its JSON-ready result, with the inputs it
    resolved (``inputs_sha256``, :func:`~drake_rus.experiments.keys.inputs_digest`), the
    registration template it used (``template``:
    :func:`~drake_rus.experiments.templates.template_info`), the patient's kind
    (``patient_kind``: generated, ct, real) and its ``provenance``
    (:func:`~drake_rus.experiments.keys.run_provenance`)."""
    if task.study == "closed-loop":
        result = run_closed_loop(task)
    elif check_mode(task.mode) == "closed-loop":
        result = run_closed_loop_study(task)
    else:
        result = run_kinematic_task(task)
    result["inputs_sha256"] = task_inputs_digest(task)
    result["template"] = template_info(task.template, task_scenario(task).localization.template)
    result["patient_kind"] = patient_kind(task.patient)
    result["provenance"] = run_provenance(task)
    return result
