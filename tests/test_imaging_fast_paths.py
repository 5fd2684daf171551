"""The per-frame imaging chain gives the same values, bit for bit, as the straightforward
computations it was sped up from (the reference implementations below): on views of a
held-out patient (test:0: skin, fat, muscle, ribs, bowel gas, the kidney) and on synthetic
edge cases. No tolerance anywhere: every fast path does the same float operations in the
same order on every value."""

import warnings
from dataclasses import replace

import numpy as np
import pytest
from pydrake.math import RigidTransform, RotationMatrix
from scipy import ndimage

from drake_rus.anatomy.labels import Label, LabelVolume
from drake_rus.imaging import emulator as E
from drake_rus.imaging.backprojection import accumulate, backproject_pixels
from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.frames import BoundaryPixels, PointCloud
from drake_rus.imaging.onnx_backend import OnnxSegmenter, _dilate_cross, _max_3x3, _true_box
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.imaging.segment import (
    boundary_pixels,
    mask_box,
    mask_centroid,
    read_mask,
    tracked_component,
)
from drake_rus.imaging.slicing import _lookup_padded, padded_labels, slice_volume

DOWN = RotationMatrix(np.diag([1.0, -1.0, -1.0]))


# --- references: the computations before the fast paths ----------------------------------


def ref_slice(g, volume, X_BV, X_BP, y=0.0):
    """One plane of ``slice_volume``: every fan pixel's voxel coordinates, then the padded
    look-up."""
    X_VP = X_BV.InvertAndCompose(X_BP)
    A = (X_VP.rotation().matrix() / volume.voxel_size).astype(np.float32)
    b = (X_VP.translation() / volume.voxel_size).astype(np.float32)
    px, pz = g.fan_x_z32
    c = b + np.float32(y) * A[:, 1] + np.float32(1.5)
    return _lookup_padded(
        padded_labels(volume.labels),
        px * A[0, 0] + (pz * A[0, 2] + c[0]),
        px * A[1, 0] + (pz * A[1, 2] + c[1]),
        px * A[2, 0] + (pz * A[2, 2] + c[2]),
        shifted=True,
    )


def ref_line_db(labels_ls, model, speckle):
    """``line_db`` along the lines (L, S): compact codes, pair tables, np.cumsum."""
    n_gel = model.gel_samples
    if n_gel > 0:
        head = labels_ls[:, :n_gel]
        leading_air = np.cumprod(head == Label.OUTSIDE, axis=1, dtype=np.uint8).astype(bool)
        if leading_air.any():
            labels_ls = labels_ls.copy()
            labels_ls[:, :n_gel][leading_air] = E.GEL
    cur = np.take(model.compact_codes, labels_ls)
    pair = np.empty_like(cur)
    pair[:, 0] = model.compact_codes[E.PROBE_LABEL] << 4
    pair[:, 1:] = cur[:, :-1] << 4
    pair |= cur
    loss_lut, diffuse_lut, spec_lut = model.pair_luts
    loss = np.take(loss_lut, pair)
    echo = np.take(diffuse_lut, pair)
    if speckle is not None:
        echo *= speckle
    echo += np.take(spec_lut, pair)
    np.maximum(echo, np.float32(1e-12), out=echo)
    db = np.log10(echo, out=echo)
    db *= np.float32(10.0)
    db -= np.cumsum(loss, axis=1, out=loss)
    db += model.tgc_db
    return db


def ref_speckle(model, seed, frame):
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, int(frame) & 0xFFFFFFFF])
    L, S = model.scan_lines, model.samples_per_line
    i, j = rng.integers(0, L + 1), rng.integers(0, S + 1)
    return model.speckle_bank(seed)[i : i + L, j : j + S]


def ref_emulate(label_image, model, seed, frame):
    labels_ls = np.take(label_image.reshape(-1), model.polar_to_image_index).astype(np.uint8)
    speckle = ref_speckle(model, seed, frame) if model.speckle else None
    grey = ref_line_db(labels_ls, model, speckle) + np.float32(model.dynamic_range_db)
    grey *= np.float32(255.0 / model.dynamic_range_db)
    np.clip(grey, 0.0, 255.0, out=grey)
    values = model.scan_matrix @ grey.reshape(-1)
    values += np.float32(0.5)
    return values.astype(np.uint8).reshape(model.geometry.image_shape)


def ref_mask_box(mask):
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(mask.any(axis=0))
    return slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1)


def ref_boundary(mask):
    inner = ndimage.binary_erosion(mask, ndimage.generate_binary_structure(2, 1), border_value=0)
    v, u = np.nonzero(mask & ~inner)
    return np.stack([u, v], axis=1).astype(float)


def ref_centroid(mask):
    if not mask.any():
        return 0.5
    cols = mask.sum(axis=0)
    return float(np.dot(cols, np.arange(mask.shape[1]) + 0.5) / (cols.sum() * mask.shape[1]))


# --- realistic frames: views of test:0 ---------------------------------------------------


@pytest.fixture(scope="module")
def source():
    from drake_rus.imaging.training.evaluation import load_source

    return load_source("test:0", posture="supine")


def views(source, n, seed):
    from drake_rus.imaging.training.evaluation import sample_views

    return sample_views(source, n, seed=seed)


@pytest.mark.parametrize("depth", [0.10, 0.20])
def test_slice_volume_equals_the_per_pixel_lookup(source, depth):
    g = ProbeGeometry.from_config(ImagingConfig(depth=depth))
    z, per_row = g.fan_rows
    assert np.array_equal(np.repeat(z, per_row), g.fan_x_z32[1])
    X_id = RigidTransform()
    poses = views(source, 6, seed=1)
    # Views partly or wholly outside the volume (clipped onto the air border).
    poses += [
        RigidTransform(DOWN, [0.05, 0.05, 0.30]),
        RigidTransform(DOWN, [-0.2, 0.1, 0.1]),
        RigidTransform(RotationMatrix.MakeXRotation(0.7), [0.1, 0.3, 0.05]),
    ]
    for X_VP in poses:
        image = slice_volume(g, source.volume, X_id, X_VP)
        want = np.zeros(g.image_shape, np.uint8)
        want.reshape(-1)[g.fan_flat_index] = ref_slice(g, source.volume, X_id, X_VP)
        assert np.array_equal(image, want)
    # Several planes across the beam width, combined by their maximum.
    X_VP = poses[0]
    got = slice_volume(g, source.volume, X_id, X_VP, planes=3, combine="max")
    planes = [ref_slice(g, source.volume, X_id, X_VP, y) for y in (-0.005, 0.0, 0.005)]
    want = np.zeros(g.image_shape, np.uint8)
    want.reshape(-1)[g.fan_flat_index] = np.max(planes, axis=0)
    assert np.array_equal(got, want)


@pytest.mark.parametrize("depth, lines, samples", [(0.15, 128, 256), (0.20, 96, 320)])
def test_emulate_equals_the_line_by_line_emulation(source, depth, lines, samples):
    cfg = ImagingConfig(depth=depth, scan_lines=lines, samples_per_line=samples)
    g = ProbeGeometry.from_config(cfg)
    model = E.EmulatorModel.from_config(cfg, g)
    X_id = RigidTransform()
    poses = views(source, 8, seed=2)
    # The first probe lifted 4 mm off the skin: air under most of the face (the gel rule).
    X = poses[0]
    lift = 0.004 * X.rotation().matrix()[:, 2]
    poses.append(RigidTransform(X.rotation(), X.translation() - lift))
    labels = [slice_volume(g, source.volume, X_id, X_VP) for X_VP in poses]
    for k, image in enumerate(labels):
        assert np.array_equal(E.emulate(image, model, 7, k), ref_emulate(image, model, 7, k))
    plain = E.EmulatorModel.from_config(replace(cfg, speckle=False), g)
    assert np.array_equal(E.emulate(labels[0], plain), ref_emulate(labels[0], plain, 0, 0))


def test_line_db_equals_the_line_by_line_computation(source):
    cfg = ImagingConfig()
    g = ProbeGeometry.from_config(cfg)
    model = E.EmulatorModel.from_config(cfg, g)
    image = slice_volume(g, source.volume, RigidTransform(), views(source, 1, seed=4)[0])
    labels = np.take(image.reshape(-1), model.polar_to_image_index).astype(np.uint8)
    speckle = E.speckle_field(model, 3, 11)
    for lab, sp in [
        (labels, speckle),
        (labels, None),
        (labels, speckle.astype(np.float64)),
        (labels.astype(np.int64), speckle),
        (labels[3:9], speckle[3:9]),
        (np.asfortranarray(labels), speckle),
    ]:
        before = lab.copy()
        got = E.line_db(lab, model, sp)
        assert got.dtype == np.float32 and got.flags.c_contiguous
        assert np.array_equal(got, ref_line_db(lab, model, sp))
        assert np.array_equal(lab, before)  # the caller's labels are left alone
    # Labels outside the compact codes (gel, others as soft tissue), air before tissue.
    odd = labels.copy()
    odd[::5, 40:60] = E.GEL
    odd[1::7, 100:130] = 200
    odd[:, :3] = Label.OUTSIDE
    assert np.array_equal(E.line_db(odd, model, speckle), ref_line_db(odd, model, speckle))
    # A speckle that could go below the echo floor: the floor is then taken explicitly.
    tiny = speckle * np.float32(1e-12)
    assert np.array_equal(E.line_db(labels, model, tiny), ref_line_db(labels, model, tiny))


def test_speckle_is_the_same_in_any_frame_order():
    cfg = ImagingConfig(image_height_px=64, image_width_px=64, scan_lines=32, samples_per_line=64)
    model = E.EmulatorModel.from_config(cfg)
    frames = list(range(150)) + [7, 3, 149, 500, 2**33 + 5, 150, 151, 0]
    for f in frames:
        for seed in (0, 9):
            assert np.array_equal(E.speckle_field(model, seed, f), ref_speckle(model, seed, f))
    fresh = E.EmulatorModel.from_config(cfg)
    labels = np.full(cfg.image_height_px * cfg.image_width_px, Label.SOFT_TISSUE, np.uint8).reshape(
        64, 64
    )
    for f in (40, 2, 41, 42):
        assert np.array_equal(E.emulate(labels, fresh, 9, f), E.emulate(labels, model, 9, f))


def test_segmenter_preprocessing_and_probability_equal_their_definitions(source):
    cfg = ImagingConfig(segmenter="onnx")
    g = ProbeGeometry.from_config(cfg)
    seg = OnnxSegmenter.from_config(cfg, g)
    model = E.EmulatorModel.from_config(cfg, g)
    canvas = seg.canvas
    fan = seg._canvas_fan(*canvas.shape)
    for k, X_VP in enumerate(views(source, 4, seed=5)):
        us = E.emulate(slice_volume(g, source.volume, RigidTransform(), X_VP), model, 1, k)
        img = us.astype(np.float32)
        on_canvas = np.asarray((canvas._rows @ img) @ canvas._cols.T.tocsr())
        x = seg.preprocess(us)
        assert x.shape == (1, 1) + canvas.shape and x.flags.c_contiguous
        assert np.array_equal(x[0, 0], on_canvas * np.float32(1.0 / 255.0))
        out = seg.session.run([seg.output_name], {seg.input_name: x})[0]
        sigmoid = (1.0 / (1.0 + np.exp(-out[0, 0]))).astype(np.float32)
        assert np.array_equal(seg._kidney_map(out), sigmoid)
        assert np.array_equal(seg.model_probability(us), np.where(fan, sigmoid, 0.0))
    logits = np.array([[[[-200.0, -30.0, -1e-3, 0.0, 1e-3, 30.0, 200.0]]]], np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # exp(200) is inf: the probability 0, silently
        kidney_map = seg._kidney_map(logits)
    with np.errstate(over="ignore"):
        assert np.array_equal(kidney_map, (1.0 / (1.0 + np.exp(-logits[0, 0]))).astype(np.float32))
    assert kidney_map[0, 0] == 0.0 and kidney_map[0, -1] == 1.0
    # A normalisation other than (0, 1): (x - mean) / std as before.
    other = OnnxSegmenter(seg.path, g, seg.input_shape, mean=0.3, std=0.7)
    x = canvas.to_canvas(us) * np.float32(1.0 / 255.0)
    assert np.array_equal(other.preprocess(us)[0, 0], (x - np.float32(0.3)) * np.float32(1.0 / 0.7))


def test_mask_helpers_equal_scipy_and_the_plain_definitions():
    rng = np.random.default_rng(3)
    masks = []
    for shape in [(256, 256), (64, 96), (37, 45), (8, 8), (1, 16), (16, 1), (3, 3)]:
        masks += [np.zeros(shape, bool), np.ones(shape, bool), rng.random(shape) < 0.3]
        blob = np.zeros(shape, bool)
        blob[shape[0] // 3 : 2 * shape[0] // 3 + 1, shape[1] // 4 : shape[1] // 2 + 1] = True
        masks.append(blob)
        corner = np.zeros(shape, bool)
        corner[-1, -1] = True
        masks.append(corner)
    masks.append((rng.random((256, 512)) < 0.001)[:, ::2])  # not contiguous
    for m in masks:
        assert _true_box(m) == ref_mask_box(m)
        assert mask_box(m) == ref_mask_box(m)
        assert np.array_equal(boundary_pixels(m), ref_boundary(m))
        assert mask_centroid(m) == ref_centroid(m)
        assert np.array_equal(_dilate_cross(m), ndimage.binary_dilation(m))
        p = rng.random(m.shape).astype(np.float32) * m
        assert np.array_equal(_max_3x3(p), ndimage.grey_dilation(p, size=(3, 3)))
    g = ProbeGeometry.from_config(ImagingConfig())
    m = masks[3] & g.fan_mask
    r = read_mask(m, g, 0.0)
    assert r.visible and r.centroid == ref_centroid(m)
    assert r.area == np.count_nonzero(m) * g.dx * g.dz
    assert np.array_equal(r.boundary, ref_boundary(m))


def test_tracked_component_follows_only_a_recent_nonempty_prior(geometry):
    a = np.zeros(geometry.image_shape, bool)
    a[100:140, 100:140] = True
    b = np.zeros_like(a)
    b[10:30, 10:30] = True
    b[100:105, 100:105] = True
    kw = dict(max_gap=1.0, reach=0.01)
    assert tracked_component([b, a], a, 0.5, geometry, **kw) == 1
    for age in (2.0, np.nan):  # too old, or unknown: the largest region
        assert tracked_component([b, a], a, age, geometry, **kw) == 1
        assert tracked_component([a, b], a, age, geometry, **kw) == 0
    assert tracked_component([b, a], np.zeros_like(a), 0.5, geometry, **kw) == 1


def test_accumulated_clouds_are_the_concatenation_and_stay_as_they_were(geometry):
    rng = np.random.default_rng(2)
    frames = [
        BoundaryPixels(
            rng.integers(0, 256, (int(rng.integers(0, 400)), 2)),
            0.05 * k,
            RigidTransform(RotationMatrix.MakeZRotation(0.1 * k), [0.01 * k, 0.0, 0.3]),
            k,
        )
        for k in range(40)
    ]
    clouds = [PointCloud()]
    for f in frames:
        clouds.append(accumulate(clouds[-1], f, geometry))
    want = [np.zeros((0, 3))]
    for f in frames:
        want.append(np.concatenate([want[-1], backproject_pixels(geometry, f.pixels, f.X_BP)]))
    # A second branch from an earlier cloud must not overwrite the later clouds' points.
    branch = accumulate(clouds[10], frames[30], geometry)
    for c, w in zip(clouds, want):
        assert np.array_equal(c.points, w)
        assert not c.points.flags.writeable
    assert np.array_equal(
        branch.points,
        np.concatenate(
            [want[10], backproject_pixels(geometry, frames[30].pixels, frames[30].X_BP)]
        ),
    )
    assert clouds[-1].frame_count == 40 and len(clouds[-1].poses) == 40
    # A cloud built from any points (not a growth buffer's) still accumulates.
    own = PointCloud(points=np.ones((5, 3)), frame_count=1)
    assert np.array_equal(accumulate(own, frames[1], geometry).points[:5], np.ones((5, 3)))


def test_label_volume_sampling_is_unchanged():
    vol = LabelVolume(np.arange(24, dtype=np.uint8).reshape(2, 3, 4), 0.01)
    g = ProbeGeometry.from_config(ImagingConfig(image_height_px=32, image_width_px=32))
    got = slice_volume(g, vol, RigidTransform(), RigidTransform(DOWN, [0.01, 0.01, 0.035]))
    want = np.zeros(g.image_shape, np.uint8)
    want.reshape(-1)[g.fan_flat_index] = ref_slice(
        g, vol, RigidTransform(), RigidTransform(DOWN, [0.01, 0.01, 0.035])
    )
    assert np.array_equal(got, want) and got.any()
