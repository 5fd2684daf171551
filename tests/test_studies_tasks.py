"""The typed study run (``StudyTask``): the run files' JSON layout and settings keys of the
untyped tasks it replaced, older records, bad records; and the patient-spec list
(``ct:`` specs with commas inside, ``;`` as a separator)."""

import dataclasses
import json
import pickle

import pytest

from drake_rus.cli import main
from drake_rus.experiments import keys, specs
from drake_rus.experiments.specs import StudyOptions, StudyTask

# Tasks as the untyped code wrote them into run files (key order included), with their run
# ids and settings keys computed by that code with the inputs digest fixed at "0" * 64
# (the real digest hashes the scenario and template files, which other changes edit).
BEFORE = [
    (
        {
            "scenario": "default",
            "scenarios_file": None,
            "overrides": None,
            "segmenter": "oracle",
            "method": "seed",
            "voxel": 0.002,
            "seed": 0,
            "recon_spacing": 0.001,
            "er_unit": "kidney",
            "mode": "kinematic",
            "posture": None,
            "study": "er-sweep",
            "patient": "test:0",
            "er": 0.6,
            "start": -1,
        },
        "er-sweep__test-0__erk060",
        "f6dd84dc589853c63c89576a601ab2ba46c4bb2fd2336bd9497027e03a4ce070",
    ),
    (
        {
            "scenario": "default",
            "scenarios_file": None,
            "overrides": None,
            "segmenter": "oracle",
            "method": "seed",
            "voxel": 0.002,
            "seed": 7,
            "recon_spacing": 0.001,
            "er_unit": "fixed",
            "mode": "kinematic",
            "posture": None,
            "study": "starts",
            "patient": "test:3",
            "er": 0.6,
            "start": 4,
        },
        "starts__test-3__er060__s4",
        "00dcf68ad4cebf55ac5a6a400fc579775e3f446374b7084b31838662cec0d30f",
    ),
    (
        {
            "scenario": "quick",
            "scenarios_file": None,
            "overrides": None,
            "segmenter": "oracle",
            "method": "seed",
            "voxel": 0.002,
            "seed": 0,
            "recon_spacing": 0.001,
            "er_unit": "kidney",
            "mode": "closed-loop",
            "posture": None,
            "study": "efficiency",
            "patient": "seed:5",
            "er": 0.6,
            "start": -1,
            "export_dir": "/tmp/volumes",
            "strategies": ["OP", "SL"],
        },
        "efficiency__seed-5__erk060__cl",
        "110d002f12e642cd2a3a11dc73cc31de604635ad814f08b019762ece23178267",
    ),
    (
        {
            "scenario": "default",
            "scenarios_file": None,
            "overrides": None,
            "segmenter": "classical",
            "method": "seed",
            "voxel": 0.002,
            "seed": 0,
            "recon_spacing": 0.001,
            "er_unit": "kidney",
            "mode": "kinematic",
            "posture": "left_lateral_decubitus",
            "study": "template",
            "patient": "train:3",
            "er": 0.6,
            "start": -1,
            "template_variant": "loo",
        },
        "template__train-3__erk060__t-loo__lld",
        "877c570fbc55b0de2d3eebe98344944396be5d41980c070fed56182e888a06f8",
    ),
    (
        {
            "scenario": "default",
            "scenarios_file": None,
            "overrides": "{localization: {max_points: 1500}}",
            "segmenter": "oracle",
            "method": "seed",
            "voxel": 0.002,
            "seed": 0,
            "recon_spacing": 0.001,
            "er_unit": "kidney",
            "mode": "kinematic",
            "posture": None,
            "study": "closed-loop",
            "patient": "test:1",
            "er": 0.7,
            "start": -1,
            "start_fraction": 0.1,
        },
        "closed-loop__test-1__erk070__f010",
        "10f3930de309b71e04b0a2e0bb1bc49b984714e79cfddad0c85570af14fd6546",
    ),
]


@pytest.mark.parametrize("before,run_id,key", BEFORE, ids=[b[1] for b in BEFORE])
def test_a_task_written_before_the_type_keys_identically(before, run_id, key, monkeypatch):
    """Stored runs are reused exactly as before: the same dict back (key order too), the
    same run id and the same settings key."""
    monkeypatch.setattr(keys, "task_inputs_digest", lambda task: "0" * 64)
    task = StudyTask.from_dict(json.loads(json.dumps(before)))
    assert list(task.to_dict().items()) == list(before.items())
    assert keys.run_id(task) == run_id
    assert keys.task_key(task) == key


def test_the_generators_make_the_tasks_of_before():
    made = [
        specs.er_sweep_tasks(["test:0"], StudyOptions(), [0.6])[0],
        specs.starts_tasks(["test:3"], StudyOptions(er_unit="fixed", seed=7), 0.6, 5)[4],
        specs.efficiency_tasks(
            ["seed:5"],
            StudyOptions(mode="closed-loop", scenario="quick"),
            0.6,
            "/tmp/volumes",
            ["SL", "OP"],
        )[0],
        specs.template_tasks(
            ["train:3@decubitus"],
            StudyOptions(posture="supine", segmenter="classical"),
            0.6,
            ["loo"],
        )[0],
        specs.closed_loop_tasks(
            ["test:1"], StudyOptions(overrides="{localization: {max_points: 1500}}"), 0.7
        )[0],
    ]
    for task, (before, _, _) in zip(made, BEFORE):
        assert list(task.to_dict().items()) == list(before.items())
    assert made[2].strategies == ("OP", "SL")  # the report's order, a tuple


def test_the_real_key_survives_the_run_file():
    """With the real inputs digest: a task written to JSON and read back keys the same."""
    for task in specs.efficiency_tasks(
        ["test:0"], StudyOptions(), 0.6, "/tmp/v"
    ) + specs.template_tasks(["test:1@decubitus"], StudyOptions(), 0.6, ["scale-1.1"]):
        again = StudyTask.from_dict(json.loads(json.dumps(task.to_dict())))
        assert again == task and keys.task_key(again) == keys.task_key(task)


def test_an_older_record_loads_with_its_defaults():
    """A task recorded before ER units, modes and postures existed: ER x L_m (the "er"
    run id, as before), kinematic, the scenario's posture, the mean template."""
    old = {
        "scenario": "default",
        "scenarios_file": None,
        "overrides": None,
        "segmenter": "oracle",
        "method": "seed",
        "voxel": 0.002,
        "seed": 0,
        "recon_spacing": 0.001,
        "study": "er-sweep",
        "patient": "test:0",
        "er": 0.6,
        "start": -1,
    }
    task = StudyTask.from_dict(old)
    assert (task.er_unit, task.mode, task.posture) == ("fixed", "kinematic", None)
    assert task.template_variant == "mean" and task.strategies is None
    assert keys.run_id(task) == "er-sweep__test-0__er060"
    # A new task's default is the patient's kidney length (the paper's simulation).
    assert StudyTask(study="er-sweep", patient="test:0", er=0.6).er_unit == "kidney"


@pytest.mark.parametrize(
    "record,words",
    [
        (
            {"study": "er-sweep", "patient": "test:0", "er": 0.6, "segmentor": "oracle"},
            "unknown field(s) segmentor",
        ),
        ({"study": "er-sweep", "patient": "test:0"}, "missing er"),
        ({"study": "sweep", "patient": "test:0", "er": 0.6}, "study expected one of"),
        (
            {"study": "er-sweep", "patient": "test:0", "er": 0.6, "template_variant": "loo"},
            "template_variant is read by template runs only",
        ),
        (["er-sweep"], "expected a dict"),
        ({"study": "er-sweep", "patient": "test:0", "er": "most"}, "er expected a number"),
    ],
)
def test_a_bad_record_is_refused_naming_the_field(record, words):
    with pytest.raises(
        ValueError, match=r"study task: .*" + words.replace("(", r"\(").replace(")", r"\)")
    ):
        StudyTask.from_dict(record)


def test_a_task_is_frozen_typed_and_picklable():
    task = StudyTask(study="efficiency", patient="test:0", er=1, seed="3", strategies=["OP", "SL"])
    assert isinstance(task.er, float) and task.seed == 3 and task.strategies == ("OP", "SL")
    with pytest.raises(dataclasses.FrozenInstanceError):
        task.er = 0.5
    assert pickle.loads(pickle.dumps(task)) == task and hash(task) == hash(
        dataclasses.replace(task)
    )
    assert isinstance(task, StudyOptions)  # a run carries its study's options
    # Every option is recorded, but those left out while at their default (the template
    # asked for and its file: runs from before them keep their keys).
    omitted = {f.name for f in dataclasses.fields(StudyOptions) if f.metadata.get("omit_default")}
    assert omitted == {"template", "template_file"}
    assert {f.name for f in dataclasses.fields(StudyOptions)} - omitted < set(task.to_dict())
    real = dataclasses.replace(task, template="real", template_file="/cache/ct-x.npz")
    assert {"template", "template_file"} < set(real.to_dict())


CT = "ct:../shared/anatomy/kits19/case_00003"


@pytest.mark.parametrize(
    "text,want",
    [
        (f"{CT}#right", [f"{CT}#right"]),
        (f"{CT}#left,body=7", [f"{CT}#left,body=7"]),
        (f"{CT}#left,body=7,test:0-1", [f"{CT}#left,body=7", "test:0", "test:1"]),
        (
            f"test:2,{CT}#left,kidney=parenchyma,pose=ct,{CT}",
            ["test:2", f"{CT}#left,kidney=parenchyma,pose=ct", CT],
        ),
        (f"{CT}#left,body=7;{CT}#right ; train:3", [f"{CT}#left,body=7", f"{CT}#right", "train:3"]),
        (f"{CT}#left,body=7@decubitus,test:0", [f"{CT}#left,body=7@decubitus", "test:0"]),
        (f"{CT},pose=ct", None),  # no '#': the comma separates
        ("test:0-1;seed:4", ["test:0", "test:1", "seed:4"]),
        ("seed:7, train:3,test:1-1", ["seed:7", "train:3", "test:1"]),
    ],
)
def test_patient_lists_with_ct_specs(text, want):
    """A ``ct:PATH#OPTIONS`` spec keeps its own commas; ``;`` also separates; the other
    forms read as before."""
    if want is None:
        with pytest.raises(ValueError, match=r"--patients: cannot read 'pose=ct'"):
            specs.expand_patients(text)
    else:
        assert specs.expand_patients(text) == want


def test_a_ct_spec_without_a_path_is_refused():
    with pytest.raises(ValueError, match=r"--patients: 'ct:#left' names no label map"):
        specs.expand_patients("test:0,ct:#left")
    assert keys.run_id(StudyTask(study="er-sweep", patient=f"{CT}#left,body=7", er=0.6)) == (
        "er-sweep__ct-shared-anatomy-kits19-case-00003-left-body-7__erk060"
    )


def test_the_study_command_names_a_bad_ct_spec_once(tmp_path, capsys):
    out = tmp_path / "study"
    assert (
        main(
            [
                "study",
                "er-sweep",
                "--patients",
                "test:0,ct:#left",
                "--workers",
                "0",
                "--out",
                str(out),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.count("--patients") == 1 and "'ct:#left' names no label map" in err
    assert not out.exists()
