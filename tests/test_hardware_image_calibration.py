"""Image-to-probe calibration: the file (yaml_load_typed), the fit to point-target pictures
(scale, origin, in-plane angle, mirror; residuals; degenerate input refused), the map of
grabbed pictures onto the probe's image grid, `drake-rus hardware calibrate-image`, and the
hardware station using the entry for imaging.depth."""

import math

import numpy as np
import pytest
from pydrake.common.yaml import yaml_dump_typed
from pydrake.lcm import DrakeLcm
from pydrake.systems.analysis import Simulator

from drake_rus.config_schema import ScenarioError
from drake_rus.hardware.image_calibration import (
    DepthPresetCalibration,
    ImageCalibration,
    ImageToProbeMap,
    TargetImage,
    TargetSet,
    find_point_target,
    fit_image_calibration,
    fit_target_set,
    load_image_calibration,
    load_target_set,
    preset_for_depth,
    save_image_calibration,
    targets_in_probe_frame,
    with_preset,
)
from drake_rus.hardware.lcm_sim_driver import SimulatedPandaDriver
from drake_rus.hardware.station import MakeHardwareStation, RunHardware
from drake_rus.hardware.video import SyntheticVideo
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.scenario import ApplyOverrides, LoadScenario, Scenario

cv2 = pytest.importorskip("cv2", reason="opencv-python-headless is not installed")

pytestmark = [pytest.mark.timeout(120), pytest.mark.wallclock]

PICTURE = (480, 640)  # rows, cols of the grabbed picture
CROP = [100, 30, 440, 430]  # the sector in it


def true_calibration(depth=0.15, angle_deg=1.5, mirror=False):
    cal = with_preset(
        ImageCalibration(),
        DepthPresetCalibration(
            depth=depth, crop=list(CROP), mm_per_pixel=[0.36, 0.38], origin_px=[321.5, 52.0]
        ),
        angle_deg=angle_deg,
        mirror_x=mirror,
    )
    return cal


def target_grid():
    """Target positions in P (m): 4 lateral x 3 depths."""
    xs, zs = np.meshgrid([-0.03, -0.01, 0.012, 0.028], [0.04, 0.08, 0.12])
    return np.stack([xs.ravel(), np.zeros(xs.size), zs.ravel()], axis=1)


def dot_picture(col, row, shape=PICTURE, sigma=1.6):
    rr, cc = np.mgrid[0 : shape[0], 0 : shape[1]]
    grey = 15 + 230 * np.exp(-((cc - col) ** 2 + (rr - row) ** 2) / (2 * sigma**2))
    picture = np.repeat(grey.astype(np.uint8)[:, :, None], 3, axis=2)
    picture[:20, :] = 255  # the machine's menu bar, outside the crop
    return picture


def write_targets(tmp_path, cal, p_P, depth=0.15, noise_px=0.0, seed=0):
    m = ImageToProbeMap(cal, preset_for_depth(cal, depth), geometry())
    pixels = m.P_to_picture(p_P) + np.random.default_rng(seed).normal(0, noise_px, (len(p_P), 2))
    targets = []
    for k, ((c, r), p) in enumerate(zip(pixels, p_P)):
        name = f"t{k:02d}.png"
        cv2.imwrite(str(tmp_path / name), dot_picture(c, r))
        targets.append(TargetImage(image=name, p_P=[float(v) for v in p]))
    path = tmp_path / "targets.yaml"
    path.write_text(yaml_dump_typed(TargetSet(depth=depth, crop=list(CROP), targets=targets)))
    return path, pixels


def geometry(depth=0.15):
    s = Scenario()
    s.imaging.depth = depth
    return ProbeGeometry.from_config(s.imaging)


@pytest.mark.parametrize("mirror", [False, True])
def test_fit_recovers_scale_origin_angle_from_point_targets(tmp_path, mirror):
    cal = true_calibration(mirror=mirror)
    path, pixels = write_targets(tmp_path, cal, target_grid(), noise_px=0.15)
    from drake_rus.hardware.image_calibration import load_target_set

    report = fit_target_set(load_target_set(path), tmp_path)
    fit = report.fit
    np.testing.assert_allclose(report.pixels, pixels, atol=0.5)  # targets found
    np.testing.assert_allclose(fit.mm_per_pixel, [0.36, 0.38], rtol=3e-3)
    np.testing.assert_allclose(fit.origin_px, [321.5, 52.0], atol=0.6)
    assert fit.angle_deg == pytest.approx(1.5, abs=0.1)
    assert fit.mirror_x == mirror and abs(fit.skew_deg) < 0.2
    assert fit.rms_mm < 0.15 and len(fit.residuals_mm) == 12
    # The fitted calibration maps the targets back onto their pixels.
    refit = with_preset(
        ImageCalibration(), fit.preset(0.15, CROP), angle_deg=fit.angle_deg, mirror_x=fit.mirror_x
    )
    m = ImageToProbeMap(refit, refit.presets[0], geometry())
    np.testing.assert_allclose(m.P_to_picture(target_grid()), pixels, atol=0.6)
    np.testing.assert_allclose(
        m.picture_to_P(m.P_to_picture(target_grid()))[:, [0, 2]],
        target_grid()[:, [0, 2]],
        atol=1e-12,
    )
    print(
        f"\n[image cal] mirror {mirror}: {fit.mm_per_pixel[0]:.4f} x "
        f"{fit.mm_per_pixel[1]:.4f} mm/px (true 0.36 x 0.38), origin "
        f"({fit.origin_px[0]:.2f}, {fit.origin_px[1]:.2f}) (true 321.5, 52.0), angle "
        f"{fit.angle_deg:.3f} deg (true 1.5), RMS {fit.rms_mm:.3f} mm"
    )


def test_degenerate_input_is_refused_with_a_clear_message(tmp_path):
    grid = target_grid()
    cal = true_calibration()
    pixels = ImageToProbeMap(cal, cal.presets[0], geometry()).P_to_picture(grid)
    with pytest.raises(ValueError, match="at least 3 target images, got 2"):
        fit_image_calibration(pixels[:2], grid[:2])
    same_depth = grid[:, 2] == grid[0, 2]
    with pytest.raises(ValueError, match="lie on a line.*different depths AND lateral"):
        fit_image_calibration(pixels[same_depth], grid[same_depth])
    with pytest.raises(ValueError, match="lie on a line"):
        fit_image_calibration(np.repeat(pixels[:1], 5, axis=0), np.repeat(grid[:1], 5, axis=0))
    bad = pixels.copy()
    bad[3, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        fit_image_calibration(bad, grid)
    with pytest.raises(ValueError, match=r"\(12, 3\) or \(12, 2\)"):
        fit_image_calibration(pixels, grid[:5])
    # A picture without a target names the picture.
    path, _ = write_targets(tmp_path, cal, grid[:4])
    cv2.imwrite(str(tmp_path / "t02.png"), np.full(PICTURE + (3,), 40, np.uint8))
    from drake_rus.hardware.image_calibration import load_target_set

    with pytest.raises(ValueError, match=r"targets\[2\] \(t02.png\): no point target"):
        fit_target_set(load_target_set(path), tmp_path)


def test_calibration_file_round_trip_and_errors(tmp_path):
    cal = with_preset(true_calibration(), DepthPresetCalibration(depth=0.2, crop=list(CROP)))
    path = tmp_path / "cal.yaml"
    save_image_calibration(cal, path)
    back = load_image_calibration(path)
    assert [p.depth for p in back.presets] == [0.15, 0.2]
    assert back.presets[0].mm_per_pixel == [0.36, 0.38]
    np.testing.assert_allclose(
        back.X_PI.GetDeterministicValue().GetAsMatrix4(),
        cal.X_PI.GetDeterministicValue().GetAsMatrix4(),
        atol=1e-12,
    )
    with pytest.raises(ScenarioError, match=r"no entry for imaging.depth 0.3 m .*0.15, 0.2"):
        preset_for_depth(back, 0.3, source=str(path))
    path.write_text("presets:\n- {depth: 0.15, mm_per_pixel: [0.3]}\n")
    with pytest.raises(ScenarioError, match=r"image_calibration.*presets\[0\].mm_per_pixel"):
        load_image_calibration(path)
    with pytest.raises(ScenarioError, match="not found"):
        load_image_calibration(tmp_path / "missing.yaml")


def test_map_puts_targets_on_the_probe_grid():
    """A point at p_P drawn where the calibration says it is in the grabbed picture lands on
    ProbeGeometry.P_to_pixel(p_P) in the mapped image: segmentation and back-projection are
    metric."""
    cal = true_calibration()
    g = geometry()
    m = ImageToProbeMap(cal, cal.presets[0], g)
    for p in target_grid()[[0, 5, 11]]:
        col, row = m.P_to_picture(p[None])[0]
        image = m(dot_picture(col, row, sigma=3.0))
        assert image.shape == g.image_shape and image.dtype == np.uint8
        found = find_point_target(image, radius=4, blur_px=0.0)
        np.testing.assert_allclose(found, g.P_to_pixel(p[None])[0], atol=0.6)
    # Nothing outside the crop (the menu bar) reaches the image.
    assert m(np.full(PICTURE + (3,), 255, np.uint8)).max() == 255
    blank = np.zeros(PICTURE + (3,), np.uint8)
    blank[: CROP[1]] = 255
    assert m(blank).max() == 0


def test_targets_in_probe_frame():
    from pydrake.math import RigidTransform, RotationMatrix

    X = RigidTransform(RotationMatrix.MakeXRotation(math.pi), [0.5, 0.0, 0.3])
    np.testing.assert_allclose(
        targets_in_probe_frame([X], [0.51, 0.0, 0.2])[0], [0.01, 0.0, 0.1], atol=1e-12
    )


def test_cli_calibrate_image_writes_merges_and_refuses(tmp_path, capsys):
    from drake_rus.cli import main

    path, _ = write_targets(tmp_path, true_calibration(), target_grid(), noise_px=0.1)
    out = tmp_path / "image_calibration.yaml"
    assert main(["hardware", "calibrate-image", str(path), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "0.36" in text and "residuals: RMS" in text and "t11.png" in text
    cal = load_image_calibration(out)
    assert [p.depth for p in cal.presets] == [0.15]
    # Another preset merges into the same file.
    deeper = tmp_path / "deep"
    deeper.mkdir()
    cal30 = with_preset(
        ImageCalibration(),
        DepthPresetCalibration(
            depth=0.3, crop=list(CROP), mm_per_pixel=[0.7, 0.72], origin_px=[321.0, 50.0]
        ),
        angle_deg=1.5,
    )
    grid30 = target_grid() * [1, 1, 2]
    path30, _ = write_targets(deeper, cal30, grid30, depth=0.3)
    assert main(["hardware", "calibrate-image", str(path30), "--out", str(out)]) == 0
    capsys.readouterr()
    assert [p.depth for p in load_image_calibration(out).presets] == [0.15, 0.3]
    # Degenerate input: refused, exit 2, the file untouched.
    line = tmp_path / "line"
    line.mkdir()
    same = target_grid()[target_grid()[:, 2] == 0.08]
    path_line, _ = write_targets(line, true_calibration(), same)
    before = out.read_text()
    assert main(["hardware", "calibrate-image", str(path_line), "--out", str(out)]) == 2
    assert "refused" in capsys.readouterr().err and out.read_text() == before
    # Poor pictures (2 px of detection noise): residuals above the limits, not written.
    noisy = tmp_path / "noisy"
    noisy.mkdir()
    path_noisy, _ = write_targets(noisy, true_calibration(), target_grid(), noise_px=4.0)
    assert main(["hardware", "calibrate-image", str(path_noisy), "--out", str(out)]) == 1
    assert "not written" in capsys.readouterr().out and out.read_text() == before


def test_station_maps_pictures_with_the_entry_for_imaging_depth(tmp_path):
    """The hardware station (LCM route, simulated driver) with an image calibration: a
    picture of a target at a known p_P becomes a us_image with the target at
    ProbeGeometry.P_to_pixel(p_P)."""
    cal = true_calibration()
    cal_path = tmp_path / "cal.yaml"
    save_image_calibration(cal, cal_path)
    p_target = np.array([[0.012, 0.0, 0.09]])
    col, row = ImageToProbeMap(cal, cal.presets[0], geometry()).P_to_picture(p_target)[0]
    picture = dot_picture(col, row, sigma=3.0)
    scenario = ApplyOverrides(
        LoadScenario(),
        (
            "{hardware: true, imaging: {depth: 0.15}, hardware_interface: {backend: lcm, "
            "tau_external_bias_duration: 0.0, connect_timeout: 5.0, status_timeout: 1.0, "
            "image_calibration: '%s'}}" % cal_path
        ),
    )
    lcm = DrakeLcm("memq://")
    driver = SimulatedPandaDriver(lcm, scenario.robot.initial_joint_positions)
    dsim = Simulator(driver)
    dsim.Initialize()

    def step():
        dsim.AdvanceTo(dsim.get_context().get_time() + 0.005)

    station = MakeHardwareStation(
        scenario, lcm=lcm, lcm_idle=step, video=SyntheticVideo(lambda t: picture, 30.0)
    )
    try:
        sim = Simulator(station)
        ctx = station.GetMyContextFromRoot(sim.get_context())
        station.get_input_port().FixValue(ctx, np.zeros(7))
        sim.Initialize()
        RunHardware(sim, station, 0.3, check_period=0.005, realtime_rate=1.0, on_step=step)
        frame = station.GetOutputPort("us_image").Eval(ctx)
    finally:
        station.close()
    g = geometry()
    assert frame.valid and frame.image.shape == g.image_shape
    found = find_point_target(frame.image, radius=4, blur_px=0.0)
    np.testing.assert_allclose(found, g.P_to_pixel(p_target)[0], atol=0.6)
    # A depth without an entry is refused before connecting.
    other = ApplyOverrides(scenario, "{imaging: {depth: 0.25}}")
    with pytest.raises(ScenarioError, match="no entry for imaging.depth 0.25"):
        MakeHardwareStation(other, lcm=DrakeLcm("memq://"))


def test_yaml_syntax_errors_are_one_line_naming_the_file(tmp_path, capsys):
    """A YAML syntax error in the target file (calibrate-image) or in the calibration file is
    one line naming the file, the line and the column, not PyYAML's four-line text."""
    from drake_rus.cli import main

    bad = tmp_path / "targets.yaml"
    bad.write_text("depth: 0.15\ntargets: [\n  {image: a.png\n")
    out = tmp_path / "cal.yaml"
    assert main(["hardware", "calibrate-image", str(bad), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and str(bad) in err and "line 4, column 1" in err, err
    assert not out.exists()
    out.write_text("presets: [\n")
    with pytest.raises(ScenarioError) as info:
        load_image_calibration(out)
    assert "\n" not in str(info.value) and "not valid YAML" in str(info.value)
    assert "line 2, column 1" in str(info.value)


@pytest.mark.parametrize("text,expected", [("", "the file is empty"), ("- 1\n", "got a list")])
def test_an_empty_or_non_mapping_file_is_named(tmp_path, text, expected):
    """An empty target or calibration file, or one holding a list, is one line naming the
    file and the expected mapping, not Drake's "YAML root was a <class 'NoneType'>"."""
    for name, load in (("targets.yaml", load_target_set), ("cal.yaml", load_image_calibration)):
        path = tmp_path / name
        path.write_text(text)
        with pytest.raises(ScenarioError) as info:
            load(path)
        message = str(info.value)
        assert str(path) in message and expected in message and "YAML mapping" in message
        assert "\n" not in message and "YAML root" not in message


def test_a_failed_write_leaves_the_calibration_file_as_it_was(tmp_path, monkeypatch):
    """Writing the calibration file is atomic: a write that fails part-way (a full disk, a
    file size limit) leaves the old file, not a cut-off one whose last entry would load
    with the default scale and origin."""
    import pathlib

    path = tmp_path / "cal.yaml"
    cal = true_calibration()
    save_image_calibration(cal, path)
    before = path.read_text()
    deeper = with_preset(
        cal,
        DepthPresetCalibration(
            depth=0.3, crop=list(CROP), mm_per_pixel=[0.7, 0.72], origin_px=[321.0, 50.0]
        ),
    )
    real_write_text = pathlib.Path.write_text

    def write_half_then_fail(self, text, *args, **kwargs):
        real_write_text(self, text[: len(text) // 2], *args, **kwargs)
        raise OSError(27, "File too large")

    monkeypatch.setattr(pathlib.Path, "write_text", write_half_then_fail)
    with pytest.raises(OSError):
        save_image_calibration(deeper, path)
    monkeypatch.undo()
    assert path.read_text() == before
    assert [p.depth for p in load_image_calibration(path).presets] == [0.15]
    assert sorted(q.name for q in tmp_path.iterdir()) == ["cal.yaml"]
