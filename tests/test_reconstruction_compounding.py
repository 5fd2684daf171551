"""3-D compounding: pasting, fan clipping, hole filling, volume of an analytic sphere, NRRD."""

import numpy as np
import pytest
from pydrake.math import RigidTransform, RotationMatrix

from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.metrics.reconstruction import (
    VoxelGrid,
    compound,
    fill_holes,
    grid_around,
    kidney_mask_from,
    mask_volume_ml,
    reconstruct_kidney,
    write_nrrd,
)

G = ProbeGeometry.from_config(ImagingConfig(image_height_px=128, image_width_px=128))
CENTRE = np.array([0.0, 0.0, -0.08])  # sphere centre in B, 80 mm under the probe face
RADIUS = 0.025


def sphere_masks(poses):
    """Exact masks of the sphere in each frame's image plane."""
    v, u = np.mgrid[0 : G.height_px, 0 : G.width_px]
    uv = np.stack([u.ravel(), v.ravel()], 1).astype(float)
    out = []
    for X in poses:
        p = G.pixel_to_B(uv, X)
        out.append(
            (np.linalg.norm(p - CENTRE, axis=1) <= RADIUS).reshape(G.image_shape) & G.fan_mask
        )
    return out


def line_poses(step=0.0005):
    """Probe pointing down (z_P = -z_B) at the origin, sliding along y across the sphere."""
    R = RotationMatrix(np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]]))
    ys = np.arange(-0.035, 0.035 + 1e-9, step)
    return [RigidTransform(R, [0.0, y, 0.0]) for y in ys]


def test_sphere_volume_from_a_dense_sweep():
    poses = line_poses()
    result = reconstruct_kidney(sphere_masks(poses), poses, G, spacing=0.001)
    true_ml = 4 / 3 * np.pi * RADIUS**3 * 1e6
    assert result["volume_ml"] == pytest.approx(true_ml, rel=0.03)


def test_sparse_sweep_needs_hole_filling():
    poses = line_poses(step=0.0025)  # 2.5 mm between frames, 1 mm voxels
    masks = sphere_masks(poses)
    grid = grid_around(np.array([CENTRE - RADIUS, CENTRE + RADIUS]), 0.001)
    raw = compound(masks, poses, G, grid, fill_iterations=0)
    filled = compound(masks, poses, G, grid, fill_iterations=2)
    true_ml = 4 / 3 * np.pi * RADIUS**3 * 1e6
    v_raw = mask_volume_ml(np.nan_to_num(raw.values) >= 0.5, grid)
    v_fill = mask_volume_ml(kidney_mask_from(filled), grid)
    assert v_raw < 0.6 * true_ml  # gaps between the slices
    assert v_fill == pytest.approx(true_ml, rel=0.05)
    assert filled.filled.any() and not raw.filled.any()
    assert np.all(filled.hits[filled.filled] == 0)  # only unhit voxels are filled


def test_fan_clipping_pastes_only_fan_pixels():
    grid = VoxelGrid(np.array([-0.1, -0.01, -0.2]), 0.002, (100, 10, 110))
    X = line_poses()[len(line_poses()) // 2]
    ones = np.ones(G.image_shape)
    rec = compound([ones], [X], G, grid, fill_iterations=0)
    ijk = np.argwhere(rec.hits > 0)
    p_B = grid.centres(ijk)
    p_P = X.inverse().multiply(p_B.T).T
    p_P[:, 1] = 0.0
    # Every hit voxel centre is within a voxel of the fan; the corners are never written.
    inside = G.in_fan(p_P)
    assert inside.mean() > 0.9
    theta, d = G.P_to_polar(p_P)
    assert np.all(np.abs(theta) <= G.half_angle + 0.002 / 0.05)
    assert np.all(d <= G.depth + 0.002)


def test_compounding_modes():
    grid = VoxelGrid(np.array([-0.02, -0.001, -0.002]), 0.001, (41, 3, 10))
    g = ProbeGeometry(radius=0.05, half_angle=0.3, depth=0.004, height_px=8, width_px=8)
    X = RigidTransform()
    a, b = np.full(g.image_shape, 1.0), np.full(g.image_shape, 3.0)
    for mode, expect in (("mean", 2.0), ("max", 3.0), ("latest", 3.0)):
        rec = compound([a, b], [X, X], g, grid, mode=mode, fill_iterations=0)
        vals = rec.values[rec.hits > 0]
        assert len(vals) and np.allclose(vals, expect)
    with pytest.raises(ValueError, match="mode"):
        compound([a], [X], g, grid, mode="median")
    with pytest.raises(ValueError, match="poses"):
        compound([a, b], [X], g, grid)


def test_fill_holes_grows_kernels():
    v = np.full((7, 7, 7), np.nan)
    v[3, 3, 3] = 2.0
    out, filled = fill_holes(v, 1)
    assert np.isclose(out[2, 3, 3], 2.0) and np.isnan(out[0, 0, 0])
    out, filled = fill_holes(v, 2)
    # The second pass (5^3 kernel) grows from the first pass's 3^3 block: 1 + 2 voxels.
    assert np.isclose(out[0, 0, 0], 2.0) and filled.sum() == 7**3 - 1


def test_nrrd_export_roundtrip(tmp_path):
    import nrrd

    grid = VoxelGrid(np.array([0.4, -0.1, 0.05]), 0.002, (4, 5, 6))
    vol = np.random.default_rng(0).random(grid.shape).astype(np.float32)
    vol[0, 0, 0] = np.nan
    path = tmp_path / "kidney.nrrd"
    write_nrrd(path, vol, grid, description="test")
    data, header = nrrd.read(str(path))
    assert data.shape == grid.shape and data[0, 0, 0] == 0.0
    np.testing.assert_allclose(data[1:, 1:, 1:], vol[1:, 1:, 1:])
    np.testing.assert_allclose(header["space directions"], np.eye(3) * 2.0)
    np.testing.assert_allclose(header["space origin"], [400.0, -100.0, 50.0])
    write_nrrd(tmp_path / "mask.nrrd", vol > 0.5, grid)
    assert nrrd.read(str(tmp_path / "mask.nrrd"))[0].dtype == np.uint8
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp files
    with pytest.raises(ValueError, match="shape"):
        write_nrrd(tmp_path / "bad.nrrd", vol[:2], grid)
