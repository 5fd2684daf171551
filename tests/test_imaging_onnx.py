"""The ONNX segmenter backend: the shipped model, and clear errors for bad models/shapes."""

import json
import shutil

import numpy as np
import pytest
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from scipy import ndimage

from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.frames import UsFrame
from drake_rus.imaging.onnx_backend import (
    OnnxSegmenter,
    PhysicalCanvas,
    card_canvas,
    largest_component,
    read_model_card,
    resize_to,
    resolve_model_path,
    upsample_to,
)
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.imaging.systems import Segmenter

CFG = ImagingConfig(segmenter="onnx")
MODEL = resolve_model_path(CFG.onnx_model)


def test_the_default_model_ships_with_its_card():
    """The default segmenter is shipped in models/segmenter with its model card; a missing
    file fails here rather than skipping the tests that use it."""
    assert MODEL.is_file() and MODEL.stat().st_size > 10_000, MODEL
    card = json.loads(MODEL.with_suffix(".json").read_text())
    assert card, "the model card is empty"


def test_resize_helpers():
    img = np.arange(16, dtype=np.float32).reshape(4, 4)
    np.testing.assert_allclose(resize_to(img, 2, 2), [[2.5, 4.5], [10.5, 12.5]])
    up = upsample_to(np.array([[0.0, 1.0], [0.0, 1.0]], np.float32), 4, 4)
    np.testing.assert_allclose(up[0], [0.0, 0.25, 0.75, 1.0])
    m = np.zeros((8, 8), bool)
    m[1:3, 1:3] = True
    m[4:8, 4:8] = True
    m[5, 5] = False
    big = largest_component(m)
    assert big[4:8, 4:8].all() and not big[1:3, 1:3].any()


def test_missing_model_is_named(geometry, tmp_path):
    with pytest.raises(ValueError, match="imaging.onnx_model: ONNX model file not found"):
        OnnxSegmenter(tmp_path / "nope.onnx", geometry)


def test_a_folder_given_as_the_model_is_named(geometry, tmp_path):
    with pytest.raises(ValueError, match="imaging.onnx_model: expected an .onnx model file, got a"):
        OnnxSegmenter(tmp_path, geometry)


def test_garbage_model_is_named(geometry, tmp_path):
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"this is not an onnx model" * 10)
    with pytest.raises(ValueError, match="imaging.onnx_model: cannot load ONNX model"):
        OnnxSegmenter(bad, geometry)


def _bare_copy(tmp_path):
    """The shipped model without its card (so the scenario's input shape rules)."""
    bare = tmp_path / "bare.onnx"
    shutil.copyfile(MODEL, bare)
    return bare


def test_wrong_input_shape_is_named(geometry, tmp_path):
    with pytest.raises(ValueError, match="imaging.onnx_input_shape.*1, 1, 96, 96"):
        OnnxSegmenter(_bare_copy(tmp_path), geometry, input_shape=(1, 1, 96, 96))


def test_shipped_model_matches_its_json_and_the_default_scenario(geometry):
    meta = json.loads(MODEL.with_suffix(".json").read_text())
    seg = OnnxSegmenter.from_config(CFG, geometry)
    # The default scenario runs the model at the card's input shape: N, C from the scenario,
    # H, W = the card's physical canvas.
    assert meta["input"]["shape"] == list(seg.input_shape)
    assert meta["input"]["shape"][:2] == CFG.onnx_input_shape[:2]
    assert meta["input"]["shape"][2:] == meta["canvas_px"]
    assert seg.pixel_size_mm == pytest.approx(meta["pixel_size_mm"])
    assert meta["scenario"]["onnx_output"] == CFG.onnx_output
    assert MODEL.stat().st_size < 5e6
    # A blank (black) image has no kidney.
    assert not seg(np.zeros(geometry.image_shape, np.uint8)).any()
    with pytest.raises(ValueError, match="image shape"):
        seg(np.zeros((10, 10), np.uint8))


def test_shipped_model_segments_an_emulated_kidney(geometry):
    from pydrake.math import RotationMatrix

    from drake_rus.anatomy.labels import is_kidney
    from drake_rus.imaging.emulator import EmulatorModel, emulate
    from drake_rus.imaging.phantoms import kidney_phantom
    from drake_rus.imaging.segment import iou
    from drake_rus.imaging.slicing import slice_volume

    ph = kidney_phantom(None, shape=(140, 180, 140), rib=False, gas=False)
    c = ph.X_VK.translation()
    X_BP = RigidTransform(
        RotationMatrix(np.diag([1.0, -1.0, -1.0])), [c[0], c[1], ph.skin_z - 0.003]
    )
    labels = slice_volume(geometry, ph.volume, RigidTransform(), X_BP)
    us = emulate(labels, EmulatorModel.from_config(CFG, geometry), 0, 0)
    seg = OnnxSegmenter.from_config(CFG, geometry)
    assert iou(seg(us), is_kidney(labels)) > 0.7
    # Through the LeafSystem as well.
    system = Segmenter(CFG)
    ctx = system.CreateDefaultContext()
    system.GetInputPort("us_image").FixValue(ctx, AbstractValue.Make(UsFrame(us, 1.0, X_BP, 3)))
    assert system.GetOutputPort("kidney_visible").Eval(ctx)[0] == 1.0
    mask = system.GetOutputPort("kidney_mask").Eval(ctx)
    assert mask.frame_index == 3 and mask.time == 1.0
    assert iou(mask.image, is_kidney(labels)) > 0.7


def test_segmenter_system_with_a_bad_model_fails_at_construction(tmp_path):
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"\x00" * 100)
    with pytest.raises(ValueError, match="onnx_model"):
        Segmenter(ImagingConfig(segmenter="onnx", onnx_model=str(bad)))


def test_fill_holes_matches_scipy():
    from scipy import ndimage

    from drake_rus.imaging.onnx_backend import fill_holes

    rng = np.random.default_rng(0)
    for _ in range(50):
        m = ndimage.binary_opening(rng.random((40, 40)) < 0.6)
        assert np.array_equal(fill_holes(m), ndimage.binary_fill_holes(m))
    # One background region, enclosed: a mask covering the whole border around a hole.
    ring = np.ones((9, 9), bool)
    ring[3:6, 4] = False
    assert fill_holes(ring).all()
    assert np.array_equal(fill_holes(~ring), ~ring)  # one region touching the border


# --- physical pixel size ------------------------------------------------------------------------


def _disc(g: ProbeGeometry, x: float, z: float, r: float) -> np.ndarray:
    p = g.pixel_to_P(g._all_uv)
    return (((p[:, 0] - x) ** 2 + (p[:, 2] - z) ** 2) <= r * r).reshape(g.image_shape)


def test_a_disc_keeps_its_physical_size_on_the_canvas_and_back():
    """A disc of 20 mm radius imaged at 100 and 250 mm depth (0.40 and 0.99 mm per pixel
    along the beam) covers the same canvas pixels (2.4 mm), and maps back onto itself within
    a pixel."""
    canvases, discs = [], []
    for depth in (0.10, 0.25):
        g = ProbeGeometry.from_config(ImagingConfig(depth=depth))
        c = PhysicalCanvas(g, 0.0024, (128, 112), -0.004)
        disc = _disc(g, 0.012, 0.055, 0.020)
        on_canvas = c.to_canvas(disc.astype(np.float32))
        # Area preserved (the canvas holds the area fraction per pixel).
        assert on_canvas.sum() * 2.4**2 == pytest.approx(np.pi * 20.0**2, rel=0.01)
        back = c.to_image(on_canvas) > 0.5
        ring = ndimage.binary_dilation(disc, iterations=1) & ~ndimage.binary_erosion(disc)
        assert not (back ^ disc)[~ring].any(), "more than a pixel off the disc's edge"
        canvases.append(on_canvas > 0.5)
        discs.append(disc)
        # Pixels outside the image (below 100 mm) are zero padding; the fan is inside.
        assert c.fan_mask.any() and not c.fan_mask[-1].any()
    a, b = canvases
    assert (a ^ b).sum() <= 0.1 * a.sum()  # the same canvas pixels, up to the edge
    assert (a & b).sum() / (a | b).sum() > 0.9
    # A grey image maps to the same canvas grey, whatever the depth.
    for depth in (0.10, 0.30):
        g = ProbeGeometry.from_config(ImagingConfig(depth=depth))
        c = PhysicalCanvas(g, 0.0024, (128, 112), -0.004)
        flat = np.full(g.image_shape, 200, np.uint8)
        inner = ndimage.binary_erosion(c.fan_mask, iterations=2)
        assert np.allclose(c.to_canvas(flat * g.fan_mask)[inner], 200, atol=1e-3)


def test_card_fields_are_read_and_a_missing_field_falls_back(geometry, tmp_path):
    assert card_canvas({}) is None
    assert card_canvas({"pixel_size_mm": 2.4}) is None  # no canvas_px
    assert card_canvas({"canvas_px": [128, 112]}) is None  # no pixel size
    spec = card_canvas({"pixel_size_mm": 2.4, "canvas_px": [128, 112]})
    assert spec["pixel_size"] == pytest.approx(0.0024) and spec["shape"] == (128, 112)
    assert spec["top"] is None  # default: the image's top
    assert PhysicalCanvas(geometry, 0.0024, (128, 112)).top == pytest.approx(geometry.z_min)
    with pytest.raises(ValueError, match="pixel_size_mm"):
        card_canvas({"pixel_size_mm": -1, "canvas_px": [128, 112]})
    # The shipped card declares the canvas; the backend reads it from the .json.
    card = read_model_card(MODEL)
    seg = OnnxSegmenter.from_config(CFG, geometry)
    assert seg.canvas is not None and seg.canvas.shape == tuple(card["canvas_px"])
    assert seg.canvas.top == pytest.approx(card["canvas_top_mm"] * 1e-3)
    # A card without the fields: today's plain resize to the scenario's H x W.
    bare = _bare_copy(tmp_path)
    shape = (1, 1) + tuple(card["canvas_px"])
    bare.with_suffix(".json").write_text(json.dumps({"pixel_size_mm": 2.4}))
    legacy = OnnxSegmenter(bare, geometry, input_shape=shape)
    assert legacy.canvas is None and legacy.pixel_size_mm is None
    img = np.random.default_rng(0).integers(0, 255, geometry.image_shape).astype(np.uint8)
    np.testing.assert_allclose(
        legacy.preprocess(img)[0, 0], resize_to(img, *shape[2:]) / 255.0, atol=1e-6
    )
    # No card at all: the same; a broken card is named.
    bare.with_suffix(".json").unlink()
    assert OnnxSegmenter(bare, geometry, input_shape=shape).canvas is None
    bare.with_suffix(".json").write_text("{not json")
    with pytest.raises(ValueError, match="bare.json"):
        OnnxSegmenter(bare, geometry, input_shape=shape)
    # A card whose canvas the model does not take is named too.
    bare.with_suffix(".json").write_text(json.dumps({"pixel_size_mm": 2.4, "canvas_px": [96, 96]}))
    with pytest.raises(ValueError, match="canvas_px"):
        OnnxSegmenter(bare, geometry)


def test_shipped_model_holds_at_shallow_and_deep_presets():
    """The shipped model on a held-out patient (test:0, supine) at 100 and 250 mm depth:
    the scan's vertical views over the kidney, the array at four angles; the IoU of each
    emulated frame above a floor."""
    from drake_rus.imaging.emulator import EmulatorModel, emulate
    from drake_rus.imaging.segment import iou
    from drake_rus.imaging.slicing import slice_volume
    from drake_rus.imaging.training.evaluation import centred_views, load_source

    src = load_source("test:0", posture="supine")
    poses = centred_views(src, (0.0, 45.0, 90.0, 135.0))
    for depth in (0.10, 0.25):
        cfg = ImagingConfig(depth=depth)
        g = ProbeGeometry.from_config(cfg)
        model = EmulatorModel.from_config(cfg, g)
        seg = OnnxSegmenter.from_config(cfg, g)
        ious = []
        for i, X in enumerate(poses):
            labels = slice_volume(g, src.volume, RigidTransform(), X)
            gt = src.kidney_mask(labels, g, X)
            assert gt.sum() * g.pixel_area >= cfg.min_kidney_area
            ious.append(iou(seg(emulate(labels, model, 1, i)), gt))
        assert np.mean(ious) > 0.75 and min(ious) > 0.6, (depth, ious)


def test_onnx_segmenter_follows_the_kidney_through_the_leaf_system(monkeypatch):
    """The model marks a kidney, then also a larger region deeper in the image (a muscle
    band), then the band alone: the Segmenter keeps the kidney (followed for longer than
    imaging.track_confirm), and does not take the band for it until imaging.track_gap has
    passed since the kidney was last seen."""
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import DiagramBuilder, LeafSystem

    cfg = ImagingConfig(segmenter="onnx", track_gap=0.5, track_confirm=0.1)
    system_geometry = ProbeGeometry.from_config(cfg)
    seg = OnnxSegmenter.from_config(cfg, system_geometry)
    h, w = seg.input_shape[2:]
    r, c = np.ogrid[:h, :w]
    kidney = ((r - 40) ** 2 + (c - w // 2) ** 2 <= 8**2).astype(np.float32)
    band = ((r - 75) ** 2 + (c - w // 2 + 5) ** 2 <= 14**2).astype(np.float32)

    calls = []

    def fake_probability(self, image):
        # The frame's grey level says what the "model" sees: 1 kidney, 2 both, 3 the band.
        what = int(np.asarray(image)[0, 0])
        calls.append(what)
        return {1: kidney, 2: np.maximum(kidney, band), 3: band}[what] * self._canvas_fan(h, w)

    monkeypatch.setattr(OnnxSegmenter, "model_probability", fake_probability)

    class Frames(LeafSystem):
        """One UsFrame per imaging period: kidney for 0.2 s, both until 0.4 s, then band."""

        def __init__(self):
            super().__init__()
            self.made = {}
            self.DeclareAbstractOutputPort(
                "us", lambda: AbstractValue.Make(UsFrame(np.zeros((1, 1), np.uint8))), self._calc
            )

        def _calc(self, context, out):
            # Frame k from t = k / rate on, the same object while it lasts (like the slice
            # sensor's sampled output).
            k = int(np.floor(context.get_time() * cfg.frame_rate_hz + 1e-9))
            what = 1 if k < 4 else (2 if k < 8 else 3)
            if k not in self.made:
                self.made[k] = UsFrame(
                    np.full(system_geometry.image_shape, what, np.uint8),
                    k / cfg.frame_rate_hz,
                    RigidTransform(),
                    k,
                )
            out.set_value(self.made[k])

    builder = DiagramBuilder()
    frames = builder.AddSystem(Frames())
    system = builder.AddSystem(Segmenter(cfg))
    builder.Connect(frames.get_output_port(), system.GetInputPort("us_image"))
    sim = Simulator(builder.Build())
    ctx = system.GetMyContextFromRoot(sim.get_mutable_context())
    # The band alone, never having seen the kidney: the largest region.
    unseen = seg(np.full(system_geometry.image_shape, 3, np.uint8))
    assert unseen.any()

    def mask_at(t):
        # Read like the controller does, every 10 ms, up to t.
        while sim.get_context().get_time() < t - 1e-9:
            sim.AdvanceTo(min(sim.get_context().get_time() + 0.01, t))
            system.GetOutputPort("kidney_visible").Eval(ctx)
        return system.GetOutputPort("kidney_mask").Eval(ctx).image

    first = mask_at(0.1)
    assert first.any()
    both = mask_at(0.3)  # the band is larger; the kidney is kept
    assert np.array_equal(both, first)
    assert not mask_at(0.5).any()  # band alone, 0.15 s after the kidney: none
    assert system.GetOutputPort("kidney_visible").Eval(ctx)[0] == 0.0
    late = mask_at(1.0)  # more than track_gap later: the band
    assert np.array_equal(late, unseen)
    # Each frame was segmented once (the prior taken from a frame does not re-segment it):
    # 21 frames in 1 s at 20 Hz, plus the one direct call above.
    assert len(calls) == 21 + 1, len(calls)


# --- candidate regions worked on their boxes ------------------------------------------------


def _candidates_on_the_whole_grid(seg: OnnxSegmenter, prob: np.ndarray) -> list[np.ndarray]:
    """The candidate regions computed on the whole model grid and mapped back with the
    canvas's sparse maps: the reference for the boxed computation."""
    from drake_rus.imaging.onnx_backend import fill_holes

    labels, n = ndimage.label(prob > seg.threshold, structure=np.ones((3, 3), bool))
    if n == 0:
        return []
    sizes = np.bincount(labels.ravel())[1:]
    out = []
    for k in np.argsort(-sizes, kind="stable"):
        keep = fill_holes(labels == k + 1)
        p = np.where(ndimage.binary_dilation(keep), prob, 0.0).astype(np.float32)
        p[keep & (p <= seg.threshold)] = 1.0
        mask = (seg.to_image(seg._past_fan(p)) > seg.threshold) & seg.geometry.fan_mask
        if mask.any():
            out.append(mask)
    return out


@pytest.mark.parametrize("depth", [0.10, 0.20, 0.30])
def test_candidates_on_their_boxes_equal_the_whole_grid(depth, monkeypatch):
    """Regions anywhere on the grid (inside the fan, across its edges, on the canvas's
    border, with holes, several at once): the masks are those of the whole-grid computation,
    bit for bit, and so is the window of the back map (the guided filter off: its window is
    tested in test_guided_filter.py)."""
    g = ProbeGeometry.from_config(ImagingConfig(depth=depth))
    seg = OnnxSegmenter.from_config(
        ImagingConfig(depth=depth, segmenter="onnx", onnx_guided_radius=0.0), g
    )
    h, w = seg.input_shape[2:]
    rng = np.random.default_rng(int(depth * 100))
    r, c = np.ogrid[:h, :w]
    probs = []
    for _ in range(12):
        prob = np.zeros((h, w), np.float32)
        for _ in range(rng.integers(1, 4)):
            cr, cc = rng.integers(-5, h + 5), rng.integers(-5, w + 5)
            rad = rng.integers(2, 15)
            blob = np.exp(-((r - cr) ** 2 + (c - cc) ** 2) / (2.0 * rad**2))
            prob = np.maximum(prob, (blob * rng.uniform(0.6, 1.0)).astype(np.float32))
        prob[rng.random((h, w)) < 0.02] = 0.0  # holes
        probs.append(prob * seg._canvas_fan(h, w))
    probs.append(np.ones((h, w), np.float32) * seg._canvas_fan(h, w))  # the whole fan
    # The same model without its card: the plain resize and bilinear map back.
    plain = OnnxSegmenter(MODEL, g, input_shape=seg.input_shape, card={})
    assert plain.canvas is None
    for prob in probs:
        monkeypatch.setattr(OnnxSegmenter, "model_probability", lambda self, image: prob)
        for model in (seg, plain):
            got = model.candidates(np.zeros(g.image_shape, np.uint8))
            want = _candidates_on_the_whole_grid(model, prob)
            assert len(got) == len(want)
            for a, b in zip(got, want):
                assert np.array_equal(a, b)
    # The back map of a window: the whole map's values there, 0 elsewhere.
    canvas = seg.canvas
    full = np.zeros((h, w), np.float32)
    full[10:31, 40:57] = rng.random((21, 17)).astype(np.float32)
    rows, cols, values = canvas.to_image_window(full[10:31, 40:57], (10, 40), (h, w))
    whole = canvas.to_image(full)
    assert np.array_equal(whole[rows, cols], values)
    outside = np.ones(g.image_shape, bool)
    outside[rows, cols] = False
    assert not whole[outside].any()
    # The forward map sums in the same order as the dense @ sparse product it replaced.
    image = rng.integers(0, 256, g.image_shape).astype(np.float32)
    assert np.array_equal(
        canvas.to_canvas(image), np.asarray((canvas._rows @ image) @ canvas._cols.T.tocsr())
    )
