"""``python -m benchmarks real_kidneys`` on tiny synthetic KiTS-layout cases: the cases in
sorted order, a case without the requested kidney skipped with its reason, the scans' rows
in case order, the JSON totals, a real template built without the benchmarked cases, and
bad input as one line with exit status 2. The scan itself is stubbed (a closed-loop scan
takes minutes; it is measured by the benchmark, not by the tests)."""

import functools
import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
from conftest import stored_as, synthetic_ct_case

from benchmarks import real_kidneys
from drake_rus.scenario import LoadScenario
from drake_rus.template import ct
from drake_rus.template.io import load_template

FAST = ct.CtTemplateOptions(n=1, n_points=300, voxel=0.002)


def _write_case(folder, drop_right=False, tumour=True):
    """A synthetic case written like KiTS (in-plane, in-plane, slices head to foot);
    ``drop_right``: without its right kidney (and its tumour)."""
    labels, spacing, _ = synthetic_ct_case(tumour=tumour)
    if drop_right:  # axes of A: x (left) first; the right kidney lies at x < 0
        labels[: labels.shape[0] // 2] = 0
    a, sp, R = stored_as(labels, spacing, (0, 2, 1), (1, 2))
    img = sitk.GetImageFromArray(a)
    img.SetSpacing([float(s) for s in sp[::-1]])
    R_LPS_A = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    img.SetDirection([float(v) for v in (R_LPS_A @ R[:, ::-1]).ravel()])
    folder.mkdir(parents=True)
    sitk.WriteImage(img, str(folder / "segmentation.nii.gz"))


@pytest.fixture(scope="module")
def cases(tmp_path_factory):
    """case_00000: both kidneys, a tumour on the right; case_00001: no right kidney;
    case_00002: both kidneys, no tumour (builds the real template)."""
    d = tmp_path_factory.mktemp("kits")
    _write_case(d / "case_00001", drop_right=True)
    _write_case(d / "case_00000")
    _write_case(d / "case_00002", tumour=False)
    return d


@pytest.fixture
def scans(monkeypatch):
    """The scan stubbed: each job recorded, a row with known errors returned."""
    jobs = []

    def fake(job):
        jobs.append(job)
        k = len(jobs)
        return {
            "case": job["case"],
            "tumour_ml": job["tumour_ml"],
            "parenchyma_ml": job["par_ml"],
            "status": "DONE",
            "reason": "",
            "e_trans_mm": 2.0 * k,
            "e_rot_x_deg": 3.0 * k,
            "volume_ratio": 1.0 - 0.1 * k,
            "wall_s": 0.1,
        }

    monkeypatch.setattr(real_kidneys, "scan_case", fake)
    return jobs


def _json(capsys) -> dict:
    out = capsys.readouterr().out.strip().splitlines()
    return json.loads(out[-1])


def test_benchmark_json_on_two_tiny_cases(cases, scans, capsys):
    code = real_kidneys.main(["--cases", str(cases), "--limit", "2", "--workers", "0"])
    assert code == 0
    doc = _json(capsys)
    assert (doc["n"], doc["done"], doc["skipped"]) == (2, 1, 1)
    rows = doc["rows"]
    assert [r["case"] for r in rows] == ["case_00000", "case_00001"]
    assert rows[1]["status"] == "SKIPPED" and "no right kidney" in rows[1]["reason"]
    # The scanned case: its right kidney, with its tumour (16 mm radius: 17 mL).
    (job,) = scans
    assert job["spec"] == f"ct:{cases / 'case_00000'}#right" and job["side"] == "right"
    assert job["template"].endswith("models/kidney_template.npz")
    assert rows[0]["tumour_ml"] == pytest.approx(4 / 3 * np.pi * 16.0**3 / 1000, rel=0.25)
    assert doc["e_trans_mm"] == {"mean": 2.0, "max": 2.0}
    assert doc["e_rot_x_deg"] == {"mean": 3.0, "max": 3.0}
    assert doc["volume_ratio"] == {"mean": 0.9, "min": 0.9}
    assert list(doc)[:6] == ["n", "done", "skipped", "statuses", "e_trans_mm", "e_rot_x_deg"]
    assert list(doc)[-1] == "rows"
    # What produced the rows: the template's bytes and the packages that shape a scan.
    shipped = Path(job["template"])
    assert doc["template"]["sha256"] == hashlib.sha256(shipped.read_bytes()).hexdigest()
    packages = doc["provenance"]["packages"]
    assert packages["onnxruntime"] and packages["open3d"] and packages["numpy"]
    assert doc["provenance"]["argv"] == ["--cases", str(cases), "--limit", "2", "--workers", "0"]


def test_an_interrupted_run_keeps_the_rows_it_has(cases, monkeypatch, capsys):
    """Ctrl-C during the second scan: the first scan's row, the second NOT RUN, the table
    and the JSON printed, exit status 1 (before, a traceback lost every finished row)."""
    calls = []

    def fake(job):
        calls.append(job["case"])
        if len(calls) == 2:
            raise KeyboardInterrupt
        return {
            "case": job["case"],
            "status": "DONE",
            "reason": "",
            "e_trans_mm": 1.5,
            "e_rot_x_deg": 2.5,
            "volume_ratio": 0.98,
            "wall_s": 0.1,
        }

    monkeypatch.setattr(real_kidneys, "scan_case", fake)
    code = real_kidneys.main(["--cases", str(cases), "--workers", "0"])
    assert code == 1
    doc = _json(capsys)
    statuses = [(r["case"], r["status"]) for r in doc["rows"]]
    assert statuses == [
        ("case_00000", "DONE"),
        ("case_00001", "SKIPPED"),
        ("case_00002", "NOT RUN"),
    ]
    assert "Ctrl-C" in doc["interrupted"] and "Ctrl-C" in doc["rows"][2]["reason"]
    assert doc["done"] == 1 and doc["e_trans_mm"] == {"mean": 1.5, "max": 1.5}


def test_benchmark_offset(cases, scans, capsys):
    """--offset skips the first cases (held-out runs), in sorted order."""
    assert real_kidneys.main(["--cases", str(cases), "--offset", "2", "--workers", "0"]) == 0
    doc = _json(capsys)
    assert [r["case"] for r in doc["rows"]] == ["case_00002"] and doc["done"] == 1
    assert real_kidneys.main(["--cases", str(cases), "--offset", "3", "--workers", "0"]) == 2
    assert "--offset" in capsys.readouterr().err


def test_benchmark_left_side_and_totals(cases, scans, capsys):
    """--side left scans the left kidneys (every case has one); the totals are over the
    DONE scans in case order."""
    code = real_kidneys.main(["--cases", str(cases), "--side", "left", "--workers", "0"])
    assert code == 0
    doc = _json(capsys)
    assert (doc["n"], doc["done"], doc["skipped"]) == (3, 3, 0)
    assert [j["case"] for j in scans] == ["case_00000", "case_00001", "case_00002"]
    assert all(j["spec"].endswith("#left") and j["side"] == "left" for j in scans)
    assert doc["e_trans_mm"] == {"mean": 4.0, "max": 6.0}
    assert doc["volume_ratio"] == {"mean": 0.8, "min": 0.7}
    assert all(r["tumour_ml"] == 0.0 for r in doc["rows"])


def test_benchmark_real_template_leaves_out_the_benchmarked_cases(
    cases, scans, capsys, monkeypatch
):
    monkeypatch.setattr(
        real_kidneys, "resolve_template", functools.partial(ct.resolve_template, opts=FAST)
    )
    code = real_kidneys.main(
        ["--cases", str(cases), "--limit", "2", "--template", "real", "--workers", "0"]
    )
    assert code == 0
    doc = _json(capsys)
    assert doc["template"]["cases"] == ["case_00002"]
    assert load_template(scans[0]["template"]).meta["cases"] == ["case_00002"]


def test_benchmark_bad_input(tmp_path, capsys):
    assert real_kidneys.main(["--cases", str(tmp_path / "none")]) == 2
    assert "--cases" in capsys.readouterr().err
    assert real_kidneys.main(["--cases", str(tmp_path), "--limit", "0"]) == 2
    assert "--limit" in capsys.readouterr().err
    assert real_kidneys.main(["--cases", str(tmp_path), "--workers", "-1"]) == 2
    assert "--workers" in capsys.readouterr().err
    assert real_kidneys.main(["--cases", str(tmp_path), "--offset", "-1"]) == 2
    assert "--offset" in capsys.readouterr().err


def test_a_patient_that_cannot_be_built_is_skipped_not_an_error(monkeypatch):
    """scan_row: an exception of a ``skip`` type (a CT kidney that fits no body) makes the
    case SKIPPED with its message; any other exception stays an ERROR with its traceback."""
    from benchmarks import _scan_rows
    from drake_rus.anatomy.ct_patient import CtKidneyDoesNotFit

    def raise_(exc):
        def f(*a, **k):
            raise exc

        return f

    monkeypatch.setattr(_scan_rows, "load_patient", raise_(CtKidneyDoesNotFit("too wide")))
    from drake_rus.scenario import LoadScenario

    s = LoadScenario()
    row = _scan_rows.scan_row({}, "ct:x", s, "{}", None, 1.0, skip=(CtKidneyDoesNotFit,))
    assert row["status"] == "SKIPPED" and row["reason"] == "too wide"
    assert "traceback" not in row
    row = _scan_rows.scan_row({}, "ct:x", s, "{}", None, 1.0)
    assert row["status"] == "ERROR" and "traceback" in row
    monkeypatch.setattr(_scan_rows, "load_patient", raise_(RuntimeError("boom")))
    row = _scan_rows.scan_row({}, "ct:x", s, "{}", None, 1.0, skip=(CtKidneyDoesNotFit,))
    assert row["status"] == "ERROR" and row["reason"] == "RuntimeError: boom"


def test_benchmark_scenario_overrides(cases, scans, capsys):
    """--set reaches every scan and the JSON; bad text or the template field is refused
    with one line naming --set, before any scan."""
    text = "{imaging: {segmenter: oracle}}"
    code = real_kidneys.main(
        ["--cases", str(cases), "--limit", "1", "--workers", "0", "--set", text]
    )
    assert code == 0
    assert _json(capsys)["overrides"] == text
    assert [j["overrides"] for j in scans] == [text]
    assert [j["scenario"] for j in scans] == ["default"]
    for args, word in [
        (["--set", "{imaging: {segmenter: foo}}"], "imaging.segmenter"),
        (["--set", "{localization: {template: real}}"], "--template"),
        (["--scenario", "no_such_scenario"], "no_such_scenario"),
    ]:
        scans.clear()
        assert real_kidneys.main(["--cases", str(cases), "--workers", "0", *args]) == 2
        err = capsys.readouterr().err
        assert err.startswith(("--set: ", "--scenario/--set: ")) and word in err
        assert len(err.strip().splitlines()) == 1 and scans == []


def test_scan_case_applies_the_overrides(monkeypatch):
    """The worker builds its scenario from the job's --set text."""
    seen = {}

    def fake_scan_row(row, spec, scenario, overrides, template, *a, **k):
        seen["segmenter"] = scenario.imaging.segmenter
        return row

    import benchmarks._scan_rows as scan_rows

    monkeypatch.setattr(scan_rows, "scan_row", fake_scan_row)
    job = {
        "case": "case_00000",
        "tumour_ml": 0.0,
        "par_ml": 100.0,
        "template": str(ct.resolve_template("generated")),
        "spec": "ct:x#right",
        "side": "right",
        "max_sim_time": 1.0,
        "out": None,
        "overrides": "{imaging: {segmenter: oracle}}",
    }
    real_kidneys.scan_case(job)
    assert seen["segmenter"] == "oracle"
    real_kidneys.scan_case({**job, "overrides": None})
    assert seen["segmenter"] == "onnx"
    real_kidneys.scan_case({**job, "overrides": None, "scenario": "seed_method"})
    assert seen["segmenter"] == LoadScenario(scenario_name="seed_method").imaging.segmenter
