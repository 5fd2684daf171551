"""Bad-input corpus, runs (issue 32): inputs that used to end in a traceback, run for hours or
say too little now end in one line naming the argument or field, exit status 2, and nothing
half-written: ``--set`` nested 500 deep, an ONNX model with int64 output, ``rehearse
--status-rate-hz 0``, ``demo --duration 1e6``, a full disk mid-run, a busy output folder
(the message names the run holding it), a ``--rerun`` of something that is not a summary."""

import errno
import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest

from drake_rus.cli import main
from drake_rus.config_schema import MAX_YAML_DEPTH, ScenarioError, check_nesting_depth, yaml_depth
from drake_rus.io_utils import LOCK_NAME, OutputError, describe_os_error, output_dir
from drake_rus.paths import REPO_ROOT
from drake_rus.scenario import DEFAULT_SCENARIOS_FILE, LoadScenario, Scenario, ScenarioToYaml


def _run(argv, capsys):
    code = main(argv)
    captured = capsys.readouterr()
    return code, captured.err


def _nothing_written(out):
    assert not out.exists(), sorted(p.name for p in out.iterdir())


# ------------------------------------------------------------------------ --set nesting
@pytest.mark.parametrize(
    "text",
    [
        "{a: " * 500 + "1" + "}" * 500,
        "{contact: {patient_section_half_lengths: " + "[" * 500 + "]" * 500 + "}}",
        "{controller: " * 30 + "{}" + "}" * 30,
    ],
    ids=["mappings_500", "lists_500", "mappings_31"],
)
def test_deep_set_is_one_line_naming_set(tmp_path, capsys, text):
    out = tmp_path / "scan"
    code, err = _run(["scan", "--out", str(out), "--set", text], capsys)
    assert code == 2
    assert err.startswith("drake-rus scan: error: --set: the YAML nests ")
    assert f"at most {MAX_YAML_DEPTH} levels" in err and err.count("\n") == 1
    _nothing_written(out)


def test_deep_scenarios_file_is_named(tmp_path, capsys):
    deep = tmp_path / "deep.yaml"
    deep.write_text(
        "deep:\n" + "".join("  " * (i + 1) + f"k{i}:\n" for i in range(300)) + "  " * 301 + "x: 1\n"
    )
    code, err = _run(
        ["demo", "--out", str(tmp_path / "d"), "--scenarios-file", str(deep), "--scenario", "deep"],
        capsys,
    )
    assert code == 2 and f"scenario file {deep}: the YAML nests more than" in err
    _nothing_written(tmp_path / "d")


def test_the_depth_bound_admits_every_shipped_scenario():
    """The bound sits above what the schema needs: every scenario file of the repository,
    a whole resolved scenario dumped as YAML (the deepest: patient.X_BPt.rotation.deg)."""
    for path in sorted((REPO_ROOT / "diagrams").glob("*.scenarios.yaml")):
        depth, _ = yaml_depth(path.read_text())
        assert depth <= MAX_YAML_DEPTH, path
    depth, _ = yaml_depth(ScenarioToYaml(Scenario()))
    assert 3 <= depth <= MAX_YAML_DEPTH // 2
    check_nesting_depth(DEFAULT_SCENARIOS_FILE.read_text(), "x")
    with pytest.raises(ScenarioError, match="^x: the YAML nests 17 levels"):
        check_nesting_depth("{a: " * 17 + "1" + "}" * 17, "x")
    # Overrides given to the library directly are bounded too.
    with pytest.raises(ScenarioError, match="nests more than"):
        LoadScenario(scenario_text="[" * 5000 + "]" * 5000)


# ------------------------------------------------------------------------ ONNX model types
def _model(path, out_type, out_shape=(1, 1, 64, 64)):
    from onnx import TensorProto, helper, save

    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 1, 64, 64])
    y = helper.make_tensor_value_info("y", out_type, list(out_shape))
    nodes = [helper.make_node("Cast", ["x"], ["y"], to=out_type)]
    if len(out_shape) != 4:
        shape = helper.make_tensor("s", TensorProto.INT64, [len(out_shape)], list(out_shape))
        nodes = [
            helper.make_node("Reshape", ["x", "s"], ["r"]),
            helper.make_node("Cast", ["r"], ["y"], to=out_type),
        ]
        graph = helper.make_graph(nodes, "g", [x], [y], initializer=[shape])
    else:
        graph = helper.make_graph(nodes, "g", [x], [y])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    save(model, str(path))
    return path


def test_onnx_output_types_are_checked_when_loading(tmp_path, geometry):
    from onnx import TensorProto

    from drake_rus.imaging.onnx_backend import OnnxSegmenter

    int64 = _model(tmp_path / "int64.onnx", TensorProto.INT64)
    for output in ("logits", "probability"):
        with pytest.raises(ValueError) as e:
            OnnxSegmenter(int64, geometry, (1, 1, 64, 64), output=output)
        text = str(e.value)
        assert text.startswith("imaging.onnx_model: model int64.onnx outputs tensor(int64)")
        assert f"imaging.onnx_output '{output}' expects a float tensor" in text
        assert "onnx_output: labels" in text
    # Class indices as int64 are what "labels" means: accepted, and they segment.
    seg = OnnxSegmenter(int64, geometry, (1, 1, 64, 64), output="labels", kidney_channel=1)
    assert seg(np.full(geometry.image_shape, 255, np.uint8)).any()
    boolean = _model(tmp_path / "bool.onnx", TensorProto.BOOL)
    with pytest.raises(
        ValueError,
        match=r"outputs tensor\(bool\); imaging.onnx_output "
        r"'labels' expects a float or integer tensor",
    ):
        OnnxSegmenter(boolean, geometry, (1, 1, 64, 64), output="labels")
    flat = _model(tmp_path / "flat.onnx", TensorProto.FLOAT, (1, 4096))
    with pytest.raises(
        ValueError,
        match=r"imaging.onnx_model: model flat.onnx output has "
        r"shape \[1, 4096\]; expected \(N, K, h, w\)",
    ):
        OnnxSegmenter(flat, geometry, (1, 1, 64, 64))


def test_onnx_int64_model_through_the_scan(tmp_path, capsys):
    from onnx import TensorProto

    model = _model(tmp_path / "int64.onnx", TensorProto.INT64)
    out = tmp_path / "scan"
    code, err = _run(
        [
            "scan",
            "--scenario",
            "quick",
            "--no-record",
            "--out",
            str(out),
            "--set",
            f"{{imaging: {{onnx_model: {model}}}}}",
        ],
        capsys,
    )
    assert code == 2
    assert (
        err.startswith(
            "drake-rus scan: error: imaging.onnx_model: model int64.onnx outputs tensor(int64)"
        )
        and err.count("\n") == 1
    )
    _nothing_written(out)


# ------------------------------------------------------------------------ rehearse, demo
@pytest.mark.parametrize("rate", ["0", "-5", "nan", "inf", "1e9", "5"])
def test_rehearse_status_rate_is_checked_up_front(tmp_path, capsys, rate):
    out = tmp_path / "r"
    code, err = _run(
        ["rehearse", "--status-rate-hz", rate, "--out", str(out), "--netns", "no"], capsys
    )
    assert code == 2
    assert (
        err.startswith(
            "drake-rus rehearse: error: --status-rate-hz: expected a status rate of 10-10000 Hz"
        )
        and "ZeroDivision" not in err
    )
    _nothing_written(out)


@pytest.mark.parametrize("load", ["-1", "65"])
def test_rehearse_cpu_load_is_checked_up_front(tmp_path, capsys, load):
    out = tmp_path / "r"
    code, err = _run(["rehearse", "--cpu-load", load, "--out", str(out), "--netns", "no"], capsys)
    assert code == 2
    assert err.startswith(
        "drake-rus rehearse: error: --cpu-load: expected a number of busy processes, 0-64"
    )
    _nothing_written(out)


@pytest.mark.parametrize(
    "spec,words",
    [
        ("test:abc", ["test:K", "'test:abc'"]),
        ("train:1000000", ["train:K", "out of range"]),
        ("seed:-1", ["seed:N"]),
        ("phantom:3", ["imaging-pictures only"]),
        ("no/such/patient", ["no such file or folder", "test:K"]),
    ],
    ids=["not_an_integer", "index_too_big", "negative_seed", "phantom", "missing_path"],
)
def test_rehearse_patient_is_checked_up_front(tmp_path, capsys, spec, words):
    """The rehearsal's simulated side loads the patient in its own process: a spec that
    cannot load is refused before it starts (it used to end, some 30 s later, in the sim
    process's traceback and a rehearsal.json)."""
    out = tmp_path / "r"
    code, err = _run(["rehearse", "--patient", spec, "--out", str(out), "--netns", "no"], capsys)
    assert code == 2 and err.startswith("drake-rus rehearse: error: --patient:"), err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for word in words:
        assert word in err, err
    _nothing_written(out)


@pytest.mark.parametrize("duration", ["1e6", "601", "inf"])
def test_demo_duration_is_bounded_with_its_reason(tmp_path, capsys, duration):
    out = tmp_path / "demo"
    code, err = _run(["demo", "--duration", duration, "--out", str(out)], capsys)
    assert code == 2 and "--duration" in err
    if duration != "inf":  # inf: the shared rule (a positive finite time)
        assert "at most 600 s" in err and "0.5 MB per simulated s" in err
    _nothing_written(out)


# ------------------------------------------------------------------------ full disk
def test_a_full_disk_names_the_file_being_written(tmp_path, capsys, monkeypatch):
    """A write that fills the disk raises OSError(ENOSPC) without a file name (as a write()
    does): the message names the file and --out; no temporary file, no lock is left."""
    import matplotlib.figure

    def full(self, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", full)
    out = tmp_path / "demo"
    code, err = _run(["demo", "--duration", "0.05", "--out", str(out)], capsys)
    assert code == 2
    assert err.strip() == (
        f"drake-rus demo: error: --out: no space left on the device writing {out / 'force.png'}"
    )
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == []
    assert not (out / "summary.json").exists()


def test_an_os_error_without_a_file_name_never_says_none():
    text = describe_os_error(OSError(errno.ENOSPC, "No space left on device"))
    assert "None" not in text and text.startswith("no space left on the device")
    assert "None" not in describe_os_error(OSError(errno.EACCES, "Permission denied"))


# ------------------------------------------------------------------------ busy output folder
def test_a_busy_folder_names_the_run_holding_it(tmp_path, capsys):
    out = tmp_path / "runs"
    holder = ["drake-rus", "scan", "--patient", "test:3", "--out", str(out)]
    with output_dir(out, "--out", what="scan", argv=holder):
        code, err = _run(["demo", "--out", str(out)], capsys)
        lock = json.loads((out / LOCK_NAME).read_text())
    assert code == 2
    assert (
        f"--out: {out} is in use by another run (drake-rus scan, process {os.getpid()}, "
        f"started {lock['started_utc'][:10]} " in err
    )
    assert re.search(r"UTC \(\d+ s ago\): drake-rus scan --patient test:3 --out ", err), err
    assert "wait for it to finish or choose another --out" in err
    assert not (out / LOCK_NAME).exists() and not (out / "summary.json").exists()


def test_a_stale_lock_is_taken_over(tmp_path):
    out = tmp_path / "runs"
    out.mkdir()
    finished = subprocess.Popen([sys.executable, "-c", "pass"])
    finished.wait()
    dead = finished.pid
    (out / LOCK_NAME).write_text(json.dumps({"pid": dead, "command": "scan"}))
    with output_dir(out, "--out", what="demo"):
        assert json.loads((out / LOCK_NAME).read_text())["pid"] == os.getpid()
    # A live process number that another process now holds (started at another time).
    (out / LOCK_NAME).write_text(
        json.dumps({"pid": os.getpid(), "command": "scan", "process_start": 1})
    )
    with output_dir(out, "--out", what="demo"):
        pass
    # A lock of an older drake-rus ("PID COMMAND") held by a live process is respected.
    (out / LOCK_NAME).write_text(f"{os.getpid()} scan\n")
    with pytest.raises(
        OutputError, match=f"in use by another run \\(drake-rus scan, process {os.getpid()}\\)"
    ):
        with output_dir(out, "--out", what="demo"):
            pass
    assert (out / LOCK_NAME).exists()


# ------------------------------------------------------------------------ --rerun
@pytest.mark.parametrize(
    "content,words",
    [
        (None, ["--rerun: no such file"]),
        ("not json {", ["--rerun:", "is not a drake-rus scan summary (not JSON"]),
        ("[1, 2]", ["--rerun:", "is not a drake-rus scan summary (no 'status')"]),
        ('{"status": "DONE", "e_trans_mm": 3.0}', ["--rerun:", "records no provenance"]),
        (
            '{"status": "DONE", "provenance": {"command": "demo", "scenario_yaml": "{}", '
            '"arguments": {}}}',
            ["--rerun:", "summary of 'drake-rus demo'"],
        ),
        (
            '{"status": "DONE", "provenance": {"command": "scan", "scenario_yaml": "{contact: '
            '{model: magic}}", "arguments": {"patient": "test:0", "max_sim_time": 5}}}',
            ["--rerun:", "provenance.scenario_yaml", "'contact.model'"],
        ),
        (
            '{"status": "DONE", "provenance": {"command": "scan", "scenario_yaml": "{}", '
            '"arguments": {"max_sim_time": 5}}}',
            ["--rerun:", "lacks the patient"],
        ),
    ],
    ids=[
        "missing",
        "not_json",
        "not_a_mapping",
        "no_provenance",
        "a_demo",
        "bad_scenario",
        "no_patient",
    ],
)
def test_rerun_of_what_is_not_a_scan_summary(tmp_path, capsys, content, words):
    src = tmp_path / "old" / "summary.json"
    if content is not None:
        src.parent.mkdir()
        src.write_text(content)
    out = tmp_path / "new"
    code, err = _run(["scan", "--rerun", str(src), "--out", str(out)], capsys)
    assert code == 2 and err.startswith("drake-rus scan: error: --rerun:"), err
    for w in words:
        assert w in err, err
    assert err.count("\n") == 1
    _nothing_written(out)


def test_rerun_refuses_arguments_that_change_the_run(tmp_path, capsys):
    src = tmp_path / "summary.json"
    src.write_text("{}")
    code, err = _run(
        ["scan", "--rerun", str(src), "--seed", "3", "--set", "{}", "--out", str(tmp_path / "n")],
        capsys,
    )
    assert (
        code == 2
        and "--rerun: repeats the recorded run as it was; --set, --seed cannot be given with it"
        in err
    )


def test_a_long_run_says_how_far_it_is_on_a_log(capsys, monkeypatch):
    """Without a terminal (a log, CI) a long run prints where it is every PROGRESS_LINE_S s
    of wall time, even without phases (the demo)."""
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.primitives import ConstantVectorSource

    from drake_rus import progress

    monkeypatch.setattr(progress, "PROGRESS_LINE_S", 0.0)
    simulator = Simulator(ConstantVectorSource([0.0]))
    progress.AdvanceWithProgress(simulator, 1.0, desc="pressing", step=0.25)
    lines = capsys.readouterr().err.splitlines()
    assert lines[0].startswith("pressing: 0.2 of 1.0 sim s (") and len(lines) == 4, lines
    assert lines[-1].startswith("pressing: 1.0 of 1.0 sim s")
