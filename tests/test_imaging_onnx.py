"""The ONNX segmenter backend: the shipped model, and clear errors for bad models/shapes."""

import json

import numpy as np
import pytest
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform

from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.frames import UsFrame
from drake_rus.imaging.onnx_backend import (OnnxSegmenter, largest_component, resize_to,
                                            resolve_model_path, upsample_to)
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


def test_garbage_model_is_named(geometry, tmp_path):
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"this is not an onnx model" * 10)
    with pytest.raises(ValueError, match="imaging.onnx_model: cannot load ONNX model"):
        OnnxSegmenter(bad, geometry)


def test_wrong_input_shape_is_named(geometry):
    with pytest.raises(ValueError, match="imaging.onnx_input_shape.*1, 1, 96, 96"):
        OnnxSegmenter(MODEL, geometry, input_shape=(1, 1, 96, 96))


def test_shipped_model_matches_its_json_and_the_default_scenario(geometry):
    meta = json.loads(MODEL.with_suffix(".json").read_text())
    assert meta["input"]["shape"] == CFG.onnx_input_shape
    assert meta["scenario"]["onnx_output"] == CFG.onnx_output
    assert MODEL.stat().st_size < 5e6
    seg = OnnxSegmenter.from_config(CFG, geometry)
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
    X_BP = RigidTransform(RotationMatrix(np.diag([1.0, -1.0, -1.0])),
                          [c[0], c[1], ph.skin_z - 0.003])
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
