"""What a study asks for: patient specs, study options, the typed run (:class:`StudyTask`)
and the generators that make a study's runs.

- Values a study may be asked for, each with its check: the ER grid and ER units, the run
  modes, postures, patient specs (:func:`expand_patients`), template variants
  (:func:`check_variant`) and efficiency strategies (:func:`check_strategies`, with what
  each strategy sweeps in both modes).
- :class:`StudyOptions`: what every run of a study shares; :class:`StudyTask`: one run,
  every field it is defined by (``to_dict`` / ``from_dict``: the ``task`` of a run file,
  the same JSON layout as before the type existed).
- The generators: :func:`er_sweep_tasks`, :func:`starts_tasks`, :func:`efficiency_tasks`,
  :func:`template_tasks`, :func:`closed_loop_tasks`.

Nothing here runs anything: a run's id and settings key are in
:mod:`~drake_rus.experiments.keys`, its execution in :mod:`~drake_rus.experiments.tasks`.
"""

from __future__ import annotations

import dataclasses
import re

from drake_rus.experiments import kinematic as km
from drake_rus.experiments.analysis import PAPER_STRATEGIES, STRATEGY_ORDER
from drake_rus.template.population import DEFAULT_SUBJECTS as POPULATION_SUBJECTS
from drake_rus.template.population import POPULATIONS, parse_population

# ------------------------------------------------------------------------------- ER, modes
ER_GRID = tuple(round(0.1 * k, 1) for k in range(11))
# What ER multiplies: the patient's kidney length (the paper's simulation) or L_m.
ER_UNITS = ("kidney", "fixed")
ER_UNIT_TEXT = {
    "kidney": "fraction of the patient's kidney length along the exploration line "
    "(the paper's simulation, III-C)",
    "fixed": "fraction of the fixed length L_m = 100 mm (the paper's in-vivo rule, III-F)",
}
# How a study run is executed: the kinematic twin (default, fast) or a closed-loop scan.
MODES = ("kinematic", "closed-loop")
# The studies a run may belong to ("closed-loop": the paper study's closed-loop check).
STUDIES = ("er-sweep", "starts", "efficiency", "template", "closed-loop")


# The segmenter a study's runs use unless asked (--segmenter): kinematic runs slice the
# label volume and take its kidney labels (the oracle), as the seed's simulation sliced its
# labelled CT volume (III-A); closed-loop runs segment the emulated images with the
# product's learned segmenter, as the seed's system segmented with its network (II-C).
DEFAULT_SEGMENTER = {"kinematic": "oracle", "closed-loop": "onnx"}
SEGMENTER_TEXT = {
    "oracle": "the label volume's kidney labels: an oracle, not a segmenter the product ships",
    "onnx": "the product's learned segmenter (ONNX) on the emulated images",
    "classical": "filtering, thresholding and morphology on the emulated images",
}


def check_mode(mode: str) -> str:
    if mode not in MODES:
        raise ValueError(f"--mode: expected one of {', '.join(MODES)}, got {mode!r}")
    return mode


# ------------------------------------------------------------------------------- patients
POSTURES = ("supine", "left_lateral_decubitus")
POSTURE_SUFFIXES = {
    "supine": "supine",
    "decubitus": "left_lateral_decubitus",
    "left_lateral_decubitus": "left_lateral_decubitus",
}
COHORT_SPEC = r"(test|train|seed):\d+"
COHORT_RANGE = r"(test|train|seed):(\d+)-(\d+)"
# A real CT kidney in a generated body: ``ct:PATH[#OPTION,OPTION...]`` (issue 27); its
# options are comma-separated words or key=value pairs, optionally with a @posture suffix.
CT_PREFIX = "ct:"
CT_OPTION = r"[A-Za-z_][A-Za-z0-9_]*(=[A-Za-z0-9_.+-]*)?(@[A-Za-z_]+)?"
# A cohort of real CT kidneys from a folder of label maps (KiTS layout):
# ``ct:DIR:SELECTION[#OPTIONS]``, SELECTION either case numbers and ranges joined by "+"
# (``0-14``, ``3``, ``0-4+20-29``: those cases, each a ``ct:DIR/CASE`` patient; a case
# without a usable kidney is skipped with its reason) or ``firstN`` (the first N cases in
# sorted order with a usable kidney that did not build the study's template);
# :mod:`~drake_rus.experiments.ct_cohort` expands it.
CT_SELECTION = r"first(\d+)|\d+(-\d+)?(\+\d+(-\d+)?)*"
PATIENTS_SYNTAX = (
    "test:0-14, seed:100-120, train:3, ct:PATH[#OPTIONS], ct:DIR:0-14 or ct:DIR:first15 "
    "[#OPTIONS] (cases of a folder of CT label maps) or a patient path, separated by "
    "commas (or semicolons)"
)


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


def split_patient_list(text: str) -> list[str]:
    """The patient specs of a list separated by ``;`` or ``,``. A comma inside a ``ct:``
    spec's options (``ct:PATH#left,body=7``) does not separate: a part that reads as a CT
    option (a word or key=value, :data:`CT_OPTION`) right after a ``ct:PATH#...`` spec
    continues it. ``;`` always separates."""
    specs: list[str] = []
    for group in str(text).split(";"):
        in_ct_options = False
        for part in group.split(","):
            part = part.strip()
            if in_ct_options and re.fullmatch(CT_OPTION, part):
                specs[-1] += "," + part
                continue
            specs.append(part)
            in_ct_options = part.startswith(CT_PREFIX) and "#" in part
    return [s for s in specs if s]


def expand_patients(text: str) -> list[str]:
    """Patient specs from a list (:func:`split_patient_list`: commas or semicolons) of
    ``test:0-14``, ``seed:100-120``, ``train:3``, ``ct:PATH[#OPTIONS]`` (a real CT kidney,
    its options parsed when the patient is loaded) or patient paths, each optionally with
    ``@supine`` / ``@decubitus`` (the template study's per-patient posture). Ranges are
    inclusive."""
    specs = []
    for part in split_patient_list(text):
        if "@" in part:
            spec, posture = split_posture(part)
            suffix = part[len(spec) :]
            specs += [s + suffix for s in expand_patients(spec)]
            continue
        m = re.fullmatch(COHORT_RANGE, part)
        if m:
            lo, hi = int(m.group(2)), int(m.group(3))
            if hi < lo:
                raise ValueError(f"--patients: range {part!r} runs backwards")
            specs += [f"{m.group(1)}:{k}" for k in range(lo, hi + 1)]
        elif part.startswith(CT_PREFIX):
            if not part[len(CT_PREFIX) :].partition("#")[0].strip():
                raise ValueError(
                    f"--patients: {part!r} names no label map (expected ct:PATH[#OPTIONS])"
                )
            sel = ct_selection(part)
            if sel is not None and sel[1] == "first0":
                raise ValueError(f"--patients: {part!r} selects no case (firstN needs N >= 1)")
            specs.append(part)
        elif re.fullmatch(COHORT_SPEC, part) or "/" in part or "." in part:
            specs.append(part)
        else:
            raise ValueError(f"--patients: cannot read {part!r} (expected {PATIENTS_SYNTAX})")
    if not specs:
        raise ValueError("--patients: no patients given")
    return specs


def ct_selection(spec: str) -> tuple[str, str, str] | None:
    """(folder, selection, options) of a ``ct:DIR:SELECTION[#OPTIONS]`` cohort spec
    (:data:`CT_SELECTION`; options without the "#", posture suffix included), None for any
    other spec (a single ``ct:PATH`` patient among them)."""
    spec = str(spec)
    if not spec.startswith(CT_PREFIX):
        return None
    body = spec[len(CT_PREFIX) :]
    head, sep, options = body.partition("#")
    folder, colon, selection = head.rpartition(":")
    if not colon or not folder.strip() or not re.fullmatch(CT_SELECTION, selection):
        return None
    return folder, selection, options if sep else ""


# What each kind of patient is (issue 27): tables and figures group them apart.
PATIENT_KINDS = {
    "generated": "generated patient (the generator's body and kidney)",
    "ct": "real CT kidney in a generated body",
    "real": "real body (imported anatomy)",
}


def patient_kind(spec: str) -> str:
    """ "generated" (seed:N, train:K, test:K), "ct" (``ct:``: a real CT kidney in a generated
    body) or "real" (a real body: a patient file or folder); :data:`PATIENT_KINDS`."""
    spec = split_posture(str(spec))[0] if "@" in str(spec) else str(spec)
    if re.fullmatch(COHORT_SPEC, spec):
        return "generated"
    return "ct" if spec.startswith(CT_PREFIX) else "real"


# ------------------------------------------------------------------------------- templates
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


def population_of_variant(v: str) -> tuple[str, int] | None:
    """(population name, subjects) of a ``population:NAME[:N]`` variant, else None."""
    m = re.fullmatch(r"population:([^:]+)(?::(\d+))?", str(v))
    if m is None:
        return None
    return m.group(1), int(m.group(2)) if m.group(2) else POPULATION_SUBJECTS


def check_variant(v: str) -> None:
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


# ------------------------------------------------------------------------------- strategies
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
# How a closed-loop scan runs each strategy
# (:func:`~drake_rus.experiments.closed_loop_runs.closed_loop_strategy_run`): the scan never
# reads the truth; GT-OP's and NOP's poses reach it as a scenario value the study computes
# from the true pose, as an operator's placement would.
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


# ------------------------------------------------------------------------------- the runs
@dataclasses.dataclass(frozen=True)
class StudyOptions:
    """What every run of a study shares."""

    scenario: str = "default"  # scenario name in the scenarios file
    scenarios_file: str | None = None  # None: diagrams/default.scenarios.yaml
    overrides: str | None = None  # YAML overrides of the scenario (--set)
    segmenter: str = "oracle"  # the runs' segmenter (oracle, classical, onnx)
    method: str = "seed"  # localization method of the runs (the seed's by default)
    voxel: float = 0.002  # label-volume voxel size (m)
    seed: int = 0  # random starts, emulator speckle
    recon_spacing: float = 0.001  # reconstruction grid (m; read by efficiency runs only)
    er_unit: str = "kidney"  # ER x the patient's kidney length, or "fixed" (x L_m)
    mode: str = "kinematic"  # "kinematic" (the twin) or "closed-loop" (RunScan)
    posture: str | None = None  # the patients' posture; None: the scenario's
    # The registration template as asked for (--template: generated, real, real:DIR or a
    # file; None: the scenario's localization.template, unresolved) and the file it
    # resolved to (its bytes are keyed through the inputs digest, not its path). Left out
    # of a run's task while None, so runs from before these fields keep their keys.
    template: str | None = dataclasses.field(default=None, metadata={"omit_default": True})
    template_file: str | None = dataclasses.field(default=None, metadata={"omit_default": True})


# Task fields whose absence from a recorded task means another value than their default:
# runs recorded before ER units existed explored ER x L_m.
ABSENT_MEANS = {"er_unit": "fixed"}


def _only(*studies: str) -> dict:
    """Field metadata: the field belongs to these studies' runs only (:meth:`StudyTask.to_dict`
    leaves it out of the others')."""
    return {"studies": studies}


@dataclasses.dataclass(frozen=True, kw_only=True)
class StudyTask(StudyOptions):
    """One study run: the study's options (:class:`StudyOptions`, inherited) and the run's
    own fields. Frozen and picklable (Dask sends it to the workers as it is); the run file
    records :meth:`to_dict`, whose key set is the one runs had before this type existed
    (the fields of other studies left out), so settings keys
    (:func:`~drake_rus.experiments.keys.task_key`) of unchanged runs are unchanged."""

    study: str  # one of STUDIES
    patient: str  # patient spec (expand_patients), without @posture
    er: float  # exploration ratio, in units of er_unit
    start: int = -1  # random start index (starts study); -1: none
    # The registration template's variant (template study; TEMPLATE_VARIANTS, check_variant).
    template_variant: str = dataclasses.field(default="mean", metadata=_only("template"))
    # Where the OP and GT-OP reconstructions go as NRRD (efficiency; None: nowhere; unkeyed).
    export_dir: str | None = dataclasses.field(default=None, metadata=_only("efficiency"))
    # The efficiency strategies (STRATEGY_ORDER); None: the mode's default_strategies.
    strategies: tuple[str, ...] | None = dataclasses.field(
        default=None, metadata=_only("efficiency")
    )
    # The closed-loop check's start, as a fraction of the E-ROI's length.
    start_fraction: float = dataclasses.field(default=0.1, metadata=_only("closed-loop"))

    def __post_init__(self):
        if self.study not in STUDIES:
            raise ValueError(
                f"study task: study expected one of {', '.join(STUDIES)}, got {self.study!r}"
            )
        for name, kind in (
            ("er", float),
            ("voxel", float),
            ("recon_spacing", float),
            ("start_fraction", float),
            ("seed", int),
            ("start", int),
        ):
            try:
                object.__setattr__(self, name, kind(getattr(self, name)))
            except (TypeError, ValueError):
                raise ValueError(
                    f"study task: {name} expected a number, got {getattr(self, name)!r}"
                ) from None
        if self.strategies is not None:
            object.__setattr__(self, "strategies", tuple(str(s) for s in self.strategies))
        for f in dataclasses.fields(self):
            only = f.metadata.get("studies")
            if only and self.study not in only and getattr(self, f.name) != f.default:
                raise ValueError(
                    f"study task: {f.name} is read by {', '.join(only)} runs "
                    f"only, not by a {self.study} run"
                )

    def to_dict(self) -> dict:
        """The run file's ``task``: every field, but those of other studies and those
        marked ``omit_default`` at their default (JSON-ready: ``strategies`` a list)."""
        out = {}
        for f in dataclasses.fields(self):
            only = f.metadata.get("studies")
            if only and self.study not in only:
                continue
            v = getattr(self, f.name)
            if f.metadata.get("omit_default") and v == f.default:
                continue
            out[f.name] = list(v) if isinstance(v, tuple) else v
        return out

    @classmethod
    def from_dict(cls, task: dict) -> StudyTask:
        """The task of a run file's ``task`` dict: absent fields take their defaults (or
        :data:`ABSENT_MEANS`'s value), an unknown one is refused (ValueError naming it)."""
        if not isinstance(task, dict):
            raise ValueError(f"study task: expected a dict, got {type(task).__name__}")
        names = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(task) - set(names))
        if unknown:
            raise ValueError(
                f"study task: unknown field(s) {', '.join(unknown)} (expected {', '.join(names)})"
            )
        missing = [k for k in ("study", "patient", "er") if k not in task]
        if missing:
            raise ValueError(f"study task: missing {', '.join(missing)}")
        return cls(**(ABSENT_MEANS | task))


def _task(options: StudyOptions, **fields) -> StudyTask:
    """The run of ``options`` with ``fields`` (which may override an option)."""
    shared = {f.name: getattr(options, f.name) for f in dataclasses.fields(StudyOptions)}
    return StudyTask(**(shared | fields))


def er_sweep_tasks(patients, options: StudyOptions, ers=ER_GRID) -> list[StudyTask]:
    return [
        _task(options, study="er-sweep", patient=p, er=float(er), start=-1)
        for p in patients
        for er in ers
    ]


def starts_tasks(patients, options: StudyOptions, er: float, n_starts: int = 5) -> list[StudyTask]:
    return [
        _task(options, study="starts", patient=p, er=float(er), start=k)
        for p in patients
        for k in range(n_starts)
    ]


def efficiency_tasks(
    patients, options: StudyOptions, er: float, export_dir: str | None = None, strategies=None
) -> list[StudyTask]:
    """``export_dir``: write the OP and GT-OP reconstructions there as NRRD. ``strategies``:
    default all (kinematic) or the paper's four (closed loop, one scan each)."""
    strategies = check_strategies(strategies or default_strategies(options.mode), options.mode)
    return [
        _task(
            options,
            study="efficiency",
            patient=p,
            er=float(er),
            start=-1,
            export_dir=None if export_dir is None else str(export_dir),
            strategies=strategies,
        )
        for p in patients
    ]


def closed_loop_tasks(
    patients, options: StudyOptions, er: float, start_fraction: float = 0.1
) -> list[StudyTask]:
    """A few closed-loop dynamic scans (``RunScan``) with their kinematic twins."""
    return [
        _task(
            options,
            study="closed-loop",
            patient=p,
            er=float(er),
            start=-1,
            start_fraction=float(start_fraction),
        )
        for p in patients
    ]


def template_tasks(
    patients, options: StudyOptions, er: float, variants=TEMPLATE_VARIANTS
) -> list[StudyTask]:
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
        check_variant(v)
    if options.posture is not None and options.posture not in POSTURES:
        raise ValueError(f"posture: expected one of {', '.join(POSTURES)}, got {options.posture!r}")
    tasks = []
    for p in patients:
        spec, posture = split_posture(p)
        for v in variants:
            if v == "loo" and not re.fullmatch(r"train:\d+", spec):
                continue
            tasks.append(
                _task(
                    options,
                    study="template",
                    patient=spec,
                    er=float(er),
                    start=-1,
                    template_variant=v,
                    posture=posture or options.posture,
                )
            )
    return tasks
