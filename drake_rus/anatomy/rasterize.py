"""Watertight mesh <-> voxel mask.

Mesh -> mask (:func:`rasterize_mesh`) by ray parity along the grid's k axis (vectorised
numpy): for every grid column (i, j) a ray along +k counts the surface crossings below each
voxel centre; an odd count means inside. Column positions carry a tiny irrational offset so no
ray passes exactly through a mesh edge or vertex (each crossing is counted once).

Mask -> mesh (:func:`mask_to_mesh`) by marching cubes on the smoothed, padded mask.
"""

import numpy as np
import trimesh
from pydrake.math import RigidTransform
from scipy import ndimage
from skimage import measure

__all__ = [
    "rasterize_mesh",
    "mesh_mask_on_aligned_grid",
    "mask_to_mesh",
    "grid_around",
    "check_grid_size",
    "MAX_GRID_VOXELS",
]

_JITTER = (1e-4 * np.pi, 1e-4 * np.e)
# Largest grid a mesh is rasterised on (voxels; three bytes each while it is built): 0.8 m
# cubed at 1 mm, more than any body section needs. A mesh in mm read as m asks for far more.
MAX_GRID_VOXELS = 512 * 1024**2


def rasterize_mesh(
    mesh, shape, X_PtV: RigidTransform, voxel_size: float, chunk: int = 4_000_000
) -> np.ndarray:
    """Boolean mask (shape) of the voxels of grid (X_PtV, voxel_size) inside ``mesh`` (Pt)."""
    nx, ny, nz = (int(s) for s in shape)
    check_grid_size(shape, voxel_size, "mesh")
    v = X_PtV.inverse().multiply(np.asarray(mesh.vertices, dtype=float).T).T / voxel_size
    tri = v[np.asarray(mesh.faces)]
    x, y, z = tri[:, :, 0], tri[:, :, 1], tri[:, :, 2]
    area2 = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (x[:, 2] - x[:, 0]) * (y[:, 1] - y[:, 0])
    dx, dy = _JITTER
    i_lo = np.maximum(np.ceil(x.min(axis=1) - dx), 0).astype(np.int64)
    i_hi = np.minimum(np.floor(x.max(axis=1) - dx), nx - 1).astype(np.int64)
    j_lo = np.maximum(np.ceil(y.min(axis=1) - dy), 0).astype(np.int64)
    j_hi = np.minimum(np.floor(y.max(axis=1) - dy), ny - 1).astype(np.int64)
    wi = np.maximum(i_hi - i_lo + 1, 0)
    wj = np.maximum(j_hi - j_lo + 1, 0)
    counts = wi * wj
    counts[np.abs(area2) < 1e-12] = 0
    toggles = np.zeros((nx, ny, nz + 1), dtype=np.uint8)
    tri_ids = np.nonzero(counts)[0]
    csum = np.cumsum(counts[tri_ids])
    start = 0
    while start < len(tri_ids):
        base = csum[start - 1] if start > 0 else 0
        stop = int(np.searchsorted(csum, base + chunk, side="right"))
        stop = max(stop, start + 1)
        ids = tri_ids[start:stop]
        n = counts[ids]
        t = np.repeat(ids, n)
        offs = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
        ii = i_lo[t] + offs // wj[t]
        jj = j_lo[t] + offs % wj[t]
        px, py = ii + dx, jj + dy
        x0, x1, x2 = x[t, 0], x[t, 1], x[t, 2]
        y0, y1, y2 = y[t, 0], y[t, 1], y[t, 2]
        a = area2[t]
        w1 = ((px - x0) * (y2 - y0) - (x2 - x0) * (py - y0)) / a
        w2 = ((x1 - x0) * (py - y0) - (px - x0) * (y1 - y0)) / a
        w0 = 1.0 - w1 - w2
        hit = (w0 >= 0) & (w1 >= 0) & (w2 >= 0)
        zz = w0 * z[t, 0] + w1 * z[t, 1] + w2 * z[t, 2]
        kk = np.clip(np.ceil(zz[hit]), 0, nz).astype(np.int64)
        np.add.at(toggles, (ii[hit], jj[hit], kk), 1)
        start = stop
    parity = np.cumsum(toggles, axis=2, dtype=np.uint8)[:, :, :nz] & 1
    return parity.astype(bool)


def check_grid_size(shape, voxel_size: float, what: str) -> None:
    """Refuses a voxel grid larger than :data:`MAX_GRID_VOXELS` (before allocating it),
    naming its extent: a mesh in other units than it is read in asks for such grids."""
    n = float(np.prod(np.asarray(shape, dtype=float)))
    if n > MAX_GRID_VOXELS:
        ext = " x ".join(f"{s * voxel_size:.3g}" for s in shape)
        raise ValueError(
            f"{what}: a voxel grid of {ext} m at {voxel_size * 1e3:g} mm voxels "
            f"({n:.3g} voxels, at most {MAX_GRID_VOXELS:.3g}): the mesh is far "
            "larger than a body; check its unit (mm read as m?)"
        )


def mesh_mask_on_aligned_grid(mesh, voxel_size: float, margin: float = 0.003):
    """Mask of ``mesh`` on a grid aligned with the mesh's frame, covering its bounds plus
    ``margin``: returns (mask, X_PtV)."""
    lo = mesh.bounds[0] - margin
    hi = mesh.bounds[1] + margin
    shape = np.ceil((hi - lo) / voxel_size).astype(int) + 1
    X_PtV = RigidTransform(lo)
    return rasterize_mesh(mesh, shape, X_PtV, voxel_size), X_PtV


def grid_around(bounds, voxel_size: float):
    """(shape, X_PtV) of the Pt-aligned grid of ``voxel_size`` covering ``bounds`` (lo, hi)."""
    lo, hi = bounds
    shape = np.ceil((hi - lo) / voxel_size).astype(int) + 1
    return shape, RigidTransform(lo)


def mask_to_mesh(
    mask: np.ndarray,
    X_PtV: RigidTransform,
    voxel_size: float,
    sigma_vox: float = 1.0,
    keep_point=None,
    what: str = "mask",
) -> trimesh.Trimesh:
    """Watertight surface of a binary mask (marching cubes on a smoothed, padded mask).
    ``keep_point`` (Pt): keep the connected component containing it (else the largest)."""
    if not mask.any():
        raise ValueError(f"{what}: empty mask")
    m = np.pad(mask.astype(np.float32), 2)
    if sigma_vox > 0:
        m = ndimage.gaussian_filter(m, sigma_vox)
    verts, faces, _, _ = measure.marching_cubes(m, 0.5)
    verts = (verts - 2.0) * voxel_size
    v_Pt = X_PtV.multiply(verts.T).T
    mesh = trimesh.Trimesh(v_Pt, faces, process=True)
    parts = mesh.split(only_watertight=False)
    if len(parts) > 1:
        if keep_point is not None:
            inside = [pt for pt in parts if pt.is_watertight and pt.contains([keep_point])[0]]
            parts = inside or parts
        mesh = max(parts, key=lambda q: abs(q.volume) if q.is_watertight else 0.0)
    faces = np.asarray(mesh.faces)
    fresh = trimesh.Trimesh(np.asarray(mesh.vertices), faces, process=False)
    if fresh.volume < 0:
        fresh = trimesh.Trimesh(np.asarray(mesh.vertices), faces[:, ::-1], process=False)
    if not fresh.is_watertight:
        raise ValueError(f"{what}: marching cubes did not give a watertight surface")
    return fresh
