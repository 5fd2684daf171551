"""The boundary study's pieces (benchmarks/segmenter_boundary.py): the canvas ceiling, the
error split, a variant's mask and the choice rule."""

import numpy as np
import pytest

from benchmarks.segmenter_boundary import (
    PLAIN,
    VARIANTS,
    canvas_ceiling,
    choose,
    error_split,
    variant_mask,
)
from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.onnx_backend import OnnxSegmenter
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.imaging.segment import iou


def _segmenter(depth=0.10):
    cfg = ImagingConfig(depth=depth, segmenter="onnx")
    g = ProbeGeometry.from_config(cfg)
    return g, OnnxSegmenter.from_config(cfg, g)


def _disk(g, centre_z, radius):
    z = g.z0 + np.arange(g.height_px)[:, None] * g.dz
    x = g.x0 + np.arange(g.width_px)[None, :] * g.dx
    return ((z - centre_z) ** 2 + x**2 <= radius**2) & g.fan_mask


def test_canvas_ceiling_of_a_large_section_is_close_and_of_a_small_one_lower():
    g, seg = _segmenter(0.10)
    big = _disk(g, 0.06, 0.020)
    small = _disk(g, 0.06, 0.003)
    ceiling_big = iou(canvas_ceiling(seg, big), big)
    ceiling_small = iou(canvas_ceiling(seg, small), small)
    assert ceiling_big > 0.97
    assert ceiling_small < ceiling_big


def test_error_split_puts_a_shifted_edge_in_the_band_and_a_false_region_out():
    g, _ = _segmenter(0.10)
    gt = _disk(g, 0.06, 0.020)
    grown = _disk(g, 0.06, 0.022)  # 2 mm too large all round: boundary errors only
    s = error_split(grown, gt, g, band=0.0048)
    assert s["gross_error"] == 0.0 and s["boundary_error"] > 0.15
    assert s["iou_boundary_fixed"] == 1.0 and s["iou_gross_fixed"] == pytest.approx(s["iou"])
    far = grown | _disk(g, 0.085, 0.004)  # plus a false region 25 mm away
    s = error_split(far, gt, g, band=0.0048)
    assert s["gross_error"] > 0.0
    assert s["iou_gross_fixed"] > s["iou"] and s["iou_boundary_fixed"] > s["iou"]


def test_variant_masks_restore_the_segmenter_and_plain_is_its_unrefined_mask(monkeypatch):
    g, seg = _segmenter(0.15)
    h, w = seg.input_shape[2:]
    prob = np.zeros((h, w), np.float32)
    prob[20:40, 46:66] = 0.9
    rng = np.random.default_rng(3)
    us = (rng.random(g.image_shape) * 255).astype(np.uint8)
    before = seg.guided_radius, seg.guided_eps
    masks = {v: variant_mask(seg, v, us, prob) for v in VARIANTS}
    assert (seg.guided_radius, seg.guided_eps) == before
    seg.guided_radius = 0.0
    assert np.array_equal(masks[PLAIN], seg._candidates(prob, True)[0])
    for v, m in masks.items():
        assert iou(m, masks[PLAIN]) > 0.8, v


def test_choice_refuses_a_loss_at_any_preset_and_more_false_positives():
    presets = (0.1, 0.2)

    def cell(g1, g2, i1, i2, fp=0):
        return {
            "generated": {0.1: {"iou": g1, "fp": fp}, 0.2: {"iou": g2, "fp": 0}},
            "imported_like": {0.1: {"iou": i1, "fp": 0}, 0.2: {"iou": i2, "fp": 0}},
        }

    a = ("guided", 1.5, 0.01, 0.0)
    b = ("guided", 3.0, 0.01, 0.0)
    c = ("guided", 1.5, 0.001, 0.0)
    table = {
        PLAIN: cell(0.80, 0.90, 0.70, 0.75),
        a: cell(0.805, 0.905, 0.70, 0.75),  # +0.005 everywhere on generated, equal elsewhere
        b: cell(0.82, 0.92, 0.699, 0.76),  # larger gain, but a loss on imported-like
        c: cell(0.8055, 0.9055, 0.70, 0.75, fp=1),  # one more false positive
    }
    chosen, gain = choose(table, presets)
    assert chosen == a and gain[b] == pytest.approx(0.02)
    # Within the tie margin the cheaper one (smaller radius, larger eps) is taken.
    table[("guided", 1.5, 0.05, 0.0)] = cell(0.8045, 0.9045, 0.70, 0.75)
    assert choose(table, presets)[0] == ("guided", 1.5, 0.05, 0.0)
    # A gain under 0.002: nothing is chosen.
    small = {PLAIN: table[PLAIN], a: cell(0.801, 0.901, 0.70, 0.75)}
    assert choose(small, presets)[0] is None
