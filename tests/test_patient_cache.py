"""The on-disk patient cache behind load_patient (drake_rus.anatomy.cache): warm loads equal
cold ones, every key input matters, broken entries and folders never break a load."""

import logging
import os

import numpy as np
import pytest
from conftest import write_small_label_map

from drake_rus.anatomy import cache as cache_mod
from drake_rus.anatomy import cohort, generator, load_patient
from drake_rus.anatomy.cache import CACHE_DIR_ENV, entry_path, patient_cache_dir

VOXEL = 0.004  # coarse label volumes keep these tests fast


@pytest.fixture
def cache_dir(tmp_path, monkeypatch):
    d = tmp_path / "patients"
    monkeypatch.setenv(CACHE_DIR_ENV, str(d))
    return d


@pytest.fixture
def builds(monkeypatch):
    """Counts the generator runs behind load_patient."""
    calls = []
    real = cohort.generate_patient

    def counting(*args, **kwargs):
        calls.append(args)
        return real(*args, **kwargs)

    monkeypatch.setattr(cohort, "generate_patient", counting)
    return calls


def _entries(d):
    return sorted(p.name for p in d.iterdir()) if d.is_dir() else []


def assert_same_patient(p, q, labels=True):
    assert (p.name, p.side, p.posture) == (q.name, q.side, q.posture)
    for a, b in ((p.kidney_mesh, q.kidney_mesh), (p.skin_mesh, q.skin_mesh)):
        np.testing.assert_array_equal(a.vertices, b.vertices)
        np.testing.assert_array_equal(a.faces, b.faces)
    np.testing.assert_array_equal(p.X_PtK.GetAsMatrix4(), q.X_PtK.GetAsMatrix4())
    assert p.meta == q.meta
    assert p.metrics() == q.metrics()
    if labels:
        assert p.labels.labels.dtype == q.labels.labels.dtype
        np.testing.assert_array_equal(p.labels.labels, q.labels.labels)
        assert p.labels.voxel_size == q.labels.voxel_size
        np.testing.assert_array_equal(p.labels.X_PtV.GetAsMatrix4(), q.labels.X_PtV.GetAsMatrix4())


def test_cache_dir_resolution(monkeypatch, tmp_path):
    monkeypatch.setenv(CACHE_DIR_ENV, str(tmp_path / "c"))
    assert patient_cache_dir() == tmp_path / "c"
    monkeypatch.delenv(CACHE_DIR_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert patient_cache_dir() == tmp_path / "xdg" / "drake_rus" / "patients"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert patient_cache_dir() == tmp_path / "home" / ".cache" / "drake_rus" / "patients"


def test_warm_load_equals_cold_and_fresh(cache_dir, builds, monkeypatch):
    # Without the anatomy check (which reads the label volume) the volume stays lazy.
    cold = load_patient("seed:5", voxel_size=VOXEL, progress=False, check=False)
    assert not cold.has_labels  # still lazy for callers that never ask
    assert len(_entries(cache_dir)) == 1
    cold_labels = cold.labels  # built now, and stored in the entry
    assert len(builds) == 1

    # A warm load neither runs the generator nor builds labels: they come from the entry.
    def no_labels(*a, **k):
        raise AssertionError("label volume rebuilt on a warm load")

    with monkeypatch.context() as m:
        m.setattr(generator, "_build_labels", no_labels)
        warm = load_patient("seed:5", voxel_size=VOXEL, progress=False)
        assert len(builds) == 1 and warm.has_labels
        assert warm.labels.labels is not cold_labels.labels
    fresh = load_patient("seed:5", voxel_size=VOXEL, progress=False, cache=False)
    assert_same_patient(warm, cold)
    assert_same_patient(warm, fresh)
    # The lazily built parts of a cached patient are the generator's.
    np.testing.assert_array_equal(
        warm.torso_section(0.12).vertices, fresh.torso_section(0.12).vertices
    )
    (m1, X1), (m2, X2) = warm.kidney_mask(0.003), fresh.kidney_mask(0.003)
    np.testing.assert_array_equal(m1, m2)
    np.testing.assert_array_equal(X1.GetAsMatrix4(), X2.GetAsMatrix4())
    assert len(_entries(cache_dir)) == 1  # no temporary files left


def test_entry_without_labels_gets_them_on_a_warm_load(cache_dir, builds):
    load_patient("seed:6", voxel_size=VOXEL, progress=False, check=False)  # no labels
    warm = load_patient("seed:6", voxel_size=VOXEL, progress=False, check=False)
    assert not warm.has_labels and len(builds) == 1
    labels = warm.labels.labels  # built from the seed, then stored
    third = load_patient("seed:6", voxel_size=VOXEL, progress=False)
    assert third.has_labels and len(builds) == 1
    np.testing.assert_array_equal(third.labels.labels, labels)
    assert_same_patient(
        third, load_patient("seed:6", voxel_size=VOXEL, cache=False, progress=False)
    )


@pytest.mark.parametrize(
    "change",
    [
        {"spec": "seed:8"},
        {"posture": "left_lateral_decubitus"},
        {"voxel_size": 0.005},
        {"side": "left"},
        {"spec": "seed:0000007"},
    ],
    ids=["seed", "posture", "voxel", "side", "spec_spelling"],
)
def test_changed_key_input_misses(cache_dir, builds, change):
    base = {"spec": "seed:7", "voxel_size": VOXEL}
    load_patient(**base, progress=False)
    load_patient(**base, progress=False)
    assert len(builds) == 1
    other = load_patient(**{**base, **change}, progress=False)
    assert len(builds) == 2 and len(_entries(cache_dir)) == 2
    if "spec" in change:
        assert other.name == change["spec"]
    if "voxel_size" in change:
        assert other.labels.voxel_size == change["voxel_size"]


def test_code_change_misses(cache_dir, builds, monkeypatch):
    load_patient("seed:7", voxel_size=VOXEL, progress=False)
    monkeypatch.setattr(cache_mod, "code_digest", lambda: "other code")
    load_patient("seed:7", voxel_size=VOXEL, progress=False)
    assert len(builds) == 2 and len(_entries(cache_dir)) == 2


@pytest.mark.parametrize("damage", ["truncate", "garbage", "empty", "other_entry"])
def test_corrupt_entry_is_rebuilt(cache_dir, builds, caplog, damage):
    ref = load_patient("seed:9", voxel_size=VOXEL, progress=False)
    ref.labels
    path = entry_path(
        {
            "kind": "generator",
            "seed": 9,
            "spec": "seed:9",
            "side": "right",
            "posture": "supine",
            "voxel_size": VOXEL,
        }
    )
    assert path.is_file()
    data = path.read_bytes()
    if damage == "truncate":
        path.write_bytes(data[: len(data) // 2])
    elif damage == "garbage":
        path.write_bytes(b"\x00 not a cache entry" * 100)
    elif damage == "empty":
        path.write_bytes(b"")
    else:  # a valid entry of another patient under this name
        load_patient("seed:10", voxel_size=VOXEL, progress=False)
        other = next(p for p in cache_dir.iterdir() if p != path)
        path.write_bytes(other.read_bytes())
    n = len(builds)
    with caplog.at_level(logging.WARNING, logger="drake_rus.anatomy.cache"):
        p = load_patient("seed:9", voxel_size=VOXEL, progress=False)
    assert len(builds) == n + 1
    warnings = [r for r in caplog.records if "unreadable entry" in r.getMessage()]
    assert len(warnings) == 1 and "\n" not in warnings[0].getMessage()
    assert_same_patient(p, ref)  # builds (and stores) the labels again
    again = load_patient("seed:9", voxel_size=VOXEL, progress=False)  # the entry is good
    assert len(builds) == n + 1 and again.has_labels
    assert_same_patient(again, ref)


def test_failed_write_leaves_no_entry(cache_dir, builds, monkeypatch, caplog):
    """A writer that dies half-way leaves no entry (and no temporary file) behind."""

    def crash(f, **arrays):
        f.write(b"PK\x03\x04 half an entry")
        raise OSError(28, "No space left on device")

    with (
        monkeypatch.context() as m,
        caplog.at_level(logging.WARNING, logger="drake_rus.anatomy.cache"),
    ):
        m.setattr(cache_mod.np, "savez_compressed", crash)
        p = load_patient("seed:11", voxel_size=VOXEL, progress=False)
        p.labels
    assert "No space left" in caplog.text
    assert _entries(cache_dir) == []
    (cache_dir / ".tmp-leftover.npz").write_bytes(b"from a crashed writer")
    q = load_patient("seed:11", voxel_size=VOXEL, progress=False)
    assert len(builds) == 2
    assert_same_patient(p, q)


@pytest.mark.parametrize("where", ["file", "under_file"])
def test_unusable_cache_dir_does_not_fail(tmp_path, monkeypatch, caplog, where):
    blocker = tmp_path / "blocker"
    blocker.write_text("not a folder")
    d = blocker if where == "file" else blocker / "patients"
    monkeypatch.setenv(CACHE_DIR_ENV, str(d))
    with caplog.at_level(logging.WARNING, logger="drake_rus.anatomy.cache"):
        p = load_patient("seed:12", voxel_size=VOXEL, progress=False)
        p.labels
        q = load_patient("seed:12", voxel_size=VOXEL, progress=False)
    assert "cannot write" in caplog.text
    assert blocker.read_text() == "not a folder"
    assert_same_patient(p, q)


def test_unwritable_cache_dir_does_not_fail(cache_dir, monkeypatch, caplog):
    def denied(*a, **k):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(cache_mod.tempfile, "mkstemp", denied)
    with caplog.at_level(logging.WARNING, logger="drake_rus.anatomy.cache"):
        p = load_patient("seed:12", voxel_size=VOXEL, progress=False)
    assert "Permission denied" in caplog.text and p.name == "seed:12"
    assert _entries(cache_dir) == []


def test_cache_false_writes_nothing(cache_dir, builds):
    p = load_patient("seed:13", voxel_size=VOXEL, progress=False, cache=False)
    p.labels
    assert not cache_dir.exists()
    load_patient("seed:13", voxel_size=VOXEL, progress=False)
    load_patient("seed:13", voxel_size=VOXEL, progress=False, cache=False)
    assert len(builds) == 3  # cache=False never reads either


_write_label_map = write_small_label_map


def test_imported_patient_keyed_by_file_bytes(cache_dir, tmp_path, monkeypatch):
    path = tmp_path / "seg.nrrd"
    _write_label_map(path)
    calls = []
    real = cohort.patient_from_label_map

    def counting(*a, **k):
        calls.append(a)
        return real(*a, **k)

    monkeypatch.setattr(cohort, "patient_from_label_map", counting)
    cold = load_patient(str(path), voxel_size=VOXEL)
    cold.labels
    warm = load_patient(str(path), voxel_size=VOXEL)
    assert len(calls) == 1 and warm.has_labels
    assert_same_patient(warm, cold)
    np.testing.assert_array_equal(warm.torso_center_Pt, cold.torso_center_Pt)
    np.testing.assert_array_equal(
        warm.torso_section(0.05).vertices, cold.torso_section(0.05).vertices
    )
    assert_same_patient(warm, load_patient(str(path), voxel_size=VOXEL, cache=False))
    assert len(calls) == 2
    # Same size and modification time, other bytes: a miss.
    data = bytearray(path.read_bytes())
    st = path.stat()
    data[-1] ^= 0xFF
    path.write_bytes(bytes(data))
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert path.stat().st_size == st.st_size
    load_patient(str(path), voxel_size=VOXEL)
    assert len(calls) == 3
    # The mapping is part of the key of label maps.
    load_patient(str(path), voxel_size=VOXEL, mapping={2: "kidney_right", 200: "body"})
    assert len(calls) == 4
