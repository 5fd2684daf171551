"""The imaging LeafSystems in a small diagram: sampling clock, stamps, errors."""

import numpy as np
import pytest
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantValueSource

from drake_rus.anatomy.labels import Label
from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.phantoms import sphere_volume
from drake_rus.imaging.systems import (
    PointCloudAccumulator,
    Segmenter,
    SliceSensor,
    UltrasoundEmulator,
)

DOWN = RotationMatrix(np.diag([1.0, -1.0, -1.0]))


def build(X_BP, config=None, with_accumulator=True):
    config = config or ImagingConfig(
        image_height_px=128,
        image_width_px=128,
        scan_lines=64,
        samples_per_line=128,
        segmenter="oracle",
    )
    # Sphere of kidney cortex 20 mm radius, centre 60 mm under the probe, 15 mm to +x_P.
    vol = sphere_volume(
        shape=(120, 60, 120), center=(0.075, 0.03, 0.04), radius=0.02, label=Label.KIDNEY_CORTEX
    )
    X_BV = RigidTransform([-0.06, -0.03, -0.10])
    b = DiagramBuilder()
    src = b.AddSystem(ConstantValueSource(AbstractValue.Make(X_BP)))
    sensor = b.AddSystem(SliceSensor(config, vol, X_BV))
    emu = b.AddSystem(UltrasoundEmulator(config, seed=2))
    seg = b.AddSystem(Segmenter(config))
    b.Connect(src.get_output_port(), sensor.GetInputPort("X_BP"))
    b.Connect(sensor.GetOutputPort("label_image"), emu.GetInputPort("label_image"))
    b.Connect(emu.GetOutputPort("us_image"), seg.GetInputPort("us_image"))
    b.Connect(sensor.GetOutputPort("label_image"), seg.GetInputPort("label_image"))
    acc = None
    if with_accumulator:
        acc = b.AddSystem(PointCloudAccumulator(config))
        b.Connect(seg.GetOutputPort("boundary_pixels"), acc.GetInputPort("boundary_pixels"))
    for name, sys_ in (("sensor", sensor), ("emu", emu), ("seg", seg), ("acc", acc)):
        if sys_ is not None:
            sys_.set_name(name)
    return b.Build(), sensor, emu, seg, acc


def test_pipeline_samples_at_frame_rate_and_stamps_frames():
    X_BP = RigidTransform(DOWN, [0.0, 0.0, 0.0])
    diagram, sensor, emu, seg, acc = build(X_BP)
    sim = Simulator(diagram)
    ctx = sim.get_mutable_context()
    sim.Initialize()
    sim.AdvanceTo(0.51)
    sc = sensor.GetMyContextFromRoot(ctx)
    label = sensor.GetOutputPort("label_image").Eval(sc)
    # 20 fps: initial frame at t = 0, then one every 50 ms -> frame 10 at t = 0.5 s.
    assert label.frame_index == 10
    assert label.time == pytest.approx(0.5)
    assert label.X_BP.IsExactlyEqualTo(X_BP)
    us = emu.GetOutputPort("us_image").Eval(emu.GetMyContextFromRoot(ctx))
    assert us.frame_index == 10 and us.time == pytest.approx(0.5)
    assert us.image.dtype == np.uint8 and us.image.max() > 50
    segc = seg.GetMyContextFromRoot(ctx)
    assert seg.GetOutputPort("kidney_visible").Eval(segc)[0] == 1.0
    c = seg.GetOutputPort("mask_centroid").Eval(segc)[0]
    # Centre 15 mm along +x_P: c_msk = (x - x_min) / width.
    g = sensor.geometry
    assert c == pytest.approx((0.015 - g.x_min) / (g.x_max - g.x_min), abs=0.01)
    mask = seg.GetOutputPort("kidney_mask").Eval(segc)
    assert mask.frame_index == 10 and mask.image.dtype == bool
    assert np.array_equal(mask.image, label.image == Label.KIDNEY_CORTEX)
    cloud = acc.GetOutputPort("point_cloud").Eval(acc.GetMyContextFromRoot(ctx))
    # Accumulated half a period after each frame: frames 0..10 at t = 0.025 .. 0.525 -> 10.
    assert cloud.frame_count == 10
    assert len(cloud.poses) == 10 and len(cloud.points) > 100
    # All points lie on the sphere (20 mm radius around its centre in B).
    c_B = np.array([0.075 - 0.06, 0.0, 0.04 - 0.10])
    r = np.linalg.norm(cloud.points - c_B, axis=1)
    assert abs(np.mean(r) - 0.02) < 0.001


def test_accumulator_enable_and_reset():
    config = ImagingConfig(
        image_height_px=64,
        image_width_px=64,
        scan_lines=32,
        samples_per_line=64,
        segmenter="oracle",
    )
    X_BP = RigidTransform(DOWN, [0.0, 0.0, 0.0])
    diagram, sensor, emu, seg, acc = build(X_BP, config)
    ctx = diagram.CreateDefaultContext()
    ac = acc.GetMyContextFromRoot(ctx)
    acc.GetInputPort("enable").FixValue(ac, [0.0])
    sim = Simulator(diagram, ctx)
    sim.AdvanceTo(0.3)
    assert acc.GetOutputPort("frame_count").Eval(ac)[0] == 0
    acc.GetInputPort("enable").FixValue(ac, [1.0])
    sim.AdvanceTo(0.6)
    n = acc.GetOutputPort("frame_count").Eval(ac)[0]
    assert 5 <= n <= 7
    acc.GetInputPort("reset").FixValue(ac, [1.0])
    sim.AdvanceTo(0.7)
    assert acc.GetOutputPort("frame_count").Eval(ac)[0] == 0
    assert len(acc.GetOutputPort("point_cloud").Eval(ac).points) == 0


def test_non_finite_pose_gives_a_clear_error():
    bad = RigidTransform()
    bad.set_translation([np.nan, 0.0, 0.0])
    diagram2, *_ = build(bad, with_accumulator=False)
    with pytest.raises(Exception, match="X_BP.*non-finite"):
        Simulator(diagram2).Initialize()


def test_segmenter_on_unconnected_input_names_the_port():
    config = ImagingConfig(segmenter="oracle")
    seg = Segmenter(config)
    ctx = seg.CreateDefaultContext()
    with pytest.raises(RuntimeError, match="label_image"):
        seg.GetOutputPort("kidney_visible").Eval(ctx)
