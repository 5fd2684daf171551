"""Metrics on analytic cases: translation, rotation about a known axis, a sphere's coverage."""

import numpy as np
import pytest
from pydrake.math import RigidTransform, RotationMatrix

from drake_rus.metrics.core import (
    CoverageAccumulator,
    e_rot_x,
    e_trans,
    imaging_window_path_length,
    volume_ratio,
)


def test_e_trans_ignores_z_and_rotation():
    a = RigidTransform(RotationMatrix.MakeZRotation(0.3), [0.50, 0.10, 0.20])
    b = RigidTransform([0.53, 0.14, -0.40])
    assert e_trans(a, b) == pytest.approx(0.05)


def test_e_rot_x_pure_rotations():
    X = RigidTransform()
    # Rotation about x leaves the x-axis alone.
    assert e_rot_x(
        RigidTransform(RotationMatrix.MakeXRotation(0.7), [0, 0, 0]), X
    ) == pytest.approx(0.0, abs=1e-12)
    # About z by 20 deg moves it by 20 deg.
    assert e_rot_x(
        RigidTransform(RotationMatrix.MakeZRotation(np.deg2rad(20)), [0, 0, 0]), X
    ) == pytest.approx(np.deg2rad(20))
    # A flipped axis is 180 deg, not 0.
    assert e_rot_x(
        RigidTransform(RotationMatrix.MakeZRotation(np.pi), [0, 0, 0]), X
    ) == pytest.approx(np.pi)


def test_path_length_translation_and_pivot():
    L = 0.15
    line = [RigidTransform([0, 0.001 * k, 0]) for k in range(51)]
    assert imaging_window_path_length(line, L) == pytest.approx(0.05)
    pivot = [
        RigidTransform(RotationMatrix.MakeXRotation(np.deg2rad(k)), [0, 0, 0]) for k in range(31)
    ]
    assert imaging_window_path_length(pivot, L) == pytest.approx(L * np.deg2rad(30))
    # Both at once: the steps combine as a hypotenuse.
    both = [
        RigidTransform(RotationMatrix.MakeXRotation(0.01 * k), [0.002 * k, 0, 0]) for k in range(3)
    ]
    assert imaging_window_path_length(both, L) == pytest.approx(2 * np.hypot(0.002, 0.0015))
    with pytest.raises(ValueError, match="image_depth"):
        imaging_window_path_length(line, 0.0)


def sphere_voxels(radius, spacing, center):
    g = np.arange(-radius, radius + spacing / 2, spacing)
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    p = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    p = p[np.linalg.norm(p, axis=1) <= radius]
    return p + center


def test_sphere_coverage_by_a_sweep():
    r, h = 0.03, 0.001
    center = np.array([0.0, 0.0, 0.08])
    points = sphere_voxels(r, h, center)

    def everything(p_P):
        return np.ones(len(p_P), dtype=bool)

    # One plane through the centre with a 10 mm slab: the slab's share of the ball,
    # pi h (r^2 - h^2 / 12) / (4/3 pi r^3) with slab thickness h = 10 mm.
    acc = CoverageAccumulator(points, h**3, everything, elevation_width=0.010)
    v1 = acc.add_frame(RigidTransform())
    slab = 0.010
    expected = np.pi * slab * (r**2 - slab**2 / 12) / (4 / 3 * np.pi * r**3)
    assert v1 == pytest.approx(expected, rel=0.05)
    # Translating the plane along y_P through the whole ball covers all of it.
    poses = [RigidTransform([0, y, 0]) for y in np.arange(-0.035, 0.0351, 0.005)]
    V = volume_ratio(points, h**3, everything, 0.010, poses)
    assert V[-1] == 1.0
    assert np.all(np.diff(V) >= 0)

    # A fan that only sees x_P > 0 covers half of the ball.
    def half(p_P):
        return p_P[:, 0] > 0

    V_half = volume_ratio(points, h**3, half, 0.010, poses)
    assert V_half[-1] == pytest.approx(0.5, abs=0.02)
    assert acc.total_volume == pytest.approx(4 / 3 * np.pi * r**3, rel=0.02)
