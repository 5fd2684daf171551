"""The segmenter's inference-side options: the lateral mirror average, the minimum region
area, and the validation study's variants and choice (benchmarks/segmenter_inference.py)."""

import numpy as np
import pytest

from benchmarks.segmenter_inference import PLAIN, choose, score_variants, variant_masks
from drake_rus.config_schema import ScenarioError
from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.emulator import EmulatorModel
from drake_rus.imaging.onnx_backend import OnnxSegmenter, drop_small_regions, mirror_average
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.imaging.training.evaluation import make_source_frames
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
