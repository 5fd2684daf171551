"""The trunk of an imported body: the arms cut off the skin surface before the posture roll.

Real bodies come with their arms: the HuBMAP Visible Human female (``../shared/anatomy``)
holds them abducted, about 60 mm beside the trunk at the kidney's level, and CT bodies often
have them along the sides. Rolled onto the left side (left lateral decubitus) the right arm
then lies over the right flank, where the probe must go; supine, an arm beside the trunk
becomes part of the contact body's convex hull. The arms are therefore removed from the
skin surface for both postures (the trunk, neck, head and legs stay).

Method (voxels, axial slices; nothing is tuned to one body):

1. The skin surface is rasterised on a grid (default 4 mm) in the body frame Bd; a label
   map's body mask is used as it is.
2. Seed slice: the axial slice through the target kidney's centroid. Its 2-D components
   are split at narrow contacts: the slice is eroded by a disk of radius ``detach_m``
   (default 30 mm, thinner than a trunk, thicker than the skin bridge where an arm touches
   the side), the eroded part containing the kidney is the trunk core, and every pixel of
   the slice goes to the nearest core (trunk or other). Components that do not contain the
   kidney are "other" (arms, hands).
3. Propagation slice by slice, upwards and downwards from the seed: a 2-D component of the
   next slice that overlaps only trunk pixels of the previous slice is trunk, one that
   overlaps only other pixels (or nothing: an arm's or a finger's end) is other, and one
   that overlaps both (an arm meeting the trunk at the axilla, a hand resting on the hip)
   is split between them, each pixel going to the nearest labelled pixel of the previous
   slice. The split line therefore continues the gap between arm and trunk of the slices
   below the contact (the shoulder is cut roughly along the axilla's sagittal plane). Both
   legs meet the trunk at the groin and stay, as do neck and head.
4. The trunk voxels (3-D component of the kidney, holes filled) are re-surfaced with
   marching cubes. A body in which nothing is removed keeps its original surface.

Limits: the arms must be separate from the trunk, or touch it only over a contact
narrower than about ``2 * detach_m``, in the slice through the kidney; an arm pressed along
the flank over its whole width at that level stays (it cannot be told from the trunk in
that slice). Arms raised above the head (a common CT position) join the trunk only above
the shoulders and are kept: they lie far from the kidneys. The re-surfaced skin is smooth
to about one voxel (4 mm from meshes; a label map's own voxels).

What the posture roll ignores: a patient turned onto the side is a rigid rotation of the
supine body here. Organs shift under gravity when the posture changes; MRI of healthy
volunteers shows the right kidney moving cranially between supine and prone (Smith 2023,
facts file) and arm position leaving the kidneys in place. For the left lateral decubitus
the shift of the kidney (a few centimetres downwards, towards the bed, and medially) is
unsourced here. The arms' removal itself does not move any organ.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy import ndimage

from drake_rus.anatomy.rasterize import grid_around, mask_to_mesh, rasterize_mesh

__all__ = ["trunk_mask", "remove_arms", "TRUNK", "OTHER"]

TRUNK, OTHER = 1, 2


def _nearest_label(labels: np.ndarray, where: np.ndarray) -> np.ndarray:
    """For each pixel of ``where``: the label (> 0) of the nearest labelled pixel."""
    _, idx = ndimage.distance_transform_edt(labels == 0, return_indices=True)
    out = np.zeros_like(labels)
    out[where] = labels[idx[0][where], idx[1][where]]
    return out


def _seed_slice(sl: np.ndarray, seed: tuple, r: float) -> np.ndarray:
    """Trunk/other labels of the slice through the kidney (narrow contacts split)."""
    comp, n = ndimage.label(sl)
    if n == 0:
        raise ValueError("trunk: the body has no voxel in the kidney's axial slice")
    seed_comp = comp[seed]
    if seed_comp == 0:  # kidney centroid just outside: nearest component
        _, idx = ndimage.distance_transform_edt(comp == 0, return_indices=True)
        seed_comp = comp[idx[0][seed], idx[1][seed]]
    out = np.where(sl, OTHER, 0).astype(np.uint8)
    own = comp == seed_comp
    core = ndimage.distance_transform_edt(np.pad(own, 1))[1:-1, 1:-1] > r  # disk erosion
    core_lab, n_core = ndimage.label(core)
    if n_core <= 1:
        out[own] = TRUNK
        return out
    # The core containing (or nearest to) the seed is the trunk; pixels go to the nearest core.
    if core_lab[seed] > 0:
        trunk_core = core_lab[seed]
    else:
        _, idx = ndimage.distance_transform_edt(core_lab == 0, return_indices=True)
        trunk_core = core_lab[idx[0][seed], idx[1][seed]]
    near = _nearest_label(core_lab, own)
    out[own & (near == trunk_core)] = TRUNK
    # A pixel that went to the trunk core but is cut off from it by an arm's share stays other.
    t_lab, _ = ndimage.label(out == TRUNK)
    keep = (
        t_lab[seed]
        if t_lab[seed] > 0
        else (np.bincount(t_lab[t_lab > 0]).argmax() if (t_lab > 0).any() else 0)
    )
    out[(out == TRUNK) & (t_lab != keep)] = OTHER
    return out


def _propagate(sl: np.ndarray, prev: np.ndarray) -> np.ndarray:
    """Trunk/other labels of a slice from those of the neighbouring slice ``prev``."""
    out = np.zeros(sl.shape, dtype=np.uint8)
    comp, n = ndimage.label(sl)
    if n == 0:
        return out
    t_hits = np.bincount(comp[prev == TRUNK], minlength=n + 1)
    o_hits = np.bincount(comp[prev == OTHER], minlength=n + 1)
    near = None
    for c in range(1, n + 1):
        m = comp == c
        if t_hits[c] and o_hits[c]:
            if near is None:
                near = _nearest_label(prev, sl)
            out[m] = near[m]
        elif t_hits[c]:
            out[m] = TRUNK
        else:
            out[m] = OTHER
    return out


def trunk_mask(
    body: np.ndarray, axis: int, seed_index, voxel_size: float, detach_m: float = 0.030
) -> np.ndarray:
    """The trunk (without the arms) of a boolean body mask; slices normal to index ``axis``
    (the body's superior axis), ``seed_index`` (i, j, k) a voxel of the trunk at the target
    kidney's level (its centroid). See the module docstring for the method."""
    body = np.asarray(body, dtype=bool)
    b = np.moveaxis(body, axis, 0)
    seed = np.clip(
        np.round(np.asarray(seed_index, dtype=float)).astype(int), 0, np.array(body.shape) - 1
    )
    s0 = int(seed[axis])
    seed2 = tuple(int(v) for a, v in enumerate(seed) if a != axis)
    lab = np.zeros(b.shape, dtype=np.uint8)
    r = max(1.0, detach_m / voxel_size)
    lab[s0] = _seed_slice(b[s0], seed2, r)
    for step in (1, -1):
        s = s0 + step
        while 0 <= s < b.shape[0]:
            lab[s] = _propagate(b[s], lab[s - step])
            s += step
    trunk = lab == TRUNK
    comp, n = ndimage.label(trunk)
    if n > 1:
        keep = comp[(s0, *seed2)] or int(np.bincount(comp[comp > 0]).argmax())
        trunk = comp == keep
    trunk = ndimage.binary_fill_holes(trunk)
    return np.moveaxis(trunk, 0, axis)


def remove_arms(
    skin_Bd: trimesh.Trimesh,
    kidney_centroid_Bd,
    *,
    voxel_size: float = 0.004,
    detach_m: float = 0.030,
    min_removed_m3: float = 20e-6,
):
    """The skin surface (Bd, m) without the arms, and a report dict. The surface is
    re-surfaced from ``voxel_size`` voxels when more than ``min_removed_m3`` of the body was
    removed; otherwise the input mesh is returned unchanged (a body without arms)."""
    lo, hi = skin_Bd.bounds
    shape, X_BdV = grid_around((lo - 2 * voxel_size, hi + 2 * voxel_size), voxel_size)
    body = rasterize_mesh(skin_Bd, shape, X_BdV, voxel_size)
    seed = (np.asarray(kidney_centroid_Bd, dtype=float) - X_BdV.translation()) / voxel_size
    trunk = trunk_mask(body, 1, seed, voxel_size, detach_m)
    removed = float((body & ~trunk).sum()) * voxel_size**3
    report = {
        "method": "axial-slice trunk tracking (anatomy/trunk.py)",
        "voxel_size": voxel_size,
        "detach_m": detach_m,
        "removed_volume_l": round(removed * 1e3, 3),
    }
    if removed <= min_removed_m3:
        report["resurfaced"] = False
        return skin_Bd, report
    mesh = mask_to_mesh(
        trunk,
        X_BdV,
        voxel_size,
        sigma_vox=0.7,
        keep_point=np.asarray(kidney_centroid_Bd, dtype=float),
        what="skin mesh (trunk without the arms)",
    )
    report["resurfaced"] = True
    return mesh, report
