"""The runs of the seed's section III studies on the virtual cohort, in kinematic mode.

Studies (each a list of independent runs; a run is a plain dict, its result a JSON file):

- ``er-sweep`` (III-C, Fig. 7d): exploration ratios 0..100% in 10% steps per patient.
- ``starts`` (III-D, Fig. 9d): at the critical ER, five random starts per patient inside the
  E-ROI (start fraction along y leaving room for the whole ER travel, and an x
  offset within the middle half of the E-ROI's width), drawn again until the kidney is
  visible at the start (the paper's II-A assumption (i); :func:`start_visibility`), in
  both modes.

ER 0 is the initial alignment alone (III-C) in both modes. A closed-loop run whose planned
exploration is shorter than the product's ``min_exploration_travel`` registers it without
the product's minimum and acceptance checks, as the paper and the twin do
(:func:`study_localization`, the study's scenario only).
- ``efficiency`` (III-E, Fig. 10): OP (at T* of the registered pose), GT-OP, NOP and SL per
  patient, and beyond the paper OP-PE (OP's pose with the predicted_end pivot, the
  supervisor's prediction); closed loop, each strategy is its own scan
  (:func:`closed_loop_strategy_run`: GT-OP and NOP pivot at a pose the study computes from
  the true kidney pose and gives the scan as ``controller.pivot_pose``, SL is the scan's
  ``controller.sweep: line``): V against n and eps pole to pole (the paper's), the whole pivot's
  n, eps and V
  beside them, n and eps needed to reach V = 0.9, the pivot legs the tilt cap ended
  (:mod:`drake_rus.metrics.sweep`, the same functions the closed-loop scan uses), and the
  kidney volume reconstructed from each sweep's masks
  (:mod:`drake_rus.metrics.reconstruction`).
- ``closed-loop``: a few closed-loop dynamic scans (``RunScan``) beside their kinematic
  twins.
- ``template`` (beyond the paper, issue 18): localization at one ER with template variants
  that differ from the patient by known amounts (:func:`template_variant`): the mean
  template, the mean scaled by 0.9 / 1.1, a single training kidney (``single:K``), and for
  training patients the leave-one-out mean (``loo``, the mean of the other 19 corresponded
  training shapes), and a template built from another population (``population:NAME``,
  :mod:`drake_rus.template.population`: generated kidneys with other size statistics, e.g.
  ``long``/``short`` = Glodny's length +-1 SD, built once and cached); each run records
  the template's distance from the patient's kidney (:func:`template_distance`), so E_trans
  and E_rot,x can be read against it. A patient may be a real body (a patient path, e.g.
  the Visible Human female's meshes); ``StudyOptions.posture`` lays every patient supine or
  in left lateral decubitus.

ER (``StudyOptions.er_unit``): ``kidney`` (default, the paper's simulation, III-C: "the
fraction of total kidney length traversed by the probe") explores ER x the patient's kidney
length along the exploration line (the E-ROI's length along base y, :func:`kidney_length`);
``fixed`` explores ER x L_m (``controller.kidney_length``, 100 mm: the paper's in-vivo rule,
III-F).

Mode (``StudyOptions.mode``): ``kinematic`` (default, the fast twin,
:mod:`drake_rus.experiments.kinematic`: probe poses planned exactly, no robot dynamics) or
``closed-loop`` (:func:`run_closed_loop_study`: every run is a full closed-loop scan on the
Drake diagram, ``RunScan``, with the same run record). Closed-loop runs have their own run
ids (suffix ``__cl``), so both modes' runs can share an output directory. Kinematic runs are
deterministic given their dict (seeded starts).

Resume and labels: a run's settings key (:func:`task_key`) covers its whole task (study,
patient, ER, start, segmenter, method, voxel, seed, ER unit, mode, posture, scenario name,
overrides, strategies, template variant...) and the resolved inputs (:func:`inputs_digest`:
the resolved scenario's YAML and the bytes of the registration template file it names); a
stored run is reused only with the same key (:mod:`drake_rus.batch`). Every run records its
task, that key, the digest and a :func:`~drake_rus.provenance.Provenance` (resolved scenario
YAML, overrides, seeds, package versions, commit), so tables and reports take their labels
from the runs (:func:`settings_of`), never from the command line, and refuse to put runs of
different settings in one table (:class:`MixedSettingsError`).
:func:`run_task` executes one run; the batch runner (:func:`drake_rus.batch.run_tasks`
with :func:`run_task` and :func:`run_id`) executes a list of them through Dask, writing
each result as it finishes, so an interrupted study resumes. The statistics are in
:mod:`drake_rus.experiments.analysis`, tables, figures and report in
:mod:`drake_rus.experiments.report`.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import math
import re
import time
import zlib
from pathlib import Path

import numpy as np
from pydrake.common.yaml import yaml_dump_typed
from scipy.spatial import cKDTree

from drake_rus import batch
from drake_rus.anatomy import load_patient
from drake_rus.control.supervisor import Phase, pivot_pose_as_given
from drake_rus.experiments import kinematic as km
from drake_rus.experiments.analysis import PAPER_STRATEGIES, STRATEGY_ORDER
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.localization.localize import RegistrationTemplate, load_registration_template
from drake_rus.metrics.core import CoverageAccumulator, e_rot_x, e_trans
from drake_rus.metrics.reconstruction import compound, reconstruct_kidney, write_nrrd
from drake_rus.metrics.sweep import sweep_efficiency
from drake_rus.paths import REPO_ROOT
from drake_rus.provenance import Provenance
from drake_rus.scan import RunScan, ScanMetrics
from drake_rus.scenario import DEFAULT_SCENARIOS_FILE, CheckScenario, LoadScenario
from drake_rus.template.io import DEFAULT_TEMPLATE_PATH
from drake_rus.template.population import DEFAULT_SUBJECTS as POPULATION_SUBJECTS
from drake_rus.template.population import POPULATIONS, parse_population, population_template

ER_GRID = tuple(round(0.1 * k, 1) for k in range(11))
# What ER multiplies: the patient's kidney length (the paper's simulation) or L_m.
ER_UNITS = ("kidney", "fixed")
ER_UNIT_TEXT = {
    "kidney": "fraction of the patient's kidney length along the exploration line "
    "(the paper's simulation, III-C)",
    "fixed": "fraction of the fixed length L_m = 100 mm (the paper's in-vivo rule, III-F)",
}
# Coverage at which the sweep costs are also compared (matched coverage).
V_TARGETS = (0.9,)
# How a study run is executed: the kinematic twin (default, fast) or a closed-loop scan.
MODES = ("kinematic", "closed-loop")
# What each efficiency strategy sweeps (III-E), the same in both modes.
STRATEGY_TEXT = {
    "OP": "two-leg pivot at T* of the registered kidney pose (eq. 20-22)",
    "GT-OP": "two-leg pivot at T* of the true kidney pose",
    "NOP": "two-leg pivot with the array along the true kidney's y-axis projected on the "
    "horizontal, tip over the true centroid (the in-vivo NOP was expert-placed)",
    "SL": f"straight line (the exploration controller, eq. 17) from "
    f"{km.SL_MARGIN * 1e3:g} mm beyond the E-ROI's end until the kidney has left the "
    "image (ER 100%)",
    "OP-PE": "predicted-end pivot (beyond the paper) at T* of the registered kidney pose",
}
# The kidney pose each strategy's pivot pose comes from ("registered" or "true"; SL: None),
# in both modes.
POSE_FROM = {"OP": "registered", "OP-PE": "registered", "GT-OP": "true", "NOP": "true", "SL": None}
# How a closed-loop scan runs each strategy (:func:`closed_loop_strategy_run`): the scan
# never reads the truth; GT-OP's and NOP's poses reach it as a scenario value the study
# computes from the true pose, as an operator's placement would.
CLOSED_LOOP_STRATEGY_HOW = {
    "OP": "the scan's own exploration, registration and T* (controller.pivot_pose [])",
    "GT-OP": "the study gives T* of the true pose as controller.pivot_pose (the scan skips "
    "exploration and localization)",
    "NOP": "the study gives the NOP pose of the true pose as controller.pivot_pose (the "
    "scan skips exploration and localization)",
    "SL": "controller.sweep: line, landing at controller.start_xy "
    f"{km.SL_MARGIN * 1e3:g} mm beyond the E-ROI's end",
    "OP-PE": "the scan's own registration and T*, controller.pivot_strategy: predicted_end",
}
# Every efficiency strategy has a closed-loop scan; a closed-loop efficiency study runs the
# paper's four unless asked (OP-PE: --strategies OP,GT-OP,NOP,SL,OP-PE).
CLOSED_LOOP_STRATEGIES = STRATEGY_ORDER
CLOSED_LOOP_DEFAULT_STRATEGIES = PAPER_STRATEGIES
# GT-OP and NOP: the start planner puts the probe over this fraction of the kidney's length
# (the middle; an operator placing the probe), then TRANSIT slides it to the given pose.
GIVEN_POSE_START_FRACTION = 0.5
# Random starts are drawn where the kidney is visible (the paper's II-A (i)), checked at the
# start and this far (m) around it (the closed loop lands within 2 mm), at most this often.
START_VISIBILITY_TOLERANCE = 0.002
START_MAX_DRAWS = 200
# A study run below the product's exploration minimum registers unchecked: these limits
# (m) stand for "no limit" (study_localization).
RELAXED_LIMIT = 1.0


def kidney_length(kp) -> float:
    """The patient's kidney length (m) along the exploration line (base y): the E-ROI's
    length, i.e. the travel that takes the transverse view from one pole to the other."""
    return float(kp.roi.length_y)


def exploration_travel(er: float, unit: str, patient_length: float, L_m: float) -> float:
    """Travel (m) of an exploration at ratio ``er``: er x the patient's kidney length
    (``unit`` "kidney") or er x L_m ("fixed")."""
    if unit == "kidney":
        return float(er) * float(patient_length)
    if unit == "fixed":
        return float(er) * float(L_m)
    raise ValueError(f"er_unit: expected one of {', '.join(ER_UNITS)}, got {unit!r}")


# ------------------------------------------------------------------------------- patients
POSTURE_SUFFIXES = {
    "supine": "supine",
    "decubitus": "left_lateral_decubitus",
    "left_lateral_decubitus": "left_lateral_decubitus",
}


def split_posture(spec: str) -> tuple[str, str | None]:
    """(patient spec, posture or None) of a spec with an optional ``@supine`` /
    ``@decubitus`` suffix (the template study lays that patient in that posture)."""
    head, sep, tail = str(spec).rpartition("@")
    if not sep:
        return str(spec), None
    if tail not in POSTURE_SUFFIXES:
        raise ValueError(
            f"patient {spec!r}: unknown posture suffix @{tail} (expected @supine or @decubitus)"
        )
    return head, POSTURE_SUFFIXES[tail]


def expand_patients(text: str) -> list[str]:
    """Patient specs from a comma list of ``test:0-14``, ``seed:100-120``, ``train:3`` or
    patient paths, each optionally with ``@supine`` / ``@decubitus`` (the template study's
    per-patient posture). Ranges are inclusive."""
    specs = []
    for part in str(text).split(","):
        part = part.strip()
        if not part:
            continue
        if "@" in part:
            spec, posture = split_posture(part)
            suffix = part[len(spec) :]
            specs += [s + suffix for s in expand_patients(spec)]
            continue
        m = re.fullmatch(r"(test|train|seed):(\d+)-(\d+)", part)
        if m:
            lo, hi = int(m.group(2)), int(m.group(3))
            if hi < lo:
                raise ValueError(f"--patients: range {part!r} runs backwards")
            specs += [f"{m.group(1)}:{k}" for k in range(lo, hi + 1)]
        elif re.fullmatch(r"(test|train|seed):\d+", part) or "/" in part or "." in part:
            specs.append(part)
        else:
            raise ValueError(
                f"--patients: cannot read {part!r} (expected test:0-14, "
                "seed:100-120, train:3 or a patient path)"
            )
    if not specs:
        raise ValueError("--patients: no patients given")
    return specs


# ------------------------------------------------------------------------------- run specs
@dataclasses.dataclass(frozen=True)
class StudyOptions:
    """What every run of a study shares."""

    scenario: str = "default"
    scenarios_file: str | None = None
    overrides: str | None = None
    segmenter: str = "oracle"
    method: str = "seed"  # localization method of the runs (the seed's by default)
    voxel: float = 0.002  # label-volume voxel size (m)
    seed: int = 0  # random starts, emulator speckle
    recon_spacing: float = 0.001  # reconstruction grid (m)
    er_unit: str = "kidney"  # ER x the patient's kidney length, or "fixed" (x L_m)
    mode: str = "kinematic"  # "kinematic" (the twin) or "closed-loop" (RunScan)
    posture: str | None = None  # the patients' posture; None: the scenario's

    def base(self) -> dict:
        return dataclasses.asdict(self)


TEMPLATE_VARIANTS = (
    "mean",
    "scale-0.9",
    "scale-1.1",
    "single:0",
    "loo",
    "population:base",
    "population:short",
    "population:long",
)
VARIANT_SYNTAX = (
    "mean, scale-S (0 < S <= 3), single:K, loo, population:NAME or "
    "population:NAME:N (N subjects, default 20; NAME one of "
    + ", ".join(POPULATIONS)
    + " or length+Xsd / length-Xsd)"
)
POSTURES = ("supine", "left_lateral_decubitus")


def template_tasks(
    patients, options: StudyOptions, er: float, variants=TEMPLATE_VARIANTS
) -> list[dict]:
    """One run per patient and template variant; ``loo`` only for training patients
    (``train:K``: the template without K); others are not in the template anyway. A patient
    ``SPEC@decubitus`` (``@supine``) is laid in that posture, the others in
    ``options.posture`` (None: the scenario's)."""
    variants = list(variants)
    if not variants:
        raise ValueError(
            f"template variant: none given (expected a comma list of {VARIANT_SYNTAX})"
        )
    for v in variants:
        _check_variant(v)
    if options.posture is not None and options.posture not in POSTURES:
        raise ValueError(f"posture: expected one of {', '.join(POSTURES)}, got {options.posture!r}")
    tasks = []
    for p in patients:
        spec, posture = split_posture(p)
        for v in variants:
            if v == "loo" and not re.fullmatch(r"train:\d+", spec):
                continue
            tasks.append(
                dict(
                    options.base(),
                    study="template",
                    patient=spec,
                    er=float(er),
                    start=-1,
                    template_variant=v,
                    posture=posture or options.posture,
                )
            )
    return tasks


def population_of_variant(v: str) -> tuple[str, int] | None:
    """(population name, subjects) of a ``population:NAME[:N]`` variant, else None."""
    m = re.fullmatch(r"population:([^:]+)(?::(\d+))?", str(v))
    if m is None:
        return None
    return m.group(1), int(m.group(2)) if m.group(2) else POPULATION_SUBJECTS


def _check_variant(v: str) -> None:
    """Raises ValueError naming the template variant and what was expected."""
    v = str(v)
    m = re.fullmatch(r"scale-(\d+(\.\d+)?)", v)
    if m and not 0 < float(m.group(1)) <= 3:
        raise ValueError(f"template variant {v!r}: the scale S must lie in (0, 3]")
    if v.startswith("population:"):
        pop = population_of_variant(v)
        if pop is None:
            raise ValueError(
                f"template variant {v!r}: expected population:NAME or population:NAME:N"
            )
        try:
            parse_population(pop[0])
        except ValueError as e:
            raise ValueError(f"template variant {v!r}: {e}") from None
        if not 1 <= pop[1] <= 200:
            raise ValueError(f"template variant {v!r}: subjects N must lie in 1..200, got {pop[1]}")
        return
    if not (v in ("mean", "loo") or m or re.fullmatch(r"single:\d+", v)):
        raise ValueError(f"template variant: expected {VARIANT_SYNTAX}, got {v!r}")


def run_id(task: dict) -> str:
    """File-name-safe unique name of a run."""
    patient = re.sub(r"[^A-Za-z0-9]+", "-", str(task["patient"])).strip("-")
    # "erk": ER in units of the patient's kidney length; "er": of L_m (the runs before
    # ER units existed were all L_m).
    unit = "erk" if task.get("er_unit", "fixed") == "kidney" else "er"
    parts = [task["study"], patient, f"{unit}{int(round(task['er'] * 100)):03d}"]
    if task["study"] == "closed-loop":
        parts.append(f"f{int(round(task['start_fraction'] * 100)):03d}")
    if task["study"] == "starts":
        parts.append(f"s{task['start']}")
    if task["study"] == "template":
        parts.append("t-" + re.sub(r"[^A-Za-z0-9.+]+", "-", task["template_variant"]))
    if task.get("posture") == "left_lateral_decubitus":
        parts.append("lld")
    if task.get("mode", "kinematic") == "closed-loop" and task["study"] != "closed-loop":
        parts.append("cl")
    return "__".join(parts)


# Task fields that do not change a run's numbers: where its NRRD volumes go, and where the
# scenarios file lies (its resolved contents are keyed instead, :func:`inputs_digest`).
UNKEYED_FIELDS = ("export_dir", "scenarios_file")
# Fields only some studies read (the reconstruction grid: the efficiency study's volumes).
STUDY_FIELDS = {"recon_spacing": ("efficiency",)}


def _template_file(path) -> Path:
    """The registration template file a scenario's ``localization.template`` names."""
    if path is None:
        return Path(DEFAULT_TEMPLATE_PATH)
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
    scenario: str, scenarios_file: str | None, overrides: str | None, posture: str | None
) -> str:
    """SHA-256 (hex) of what a study run reads besides its task: the resolved scenario (its
    YAML, with the overrides and the task's posture) and the registration template file it
    names. Two runs with equal tasks and digests are the same run."""
    sc = _with_posture(_scenario(scenario, scenarios_file, overrides), {"posture": posture})
    h = hashlib.sha256(yaml_dump_typed(sc).encode())
    h.update(_file_sha256(_template_file(sc.localization.template)).encode())
    return h.hexdigest()


def task_inputs_digest(task: dict) -> str:
    return inputs_digest(
        task["scenario"], task.get("scenarios_file"), task.get("overrides"), task.get("posture")
    )


def task_key(task: dict) -> str:
    """The settings key of a study run: SHA-256 of its task (without
    :data:`UNKEYED_FIELDS`, and without the :data:`STUDY_FIELDS` its study does not read)
    and :func:`inputs_digest`. A stored run is reused only with the same key."""
    keyed = {
        k: v
        for k, v in task.items()
        if k not in UNKEYED_FIELDS
        and task.get("study") in STUDY_FIELDS.get(k, (task.get("study"),))
    }
    keyed["inputs_sha256"] = task_inputs_digest(task)
    return batch.content_key(keyed)


def run_provenance(task: dict, scenario=None) -> dict:
    """The :func:`~drake_rus.provenance.Provenance` record of a study run (resolved scenario
    with the task's posture, its name, file and overrides, every seed the run draws from)."""
    if scenario is None:
        scenario = _with_posture(
            _scenario(task["scenario"], task.get("scenarios_file"), task.get("overrides")), task
        )
    seeds = {"study_seed": int(task.get("seed", 0)), "patient": str(task["patient"])}
    if int(task.get("start", -1)) >= 0:
        seeds["start"] = int(task["start"])
    return Provenance(
        scenario,
        scenario_name=task["scenario"],
        scenarios_file=task.get("scenarios_file") or str(DEFAULT_SCENARIOS_FILE),
        overrides=task.get("overrides"),
        seeds=seeds,
    )


# What a table's runs must share (per-run fields, e.g. the patient, ER, start, template
# variant, may differ); the template study lays patients in their own postures; the
# efficiency study's runs share their reconstruction grid too.
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
    "inputs_sha256",
)
SETTINGS_PER_RUN = {"template": ("posture",)}
SETTINGS_OF_STUDY = {"efficiency": ("recon_spacing",)}


class MixedSettingsError(ValueError):
    """Runs of different settings were to go into one table."""


def run_settings(result: dict) -> dict:
    """The settings a run was made with, from its own record (its task and the inputs
    digest it recorded; None where an older run recorded none)."""
    task = result.get("task") or {}
    out = {k: task.get(k) for k in SETTINGS if k != "inputs_sha256"}
    out["mode"] = task.get("mode", "kinematic")
    out["inputs_sha256"] = result.get("inputs_sha256")
    return out


def settings_of(results: list[dict], what: str = "these runs", study: str = "") -> dict:
    """The settings the ``results`` share (:func:`run_settings`); raises
    :class:`MixedSettingsError` naming each setting that differs and how many runs have each
    value, so a table never mixes them under one label."""
    skip = SETTINGS_PER_RUN.get(study, ())
    values = {}
    for r in results:
        settings = run_settings(r) | {
            k: (r.get("task") or {}).get(k) for k in SETTINGS_OF_STUDY.get(study, ())
        }
        for k, v in settings.items():
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
    return {k: next(iter(vs.values()))[0] for k, vs in values.items()}


def check_mode(mode: str) -> str:
    if mode not in MODES:
        raise ValueError(f"--mode: expected one of {', '.join(MODES)}, got {mode!r}")
    return mode


def check_strategies(strategies, mode: str = "kinematic") -> tuple:
    """The efficiency strategies, in the report's order; raises ValueError (naming
    ``--strategies``) for an unknown one (or ``--mode`` for an unknown mode)."""
    strategies = [str(s).strip() for s in strategies if str(s).strip()]
    allowed = CLOSED_LOOP_STRATEGIES if check_mode(mode) == "closed-loop" else STRATEGY_ORDER
    bad = [s for s in strategies if s not in allowed]
    if bad or not strategies:
        raise ValueError(
            f"--strategies: expected a comma list of {', '.join(allowed)}, "
            f"got {','.join(strategies) or 'nothing'}"
            + (f" ({', '.join(bad)} unknown)" if bad else "")
        )
    return tuple(s for s in STRATEGY_ORDER if s in strategies)


def default_strategies(mode: str) -> tuple:
    return CLOSED_LOOP_DEFAULT_STRATEGIES if mode == "closed-loop" else STRATEGY_ORDER


def er_sweep_tasks(patients, options: StudyOptions, ers=ER_GRID) -> list[dict]:
    return [
        dict(options.base(), study="er-sweep", patient=p, er=float(er), start=-1)
        for p in patients
        for er in ers
    ]


def starts_tasks(patients, options: StudyOptions, er: float, n_starts: int = 5) -> list[dict]:
    return [
        dict(options.base(), study="starts", patient=p, er=float(er), start=k)
        for p in patients
        for k in range(n_starts)
    ]


def efficiency_tasks(
    patients, options: StudyOptions, er: float, export_dir: str | None = None, strategies=None
) -> list[dict]:
    """``export_dir``: write the OP and GT-OP reconstructions there as NRRD. ``strategies``:
    default all (kinematic) or the paper's four (closed loop, one scan each)."""
    strategies = check_strategies(strategies or default_strategies(options.mode), options.mode)
    return [
        dict(
            options.base(),
            study="efficiency",
            patient=p,
            er=float(er),
            start=-1,
            export_dir=None if export_dir is None else str(export_dir),
            strategies=list(strategies),
        )
        for p in patients
    ]


def closed_loop_tasks(
    patients, options: StudyOptions, er: float, start_fraction: float = 0.1
) -> list[dict]:
    """A few closed-loop dynamic scans (``RunScan``) with their kinematic twins."""
    return [
        dict(
            options.base(),
            study="closed-loop",
            patient=p,
            er=float(er),
            start=-1,
            start_fraction=float(start_fraction),
        )
        for p in patients
    ]


# ------------------------------------------------------------------------------- one run
@functools.lru_cache(maxsize=4)
def _scenario(name, filename, overrides):
    return LoadScenario(
        filename=filename or DEFAULT_SCENARIOS_FILE, scenario_name=name, scenario_text=overrides
    )


def _with_posture(scenario, task: dict):
    """``scenario`` with the task's patient posture (``posture`` None: unchanged)."""
    posture = task.get("posture")
    if posture is None or posture == scenario.patient.posture:
        return scenario
    if posture not in POSTURES:
        raise ValueError(f"posture: expected one of {', '.join(POSTURES)}, got {posture!r}")
    return dataclasses.replace(
        scenario, patient=dataclasses.replace(scenario.patient, posture=posture)
    )


@functools.lru_cache(maxsize=2)
def _template(path):
    return load_registration_template(path)


def _normals_like(points: np.ndarray, reference_normals: np.ndarray, k: int = 12):
    """Unit normals of a point set by local PCA (``k`` neighbours), each oriented like the
    corresponding (same index) reference normal."""
    _, nb = cKDTree(points).query(points, k=k)
    q = points[nb] - points[nb].mean(axis=1, keepdims=True)
    _, _, vt = np.linalg.svd(q, full_matrices=False)
    n = vt[:, -1, :]
    n *= (
        np.sign(np.sum(n * reference_normals, axis=1))[:, None]
        + (np.sum(n * reference_normals, axis=1) == 0)[:, None]
    )
    return n / np.linalg.norm(n, axis=1, keepdims=True)


@functools.lru_cache(maxsize=8)
def template_variant(path, variant: str, patient: str = "", side: str = "right"):
    """The registration template of ``variant`` (see the module doc), from the template file
    at ``path`` (its corresponded training shapes ``aligned``, subjects train:0..N-1), or for
    ``population:NAME[:N]`` the template of that population's ``side`` kidneys (built on
    first use and cached, :func:`drake_rus.template.population.population_template`).
    ``mean`` and ``population:*`` carry their own shape modes (used by the ``deformable``
    method only), the others none (rigid registration)."""
    _check_variant(variant)
    pop = population_of_variant(variant)
    if pop is not None:
        return _template(str(population_template(pop[0], n=pop[1], side=side)))
    base = _template(path)
    if variant == "mean":
        return base
    if variant.startswith("scale-"):
        f = float(variant.split("-", 1)[1])
        return RegistrationTemplate(base.points * f, base.normals)
    file = (
        DEFAULT_TEMPLATE_PATH
        if path is None
        else (path if str(path).startswith("/") else REPO_ROOT / path)
    )
    with np.load(file) as z:
        aligned = np.asarray(z["aligned"], float)
    if variant.startswith("single:"):
        k = int(variant.split(":")[1])
        if not 0 <= k < len(aligned):
            raise ValueError(
                f"template variant {variant}: the template has {len(aligned)} training shapes"
            )
        pts = aligned[k]
    else:  # loo
        m = re.fullmatch(r"train:(\d+)", str(patient))
        if m is None:
            raise ValueError(
                f"template variant loo: only for training patients (train:K), got {patient!r}"
            )
        k = int(m.group(1))
        pts = np.delete(aligned, k, axis=0).mean(axis=0) if k < len(aligned) else aligned.mean(0)
    pts = pts - pts.mean(axis=0)
    return RegistrationTemplate(pts, _normals_like(pts, base.normals))


def template_distance(template, kp) -> float:
    """Symmetric mean nearest-neighbour distance (m) between the template's points and the
    patient's true kidney surface, both in their canonical frames K."""
    v = np.asarray(kp.patient.kidney_mesh.vertices, float)
    X_KB = kp.X_BK_true.inverse()
    p_K = X_KB.multiply(kp.X_BPt.multiply(v.T)).T
    a = cKDTree(p_K).query(template.points)[0].mean()
    b = cKDTree(template.points).query(p_K)[0].mean()
    return float(0.5 * (a + b))


def patient_kind(spec: str) -> str:
    """ "generated" (seed:N, train:K, test:K) or "real" (a patient file or folder)."""
    return "generated" if re.fullmatch(r"(test|train|seed):\d+", str(spec)) else "real"


def template_record(variant: str, template, kp, posture: str, spec: str) -> dict:
    """The template study's fields of a run: the variant, the template's distance from the
    patient's kidney, the template's canonical extents and the kidney's (mm), the patient's
    kind and posture."""
    v = np.asarray(kp.patient.kidney_mesh.vertices, float)
    p_K = kp.X_BK_true.inverse().multiply(kp.X_BPt.multiply(v.T)).T
    return {
        "template_variant": variant,
        "template_distance_mm": template_distance(template, kp) * 1e3,
        "template_extent_mm": [round(float(x), 2) for x in np.ptp(template.points, 0) * 1e3],
        "kidney_extent_mm": [round(float(x), 2) for x in np.ptp(p_K, 0) * 1e3],
        "patient_kind": patient_kind(spec),
        "posture": posture,
    }


_PATIENTS: dict = {}


def prepared_patient(spec: str, side: str, posture: str, voxel: float, X_BPt):
    """Kinematic patient, cached per process (label volumes take seconds to build)."""
    key = (spec, side, posture, voxel, tuple(X_BPt.GetAsMatrix4().ravel()))
    if key not in _PATIENTS:
        if len(_PATIENTS) >= 16:
            _PATIENTS.pop(next(iter(_PATIENTS)))
        patient = load_patient(spec, side=side, posture=posture, voxel_size=voxel, progress=False)
        _PATIENTS[key] = km.prepare_patient(patient, X_BPt)
    return _PATIENTS[key]


def random_start(
    task: dict, kp, controller, visible=None, max_draws: int = START_MAX_DRAWS
) -> tuple[float, float]:
    """(start_fraction, x_offset) of random start ``task['start']`` (deterministic in the
    study seed, the patient and the start index): the start fraction along the E-ROI leaves
    room for the whole ER travel, the x offset lies within the middle half of its width.
    With ``visible`` (a callable (x, y) -> bool, e.g. :func:`start_visibility`) draws are
    repeated, from the same random stream, until the kidney is visible at the start (the
    paper's assumption II-A (i)); :func:`visible_random_start` also says how many were
    rejected."""
    return visible_random_start(task, kp, controller, visible, max_draws)[:2]


def visible_random_start(
    task: dict, kp, controller, visible=None, max_draws: int = START_MAX_DRAWS
) -> tuple[float, float, int]:
    """:func:`random_start` and the number of draws rejected because ``visible`` said the
    kidney is not in the image there. Raises ValueError when no draw of ``max_draws`` is
    visible (the E-ROI shows no kidney where the exploration could start)."""
    rng = np.random.default_rng(
        [int(task["seed"]), zlib.crc32(str(task["patient"]).encode()), int(task["start"])]
    )
    travel = exploration_travel(
        task["er"], task.get("er_unit", "fixed"), kidney_length(kp), controller.kidney_length
    )
    room = max(0.0, 1.0 - travel / max(kp.roi.length_y, 1e-9))
    width = kp.roi.x_max - kp.roi.x_min
    for draw in range(max(1, int(max_draws))):
        sf, xo = float(rng.uniform(0.0, room)), float(rng.uniform(-0.25, 0.25) * width)
        if visible is None or visible(km.start_xy(kp, sf, controller.scan_direction, xo)):
            return sf, xo, draw
    raise ValueError(
        f"random start {task['start']} of {task['patient']}: the kidney is not "
        f"visible at any of {max_draws} drawn starts"
    )


def start_visibility(kp, imager, tolerance: float = START_VISIBILITY_TOLERANCE):
    """A callable (x, y) -> bool: the kidney is visible (the segmenter's read-out, area >=
    ``imaging.min_kidney_area``) in the transverse frame with the tip on the skin at (x, y)
    and at (x +- ``tolerance``, y) and (x, y +- ``tolerance``): the paper's assumption II-A
    (i), "the robot starts where the kidney is visible", kept by the closed-loop scan, which
    lands within ``transit_position_tolerance`` (2 mm) of its start. The imager's frame
    counter and temporal prior are restored, so the exploration after it is unchanged."""
    d = float(tolerance)
    offsets = ((0.0, 0.0), (d, 0.0), (-d, 0.0), (0.0, d), (0.0, -d))

    def visible(xy) -> bool:
        index = imager.frame_index
        try:
            for dx, dy in offsets:
                imager.reset()
                X = km.tip_pose(kp, km.R_B_TRANSVERSE, float(xy[0]) + dx, float(xy[1]) + dy)
                if not imager(X).visible:
                    return False
            return True
        finally:
            imager.frame_index = index
            imager.reset()

    return visible


def study_localization(config, er: float, planned_travel: float):
    """The localization settings of a closed-loop study run and a note ("" if unchanged).

    The product refuses to localize from an exploration shorter than
    ``min_exploration_travel`` (15 mm) and rejects registrations that fail its acceptance
    checks (RMS residual, inlier fraction, centre offset); the paper's registration (II-F)
    has neither, and its ER sweep (III-C) reports both errors at every ER of its grid. So a
    study run whose planned exploration (ER x length) is shorter than the product's minimum
    registers whatever it explored, unchecked, as the paper (and the kinematic twin) do.
    ER 0 is left alone: it has nothing to register (the study takes the initial alignment,
    :func:`initial_alignment_record`). Only the study's scenario changes, never the product
    default."""
    if er <= 0 or planned_travel >= config.min_exploration_travel - 1e-12:
        return config, ""
    relaxed = dataclasses.replace(
        config,
        min_exploration_travel=0.0,
        min_inlier_fraction=0.0,
        max_rms_residual=RELAXED_LIMIT,
        max_rms_residual_deformable=RELAXED_LIMIT,
        max_centroid_offset=RELAXED_LIMIT,
    )
    return relaxed, (
        f"planned exploration {planned_travel * 1e3:.1f} mm is below the "
        f"product's minimum {config.min_exploration_travel * 1e3:.0f} mm: the "
        "study registers it without the product's minimum travel and acceptance "
        "checks (the paper has none)"
    )


def rejected_registration_record(kp, loc) -> dict:
    """The errors of a registration the product's acceptance checks rejected (``loc``, the
    scan's LocalizationOutcome with ``rejected``): the scan stopped, as the product must,
    but the paper's registration has no such check and its studies report the errors of
    whatever it registered, so the study records them (the run has no pivot)."""
    X = loc.rejected.X_BK
    return {
        "e_trans_mm": e_trans(X, kp.X_BK_true) * 1e3,
        "e_rot_x_deg": math.degrees(e_rot_x(X, kp.X_BK_true)),
        "localization_note": f"the product rejected the registration ({loc.error}); its "
        "errors are recorded (the paper has no acceptance check)",
    }


def initial_alignment_record(kp, scan, start_xy) -> dict:
    """ER 0 of a closed-loop study run (the paper's III-C: "at ER = 0% ... the localization
    is purely based on the initial alignment"): E_trans and E_rot,x of the heuristic initial
    alignment (:func:`drake_rus.experiments.kinematic.heuristic_pose`, the twin's) at the
    tip's (x, y) where the scan's exploration began (its first EXPLORE frame, else its last
    frame, else ``start_xy``)."""
    explore = [f for f in scan.frames if f.phase == int(Phase.EXPLORE)]
    frames = explore or list(scan.frames)
    xy = (
        np.asarray(frames[0 if explore else -1].X_BP.translation()[:2], float)
        if frames
        else np.asarray(start_xy, float)
    )
    X0 = km.heuristic_pose(kp, xy)
    return {
        "e_trans_mm": e_trans(X0, kp.X_BK_true) * 1e3,
        "e_rot_x_deg": math.degrees(e_rot_x(X0, kp.X_BK_true)),
        "localization_note": "ER 0: initial alignment only (the paper's III-C)"
        + (f"; the scan: {scan.status} {scan.reason}".rstrip() if scan.reason else ""),
    }


_EXPLORATIONS: dict = {}


def exploration(task: dict, kp, imager, controller, start_fraction: float, x_offset: float):
    """The exploration of ``task``. Runs that differ only in ER share one full (ER 100%)
    exploration per process and take its prefix (identical to exploring less: see
    ``Sweep.prefix``)."""
    key = (
        task["patient"],
        task.get("posture"),
        task["voxel"],
        task["segmenter"],
        task["seed"],
        task["scenario"],
        task.get("scenarios_file"),
        task.get("overrides"),
        start_fraction,
        x_offset,
    )
    full = _EXPLORATIONS.get(key)
    if full is None:
        full = km.explore(
            kp,
            imager,
            controller,
            exploration_ratio=1.0,
            start_fraction=start_fraction,
            x_offset=x_offset,
            travel=max(kidney_length(kp), controller.kidney_length),
        )
        if len(_EXPLORATIONS) >= 16:
            _EXPLORATIONS.pop(next(iter(_EXPLORATIONS)))
        _EXPLORATIONS[key] = full
    return full.prefix(
        exploration_travel(
            task["er"], task.get("er_unit", "fixed"), kidney_length(kp), controller.kidney_length
        )
    )


def _reach(r):
    return None if r is None else {"n": int(r["n"]), "eps_mm": r["eps"] * 1e3}


def sweep_entry(kp, sweep, geometry, controller) -> dict:
    """The sweep costs of one kinematic sweep (:func:`drake_rus.metrics.sweep_efficiency`,
    the definitions the closed-loop scan uses): pole to pole (``n``, ``eps_mm``, ``V``, the
    paper's), the whole pivot (``n_whole_pivot``, ``eps_whole_pivot_mm``,
    ``V_whole_pivot``), n and eps to reach V (``at_V``, pole to pole; ``at_V_whole_pivot``),
    and the pivot legs ended by the tilt cap (``tilt_cap_legs``). Also returns the
    pole-to-pole curves (``curve_eps_mm``, ``curve_V``) and the sweep's events."""

    def coverage():
        return CoverageAccumulator(
            kp.kidney_points_B, kp.voxel_volume, geometry.in_fan, geometry.elevation_width
        )

    eff = sweep_efficiency(
        sweep.poses,
        sweep.visible,
        geometry.depth,
        legs=sweep.leg,
        coverage=coverage,
        V_targets=V_TARGETS,
        angles=sweep.angles,
        max_tilt=controller.max_pivot_tilt if sweep.angles is not None else None,
    )
    return {
        "n": int(eff["n"]),
        "eps_mm": eff["eps"] * 1e3,
        "V": eff["V"],
        "n_whole_pivot": int(eff["n_whole_pivot"]),
        "eps_whole_pivot_mm": eff["eps_whole_pivot"] * 1e3,
        "V_whole_pivot": eff["V_whole_pivot"],
        "at_V": {f"{t:g}": _reach(eff["at_V"][t]) for t in V_TARGETS},
        "at_V_whole_pivot": {f"{t:g}": _reach(eff["at_V_whole_pivot"][t]) for t in V_TARGETS},
        "tilt_cap_legs": list(eff["tilt_cap_legs"]),
        "events": list(sweep.events),
        "curve_eps_mm": np.round(eff["eps_curve"] * 1e3, 3).tolist(),
        "curve_V": np.round(eff["V_curve"], 5).tolist(),
        "pole_to_pole": [int(i) for i in eff["pole_to_pole"][[0, -1]]]
        if len(eff["pole_to_pole"])
        else [],
    }


def run_closed_loop(task: dict) -> dict:
    """One closed-loop dynamic scan (the lead's ``RunScan``: MultibodyPlant, controller,
    contact) and the same scan in kinematic mode (same patient, start, ER, segmenter,
    localization method): E_trans, E_rot,x, and n, eps, V pole to pole (the paper's) and
    over the whole pivot, both by :mod:`drake_rus.metrics.sweep`. The closed-loop scan's ER
    multiplies its controller's ``exploration_length`` (the estimated kidney length by
    default); the twin's the task's ``er_unit``."""
    t0 = time.perf_counter()
    base = _scenario(task["scenario"], task.get("scenarios_file"), task.get("overrides"))
    scenario = dataclasses.replace(
        base,
        controller=dataclasses.replace(base.controller, exploration_ratio=task["er"]),
        localization=dataclasses.replace(base.localization, method=task["method"]),
        imaging=dataclasses.replace(base.imaging, segmenter=task["segmenter"]),
    )
    X_BPt = scenario.patient.X_BPt.GetDeterministicValue()
    kp = prepared_patient(
        task["patient"],
        scenario.patient.side,
        scenario.patient.posture,
        float(task["voxel"]),
        X_BPt,
    )
    template = _template(scenario.localization.template)
    scan = RunScan(
        scenario, kp.patient, template, progress=False, start_fraction=float(task["start_fraction"])
    )
    m = ScanMetrics(scan)
    at = m["at_matched_V"]
    closed = {
        "status": scan.status,
        "reason": scan.reason,
        "e_trans_mm": m["e_trans_mm"],
        "e_rot_x_deg": m["e_rot_x_deg"],
        "n": m["n_frames"],
        "eps_mm": m["eps_mm"],
        "V": m["volume_ratio"],
        "n_whole_pivot": m["n_whole_pivot"],
        "eps_whole_pivot_mm": m["eps_whole_pivot_mm"],
        "V_whole_pivot": m["volume_ratio_whole_pivot"],
        "at_V": {k: v["pole_to_pole"] for k, v in at.items()},
        "at_V_whole_pivot": {k: v["whole_pivot"] for k, v in at.items()},
        "tilt_cap_legs": m["pivot"]["tilt_cap_legs"],
        "er_unit": getattr(scenario.controller, "exploration_length", "fixed"),
        "sim_s": scan.sim_s,
        "wall_s": scan.wall_s,
        "mode": "closed-loop dynamic simulation",
    }
    t1 = time.perf_counter()
    imager = km.Imager(
        kp,
        km.imaging_for(kp, scenario.imaging, scenario.start),
        task["segmenter"],
        seed=int(task["seed"]),
    )
    sweep = km.explore(
        kp,
        imager,
        scenario.controller,
        exploration_ratio=task["er"],
        start_fraction=float(task["start_fraction"]),
        travel=exploration_travel(
            task["er"],
            task.get("er_unit", "fixed"),
            kidney_length(kp),
            scenario.controller.kidney_length,
        ),
    )
    loc = km.localize_cloud(
        kp,
        sweep.point_cloud(),
        template,
        scenario.localization,
        sweep.frames[0].X_BP.translation()[:2],
    )
    op = km.strategy_sweep(kp, imager, "OP", scenario.controller, loc.X_BK)
    kin = sweep_entry(kp, op, imager.geometry, scenario.controller)
    for k in ("curve_eps_mm", "curve_V", "events", "pole_to_pole"):
        kin.pop(k)
    kin.update(
        {
            "e_trans_mm": e_trans(loc.X_BK, kp.X_BK_true) * 1e3,
            "e_rot_x_deg": math.degrees(e_rot_x(loc.X_BK, kp.X_BK_true)),
            "er_unit": task.get("er_unit", "fixed"),
            "wall_s": time.perf_counter() - t1,
            "mode": km.MODE,
        }
    )
    return {
        "run_id": run_id(task),
        "task": task,
        "mode": "closed-loop + kinematic twin",
        "patient": task["patient"],
        "er": task["er"],
        "start": -1,
        "kidney_length_mm": kidney_length(kp) * 1e3,
        "closed_loop": closed,
        "kinematic": kin,
        "wall_s": time.perf_counter() - t0,
    }


def closed_loop_scenario(task: dict, kp, base):
    """The scenario of a closed-loop study run: ``base`` with the run's ER, localization
    method and segmenter. ER: with ``er_unit`` "kidney" the exploration travels ER x the
    patient's kidney length along the exploration line (the controller's reference length
    L_m set to it, ``exploration_length: fixed``: the simulation knows the truth, as the
    paper's simulation did), with "fixed" ER x the scenario's L_m; the scan's
    ``exploration_length: estimated`` is not used, so both modes explore the same travel.
    A random start (``starts``) lands the probe at the twin's start (x, y)
    (``controller.start_xy``), drawn where the kidney is visible (:func:`start_visibility`).
    A run whose planned exploration is below the product's ``min_exploration_travel``
    registers without the product's minimum and acceptance checks
    (:func:`study_localization`)."""
    return closed_loop_setup(task, kp, base)[:3]


def closed_loop_setup(task: dict, kp, base):
    """:func:`closed_loop_scenario` and what the study changed for the run:
    ``(scenario, start_fraction, x_offset, notes)``, ``notes`` a dict with
    ``start_rejected_draws`` (random starts drawn where the kidney was not visible,
    :func:`start_visibility`) and ``study_relaxation`` (:func:`study_localization`)."""
    c = base.controller
    unit = task.get("er_unit", "fixed")
    length = kidney_length(kp) if unit == "kidney" else float(c.kidney_length)
    planned = exploration_travel(task["er"], unit, kidney_length(kp), c.kidney_length)
    controller = dataclasses.replace(
        c, exploration_ratio=float(task["er"]), exploration_length="fixed", kidney_length=length
    )
    start_fraction, x_offset, notes = 0.0, 0.0, {}
    if task["study"] == "starts":
        imager = km.Imager(
            kp,
            km.imaging_for(kp, base.imaging, base.start),
            task["segmenter"],
            seed=int(task["seed"]),
        )
        start_fraction, x_offset, rejected = visible_random_start(
            task, kp, c, start_visibility(kp, imager)
        )
        notes["start_rejected_draws"] = rejected
        xy = km.start_xy(kp, start_fraction, c.scan_direction, x_offset)
        controller = dataclasses.replace(controller, start_xy=[float(xy[0]), float(xy[1])])
    localization, relaxation = study_localization(
        dataclasses.replace(base.localization, method=task["method"]), float(task["er"]), planned
    )
    notes["study_relaxation"] = relaxation
    scenario = dataclasses.replace(
        base,
        controller=controller,
        localization=localization,
        imaging=dataclasses.replace(base.imaging, segmenter=task["segmenter"]),
    )
    return scenario, start_fraction, x_offset, notes


@dataclasses.dataclass
class StrategyScan:
    """How the closed-loop scan of one efficiency strategy runs: its scenario (validated
    like any scenario), the start planner's start fraction, and what the run records about
    the pose (``pivot_pose``: "registered", "given" or None for SL; ``given_pivot_pose``
    [x m, y m, yaw rad] or None; ``pose_source`` the truth it came from, ``how`` and
    ``text`` for people)."""

    scenario: object
    start_fraction: float
    pose: dict


def closed_loop_strategy_run(
    scenario, strategy: str, kp=None, start_fraction: float = 0.0
) -> StrategyScan:
    """The closed-loop scan of efficiency strategy ``strategy`` from the run's ``scenario``
    (its ER, segmenter, registration) and start fraction:

    - OP: the scan as it is (two-leg pivot at the registered T*, ``pivot_pose`` []);
    - OP-PE: ``pivot_strategy: predicted_end``;
    - GT-OP, NOP: ``pivot_pose`` = the strategy's pose from the true kidney pose
      (:func:`~drake_rus.experiments.kinematic.strategy_pivot_pose`, the twin's), two-leg
      pivot, ER 0 (the scan skips exploration and localization; the start planner checks
      no sweep) and the probe's start over the kidney's middle
      (:data:`GIVEN_POSE_START_FRACTION`);
    - SL: ``sweep: line`` from ``start_xy`` beyond the E-ROI's end for at most the twin's
      travel (:func:`~drake_rus.experiments.kinematic.sl_line`), the start planner's start
      at the E-ROI's end, ER 100% (what the planner's window must hold; the line itself
      ends where the kidney leaves the image), no kidney-length estimation or adaptive stop
      (nothing to localize).

    The truth (``kp``, a prepared patient; needed by GT-OP, NOP, SL) enters only as these
    scenario values, checked by ``CheckScenario``: the scan never reads it."""
    check_strategies([strategy], "closed-loop")
    c = dataclasses.replace(
        scenario.controller, pivot_pose=[], sweep="pivot", pivot_strategy="two_leg"
    )
    loc = scenario.localization
    sf = float(start_fraction)
    pose = {"pivot_pose": "registered", "given_pivot_pose": None, "pose_source": None}
    if strategy in ("GT-OP", "NOP", "SL") and kp is None:
        raise ValueError(
            f"strategy {strategy}: needs the prepared patient (its true kidney pose or E-ROI)"
        )
    if strategy == "OP-PE":
        c = dataclasses.replace(c, pivot_strategy="predicted_end")
    elif strategy in ("GT-OP", "NOP"):
        given = pivot_pose_as_given(*km.strategy_pivot_pose(strategy, kp.X_BK_true))
        c = dataclasses.replace(c, pivot_pose=given, exploration_ratio=0.0)
        sf = GIVEN_POSE_START_FRACTION
        pose = {
            "pivot_pose": "given",
            "given_pivot_pose": given,
            "pose_source": "the true kidney pose (simulation truth, study only)",
        }
    elif strategy == "SL":
        start, travel = km.sl_line(kp, c.scan_direction)
        c = dataclasses.replace(
            c,
            sweep="line",
            start_xy=[float(v) for v in start],
            line_sweep_max_travel=travel,
            exploration_ratio=1.0,
        )
        loc = dataclasses.replace(loc, length_estimation=False, adaptive_exploration=False)
        sf = 0.0
        pose = {
            "pivot_pose": None,
            "given_pivot_pose": None,
            "pose_source": "the true kidney's E-ROI (the line's start, study only)",
        }
    out = dataclasses.replace(scenario, controller=c, localization=loc)
    CheckScenario(out)
    pose.update(
        pivot_pose_from=POSE_FROM[strategy],
        how=CLOSED_LOOP_STRATEGY_HOW[strategy],
        text=STRATEGY_TEXT[strategy],
    )
    return StrategyScan(out, sf, pose)


def closed_loop_strategy_scenario(scenario, strategy: str, kp=None):
    """The scenario of :func:`closed_loop_strategy_run` (OP the two-leg pivot at the
    registered T*, OP-PE the predicted_end one, GT-OP and NOP a given pivot pose, SL a
    line sweep)."""
    return closed_loop_strategy_run(scenario, strategy, kp).scenario


def _closed_loop_entry(m: dict) -> dict:
    """A strategy entry (like :func:`sweep_entry`'s) from a closed-loop scan's metrics."""
    at = m["at_matched_V"]
    sweep = m.get("sweep") or {}
    return {
        "n": int(m["n_frames"]),
        "eps_mm": m["eps_mm"],
        "V": m["volume_ratio"],
        "sweep": sweep.get("kind", "pivot"),
        "pivot_pose": sweep.get("pivot_pose"),
        "given_pivot_pose": sweep.get("given_pivot_pose"),
        "n_whole_pivot": int(m["n_whole_pivot"]),
        "eps_whole_pivot_mm": m["eps_whole_pivot_mm"],
        "V_whole_pivot": m["volume_ratio_whole_pivot"],
        "at_V": {k: v["pole_to_pole"] for k, v in at.items()},
        "at_V_whole_pivot": {k: v["whole_pivot"] for k, v in at.items()},
        "tilt_cap_legs": list(m["pivot"]["tilt_cap_legs"]),
        "events": [],
        "curve_eps_mm": np.round(np.asarray(m["eps_curve_mm"], float), 3).tolist(),
        "curve_V": np.round(np.asarray(m["V_curve"], float), 5).tolist(),
        "pole_to_pole": list(m["pivot"]["pole_to_pole_frames"]),
        "volume_ml": None,
        "volume_error_pct": None,
        "volume_note": "closed loop: reconstructed in the efficiency study only",
    }


def closed_loop_volume(scan, metrics: dict, kp, spacing: float) -> dict:
    """The kidney volume reconstructed from a closed-loop scan's pole-to-pole frames (the
    masks ``RunScan(keep_sweep_masks=True)`` kept, compounded as the kinematic study does:
    :func:`~drake_rus.metrics.reconstruction.reconstruct_kidney`) against the true kidney's:
    {volume_ml, volume_error_pct, volume_note}."""
    line = (metrics.get("sweep") or {}).get("kind") == "line"
    phase = int(Phase.EXPLORE if line else Phase.PIVOT)
    frames = [f for f in scan.frames if f.phase == phase]
    ends = metrics["pivot"]["pole_to_pole_frames"]
    out = {"volume_ml": None, "volume_error_pct": None}
    if not ends:
        return out | {"volume_note": "no pole-to-pole span to reconstruct"}
    span = frames[ends[0] : ends[1] + 1]
    masks = [scan.sweep_masks.get(f.frame_index) for f in span]
    if not span or any(m is None for m in masks):
        return out | {"volume_note": "the scan kept no masks (RunScan keep_sweep_masks)"}
    geometry = ProbeGeometry.from_config(scan.scenario.imaging)
    try:
        rec = reconstruct_kidney(masks, [f.X_BP for f in span], geometry, spacing=spacing)
    except ValueError as e:
        return out | {"volume_note": str(e)}
    return {
        "volume_ml": rec["volume_ml"],
        "volume_error_pct": 100 * (rec["volume_ml"] / (kp.kidney_volume * 1e6) - 1),
        "volume_note": f"closed loop: {len(span)} pole-to-pole masks compounded at "
        f"{spacing * 1e3:g} mm",
    }


def task_scenario_and_patient(task: dict):
    """(scenario, prepared patient) of a study task: the task's scenario with its overrides
    and posture, and the patient placed on the bed at that scenario's X_BPt."""
    scenario = _with_posture(
        _scenario(task["scenario"], task.get("scenarios_file"), task.get("overrides")), task
    )
    kp = prepared_patient(
        task["patient"],
        scenario.patient.side,
        scenario.patient.posture,
        float(task["voxel"]),
        scenario.patient.X_BPt.GetDeterministicValue(),
    )
    return scenario, kp


def run_closed_loop_study(task: dict) -> dict:
    """One study run (er-sweep, starts, efficiency, template) as a full closed-loop scan on
    the Drake diagram (``RunScan``: MultibodyPlant, controller, contact, the scan's own
    imaging, localization and OP pivot), with the kinematic run's record (E_trans,
    E_rot,x, the sweep costs pole to pole and over the whole pivot, V) plus the scan's
    ``status``, ``reason`` and simulated time. A scan that stops before localizing has
    E_trans and E_rot,x None, except at ER 0, where the paper localizes by the initial
    alignment alone (:func:`initial_alignment_record`), and after a registration the
    product's acceptance checks rejected (:func:`rejected_registration_record`).
    ``start_rejected_draws`` and
    ``study_relaxation`` say what the study changed (:func:`closed_loop_setup`)."""
    t0 = time.perf_counter()
    base, kp = task_scenario_and_patient(task)
    scenario, start_fraction, x_offset, notes = closed_loop_setup(task, kp, base)
    variant = task.get("template_variant", "mean")
    template = template_variant(
        scenario.localization.template,
        variant,
        str(task["patient"]) if variant == "loo" else "",
        scenario.patient.side,
    )
    efficiency = task["study"] == "efficiency"
    scan = RunScan(
        scenario,
        kp.patient,
        template,
        progress=False,
        start_fraction=start_fraction,
        keep_sweep_masks=efficiency,
    )
    m = ScanMetrics(scan)
    loc = scan.localization
    explore = [f for f in scan.frames if f.phase == int(Phase.EXPLORE)]
    travel = (
        float(
            np.linalg.norm(explore[-1].X_BP.translation()[:2] - explore[0].X_BP.translation()[:2])
            * 1e3
        )
        if len(explore) > 1
        else 0.0
    )
    result = {
        "run_id": run_id(task),
        "task": task,
        "mode": "closed-loop",
        "status": scan.status,
        "reason": scan.reason,
        "patient": task["patient"],
        "er": task["er"],
        "start": task["start"],
        "start_fraction": start_fraction,
        "x_offset_mm": x_offset * 1e3,
        "explore_frames": len(explore),
        "explore_travel_mm": travel,
        "kidney_length_mm": kidney_length(kp) * 1e3,
        "er_unit": task.get("er_unit", "fixed"),
        "points": int(len(scan.partial_cloud_B)),
        "e_trans_mm": m["e_trans_mm"],
        "e_rot_x_deg": m["e_rot_x_deg"],
        "registration_ms": loc.compute_s * 1e3 if loc.result is not None else None,
        "iterations": None if loc.result is None else int(loc.result.iterations),
        "localization_note": loc.error or "",
        "true_volume_ml": kp.kidney_volume * 1e6,
        "sim_s": scan.sim_s,
        "scan_wall_s": scan.wall_s,
        # The scan's pivot (OP) pole to pole and over the whole pivot, whatever the study.
        "sweep": {
            k: v
            for k, v in _closed_loop_entry(m).items()
            if k not in ("curve_eps_mm", "curve_V", "events")
        },
        **notes,
    }
    if result["e_trans_mm"] is None and getattr(loc, "rejected", None) is not None:
        result.update(rejected_registration_record(kp, loc))
    if float(task["er"]) <= 0:
        xy = scenario.controller.start_xy or km.start_xy(
            kp, start_fraction, scenario.controller.scan_direction, x_offset
        )
        result.update(initial_alignment_record(kp, scan, xy))
        result["registration_ms"], result["iterations"] = None, None
    if task["study"] == "template":
        result.update(
            template_record(variant, template, kp, scenario.patient.posture, task["patient"])
        )
    if task["study"] == "efficiency":
        strategies = check_strategies(
            task.get("strategies") or CLOSED_LOOP_DEFAULT_STRATEGIES, "closed-loop"
        )
        result["strategies"] = {}
        for s in strategies:
            run = closed_loop_strategy_run(scenario, s, kp, start_fraction)
            same = run.scenario == scenario and run.start_fraction == start_fraction
            other = (
                scan
                if same
                else RunScan(
                    run.scenario,
                    kp.patient,
                    template,
                    progress=False,
                    start_fraction=run.start_fraction,
                    keep_sweep_masks=True,
                )
            )
            mo = m if same else ScanMetrics(other)
            volume = closed_loop_volume(other, mo, kp, float(task.get("recon_spacing", 0.001)))
            result["strategies"][s] = (
                _closed_loop_entry(mo)
                | run.pose
                | volume
                | {
                    "status": other.status,
                    "reason": other.reason,
                    "e_trans_mm": mo["e_trans_mm"],
                    "e_rot_x_deg": mo["e_rot_x_deg"],
                    "sim_s": other.sim_s,
                    "scan_wall_s": other.wall_s,
                    "scan": "the run's own scan" if same else "its own scan",
                }
            )
    result["wall_s"] = time.perf_counter() - t0
    return result


def run_task(task: dict) -> dict:
    """Executes one run (kinematic, or closed loop with ``mode`` "closed-loop") and
    returns its JSON-ready result, with the inputs it resolved (``inputs_sha256``,
    :func:`inputs_digest`) and its ``provenance`` (:func:`run_provenance`)."""
    if task["study"] == "closed-loop":
        result = run_closed_loop(task)
    elif check_mode(task.get("mode", "kinematic")) == "closed-loop":
        result = run_closed_loop_study(task)
    else:
        result = run_kinematic_task(task)
    result["inputs_sha256"] = task_inputs_digest(task)
    result["provenance"] = run_provenance(task)
    return result


def run_kinematic_task(task: dict) -> dict:
    """One study run in kinematic mode (the twin)."""
    t0 = time.perf_counter()
    scenario, kp = task_scenario_and_patient(task)
    controller = scenario.controller
    imager = km.Imager(
        kp,
        km.imaging_for(kp, scenario.imaging, scenario.start),
        task["segmenter"],
        seed=int(task["seed"]),
    )
    start_fraction, x_offset, rejected = 0.0, 0.0, None
    if task["study"] == "starts":
        # Where the kidney is visible (II-A (i)): the same starts as the closed loop's.
        start_fraction, x_offset, rejected = visible_random_start(
            task, kp, controller, start_visibility(kp, imager)
        )
    sweep = exploration(task, kp, imager, controller, start_fraction, x_offset)
    P = sweep.point_cloud()
    variant = task.get("template_variant", "mean")
    template = template_variant(
        scenario.localization.template,
        variant,
        str(task["patient"]) if variant == "loo" else "",
        scenario.patient.side,
    )
    config = dataclasses.replace(scenario.localization, method=task["method"])
    # ER 0: the initial alignment alone, whatever the start frame shows (III-C).
    loc = km.localize_cloud(
        kp,
        P,
        template,
        config,
        sweep.frames[0].X_BP.translation()[:2],
        min_points=50 if float(task["er"]) > 0 else math.inf,
    )
    result = {
        "run_id": run_id(task),
        "task": task,
        "mode": km.MODE,
        "patient": task["patient"],
        "er": task["er"],
        "start": task["start"],
        "start_fraction": start_fraction,
        "x_offset_mm": x_offset * 1e3,
        "explore_frames": len(sweep.frames),
        "explore_travel_mm": float(sweep.travel[-1] * 1e3),
        "kidney_length_mm": kidney_length(kp) * 1e3,
        "er_unit": task.get("er_unit", "fixed"),
        "points": int(len(P)),
        "e_trans_mm": e_trans(loc.X_BK, kp.X_BK_true) * 1e3,
        "e_rot_x_deg": math.degrees(e_rot_x(loc.X_BK, kp.X_BK_true)),
        "registration_ms": loc.compute_s * 1e3,
        "iterations": None if loc.result is None else int(loc.result.iterations),
        "localization_note": loc.note,
        "true_volume_ml": kp.kidney_volume * 1e6,
    }
    if rejected is not None:
        result["start_rejected_draws"] = rejected
    if task["study"] == "template":
        result.update(
            template_record(variant, template, kp, scenario.patient.posture, task["patient"])
        )
    if task["study"] == "efficiency":
        export = task.get("export_dir")
        result["strategies"] = efficiency_of(
            kp,
            imager,
            controller,
            loc.X_BK,
            float(task.get("recon_spacing", 0.001)),
            export_dir=export,
            name=re.sub(r"[^A-Za-z0-9]+", "-", task["patient"]).strip("-"),
            strategies=check_strategies(task.get("strategies") or STRATEGY_ORDER),
            pivot_model=km.pivot_model_for(template, imager.imaging),
        )
    result["wall_s"] = time.perf_counter() - t0
    return result


EXPORT_STRATEGIES = ("OP", "GT-OP")


def efficiency_of(
    kp,
    imager,
    controller,
    X_BK_est,
    recon_spacing: float,
    *,
    export_dir=None,
    name: str = "patient",
    strategies=STRATEGY_ORDER,
    pivot_model=None,
) -> dict:
    """Per strategy: :func:`sweep_entry` (pole-to-pole curves and totals, the whole pivot's
    totals, matched coverage, tilt cap) and the reconstructed kidney volume (mL) from the
    pole-to-pole masks; OP-PE (the predicted_end pivot, needs ``pivot_model``) also its
    predicted ends and pre-tilt (``pretilt``: target, end, check frames, window path mm).
    With
    ``export_dir``, the OP and GT-OP reconstructions are written there as NRRD (kidney
    probability, kidney mask and, for the classical/onnx segmenters, the grey volume)."""
    out = {}
    for s in strategies:
        sweep = km.strategy_sweep(
            kp, imager, s, controller, X_BK_est, keep_images=True, pivot_model=pivot_model
        )
        p2p = sweep.pole_to_pole()
        entry = sweep_entry(kp, sweep, imager.geometry, controller)
        entry.update(
            volume_ml=None,
            volume_error_pct=None,
            sweep="line" if s == "SL" else "pivot",
            pivot_pose_from=POSE_FROM[s],
            text=STRATEGY_TEXT[s],
        )
        if sweep.info:
            i = sweep.info
            entry["pretilt"] = {
                "predicted_ends_deg": [math.degrees(x) for x in i["predicted_ends"]],
                "target_deg": math.degrees(i["pretilt_target"]),
                "end_deg": math.degrees(i["pretilt_end"]),
                "check_frames": i["pretilt_check_frames"],
                "eps_mm": i["eps_pretilt"] * 1e3,
            }
        if p2p.frames:
            try:
                rec = reconstruct_kidney(
                    [f.mask for f in p2p.frames], p2p.poses, imager.geometry, spacing=recon_spacing
                )
                entry["volume_ml"] = rec["volume_ml"]
                entry["volume_error_pct"] = 100 * (rec["volume_ml"] / (kp.kidney_volume * 1e6) - 1)
                if export_dir is not None and s in EXPORT_STRATEGIES:
                    d = Path(export_dir)
                    tag = f"{name}__{s}"
                    note = (
                        f"drake-rus {s} sweep of {name}, kinematic mode; axes = robot base "
                        "frame x, y, z (mm)"
                    )
                    write_nrrd(
                        d / f"{tag}__kidney_probability.nrrd",
                        rec["reconstruction"].values,
                        rec["grid"],
                        description=note,
                    )
                    write_nrrd(
                        d / f"{tag}__kidney_mask.nrrd", rec["mask"], rec["grid"], description=note
                    )
                    if all(f.image is not None for f in p2p.frames):
                        grey = compound(
                            [f.image for f in p2p.frames], p2p.poses, imager.geometry, rec["grid"]
                        )
                        write_nrrd(
                            d / f"{tag}__grey.nrrd", grey.values, rec["grid"], description=note
                        )
                    entry["nrrd"] = sorted(str(p.name) for p in d.glob(f"{tag}__*.nrrd"))
            except ValueError as e:
                entry["volume_note"] = str(e)
        out[s] = entry
    return out


# ------------------------------------------------------------------------------- results
def load_study_results(out_dir, study: str | None = None) -> list[dict]:
    """All finished run results under ``out_dir/runs`` (optionally of one study)."""
    if study is None:
        return batch.load_results(out_dir)
    return batch.load_results(out_dir, lambda r: r["task"]["study"] == study)


def results_of(results: list[dict], tasks: list[dict]) -> list[dict]:
    """The results made by exactly ``tasks`` (same run id and settings key; OUT may hold
    other runs)."""
    wanted = {run_id(t): task_key(t) for t in tasks}
    return [
        r
        for r in results
        if wanted.get(r.get("run_id")) is not None and r.get("task_key") == wanted[r["run_id"]]
    ]
