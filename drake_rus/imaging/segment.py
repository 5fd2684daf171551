"""Kidney segmentation of ultrasound frames, and what the controller reads off a mask.

Backends (``ImagingConfig.segmenter``):

- ``oracle``: kidney labels of the label image (ground truth);
- ``classical``: despeckle, dark-region threshold, hole filling (the bright sinus inside the
  darker parenchyma), morphology, then the plausible component that best overlaps the
  previous frame's mask (temporal prior) or else the largest one;
- ``onnx``: a learned model (:mod:`drake_rus.imaging.onnx_backend`).

Mask read-outs (seed II-E): visible flag (area above ``min_kidney_area``), horizontal mask
centroid ``c_msk`` in [0, 1] (eq. 17) and the boundary pixels that are back-projected.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from drake_rus.anatomy.labels import is_kidney
from drake_rus.imaging.probe import ProbeGeometry

_CROSS = ndimage.generate_binary_structure(2, 1)


def segment_oracle(label_image: np.ndarray) -> np.ndarray:
    """Ground-truth kidney mask (bool, rows x cols) of a label image."""
    return is_kidney(np.asarray(label_image))


@dataclass(frozen=True)
class MaskReadout:
    visible: bool
    centroid: float          # c_msk in [0, 1] across the image width; 0.5 when not visible
    area: float              # m^2
    boundary: np.ndarray     # (N, 2) boundary pixels (u, v)


def mask_centroid(mask: np.ndarray) -> float:
    """Horizontal centroid of a mask in [0, 1] (pixel centres at (u + 0.5) / width); 0.5 for
    an empty mask (no centring correction, eq. 17)."""
    mask = np.asarray(mask, bool)
    cols = mask.sum(axis=0)
    n = cols.sum()
    if n == 0:
        return 0.5
    return float(np.dot(cols, np.arange(mask.shape[1]) + 0.5) / (n * mask.shape[1]))


def boundary_pixels(mask: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) as (u, v) of the mask's inner boundary (4-connected)."""
    mask = np.asarray(mask, bool)
    # Erosion by the 4-neighbour cross with a zero border, by array shifts (fast).
    inner = np.zeros_like(mask)
    inner[1:-1, 1:-1] = (mask[1:-1, 1:-1] & mask[:-2, 1:-1] & mask[2:, 1:-1]
                         & mask[1:-1, :-2] & mask[1:-1, 2:])
    edge = mask & ~inner
    v, u = np.nonzero(edge)
    return np.stack([u, v], axis=1).astype(float)


def read_mask(mask: np.ndarray, geometry: ProbeGeometry, min_area: float) -> MaskReadout:
    """Visible flag, c_msk, area (m^2) and boundary pixels of a kidney mask."""
    mask = np.asarray(mask, bool)
    area = float(mask.sum()) * geometry.pixel_area
    visible = area >= min_area and area > 0
    if not visible:
        return MaskReadout(False, 0.5, area, np.zeros((0, 2)))
    return MaskReadout(True, mask_centroid(mask), area, boundary_pixels(mask))


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two masks (1.0 when both are empty)."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    union = np.count_nonzero(a | b)
    return 1.0 if union == 0 else np.count_nonzero(a & b) / union


# --- classical ------------------------------------------------------------------------------
def _block_mean(image: np.ndarray, f: int) -> np.ndarray:
    h, w = image.shape
    h2, w2 = h // f, w // f
    return image[:h2 * f, :w2 * f].reshape(h2, f, w2, f).mean(axis=(1, 3), dtype=np.float32)


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


def segment_classical(us_image: np.ndarray, geometry: ProbeGeometry,
                      prev_mask: np.ndarray | None = None, min_area: float = 1.0e-4,
                      strong: float = 0.9, weak: float = 1.0, grow_m: float = 0.008,
                      reject_edge: bool = False, floor: float = 0.45) -> np.ndarray:
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
        raise ValueError(f"segment_classical: image shape {img.shape} != probe image shape "
                         f"{geometry.image_shape}")
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
                continue          # mostly outside the fan: an edge artefact
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
    out[:full.shape[0], :full.shape[1]] = full
    return out & geometry.fan_mask
