"""Templates from another population and the real body as a template-study patient (issue 18,
part 3): the population template's size differs from the repository's by the population
shift, it is cached by content, the real body's kidney gets a template distance, and bad
variant text is refused naming the field."""

import types

import numpy as np
import pytest

from drake_rus.cli import main
from drake_rus.experiments import analysis, keys, specs, templates
from drake_rus.paths import REPO_ROOT
from drake_rus.template import population as pop

# The real body (CI has ../shared beside the repository).
VH = str(REPO_ROOT.parent / "shared" / "anatomy" / "hubmap_vh_female")


@pytest.fixture
def template_cache(tmp_path, monkeypatch):
    monkeypatch.setenv(pop.CACHE_DIR_ENV, str(tmp_path / "cache"))
    return tmp_path / "cache" / "templates"


def _length_mm(template) -> float:
    return float(np.ptp(template.points[:, 0]) * 1e3)


def test_population_shape_params_shift_by_one_glodny_sd():
    base, long, short, slim = (pop.parse_population(n) for n in ("base", "long", "short", "slim"))
    for k in range(5):
        b, lo, sh, sl = (pop.population_shape_params(p, k) for p in (base, long, short, slim))
        # The same person, 12.2 mm (Glodny 2009's SD) longer / shorter, with the allometry.
        assert (lo.length - b.length) * 1e3 == pytest.approx(12.2)
        assert (b.length - sh.length) * 1e3 == pytest.approx(12.2)
        assert (lo.width - b.width) * 1e3 == pytest.approx(0.08 * 12.2)
        assert (lo.thickness - b.thickness) * 1e3 == pytest.approx(0.03 * 12.2)
        assert sl.length == b.length and (b.width - sl.width) * 1e3 == pytest.approx(4.5)
        assert lo.bend == b.bend and lo.lobulation == b.lobulation
    # Other people than the training cohort: not the generator's train:0 kidney.
    from drake_rus.anatomy.generator import sample_patient_params

    assert (
        sample_patient_params(1_000_000).kidney.length
        != pop.population_shape_params(base, 0).length
    )
    assert pop.parse_population("length-2sd").length_shift() == pytest.approx(-0.0244)


def test_population_template_size_and_cache(template_cache):
    """population:long's template is about one SD (12.2 mm) longer than the same people's
    (population:base) and than the repository's mean template (108.5 mm kidneys); it is
    built once and then read from the cache."""
    mean = templates.template_variant(None, "mean")
    long = templates.template_variant(None, "population:long:3")
    path = pop.population_template_path("long", n=3)
    assert path.parent == template_cache and path.is_file()
    assert path.with_suffix(".json").is_file()
    base = templates.template_variant(None, "population:base:3")
    shift = _length_mm(long) - _length_mm(base)
    assert shift == pytest.approx(12.2, abs=2.0)
    # Against the repository's template: the shift plus the 3-person sample's offset.
    assert 8.0 < _length_mm(long) - _length_mm(mean) < 18.0
    assert abs(_length_mm(base) - _length_mm(mean)) < 5.0
    # Cached: the second request reads the file (no build), the same content-addressed name;
    # another population or subject count has another name.
    mtime = path.stat().st_mtime_ns
    assert pop.population_template("long", n=3) == path and path.stat().st_mtime_ns == mtime
    assert pop.population_template_path("short", n=3) != path
    assert pop.population_template_path("long", n=4) != path
    # Unit normals, outward like the mean template's (same canonical frame).
    np.testing.assert_allclose(np.linalg.norm(long.normals, axis=1), 1.0, atol=1e-6)
    _, idx = (
        __import__("scipy.spatial", fromlist=["cKDTree"]).cKDTree(mean.points).query(long.points)
    )
    assert np.mean(np.sum(long.normals * mean.normals[idx], axis=1)) > 0.8


@pytest.mark.parametrize(
    "variant, words",
    [
        ("population:huge", ["template variant 'population:huge'", "population", "long"]),
        ("population:long:0", ["template variant 'population:long:0'", "subjects"]),
        ("population:", ["template variant 'population:'", "population:NAME"]),
        ("scale-0", ["template variant 'scale-0'", "scale"]),
        ("median", ["template variant", "population:NAME", "'median'"]),
    ],
)
def test_bad_variant_is_named(variant, words):
    with pytest.raises(ValueError) as e:
        specs.template_tasks(["test:0"], specs.StudyOptions(), 0.6, [variant])
    for w in words:
        assert w in str(e.value)


def test_bad_variant_and_posture_on_the_command_line(tmp_path, capsys):
    assert (
        main(
            [
                "study",
                "template",
                "--patients",
                "test:0",
                "--variants",
                "mean,population:huge",
                "--workers",
                "0",
                "--out",
                str(tmp_path / "a"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "--variants" in err and "population:huge" in err
    assert (
        main(
            [
                "study",
                "template",
                "--patients",
                "test:0@sideways",
                "--workers",
                "0",
                "--out",
                str(tmp_path / "b"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "--patients" in err and "@sideways" in err
    assert (
        main(
            [
                "study",
                "starts",
                "--patients",
                "test:0@decubitus",
                "--workers",
                "0",
                "--out",
                str(tmp_path / "c"),
            ]
        )
        == 2
    )
    assert "only read by study template" in capsys.readouterr().err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_real_body_tasks_posture_and_run_ids():
    patients = specs.expand_patients(f"test:0-1,{VH},{VH}@decubitus")
    assert patients == ["test:0", "test:1", VH, VH + "@decubitus"]
    tasks = specs.template_tasks(
        patients, specs.StudyOptions(posture="supine"), 0.6, ["mean", "population:long", "loo"]
    )
    real = [t for t in tasks if t.patient == VH]
    # loo is for training patients only; the real body gets mean and population, both
    # postures, with distinct run ids.
    assert sorted((t.template_variant, t.posture) for t in real) == [
        ("mean", "left_lateral_decubitus"),
        ("mean", "supine"),
        ("population:long", "left_lateral_decubitus"),
        ("population:long", "supine"),
    ]
    ids = [keys.run_id(t) for t in tasks]
    assert len(ids) == len(set(ids)) == 8
    assert any(i.endswith("shared-anatomy-hubmap-vh-female__erk060__t-mean__lld") for i in ids)
    assert specs.patient_kind(VH) == "real" and specs.patient_kind("train:3") == "generated"


@pytest.fixture(scope="module")
def vh_female():
    from drake_rus.anatomy import load_patient

    return load_patient(VH, voxel_size=0.002, progress=False)


def test_template_distance_on_the_real_kidney(vh_female):
    """The template record of a run on the Visible Human female: her kidney (112.5 mm,
    docs/facts) in its canonical frame, the mean template about 5 mm from it, a template
    further off in size further away (the record the study plots)."""
    from drake_rus.scenario import LoadScenario

    X_BPt = LoadScenario().patient.X_BPt.GetDeterministicValue()
    kp = types.SimpleNamespace(patient=vh_female, X_BPt=X_BPt, X_BK_true=vh_female.X_BK(X_BPt))
    rec = templates.template_record(
        "mean", templates.template_variant(None, "mean"), kp, "supine", VH
    )
    assert rec["patient_kind"] == "real" and rec["posture"] == "supine"
    assert rec["kidney_extent_mm"][0] == pytest.approx(112.5, abs=1.5)
    assert rec["template_extent_mm"][0] == pytest.approx(106.7, abs=0.5)
    assert 3.0 < rec["template_distance_mm"] < 7.0
    small = templates.template_record(
        "scale-0.8", templates.template_variant(None, "scale-0.8"), kp, "supine", VH
    )
    assert small["template_distance_mm"] > rec["template_distance_mm"] + 2.0
    # The analysis puts the real body in its own group beside the generated patients.
    runs = [
        dict(rec, patient=VH, er=0.6, e_trans_mm=7.8, e_rot_x_deg=16.0),
        dict(small, patient=VH, er=0.6, e_trans_mm=12.0, e_rot_x_deg=22.0),
        dict(
            rec,
            patient=VH,
            er=0.6,
            e_trans_mm=9.0,
            e_rot_x_deg=30.0,
            posture="left_lateral_decubitus",
        ),
    ]
    runs += [
        {
            "patient": f"test:{k}",
            "er": 0.6,
            "template_variant": v,
            "template_distance_mm": d + 0.1 * k,
            "e_trans_mm": d + k,
            "e_rot_x_deg": 2.0 + k,
        }
        for k in range(3)
        for v, d in (("mean", 2.0), ("population:long", 3.0))
    ]
    an = analysis.analyze_template(runs)
    assert an["groups"] == ["generated", "hubmap_vh_female", "hubmap_vh_female, decubitus"]
    real_rows = [r for r in an["rows"] if r["group"] == "hubmap_vh_female"]
    assert [r["variant"] for r in real_rows] == ["mean", "scale-0.8"]
    assert real_rows[0]["e_trans_mm_mean"] == 7.8
    # The generated patients' trend line ignores the real body; trend_all includes it.
    assert an["trend"]["e_trans_mm"]["runs"] == 6 and an["trend_all"]["e_trans_mm"]["runs"] == 9
    assert sum(b["n"] for b in an["bins"]) == 9
    assert sum(b["real_runs"] for b in an["bins"]) == 3


def test_cli_template_build_population(tmp_path, capsys):
    out = tmp_path / "long.npz"
    assert (
        main(
            [
                "template",
                "build",
                "--population",
                "long",
                "--n",
                "2",
                "--points",
                "300",
                "--voxel-mm",
                "2",
                "--out",
                str(out),
                "--quiet",
            ]
        )
        == 0
    )
    import json

    summary = json.loads(capsys.readouterr().out)
    assert summary["n_subjects"] == 2 and summary["source"] == "population:long"
    # The sampled lengths: the first two population kidneys, each 12.2 mm longer.
    base = [pop.population_shape_params(pop.POPULATIONS["base"], k).length for k in (0, 1)]
    assert summary["sampled_length_mm"]["mean"] == pytest.approx(
        np.mean(base) * 1e3 + 12.2, abs=0.01
    )
    assert (tmp_path / "long_convergence.png").is_file()
    assert main(["template", "build", "--population", "huge", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "--population" in err and "huge" in err
