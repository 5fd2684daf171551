"""The compiled kernels of the imaging chain (drake_rus.imaging.kernels) give the same values,
bit for bit, as plain numpy references written here: on realistic frames (views of test:0)
and on edge cases (lines of air only, of gas, of bone, gel, unknown labels, views far outside
the volume). No tolerance anywhere."""

import numpy as np
import pytest
import scipy.sparse as sps
from pydrake.math import RigidTransform, RotationMatrix

from drake_rus.anatomy.labels import Label, LabelVolume
from drake_rus.imaging import emulator as E
from drake_rus.imaging import kernels as K
from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.imaging.slicing import padded_labels, slice_volume
from drake_rus.imaging.slicing import warm_up as warm_slicer

DOWN = RotationMatrix(np.diag([1.0, -1.0, -1.0]))


# --- numpy references ---------------------------------------------------------------------


def ref_line_db(labels_ls, model, speckle):
    """Echo level (L, S) along each line: compact codes with the gel rule, pair tables,
    np.cumsum of the losses along the line, numpy's log10."""
    labels_ls = np.asarray(labels_ls)
    codes = np.take(model.compact_codes, labels_ls)
    n_gel = model.gel_samples
    if n_gel:
        air = np.cumprod(labels_ls[:, :n_gel] == Label.OUTSIDE, axis=1).astype(bool)
        codes[:, :n_gel][air] = model.compact_codes[E.GEL]
    pair = np.empty(codes.shape, np.intp)
    pair[:, 0] = int(model.compact_codes[E.PROBE_LABEL]) << 4
    pair[:, 1:] = codes[:, :-1].astype(np.intp) << 4
    pair |= codes
    loss_lut, diffuse_lut, spec_lut = model.pair_luts
    echo = diffuse_lut[pair]
    if speckle is not None:
        echo = echo * speckle
    echo = np.maximum(echo + spec_lut[pair], np.float32(1e-12))
    db = np.log10(echo) * np.float32(10.0)
    return (db - np.cumsum(loss_lut[pair], axis=1, dtype=np.float32)) + model.tgc_db


def ref_emulate(label_image, model, seed, frame):
    labels = label_image.reshape(-1)[model.polar_to_image_index].astype(np.uint8)
    speckle = E.speckle_field(model, seed, frame) if model.speckle else None
    grey = ref_line_db(labels, model, speckle) + np.float32(model.dynamic_range_db)
    grey = np.clip(grey * np.float32(255.0 / model.dynamic_range_db), 0.0, 255.0)
    return ref_scan_convert(grey, model)


def ref_scan_convert(grey, model):
    values = model.scan_matrix @ grey.astype(np.float32).reshape(-1)
    return (values + np.float32(0.5)).astype(np.uint8).reshape(model.geometry.image_shape)


def ref_slice(g, volume, X_VP, y=0.0):
    """One plane: per fan pixel float32 voxel coordinates, truncated, clipped, looked up."""
    A = (X_VP.rotation().matrix() / volume.voxel_size).astype(np.float32)
    b = (X_VP.translation() / volume.voxel_size).astype(np.float32)
    c = b + np.float32(y) * A[:, 1] + np.float32(1.5)
    px, pz = g.fan_x_z32
    padded = padded_labels(volume.labels)
    index = []
    for a in range(3):
        f = px * A[a, 0] + (pz * A[a, 2] + c[a])
        with np.errstate(invalid="ignore"):
            index.append(np.clip(f.astype(np.int32), 0, padded.shape[a] - 1))
    image = np.zeros(g.image_shape, np.uint8)
    image.reshape(-1)[g.fan_flat_index] = padded[tuple(index)]
    return image


# --- inputs -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def source():
    from drake_rus.imaging.training.evaluation import load_source

    return load_source("test:0", posture="supine")


@pytest.fixture(scope="module")
def model():
    cfg = ImagingConfig()
    m = E.EmulatorModel.from_config(cfg, ProbeGeometry.from_config(cfg))
    E.warm_up(m, 5)
    return m


def edge_labels(model, rng):
    """(L, S) uint8 label lines: realistic layers, then whole lines of air (probe off the
    body), gas, bone, gel, labels without a table entry, air gaps after tissue."""
    L, S = model.scan_lines, model.samples_per_line
    layers = [
        Label.OUTSIDE,
        Label.SOFT_TISSUE,
        Label.FAT,
        Label.MUSCLE,
        Label.KIDNEY_CORTEX,
        Label.KIDNEY_MEDULLA,
        Label.KIDNEY_SINUS,
        Label.VESSEL,
        Label.LIVER,
    ]
    lab = np.empty((L, S), np.uint8)
    for ln in range(L):
        cuts = np.sort(rng.integers(0, S, 6))
        lab[ln] = np.repeat(rng.choice(layers, 7), np.diff(np.r_[0, cuts, S]))
    lab[0] = Label.OUTSIDE
    lab[1] = Label.GAS
    lab[2] = Label.BONE
    lab[3, :] = Label.SOFT_TISSUE
    lab[3, 40:44] = Label.BONE
    lab[4] = E.GEL
    lab[5] = 200
    lab[6, :] = Label.FAT
    lab[6, 100:] = Label.OUTSIDE
    lab[7, : model.gel_samples + 2] = Label.OUTSIDE
    lab[8, 1::2] = Label.OUTSIDE
    return lab


def test_line_db_kernel_equals_numpy_on_edge_lines(model):
    rng = np.random.default_rng(0)
    lab = edge_labels(model, rng)
    speckle = E.speckle_field(model, 5, 3)
    for sp in (speckle, None, np.float32(0.0) * speckle, speckle * np.float32(1e-12)):
        got = E.line_db(lab, model, sp)
        assert got.dtype == np.float32 and got.shape == lab.shape
        assert np.array_equal(got.view(np.uint32), ref_line_db(lab, model, sp).view(np.uint32))
    # A single line, and air-only lines (no tissue at all: gel, then air to the end).
    for part in (lab[:1], lab[5:6], np.zeros_like(lab)):
        sp = speckle[: len(part)]
        assert np.array_equal(
            E.line_db(part, model, sp).view(np.uint32), ref_line_db(part, model, sp).view(np.uint32)
        )


def test_emulate_kernels_equal_numpy_on_edge_images(model):
    g = model.geometry
    rng = np.random.default_rng(1)
    images = [
        np.zeros(g.image_shape, np.uint8),  # nothing under the probe
        np.full(g.image_shape, Label.GAS, np.uint8),
        np.full(g.image_shape, Label.BONE, np.uint8),
        rng.integers(0, 16, g.image_shape).astype(np.uint8),
        rng.choice([0, 1, 8, 9, 200, 255], g.image_shape).astype(np.uint8),
    ]
    layered = np.full(g.image_shape, Label.SOFT_TISSUE, np.uint8)
    layered[:6] = Label.OUTSIDE
    layered[60:64] = Label.BONE
    layered[120:] = Label.GAS
    images.append(layered)
    for k, image in enumerate(images):
        image = image * g.fan_mask.astype(np.uint8)
        frozen = image.copy()
        frozen.flags.writeable = False
        want = ref_emulate(image, model, 5, k)
        assert np.array_equal(E.emulate(image, model, 5, k), want)
        assert np.array_equal(E.emulate(frozen, model, 5, k), want)
        assert np.array_equal(E.emulate(image.astype(np.int64), model, 5, k), want)


def test_emulate_kernels_equal_numpy_on_test0_views(source, model):
    from drake_rus.imaging.training.evaluation import sample_views

    g = model.geometry
    for k, X_VP in enumerate(sample_views(source, 6, seed=3)):
        image = slice_volume(g, source.volume, RigidTransform(), X_VP)
        assert np.array_equal(E.emulate(image, model, 2, k), ref_emulate(image, model, 2, k))
        labels = image.reshape(-1)[model.polar_to_image_index]
        sp = E.speckle_field(model, 2, k)
        assert np.array_equal(
            E.line_db(labels, model, sp).view(np.uint32),
            ref_line_db(labels, model, sp).view(np.uint32),
        )


def test_scan_convert_kernel_equals_scipy(model):
    rng = np.random.default_rng(2)
    L, S = model.scan_lines, model.samples_per_line
    for grey in (
        rng.random((L, S)) * 255,
        np.zeros((L, S)),
        np.full((L, S), 255.0),
        rng.choice([0.0, 254.5, 255.0], (L, S)),
    ):
        grey = grey.astype(np.float32)
        assert np.array_equal(E.scan_convert(grey, model), ref_scan_convert(grey, model))
    assert model._scan_quads is not None  # the fixed-length path is the one in use


def test_generic_csr_kernel_equals_scipy():
    rng = np.random.default_rng(3)
    m = sps.random(500, 300, density=0.008, format="csr", dtype=np.float32, random_state=4)
    m.data *= np.float32(3.0)
    x = (rng.random(300) * 200).astype(np.float32)
    out = np.empty(500, np.uint8)
    K.csr_to_uint8(m.indptr, m.indices, m.data, x, out)
    want = ((m @ x) + np.float32(0.5)).astype(np.uint8)
    assert np.array_equal(out, want)
    assert (np.diff(m.indptr) == 0).any() and len(set(np.diff(m.indptr))) > 3


def test_slice_kernel_equals_numpy(source):
    g = ProbeGeometry.from_config(ImagingConfig(depth=0.16))
    vol = source.volume
    warm_slicer(g, vol)
    from drake_rus.imaging.training.evaluation import sample_views

    poses = sample_views(source, 5, seed=5)
    poses += [
        RigidTransform(DOWN, [0.05, 0.05, 0.30]),  # partly out
        RigidTransform(DOWN, [-0.2, 0.1, 0.1]),  # wholly out
        RigidTransform(RotationMatrix.MakeXRotation(0.7), [0.1, 0.3, 0.05]),
        RigidTransform(DOWN, [1e7, -1e7, 3e7]),  # beyond int32 voxel indices
        RigidTransform(DOWN, [-1e7, 0.0, 0.0]),
    ]
    for X_VP in poses:
        got = slice_volume(g, vol, RigidTransform(), X_VP)
        assert np.array_equal(got, ref_slice(g, vol, X_VP))
    got = slice_volume(g, vol, RigidTransform(), poses[0], planes=3, combine="max")
    want = np.maximum.reduce([ref_slice(g, vol, poses[0], y) for y in (-0.005, 0.0, 0.005)])
    assert np.array_equal(got, want)


def test_slice_kernel_on_a_tiny_volume_seen_from_every_side():
    g = ProbeGeometry.from_config(ImagingConfig(image_height_px=48, image_width_px=40, depth=0.05))
    labels = np.random.default_rng(6).integers(1, 12, (7, 5, 9)).astype(np.uint8)
    vol = LabelVolume(labels, 0.004)
    for X_VP in (
        RigidTransform(DOWN, [0.01, 0.01, 0.03]),
        RigidTransform(RotationMatrix.MakeYRotation(2.0), [0.0, 0.01, 0.0]),
        RigidTransform(RotationMatrix.MakeZRotation(0.4) @ DOWN, [0.02, -0.01, 0.05]),
    ):
        got = slice_volume(g, vol, RigidTransform(), X_VP)
        assert np.array_equal(got, ref_slice(g, vol, X_VP))


def test_warm_up_compiles_every_signature_the_chain_uses(source, model):
    """After the warm-ups, frames (read-only, as the systems pass them) compile nothing."""
    g = model.geometry
    warm_slicer(g, source.volume)
    kernels = (K.echo_and_loss, K.grey_scan_convert, K.quads_to_uint8, K.slice_plane)
    before = [len(k.signatures) for k in kernels]
    image = slice_volume(g, source.volume, RigidTransform(), RigidTransform(DOWN, [0.1, 0.1, 0.2]))
    image.flags.writeable = False
    E.emulate(image, model, 5, 9)
    assert [len(k.signatures) for k in kernels] == before


def test_line_db_rejects_bad_labels_with_the_expected_form():
    cfg = ImagingConfig()
    model = E.EmulatorModel.from_config(cfg, ProbeGeometry.from_config(cfg))
    S = model.samples_per_line
    with pytest.raises(ValueError, match=rf"labels_ls: expected \(lines, {S}\)"):
        E.line_db(np.zeros((4, S + 1), np.uint8), model, None)
    with pytest.raises(ValueError, match="label values 0-255, got -1..3"):
        E.line_db(np.array([[3] * S, [-1] * S]), model, None)
