"""Bad-input corpus, command line: bad arguments give exit status 2 and one message naming
the argument or field, and nothing is written to the output directory."""

import pytest

from drake_rus.cli import main


def _run(argv, capsys):
    code = main(argv)
    err = capsys.readouterr().err
    return code, err


CAMPAIGN_CASES = [
    ("zero_runs", ["--runs", "0"], ["--runs"]),
    ("negative_runs", ["--runs", "-5"], ["--runs"]),
    ("negative_workers", ["--runs", "2", "--workers", "-1"], ["--workers"]),
    ("nan_time", ["--runs", "2", "--max-sim-time", "nan"], ["--max-sim-time"]),
    ("zero_time", ["--runs", "2", "--max-sim-time", "0"], ["--max-sim-time"]),
    ("negative_seed", ["--runs", "2", "--seed", "-3"], ["--seed"]),
    ("seed_2_64", ["--runs", "2", "--seed", str(2**64)], ["--seed", "0-4294967295"]),
    ("zero_patients", ["--runs", "2", "--patients", "0"], ["--patients"]),
    ("unknown_scenario", ["--runs", "2", "--scenario", "nope"], ["'nope'", "available"]),
]


@pytest.mark.parametrize("case,args,words", CAMPAIGN_CASES, ids=[c[0] for c in CAMPAIGN_CASES])
def test_campaign_bad_arguments(tmp_path, capsys, case, args, words):
    out = tmp_path / "campaign"
    code, err = _run(["campaign", "--out", str(out), *args], capsys)
    assert code == 2
    assert err.startswith("drake-rus campaign: error:")
    for w in words:
        assert w in err, err
    assert not out.exists()


def test_campaign_missing_scenarios_file(tmp_path, capsys):
    code, err = _run(
        [
            "campaign",
            "--runs",
            "1",
            "--out",
            str(tmp_path / "c"),
            "--scenarios-file",
            str(tmp_path / "none.yaml"),
        ],
        capsys,
    )
    assert code == 2 and "none.yaml" in err and not (tmp_path / "c").exists()


def test_campaign_out_is_a_file(tmp_path, capsys):
    target = tmp_path / "file.txt"
    target.write_text("keep me")
    code, err = _run(["campaign", "--runs", "1", "--out", str(target)], capsys)
    assert code == 2 and "--out" in err and target.read_text() == "keep me"


@pytest.mark.parametrize(
    "argv,word",
    [
        (["campaign", "--runs", "abc", "--out", "x"], "--runs"),
        (["campaign", "--out", "x"], "--runs"),
        (["campaign", "--runs", "3"], "--out"),
        (["scan", "--seed", "one"], "--seed"),
    ],
    ids=["non_integer_runs", "missing_runs", "missing_out", "non_integer_seed"],
)
def test_argparse_errors_name_the_argument(capsys, argv, word):
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    assert word in capsys.readouterr().err


SCAN_CASES = [
    ("negative_seed", ["--seed", "-1"], ["--seed"]),
    # A seed above 2**32 - 1 (a 400-digit one was a traceback from the scenario check).
    ("seed_2_32", ["--seed", str(2**32)], ["--seed", "0-4294967295"]),
    ("seed_400_digits", ["--seed", "1" + "0" * 400], ["--seed", "0-4294967295"]),
    ("zero_time", ["--max-sim-time", "0"], ["--max-sim-time"]),
    ("inf_time", ["--max-sim-time", "inf"], ["--max-sim-time"]),
    ("unknown_scenario", ["--scenario", "nope"], ["'nope'"]),
    ("bad_override", ["--set", "{contact: {time_step: -1}}"], ["contact.time_step"]),
    ("bad_override_yaml", ["--set", "{contact: ["], ["YAML"]),
    (
        "missing_template",
        ["--set", "{localization: {template: /nonexistent/t.npz}}"],
        ["localization.template", "t.npz"],
    ),
    ("unknown_patient", ["--patient", "nobody:1", "--no-record"], ["nobody:1"]),
]


@pytest.mark.parametrize("case,args,words", SCAN_CASES, ids=[c[0] for c in SCAN_CASES])
def test_scan_bad_arguments(tmp_path, capsys, case, args, words):
    out = tmp_path / "scan"
    code, err = _run(["scan", "--out", str(out), *args], capsys)
    assert code == 2
    assert err.startswith("drake-rus scan: error:")
    for w in words:
        assert w in err, err
    assert not out.exists()


def test_missing_template_says_how_to_build_it_once(tmp_path, capsys):
    out = tmp_path / "scan"
    code, err = _run(
        ["scan", "--out", str(out), "--set", "{localization: {template: /nonexistent/t.npz}}"],
        capsys,
    )
    assert code == 2 and "localization.template" in err and "/nonexistent/t.npz" in err, err
    assert err.count("template build") == 1, err
    assert not out.exists()


@pytest.mark.parametrize("where", ["set", "file", "campaign"])
def test_yaml_syntax_error_is_one_line(tmp_path, capsys, where):
    """A YAML syntax error in --set or a scenarios file is one line saying where (PyYAML's
    own text is four, quoting the source)."""
    scenarios = tmp_path / "bad.scenarios.yaml"
    scenarios.write_text("default: {contact: [\n")
    out = tmp_path / "out"
    argv = {
        "set": ["scan", "--set", "{contact: ["],
        "file": ["scan", "--scenarios-file", str(scenarios)],
        "campaign": ["campaign", "--runs", "1", "--scenario", "default"]
        + ["--scenarios-file", str(scenarios)],
    }[where]
    code, err = _run([*argv, "--out", str(out)], capsys)
    assert code == 2 and "not valid YAML" in err and "line" in err, err
    assert err.count("\n") == 1, err
    assert not out.exists()


# ------------------------------------------------ issue 17: fail before the work, not after
import errno  # noqa: E402
import os  # noqa: E402
import shutil  # noqa: E402
import time  # noqa: E402
from collections import namedtuple  # noqa: E402

import numpy as np  # noqa: E402

from drake_rus import io_utils  # noqa: E402

_Usage = namedtuple("_Usage", "total used free")


@pytest.fixture
def readonly_dir(tmp_path, monkeypatch):
    """A folder nothing can be written into: mode 0555, and since permission bits do not
    stop root, writes under it fail as on a read-only file system for root too."""
    folder = tmp_path / "readonly"
    folder.mkdir()
    real_probe = io_utils._probe_write

    def probe(path):
        if str(os.path.abspath(path)).startswith(str(folder)):
            raise OSError(errno.EROFS, "Read-only file system", str(path))
        return real_probe(path)

    monkeypatch.setattr(io_utils, "_probe_write", probe)
    folder.chmod(0o555)
    yield folder
    folder.chmod(0o755)


@pytest.fixture
def full_disk(monkeypatch):
    """Every file system reports 100 kB free."""
    monkeypatch.setattr(shutil, "disk_usage", lambda p: _Usage(10**9, 10**9 - 10**5, 10**5))


def _nothing_written(folder):
    return not folder.exists() or not any(folder.iterdir())


def test_scan_out_is_an_existing_file(tmp_path, capsys):
    target = tmp_path / "summary.txt"
    target.write_text("keep me")
    code, err = _run(["scan", "--out", str(target), "--no-record"], capsys)
    assert code == 2 and "--out" in err and "is a file" in err
    assert target.read_text() == "keep me"
    assert err.count("\n") == 1, err


def test_scan_out_in_a_readonly_folder(readonly_dir, capsys):
    out = readonly_dir / "scan"
    code, err = _run(["scan", "--out", str(out), "--no-record"], capsys)
    assert code == 2 and "--out" in err and "cannot write" in err, err
    assert not out.exists()


def test_scan_out_on_a_full_disk(tmp_path, full_disk, capsys):
    out = tmp_path / "scan"
    code, err = _run(["scan", "--out", str(out), "--no-record"], capsys)
    assert code == 2 and "--out" in err and "free space" in err, err
    assert not out.exists()


def test_scan_record_is_a_folder(tmp_path, capsys):
    out = tmp_path / "scan"
    code, err = _run(["scan", "--out", str(out), "--record", str(tmp_path)], capsys)
    assert code == 2 and "--record" in err and "is a folder" in err, err
    assert not out.exists()


def test_scan_record_needs_html(tmp_path, capsys):
    out = tmp_path / "scan"
    code, err = _run(["scan", "--out", str(out), "--record", str(tmp_path / "r.png")], capsys)
    assert code == 2 and "--record" in err and ".html" in err, err
    assert not out.exists()


def test_scan_record_in_a_readonly_folder(tmp_path, readonly_dir, capsys):
    out = tmp_path / "scan"
    code, err = _run(["scan", "--out", str(out), "--record", str(readonly_dir / "r.html")], capsys)
    assert code == 2 and "--record" in err, err
    assert not out.exists()


def test_scan_out_inside_a_file_path(tmp_path, capsys):
    (tmp_path / "plain").write_text("x")
    code, err = _run(["scan", "--out", str(tmp_path / "plain" / "sub"), "--no-record"], capsys)
    assert code == 2 and "--out" in err and "not a folder" in err, err


def test_scan_busy_out_is_refused(tmp_path, capsys):
    """Two scans into the same --out: the second is refused while the first holds it."""
    out = tmp_path / "scan"
    out.mkdir()
    (out / io_utils.LOCK_NAME).write_text(f"{os.getppid()} scan\n")  # a live process
    code, err = _run(["scan", "--out", str(out), "--no-record"], capsys)
    assert code == 2 and "--out" in err and "in use" in err, err
    assert sorted(p.name for p in out.iterdir()) == [io_utils.LOCK_NAME]


def test_scan_patient_100_m_away(tmp_path, capsys):
    out = tmp_path / "scan"
    code, err = _run(
        [
            "scan",
            "--out",
            str(out),
            "--no-record",
            "--set",
            "{patient: {X_BPt: {translation: [100, 0, 0]}}}",
        ],
        capsys,
    )
    assert code == 2 and "patient.X_BPt" in err and "1.5 m" in err, err
    assert not out.exists()


def test_scan_template_is_a_folder(tmp_path, capsys):
    out = tmp_path / "scan"
    code, err = _run(
        [
            "scan",
            "--out",
            str(out),
            "--no-record",
            "--set",
            f"{{localization: {{template: '{tmp_path}'}}}}",
        ],
        capsys,
    )
    assert code == 2 and "localization.template" in err and "folder" in err, err
    assert not out.exists()


@pytest.mark.parametrize(
    "text,field",
    [
        ("{probe: {mass: 1000}}", "probe.mass"),
        ("{contact: {time_step: 10}}", "contact.time_step"),
        ("{controller: {desired_force: 25}}", "controller.desired_force"),
        ("{imaging: {frame_rate_hz: 1e9}}", "imaging.frame_rate_hz"),
        ("{contact: {model: point, model: hydroelastic}}", "contact.model"),
    ],
    ids=["probe_1000_kg", "time_step_10", "force_above_ceiling", "frame_rate_1e9", "duplicate_key"],
)
def test_scan_unphysical_override(tmp_path, capsys, text, field):
    out = tmp_path / "scan"
    code, err = _run(["scan", "--out", str(out), "--no-record", "--set", text], capsys)
    assert code == 2 and field in err, err
    assert not out.exists()


@pytest.mark.parametrize("value", ["0", "-1", "1000"])
@pytest.mark.parametrize("action", ["info", "export", "show"])
def test_patient_voxel_mm(tmp_path, capsys, action, value):
    extra = {
        "info": [],
        "export": ["--out", str(tmp_path / "exp")],
        "show": ["--png", str(tmp_path / "s.png")],
    }[action]
    code, err = _run(["patient", action, "test:0", "--voxel-mm", value, *extra], capsys)
    assert code == 2 and "--voxel-mm" in err and "0.1-10 mm" in err, err
    assert not any(tmp_path.iterdir())


def test_patient_export_onto_a_full_disk(tmp_path, full_disk, capsys):
    out = tmp_path / "exp"
    code, err = _run(["patient", "export", "test:0", "--out", str(out)], capsys)
    assert code == 2 and "--out" in err and "free space" in err, err
    assert not out.exists()


def test_patient_export_out_is_a_file(tmp_path, capsys):
    target = tmp_path / "exp"
    target.write_text("keep")
    code, err = _run(["patient", "export", "test:0", "--out", str(target)], capsys)
    assert code == 2 and "--out" in err and target.read_text() == "keep", err


def test_patient_export_into_a_readonly_folder(readonly_dir, capsys):
    code, err = _run(["patient", "export", "test:0", "--out", str(readonly_dir / "e")], capsys)
    assert code == 2 and "--out" in err and not (readonly_dir / "e").exists(), err


def test_patient_show_png_is_a_folder(tmp_path, capsys):
    code, err = _run(["patient", "show", "test:0", "--png", str(tmp_path)], capsys)
    assert code == 2 and "--png" in err and "is a folder" in err, err


def _label_map(path, spacing_mm, kidney_voxels=None):
    import SimpleITK as sitk

    a = np.zeros((40, 40, 40), np.uint8)
    a[5:35, 5:35, 5:35] = 200
    if kidney_voxels is None:
        a[15:25, 15:25, 15:25] = 2
    else:
        a[20, 20, 20] = 2
    img = sitk.GetImageFromArray(a)
    img.SetSpacing([spacing_mm] * 3)
    sitk.WriteImage(img, str(path))
    return path


@pytest.mark.parametrize(
    "spacing,words",
    [
        (100.0, ["spacing", "100", "0.1-10 mm"]),
        (0.002, ["spacing", "in metres"]),
    ],
    ids=["spacing_100_mm", "spacing_in_metres"],
)
def test_label_map_spacing_is_named(tmp_path, capsys, spacing, words):
    path = _label_map(tmp_path / "map.nii.gz", spacing)
    code, err = _run(["patient", "info", str(path)], capsys)
    assert code == 2 and "patient spec" in err and "map.nii.gz" in err, err
    for w in words:
        assert w in err, err
    out = tmp_path / "scan"
    code, err = _run(["scan", "--patient", str(path), "--out", str(out), "--no-record"], capsys)
    assert code == 2 and "--patient" in err and "spacing" in err, err
    assert not out.exists()


def test_label_map_folder_spacing_is_named(tmp_path, capsys):
    folder = tmp_path / "masks"
    folder.mkdir()
    _label_map(folder / "kidney_right.nii.gz", 50.0)
    code, err = _run(["patient", "info", str(folder)], capsys)
    assert code == 2 and "kidney_right.nii.gz" in err and "spacing" in err, err


def test_one_voxel_kidney_is_named(tmp_path, capsys):
    import SimpleITK as sitk

    # A body of human size (300 x 220 mm at 2 mm voxels: a smaller one is named for that).
    a = np.zeros((20, 120, 160), np.uint8)  # (k, j, i)
    a[2:18, 5:115, 5:155] = 200
    a[10, 60, 40] = 2
    img = sitk.GetImageFromArray(a)
    img.SetSpacing([2.0] * 3)
    path = tmp_path / "tiny.nii.gz"
    sitk.WriteImage(img, str(path))
    code, err = _run(["patient", "info", str(path)], capsys)
    assert code == 2 and "too small" in err and "Surface level" not in err, err


def test_phantom_spec_needs_an_integer(tmp_path, capsys):
    out = tmp_path / "pics"
    code, err = _run(["imaging-pictures", "--patient", "phantom:abc", "--out", str(out)], capsys)
    assert code == 2 and "--patient" in err and "phantom:N" in err, err
    assert "invalid literal" not in err and not out.exists()


@pytest.mark.parametrize("views", ["-2", "-1"])
def test_negative_views(tmp_path, capsys, views):
    out = tmp_path / "pics"
    code, err = _run(["imaging-pictures", "--views", views, "--out", str(out)], capsys)
    assert code == 2 and "--views" in err and not out.exists(), err


def test_segmenter_fine_tune_seed_out_of_range(tmp_path, capsys):
    """PyTorch's generator refuses 2**64: a traceback once the frames were read."""
    out = tmp_path / "tuned"
    argv = ["segmenter", "fine-tune", "--frames", str(tmp_path), "--out", str(out)]
    code, err = _run([*argv, "--seed", str(2**64)], capsys)
    assert code == 2 and "--seed: expected an integer 0-4294967295" in err, err
    assert not out.exists()


def test_render_diagram_negative_depth(tmp_path, capsys):
    out = tmp_path / "d.svg"
    code, err = _run(["render-diagram", "--depth", "-1", "--out", str(out)], capsys)
    assert code == 2 and "--depth" in err and not out.exists(), err


@pytest.mark.parametrize(
    "extra, flag",
    [
        (["--depth", "3"], "--depth"),
        (["--patient", "test:7"], "--patient"),
        (["--scenarios-file", "other.scenarios.yaml"], "--scenarios-file"),
        (["--scenario", "other"], "--scenario"),
    ],
    ids=["depth", "patient", "scenarios_file", "scenario"],
)
def test_render_diagram_all_refuses_what_it_would_ignore(capsys, extra, flag):
    """--all draws each committed picture with its own patient and depth on the default
    scenario: a --depth or --patient given with it is named, not silently dropped."""
    code, err = _run(["render-diagram", "--all", "--check", *extra], capsys)
    assert code == 2 and f"{flag}:" in err and "--all" in err, err


def test_render_diagram_when_graphviz_fails(tmp_path, capsys, failing_dot):
    """A Graphviz that fails (a broken install, a dot that cannot write) is one line with
    what dot said, not a CalledProcessError traceback, and nothing is left behind."""
    out = tmp_path / "out" / "d.svg"
    out.parent.mkdir()
    code, err = _run(["render-diagram", "--out", str(out)], capsys)
    assert code == 2 and "Graphviz 'dot' failed (exit 3): Error: layout" in err, err
    assert "Traceback" not in err and not any(out.parent.iterdir())


@pytest.mark.parametrize("name", ["d.pdf", "d"], ids=["pdf", "no_suffix"])
def test_render_diagram_bad_out(tmp_path, capsys, name):
    code, err = _run(["render-diagram", "--out", str(tmp_path / name)], capsys)
    assert code == 2 and "--out" in err and not any(tmp_path.iterdir()), err


def test_render_diagram_out_is_a_folder(tmp_path, capsys):
    code, err = _run(["render-diagram", "--out", str(tmp_path)], capsys)
    assert code == 2 and "--out" in err and "folder" in err, err


def test_template_info_path_is_a_folder(tmp_path, capsys):
    code, err = _run(["template", "info", str(tmp_path)], capsys)
    assert code == 2 and "folder" in err and "not found" not in err, err


def test_template_build_out_in_readonly_folder(readonly_dir, capsys):
    code, err = _run(
        ["template", "build", "--n", "2", "--out", str(readonly_dir / "t.npz")], capsys
    )
    assert code == 2 and "--out" in err, err


@pytest.mark.parametrize(
    "study,args,word",
    [
        ("starts", ["--starts", "0"], "--starts"),
        ("starts", ["--starts", "-3"], "--starts"),
        ("er-sweep", ["--ers", "0.2,3"], "--ers"),
        ("er-sweep", ["--ers", "a,b"], "--ers"),
        ("efficiency", ["--er", "2"], "--er"),
        ("efficiency", ["--er", "nan"], "--er"),
        ("er-sweep", ["--voxel", "0"], "--voxel"),
        ("er-sweep", ["--voxel", "1"], "--voxel"),
        ("efficiency", ["--recon-spacing", "-0.001"], "--recon-spacing"),
        ("er-sweep", ["--workers", "-1"], "--workers"),
        ("er-sweep", ["--seed", "-1"], "--seed"),
        ("er-sweep", ["--seed", str(2**63)], "--seed"),
        ("er-sweep", ["--set", "{controller: {desired_force: 25}}"], "controller.desired_force"),
        ("er-sweep", ["--scenario", "nope"], "'nope'"),
    ],
    ids=[
        "starts_0",
        "starts_negative",
        "ers_above_1",
        "ers_not_numbers",
        "er_2",
        "er_nan",
        "voxel_0",
        "voxel_1_m",
        "recon_negative",
        "workers_negative",
        "seed_negative",
        "seed_2_63",
        "force_above_ceiling",
        "unknown_scenario",
    ],
)
def test_study_bad_arguments_leave_no_folder(tmp_path, capsys, study, args, word):
    out = tmp_path / "study"
    code, err = _run(["study", study, "--patients", "test:0", "--out", str(out), *args], capsys)
    assert code == 2 and word in err, err
    assert not out.exists()


@pytest.mark.parametrize(
    "command",
    [["study", "er-sweep", "--patients", "test:0"], ["campaign", "--runs", "1"]],
    ids=["study", "campaign"],
)
def test_unreachable_scheduler_fails_fast(tmp_path, capsys, command):
    import socket

    with socket.socket() as s:  # a port with nobody listening
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out = tmp_path / "o"
    start = time.perf_counter()
    code, err = _run(
        [*command, "--out", str(out), "--scheduler", f"tcp://127.0.0.1:{port}"], capsys
    )
    assert time.perf_counter() - start < 10.0
    assert code == 2 and "--scheduler" in err and not out.exists(), err


def test_malformed_scheduler_address(tmp_path, capsys):
    code, err = _run(
        ["study", "er-sweep", "--out", str(tmp_path / "o"), "--scheduler", "tcp://nohost"], capsys
    )
    assert code == 2 and "--scheduler" in err and "tcp://HOST:PORT" in err, err


def test_demo_into_a_readonly_folder(readonly_dir, capsys):
    code, err = _run(["demo", "--out", str(readonly_dir / "demo")], capsys)
    assert code == 2 and "--out" in err and not (readonly_dir / "demo").exists(), err


def test_demo_out_is_a_file(tmp_path, capsys):
    target = tmp_path / "demo"
    target.write_text("keep")
    code, err = _run(["demo", "--out", str(target)], capsys)
    assert code == 2 and "--out" in err and target.read_text() == "keep", err


def test_demo_record_is_a_folder(tmp_path, capsys):
    out = tmp_path / "demo"
    code, err = _run(["demo", "--out", str(out), "--record", str(tmp_path)], capsys)
    assert code == 2 and "--record" in err and not out.exists(), err


@pytest.mark.parametrize("value", ["0", "-1", "nan"])
def test_demo_bad_duration(tmp_path, capsys, value):
    out = tmp_path / "demo"
    code, err = _run(["demo", "--out", str(out), "--duration", value], capsys)
    assert code == 2 and "--duration" in err and not out.exists(), err


def test_demo_unphysical_probe(tmp_path, capsys):
    out = tmp_path / "demo"
    code, err = _run(["demo", "--out", str(out), "--set", "{probe: {mass: 1000}}"], capsys)
    assert code == 2 and "probe.mass" in err and not out.exists(), err


def test_cohort_png_into_a_readonly_folder(readonly_dir, capsys):
    code, err = _run(["cohort", "--count", "1", "--png", str(readonly_dir / "c.png")], capsys)
    assert code == 2 and "--png" in err, err


@pytest.mark.parametrize("name", ["c.jpg", "c"], ids=["jpg", "no_suffix"])
def test_cohort_png_needs_png_suffix(tmp_path, capsys, name):
    code, err = _run(["cohort", "--count", "1", "--png", str(tmp_path / name)], capsys)
    assert code == 2 and "--png" in err and ".png" in err, err


def test_cohort_zero_count(capsys):
    code, err = _run(["cohort", "--count", "0"], capsys)
    assert code == 2 and "--count" in err, err


def test_campaign_into_a_readonly_folder(readonly_dir, capsys):
    code, err = _run(["campaign", "--runs", "1", "--out", str(readonly_dir / "c")], capsys)
    assert code == 2 and "--out" in err and not (readonly_dir / "c").exists(), err


def test_os_error_inside_a_command_is_one_line(tmp_path, capsys, monkeypatch):
    """An OSError the checks could not foresee (the disk fills during the run) still ends in
    one line naming the argument, exit status 2."""
    import drake_rus.template.cli as tcli

    def boom(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "t.npz"))

    monkeypatch.setattr(tcli, "subjects_from_cohort", boom)
    code, err = _run(["template", "build", "--n", "2", "--out", str(tmp_path / "t.npz")], capsys)
    assert code == 2 and "--out" in err and "no space left" in err, err
    assert err.count("\n") == 1 and "Traceback" not in err


def test_study_help_does_not_crash(capsys):
    for study in ("er-sweep", "starts", "efficiency", "paper"):
        with pytest.raises(SystemExit) as e:
            main(["study", study, "--help"])
        assert e.value.code == 0
    with pytest.raises(SystemExit) as e:
        main(["study", "--help"])
    assert e.value.code == 0 and "100%" in capsys.readouterr().out


def test_scan_patient_out_of_reach_is_one_line(tmp_path, capsys):
    """A bed inside the 1.5 m rule but out of the FR3's reach: the start planner's reason,
    naming --patient and patient.X_BPt, before any simulation."""
    out = tmp_path / "scan"
    code, err = _run(
        [
            "scan",
            "--patient",
            "test:0",
            "--out",
            str(out),
            "--no-record",
            "--set",
            "{patient: {X_BPt: {translation: [1.4, 0.0, 0.0]}}}",
        ],
        capsys,
    )
    assert code == 2 and "--patient" in err and "patient.X_BPt" in err and "reach" in err, err
    assert not out.exists()
