"""Template-mismatch study (issue 18, part 3) in kinematic mode: the variants, the template's
distance from the patient, the analysis, and one tiny study through the CLI."""

import json

import numpy as np
import pytest

from drake_rus.cli import main
from drake_rus.experiments import analysis, keys, specs, templates
from drake_rus.experiments import results as study_results


def test_variants_tasks_and_run_ids():
    o = specs.StudyOptions()
    tasks = specs.template_tasks(["test:0", "train:3"], o, 0.6)
    ids = [keys.run_id(t) for t in tasks]
    # loo only for the training patient.
    n = len(specs.TEMPLATE_VARIANTS)
    assert len(ids) == len(set(ids)) == (n - 1) + n
    assert "template__test-0__erk060__t-population-long" in ids
    assert "template__train-3__erk060__t-loo" in ids
    assert "template__test-0__erk060__t-scale-1.1" in ids
    for bad in ("scale", "single:x", "median"):
        with pytest.raises(ValueError, match="template variant"):
            specs.template_tasks(["test:0"], o, 0.6, [bad])


def test_template_variants_geometry():
    mean = templates.template_variant(None, "mean")
    big = templates.template_variant(None, "scale-1.1")
    np.testing.assert_allclose(big.points, 1.1 * mean.points)
    single = templates.template_variant(None, "single:0")
    loo = templates.template_variant(None, "loo", "train:3")
    for t in (single, loo):
        assert t.points.shape == mean.points.shape and t.modes is None
        np.testing.assert_allclose(np.linalg.norm(t.normals, axis=1), 1.0)
        np.testing.assert_allclose(t.points.mean(axis=0), 0.0, atol=1e-12)
        # Outward like the mean's.
        assert np.mean(np.sum(t.normals * mean.normals, axis=1)) > 0.8
    # The leave-one-out mean is close to the mean (19 of its 20 shapes).
    assert np.mean(np.linalg.norm(loo.points - mean.points, axis=1)) < 0.002
    with pytest.raises(ValueError, match="loo"):
        templates.template_variant(None, "loo", "test:0")


def test_analyze_template_trend():
    res = [
        {
            "patient": f"test:{k}",
            "er": 0.6,
            "template_variant": v,
            "template_distance_mm": d + 0.1 * k,
            "e_trans_mm": 2 * (d + 0.1 * k) + 1,
            "e_rot_x_deg": 3.0 + k,
        }
        for k in range(4)
        for v, d in (("mean", 2.0), ("scale-0.9", 6.0))
    ]
    an = analysis.analyze_template(res)
    assert [r["variant"] for r in an["rows"]] == ["mean", "scale-0.9"]
    assert an["trend"]["e_trans_mm"]["slope_per_mm"] == pytest.approx(2.0)
    assert an["trend"]["e_trans_mm"]["r"] == pytest.approx(1.0)
    assert an["rows"][1]["e_trans_mm_mean"] == pytest.approx(2 * 6.15 + 1)


def test_tiny_template_study(tmp_path):
    code = main(
        [
            "study",
            "template",
            "--patients",
            "test:2",
            "--variants",
            "mean,scale-0.9",
            "--er",
            "0.6",
            "--out",
            str(tmp_path),
            "--workers",
            "0",
            "--no-progress",
            "--set",
            "{localization: {max_points: 1500}}",
        ]
    )
    assert code == 0
    runs = study_results.load_study_results(tmp_path, "template")
    d = {r["template_variant"]: r["template_distance_mm"] for r in runs}
    assert d["scale-0.9"] > d["mean"] > 0
    table = json.loads((tmp_path / "template.json").read_text())
    assert len(table["rows"]) == 2
    report = (tmp_path / "report.md").read_text()
    assert "## Template mismatch" in report and "registration: `seed`" in report
    assert (tmp_path / "fig_template_mismatch.png").stat().st_size > 0
    assert (
        main(
            [
                "study",
                "template",
                "--patients",
                "test:2",
                "--variants",
                "bogus",
                "--workers",
                "0",
                "--out",
                str(tmp_path / "x"),
            ]
        )
        == 2
    )
