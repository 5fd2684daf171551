"""Oblique slicing of a labelled volume on the probe's image plane (seed section III-A).

The probe pose defines the image plane; every fan pixel takes the label of the voxel nearest
to its centre (nearest neighbour, no interpolation of labels). Pixels outside the fan are 0.
Samples outside the volume get ``Label.OUTSIDE`` (air): a probe off the body sees nothing.
"""

from __future__ import annotations

import numpy as np
from pydrake.math import RigidTransform

from drake_rus.anatomy.labels import Label, LabelVolume
from drake_rus.imaging import kernels
from drake_rus.imaging.probe import ProbeGeometry, check_pose


def elevation_offsets(width: float, planes: int) -> np.ndarray:
    """y_P offsets (m) of ``planes`` parallel planes spread evenly across ``width`` (centred)."""
    if planes <= 1:
        return np.zeros(1)
    return np.linspace(-width / 2, width / 2, planes)


def sample_labels(
    volume: LabelVolume, p_V: np.ndarray, outside: int = int(Label.OUTSIDE)
) -> np.ndarray:
    """Nearest-voxel labels at points ``p_V`` (N, 3) given in the grid frame V (m)."""
    f = np.asarray(p_V, dtype=float) / volume.voxel_size
    return _lookup(volume.labels, f, outside)


def _lookup(labels: np.ndarray, f: np.ndarray, outside: int) -> np.ndarray:
    """Labels at continuous voxel coordinates ``f`` (N, 3) (voxel centres at integers)."""
    padded = padded_labels(labels, outside)
    return _lookup_padded(padded, f[:, 0], f[:, 1], f[:, 2])


_PAD_CACHE: dict = {}


def padded_labels(labels: np.ndarray, outside: int = int(Label.OUTSIDE)) -> np.ndarray:
    """``labels`` (uint8) with a one-voxel border of ``outside``; cached per array, so that
    out-of-volume samples are found by clipping indices instead of masking."""
    key = (id(labels), labels.shape, outside)
    hit = _PAD_CACHE.get(key)
    if hit is not None and hit[0] is labels:
        return hit[1]
    padded = np.pad(np.asarray(labels, dtype=np.uint8), 1, constant_values=outside)
    if len(_PAD_CACHE) >= 4:
        _PAD_CACHE.pop(next(iter(_PAD_CACHE)))
    _PAD_CACHE[key] = (labels, padded)
    return padded


def _lookup_padded(
    padded: np.ndarray, fi: np.ndarray, fj: np.ndarray, fk: np.ndarray, shifted: bool = False
) -> np.ndarray:
    """Nearest labels at voxel coordinates (fi, fj, fk) of the unpadded grid.

    Index in the padded grid = round(f) + 1 = trunc(f + 1.5) for f > -1.5; any f below
    -0.5 truncates to 0 or less and clips onto the air border, and any f beyond the grid
    clips onto the far border: no validity masks needed. ``shifted``: the caller already
    added the 1.5.
    """
    m0, m1, m2 = padded.shape
    itype = np.int32 if padded.size < 2**31 else np.intp
    if shifted:
        i, j, k = fi.astype(itype), fj.astype(itype), fk.astype(itype)
    else:
        i = (fi + 1.5).astype(itype)
        j = (fj + 1.5).astype(itype)
        k = (fk + 1.5).astype(itype)
    np.clip(i, 0, m0 - 1, out=i)
    np.clip(j, 0, m1 - 1, out=j)
    np.clip(k, 0, m2 - 1, out=k)
    i *= m1 * m2
    j *= m2
    i += j
    i += k
    return np.take(padded.reshape(-1), i)


def slice_volume(
    geometry: ProbeGeometry,
    volume: LabelVolume,
    X_BV: RigidTransform,
    X_BP: RigidTransform,
    planes: int = 1,
    combine: str = "majority",
) -> np.ndarray:
    """Label image (rows, cols) uint8 of ``volume`` cut by the probe's image plane.

    ``X_BV``: pose of the volume's grid frame V in the base B; ``X_BP``: probe tip pose in B.
    ``planes`` > 1 samples parallel planes across the elevational beam width and combines them
    per pixel: "majority" (most frequent label; ties go to the central plane's label) or "max".
    """
    check_pose(X_BP, "X_BP")
    check_pose(X_BV, "X_BV")
    if combine not in ("majority", "max"):
        raise ValueError(f"slice_volume: combine must be 'majority' or 'max', got {combine!r}")
    X_VP = X_BV.InvertAndCompose(X_BP)
    # Voxel coordinates f = (R_VP p_P + p_VP) / h, split so that y_P offsets are cheap.
    # float32 is ample: its rounding error is about 1e-5 voxel at index 500.
    A = (X_VP.rotation().matrix() / volume.voxel_size).astype(np.float32)
    b = (X_VP.translation() / volume.voxel_size).astype(np.float32)
    px = geometry.fan_x_z32[0]
    z_rows, per_row = geometry.fan_rows
    padded = padded_labels(volume.labels)
    flat = padded.reshape(-1)
    shape = np.array(padded.shape, np.int64)
    offsets = elevation_offsets(geometry.elevation_width, planes)
    image = np.zeros(geometry.image_shape, dtype=np.uint8)
    index = np.empty(px.size, np.int32 if padded.size < 2**31 else np.int64)

    def plane(y: float, out: np.ndarray, dest: np.ndarray) -> None:
        """The labels of plane y_P = y into ``out[dest]`` (fan pixels in row-major order):
        :func:`kernels.slice_plane`, per fan pixel ``f = x A[a, 0] + (z A[a, 2] + c[a])``,
        the bracket once per row (float32)."""
        c = b + np.float32(y) * A[:, 1] + np.float32(1.5)  # + 1.5: see _lookup_padded
        kernels.slice_plane(px, z_rows, per_row, A, c, shape, flat, dest, out, index)

    if len(offsets) == 1:
        plane(0.0, image.reshape(-1), geometry.fan_flat_index32)
        return image
    n = px.size
    stack = np.empty((len(offsets), n), np.uint8)
    every = np.arange(n, dtype=np.int32)
    for row, y in zip(stack, offsets):
        plane(y, row, every)
    if combine == "max":
        values = stack.max(axis=0)
    else:
        counts = np.zeros((int(stack.max()) + 1, n), dtype=np.float32)
        for row in stack:
            counts[row, every] += 1.0  # (row[c], c) pairs are unique within a plane
        counts[stack[len(offsets) // 2], every] += 0.5  # tie-break: central plane
        values = counts.argmax(axis=0).astype(np.uint8)
    image[geometry.fan_mask] = values  # the fan pixels in row-major order
    return image


def warm_up(
    geometry: ProbeGeometry, volume: LabelVolume, planes: int = 1, combine: str = "majority"
) -> None:
    """Pad ``volume`` and compile (or load) the slicing kernel for ``geometry``'s argument
    types: call at construction, not inside a simulation step."""
    slice_volume(geometry, volume, RigidTransform(), RigidTransform(), planes, combine)
