"""View sampling for training/test frames, IoU evaluation and the pictures command."""

import json

import numpy as np
import pytest

from drake_rus.anatomy.labels import Label
from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.dataset import ViewSampler, make_frames
from drake_rus.imaging.emulator import EmulatorModel
from drake_rus.imaging.evaluation import mean_iou
from drake_rus.imaging.phantoms import kidney_phantom
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.imaging.slicing import sample_labels


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
    cfg = ImagingConfig(image_height_px=128, image_width_px=128, scan_lines=64,
                        samples_per_line=128)
    g = ProbeGeometry.from_config(cfg)
    frames = make_frames(phantom.volume, [0, 0, 1], EmulatorModel.from_config(cfg, g), 12,
                         np.random.default_rng(1))
    assert len(frames) == 12
    seen = [m.sum() * g.pixel_area >= 1e-4 for _, m, *_ in frames]
    assert np.mean(seen) > 0.6
    perfect = {id(f[0]): f[1] for f in frames}
    r = mean_iou(lambda us: perfect[id(us)], frames, g)
    assert r["iou"] == 1.0 and r["false_positive_rate"] == 0.0
    r0 = mean_iou(lambda us: np.zeros_like(us, bool), frames, g)
    assert r0["iou"] == 0.0 and r0["frames_with_kidney"] == sum(seen)


def test_pictures_command_writes_pngs(tmp_path):
    from drake_rus.cli import main
    out = tmp_path / "pics"
    rc = main(["imaging-pictures", "--patient", "phantom:2", "--segmenter", "oracle",
               "--views", "1", "--pose", "0.08,0.1,0.15,180,0,0", "--out", str(out)])
    assert rc == 0
    summary = json.loads((out / "pictures.json").read_text())
    assert [v["view"] for v in summary["views"]] == ["centred", "pose0", "view0"]
    assert summary["views"][0]["visible"] and summary["views"][0]["iou"] == 1.0
    assert (out / "contact_sheet.png").stat().st_size > 1000
    assert (out / "00_centred.png").is_file()
    assert main(["imaging-pictures", "--patient", "phantom:2", "--pose", "1,2,3",
                 "--out", str(out)]) == 2
