"""Bad-input corpus, anatomy and patient input: anatomy that cannot exist (a kidney outside
the body, cut by the volume's edge, inside the liver; a body 18 mm wide; meshes in two
units), breathing and placement that cannot be, and inputs that used to hang or trace back
(a named pipe as --patient, an empty list of contact sections, a probe mesh hint of 1 um, a
cohort of a million). Each gives exit status 2 and one line naming the field, argument or
file, and writes nothing to --out."""

import os
import threading

import numpy as np
import pytest
import SimpleITK as sitk
import trimesh

from drake_rus.cli import main

# The patients are small (2 mm label maps, meshes exported at 4 mm voxels) but human-sized,
# so that only the broken property fails.
EXPORT = ["--voxel-mm", "4"]


def _run(argv, capsys):
    code = main(argv)
    return code, capsys.readouterr().err


def _ellipsoid(center, semi):
    m = trimesh.creation.icosphere(subdivisions=3)
    return trimesh.Trimesh(m.vertices * np.asarray(semi) + np.asarray(center), m.faces)


def _mesh_case(root, name, kidney_center=(-60, 0, -40), kidney_scale=1.0, liver=None):
    """Skin 300 x 600 x 220 mm and a right kidney 110 mm long, STL in the LSA body frame (mm
    unless scaled); ``liver``: (centre, semi-axes) of a liver mesh."""
    d = root / name
    d.mkdir()
    _ellipsoid((0, 0, 0), (150, 300, 110)).export(d / "skin.stl")
    _ellipsoid(
        np.multiply(kidney_center, kidney_scale), np.multiply((28, 55, 20), kidney_scale)
    ).export(d / "kidney_right.stl")
    if liver is not None:
        _ellipsoid(*liver).export(d / "liver.stl")
    return d


def _label_map_case(root, name, *, spacing=2.0, kidney_z=0.0, liver_around=False):
    """A TotalSegmentator-like map (LPS grid, 320 x 240 x 160 mm at 2 mm): body 200, right
    kidney 2 (110 mm long along z, centred at ``kidney_z`` mm), liver 5 around it."""
    n = (160, 120, 80)
    ii, jj, kk = np.meshgrid(*[np.arange(s) for s in n], indexing="ij")
    x, y, z = (ii - 80) * 2.0, (jj - 60) * 2.0, (kk - 40) * 2.0
    lab = np.zeros(n, np.uint8)
    lab[(x / 150) ** 2 + (y / 100) ** 2 <= 1] = 200
    if liver_around:
        lab[(((x + 75) / 50) ** 2 + ((y - 30) / 40) ** 2 + (z / 75) ** 2 <= 1) & (lab == 200)] = 5
    lab[((x + 75) / 28) ** 2 + ((y - 40) / 20) ** 2 + ((z - kidney_z) / 55) ** 2 <= 1] = 2
    img = sitk.GetImageFromArray(np.ascontiguousarray(lab.transpose(2, 1, 0)))
    img.SetSpacing((spacing,) * 3)
    img.SetOrigin((-160.0, -120.0, -80.0))
    path = root / f"{name}.nii.gz"
    sitk.WriteImage(img, str(path))
    return path


@pytest.fixture(scope="module")
def cases(tmp_path_factory):
    root = tmp_path_factory.mktemp("anatomy_cases")
    return {
        "outside": _mesh_case(root, "outside", kidney_center=(-130, 0, -20)),
        "liver_mesh": _mesh_case(root, "liver_mesh", liver=((-60, 45, -40), (60, 40, 40))),
        "metres": _mesh_case(root, "metres", kidney_scale=1e-3),
        "cut": _label_map_case(root, "cut", kidney_z=-60.0),
        "in_liver": _label_map_case(root, "in_liver", liver_around=True),
        "tiny": _label_map_case(root, "tiny", spacing=0.1),
    }


# (case id, fixture key, words the message must contain)
ANATOMY_CASES = [
    (
        "kidney_outside_the_body",
        "outside",
        ["patient spec", "outside", "the kidney is not inside the body", "% of the voxels"],
    ),
    (
        "kidney_cut_by_the_volume_edge",
        "cut",
        [
            "cut.nii.gz",
            "cut by the label volume's edge",
            "inferior face",
            "ml of the kidney is imaged",
        ],
    ),
    (
        "kidney_inside_the_liver_label",
        "in_liver",
        ["in_liver.nii.gz", "the kidney lies inside the liver"],
    ),
    (
        "kidney_overlapping_the_liver_mesh",
        "liver_mesh",
        ["liver_mesh", "the kidney overlaps the liver", "liver.stl"],
    ),
    (
        "label_map_spacing_18_mm_body",
        "tiny",
        ["tiny.nii.gz", "voxel spacing (0.1, 0.1, 0.1) mm", "mm wide"],
    ),
    (
        "kidney_in_metres_skin_in_mm",
        "metres",
        ["kidney_right.stl", "skin.stl", "kidney mesh seems to be in m and the skin mesh in mm"],
    ),
]


@pytest.mark.parametrize("case,key,words", ANATOMY_CASES, ids=[c[0] for c in ANATOMY_CASES])
def test_anatomy_that_cannot_exist_is_refused(tmp_path, capsys, cases, case, key, words):
    out = tmp_path / "export"
    code, err = _run(["patient", "export", str(cases[key]), "--out", str(out), *EXPORT], capsys)
    assert code == 2, err
    assert err.startswith("drake-rus patient: error:") and err.count("\n") == 1, err
    for w in words:
        assert w in err, err
    assert "Traceback" not in err
    assert not out.exists()


def test_a_scan_of_meshes_in_two_units_writes_nothing(tmp_path, capsys, cases):
    """The kidney STL in metres with the skin in mm used to make the rasteriser ask for
    7 PiB; now the scan stops before any voxel grid, naming both files."""
    out = tmp_path / "scan"
    code, err = _run(
        ["scan", "--patient", str(cases["metres"]), "--out", str(out), "--no-record"], capsys
    )
    assert code == 2 and "--patient" in err and "kidney_right.stl" in err, err
    assert "seems to be in m" in err
    assert not out.exists()


# (case id, --set overrides, words the message must contain)
SCENARIO_CASES = [
    (
        "breath_hold_longer_than_period",
        "{patient: {motion: {breathing: {enabled: true, hold_period: 12, hold_duration: 20}}}}",
        ["patient.motion.breathing.hold_duration", "hold_duration < hold_period", "= 20"],
    ),
    (
        "no_breath_between_holds",
        "{patient: {motion: {breathing: {enabled: true, hold_period: 12, hold_duration: 11.5}}}}",
        ["patient.motion.breathing.hold_duration", "at least once", ">= 2 s"],
    ),
    (
        "first_hold_after_half_a_breath",
        "{patient: {motion: {breathing: {enabled: true, hold_period: 12, first_hold: 0.5}}}}",
        ["patient.motion.breathing.first_hold"],
    ),
    (
        "breathing_amplitude_not_human",
        "{patient: {motion: {breathing: {enabled: true, amplitude: 0.08}}}}",
        ["patient.motion.breathing.amplitude", "43 mm", "Schwartz 1994"],
    ),
    (
        "breathing_rate_not_human",
        "{patient: {motion: {breathing: {enabled: true, rate_per_min: 60}}}}",
        ["patient.motion.breathing.rate_per_min", "Pham 2013"],
    ),
    (
        "patient_upside_down",
        "{patient: {X_BPt: {translation: [0.55, 0, 0], rotation: !Rpy {deg: [180, 0, 0]}}}}",
        ["patient.X_BPt", "face up", "180.0 deg"],
    ),
    (
        "patient_on_its_side_bed",
        "{patient: {X_BPt: {translation: [0.55, 0, 0], rotation: !Rpy {deg: [0, 30, 0]}}}}",
        ["patient.X_BPt", "30.0 deg"],
    ),
    (
        "no_contact_sections",
        "{contact: {patient_section_half_lengths: []}}",
        ["contact.patient_section_half_lengths", "at least 1"],
    ),
    (
        "probe_mesh_hint_1_um",
        "{contact: {probe_resolution_hint: 1e-6}}",
        ["contact.probe_resolution_hint", "physical range", "probe face"],
    ),
    (
        "patient_mesh_hint_1_um",
        "{contact: {patient_resolution_hint: 1e-6}}",
        ["contact.patient_resolution_hint", "physical range"],
    ),
]


@pytest.mark.parametrize("case,overrides,words", SCENARIO_CASES, ids=[c[0] for c in SCENARIO_CASES])
def test_scan_refuses_impossible_breathing_placement_and_meshes(
    tmp_path, capsys, case, overrides, words
):
    out = tmp_path / "scan"
    code, err = _run(["scan", "--patient", "test:0", "--set", overrides, "--out", str(out)], capsys)
    assert code == 2, err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for w in words:
        assert w in err, err
    assert not out.exists()


def test_a_level_bed_turned_about_its_normal_is_accepted():
    """The bed may lie in any direction on the floor: a yaw keeps z_Pt up."""
    from drake_rus.scenario import ApplyOverrides, CheckScenario, LoadScenario

    CheckScenario(
        ApplyOverrides(
            LoadScenario(),
            "{patient: {X_BPt: {translation: [0.55, 0, 0], rotation: !Rpy {deg: [0, 0, 90]}}}}",
        )
    )


def _refused_quickly(argv, capsys, seconds=120.0):
    """Runs the command in a thread: a read of a pipe would block it forever."""
    result = {}
    thread = threading.Thread(target=lambda: result.update(code=main(argv)), daemon=True)
    thread.start()
    thread.join(seconds)
    assert not thread.is_alive(), f"{argv} did not return within {seconds} s"
    return result["code"], capsys.readouterr().err


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no named pipes here")
def test_a_named_pipe_as_patient_is_refused_before_it_is_opened(tmp_path, capsys):
    pipe = tmp_path / "seg.nii.gz"
    os.mkfifo(pipe)
    out = tmp_path / "scan"
    code, err = _refused_quickly(["scan", "--patient", str(pipe), "--out", str(out)], capsys)
    assert code == 2 and "--patient" in err and "named pipe" in err, err
    assert not out.exists()
    # A pipe with a label map's name inside a patient folder is not read either.
    folder = tmp_path / "folder"
    folder.mkdir()
    os.mkfifo(folder / "labels.nii.gz")
    code, err = _refused_quickly(["patient", "info", str(folder)], capsys)
    assert code == 2 and "no kidney" in err, err


def test_a_device_as_patient_is_refused(capsys):
    if not os.path.exists("/dev/null"):
        pytest.skip("no /dev/null")
    code, err = _refused_quickly(["patient", "info", "/dev/null"], capsys)
    assert code == 2 and "patient spec" in err and "a device" in err, err


COHORT_CASES = [
    ("a_million_patients", ["--count", "1000000"], ["--count", "at most 1000", "--fast"]),
    ("a_million_fast", ["--count", "1000000", "--fast"], ["--count", "at most 20000"]),
    (
        "picture_of_500",
        ["--count", "500", "--png", "overview.png"],
        ["--count", "at most 100 kidneys"],
    ),
]


@pytest.mark.parametrize("case,args,words", COHORT_CASES, ids=[c[0] for c in COHORT_CASES])
def test_cohort_count_is_bounded_with_its_reason(tmp_path, capsys, case, args, words):
    args = [a if a != "overview.png" else str(tmp_path / a) for a in args]
    code, err = _run(["cohort", "--split", "train", *args], capsys)
    assert code == 2, err
    for w in words:
        assert w in err, err
    assert not list(tmp_path.iterdir())


def test_an_empty_section_list_built_in_code_names_the_field():
    """A scenario built in code skips the YAML schema: the contact body still names it."""
    import dataclasses

    from drake_rus.patient_body import ContactSection
    from drake_rus.scenario import LoadScenario

    contact = dataclasses.replace(LoadScenario().contact, patient_section_half_lengths=[])
    with pytest.raises(ValueError, match="contact.patient_section_half_lengths"):
        ContactSection(None, contact)
