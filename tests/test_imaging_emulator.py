"""Ultrasound emulator: shadows behind ribs and gas, interfaces, attenuation/TGC, speckle."""

import numpy as np
import pytest
from pydrake.math import RigidTransform, RotationMatrix

from drake_rus.anatomy.labels import Label, LabelVolume
from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.emulator import EmulatorModel, emulate
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.imaging.slicing import slice_volume

DOWN = RotationMatrix(np.diag([1.0, -1.0, -1.0]))  # z_P = -z_B, x_P = x_B


@pytest.fixture(scope="module")
def model():
    cfg = ImagingConfig()
    return EmulatorModel.from_config(cfg, ProbeGeometry.from_config(cfg))


def column_band(g, x_lo, x_hi):
    u = np.arange(g.width_px)
    x = g.x0 + u * g.dx
    return (x >= x_lo) & (x <= x_hi)


def row_band(g, z_lo, z_hi):
    v = np.arange(g.height_px)
    z = g.z0 + v * g.dz
    return (z >= z_lo) & (z <= z_hi)


def slab_image(model, label, z_lo, z_hi, x_half):
    """Soft tissue with a block of ``label`` at depth [z_lo, z_hi] under the probe, |x| < x_half."""
    g = model.geometry
    labels = np.full((220, 20, 170), Label.SOFT_TISSUE, np.uint8)
    vol = LabelVolume(labels=labels, voxel_size=0.001)
    top = 0.165
    x = np.arange(220) * 0.001 - 0.11
    z = top - np.arange(170) * 0.001
    block = (np.abs(x)[:, None] <= x_half) & (z >= z_lo)[None, :] & (z <= z_hi)[None, :]
    labels[np.broadcast_to(block[:, None, :], labels.shape)] = label
    X_BP = RigidTransform(DOWN, [0.11, 0.01, top])
    return slice_volume(g, vol, RigidTransform(), X_BP), vol


def test_rib_shadow_is_behind_not_in_front(model):
    g = model.geometry
    labels, _ = slab_image(model, Label.BONE, 0.030, 0.040, 0.010)
    img = emulate(labels, model, seed=3, frame_index=0).astype(float)
    under = column_band(g, -0.006, 0.006)
    beside = column_band(g, 0.020, 0.032) | column_band(g, -0.032, -0.020)
    front = row_band(g, 0.008, 0.026)
    behind = row_band(g, 0.050, 0.120)

    def m(r, c):
        return img[np.ix_(r, c)][g.fan_mask[np.ix_(r, c)]].mean()

    # In front of the rib: same brightness as beside it (within 15%).
    assert m(front, under) == pytest.approx(m(front, beside), rel=0.15)
    # Behind it: a strong shadow (under a fifth of the brightness beside it).
    assert m(behind, under) < 0.2 * m(behind, beside)
    # The rib's top surface is a bright line.
    top = row_band(g, 0.027, 0.033)
    profile = img[np.ix_(top, under)].mean(axis=1)
    assert profile.max() > 1.3 * m(front, beside)
    z_peak = g.z0 + np.flatnonzero(top)[np.argmax(profile)] * g.dz
    assert z_peak == pytest.approx(0.0295, abs=0.001)


def test_gas_casts_a_complete_shadow(model):
    g = model.geometry
    labels, _ = slab_image(model, Label.GAS, 0.040, 0.050, 0.010)
    img = emulate(labels, model, seed=1, frame_index=0).astype(float)
    under = column_band(g, -0.006, 0.006)
    behind = row_band(g, 0.060, 0.140)
    assert img[np.ix_(behind, under)].max() <= 2


def test_attenuation_and_tgc(model):
    import dataclasses

    g = model.geometry
    labels, _ = slab_image(model, Label.SOFT_TISSUE, 1.0, 1.0, 0.0)  # homogeneous
    centre = column_band(g, -0.01, 0.01)
    shallow, deep = row_band(g, 0.02, 0.04), row_band(g, 0.11, 0.13)
    img = emulate(labels, model, 0, 0).astype(float)
    # TGC matched to soft tissue (0.7 dB/cm/MHz): no net fall-off with depth.
    assert img[np.ix_(deep, centre)].mean() == pytest.approx(
        img[np.ix_(shallow, centre)].mean(), rel=0.08
    )
    # Without TGC the image darkens with depth: 2 x 0.7 x 3.5 dB/cm over 9 cm = 44 dB.
    no_tgc = dataclasses.replace(model, tgc_db_per_cm_mhz=0.0)
    img2 = emulate(labels, no_tgc, 0, 0).astype(float)
    drop_grey = img2[np.ix_(shallow, centre)].mean() - img2[np.ix_(deep, centre)].mean()
    expected = 2 * 0.7 * 3.5 * 9.0 * 255 / model.dynamic_range_db
    assert drop_grey == pytest.approx(min(expected, img2[np.ix_(shallow, centre)].mean()), rel=0.15)


def test_echogenicity_ordering(model):
    g = model.geometry
    means = {}
    for label in (
        Label.KIDNEY_SINUS,
        Label.LIVER,
        Label.KIDNEY_CORTEX,
        Label.KIDNEY_MEDULLA,
        Label.VESSEL,
    ):
        img = np.zeros(g.image_shape, np.uint8)
        img[g.fan_mask] = label
        out = emulate(
            img, dataclasses_replace(model, tgc_db_per_cm_mhz=model.tgc_db_per_cm_mhz), 0, 0
        ).astype(float)
        means[label] = out[np.ix_(row_band(g, 0.01, 0.03), column_band(g, -0.01, 0.01))].mean()
    assert (
        means[Label.KIDNEY_SINUS]
        > means[Label.LIVER]
        > means[Label.KIDNEY_CORTEX]
        > means[Label.KIDNEY_MEDULLA]
        > means[Label.VESSEL]
    )


def dataclasses_replace(obj, **kw):
    import dataclasses

    return dataclasses.replace(obj, **kw)


def test_deterministic_per_seed_and_frame(model):
    labels, _ = slab_image(model, Label.BONE, 0.030, 0.040, 0.010)
    a = emulate(labels, model, seed=5, frame_index=7)
    assert np.array_equal(a, emulate(labels, model, seed=5, frame_index=7))
    assert not np.array_equal(a, emulate(labels, model, seed=5, frame_index=8))
    assert not np.array_equal(a, emulate(labels, model, seed=6, frame_index=7))
    g = model.geometry
    assert not a[~g.fan_mask].any()
    assert a.dtype == np.uint8 and a.shape == g.image_shape


def test_probe_in_air_sees_nothing(model):
    g = model.geometry
    img = np.zeros(g.image_shape, np.uint8)  # all OUTSIDE (air) in the fan
    out = emulate(img, model, 0, 0)
    assert out[row_band(g, 0.01, 0.15)].max() <= 2


def test_wrong_shape_is_named(model):
    with pytest.raises(ValueError, match="shape"):
        emulate(np.zeros((10, 10), np.uint8), model)


@pytest.mark.parametrize(
    "image, match",
    [
        (np.full((1, 1), 263, np.int32), "label values 0-255, got 263..263"),
        (np.full((1, 1), -1, np.int64), "label values 0-255, got -1..-1"),
        (np.full((1, 1), np.nan), "integer label values 0-255, got dtype float64"),
    ],
    ids=["above_255", "negative", "float"],
)
def test_label_values_outside_uint8_are_refused(model, image, match):
    # They used to be cast to uint8 without a word: 263 was imaged as the liver (7), as
    # line_db refuses them.
    g = model.geometry
    labels = np.broadcast_to(image, g.image_shape)
    with pytest.raises(ValueError, match=match):
        emulate(labels, model)
    wide = np.full(g.image_shape, Label.LIVER, np.int64)  # a wider type in range is fine
    assert np.array_equal(emulate(wide, model), emulate(wide.astype(np.uint8), model))
