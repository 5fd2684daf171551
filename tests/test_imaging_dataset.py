"""View sampling for training/test frames, IoU evaluation and the pictures command."""

import json

import numpy as np
import pytest
from pydrake.math import RigidTransform, RotationMatrix

from drake_rus.anatomy.labels import Label, LabelVolume, is_kidney
from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.emulator import EmulatorModel, emulate
from drake_rus.imaging.phantoms import kidney_phantom
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.imaging.slicing import sample_labels
from drake_rus.imaging.training.dataset import (
    EmulatorBank,
    Randomisation,
    ViewSampler,
    VolumeVariant,
    canvas_frames,
    make_frames,
    randomised_emulator,
    thicken_wall,
)
from drake_rus.imaging.training.evaluation import Source, cluster_bootstrap_ci, mean_iou, summarise


@pytest.fixture(scope="module")
def phantom():
    return kidney_phantom(np.random.default_rng(7), shape=(140, 180, 140))


def test_views_sit_on_the_skin_and_look_inwards(phantom):
    up = np.array([0.0, 0.0, 1.0])
    sampler = ViewSampler(phantom.volume, up, tilt_deg=20.0)
    rng = np.random.default_rng(0)
    for _ in range(20):
        X = sampler.sample(rng)
        assert X is not None
        z_P = X.rotation().matrix()[:, 2]
        assert np.degrees(np.arccos(-z_P @ up)) <= 20.0 + 1e-9
        p = X.translation()
        # The face centre is in tissue; a few mm back along the beam is air.
        assert sample_labels(phantom.volume, p[None])[0] != Label.OUTSIDE
        assert sample_labels(phantom.volume, (p - 0.008 * z_P)[None])[0] == Label.OUTSIDE


def test_frames_mostly_see_the_kidney_and_iou_counts(phantom):
    cfg = ImagingConfig(
        image_height_px=128, image_width_px=128, scan_lines=64, samples_per_line=128
    )
    g = ProbeGeometry.from_config(cfg)
    frames = make_frames(
        phantom.volume, [0, 0, 1], EmulatorModel.from_config(cfg, g), 12, np.random.default_rng(1)
    )
    assert len(frames) == 12
    seen = [m.sum() * g.pixel_area >= 1e-4 for _, m, *_ in frames]
    assert np.mean(seen) > 0.6
    perfect = {id(f[0]): f[1] for f in frames}
    r = mean_iou(lambda us: perfect[id(us)], frames, g)
    assert r["iou"] == 1.0 and r["false_positive_rate"] == 0.0
    r0 = mean_iou(lambda us: np.zeros_like(us, bool), frames, g)
    assert r0["iou"] == 0.0 and r0["frames_with_kidney"] == sum(seen)
    # Without a kidney-free frame the false-positive rate is not measured (NaN), not 0.
    with_kidney = [f for f, s in zip(frames, seen) if s]
    r1 = mean_iou(lambda us: perfect[id(us)], with_kidney, g)
    assert r1["frames_without_kidney"] == 0 and np.isnan(r1["false_positive_rate"])


def test_pictures_command_writes_pngs(tmp_path):
    from drake_rus.cli import main

    out = tmp_path / "pics"
    rc = main(
        [
            "imaging-pictures",
            "--patient",
            "phantom:2",
            "--segmenter",
            "oracle",
            "--views",
            "1",
            "--pose",
            "0.08,0.1,0.15,180,0,0",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    # Strict JSON: NaN/Infinity (a view without a kidney has no IoU) would fail here.
    summary = json.loads(
        (out / "pictures.json").read_text(),
        parse_constant=lambda c: pytest.fail(f"pictures.json holds {c}"),
    )
    assert [v["view"] for v in summary["views"]] == ["centred", "pose0", "view0"]
    assert summary["views"][0]["visible"] and summary["views"][0]["iou"] == 1.0
    assert (out / "contact_sheet.png").stat().st_size > 1000
    assert (out / "00_centred.png").is_file()
    assert (
        main(["imaging-pictures", "--patient", "phantom:2", "--pose", "1,2,3", "--out", str(out)])
        == 2
    )


def _kidney_centroid_Pt(vol: LabelVolume) -> np.ndarray:
    c_V = np.argwhere(is_kidney(vol.labels)).mean(axis=0) * vol.voxel_size
    return vol.X_PtV.multiply(c_V)


def _flipped(vol: LabelVolume) -> LabelVolume:
    """The same body on a grid whose first axis points down (up = -axis 0), like a decubitus
    patient's grid."""
    K = vol.labels.shape[2]
    labels = np.ascontiguousarray(np.moveaxis(vol.labels, 2, 0)[::-1])
    R = RotationMatrix(np.array([[0.0, 1, 0], [0, 0, 1], [-1, 0, 0]]))
    X_VW = RigidTransform(R, [0, 0, (K - 1) * vol.voxel_size])
    return LabelVolume(labels, vol.voxel_size, vol.X_PtV @ X_VW)


def test_thicken_wall_puts_the_kidney_deeper_and_keeps_it(phantom):
    vol = phantom.volume
    for v, up in ((vol, np.array([0.0, 0.0, 1.0])), (_flipped(vol), np.array([-1.0, 0, 0]))):
        before = Source("p", "supine", v, up).needed_depth(0.0)
        thick = thicken_wall(v, up, fat=0.010, inner=0.020)
        assert thick.labels.size > v.labels.size
        # The kidney keeps its voxels and its place in the patient frame ...
        assert is_kidney(thick.labels).sum() == is_kidney(v.labels).sum()
        np.testing.assert_allclose(_kidney_centroid_Pt(thick), _kidney_centroid_Pt(v), atol=1e-9)
        # ... and lies 30 mm deeper below the upper skin, under 10 mm more fat.
        after = Source("p", "supine", thick, up).needed_depth(0.0)
        assert after - before == pytest.approx(0.030, abs=1.5e-3)
        assert (thick.labels == Label.FAT).sum() > (v.labels == Label.FAT).sum()
    assert thicken_wall(vol, [0, 0, 1.0]) is vol
    with pytest.raises(ValueError, match="grid axis"):
        thicken_wall(vol, [1.0, 0, 1.0], fat=0.01)


def _sampled_frames(phantom, n: int, seed: int, **sampler_kw):
    """``n`` small frames of ``phantom`` from a ViewSampler with ``sampler_kw``, and their
    probe geometry."""
    cfg = ImagingConfig(
        image_height_px=128, image_width_px=128, scan_lines=64, samples_per_line=128
    )
    g = ProbeGeometry.from_config(cfg)
    up = np.array([0.0, 0.0, 1.0])
    sampler = ViewSampler(phantom.volume, up, **sampler_kw)
    model = EmulatorModel.from_config(cfg, g)
    return make_frames(
        phantom.volume, up, model, n, np.random.default_rng(seed), sampler=sampler
    ), g


def test_free_views_mostly_miss_the_kidney(phantom):
    frames, g = _sampled_frames(phantom, 12, 2, free_fraction=1.0, free_offset=(0.07, 0.09))
    seen = [m.sum() * g.pixel_area >= 1e-4 for _, m, *_ in frames]
    assert len(frames) == 12 and np.mean(seen) < 0.5


def test_randomised_emulator_shares_the_geometry_and_varies_the_image():
    bank = EmulatorBank(
        ImagingConfig(image_height_px=128, image_width_px=128, scan_lines=64, samples_per_line=128)
    )
    base = bank.get(0.15)
    assert bank.get(0.15) is base and bank.get(0.20) is not base
    assert bank.get(0.15, 32).scan_lines == 32
    rng = np.random.default_rng(0)
    m = randomised_emulator(base, rng)
    assert m.scan_matrix is base.scan_matrix and m.geometry is base.geometry
    assert m.gain_db != base.gain_db and m.frequency_mhz != base.frequency_mhz
    labels = np.where(base.geometry.fan_mask, int(Label.LIVER), 0).astype(np.uint8)
    a, b = emulate(labels, base, 0, 0), emulate(labels, m, 0, 0)
    assert a.shape == b.shape and not np.array_equal(a, b)


def test_canvas_frames_are_on_the_physical_canvas(phantom):
    cfg = ImagingConfig(
        image_height_px=128, image_width_px=128, scan_lines=64, samples_per_line=128
    )
    up = np.array([0.0, 0.0, 1.0])
    thick = thicken_wall(phantom.volume, up, fat=0.01)
    variants = [VolumeVariant(phantom.volume, up), VolumeVariant(thick, up, extra_depth=0.01)]
    d = canvas_frames(
        variants,
        [0.10, 0.20],
        6,
        np.random.default_rng(0),
        EmulatorBank(cfg),
        0.0048,
        (64, 56),
        -0.004,
        Randomisation(),
    )
    assert d["image"].shape == (6, 64, 56) and d["kidney"].shape == (6, 64, 56)
    assert set(d["depth"].tolist()) <= {np.float32(0.10), np.float32(0.20)}
    k = d["kidney"].astype(np.float32)
    assert k.min() >= 0 and k.max() <= 1.0 + 1e-3
    assert (d["kidney_px"] > 0).sum() >= 3
    # Kidney area on the canvas (mm^2) = kidney pixels x the image's pixel area.
    for i in range(6):
        g = ProbeGeometry.from_config(
            ImagingConfig(depth=float(d["depth"][i]), image_height_px=128, image_width_px=128)
        )
        assert k[i].sum() * 4.8**2 == pytest.approx(
            d["kidney_px"][i] * g.pixel_area * 1e6, rel=0.02, abs=1.0
        )


def test_summarise_groups_records():
    recs = [
        {"depth": 0.1, "posture": "supine", "iou": 0.8, "false_positive": False},
        {"depth": 0.1, "posture": "supine", "iou": None, "false_positive": True},
        {"depth": 0.2, "posture": "supine", "iou": 0.6, "false_positive": False},
    ]
    out = summarise(recs)
    assert out[0.1]["iou"] == 0.8 and out[0.1]["false_positive_rate"] == 1.0
    assert out[0.2]["frames_with_kidney"] == 1 and out[0.2]["frames_without_kidney"] == 0
    # No kidney-free frame: no false-positive rate (NaN), not a perfect 0.
    assert np.isnan(out[0.2]["false_positive_rate"])
    assert out[0.1]["iou_ci95"] == (0.8, 0.8)  # one source: no spread to resample


def test_false_positive_interval_resamples_whole_sources():
    # Kidney-free frames of 6 sources: two mark 4 of their 10 frames, the others none.
    recs = [
        {
            "depth": 0.1,
            "source": f"test:{k}",
            "posture": "supine",
            "iou": None,
            "false_positive": k < 2 and i < 4,
        }
        for k in range(6)
        for i in range(10)
    ]
    row = summarise(recs)[0.1]
    assert row["false_positive_rate"] == pytest.approx(8 / 60)
    lo, hi = row["false_positive_rate_ci95"]
    assert lo < 8 / 60 < hi
    # The marked frames sit in two sources: resampling sources gives a wide interval (no
    # source marked at all is a likely draw), far wider than 60 independent frames would.
    assert lo == 0.0 and hi > 0.2
    frames = [dict(r, source=f"frame:{j}") for j, r in enumerate(recs)]
    lo_iid, hi_iid = summarise(frames)[0.1]["false_positive_rate_ci95"]
    assert (hi - lo) > 1.5 * (hi_iid - lo_iid)
    # No kidney-free frame: no interval.
    assert np.isnan(
        summarise(recs[:0] + [dict(recs[0], iou=0.9)])[0.1]["false_positive_rate_ci95"][0]
    )


def test_cluster_bootstrap_interval_resamples_whole_sources():
    rng = np.random.default_rng(3)
    # 8 sources of 40 frames each: a per-source level (patient effect, sd 0.05) + frame noise.
    level = 0.85 + 0.05 * rng.standard_normal(8)
    values = np.concatenate([lv + 0.1 * rng.standard_normal(40) for lv in level])
    clusters = np.repeat([f"test:{k}" for k in range(8)], 40)
    lo, hi = cluster_bootstrap_ci(values, clusters)
    assert lo < values.mean() < hi
    assert cluster_bootstrap_ci(values, clusters) == (lo, hi)  # deterministic
    # Treating the 320 frames as independent gives a much narrower interval: the sources
    # are the unit of evidence.
    lo_iid, hi_iid = cluster_bootstrap_ci(values, np.arange(values.size))
    assert (hi - lo) > 1.5 * (hi_iid - lo_iid)
    # The interval covers about 1.96 standard errors of the per-source means each side.
    se = level.std(ddof=1) / np.sqrt(8)
    assert 0.5 * 3.92 * se < hi - lo < 2.0 * 3.92 * se
    assert np.isnan(cluster_bootstrap_ci([], [])[0])
    with pytest.raises(ValueError, match="one cluster each"):
        cluster_bootstrap_ci([0.5, 0.6], ["a"])
    with pytest.raises(ValueError, match="level"):
        cluster_bootstrap_ci([0.5], ["a"], level=95)


def test_kidney_context_and_structure_randomisation(phantom):
    from scipy import ndimage

    from drake_rus.imaging.training.dataset import remove_perirenal_fat, thin_cortex

    vol = phantom.volume
    kid = is_kidney(vol.labels)
    # A thin cortex: same kidney outline, cortex only within 3 mm of its surface.
    thin = thin_cortex(vol, 0.003)
    assert np.array_equal(is_kidney(thin.labels), kid)
    cortex = thin.labels == Label.KIDNEY_CORTEX
    assert 0 < cortex.sum() < (vol.labels == Label.KIDNEY_CORTEX).sum()
    depth = ndimage.distance_transform_edt(kid) * vol.voxel_size
    assert depth[cortex].max() <= 0.003 + 1e-9
    # No perirenal fat: fat near the kidney becomes soft tissue, the rest stays.
    fat_near = (vol.labels == Label.FAT) & (ndimage.distance_transform_edt(~kid) <= 15)
    assert fat_near.any()
    lean = remove_perirenal_fat(vol, 0.015)
    assert np.array_equal(is_kidney(lean.labels), kid)
    assert not (lean.labels[fat_near] == Label.FAT).any()
    far_fat = (vol.labels == Label.FAT) & ~fat_near
    assert (lean.labels[far_fat] == Label.FAT).all()


def test_near_miss_views_clear_the_kidney_by_the_offset(phantom):
    """A near-miss view's image plane lies beyond every kidney voxel, within the offset of
    the nearest: kidney-free frames of the kidney's surroundings (the pivot past its edge)."""
    up = np.array([0.0, 0.0, 1.0])
    offset = (0.002, 0.006)
    frames, _ = _sampled_frames(phantom, 10, 4, near_miss_fraction=1.0, near_miss_offset=offset)
    assert len(frames) == 10
    h = phantom.volume.voxel_size
    kidney_V = np.argwhere(is_kidney(phantom.volume.labels)) * h
    for _, mask, labels, X_VP in frames:
        assert not mask.any() and not is_kidney(labels).any()
        y = X_VP.rotation().matrix()[:, 1]
        gap = float(np.min((X_VP.translation() - kidney_V) @ y))
        # Beyond the last voxel centre by one voxel plus the drawn offset.
        assert h + offset[0] - 1e-9 <= gap <= h + offset[1] + 1e-9
    # At 0 the option draws nothing of its own: the default sampler's views, to the bit.
    plain = ViewSampler(phantom.volume, up, near_miss_fraction=0.0)
    a = plain.sample(np.random.default_rng(9))
    b = ViewSampler(phantom.volume, up).sample(np.random.default_rng(9))
    assert a.IsExactlyEqualTo(b)
