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
    n0, n1, n2 = labels.shape
    fi, fj, fk = f[:, 0], f[:, 1], f[:, 2]
    valid = ((fi > -0.5) & (fi < n0 - 0.5) & (fj > -0.5) & (fj < n1 - 0.5)
             & (fk > -0.5) & (fk < n2 - 0.5))
    # Round half up (valid coordinates are > -0.5, so +0.5 then truncation is a floor).
    i = (fi + 0.5).astype(np.intp)
    j = (fj + 0.5).astype(np.intp)
    k = (fk + 0.5).astype(np.intp)
    flat = (i * n1 + j) * n2 + k
    np.clip(flat, 0, labels.size - 1, out=flat)
    out = np.take(labels.reshape(-1), flat)
    out[~valid] = outside
    return out


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
    A = X_VP.rotation().matrix() / volume.voxel_size
    b = X_VP.translation() / volume.voxel_size
    p = geometry.fan_p_P
    f_plane = p[:, 0:1] * A[:, 0] + p[:, 2:3] * A[:, 2] + b   # (N, 3) at y_P = 0
    labels = volume.labels
    if labels.dtype != np.uint8:
        labels = labels.astype(np.uint8)
    offsets = elevation_offsets(geometry.elevation_width, planes)
    outside = int(Label.OUTSIDE)
    if len(offsets) == 1:
        values = _lookup(labels, f_plane, outside)
    else:
        stack = np.stack([_lookup(labels, f_plane + y * A[:, 1], outside) for y in offsets])
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
