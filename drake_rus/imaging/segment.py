"""Kidney segmentation of ultrasound frames, and what the controller reads off a mask.

Backends (``ImagingConfig.segmenter``):

- ``oracle``: kidney labels of the label image (ground truth);
- ``classical``: despeckle, dark-region threshold, hole filling (the bright sinus inside the
  darker parenchyma), morphology, then the plausible component that best overlaps the
  previous frame's mask (temporal prior) or else the largest one;
- ``onnx``: a learned model (:mod:`drake_rus.imaging.onnx_backend`), whose candidate regions
  are followed from frame to frame (:func:`tracked_component`).

Mask read-outs (seed II-E): visible flag (area above ``min_kidney_area``), horizontal mask
centroid ``c_msk`` in [0, 1] (eq. 17) and the boundary pixels that are back-projected.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import ConvexHull, QhullError

from drake_rus.anatomy.labels import is_kidney
from drake_rus.imaging.probe import ProbeGeometry

_CROSS = ndimage.generate_binary_structure(2, 1)


def segment_oracle(label_image: np.ndarray) -> np.ndarray:
    """Ground-truth kidney mask (bool, rows x cols) of a label image."""
    return is_kidney(np.asarray(label_image))


@dataclass(frozen=True)
class MaskReadout:
    visible: bool
    centroid: float  # c_msk in [0, 1] across the image width; 0.5 when not visible
    area: float  # m^2
    boundary: np.ndarray  # (N, 2) boundary pixels (u, v)


def mask_centroid(mask: np.ndarray) -> float:
    """Horizontal centroid of a mask in [0, 1] (pixel centres at (u + 0.5) / width); 0.5 for
    an empty mask (no centring correction, eq. 17)."""
    mask = np.asarray(mask, bool)
    return _centroid_in_box(mask, mask_box(mask))


def _centroid_in_box(mask: np.ndarray, box: tuple[slice, slice] | None) -> float:
    """``mask_centroid`` from the columns of the mask's box only. Exact: every term
    count x (u + 0.5) and every partial sum is a multiple of 0.5 far below 2^53, so the sum
    does not depend on which zero columns it includes or in which order it adds."""
    if box is None:
        return 0.5
    sub = mask[box]
    # Pixels per column (uint8 rows summed in int32: vectorised across the columns).
    cols = np.add.reduce(sub.view(np.uint8), axis=0, dtype=np.int32)
    n = int(cols.sum())
    u = np.arange(box[1].start, box[1].start + len(cols)) + 0.5
    return float(np.dot(cols, u) / (n * mask.shape[1]))


def mask_box(mask: np.ndarray, margin: int = 0) -> tuple[slice, slice] | None:
    """(rows, cols) slices of a 2-D bool mask's bounding box grown by ``margin`` pixels
    (clipped to the image); None for an empty mask."""
    if mask.dtype == bool and mask.flags.c_contiguous and mask.size and mask.shape[1] % 8 == 0:
        # The first and last rows from the first and last 8-pixel words holding a pixel
        # (bool argmax stops at the first True).
        words = mask.reshape(-1).view(np.uint64) != 0
        first = int(words.argmax())
        if not words[first]:
            return None
        per_row = mask.shape[1] // 8
        r0 = first // per_row
        r1 = (len(words) - 1 - int(words[::-1].argmax())) // per_row + 1
    else:
        rows = np.flatnonzero(mask.any(axis=1))
        if rows.size == 0:
            return None
        r0, r1 = int(rows[0]), int(rows[-1]) + 1
    cols = mask[r0:r1].any(axis=0).nonzero()[0]
    return _grow((slice(r0, r1), slice(int(cols[0]), int(cols[-1]) + 1)), margin)


def boundary_pixels(mask: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) as (u, v) of the mask's inner boundary (4-connected), in row-major
    order. Pixels on the image's border are boundary."""
    mask = np.asarray(mask, bool)
    return _boundary_in_box(mask, mask_box(mask))


def _grow(box: tuple[slice, slice], margin: int) -> tuple[slice, slice]:
    return (
        slice(max(box[0].start - margin, 0), box[0].stop + margin),
        slice(max(box[1].start - margin, 0), box[1].stop + margin),
    )


def _boundary_in_box(mask: np.ndarray, box: tuple[slice, slice] | None) -> np.ndarray:
    """``boundary_pixels`` of a mask whose pixels all lie in ``box`` (``mask_box``)."""
    if box is None:
        return np.zeros((0, 2))
    # Worked on the mask's box grown by one pixel: a box side inside the image then lies
    # on background, a side on the image's border is that border (same result).
    box = _grow(box, 1)
    sub = mask[box]
    # Erosion by the 4-neighbour cross, by array shifts (fast); the image's border pixels
    # are never inner. edge = sub & ~inner.
    inner = sub[1:-1, 1:-1] & sub[:-2, 1:-1]
    inner &= sub[2:, 1:-1]
    inner &= sub[1:-1, :-2]
    inner &= sub[1:-1, 2:]
    edge = sub.copy()
    edge[1:-1, 1:-1] &= ~inner
    # Row-major (v, u) of the edge pixels from their flat indices in the box.
    idx = edge.reshape(-1).nonzero()[0]
    v, u = np.divmod(idx, sub.shape[1])
    out = np.empty((idx.size, 2))
    out[:, 0] = u
    out[:, 0] += box[1].start
    out[:, 1] = v
    out[:, 1] += box[0].start
    return out


def read_mask(mask: np.ndarray, geometry: ProbeGeometry, min_area: float) -> MaskReadout:
    """Visible flag, c_msk, area (m^2) and boundary pixels of a kidney mask."""
    mask = np.asarray(mask, bool)
    area = float(np.count_nonzero(mask)) * geometry.pixel_area
    visible = area >= min_area and area > 0
    if not visible:
        return MaskReadout(False, 0.5, area, np.zeros((0, 2)))
    box = mask_box(mask)
    return MaskReadout(True, _centroid_in_box(mask, box), area, _boundary_in_box(mask, box))


# Grey (0-255) above which a pixel holds an echo: below it, the noise floor of an 8-bit
# B-mode image (segment_classical's ``lit``).
_ECHO_GREY = 8.0


def acoustic_shadow(
    us_image: np.ndarray,
    geometry: ProbeGeometry,
    floor: float,
    *,
    line_step: float = math.radians(1.0),
    window: float = 0.004,
) -> np.ndarray:
    """Bool (rows, cols): the fan's pixels in acoustic shadow, where no echo returns along
    the pixel's scan line from its depth down.

    A strong reflector (bone, bowel gas) sends back or absorbs almost all the energy: its
    scan lines are dark beyond it to the fan's bottom, and what an image shows there, a
    segmenter's mask included, is not evidence of tissue. The fan's pixels are binned into
    scan lines ``line_step`` rad wide and depth steps of one pixel row; each line's grey is
    averaged over ``window`` m of depth (speckle); a pixel is shadowed when that average
    stays below ``floor`` x the median grey of the lit fan (pixels above the noise floor) at
    every depth from the pixel's down. A hypoechoic structure (a vessel, the medulla, the
    kidney) is no shadow: the tissue below it echoes again. ``floor`` <= 0: nothing is
    shadowed; a frame without a lit pixel (no contact) is all shadow."""
    img = np.asarray(us_image)
    if img.shape != geometry.image_shape:
        raise ValueError(
            f"acoustic_shadow: image shape {img.shape} != probe image shape {geometry.image_shape}"
        )
    out = np.zeros(geometry.image_shape, bool)
    if not floor > 0.0:
        return out
    idx = geometry.fan_flat_index
    grey = img.reshape(-1)[idx].astype(np.float64)
    lit = grey > _ECHO_GREY
    if not lit.any():
        out.reshape(-1)[idx] = True
        return out
    ref = float(np.median(grey[lit]))
    flat, n_lines, n_depth, counts = geometry.scan_line_bins(line_step)
    sums = np.bincount(flat, weights=grey, minlength=n_lines * n_depth).reshape(n_lines, -1)
    size = max(int(round(window / geometry.dz)), 1)
    s = ndimage.uniform_filter1d(sums, size, axis=1, mode="constant")
    c = ndimage.uniform_filter1d(counts.astype(np.float64), size, axis=1, mode="constant")
    mean = np.where(c > 1e-9, s / np.maximum(c, 1e-9), 0.0)
    # The largest echo from each depth down the line (a running maximum from the bottom).
    below = np.maximum.accumulate(mean[:, ::-1], axis=1)[:, ::-1]
    out.reshape(-1)[idx] = (below < floor * ref).reshape(-1)[flat]
    return out


def echo_supported_boundary(
    mask: np.ndarray,
    boundary: np.ndarray,
    shadow: np.ndarray,
    geometry: ProbeGeometry,
    max_shadowed: float,
    margin: float = 0.002,
) -> np.ndarray:
    """The boundary pixels (N, 2) (u, v) of a kidney mask that the image's echoes support.

    None when more than ``max_shadowed`` of the mask's area lies in acoustic shadow
    (:func:`acoustic_shadow`): the region is the segmenter's guess where the image holds
    nothing (a learned segmenter marks the kidney on under a rib's shadow, as it was trained
    to; measured on seed 5,000,002 in left lateral decubitus: 48 frames whose masks lay in
    the shadow put a spike 25 mm deep below the kidney into the exploration cloud). Else
    the boundary pixels farther than ``margin`` m (the shadow edge's blur) from the shadow:
    a mask's outline under a shadow is drawn, not seen."""
    b = np.asarray(boundary, float).reshape(-1, 2)
    shadow = np.asarray(shadow, bool)
    if len(b) == 0 or not shadow.any():
        return b
    mask = np.asarray(mask, bool)
    area = int(np.count_nonzero(mask))
    if area and np.count_nonzero(mask & shadow) > max_shadowed * area:
        return np.zeros((0, 2))
    r = int(math.ceil(margin / min(geometry.dx, geometry.dz)))
    near = ndimage.binary_dilation(shadow, _CROSS, iterations=r) if r > 0 else shadow
    u = np.clip(b[:, 0].astype(int), 0, geometry.width_px - 1)
    v = np.clip(b[:, 1].astype(int), 0, geometry.height_px - 1)
    return b[~near[v, u]]


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two masks (1.0 when both are empty)."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    union = np.count_nonzero(a | b)
    return 1.0 if union == 0 else np.count_nonzero(a & b) / union


def edge_distance(mask: np.ndarray, sampling=None) -> np.ndarray:
    """Distance from each pixel centre of a 2-D bool ``mask`` to the nearest pixel centre
    on the other side of its edge (inside: to the nearest outside pixel; outside: to the
    nearest inside one), in the units of ``sampling`` (per-axis pixel sizes; None: pixels).
    The mask's boundary band, for a segmentation loss or an error split."""
    m = np.asarray(mask, bool)
    return np.where(
        m,
        ndimage.distance_transform_edt(m, sampling=sampling),
        ndimage.distance_transform_edt(~m, sampling=sampling),
    )


# --- classical ------------------------------------------------------------------------------
def _block_mean(image: np.ndarray, f: int) -> np.ndarray:
    h, w = image.shape
    h2, w2 = h // f, w // f
    return image[: h2 * f, : w2 * f].reshape(h2, f, w2, f).mean(axis=(1, 3), dtype=np.float32)


_FAN_CACHE: dict = {}


def _half_res_fan(geometry: ProbeGeometry) -> tuple[np.ndarray, np.ndarray]:
    """Half-resolution fan masks, cached per geometry: (interior, edge band, fan as 0/1,
    5x5 box mean of the fan: the normaliser of the box filter)."""
    hit = _FAN_CACHE.get(geometry)
    if hit is None:
        cover = _block_mean(geometry.fan_mask.astype(np.float32), 2)
        fan_any = (cover > 0.99).astype(np.float32)
        weight = np.maximum(ndimage.uniform_filter(fan_any, size=5), 1e-3)
        fan = ndimage.binary_erosion(cover > 0.99, iterations=2)
        edge = fan & ~ndimage.binary_erosion(fan, iterations=2)
        hit = _FAN_CACHE[geometry] = (fan, edge, fan_any, weight)
    return hit


def segment_classical(
    us_image: np.ndarray,
    geometry: ProbeGeometry,
    prev_mask: np.ndarray | None = None,
    min_area: float = 1.0e-4,
    strong: float = 0.9,
    weak: float = 1.0,
    grow_m: float = 0.008,
    reject_edge: bool = False,
    floor: float = 0.45,
) -> np.ndarray:
    """Kidney mask (bool, rows x cols) of an emulated/real B-mode image, no learning.

    1. 2x2 block mean then a 5x5 box mean: despeckle at half resolution;
    2. parenchyma = darker than ``strong`` x the median grey of the lit fan; pixels below
       ``floor`` x the median (shadows, anechoic vessels) and the first 10 mm under the face
       are excluded (tuned on seed:3 and synthetic phantoms, never on test patients);
    3. opening, hole filling (the bright sinus and fat inside the dark ring join the kidney);
    4. components: drop those outside the plausible area (``min_area`` to 60 cm^2) and, with
       ``reject_edge``, those touching the fan's sides or bottom (where shadows run); keep
       the one overlapping ``prev_mask`` most, else the most compact large one;
    5. hysteresis: grow the component up to ``grow_m`` into pixels darker than ``weak`` x
       the median (the cortex is only slightly darker than its surroundings);
    6. back to full resolution, closed and hole-filled.
    """
    img = np.asarray(us_image)
    if img.shape != geometry.image_shape:
        raise ValueError(
            f"segment_classical: image shape {img.shape} != probe image shape "
            f"{geometry.image_shape}"
        )
    f = 2
    small = _block_mean(img.astype(np.float32), f)
    fan, edge, fan_any, fan_weight = _half_res_fan(geometry)
    # Box mean over fan pixels only (normalised), so the black outside does not leak in.
    small = ndimage.uniform_filter(small * fan_any, size=5) / fan_weight
    lit = fan & (small > 8)
    if np.count_nonzero(lit) < 50:
        return np.zeros(geometry.image_shape, bool)
    ref = float(np.median(small[lit]))
    not_shadow = small > floor * ref
    dark = fan & (small < strong * ref) & not_shadow
    # Skip the first ~10 mm under the face (skin, fat and muscle layers).
    top_rows = int(np.ceil((0.010 - geometry.z_min) / (geometry.dz * f)))
    dark[:top_rows] = False
    dark = ndimage.binary_opening(dark, _CROSS, iterations=2)
    filled = ndimage.binary_fill_holes(dark)
    labels, n = ndimage.label(filled)
    if n == 0:
        return np.zeros(geometry.image_shape, bool)
    index = np.arange(1, n + 1)
    areas = ndimage.sum_labels(np.ones_like(labels), labels, index) * geometry.pixel_area * f * f
    touches = ndimage.maximum(edge, labels, index) > 0
    ok = (areas >= max(min_area, 1e-6)) & (areas <= 60e-4)
    if reject_edge:
        ok &= ~touches
    if not ok.any():
        return np.zeros(geometry.image_shape, bool)
    best = None
    if prev_mask is not None and np.any(prev_mask):
        prev_small = _block_mean(np.asarray(prev_mask, np.float32), f) > 0.5
        overlap = ndimage.sum_labels(prev_small, labels, index)
        overlap = np.where(ok, overlap, 0)
        if overlap.max() > 0:
            best = int(np.argmax(overlap)) + 1
    if best is None:
        # Score: sqrt(area) x compactness (area / bounding-box area) x the contrast with a
        # ring around the component (the kidney sits in bright perirenal fat; shadows and
        # the fan's edges have dark or no surroundings).
        slices = ndimage.find_objects(labels)
        score = np.zeros(n)
        for i, sl in enumerate(slices):
            if not ok[i] or sl is None:
                continue
            r0, r1 = max(sl[0].start - 4, 0), sl[0].stop + 4
            c0, c1 = max(sl[1].start - 4, 0), sl[1].stop + 4
            comp_i = labels[r0:r1, c0:c1] == i + 1
            ring = ndimage.binary_dilation(comp_i, iterations=3) & ~comp_i
            inside_mean = small[r0:r1, c0:c1][comp_i].mean()
            ring_vals = small[r0:r1, c0:c1][ring & fan[r0:r1, c0:c1]]
            if len(ring_vals) < 0.5 * ring.sum():
                continue  # mostly outside the fan: an edge artefact
            contrast = max(ring_vals.mean() - inside_mean, 0.0) / ref
            box = (sl[0].stop - sl[0].start) * (sl[1].stop - sl[1].start)
            score[i] = np.sqrt(areas[i]) * (comp_i.sum() / box) * contrast
        if score.max() <= 0:
            return np.zeros(geometry.image_shape, bool)
        best = int(np.argmax(score)) + 1
    comp = labels == best
    grow_px = int(round(grow_m / (f * 0.5 * (geometry.dx + geometry.dz))))
    if grow_px > 0:
        weak_mask = fan & (small < weak * ref) & not_shadow
        comp = ndimage.binary_dilation(comp, _CROSS, iterations=grow_px, mask=weak_mask | comp)
    comp = ndimage.binary_closing(comp, _CROSS, iterations=2, border_value=0)
    comp = ndimage.binary_fill_holes(comp)
    full = np.repeat(np.repeat(comp, f, axis=0), f, axis=1)
    out = np.zeros(geometry.image_shape, bool)
    out[: full.shape[0], : full.shape[1]] = full
    return out & geometry.fan_mask


# [(mask array, geometry, reach, near)]: the last two computed (a frame grows its last
# kidney mask and, after localization, the template's predicted section).
_NEAR_CACHE: list = []


def near_region(prior_mask: np.ndarray, geometry: ProbeGeometry, reach: float) -> np.ndarray:
    """Bool (rows, cols): the pixels within ``reach`` (m) of a mask (Euclidean, in physical
    units, over the mask's bounding box grown by ``reach``). The last two results are kept
    for the same mask objects: a frame's segmentation and its track update grow the same
    prior (and the template's predicted section is grown in between)."""
    for arr, geo, r, near in _NEAR_CACHE:
        if arr is prior_mask and geo is geometry and r == reach:
            return near
    prior = np.asarray(prior_mask, bool)
    near = np.zeros(prior.shape, bool)
    bbox = mask_box(prior)
    if bbox is not None:
        dr, dc = int(np.ceil(reach / geometry.dz)) + 1, int(np.ceil(reach / geometry.dx)) + 1
        box = (
            slice(max(bbox[0].start - dr, 0), bbox[0].stop + dr),
            slice(max(bbox[1].start - dc, 0), bbox[1].stop + dc),
        )
        near[box] = (
            ndimage.distance_transform_edt(~prior[box], sampling=(geometry.dz, geometry.dx))
            <= reach
        )
    near.flags.writeable = False
    # The mask itself is held, so its id cannot be reused by another array while cached;
    # a caller that mutates it in place must not expect a fresh result (masks are treated
    # as immutable here, as KidneyTrack's are).
    _NEAR_CACHE[:] = [(prior_mask, geometry, reach, near)] + _NEAR_CACHE[:1]
    return near


def predicted_section(
    points_B: np.ndarray, X_BP, geometry: ProbeGeometry, slab: float
) -> np.ndarray:
    """Bool (rows, cols): where the registered kidney crosses the image of a probe at X_BP.

    points_B (N, 3): the registered template's surface in B (m: the template's points in K
    mapped by the localizer's X_BK). The points within ``slab`` (m) of the image plane
    (|y_P|, half the elevational beam width) are projected onto it; the section is their
    convex hull (a kidney's sections are near convex; a hull also closes the section where
    the slab holds few points), within the fan. Empty when fewer than 3 points lie in the
    slab or they span no area."""
    out = np.zeros(geometry.image_shape, bool)
    p = np.asarray(points_B, float).reshape(-1, 3)
    if len(p) < 3:
        return out
    p_P = (p - X_BP.translation()) @ X_BP.rotation().matrix()
    near = np.abs(p_P[:, 1]) <= slab
    if np.count_nonzero(near) < 3:
        return out
    uv = geometry.P_to_pixel(p_P[near])
    lo = np.maximum(np.floor(uv.min(axis=0)).astype(int), 0)
    size = [geometry.width_px, geometry.height_px]
    hi = np.minimum(np.ceil(uv.max(axis=0)).astype(int) + 1, size)
    if np.any(hi <= lo):
        return out
    try:
        hull = ConvexHull(uv)
    except QhullError:
        return out  # the points lie on a line: no area
    v, u = np.mgrid[lo[1] : hi[1], lo[0] : hi[0]]
    inside = np.ones(u.shape, bool)
    for a, b, c in hull.equations:  # a u + b v + c <= 0 inside
        inside &= a * u + b * v + c <= 1e-9
    out[lo[1] : hi[1], lo[0] : hi[0]] = inside
    return out & geometry.fan_mask


def tracked_component(
    components: list[np.ndarray],
    prior_mask: np.ndarray | None,
    prior_age: float,
    geometry: ProbeGeometry,
    *,
    max_gap: float,
    reach: float,
    min_overlap: float = 0.5,
    section: np.ndarray | None = None,
    section_reach: float = 0.015,
) -> int | None:
    """Which candidate region of a frame is the kidney (index into ``components``, None: none).

    components: bool masks (rows, cols) of the frame's candidate regions; prior_mask: the
    kidney mask last seen, ``prior_age`` s ago (None: never seen). While the kidney was seen
    within ``max_gap`` s, the kidney is the region overlapping the last mask grown by
    ``reach`` (m) most, among the regions that continue it: at least ``min_overlap`` of the
    region lies in the grown mask, or the region covers at least ``min_overlap`` of the last
    mask itself (a kidney re-entering the image where it left, at a pivot leg's end, grows
    past the reach of its last small section). A region elsewhere is not taken for it:
    between frames 50 ms apart a kidney section moves a few millimetres, it does not jump
    across the image (a hypoechoic muscle band or bowel loop that the model also marks is
    left alone, also when its edge touches the grown mask). Else (first sight, or the kidney
    lost for longer than ``max_gap``): the largest region.

    section: after localization, where the registered template puts the kidney in this
    image (:func:`predicted_section`; None or empty: no prediction, the rules above). The
    regions that agree with it (at least ``min_overlap`` of the region within the section
    grown by ``section_reach`` m, the registration's error) are preferred: a region that
    both continues the last mask and agrees; else the agreeing region overlapping the
    section most, also when the last mask is older than ``max_gap`` or was a region that
    does not agree (the kidney found again after a pivot leg or any loss); else a region
    that continues the last mask (the kidney beyond the template's end: the template is
    one length, 108 mm, kidneys 88-140 mm); else none (a region elsewhere, while the
    template puts the kidney in view, is not the kidney).
    """
    if not components:
        return None
    agree = _agreeing(components, section, geometry, section_reach, min_overlap)
    followed = prior_mask is not None and prior_age <= max_gap
    prior = np.asarray(prior_mask, bool) if followed else None
    prior_area = 0 if prior is None else int(np.count_nonzero(prior))
    if agree is not None:
        cont = (
            _continuing(components, prior_mask, prior, prior_area, geometry, reach, min_overlap)
            if prior_area
            else {}
        )
        both = [k for k in cont if k in agree]
        if both:
            return max(both, key=lambda k: cont[k])
        if agree:
            return max(agree, key=lambda k: agree[k])
        if cont:
            return max(cont, key=lambda k: cont[k])
        return None
    if prior_area:
        areas = [int(np.count_nonzero(c)) for c in components]
        cover = [int(np.count_nonzero(c & prior)) for c in components]
        if (
            len(components) == 1
            and cover[0]
            and (cover[0] >= min_overlap * areas[0] or cover[0] >= min_overlap * prior_area)
        ):
            # It continues the last mask on its own (the mask lies within its own reach):
            # no distance transform needed.
            return 0
        near = near_region(prior_mask, geometry, reach)
        overlap = [int(np.count_nonzero(c & near)) for c in components]
        ok = [
            k
            for k in range(len(components))
            if overlap[k] > 0
            and (overlap[k] >= min_overlap * areas[k] or cover[k] >= min_overlap * prior_area)
        ]
        return max(ok, key=lambda k: overlap[k]) if ok else None
    return int(np.argmax([int(np.count_nonzero(c)) for c in components]))


def _continuing(components, prior_mask, prior, prior_area, geometry, reach, min_overlap) -> dict:
    """{index: overlap with the last mask grown by ``reach``} of the regions that continue
    the last mask (the rule of :func:`tracked_component`)."""
    areas = [int(np.count_nonzero(c)) for c in components]
    cover = [int(np.count_nonzero(c & prior)) for c in components]
    near = near_region(prior_mask, geometry, reach)
    overlap = [int(np.count_nonzero(c & near)) for c in components]
    return {
        k: overlap[k]
        for k in range(len(components))
        if overlap[k] > 0
        and (overlap[k] >= min_overlap * areas[k] or cover[k] >= min_overlap * prior_area)
    }


def _agreeing(components, section, geometry, reach, min_overlap) -> dict | None:
    """{index: pixels in the section} of the regions with at least ``min_overlap`` of
    their area within ``section`` grown by ``reach`` (m); None without a section."""
    if section is None:
        return None
    section = np.asarray(section, bool)
    if not section.any():
        return None
    near = near_region(section, geometry, reach)
    out = {}
    for k, c in enumerate(components):
        area = int(np.count_nonzero(c))
        if area and np.count_nonzero(c & near) >= min_overlap * area:
            out[k] = int(np.count_nonzero(c & section))
    return out


@dataclass(frozen=True)
class KidneyTrack:
    """The kidney followed across frames: its last visible mask (rows, cols), the time (s)
    of that frame, and since when (s) it has been followed without a jump (a region that
    did not continue the previous one starts a new track)."""

    mask: np.ndarray | None = None
    time: float = -math.inf
    since: float = math.inf

    def __copy__(self):
        return self

    def __deepcopy__(self, memo):
        return self  # immutable


def track_prior(track: KidneyTrack, t: float, confirm: float) -> tuple[np.ndarray | None, float]:
    """(prior mask, its age in s) to follow at time t, or (None, inf) while the track is not
    established: followed for less than ``confirm`` s (the first sights while the probe lands
    may be a region that is not the kidney; following it would hide the kidney)."""
    if track.mask is None or track.time - track.since < confirm - 1e-9:
        return None, math.inf
    return track.mask, t - track.time


def track_settings(imaging) -> dict:
    """The tracker's settings in an imaging config (``ImagingConfig``), as the keyword
    arguments of :func:`track_update`: ``max_gap`` (s, ``track_gap``), ``reach`` (m,
    ``track_reach``) and ``min_overlap`` (``track_min_overlap``). The scan's Segmenter, the
    kinematic studies' imager and the benchmarks read them here, so they follow the kidney
    alike."""
    return dict(
        max_gap=float(imaging.track_gap),
        reach=float(imaging.track_reach),
        min_overlap=float(imaging.track_min_overlap),
    )


def track_update(
    track: KidneyTrack,
    mask: np.ndarray,
    visible: bool,
    t: float,
    geometry: ProbeGeometry,
    *,
    max_gap: float,
    reach: float,
    min_overlap: float = 0.5,
) -> KidneyTrack:
    """The track after a frame at time t whose kidney mask is ``mask``: unchanged when the
    kidney is not visible; else this mask, continuing the track when it continues the last
    mask within ``max_gap`` s (:func:`tracked_component`, ``reach``, ``min_overlap``), a new
    track otherwise."""
    if not visible:
        return track
    # A mask after more than max_gap s without the kidney starts a new track, whatever it
    # overlaps: tracked_component takes the largest region then, without asking whether it
    # continues the last mask, so the new sight must be confirmed (track_prior) again.
    continues = (
        track.mask is not None
        and t - track.time <= max_gap
        and tracked_component(
            [np.asarray(mask, bool)],
            track.mask,
            t - track.time,
            geometry,
            max_gap=max_gap,
            reach=reach,
            min_overlap=min_overlap,
        )
        == 0
    )
    return KidneyTrack(np.asarray(mask, bool), float(t), track.since if continues else float(t))
