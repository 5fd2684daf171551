"""Cohorts of real CT kidneys for the studies (issue 27): ``ct:DIR:SELECTION`` patient
lists expanded into ``ct:`` patients, and the check that no patient helped build the
study's template.

- :func:`expand_ct_cohorts`: ``ct:DIR:0-14`` (case numbers and ranges joined by ``+``) is
  every such case of the folder DIR (KiTS layout, ``DIR/case_*/segmentation.nii.gz``, or
  label maps in DIR; :func:`drake_rus.template.ct.find_label_maps`), a case without a
  usable kidney on the patient's side skipped with its reason; ``ct:DIR:firstN`` is the
  first N cases in sorted order with a usable kidney that did not build the template (the
  seed paper tested on 15 CT subjects that did not build its template). Options after
  ``#`` (``#left,body=7``) and a posture suffix go to every patient.
- :func:`case_usable`: whether a label map has a usable kidney on a side (it reads, its
  frame is established from anatomy, the kidney is present and not cut by the field of
  view: :mod:`drake_rus.anatomy.ct_kidney`, the checks a ``ct:`` patient's build makes
  first), cached per file, side and code in the user cache.
- :func:`template_cases_of_patients`: the patients whose case built a template (by case
  name and by the label map's bytes, :func:`drake_rus.template.ct.split_warnings`).
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path

from drake_rus.anatomy.cache import code_digest
from drake_rus.anatomy.ct_kidney import import_ct_kidneys, read_label_grid, select_kidney
from drake_rus.anatomy.ct_patient import ct_label_map_path, parse_ct_spec
from drake_rus.experiments.specs import CT_PREFIX, ct_selection, split_posture
from drake_rus.template.ct import find_label_maps, label_map_digest, match_cases, split_warnings
from drake_rus.template.population import template_cache_dir


def _check_cache() -> Path:
    """Where usability checks are kept: beside the template cache (``ct-checks``)."""
    return template_cache_dir().parent / "ct-checks"


def case_usable(label_map, side: str) -> str:
    """ "" if the label map has a usable ``side`` kidney (it reads, its frame is established
    from anatomy, the kidney is there and not cut by the field of view), else the one-line
    reason. Cached by the file's bytes, the side and the anatomy code."""
    path = Path(label_map)
    digest = label_map_digest(path)
    key = hashlib.sha256(
        json.dumps({"file": digest, "side": side, "code": code_digest()}).encode()
    ).hexdigest()[:32]
    cache = _check_cache() / f"{key}.json"
    try:
        return str(json.loads(cache.read_text())["reason"])
    except (OSError, ValueError, KeyError, TypeError):
        pass
    try:
        select_kidney(import_ct_kidneys(read_label_grid(path)), side)
        reason = ""
    except (ValueError, FileNotFoundError) as e:
        reason = str(e)
    try:
        cache.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=".json", dir=str(cache.parent))
        with os.fdopen(fd, "w") as f:
            json.dump({"file": str(path), "side": side, "reason": reason}, f)
        os.replace(tmp, cache)
    except OSError:
        pass
    return reason


def _side_of(options: str, default_side: str) -> str:
    """The CT kidney side a ``ct:`` spec's options ask for (``right``/``left``), else the
    scenario's target side."""
    parsed = parse_ct_spec(f"{CT_PREFIX}x#{options}") if options else None
    return (parsed.ct_side if parsed is not None else None) or default_side


def _patient_of(folder: str, case: str, label_map: Path, options: str, posture: str) -> str:
    """The ``ct:`` spec of one case: its case folder in the KiTS layout (as the user wrote
    the folder), else the label map file."""
    base = folder.rstrip("/")
    where = f"{base}/{case}" if label_map.parent.name == case else f"{base}/{label_map.name}"
    return f"{CT_PREFIX}{where}" + (f"#{options}" if options else "") + posture


def expand_ct_cohorts(
    patients, side: str = "right", template_cases=(), log=None
) -> tuple[list[str], list[dict]]:
    """``patients`` with every ``ct:DIR:SELECTION`` cohort spec replaced by its ``ct:``
    patients (module doc), and the cases left out: ``[{"spec", "case", "reason"}]``.
    ``side``: the scenario's target side (a spec's ``#left``/``#right`` wins);
    ``template_cases``: case names that built the study's template (``firstN`` passes
    them by; a listed range keeps them, for :func:`template_cases_of_patients` to refuse).
    Raises ValueError naming the spec for a folder without label maps, a selection that
    matches no case, or a ``firstN`` the folder cannot fill."""
    out, skipped = [], []
    say = log or (lambda line: None)
    built = set(template_cases or ())
    for spec in patients:
        head, posture = split_posture(spec) if "@" in str(spec) else (str(spec), None)
        sel = ct_selection(head)
        if sel is None:
            out.append(spec)
            continue
        suffix = str(spec)[len(head) :]
        folder, selection, options = sel
        try:
            side_here = _side_of(options, side)
            maps = find_label_maps(folder)
        except ValueError as e:
            raise ValueError(f"--patients: {spec!r}: {e}") from None
        names = [c for c, _ in maps]
        first = selection.startswith("first")
        if first:
            want = int(selection[len("first") :])
            pool = names
        else:
            pool = match_cases(names, selection.split("+"))
            if not pool:
                raise ValueError(f"--patients: {spec!r}: no case of {folder} matches {selection}")
            want = len(pool)
        chosen = []
        for case in pool:
            if first and len(chosen) >= want:
                break
            path = dict(maps)[case]
            if first and case in built:
                skipped.append(
                    {"spec": spec, "case": case, "reason": "it helped build the template"}
                )
                continue
            reason = case_usable(path, side_here)
            if reason:
                skipped.append({"spec": spec, "case": case, "reason": reason})
                say(f"{spec}: {case} left out: {reason}")
                continue
            chosen.append(_patient_of(folder, case, path, options, suffix))
        if first and len(chosen) < want:
            raise ValueError(
                f"--patients: {spec!r}: {folder} has {len(chosen)} usable {side_here} "
                f"kidneys outside the template, {want} asked for"
            )
        if not chosen:
            raise ValueError(
                f"--patients: {spec!r}: no case of {selection} has a usable {side_here} kidney"
            )
        out.extend(chosen)
    return out, skipped


def ct_case_path(spec: str) -> Path | None:
    """The label map of a ``ct:`` patient (None for other patients or a missing file)."""
    head = split_posture(spec)[0] if "@" in str(spec) else str(spec)
    if not head.startswith(CT_PREFIX):
        return None
    try:
        return ct_label_map_path(parse_ct_spec(head).path)
    except (ValueError, FileNotFoundError):
        return None


def template_cases_of_patients(template, patients) -> list[str]:
    """One line per ``ct:`` patient whose case helped build ``template`` (a path, a Template
    or its metadata), matched by case name and by the label map's bytes
    (:func:`drake_rus.template.ct.split_warnings`): scoring it is not a test on an unseen
    kidney."""
    lines = []
    for p in patients:
        path = ct_case_path(p)
        if path is not None:
            lines += [w.replace(str(path), p) for w in split_warnings(template, [str(path)])]
    return lines
