"""The segmenter's inference-side options: the lateral mirror average, the minimum region
area, and the validation study's variants and choice (benchmarks/segmenter_inference.py)."""

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from benchmarks.segmenter_inference import (
    PLAIN,
    choose,
    choose_edge_threshold,
    choose_test_time,
    draw_seeds,
    interval_tables,
    intervals_json,
    paired_intervals,
    parse_edge_thresholds,
    score_settings,
    score_variants,
    share_text,
    variant_masks,
)
from benchmarks.segmenter_inference import main as segmenter_inference_main
from drake_rus.config_schema import ScenarioError
from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.emulator import EmulatorModel
from drake_rus.imaging.onnx_backend import (
    OnnxSegmenter,
    drop_small_regions,
    ensemble_average,
    mirror_average,
)
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.imaging.training.evaluation import make_source_frames
from drake_rus.io_utils import dumps_strict
from drake_rus.scenario import LoadScenario


def test_mirror_average_averages_the_mirrored_run_mirrored_back():
    """A 'model' that is not mirror-symmetric (a left-to-right ramp times the input): the
    average is that of the input's map and of its mirror's map flipped back."""
    rng = np.random.default_rng(0)
    x = rng.random((1, 1, 6, 8)).astype(np.float32)
    ramp = np.linspace(0.0, 1.0, 8, dtype=np.float32)

    def run(inp):
        return inp[0, 0] * ramp

    want = 0.5 * (x[0, 0] * ramp + (x[0, 0, :, ::-1] * ramp)[:, ::-1])
    got = mirror_average(run, x)
    np.testing.assert_allclose(got, want, rtol=1e-6)
    assert got.dtype == np.float32 and got.shape == (6, 8)
    # The average of a mirror pair is itself mirror-symmetric in the input.
    np.testing.assert_allclose(mirror_average(run, x[..., ::-1])[:, ::-1], got, rtol=1e-6)
    # A symmetric model is left unchanged.
    np.testing.assert_allclose(mirror_average(lambda inp: inp[0, 0] * 2.0, x), 2.0 * x[0, 0])


@pytest.mark.parametrize("depth", [0.10, 0.25])
def test_mirror_averaged_segmenter_is_mirror_equivariant(depth):
    """With the mirror average, the mirrored frame's probability and mask are the frame's
    mirrored (the fan and the physical canvas are symmetric about the beam axis); the model
    alone is not."""
    cfg = ImagingConfig(depth=depth, segmenter="onnx", onnx_mirror_average=True)
    g = ProbeGeometry.from_config(cfg)
    seg = OnnxSegmenter.from_config(cfg, g)
    assert seg.mirror_average
    frames = make_source_frames("phantom:5001", EmulatorModel.from_config(cfg, g), 6, seed=1)
    image = max(frames, key=lambda f: f[1].sum())[0]  # the view with the most kidney
    mirrored = np.ascontiguousarray(image[:, ::-1])
    p, q = seg.model_probability(image), seg.model_probability(mirrored)
    np.testing.assert_allclose(q, p[:, ::-1], atol=1e-4)
    mask = seg(image)
    assert mask.sum() * g.pixel_area > 5e-4
    assert np.mean(seg(mirrored) == mask[:, ::-1]) > 0.999
    seg.mirror_average = False
    p, q = seg.model_probability(image), seg.model_probability(mirrored)
    assert np.abs(q - p[:, ::-1]).max() > 1e-2


def test_small_regions_are_dropped(monkeypatch):
    """Two blobs of the kidney probability: a minimum region area between their sizes keeps
    the large one only, one above both leaves no kidney; the default 0 keeps both."""
    cfg = ImagingConfig(depth=0.15, segmenter="onnx")
    g = ProbeGeometry.from_config(cfg)
    seg = OnnxSegmenter.from_config(cfg, g)
    h, w = seg.input_shape[2:]
    prob = np.zeros((h, w), np.float32)
    prob[20:40, 46:66] = 0.9  # 20 x 20 canvas pixels of 2.4 mm: ~23 cm^2
    prob[50:53, 55:58] = 0.9  # 3 x 3: ~0.5 cm^2
    monkeypatch.setattr(OnnxSegmenter, "model_probability", lambda self, image: prob)
    image = np.zeros(g.image_shape, np.uint8)
    areas = [m.sum() * g.pixel_area for m in seg.candidates(image)]
    assert len(areas) == 2 and areas[0] > 20e-4 and areas[1] < 1e-4
    seg.min_region_area = 2e-4
    kept = seg.candidates(image)
    assert len(kept) == 1 and kept[0].sum() * g.pixel_area == pytest.approx(areas[0])
    seg.min_region_area = 50e-4
    assert seg.candidates(image) == [] and not seg(image).any()
    masks = [np.ones((2, 2), bool), np.zeros((2, 2), bool), np.eye(2, dtype=bool)]
    assert [m.sum() for m in drop_small_regions(masks, 2)] == [4, 2]


def test_inference_fields_come_from_the_scenario_and_are_checked():
    imaging = LoadScenario(
        scenario_text="{imaging: {onnx_mirror_average: true, onnx_min_region_area: 1.0e-4}}"
    ).imaging
    g = ProbeGeometry.from_config(imaging)
    seg = OnnxSegmenter.from_config(imaging, g)
    assert seg.mirror_average and seg.min_region_area == 1.0e-4
    with pytest.raises(ScenarioError, match="onnx_min_region_area"):
        LoadScenario(scenario_text="{imaging: {onnx_min_region_area: -1.0}}")
    with pytest.raises(ValueError, match="onnx_min_region_area"):
        OnnxSegmenter(seg.path, g, seg.input_shape, min_region_area=float("nan"))


def test_variant_masks_of_one_probability(monkeypatch):
    """raw keeps every pixel above the threshold, lcc the largest region only, a minimum
    area above its size none; a lower threshold grows the mask; the threshold is restored."""
    cfg = ImagingConfig(depth=0.15, segmenter="onnx")
    g = ProbeGeometry.from_config(cfg)
    seg = OnnxSegmenter.from_config(cfg, g)
    h, w = seg.input_shape[2:]
    prob = np.zeros((h, w), np.float32)
    prob[20:40, 46:66] = 0.45
    prob[23:37, 49:63] = 0.8
    prob[50:53, 55:58] = 0.9
    masks = variant_masks(seg, prob, (0.4, 0.5), (1e-4, 100e-4))
    assert seg.threshold == 0.5
    big = masks[(0.5, "lcc")]
    assert masks[(0.5, "raw")].sum() > big.sum() > 0
    assert masks[(0.4, "lcc")].sum() > big.sum()
    assert np.array_equal(masks[(0.5, "lcc+min1")], big)
    assert not masks[(0.5, "lcc+min100")].any()


def test_choice_is_the_best_worst_preset_within_the_false_positive_margin():
    def rec(depth, variant_scores, has=True):
        return {"depth": depth, "has_kidney": has, "scores": variant_scores}

    a, b, c = PLAIN, ("on", 0.5, "lcc"), ("off", 0.4, "lcc")
    records = [
        rec(0.1, {a: 0.80, b: 0.85, c: 0.90}),
        rec(0.2, {a: 0.90, b: 0.92, c: 0.95}),
        rec(0.1, {a: False, b: False, c: True}, has=False),  # c: 100% false positives
        rec(0.2, {a: False, b: False, c: False}, has=False),
    ]
    by_depth = score_variants(records, lambda r: r["depth"])
    assert by_depth[0.1][c]["fp_rate"] == 1.0 and by_depth[0.1][a]["iou"] == 0.80
    best, worst = choose(by_depth)
    assert best == b and worst[b] == pytest.approx(0.85)
    # Within the tie margin the simpler (plain) one stays.
    records[0]["scores"][b] = 0.8005
    best, _ = choose(score_variants(records, lambda r: r["depth"]))
    assert best == PLAIN


def test_ensemble_average_is_the_pixelwise_mean():
    a = np.array([[0.2, 0.9], [0.6, 0.0]], np.float32)
    b = np.array([[0.4, 0.1], [0.6, 1.0]], np.float32)
    a0 = a.copy()
    got = ensemble_average([a, b])
    np.testing.assert_allclose(got, [[0.3, 0.5], [0.6, 0.5]], rtol=1e-6)
    assert got.dtype == np.float32 and np.array_equal(a, a0)  # inputs untouched
    np.testing.assert_array_equal(ensemble_average([a]), a)
    with pytest.raises(ValueError, match="one shape"):
        ensemble_average([a, np.zeros((2, 3), np.float32)])
    with pytest.raises(ValueError, match="at least one"):
        ensemble_average([])


def test_ensemble_segmenter_averages_its_two_models(tmp_path):
    """With ``onnx_ensemble_model`` the probability is the mean of the two models' (the
    shipped int8 model and its fp32 master, which differ slightly), on the mirror too; a
    second model on another canvas, the same file or a missing file is refused naming the
    field."""
    fp32 = "models/segmenter/kidney_unet.onnx"
    cfg = ImagingConfig(depth=0.15, segmenter="onnx", onnx_ensemble_model=fp32)
    g = ProbeGeometry.from_config(cfg)
    seg = OnnxSegmenter.from_config(cfg, g)
    assert seg.ensemble is not None and seg.ensemble.path.name == "kidney_unet.onnx"
    frames = make_source_frames("phantom:5001", EmulatorModel.from_config(cfg, g), 4, seed=1)
    image = max(frames, key=lambda f: f[1].sum())[0]
    x = seg.preprocess(image)
    pa, pb = seg._run(x), seg.ensemble._run(x)
    assert np.abs(pa - pb).max() > 1e-3  # two different models
    fan = seg.canvas.fan_mask
    np.testing.assert_allclose(seg.model_probability(image), 0.5 * (pa + pb) * fan, atol=1e-6)
    seg.mirror_average = True
    want = 0.5 * (
        0.5 * (pa + pb) + 0.5 * (seg._run(x[..., ::-1]) + seg.ensemble._run(x[..., ::-1]))[:, ::-1]
    )
    np.testing.assert_allclose(seg.model_probability(image), want * fan, atol=1e-5)
    assert LoadScenario().imaging.onnx_ensemble_model == ImagingConfig().onnx_ensemble_model

    card = json.loads(Path(seg.ensemble.path).with_suffix(".json").read_text())
    card["canvas_top_mm"] = 0.0  # the same grid, 4 mm lower: another canvas
    other = tmp_path / "other.onnx"
    shutil.copy(seg.ensemble.path, other)
    other.with_suffix(".json").write_text(json.dumps(card))
    for bad, match in (
        (str(other), "onnx_ensemble_model: model other.onnx"),
        (cfg.onnx_model, "onnx_ensemble_model: names the same file"),
        (str(tmp_path / "missing.onnx"), "onnx_ensemble_model: ONNX model file not found"),
    ):
        with pytest.raises(ValueError, match=match):
            OnnxSegmenter.from_config(replace(cfg, onnx_ensemble_model=bad), g)


def test_test_time_choice_follows_the_written_rule():
    """Passes only with no loss beyond 0.001 anywhere, +0.002 at 100 mm, no more false
    positives and at most 3 times the cost; the cheaper of two within 0.001 is taken."""
    d1, d2 = 0.10, 0.15

    def table(v100, v150, imp):
        return {
            ("generated", d1): {"default": 0.850, **v100},
            ("generated", d2): {"default": 0.880, **v150},
            ("imported_like", d1): {"default": 0.800, **imp},
            ("imported_like", d2): {"default": 0.800, **imp},
        }

    iou = table(
        {"mirror": 0.8545, "ensemble": 0.855, "both": 0.860},
        {"mirror": 0.880, "ensemble": 0.8795, "both": 0.878},
        {"mirror": 0.80, "ensemble": 0.81, "both": 0.81},
    )
    fp = {d: {"default": 2, "mirror": 2, "ensemble": 1, "both": 2} for d in (d1, d2)}
    ms = {"default": 1.0, "mirror": 1.8, "ensemble": 1.4, "both": 3.2}
    chosen, verdict = choose_test_time(iou, fp, ms)
    # "both" gains most but costs x3.2 and loses 0.002 at 150 mm; the two others pass and
    # lie within 0.001 of each other at 100 mm: the cheaper is taken.
    assert "cost x3.20" in verdict["both"] and "generated 150 mm -0.0020" in verdict["both"]
    assert verdict["mirror"] == verdict["ensemble"] == "" and chosen == "ensemble"
    fp[d2]["ensemble"] = 3
    chosen, verdict = choose_test_time(iou, fp, ms)
    assert chosen == "mirror" and "false positives 150 mm 3 > 2" in verdict["ensemble"]
    iou[("generated", d1)]["mirror"] = 0.8515  # +0.0015 at 100 mm: not enough
    chosen, verdict = choose_test_time(iou, fp, ms)
    assert chosen == "default" and "100 mm gain +0.0015" in verdict["mirror"]


def test_edge_threshold_grows_the_same_regions_outward():
    """``onnx_edge_threshold`` below ``onnx_threshold`` draws each region's edge further
    out (every pixel of the default mask kept, more added next to it), finds the same
    regions, and equals the default when it is 0 or the threshold itself; outside (0, 1)
    it is refused naming the field."""
    cfg = ImagingConfig(depth=0.15, segmenter="onnx")
    g = ProbeGeometry.from_config(cfg)
    frames = make_source_frames("phantom:5001", EmulatorModel.from_config(cfg, g), 4, seed=1)
    image = max(frames, key=lambda f: f[1].sum())[0]
    base = OnnxSegmenter.from_config(cfg, g)
    low = OnnxSegmenter.from_config(replace(cfg, onnx_edge_threshold=0.3), g)
    same = OnnxSegmenter.from_config(replace(cfg, onnx_edge_threshold=cfg.onnx_threshold), g)
    assert base.edge_level == same.edge_level == cfg.onnx_threshold and low.edge_level == 0.3
    m0, m1 = base.candidates(image), low.candidates(image)
    assert len(m0) == len(m1) >= 1
    for a, b in zip(m0, m1):
        assert np.all(b[a]) and b.sum() > a.sum()
        # Only pixels next to the default region are added (within a canvas pixel).
        grown = a.copy()
        for _ in range(int(np.ceil(2.4e-3 / min(g.dx, g.dz))) + 1):
            grown |= np.roll(grown, 1, 0) | np.roll(grown, -1, 0)
            grown |= np.roll(grown, 1, 1) | np.roll(grown, -1, 1)
        assert not np.any(b & ~grown)
    np.testing.assert_array_equal(same(image), base(image))
    for bad in (1.0, 1.5, -0.2):
        with pytest.raises(ValueError, match="imaging.onnx_edge_threshold"):
            OnnxSegmenter.from_config(replace(cfg, onnx_edge_threshold=bad), g)
    with pytest.raises(ScenarioError, match="onnx_edge_threshold"):
        LoadScenario(scenario_text="{imaging: {onnx_edge_threshold: 1.5}}")


def test_edge_threshold_choice_follows_the_written_rule():
    """A value passes with no loss beyond 0.001 on either kind at any preset, +0.002 on the
    imported-like mean and no more false positives; the highest gain, or a value nearer
    the default within 0.001 of it; none: the default."""
    d1, d2 = 0.10, 0.15
    iou = {
        ("generated", d1): {0.5: 0.870, 0.45: 0.8695, 0.4: 0.869, 0.3: 0.860},
        ("generated", d2): {0.5: 0.900, 0.45: 0.8995, 0.4: 0.8992, 0.3: 0.890},
        ("imported_like", d1): {0.5: 0.750, 0.45: 0.759, 0.4: 0.7595, 0.3: 0.770},
        ("imported_like", d2): {0.5: 0.800, 0.45: 0.809, 0.4: 0.8095, 0.3: 0.820},
    }
    fp = {d: {0.5: 3, 0.45: 3, 0.4: 3, 0.3: 3} for d in (d1, d2)}
    chosen, verdict = choose_edge_threshold(iou, fp, 0.5)
    # 0.3 gains most but loses 0.010 on generated frames; 0.4 gains 0.0005 more than 0.45.
    assert "generated 100 mm -0.0100" in verdict[0.3]
    assert verdict[0.45] == verdict[0.4] == "" and chosen == 0.45
    fp[d2][0.45] = 4
    chosen, verdict = choose_edge_threshold(iou, fp, 0.5)
    assert chosen == 0.4 and "false positives 150 mm 4 > 3" in verdict[0.45]
    for cell in (iou[("imported_like", d1)], iou[("imported_like", d2)]):
        cell[0.4] = cell[0.5] + 0.001  # +0.001: not enough
    chosen, verdict = choose_edge_threshold(iou, fp, 0.5)
    assert chosen == 0.5 and "imported-like gain +0.0010" in verdict[0.4]
    assert parse_edge_thresholds("0.45,0.3") == [0.45, 0.3]
    assert parse_edge_thresholds("0.45,x") is None and parse_edge_thresholds("0,0.4") is None


def test_paired_intervals_resample_patients_not_frames():
    """The difference to the reference is the mean of the frame-by-frame differences; a
    setting equal to the reference differs by exactly 0; marked frames all in one of four
    patient-postures give a difference whose interval reaches 0 (a resample may leave that
    patient out), where frames taken as independent would exclude it."""
    clusters = [c for c in "ABCD" for _ in range(10)]
    ref = [0.0] * 40
    one_patient = [1.0] * 10 + [0.0] * 30
    out = paired_intervals({"default": ref, "same": ref, "new": one_patient}, clusters, "default")
    assert out["same"]["difference"] == 0.0 and out["same"]["difference_ci95"] == (0.0, 0.0)
    assert out["new"]["difference"] == pytest.approx(0.25)
    lo, hi = out["new"]["difference_ci95"]
    assert lo == 0.0 and hi >= 0.75
    # Spread over every patient, the same share is told apart from 0.
    spread = [1.0 if i % 4 == 0 else 0.0 for i in range(40)]
    lo, _ = paired_intervals({"default": ref, "new": spread}, clusters, "default")["new"][
        "difference_ci95"
    ]
    assert lo > 0.0
    with pytest.raises(ValueError, match="setting 'new': expected 40 values"):
        paired_intervals({"default": ref, "new": [1.0] * 39}, clusters, "default")
    with pytest.raises(ValueError, match="reference setting 'plain'"):
        paired_intervals({"default": ref}, clusters, "plain")


def test_draws_are_independent_and_the_first_is_the_rules_draw():
    """The first draw is the seed every earlier rule used; the per-source seeds of
    emulated_views (seed + 7919 * source for poses, seed + source for speckle) of different
    draws never meet for up to 100 sources."""
    seeds = draw_seeds(3)
    assert seeds[0] == 9150 and len(set(seeds)) == 3
    for offset in (7919, 1):
        used = [{s + offset * si for si in range(100)} for s in seeds]
        assert not (used[0] & used[1] or used[0] & used[2] or used[1] & used[2])
    with pytest.raises(ValueError, match="draws: expected 1 or more, got 0"):
        draw_seeds(0)


def test_score_settings_pools_draws_and_counts_each(monkeypatch):
    """Frames of two draws are pooled per preset, with each draw's kidney-free and marked
    counts kept apart and every frame tagged with its patient and posture."""
    from types import SimpleNamespace

    import drake_rus.imaging.training.evaluation as evaluation

    d = 0.10
    cfg = SimpleNamespace(min_kidney_area=2e-6)
    g = SimpleNamespace(pixel_area=1e-6)
    gt = np.zeros((4, 4), bool)
    gt[:2, :2] = True

    def fake_views(sources, by_depth, n_views, seed):
        # Draw 0 (seed 9150): one kidney-free frame per source; later draws: two.
        free = 1 if seed == 9150 else 2
        for si in range(len(sources)):
            for i in range(n_views):
                has = i >= free
                us = np.full((4, 4), si + 1.0)
                yield si, d, cfg, g, by_depth[d][2], us, (gt if has else gt & False), has

    monkeypatch.setattr(evaluation, "emulated_views", fake_views)
    sources = [
        ("generated", SimpleNamespace(name="train:28", posture="supine")),
        ("imported_like", SimpleNamespace(name="train:28", posture="supine")),
    ]
    segs = {
        d: (
            cfg,
            g,
            {"default": lambda us: us * 0 > 0, "marks_all": lambda us: np.ones_like(us, bool)},
        )
    }
    scores = score_settings(segs, sources, 3, draw_seeds(2), no_progress=True)
    assert scores.free_by_draw[d] == [2, 4] and scores.empty[d] == 6
    assert scores.marked_by_draw[d] == {"default": [0, 0], "marks_all": [2, 4]}
    assert scores.fp[d] == {"default": 0, "marks_all": 6}
    assert set(scores.free_clusters[d]) == {"train:28|supine"}
    # Frames with a kidney: 2 + 1 per source over the two draws; "marks_all" covers the
    # whole 4 x 4 frame around a 2 x 2 kidney.
    assert scores.iou[("generated", d)]["marks_all"] == [0.25] * 3
    assert scores.iou[("generated", d)]["default"] == [0.0] * 3
    assert scores.calls == 12
    tables = interval_tables(scores, "default")
    assert tables["false_positive"][d]["marks_all"]["difference"] == 1.0


def test_draws_argument_is_checked():
    """``--draws`` below 1 is one line naming the flag, before any frame is made."""
    import contextlib
    import io

    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        assert segmenter_inference_main(["--draws", "0", "--edge-thresholds", "0.45"]) == 2
    assert err.getvalue().strip() == "--draws: expected 1 or more, got 0"


def test_a_preset_without_kidney_free_frames_reads_no_frames():
    """No kidney-free frame at a preset: the text says so and the JSON gives null, never
    NaN (which is not JSON)."""
    empty = paired_intervals({"default": [], "other": []}, [], "default")
    assert share_text(empty["other"]) == "no frames"
    text = dumps_strict(intervals_json({"iou": {}, "false_positive": {0.15: empty}}))
    cell = json.loads(text)["false_positive_share"]["0.15"]["other"]
    assert cell["mean"] is None and cell["difference"] is None
    assert share_text({"mean": 0.043, "ci95": (0.006, 0.164)}) == "4.3% (0.6-16.4)"


def test_the_interval_json_is_rounded_with_null_for_nan():
    """The intervals' JSON, written by the shared strict writer (dumps_strict: NaN and
    infinities as null), reads as it did with the study's own NaN -> null helper: values
    rounded to 4 decimals, numpy scalars as numbers, a preset without frames as null."""
    nan = float("nan")
    tables = {
        "iou": {
            ("generated", 0.15): {
                "default": {
                    "mean": 0.812345678,
                    "ci95": (np.float64(0.71234567), np.float32(0.9)),
                    "difference": 0.0,
                    "difference_ci95": (0.0, 0.0),
                },
                0.45: {
                    "mean": np.float64(0.80004999),
                    "ci95": (0.7, 0.91),
                    "difference": -0.01234567,
                    "difference_ci95": (-0.02, float("inf")),
                },
            }
        },
        "false_positive": {
            0.2: {
                "default": {
                    "mean": nan,
                    "ci95": (nan, nan),
                    "difference": nan,
                    "difference_ci95": (nan, nan),
                }
            },
        },
    }
    assert dumps_strict({"intervals": intervals_json(tables)}) == (
        '{"intervals": {"iou": {"generated|0.15": {"default": {"mean": 0.8123, "ci95": '
        '[0.7123, 0.9], "difference": 0.0, "difference_ci95": [0.0, 0.0]}, "0.45": {"mean": '
        '0.8, "ci95": [0.7, 0.91], "difference": -0.0123, "difference_ci95": [-0.02, null]}}}, '
        '"false_positive_share": {"0.20": {"default": {"mean": null, "ci95": [null, null], '
        '"difference": null, "difference_ci95": [null, null]}}}}}'
    )


def test_compare_models_argument_is_checked(tmp_path):
    """A missing model or an empty entry in ``--compare-models`` is one line naming the
    flag, before any frame is made; two studies at once are refused."""
    import contextlib
    import io

    for argv, line in (
        (
            ["--compare-models", str(tmp_path / "none.onnx")],
            f"--compare-models: ONNX model file not found: {tmp_path / 'none.onnx'}",
        ),
        (["--compare-models", "a.onnx,"], "--compare-models: expected comma-separated ONNX"),
        (
            ["--compare-models", "a.onnx", "--edge-thresholds", "0.45"],
            "--edge-thresholds and --compare-models: expected one study, got 2",
        ),
    ):
        err = io.StringIO()
        with contextlib.redirect_stderr(err):
            assert segmenter_inference_main(argv + ["--no-progress"]) == 2
        assert err.getvalue().strip().startswith(line)
        assert len(err.getvalue().strip().splitlines()) == 1
