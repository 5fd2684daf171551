"""Studies on real CT kidneys (issue 27): ``ct:DIR:0-14`` / ``ct:DIR:firstN`` patient lists,
the refusal of patients whose case built the template, ``--template`` in run ids, records
and side-by-side reports, the patient kind ``ct`` grouped apart, the learned segmenter as
the closed-loop default with the oracle labelled, and the template study's mixed postures.
Synthetic KiTS-layout label maps in tmp (no data needed); one tiny real kinematic study."""

import json

import numpy as np
import pytest
import SimpleITK as sitk
from conftest import stored_as, synthetic_ct_case

from drake_rus.cli import main
from drake_rus.experiments import analysis, keys, report, specs
from drake_rus.experiments import cli as study_cli
from drake_rus.experiments import results as study_results
from drake_rus.experiments.ct_cohort import (
    case_usable,
    expand_ct_cohorts,
    template_cases_of_patients,
)
from drake_rus.template.ct import label_map_digest
from drake_rus.template.io import DEFAULT_TEMPLATE_PATH


def _write_case(folder, drop_right=False, **case):
    """A synthetic case written like KiTS (in-plane, in-plane, slices head to foot);
    ``drop_right``: without its right kidney (a nephrectomy)."""
    labels, spacing, _ = synthetic_ct_case(**case)
    if drop_right:  # grid axis 0 runs right -> left
        labels = labels.copy()
        labels[: labels.shape[0] // 2] = 0
    a, sp, R = stored_as(labels, spacing, (0, 2, 1), (1, 2))
    img = sitk.GetImageFromArray(a)
    img.SetSpacing([float(s) for s in sp[::-1]])
    R_LPS_A = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    img.SetDirection([float(v) for v in (R_LPS_A @ R[:, ::-1]).ravel()])
    folder.mkdir(parents=True)
    sitk.WriteImage(img, str(folder / "segmentation.nii.gz"))


@pytest.fixture(scope="module")
def kits(tmp_path_factory):
    """Three cases: 0 with a tumour, 1 without a right kidney, 2 tumour-free."""
    root = tmp_path_factory.mktemp("kits")
    _write_case(root / "case_00000", tumour=True)
    _write_case(root / "case_00001", drop_right=True, tumour=False)
    _write_case(root / "case_00002", tumour=False)
    return root


def _template_built_from(tmp_path, root, case):
    """The shipped template's arrays under metadata saying ``case`` of ``root`` built it."""
    with np.load(DEFAULT_TEMPLATE_PATH) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["metadata"]))
    path = root / case / "segmentation.nii.gz"
    meta.update(
        ct_dir=str(root),
        split=f"ct:{root}",
        subjects_used=[{"case": case, "side": "right", "digest": label_map_digest(path)}],
    )
    arrays["metadata"] = np.asarray(json.dumps(meta))
    out = tmp_path / "from_case.npz"
    np.savez_compressed(out, **arrays)
    return out


def _fake_run(calls):
    """A stand-in for run_task: errors that fall with ER, the record a real run carries."""

    def run(task):
        calls.append(task)
        e = 2.0 + 8.0 * (1.0 - task.er) + 0.3 * (len(calls) % 3)
        return {
            "run_id": keys.run_id(task),
            "task": task.to_dict(),
            "mode": task.mode,
            "patient": task.patient,
            "er": task.er,
            "start": task.start,
            "er_unit": task.er_unit,
            "kidney_length_mm": 110.0,
            "points": 100,
            "e_trans_mm": e,
            "e_rot_x_deg": e + 1.0,
            "registration_ms": 1.0,
            "inputs_sha256": keys.task_inputs_digest(task),
            "patient_kind": specs.patient_kind(task.patient),
        }

    return run


def _study(*argv):
    return main(["study", *argv, "--workers", "0", "--no-progress"])


# ------------------------------------------------------------------------------- specs
@pytest.mark.parametrize(
    "text,want",
    [
        ("ct:DIR:0-14", ("DIR", "0-14", "")),
        ("ct:../k/kits19:first15", ("../k/kits19", "first15", "")),
        ("ct:DIR:0-4+9#left,body=7", ("DIR", "0-4+9", "left,body=7")),
        ("ct:DIR/case_00003#left", None),
        ("ct:DIR/case_00003", None),
        ("ct:DIR:firsts", None),
        ("test:3", None),
    ],
)
def test_a_ct_cohort_spec(text, want):
    assert specs.ct_selection(text) == want


def test_cohort_specs_pass_through_the_patient_list():
    got = specs.expand_patients("ct:D:0-2#left,body=7;ct:D:first3@decubitus,test:0")
    assert got == ["ct:D:0-2#left,body=7", "ct:D:first3@decubitus", "test:0"]
    with pytest.raises(ValueError, match=r"--patients: 'ct:D:first0' selects no case"):
        specs.expand_patients("ct:D:first0")


def test_ct_patients_are_their_own_kind():
    assert specs.patient_kind("ct:D/case_00003#left") == "ct"
    assert specs.patient_kind("ct:D/case_00003@decubitus") == "ct"
    assert specs.patient_kind("test:3") == "generated"
    assert specs.patient_kind("../shared/anatomy/hubmap_vh_female") == "real"
    assert specs.PATIENT_KINDS["ct"] == "real CT kidney in a generated body"
    runs = [
        {"patient": "test:1", "template_variant": "mean"},
        {"patient": "ct:D/case_00000", "template_variant": "mean"},
        {
            "patient": "ct:D/case_00002",
            "template_variant": "mean",
            "posture": "left_lateral_decubitus",
        },
        {"patient": "../x/hubmap_vh_female", "template_variant": "mean"},
    ]
    groups = [analysis.template_group(r) for r in runs]
    assert groups == [
        "generated",
        "real CT kidneys",
        "real CT kidneys, decubitus",
        "hubmap_vh_female",
    ]
    assert [analysis.group_kind(g) for g in groups] == ["generated", "ct", "ct", "real"]
    # The template study's tables: generated, then the CT kidneys together, then each body.
    for r, d in zip(runs, (2.0, 5.0, 6.0, 7.0)):
        r.update(template_distance_mm=d, e_trans_mm=d, e_rot_x_deg=d, er=0.6)
    an = analysis.analyze_template(runs)
    assert an["groups"] == groups
    # Bins 0-3, 5-7, 7- mm: the CT kidneys counted apart from the real body.
    assert [(b["ct_runs"], b["real_runs"]) for b in an["bins"]] == [(0, 0), (2, 0), (0, 1)]


# ------------------------------------------------------------------------------- cohorts
def test_cohorts_expand_in_case_order_leaving_out_unusable_kidneys(kits):
    folder = str(kits)
    got, left = expand_ct_cohorts([f"ct:{folder}:0-2#body=5"], "right")
    assert got == [f"ct:{folder}/case_00000#body=5", f"ct:{folder}/case_00002#body=5"]
    assert [x["case"] for x in left] == ["case_00001"]
    assert "no right kidney" in left[0]["reason"]
    # firstN: the first N usable cases, passing by those that built the template.
    got, left = expand_ct_cohorts([f"ct:{folder}:first1@decubitus"], "right", ["case_00000"])
    assert got == [f"ct:{folder}/case_00002@decubitus"]
    assert left[0] == {
        "spec": f"ct:{folder}:first1@decubitus",
        "case": "case_00000",
        "reason": "it helped build the template",
    }
    # The left kidney of the case without a right one is usable; other specs pass through.
    got, left = expand_ct_cohorts(["test:0", f"ct:{folder}:1#left"], "right")
    assert got == ["test:0", f"ct:{folder}/case_00001#left"] and not left
    assert case_usable(kits / "case_00001" / "segmentation.nii.gz", "left") == ""
    with pytest.raises(ValueError, match=r"has 2 usable right kidneys outside the template, 5"):
        expand_ct_cohorts([f"ct:{folder}:first5"], "right")
    with pytest.raises(ValueError, match=r"no case of .* matches 7-9"):
        expand_ct_cohorts([f"ct:{folder}:7-9"], "right")
    with pytest.raises(ValueError, match=r"nothing: not a folder"):
        expand_ct_cohorts([f"ct:{kits / 'nothing'}:0"], "right")


def test_a_case_that_built_the_template_is_named(kits, tmp_path):
    template = _template_built_from(tmp_path, kits, "case_00000")
    lines = template_cases_of_patients(
        template, [f"ct:{kits}/case_00000#body=5", f"ct:{kits}/case_00002", "test:1"]
    )
    assert len(lines) == 1 and "case case_00000 helped build it" in lines[0]
    assert f"ct:{kits}/case_00000#body=5" in lines[0]


def test_the_study_refuses_patients_of_its_template(kits, tmp_path, capsys, monkeypatch):
    calls = []
    monkeypatch.setattr(study_cli, "run_task", _fake_run(calls))
    template = _template_built_from(tmp_path, kits, "case_00000")
    out = tmp_path / "study"
    common = ["er-sweep", "--ers", "0.6,1", "--template", str(template), "--out", str(out)]
    assert _study(*common, "--patients", f"ct:{kits}:0-2") == 2
    err = capsys.readouterr().err
    assert "--template: 1 patient(s) helped build the template" in err and not out.exists()
    # firstN passes the template's case by.
    assert _study(*common, "--patients", f"ct:{kits}:first1") == 0
    assert [t.patient for t in calls] == [f"ct:{kits}/case_00002"] * 2
    assert all(t.template == str(template) and t.template_file for t in calls)
    # Asked for anyway: run, and the report says so.
    assert _study(*common, "--patients", f"ct:{kits}:0", "--allow-template-cases") == 0
    tag = keys.template_tag(str(template))
    text = (out / f"template-{tag[4:]}" / "report.md").read_text()
    assert "Warning: 1 patient(s) helped build the template" in text
    assert "CT cases left out" not in text


def test_patients_of_several_kinds_are_refused_but_by_the_template_study(kits, capsys):
    assert _study("er-sweep", "--patients", f"test:0,ct:{kits}:2", "--out", "/nonexistent/x") == 2
    err = capsys.readouterr().err
    assert "--patients: the paper's studies compare patients of one kind" in err
    assert "1 real CT kidney in a generated body" in err


# ------------------------------------------------------------------------------- segmenter
def test_closed_loop_segments_with_the_learned_segmenter_by_default(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(study_cli, "run_task", _fake_run(calls))
    out = tmp_path / "seg"
    common = ["er-sweep", "--patients", "test:0-2", "--ers", "0.6,1", "--out", str(out)]
    assert _study(*common, "--mode", "closed-loop") == 0
    assert {t.segmenter for t in calls} == {"onnx"}
    calls.clear()
    assert _study(*common) == 0
    assert {t.segmenter for t in calls} == {"oracle"}
    # Both reports name the segmenter; the oracle is labelled as such, and the kinematic
    # report puts the closed loop (learned) beside it.
    kin = (out / "report.md").read_text()
    closed = (out / "closed-loop" / "report.md").read_text()
    oracle = "`oracle` (the label volume's kidney labels: an oracle, not a segmenter"
    assert kin.count(oracle) >= 2  # the header, every table's provenance line
    assert "`onnx` (the product's learned segmenter (ONNX)" in closed and oracle not in closed
    assert "kinematic, ORACLE segmenter" in kin and "closed loop, onnx segmenter" in kin
    assert "ORACLE" in report.figure_note({"segmenter": "oracle"})
    assert "ORACLE" not in report.figure_note({"segmenter": "onnx"})


# ------------------------------------------------------------------------------- postures
def test_the_template_study_shares_the_inputs_digest_per_posture():
    """A template study with mixed postures (``train:3,test:0@decubitus``): the inputs
    digest covers the posture, so it differs between postures; runs of one posture must
    still share it."""

    def run(patient, posture, digest):
        task = {"mode": "kinematic", "segmenter": "oracle", "posture": posture}
        return {"patient": patient, "task": task, "inputs_sha256": digest}

    mixed = [
        run("train:3", "supine", "a" * 64),
        run("test:0", "left_lateral_decubitus", "b" * 64),
    ]
    s = study_results.settings_of(mixed, "study template", "template")
    assert s["inputs_sha256"] == {"left_lateral_decubitus": "b" * 64, "supine": "a" * 64}
    assert study_results.settings_of(mixed[:1], "t", "template")["inputs_sha256"] == "a" * 64
    with pytest.raises(study_results.MixedSettingsError, match=r"inputs_sha256 \(supine\)"):
        study_results.settings_of(mixed + [run("test:1", "supine", "c" * 64)], "t", "template")
    with pytest.raises(study_results.MixedSettingsError, match="inputs_sha256"):
        study_results.settings_of(mixed, "study er-sweep", "er-sweep")


def test_a_template_study_with_mixed_postures_runs(tmp_path, capsys, monkeypatch):
    calls = []
    fake = _fake_run(calls)

    def run(task):
        return fake(task) | {
            "template_variant": task.template_variant,
            "template_distance_mm": 3.0,
            "posture": task.posture,
        }

    monkeypatch.setattr(study_cli, "run_task", run)
    out = tmp_path / "postures"
    argv = ["template", "--patients", "train:3,test:0@decubitus", "--variants", "mean"]
    assert _study(*argv, "--out", str(out)) == 0, capsys.readouterr().err
    assert {t.posture for t in calls} == {"supine", "left_lateral_decubitus"}
    digests = {keys.task_inputs_digest(t) for t in calls}
    assert len(digests) == 2  # the digest covers the posture: what made the study exit
    assert "Generated patients, decubitus" in (out / "report.md").read_text()


# ------------------------------------------------------------------------------- a real one
def test_a_tiny_study_on_a_ct_patient_with_two_templates(kits, tmp_path, capsys):
    """Kinematic ER 60% and 100% on one synthetic CT kidney in a generated body, with the
    generated template and with a copy of it named as another template: both templates'
    runs in one OUT, their own run ids, records and reports, side by side."""
    copy = tmp_path / "copy_of_generated.npz"
    copy.write_bytes(DEFAULT_TEMPLATE_PATH.read_bytes())
    out = tmp_path / "two"
    common = ["er-sweep", "--patients", f"ct:{kits}:2#body=5", "--ers", "0.6,1", "--out", str(out)]
    assert _study(*common) == 0, capsys.readouterr().err
    assert _study(*common, "--template", str(copy)) == 0, capsys.readouterr().err
    records = [json.loads(p.read_text()) for p in sorted((out / "runs").glob("*.json"))]
    assert len(records) == 4
    tag = keys.template_tag(str(copy))
    for r in records:
        assert r["patient_kind"] == "ct" and np.isfinite(r["e_trans_mm"])
        other = r["run_id"].endswith(tag)
        assert r["template"]["label"].startswith(
            "copy_of_generated.npz (20" if other else "generated (20 generated kidneys)"
        )
        assert ("template" in r["task"]) == other
    # Same bytes, same errors: the template is what differs, and only by name here.
    by = {r["run_id"]: r for r in records}
    for rid, r in by.items():
        if rid.endswith(tag):
            base = by[rid[: -len(tag) - 2]]
            assert r["e_trans_mm"] == pytest.approx(base["e_trans_mm"])
    text = (out / f"template-{tag[4:]}" / "report.md").read_text()
    assert "real CT kidneys in generated bodies" in text.splitlines()[0]
    assert "## Side by side: templates generated and copy_of_generated.npz" in text
    assert "kinematic, generated template, ORACLE segmenter" in text
    assert "Critical ER and what it rests on, side by side" in text
    assert "| patients n | 15 | 1 | 1 |" in text


def test_a_study_whose_runs_are_all_left_out_writes_no_tables(tmp_path, capsys, monkeypatch):
    """Every closed-loop efficiency run left out (here: no localization): one message, no
    crash while plotting nothing (it happened with the learned segmenter on a quick
    scenario)."""
    calls = []
    fake = _fake_run(calls)
    monkeypatch.setattr(study_cli, "run_task", lambda t: fake(t) | {"e_trans_mm": None})
    out = tmp_path / "none"
    argv = ["efficiency", "--patients", "test:0", "--mode", "closed-loop", "--er", "0.6"]
    assert _study(*argv, "--out", str(out)) == 0
    err = capsys.readouterr().err
    assert "no run to analyse (every one left out): no efficiency tables" in err
    assert not (out / "closed-loop" / "efficiency_runs.csv").exists()
    assert (
        "efficiency: efficiency__test-0__erk060__cl"
        in (out / "closed-loop" / "report.md").read_text()
    )
