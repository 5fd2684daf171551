"""On-disk cache of generated and imported patients (used by
:func:`~drake_rus.anatomy.load_patient`).

Building a patient's 1 mm label volume takes seconds (generated) to tens of seconds (imported
meshes); every scan of ``test:0`` built the same one again. An entry holds what a
:class:`Patient` is made of: the kidney, skin and liver meshes, ``X_PtK``, the metadata, the
torso-section centre and, once it was built, the label volume. Patients loaded from the cache
are equal to freshly built ones (same arrays, same metrics); their lazily built parts (torso
section, kidney mask) are rebuilt by the same code.

Content addressed: an entry's name is the SHA-256 of its inputs (the patient spec resolved to
a generator seed or to the bytes of the imported files; side, posture, voxel size, mapping),
of the source code of :mod:`drake_rus.anatomy` (the canonical frame included), and of the
versions of the libraries that shape the result. Any change gives another name; stale entries
are never read (delete the folder to reclaim the space).

Where: ``$DRAKE_RUS_CACHE_DIR`` if set, else ``$XDG_CACHE_HOME/drake_rus/patients``, else
``~/.cache/drake_rus/patients``. Entries are written to a temporary file and renamed, so a
crash never leaves a half-written entry under an entry's name; an unreadable entry is ignored
(one warning) and rebuilt; a cache folder that cannot be written is skipped with a warning.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import tempfile
import time
from functools import lru_cache
from importlib import metadata
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh
from pydrake.math import RigidTransform

from drake_rus.anatomy.labels import LabelVolume
from drake_rus.anatomy.patient import Patient

__all__ = [
    "CACHE_DIR_ENV",
    "patient_cache_dir",
    "cached_patient",
    "file_digest",
    "code_digest",
    "entry_path",
]

log = logging.getLogger(__name__)

CACHE_DIR_ENV = "DRAKE_RUS_CACHE_DIR"
FORMAT = 1  # bump when the entry layout changes
_SUFFIX = ".npz"
_TMP_PREFIX = ".tmp-"
_STALE_TMP_S = 3600.0  # leftovers of crashed writers older than this are removed
_LIBRARIES = ("numpy", "scipy", "trimesh", "scikit-image", "drake", "SimpleITK", "matplotlib")
_ANATOMY_DIR = Path(__file__).resolve().parent
_warned_dirs: set[str] = set()
_UMASK = os.umask(0o022)
os.umask(_UMASK)


def user_cache_home() -> Path:
    """``$XDG_CACHE_HOME/drake_rus``, else ``~/.cache/drake_rus``: the project's caches."""
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg).expanduser() if xdg else Path.home() / ".cache"
    return base / "drake_rus"


def patient_cache_dir() -> Path:
    """``$DRAKE_RUS_CACHE_DIR``, else ``$XDG_CACHE_HOME/drake_rus/patients``, else
    ``~/.cache/drake_rus/patients`` (not created here)."""
    env = os.environ.get(CACHE_DIR_ENV)
    if env:
        return Path(env).expanduser()
    return user_cache_home() / "patients"


def detached_data_files(path) -> list[Path]:
    """The voxel files a detached image header names, beside it: a MetaImage ``.mhd``'s
    ``ElementDataFile`` or an NRRD ``.nhdr``'s ``data file``; [] for any other file and for
    inline data (``LOCAL``). A list or pattern of files is not followed."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".mhd", ".nhdr"):
        return []
    keys = ("elementdatafile",) if suffix == ".mhd" else ("data file", "datafile")
    sep = "=" if suffix == ".mhd" else ":"
    try:
        text = path.read_text(errors="replace")
    except OSError:
        return []
    for line in text.splitlines():
        key, found, value = line.partition(sep)
        if found and key.strip().lower() in keys:
            name = value.strip()
            if not name or name.upper() in ("LOCAL", "LIST") or " " in name or "%" in name:
                return []
            return [path.parent / name]
    return []


def file_digest(path) -> str:
    """SHA-256 of a file's bytes, and of the voxel file a detached header names
    (:func:`detached_data_files`): a changed ``.raw`` beside an ``.mhd`` changes it."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    for data in detached_data_files(path):
        if data.is_file():
            h.update(b"\0" + data.name.encode() + b"\0")
            with open(data, "rb") as f:
                for block in iter(lambda: f.read(1 << 20), b""):
                    h.update(block)
    return h.hexdigest()


@lru_cache(maxsize=1)
def code_digest() -> str:
    """SHA-256 of the source of drake_rus/anatomy/*.py (the code a patient is built by, the
    canonical frame included), read once per process: the code that is running."""
    h = hashlib.sha256()
    files = sorted(_ANATOMY_DIR.rglob("*.py"))
    for p in files:
        h.update(p.relative_to(_ANATOMY_DIR.parent).as_posix().encode() + b"\0")
        h.update(p.read_bytes() + b"\0")
    return h.hexdigest()


@lru_cache(maxsize=8)
def library_versions(names: tuple = _LIBRARIES) -> dict:
    """Installed version of each distribution in ``names`` (None when not installed): part
    of the cache keys, so a library update rebuilds what it may change."""
    out = {}
    for name in names:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def _key(inputs: dict) -> tuple[str, str]:
    doc = json.dumps(
        {
            "format": FORMAT,
            "inputs": inputs,
            "code": code_digest(),
            "libraries": library_versions(),
        },
        sort_keys=True,
    )
    return hashlib.sha256(doc.encode()).hexdigest(), doc


def entry_path(inputs: dict) -> Path:
    """Where the entry of ``inputs`` lives (it may not exist)."""
    return patient_cache_dir() / (_key(inputs)[0] + _SUFFIX)


# --- entries -------------------------------------------------------------------------------
def _parts(patient: Patient, key: str, inputs: dict) -> dict:
    """The arrays of an entry without the label volume (taken when the patient is built:
    later changes of the patient's meta do not reach the cache)."""
    meta_json = json.dumps(patient.meta, sort_keys=True)
    if json.loads(meta_json) != patient.meta:
        raise TypeError("the patient's meta does not survive JSON (tuples or numpy values)")
    header = {
        "format": FORMAT,
        "key": key,
        "inputs": inputs,
        "name": patient.name,
        "side": patient.side,
        "posture": patient.posture,
    }
    arrays = {
        "header": np.array(json.dumps(header, sort_keys=True)),
        "meta": np.array(meta_json),
        "X_PtK": patient.X_PtK.GetAsMatrix4(),
        "kidney_vertices": np.array(patient.kidney_mesh.vertices, dtype=float),
        "kidney_faces": np.array(patient.kidney_mesh.faces),
        "skin_vertices": np.array(patient.skin_mesh.vertices, dtype=float),
        "skin_faces": np.array(patient.skin_mesh.faces),
    }
    if patient.liver_mesh is not None:
        arrays["liver_vertices"] = np.array(patient.liver_mesh.vertices, dtype=float)
        arrays["liver_faces"] = np.array(patient.liver_mesh.faces)
    if patient.torso_center_Pt is not None:
        arrays["torso_center_Pt"] = np.array(patient.torso_center_Pt, dtype=float)
    return arrays


def _label_arrays(lv: LabelVolume) -> dict:
    return {
        "labels": np.ascontiguousarray(lv.labels),
        "labels_X_PtV": lv.X_PtV.GetAsMatrix4(),
        "labels_voxel_size": np.array(float(lv.voxel_size)),
    }


def _write(path: Path, arrays: dict) -> bool:
    """Writes an entry atomically (temporary file in the same folder, then rename). False,
    with a warning, if the folder cannot be written."""
    folder = path.parent
    tmp = None
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=_TMP_PREFIX, suffix=_SUFFIX, dir=str(folder))
        os.chmod(tmp, 0o666 & ~_UMASK)  # like any other file (mkstemp gives 0600)
        with os.fdopen(fd, "wb") as f:
            np.savez_compressed(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        tmp = None
    except Exception as e:  # unwritable folder, disk full, ...: never an error
        if str(folder) not in _warned_dirs:
            _warned_dirs.add(str(folder))
            why = getattr(e, "strerror", None) or (str(e).strip().splitlines() or [""])[0]
            log.warning(
                "patient cache: cannot write to %s (%s: %s); going on without the cache",
                folder,
                type(e).__name__,
                why,
            )
        return False
    finally:
        if tmp is not None:
            try:
                os.remove(tmp)
            except OSError:
                pass
    _remove_stale_temporaries(folder)
    return True


def _remove_stale_temporaries(folder: Path) -> None:
    now = time.time()
    try:
        for p in folder.glob(_TMP_PREFIX + "*"):
            try:
                if now - p.stat().st_mtime > _STALE_TMP_S:
                    p.unlink()
            except OSError:
                pass
    except OSError:
        pass


def _mesh(z, name: str) -> trimesh.Trimesh:
    v, f = z[f"{name}_vertices"], z[f"{name}_faces"]
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"{name} mesh: bad array shapes {v.shape}, {f.shape}")
    return trimesh.Trimesh(v, f, process=False)


def _read(path: Path, key: str, inputs: dict, builders: dict) -> tuple[Patient, dict]:
    """The Patient of an entry and the entry's arrays without labels; raises on anything
    unexpected (the caller ignores the entry then)."""
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}  # reads (and CRC-checks) every member
    header = json.loads(str(arrays["header"]))
    if (
        header.get("format") != FORMAT
        or header.get("key") != key
        or header.get("inputs") != json.loads(json.dumps(inputs))
    ):
        raise ValueError("the entry is not the one of this key")
    meta = json.loads(str(arrays["meta"]))
    labels = None
    if "labels" in arrays:
        labels = LabelVolume(
            labels=arrays["labels"],
            voxel_size=float(arrays["labels_voxel_size"]),
            X_PtV=RigidTransform(arrays["labels_X_PtV"]),
        )
    z = arrays
    patient = Patient(
        name=header["name"],
        side=header["side"],
        posture=header["posture"],
        kidney_mesh=_mesh(z, "kidney"),
        skin_mesh=_mesh(z, "skin"),
        liver_mesh=_mesh(z, "liver") if "liver_vertices" in z else None,
        meta=meta,
        X_PtK=RigidTransform(z["X_PtK"]),
        torso_center_Pt=z.get("torso_center_Pt"),
        labels=labels,
        **builders,
    )
    base = {k: v for k, v in arrays.items() if not k.startswith("labels")}
    return patient, base


def _store_labels_when_built(patient: Patient, path: Path, base: dict) -> None:
    def store(lv: LabelVolume) -> None:
        try:
            _write(path, {**base, **_label_arrays(lv)})
        except Exception as e:  # the cache never breaks a patient
            log.warning(
                "patient cache: could not store the label volume of %s (%s)", patient.name, e
            )

    patient.on_labels_built(store)


def cached_patient(
    inputs: dict, build: Callable[[], Patient], *, builders: Callable[[], dict] | None = None
) -> Patient:
    """The patient of ``inputs`` (a JSON-able dict naming everything the patient depends on
    besides the code) from the cache, else ``build()`` stored in it.

    ``builders()`` gives the Patient keyword arguments for its lazily built parts
    (``label_builder``, ``torso_builder``, ``kidney_mask_builder``) when rebuilt from an
    entry; without it the patient's default torso section and kidney mask are used, and an
    entry without a label volume rebuilds it with ``build().labels``. The label volume is
    stored in the entry once the patient builds it (``patient.labels``).
    """
    key, _ = _key(inputs)
    path = patient_cache_dir() / (key + _SUFFIX)
    try:
        exists = path.is_file()
    except OSError:
        exists = False
    if exists:
        try:
            extra = builders() if builders is not None else {}
            if "label_builder" not in extra:
                extra = {**extra, "label_builder": lambda: build().labels}
            patient, base = _read(path, key, inputs, extra)
        except Exception as e:
            first = (str(e).strip().splitlines() or [""])[0]
            log.warning(
                "patient cache: ignoring unreadable entry %s (%s: %s); rebuilding it",
                path,
                type(e).__name__,
                first,
            )
        else:
            if not patient.has_labels:
                _store_labels_when_built(patient, path, base)
            return patient
    patient = build()
    try:
        base = _parts(patient, key, inputs)
    except TypeError as e:
        log.warning("patient cache: %s is not cached (%s)", patient.name, e)
        return patient
    arrays = {**base, **_label_arrays(patient.labels)} if patient.has_labels else base
    if _write(path, arrays) and not patient.has_labels:
        _store_labels_when_built(patient, path, base)
    return patient
