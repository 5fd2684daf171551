"""Oblique slicing of a labelled volume on the probe's image plane (seed section III-A).

The probe pose defines the image plane; every fan pixel takes the label of the voxel nearest
to its centre (nearest neighbour, no interpolation of labels). Pixels outside the fan are 0.
Samples outside the volume get ``Label.OUTSIDE`` (air): a probe off the body sees nothing.
"""

from __future__ import annotations

import numpy as np
from pydrake.math import RigidTransform

from drake_rus.anatomy.labels import Label, LabelVolume
from drake_rus.imaging.probe import ProbeGeometry, check_pose

def elevation_offsets(width: float, planes: int) -> np.ndarray:
    """y_P offsets (m) of ``planes`` parallel planes spread evenly across ``width`` (centred)."""
    if planes <= 1:
        return np.zeros(1)
    return np.linspace(-width / 2, width / 2, planes)


def sample_labels(volume: LabelVolume, p_V: np.ndarray, outside: int = int(Label.OUTSIDE)
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


def _lookup_padded(padded: np.ndarray, fi: np.ndarray, fj: np.ndarray, fk: np.ndarray,
                   shifted: bool = False) -> np.ndarray:
    """Nearest labels at voxel coordinates (fi, fj, fk) of the unpadded grid.

    Index in the padded grid = round(f) + 1 = trunc(f + 1.5) for f > -1.5; any f below
    -0.5 truncates to 0 or less and clips onto the air border, and any f beyond the grid
    clips onto the far border: no validity masks needed. ``shifted``: the caller already
    added the 1.5.
    """
    m0, m1, m2 = padded.shape
    itype = np.int32 if padded.size < 2 ** 31 else np.intp
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


def slice_volume(geometry: ProbeGeometry, volume: LabelVolume, X_BV: RigidTransform,
                 X_BP: RigidTransform, planes: int = 1, combine: str = "majority"
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
    px, pz = geometry.fan_x_z32
    padded = padded_labels(volume.labels)
    offsets = elevation_offsets(geometry.elevation_width, planes)

    def plane(y: float) -> np.ndarray:
        c = b + np.float32(y) * A[:, 1] + np.float32(1.5)   # + 1.5: see _lookup_padded
        return _lookup_padded(padded, px * A[0, 0] + (pz * A[0, 2] + c[0]),
                              px * A[1, 0] + (pz * A[1, 2] + c[1]),
                              px * A[2, 0] + (pz * A[2, 2] + c[2]), shifted=True)

    if len(offsets) == 1:
        values = plane(0.0)
    else:
        stack = np.stack([plane(y) for y in offsets])
        if combine == "max":
            values = stack.max(axis=0)
        else:
            n = stack.shape[1]
            counts = np.zeros((int(stack.max()) + 1, n), dtype=np.float32)
            cols = np.arange(n)
            for row in stack:
                counts[row, cols] += 1.0   # (row[c], c) pairs are unique within a plane
            counts[stack[len(offsets) // 2], cols] += 0.5   # tie-break: central plane
            values = counts.argmax(axis=0).astype(np.uint8)
    image = np.zeros(geometry.image_shape, dtype=np.uint8)
    image.reshape(-1)[geometry.fan_flat_index] = values
    return image
