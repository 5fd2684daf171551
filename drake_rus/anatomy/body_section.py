"""The torso section around the kidney: the compliant contact body of the simulated station
for patients without an analytic body (imported ones), cut from their skin mesh.

Lives below :mod:`drake_rus.anatomy.patient` and :mod:`drake_rus.anatomy.importers` (both use
it), so the patient never imports the importers.
"""

import numpy as np
from scipy import ndimage

from drake_rus.anatomy.rasterize import grid_around, mask_to_mesh, rasterize_mesh

__all__ = ["crop_body_section"]


def crop_body_section(skin_mesh, center_Pt, half_length_m, voxel_size=0.005, detach_m=0.035):
    """Watertight body surface between y = center_y -/+ half_length (Pt): the skin is
    rasterised in that slab, the component containing ``center_Pt`` kept, and re-surfaced
    with marching cubes (flat caps at both ends)."""
    c = np.asarray(center_Pt, dtype=float)
    lo, hi = skin_mesh.bounds.copy()
    lo[1], hi[1] = c[1] - half_length_m, c[1] + half_length_m
    shape, X_PtV = grid_around((lo - voxel_size, hi + voxel_size), voxel_size)
    body = rasterize_mesh(skin_mesh, shape, X_PtV, voxel_size)
    y = X_PtV.translation()[1] + voxel_size * np.arange(shape[1])
    body[:, (y < lo[1]) | (y > hi[1]), :] = False
    # Keep, slice by slice, the 2-D component containing the kidney's (x, z): the torso
    # without the arms. A morphological opening (radius ``detach_m``) first cuts arms that
    # touch the torso over a narrow contact.
    ijk = np.round((c - X_PtV.translation()) / voxel_size).astype(int)
    ci, ck = int(np.clip(ijk[0], 0, shape[0] - 1)), int(np.clip(ijk[2], 0, shape[2] - 1))
    r = max(1, int(round(detach_m / voxel_size)))
    disk = np.add.outer(np.arange(-r, r + 1) ** 2, np.arange(-r, r + 1) ** 2) <= r * r
    for j in range(shape[1]):
        sl = body[:, j, :]
        if not sl.any():
            continue
        core = ndimage.binary_erosion(sl, disk)
        lab, n = ndimage.label(core if core.any() else sl)
        if n == 0:
            continue
        if lab[ci, ck] > 0:
            keep = lab == lab[ci, ck]
        else:
            sizes = np.bincount(lab.ravel())[1:]
            keep = lab == (1 + int(np.argmax(sizes)))
        if core.any():
            keep = ndimage.binary_dilation(keep, disk) & sl
        lab2, _ = ndimage.label(keep)
        if lab2[ci, ck] > 0:
            keep = lab2 == lab2[ci, ck]
        body[:, j, :] = keep
    return mask_to_mesh(
        body, X_PtV, voxel_size, sigma_vox=0.7, keep_point=c, what="skin mesh (torso section)"
    )
