"""3-D compounding of tracked ultrasound frames into a voxel volume (freehand 3-D ultrasound).

What the PLUS toolkit's volume reconstructor does, in plain numpy:

1. **Fan clipping**: only pixels inside the probe's fan (``ProbeGeometry.fan_mask``) are used;
   the black corners of a curvilinear image are not data.
2. **Nearest-pixel pasting** ("PNN"): every fan pixel centre is mapped with its frame's probe
   pose X_BP into the base frame B and its value is added to the nearest voxel of an
   axis-aligned grid in B. Compounding: ``mean`` (sum / count, the default), ``max`` or
   ``latest`` (the last frame that hit a voxel wins).
3. **Hole filling**: voxels no pixel hit, but with hit voxels around them, take the mean of
   the hit voxels in a (2k+1)^3 neighbourhood (k = 1, then 2, ...; PLUS's hole-filling
   kernels), up to ``fill_iterations`` passes; farther voxels stay unknown (NaN).

Masks compound to a kidney-probability volume; the kidney is the voxels at or above 0.5
(largest connected component, cavities filled), and its volume in mL is compared with the
true kidney volume. ``write_nrrd`` exports the volume (and mask) for 3D Slicer.

Units: SI in code (m). NRRD files are written in millimetres (the unit 3D Slicer assumes),
with the base frame's axes as the file's axes.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from pydrake.math import RigidTransform
from scipy import ndimage

from drake_rus.io_utils import atomic_path

MODES = ("mean", "max", "latest")


@dataclasses.dataclass(frozen=True)
class VoxelGrid:
    """Axis-aligned grid in B: voxel (i, j, k) centred at ``origin + spacing * (i, j, k)``."""

    origin: np.ndarray  # (3,) m
    spacing: float  # m
    shape: tuple

    def __post_init__(self):
        if not (np.isfinite(self.spacing) and self.spacing > 0):
            raise ValueError(
                f"VoxelGrid.spacing: expected a positive size in m, got {self.spacing}"
            )
        if len(self.shape) != 3 or min(self.shape) < 1:
            raise ValueError(f"VoxelGrid.shape: expected three positive sizes, got {self.shape}")
        if int(np.prod(self.shape)) > 200_000_000:
            raise ValueError(
                f"VoxelGrid.shape: {self.shape} is too many voxels; use a "
                "coarser spacing or a smaller box"
            )

    @property
    def voxel_volume(self) -> float:
        return self.spacing**3

    def centres(self, ijk: np.ndarray) -> np.ndarray:
        return np.asarray(self.origin) + self.spacing * np.asarray(ijk, float)


def grid_around(points_B: np.ndarray, spacing: float, margin: float = 0.01) -> VoxelGrid:
    """The grid covering ``points_B`` (N, 3) (m) plus ``margin`` on every side."""
    p = np.asarray(points_B, float).reshape(-1, 3)
    if len(p) == 0 or not np.all(np.isfinite(p)):
        raise ValueError("points_B: expected a non-empty finite (N, 3) array of points in m")
    lo = p.min(axis=0) - margin
    hi = p.max(axis=0) + margin
    shape = tuple(int(v) for v in np.ceil((hi - lo) / spacing).astype(int) + 1)
    return VoxelGrid(lo, float(spacing), shape)


@dataclasses.dataclass
class Reconstruction:
    """Compounded volume: ``values`` (float32, NaN where unknown), ``hits`` (pixels pasted
    per voxel before hole filling), ``filled`` (voxels set by hole filling)."""

    grid: VoxelGrid
    values: np.ndarray
    hits: np.ndarray
    filled: np.ndarray

    @property
    def known(self) -> np.ndarray:
        return np.isfinite(self.values)


def compound(
    images,
    poses,
    geometry,
    grid: VoxelGrid,
    *,
    mode: str = "mean",
    fill_iterations: int = 2,
    pixel_stride: int = 1,
) -> Reconstruction:
    """Pastes fan pixels of ``images`` (each rows x cols, any numeric/bool) taken at probe
    poses ``poses`` (RigidTransform X_BP) into ``grid`` (nearest voxel), then fills holes.

    ``pixel_stride`` > 1 uses every stride-th fan pixel (faster, for coarse grids).
    """
    if mode not in MODES:
        raise ValueError(f"mode: expected one of {', '.join(MODES)}, got {mode!r}")
    images, poses = list(images), list(poses)
    if len(images) != len(poses):
        raise ValueError(f"images and poses: got {len(images)} images but {len(poses)} poses")
    shape = grid.shape
    n = int(np.prod(shape))
    acc = np.zeros(n, np.float64)
    cnt = np.zeros(n, np.int32)
    fan_idx = geometry.fan_flat_index[:: max(1, int(pixel_stride))]
    p_P = geometry.fan_p_P[:: max(1, int(pixel_stride))]
    origin = np.asarray(grid.origin, float)
    dims = np.asarray(shape)
    batch_flat, batch_v = [], []
    for k, (image, X_BP) in enumerate(zip(images, poses)):
        image = np.asarray(image)
        if image.shape != geometry.image_shape:
            raise ValueError(
                f"images[{k}]: shape {image.shape} != the probe image shape {geometry.image_shape}"
            )
        if not isinstance(X_BP, RigidTransform):
            raise ValueError(f"poses[{k}]: expected a RigidTransform X_BP")
        values = image.reshape(-1)[fan_idx].astype(np.float64)
        p_B = p_P @ X_BP.rotation().matrix().T + X_BP.translation()
        ijk = np.rint((p_B - origin) / grid.spacing).astype(np.int64)
        ok = np.all((ijk >= 0) & (ijk < dims), axis=1)
        flat = np.ravel_multi_index(ijk[ok].T, shape)
        v = values[ok]
        if mode == "mean":  # batched: one bincount per ~1e6 pasted pixels
            batch_flat.append(flat)
            batch_v.append(v)
            if sum(len(b) for b in batch_flat) > 1_000_000 or k == len(images) - 1:
                f_all, v_all = np.concatenate(batch_flat), np.concatenate(batch_v)
                acc += np.bincount(f_all, weights=v_all, minlength=n)
                cnt += np.bincount(f_all, minlength=n).astype(np.int32)
                batch_flat, batch_v = [], []
            continue
        if mode == "max":
            first = cnt[flat] == 0
            acc[flat[first]] = -np.inf
            np.maximum.at(acc, flat, v)
        else:  # latest: within a frame the last pixel written wins
            acc[flat] = v
        np.add.at(cnt, flat, 1)
    hits = cnt.reshape(shape)
    with np.errstate(invalid="ignore", divide="ignore"):
        vol = (acc / cnt if mode == "mean" else acc.copy()).reshape(shape)
    vol[hits == 0] = np.nan
    vol, filled = fill_holes(vol, fill_iterations)
    return Reconstruction(grid, vol.astype(np.float32), hits, filled)


def fill_holes(volume: np.ndarray, iterations: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Unknown (NaN) voxels take the mean of the known voxels in a growing cubic kernel
    (3^3, then 5^3, ...), ``iterations`` passes; returns (volume, filled mask)."""
    vol = np.array(volume, dtype=np.float64)
    filled = np.zeros(vol.shape, bool)
    for it in range(int(iterations)):
        known = np.isfinite(vol)
        if known.all():
            break
        size = 3 + 2 * it
        s = ndimage.uniform_filter(np.where(known, vol, 0.0), size=size, mode="constant")
        c = ndimage.uniform_filter(known.astype(np.float64), size=size, mode="constant")
        new = ~known & (c > 1e-9)
        vol[new] = s[new] / c[new]
        filled |= new
    return vol, filled


def kidney_mask_from(rec: Reconstruction, threshold: float = 0.5) -> np.ndarray:
    """Kidney voxels of a compounded mask volume: values >= ``threshold``, largest
    connected component, cavities filled."""
    m = np.nan_to_num(rec.values, nan=0.0) >= threshold
    labels, n = ndimage.label(m)
    if n == 0:
        return m
    sizes = ndimage.sum(m, labels, index=np.arange(1, n + 1))
    m = labels == (1 + int(np.argmax(sizes)))
    return ndimage.binary_fill_holes(m)


def mask_volume_ml(mask: np.ndarray, grid: VoxelGrid) -> float:
    """Volume (mL) of a voxel mask."""
    return float(np.count_nonzero(mask)) * grid.voxel_volume * 1e6


def reconstruct_kidney(
    masks,
    poses,
    geometry,
    *,
    spacing: float = 0.001,
    margin: float = 0.01,
    fill_iterations: int = 2,
    points_B: np.ndarray | None = None,
) -> dict:
    """Compounds kidney masks into a volume and measures the kidney (mL).

    The grid covers the back-projected mask pixels (``points_B``, default: computed from the
    masks) plus ``margin``. Returns {reconstruction, mask, volume_ml, grid}.
    """
    masks, poses = list(masks), list(poses)
    if points_B is None:
        pts = []
        for mask, X in zip(masks, poses):
            v, u = np.nonzero(np.asarray(mask, bool))
            if len(u):
                pts.append(geometry.pixel_to_B(np.stack([u, v], 1).astype(float)[::7], X))
        if not pts:
            raise ValueError("masks: no kidney pixel in any frame; nothing to reconstruct")
        points_B = np.concatenate(pts)
    grid = grid_around(points_B, spacing, margin)
    rec = compound(
        [np.asarray(m, np.float32) for m in masks],
        poses,
        geometry,
        grid,
        mode="mean",
        fill_iterations=fill_iterations,
    )
    mask = kidney_mask_from(rec)
    return {
        "reconstruction": rec,
        "mask": mask,
        "volume_ml": mask_volume_ml(mask, grid),
        "grid": grid,
    }


def write_nrrd(path, volume: np.ndarray, grid: VoxelGrid, *, description: str = "") -> None:
    """Writes ``volume`` (on ``grid``) as NRRD for 3D Slicer, atomically.

    Axes are the robot base frame's x, y, z, written as the file's RAS space so Slicer shows
    the volume in its true size (mm) and orientation relative to the robot; NaN (unknown)
    is written as 0 for float volumes.
    """
    import nrrd

    data = np.asarray(volume)
    if data.shape != tuple(grid.shape):
        raise ValueError(f"volume: shape {data.shape} != grid shape {grid.shape}")
    if data.dtype == bool:
        data = data.astype(np.uint8)
    elif np.issubdtype(data.dtype, np.floating):
        data = np.nan_to_num(data.astype(np.float32), nan=0.0)
    header = {
        "space": "right-anterior-superior",
        "space directions": np.eye(3) * grid.spacing * 1e3,
        "space origin": np.asarray(grid.origin, float) * 1e3,
        "kinds": ["domain", "domain", "domain"],
        "encoding": "gzip",
    }
    if description:
        header["content"] = description.replace("\n", " ")
    with atomic_path(path) as tmp:
        nrrd.write(str(tmp), data, header)
