"""The image-resolution refinement of the segmenter's probability: the guided filter
(onnx_backend.guided_filter) and its use in the onnx segmenter (imaging.onnx_guided_radius)."""

import numpy as np
import pytest
from scipy import ndimage

from drake_rus.config_schema import ScenarioError
from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.emulator import EmulatorModel
from drake_rus.imaging.onnx_backend import OnnxSegmenter, guided_filter
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.imaging.segment import iou
from drake_rus.imaging.training.evaluation import make_source_frames
from drake_rus.scenario import LoadScenario


def _crossing(row: np.ndarray) -> float:
    """Column where a decreasing row first falls below 0.5 (linear between samples)."""
    k = int(np.flatnonzero(row < 0.5)[0])
    return k - 1 + (row[k - 1] - 0.5) / (row[k - 1] - row[k])


def test_flat_guide_gives_the_window_mean_and_zero_stays_zero():
    rng = np.random.default_rng(0)
    p = rng.random((20, 30)).astype(np.float32)
    flat = np.full_like(p, 0.3)
    got = guided_filter(p, flat, (2, 3), 0.01)
    want = ndimage.uniform_filter(
        ndimage.uniform_filter(p, (5, 7), mode="nearest"), (5, 7), mode="nearest"
    )
    np.testing.assert_allclose(got, want, atol=1e-5)
    guide = rng.random(p.shape).astype(np.float32)
    assert not guided_filter(np.zeros_like(p), guide, (2, 2), 0.01).any()
    with pytest.raises(ValueError, match="guided_filter"):
        guided_filter(p, guide[:-1], (2, 2), 0.01)


def test_an_edge_of_the_probability_moves_onto_the_guide_edge():
    """A probability falling from 1 to 0 over columns 8-16 (its 0.5 at column 12, as a
    bilinear map back from coarse pixels draws it) and a guide whose edge (dark kidney,
    bright outside) is at column 14.5 or 9.5: with a window spanning the ramp the refined
    0.5 crossing moves onto the guide's edge, either way; with a large eps (a weak edge)
    it stays at the probability's own."""
    cols = np.arange(40, dtype=np.float32)
    p = np.tile(np.clip((16 - cols) / 8, 0, 1), (10, 1)).astype(np.float32)
    assert _crossing(p[5]) == pytest.approx(12.0)
    for edge in (14.5, 9.5):
        guide = np.tile(np.where(cols < edge, 0.2, 0.8), (10, 1)).astype(np.float32)
        sharp = guided_filter(p, guide, (2, 5), 1e-3)
        assert abs(_crossing(sharp[5]) - edge) < 0.6
        weak = guided_filter(p, guide, (2, 5), 10.0)
        assert abs(_crossing(weak[5]) - 12.0) < 0.1


def test_segmenter_refines_the_component_on_its_window_as_on_the_whole_image(monkeypatch):
    """A blob of probability in the fan's interior: the segmenter's mask with the guided
    filter (on the component's window) is the whole image's refined probability
    thresholded, and differs from the plain mask; radius 0 is the plain segmenter."""
    cfg = ImagingConfig(depth=0.15, segmenter="onnx", onnx_guided_radius=1.5e-3)
    g = ProbeGeometry.from_config(cfg)
    seg = OnnxSegmenter.from_config(cfg, g)
    assert seg.guided_px == (3, 3)  # 1.5 mm at 0.60 x 0.53 mm pixels
    h, w = seg.input_shape[2:]
    prob = np.zeros((h, w), np.float32)
    prob[20:40, 46:66] = 0.9
    monkeypatch.setattr(OnnxSegmenter, "model_probability", lambda self, image: prob)
    rng = np.random.default_rng(1)
    image = (rng.random(g.image_shape) * 255).astype(np.uint8)
    image[60:120, 100:160] //= 3  # a dark region overlapping the blob's edge
    mask = seg(image)
    grey = image.astype(np.float32) / 255
    want = (guided_filter(seg.canvas.to_image(prob), grey, seg.guided_px, 0.01) > 0.5) & (
        g.fan_mask
    )
    assert np.count_nonzero(mask != want) <= 2
    seg.guided_radius = 0.0
    plain = seg(image)
    assert np.count_nonzero(plain != mask) > 50
    assert iou(plain, mask) > 0.9


def test_refined_masks_of_emulated_frames_stay_close_to_the_truth():
    """Emulated frames of a phantom: the refined mask is as close to the true kidney as the
    plain one (mean IoU within 0.01) and differs from it only near the edge."""
    cfg = ImagingConfig(depth=0.10, segmenter="onnx", onnx_guided_radius=1.5e-3)
    g = ProbeGeometry.from_config(cfg)
    seg = OnnxSegmenter.from_config(cfg, g)
    frames = make_source_frames("phantom:5001", EmulatorModel.from_config(cfg, g), 8, seed=2)
    plain_iou, refined_iou = [], []
    for us, gt, *_ in frames:
        if gt.sum() * g.pixel_area < cfg.min_kidney_area:
            continue
        seg.guided_radius = 1.5e-3
        refined = seg(us)
        seg.guided_radius = 0.0
        plain = seg(us)
        refined_iou.append(iou(refined, gt))
        plain_iou.append(iou(plain, gt))
        # Changed pixels lie within 2 canvas pixels (4.8 mm) of the plain mask's edge.
        edge = plain ^ ndimage.binary_erosion(plain)
        dist = ndimage.distance_transform_edt(~edge, sampling=(g.dz, g.dx))
        assert dist[refined ^ plain].max(initial=0.0) < 4.8e-3
    assert len(plain_iou) >= 3
    assert np.mean(refined_iou) > np.mean(plain_iou) - 0.01


def test_guided_fields_come_from_the_scenario_and_are_checked():
    imaging = LoadScenario(
        scenario_text="{imaging: {onnx_guided_radius: 0.002, onnx_guided_eps: 0.05}}"
    ).imaging
    g = ProbeGeometry.from_config(imaging)
    seg = OnnxSegmenter.from_config(imaging, g)
    assert seg.guided_radius == 0.002 and seg.guided_eps == 0.05
    for bad in ("{imaging: {onnx_guided_radius: -0.001}}", "{imaging: {onnx_guided_radius: 0.5}}"):
        with pytest.raises(ScenarioError, match="onnx_guided_radius"):
            LoadScenario(scenario_text=bad)
    with pytest.raises(ScenarioError, match="onnx_guided_eps"):
        LoadScenario(scenario_text="{imaging: {onnx_guided_eps: 0}}")
    with pytest.raises(ValueError, match="onnx_guided_radius"):
        OnnxSegmenter(seg.path, g, seg.input_shape, guided_radius=float("nan"))
    with pytest.raises(ValueError, match="onnx_guided_eps"):
        OnnxSegmenter(seg.path, g, seg.input_shape, guided_eps=-1.0)
