"""Probe geometry: exact pixel <-> P <-> B round trips, fan shape, config defaults."""

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw

from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.probe import ProbeGeometry, check_pose


def random_pose(rng):
    return RigidTransform(RollPitchYaw(rng.uniform(-np.pi, np.pi, 3)), rng.uniform(-1, 1, 3))


def test_pixel_P_round_trip_is_exact(geometry):
    rng = np.random.default_rng(0)
    uv = rng.uniform(-10, 300, (500, 2))
    p_P = geometry.pixel_to_P(uv)
    assert np.all(p_P[:, 1] == 0.0)
    np.testing.assert_allclose(geometry.P_to_pixel(p_P), uv, atol=1e-9)
    # Integer pixels land on the pixel-centre grid.
    p = geometry.pixel_to_P([[0, 0], [geometry.width_px - 1, geometry.height_px - 1]])
    np.testing.assert_allclose(
        p[0, [0, 2]], [geometry.x_min + geometry.dx / 2, geometry.z_min + geometry.dz / 2]
    )
    np.testing.assert_allclose(
        p[1, [0, 2]], [geometry.x_max - geometry.dx / 2, geometry.z_max - geometry.dz / 2]
    )


def test_pixel_B_round_trip_is_exact(geometry):
    rng = np.random.default_rng(1)
    for _ in range(5):
        X_BP = random_pose(rng)
        uv = rng.uniform(0, 255, (200, 2))
        p_B = geometry.pixel_to_B(uv, X_BP)
        uv2, y = geometry.B_to_pixel(p_B, X_BP)
        np.testing.assert_allclose(uv2, uv, atol=1e-9)
        np.testing.assert_allclose(y, 0.0, atol=1e-12)
        # The points lie in the x_P-z_P plane of the pose: orthogonal to y_P.
        y_B = X_BP.rotation().matrix()[:, 1]
        np.testing.assert_allclose((p_B - X_BP.translation()) @ y_B, 0.0, atol=1e-12)


def test_polar_round_trip_and_face(geometry):
    th = np.linspace(-geometry.half_angle, geometry.half_angle, 11)
    d = np.linspace(0, geometry.depth, 11)
    p = geometry.polar_to_P(th, d)
    th2, d2 = geometry.P_to_polar(p)
    np.testing.assert_allclose(th2, th, atol=1e-12)
    np.testing.assert_allclose(d2, d, atol=1e-12)
    # The face centre is the origin of P and the central line goes along +z_P.
    np.testing.assert_allclose(geometry.polar_to_P([0.0], [0.0])[0], [0, 0, 0], atol=1e-15)
    np.testing.assert_allclose(geometry.polar_to_P([0.0], [0.05])[0], [0, 0, 0.05])


def test_defaults_match_the_seed_probe(geometry):
    # Seed: "around 10 cm lateral width at 10 cm depth".
    assert 0.09 < geometry.width_at_depth(0.10) < 0.11
    assert geometry.image_shape == (256, 256)
    assert geometry.depth == pytest.approx(0.15)


def test_fan_mask(geometry):
    m = geometry.fan_mask
    assert m.shape == geometry.image_shape
    # Central column is inside from just under the face to the full depth.
    col = int(round(geometry.column_of_x(0.0)))
    rows = np.flatnonzero(m[:, col])
    z = geometry.pixel_to_P(np.c_[np.full(len(rows), col), rows])[:, 2]
    assert z.min() == pytest.approx(0.0, abs=geometry.dz)
    assert z.max() == pytest.approx(geometry.depth, abs=geometry.dz)
    # Top corners are outside; the fan covers the expected area within 2%.
    assert not m[0, 0] and not m[0, -1] and not m[-1, 0]
    area = m.sum() * geometry.pixel_area
    R, D, a = geometry.radius, geometry.depth, geometry.half_angle
    assert area == pytest.approx(a * ((R + D) ** 2 - R**2), rel=0.02)


def test_bad_pose_is_named():
    bad = RigidTransform(np.array([0.0, np.nan, 0.0]))
    with pytest.raises(ValueError, match="X_BP.*non-finite"):
        check_pose(bad)
    with pytest.raises(ValueError, match="X_BP"):
        check_pose(np.eye(4))


def test_scenario_defaults_validate():
    from drake_rus.config_schema import check_dataclass_values

    check_dataclass_values(ImagingConfig())
    from drake_rus.scenario import LoadScenario

    s = LoadScenario(scenario_text="{imaging: {segmenter: classical, probe_radius: 0.06}}")
    assert s.imaging.segmenter == "classical" and s.imaging.probe_radius == 0.06
    from drake_rus.config_schema import ScenarioError

    with pytest.raises(ScenarioError, match="imaging.segmenter"):
        LoadScenario(scenario_text="{imaging: {segmenter: magic}}")


@pytest.mark.parametrize("bad", [256.5, "256", 1, True])
def test_pixel_counts_must_be_integers(bad):
    # 256.5 and "256" used to be accepted and fail later, deep in numpy (fan_mask's
    # reshape: "'float' object cannot be interpreted as an integer").
    with pytest.raises(ValueError, match="ProbeGeometry.height_px: expected an integer number"):
        ProbeGeometry(0.05, 0.3, 0.15, bad, 64)
    with pytest.raises(ValueError, match="ProbeGeometry.width_px: expected an integer number"):
        ProbeGeometry(0.05, 0.3, 0.15, 64, bad)
    assert ProbeGeometry(0.05, 0.3, 0.15, np.int64(64), 64).fan_mask.shape == (64, 64)
