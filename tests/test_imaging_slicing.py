"""Oblique slicing against analytic cross-sections of spheres and boxes."""

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix

from drake_rus.anatomy.labels import Label, LabelVolume
from drake_rus.imaging.phantoms import box_volume, sphere_volume
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.imaging.slicing import slice_volume

H = 0.001  # voxel size (m)
HALF_DIAG = np.sqrt(3) / 2 * H  # farthest a point can be from its nearest voxel centre


def fan_points_B(geometry, X_BP):
    v, u = np.nonzero(geometry.fan_mask)
    return v, u, geometry.pixel_to_B(np.c_[u, v], X_BP)


def probe_looking_at(target_B, depth, rpy):
    """A probe pose whose central line hits ``target_B`` at ``depth`` (oblique)."""
    R = RotationMatrix(RollPitchYaw(rpy))
    return RigidTransform(R, np.asarray(target_B) - depth * R.matrix()[:, 2])


@pytest.mark.parametrize(
    "rpy,offset", [((0.3, -0.2, 0.9), 0.0), ((2.5, 0.4, -1.2), 0.012), ((np.pi, 0.0, 0.0), -0.017)]
)
def test_sphere_cross_section_is_the_analytic_disc(geometry, rpy, offset):
    c_V, r = np.array([0.045, 0.05, 0.04]), 0.02
    vol = sphere_volume(shape=(90, 100, 80), voxel_size=H, center=c_V, radius=r)
    X_BV = RigidTransform(RollPitchYaw(0.1, -0.3, 0.7), [0.4, -0.2, 0.1])
    c_B = X_BV.multiply(c_V)
    X_BP = probe_looking_at(c_B, 0.07, rpy)
    # Shift the plane along y_P: the disc's radius is sqrt(r^2 - offset^2).
    X_BP = RigidTransform(
        X_BP.rotation(), X_BP.translation() + offset * X_BP.rotation().matrix()[:, 1]
    )
    img = slice_volume(geometry, vol, X_BV, X_BP)
    v, u, p_B = fan_points_B(geometry, X_BP)
    dist = np.linalg.norm(p_B - c_B, axis=1)
    inside = img[v, u] == Label.KIDNEY_CORTEX
    clear = np.abs(dist - r) > HALF_DIAG
    # Exact away from the surface (within half a voxel diagonal anything may happen).
    assert np.array_equal(inside[clear], (dist < r)[clear])
    # Area of the disc within 3%.
    area = inside.sum() * geometry.pixel_area
    assert area == pytest.approx(np.pi * (r**2 - offset**2), rel=0.03)
    # Nothing outside the fan.
    assert not img[~geometry.fan_mask].any()


def test_box_cross_section_is_the_analytic_rectangle(geometry):
    # Faces on voxel-cell boundaries (half-voxel positions): the labelled region is then
    # exactly the box, and nearest-voxel slicing must reproduce it exactly.
    lo, hi = np.array([0.0205, 0.0105, 0.0305]), np.array([0.0495, 0.0695, 0.0445])
    vol = box_volume(shape=(80, 80, 80), voxel_size=H, lo=lo, hi=hi, label=Label.BONE)
    X_BV = RigidTransform([0.3, 0.1, -0.05])
    # Probe above the box pointing down (z_P = -z_B), array along y_B, tilted 20 deg.
    R = RotationMatrix(RollPitchYaw(np.pi + 0.35, 0.0, np.pi / 2))
    X_BP = RigidTransform(R, X_BV.multiply([0.035, 0.04, 0.075]))
    img = slice_volume(geometry, vol, X_BV, X_BP)
    v, u, p_B = fan_points_B(geometry, X_BP)
    p_V = X_BV.inverse().multiply(p_B.T).T
    d_out = np.max(np.maximum(lo - p_V, p_V - hi), axis=1)
    inside = img[v, u] == Label.BONE
    clear = np.abs(d_out) > 1e-6
    assert inside.sum() > 500
    assert np.array_equal(inside[clear], (d_out < 0)[clear])


def test_outside_the_volume_is_air(geometry):
    vol = sphere_volume(shape=(20, 20, 20))
    X_BP = RigidTransform([5.0, 5.0, 5.0])
    img = slice_volume(geometry, vol, RigidTransform(), X_BP)
    assert np.all(img == Label.OUTSIDE)


def test_elevational_planes(geometry):
    # A 2 mm slab of gas parallel to the image plane, 4 mm off it (along y_P = y_B).
    labels = np.full((100, 40, 80), Label.SOFT_TISSUE, np.uint8)
    labels[:, 23:25, :] = Label.GAS  # y in [23, 24] mm; the plane is at y = 19 mm
    vol = LabelVolume(labels=labels, voxel_size=H)
    # x_P = x_B, y_P = -y_B, z_P = -z_B (looking down), the plane at y = 19 mm.
    X_BP = RigidTransform(RotationMatrix(np.diag([1.0, -1.0, -1.0])), [0.05, 0.019, 0.075])
    assert np.allclose(X_BP.rotation().matrix()[:, 2], [0, 0, -1])
    fan = geometry.fan_mask
    one = slice_volume(geometry, vol, RigidTransform(), X_BP, planes=1)
    assert not np.any(one[fan] == Label.GAS)
    g = ProbeGeometry(geometry.radius, geometry.half_angle, 0.07, 64, 64, elevation_width=0.010)
    fan = g.fan_mask
    mx = slice_volume(g, vol, RigidTransform(), X_BP, planes=5, combine="max")
    assert np.all(mx[fan] == Label.GAS)
    maj = slice_volume(g, vol, RigidTransform(), X_BP, planes=5, combine="majority")
    assert np.all(maj[fan] == Label.SOFT_TISSUE)


def test_non_finite_pose_raises(geometry):
    vol = sphere_volume(shape=(10, 10, 10))
    with pytest.raises(ValueError, match="X_BP"):
        slice_volume(geometry, vol, RigidTransform(), RigidTransform([np.inf, 0, 0]))
