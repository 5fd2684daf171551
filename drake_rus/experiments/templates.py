"""The registration templates of the template study (beyond the paper, issue 18) and how far
each lies from the patient's kidney.

:func:`template_variant` builds the template of a variant (syntax and check:
:func:`~drake_rus.experiments.specs.check_variant`) that differs from the patient by known
amounts: the mean template, the mean scaled by 0.9 / 1.1, a single training kidney
(``single:K``), for training patients the leave-one-out mean (``loo``, the mean of the other
19 corresponded training shapes), and a template built from another population
(``population:NAME``, :mod:`drake_rus.template.population`: generated kidneys with other
size statistics, e.g. ``long``/``short`` = Glodny's length +-1 SD, built once and cached).
Each run records the template's distance from the patient's kidney
(:func:`template_distance`, :func:`template_record`), so E_trans and E_rot,x can be read
against it. Both run modes take their template from here (``mean``: the scenario's).
"""

from __future__ import annotations

import functools
import hashlib
import re
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from drake_rus.experiments.keys import template_file
from drake_rus.experiments.specs import (
    StudyTask,
    check_variant,
    patient_kind,
    population_of_variant,
)
from drake_rus.localization.localize import RegistrationTemplate, load_registration_template
from drake_rus.template.io import load_template as read_template
from drake_rus.template.population import population_template


@functools.lru_cache(maxsize=4)
def load_template(path):
    """The registration template file at ``path`` (None: the shipped one; ``generated``,
    ``real``, ``real:DIR``: resolved, :func:`~drake_rus.experiments.keys.template_file`),
    cached."""
    return load_registration_template(None if path is None else str(template_file(path)))


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
    check_variant(variant)
    pop = population_of_variant(variant)
    if pop is not None:
        return load_template(str(population_template(pop[0], n=pop[1], side=side)))
    base = load_template(path)
    if variant == "mean":
        return base
    if variant.startswith("scale-"):
        f = float(variant.split("-", 1)[1])
        return RegistrationTemplate(base.points * f, base.normals)
    with np.load(template_file(path)) as z:
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


@functools.lru_cache(maxsize=8)
def template_info(spec: str | None, path) -> dict:
    """What a study's registration template is, for its runs' records and the report:
    ``spec`` (as asked for: generated, real, real:DIR, a file; None: the scenario's), the
    resolved ``file``, its ``sha256``, ``kind`` ("generated" or "real CT"), ``subjects``
    (how many kidneys built it), ``cases`` (the CT cases, for a real template) and a
    ``label`` ("generated (20 generated kidneys)", "real (20 CT kidneys of kits19)")."""
    from_file = template_file(path)
    try:
        meta = read_template(from_file).meta
    except (OSError, ValueError):
        meta = {}
    used = meta.get("subjects_used") or []
    cases = sorted({u["case"] for u in used}) if used else []
    n = meta.get("n_subjects") or len(used) or None
    real = bool(used) or str(meta.get("split", "")).startswith("ct:")
    name = str(spec).strip() if spec else ("generated" if not real else "real")
    if name.startswith("/") or name.endswith(".npz"):
        name = from_file.name
    where = Path(meta["ct_dir"]).name if meta.get("ct_dir") else ""
    label = (
        f"{name} ({n} CT kidneys{f' of {where}' if where else ''})"
        if real
        else f"{name} ({n} generated kidneys)"
        if n
        else name
    )
    return {
        "spec": spec,
        "file": str(from_file),
        "sha256": _sha256(from_file),
        "kind": "real CT" if real else "generated",
        "subjects": n,
        "cases": cases,
        "label": label,
    }


def _sha256(path) -> str | None:
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError:
        return None


def task_template(task: StudyTask, scenario):
    """The registration template of a study run: its ``template_variant`` of the scenario's
    template (``loo`` leaves the run's own training patient out)."""
    variant = task.template_variant
    return template_variant(
        scenario.localization.template,
        variant,
        str(task.patient) if variant == "loo" else "",
        scenario.patient.side,
    )


def template_distance(template, kp) -> float:
    """Symmetric mean nearest-neighbour distance (m) between the template's points and the
    patient's true kidney surface, both in their canonical frames K."""
    v = np.asarray(kp.patient.kidney_mesh.vertices, float)
    X_KB = kp.X_BK_true.inverse()
    p_K = X_KB.multiply(kp.X_BPt.multiply(v.T)).T
    a = cKDTree(p_K).query(template.points)[0].mean()
    b = cKDTree(template.points).query(p_K)[0].mean()
    return float(0.5 * (a + b))


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
