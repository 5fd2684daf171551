"""ONNX Runtime kidney segmenter: any model whose input/output shapes the scenario names.

Contract (``ImagingConfig``): one float32 input of shape ``onnx_input_shape`` (N, C, H, W)
(dimensions the model leaves symbolic are accepted); the grey image (0-255) is resized to
H x W (block mean when the sizes divide, else nearest), scaled to [0, 1], normalised with
``(x - onnx_input_mean) / onnx_input_std`` and repeated over C channels. The first output is
(N, K, h, w) or (N, h, w): ``logits`` (a sigmoid is applied; with K > 1 a softmax over K),
``probability`` or ``labels`` (integer class per pixel, or K scores to argmax); channel
(or class index) ``onnx_kidney_channel`` is the kidney. The kidney probability is resized back to
the image (bilinear), refined at the image's resolution by a guided filter with the frame as
guide (``onnx_guided_radius``, ``onnx_guided_eps``; :func:`guided_filter`) and thresholded.

Physical pixel size (model card): when the JSON card next to the model (same name, ``.json``)
declares ``pixel_size_mm`` (p) and ``canvas_px`` ([H, W]), the model sees every frame at that
fixed physical pixel size, whatever the imaging depth: the image (whose mm per pixel grows
with ``ImagingConfig.depth``) is area-averaged onto an H x W canvas of p mm pixels in the
probe frame P (columns centred on the beam axis x_P = 0, the top edge at z_P =
``canvas_top_mm``, default the image's top), padded with 0 where the image is shallower or
narrower (cropped where it is larger); the kidney probability is mapped back onto the image
grid (bilinear). The model input is then (N, C, H, W) with N, C from ``onnx_input_shape`` and
H, W from the card (the scenario's H, W are not used). A card without these fields, or no
card, keeps the resize above. :class:`PhysicalCanvas` does the mapping.
"""

from __future__ import annotations

import functools
import json
import logging
import math
import os
import platform
from pathlib import Path

import numpy as np
import scipy.sparse as sps
from scipy import ndimage

from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.imaging.segment import tracked_component
from drake_rus.paths import REPO_ROOT

_log = logging.getLogger("drake_rus.imaging")
# Models whose int8 saturation note was logged in this process (once each).
_SATURATION_NOTED: set = set()
# The same, for the processes this one starts afterwards (the perception workers, a study's
# workers inherit the environment): they do not repeat the note. Paths, os.pathsep-joined.
SATURATION_NOTED_ENV = "DRAKE_RUS_INT8_NOTED"


@functools.lru_cache(maxsize=1)
def cpu_has_vnni() -> bool | None:
    """Whether this x86 CPU has VNNI (AVX512-VNNI or AVX-VNNI); None when not x86 or unknown
    (/proc/cpuinfo unreadable)."""
    if platform.machine().lower() not in ("x86_64", "amd64", "i686", "x86"):
        return None
    try:
        flags = Path("/proc/cpuinfo").read_text()
    except OSError:
        return None
    return "avx512_vnni" in flags or "avx_vnni" in flags


def int8_saturation_note(card: dict, model_name: str, has_vnni: bool | None) -> str:
    """One line for a user whose x86 CPU lacks VNNI and whose model is U8S8 (uint8
    activations x int8 weights, without reduce_range, per its card's ``quantization``):
    ONNX Runtime's AVX2 kernels may saturate those products, and the model then reads
    lower than on a CPU with VNNI. '' otherwise (has_vnni True or None, or another model).
    Measured on an AMD EPYC with AVX2 and no VNNI (docs/results/segmenter.md, 2026-11-28,
    night): the shipped int8 model's held-out IoU 0.001-0.005 under the fp32 model's per
    depth preset and 0.011 on the VH female supine; the fp32 model costs about 1.3 ms more
    per frame there."""
    q = card.get("quantization") if isinstance(card, dict) else None
    if has_vnni is not False or not isinstance(q, dict):
        return ""
    if q.get("activation_type") != "QUInt8" or q.get("weight_type") != "QInt8":
        return ""
    if q.get("reduce_range"):
        return ""
    source = q.get("source_model") or "its fp32 source model"
    return (
        f"imaging.onnx_model: {model_name} is int8 (uint8 x int8) and this x86 CPU has no "
        f"VNNI, so its products may saturate: on such a CPU it reads up to 0.011 IoU under "
        f"{source}, the fp32 model beside it (docs/imaging.md); set imaging.onnx_model to "
        f"that model for the fp32 figures (about 1.3 ms more per frame)"
    )


def _note_once(key: str, note: str) -> None:
    """Log ``note`` unless this process, or the one that started it, already did for
    ``key`` (see SATURATION_NOTED_ENV)."""
    inherited = os.environ.get(SATURATION_NOTED_ENV, "").split(os.pathsep)
    if key in _SATURATION_NOTED or key in inherited:
        return
    _SATURATION_NOTED.add(key)
    os.environ[SATURATION_NOTED_ENV] = os.pathsep.join([k for k in inherited if k] + [key])
    _log.warning(note)


def resolve_model_path(path: str) -> Path:
    p = Path(path).expanduser()
    return p if p.is_absolute() else REPO_ROOT / p


def resize_to(image: np.ndarray, h: int, w: int) -> np.ndarray:
    """float32 image resized to (h, w): block mean when the size divides, else nearest."""
    H, W = image.shape
    if H % h == 0 and W % w == 0:
        fh, fw = H // h, W // w
        if image.dtype == np.uint8 and fh * fw <= 256:
            # Integer sums (exact, and much faster than a float mean over strided axes).
            s = image.reshape(h, fh, W).sum(axis=1, dtype=np.uint16)
            s = s.reshape(h, w, fw).sum(axis=2, dtype=np.uint32)
            return s.astype(np.float32) * np.float32(1.0 / (fh * fw))
        img = image.astype(np.float32, copy=False)
        return img.reshape(h, fh, w, fw).mean(axis=(1, 3))
    img = image.astype(np.float32, copy=False)
    rows = np.minimum(((np.arange(h) + 0.5) * H / h).astype(int), H - 1)
    cols = np.minimum(((np.arange(w) + 0.5) * W / w).astype(int), W - 1)
    return img[np.ix_(rows, cols)]


def _interp_weights(n_out: int, n_in: int):
    """Linear interpolation (i0, i1, w) from n_in to n_out samples, pixel-centre aligned."""
    x = np.clip((np.arange(n_out) + 0.5) * n_in / n_out - 0.5, 0, n_in - 1)
    i0 = np.minimum(np.floor(x).astype(np.intp), max(n_in - 2, 0))
    i1 = np.minimum(i0 + 1, n_in - 1)
    return i0, i1, (x - i0).astype(np.float32)


_INTERP_CACHE: dict = {}


def upsample_to(prob: np.ndarray, H: int, W: int) -> np.ndarray:
    """Bilinear resize (pixel-centre aligned, separable: rows then columns) of a (h, w) map
    to (H, W). Plain gathers, no BLAS (whose thread pool costs more than the work here)."""
    h, w = prob.shape
    if (h, w) == (H, W):
        return prob
    key = (h, w, H, W)
    hit = _INTERP_CACHE.get(key)
    if hit is None:
        r0, r1, wr = _interp_weights(H, h)
        c0, c1, wc = _interp_weights(W, w)
        hit = _INTERP_CACHE[key] = (r0, r1, wr[:, None], c0, c1, wc[None, :])
    r0, r1, wr, c0, c1, wc = hit
    p = prob.astype(np.float32, copy=False)
    rows = p[r0] + (p[r1] - p[r0]) * wr  # (H, w)
    return rows[:, c0] + (rows[:, c1] - rows[:, c0]) * wc


def cpu_session(model_path: str | Path, threads: int = 1):
    """An ONNX Runtime session of ``model_path`` on the CPU: ``threads`` intra-op threads,
    one inter-op thread, warnings silenced (the segmenter's and the training tools')."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = int(threads)
    options.inter_op_num_threads = 1
    options.log_severity_level = 3
    return ort.InferenceSession(
        str(model_path), sess_options=options, providers=["CPUExecutionProvider"]
    )


def read_model_card(model_path: str | Path) -> dict:
    """The model card (the ``.json`` next to the ``.onnx``) as a dict; {} when there is none.
    A card that is not a JSON object raises ValueError naming the file."""
    card = Path(model_path).with_suffix(".json")
    if not card.is_file():
        return {}
    try:
        data = json.loads(card.read_text())
    except (OSError, ValueError) as e:
        raise ValueError(f"imaging.onnx_model: model card {card} is not valid JSON: {e}") from None
    if not isinstance(data, dict):
        raise ValueError(f"imaging.onnx_model: model card {card} is not a JSON object")
    return data


def card_canvas(card: dict, where: str = "model card") -> dict | None:
    """``{"pixel_size": m, "shape": (H, W), "top": m or None}`` from a card's
    ``pixel_size_mm``, ``canvas_px`` and optional ``canvas_top_mm``; None (the plain
    resize) when ``pixel_size_mm`` or ``canvas_px`` is missing. Bad values raise ValueError."""
    if "pixel_size_mm" not in card or "canvas_px" not in card:
        return None
    try:
        p = float(card["pixel_size_mm"])
        shape = tuple(int(v) for v in card["canvas_px"])
        top = card.get("canvas_top_mm")
        top = None if top is None else float(top) * 1e-3
    except (TypeError, ValueError):
        raise ValueError(
            f"{where}: pixel_size_mm must be a number, canvas_px two integers "
            f"and canvas_top_mm a number; got {card.get('pixel_size_mm')!r}, "
            f"{card.get('canvas_px')!r}, {card.get('canvas_top_mm')!r}"
        ) from None
    if not (np.isfinite(p) and p > 0) or len(shape) != 2 or min(shape) < 2:
        raise ValueError(
            f"{where}: expected pixel_size_mm > 0 and canvas_px [H, W] of at "
            f"least 2 pixels, got {card['pixel_size_mm']!r}, {card['canvas_px']!r}"
        )
    return {"pixel_size": p * 1e-3, "shape": shape, "top": top}


def _area_matrix(centres: np.ndarray, size: float, lo: float, step: float, n_out: int):
    """Sparse (n_out, n_in) box filter from input cells (centres, width ``size``) to output
    cells ``[lo + i step, lo + (i + 1) step]``: each weight is the overlap length over
    ``step``, so an output cell half outside the input gets half its area filled with 0
    (zero padding)."""
    edges = lo + np.arange(n_out + 1) * step
    a, b = centres - 0.5 * size, centres + 0.5 * size
    ov = (
        np.clip(
            np.minimum(b[None, :], edges[1:, None]) - np.maximum(a[None, :], edges[:-1, None]),
            0.0,
            None,
        )
        / step
    )
    return sps.csr_matrix(ov.astype(np.float32))


def _span(matrix) -> slice:
    """The rows of a sparse matrix from its first to its last non-empty one."""
    filled = np.flatnonzero(np.diff(matrix.indptr))
    return slice(int(filled[0]), int(filled[-1]) + 1) if filled.size else slice(0, 0)


def _linear_taps(pos: np.ndarray, n: int):
    """Linear interpolation at continuous indices ``pos`` of n samples (pixel centres at
    integers) as two taps per output: (i0, i1, w0, w1) with i0 < i1 (for n >= 2) and float32
    weights; outputs more than half a sample outside the grid get weights 0."""
    inside = (pos >= -0.5) & (pos <= n - 0.5)
    x = np.clip(pos, 0, n - 1)
    i0 = np.minimum(np.floor(x).astype(np.intp), max(n - 2, 0))
    i1 = np.minimum(i0 + 1, n - 1)
    w = (x - i0) * inside
    return i0, i1, ((1 - w) * inside).astype(np.float32), w.astype(np.float32)


def _linear_matrix(pos: np.ndarray, n: int):
    """Sparse (len(pos), n) linear interpolation at continuous indices ``pos`` of n samples
    (pixel centres at integers); rows more than half a sample outside the grid are 0."""
    i0, i1, w0, w1 = _linear_taps(pos, n)
    rows = np.arange(len(pos))
    return sps.csr_matrix(
        (np.concatenate([w0, w1]), (np.concatenate([rows, rows]), np.concatenate([i0, i1]))),
        shape=(len(pos), n),
    )


class PhysicalCanvas:
    """Maps images of a probe geometry to and from a fixed canvas of square physical pixels.

    Canvas pixel (row i, column j) covers z_P in ``top + [i, i + 1] * pixel_size`` and x_P in
    ``(j - W / 2 + [0, 1]) * pixel_size`` (m): the canvas is centred on the beam axis and its
    top edge is at ``top`` (default the image's top edge ``geometry.z_min``). Both maps are
    separable (rows along z_P, columns along x_P): two sparse products, precomputed per
    geometry (sparse, not dense BLAS, whose thread pool costs more than the work here).
    """

    def __init__(
        self,
        geometry: ProbeGeometry,
        pixel_size: float,
        shape: tuple[int, int],
        top: float | None = None,
    ):
        g = geometry
        self.geometry = g
        self.pixel_size = float(pixel_size)
        self.shape = (int(shape[0]), int(shape[1]))
        self.top = float(g.z_min if top is None else top)
        self.left = -0.5 * self.shape[1] * self.pixel_size
        self._z = g.z0 + np.arange(g.height_px) * g.dz
        self._x = g.x0 + np.arange(g.width_px) * g.dx
        self._rows = _area_matrix(self._z, g.dz, self.top, self.pixel_size, self.shape[0])
        # The column map as (canvas columns, image columns): applied as cols @ tmp.T, which
        # sums over image columns in the same (ascending) order as tmp @ cols.T, without
        # scipy's per-call transposes of a dense @ sparse product.
        self._cols = _area_matrix(self._x, g.dx, self.left, self.pixel_size, self.shape[1])
        self._back: dict = {}
        self._taps: dict = {}
        # The canvas rows and columns that overlap the image (the others are 0): to_canvas
        # works on them only, with the same sums in the same order.
        self._row_span = _span(self._rows)
        self._col_span = _span(self._cols)
        self._rows_in = self._rows[self._row_span]
        self._cols_in = self._cols[self._col_span]
        #: Canvas pixels at least half covered by the image's fan.
        self.fan_mask = self.to_canvas(g.fan_mask.astype(np.float32)) >= 0.5
        self.fan_mask.flags.writeable = False

    def to_canvas(self, image: np.ndarray) -> np.ndarray:
        """float32 (H, W) canvas of an image (rows, cols): the area mean of the image over
        each canvas pixel, 0 where the canvas lies outside the image."""
        img = np.asarray(image, dtype=np.float32)
        out = np.zeros(self.shape, np.float32)
        out[self._row_span, self._col_span] = (self._cols_in @ (self._rows_in @ img).T).T
        return out

    def to_image(self, canvas_map: np.ndarray) -> np.ndarray:
        """float32 (rows, cols) image of a map (h, w) over the canvas (the canvas's shape or
        any other grid covering the same extent): bilinear at the image's pixel centres, 0
        where the image lies outside the canvas."""
        m = np.asarray(canvas_map, dtype=np.float32)
        h, w = m.shape
        hit = self._back.get((h, w))
        if hit is None:
            sz = self.shape[0] * self.pixel_size / h
            sx = self.shape[1] * self.pixel_size / w
            hit = self._back[(h, w)] = (
                _linear_matrix((self._z - self.top) / sz - 0.5, h),
                _linear_matrix((self._x - self.left) / sx - 0.5, w).T.tocsr(),
            )
        rows, cols_T = hit
        return np.asarray((rows @ m) @ cols_T, dtype=np.float32)

    def _back_taps(self, h: int, w: int):
        """The two-tap bilinear interpolation ``to_image`` applies to a (h, w) map: (rows,
        cols), each (i0, i1, w0, w1) per image row / column (see ``_linear_taps``)."""
        hit = self._taps.get((h, w))
        if hit is None:
            sz = self.shape[0] * self.pixel_size / h
            sx = self.shape[1] * self.pixel_size / w
            hit = self._taps[(h, w)] = (
                _linear_taps((self._z - self.top) / sz - 0.5, h),
                _linear_taps((self._x - self.left) / sx - 0.5, w),
            )
        return hit

    def to_image_window(
        self, window: np.ndarray, origin: tuple[int, int], map_shape: tuple[int, int]
    ) -> tuple[slice, slice, np.ndarray]:
        """``to_image`` of a (h, w) = ``map_shape`` map that is 0 outside one window:
        ``window`` (a, b) is the map at rows ``origin[0] + [0, a)`` and columns
        ``origin[1] + [0, b)``. Returns (image rows, image columns, float32 values) of the
        image pixels whose interpolation reaches the window; ``to_image`` of the whole map is
        0 everywhere else. The values are those of ``to_image`` bit for bit: the same two
        float32 taps per row and column, summed in the same order as its sparse products
        (the terms left out are exact zeros)."""
        m = np.asarray(window, dtype=np.float32)
        (ri0, ri1, rw0, rw1), (ci0, ci1, cw0, cw1) = self._back_taps(*map_shape)
        r0, c0 = int(origin[0]), int(origin[1])
        a, b = m.shape
        # Taps are non-decreasing along the image: the rows reaching the window are the
        # contiguous range with i1 >= r0 and i0 < r0 + a (likewise the columns).
        rows = slice(int(ri1.searchsorted(r0)), int(ri0.searchsorted(r0 + a)))
        cols = slice(int(ci1.searchsorted(c0)), int(ci0.searchsorted(c0 + b)))
        # The window with a ring of zeros: taps outside it read 0, as they do on the map.
        padded = np.zeros((a + 2, b + 2), np.float32)
        padded[1:-1, 1:-1] = m
        # Local tap indices in the padded window. In range without clipping: i1 - 1 <= i0
        # < i1 (or both 0), so on those rows r0 - 1 <= i0 and i1 <= r0 + a.
        lr0 = ri0[rows] - (r0 - 1)
        lr1 = ri1[rows] - (r0 - 1)
        lc0 = ci0[cols] - (c0 - 1)
        lc1 = ci1[cols] - (c0 - 1)
        t = padded.take(lr0, axis=0)
        t *= rw0[rows, None]
        t1 = padded.take(lr1, axis=0)
        t1 *= rw1[rows, None]
        t += t1
        values = t[:, lc0]
        values *= cw0[cols]
        v1 = t[:, lc1]
        v1 *= cw1[cols]
        values += v1
        return rows, cols, values


# ONNX Runtime's element type names of the outputs each ``onnx_output`` accepts: scores need
# a float tensor; labels (class indices) may be integers too.
_FLOAT_TYPES = (
    "tensor(float)",
    "tensor(double)",
    "tensor(float16)",
    "tensor(bfloat16)",
    "tensor(float32)",
    "tensor(float64)",
)
_INTEGER_TYPES = tuple(f"tensor({k}{b})" for k in ("int", "uint") for b in (8, 16, 32, 64))


def check_output_type(
    type_name: str, shape, output: str, where: str, model: str, field_prefix: str = "imaging."
) -> None:
    """Raises ValueError naming ``where`` (the field that selects the model) when a model's
    first output cannot be read as ``output`` ("logits", "probability" or "labels"): its
    element type (``tensor(float)``, ``tensor(int64)``, ...) or rank (3 or 4; symbolic or
    unknown dimensions pass)."""
    accepted = _FLOAT_TYPES + (_INTEGER_TYPES if output == "labels" else ())
    if type_name not in accepted:
        hint = (
            f" (a model that outputs class indices: set {field_prefix}onnx_output: labels)"
            if type_name in _INTEGER_TYPES
            else ""
        )
        raise ValueError(
            f"{where}: model {model} outputs {type_name}; "
            f"{field_prefix}onnx_output {output!r} expects "
            f"{'a float or integer' if output == 'labels' else 'a float'} "
            f"tensor{hint}"
        )
    if isinstance(shape, (list, tuple)) and len(shape) not in (3, 4):
        raise ValueError(
            f"{where}: model {model} output has shape {list(shape)}; expected "
            "(N, K, h, w) or (N, h, w)"
        )


class OnnxSegmenter:
    """A loaded ONNX model; call it on a uint8 grey image to get a bool kidney mask."""

    def __init__(
        self,
        model_path: str | Path,
        geometry: ProbeGeometry,
        input_shape=(1, 1, 128, 128),
        mean: float = 0.0,
        std: float = 1.0,
        output: str = "logits",
        kidney_channel: int = 0,
        threshold: float = 0.5,
        threads: int = 1,
        field_prefix: str = "imaging.",
        card: dict | None = None,
        track_gap: float = 2.0,
        track_reach: float = 0.010,
        track_min_overlap: float = 0.5,
        track_section_reach: float = 0.015,
        mirror_average: bool = False,
        min_region_area: float = 0.0,
        guided_radius: float = 0.0,
        guided_eps: float = 0.01,
        ensemble_model: str | Path | None = None,
        model_field: str = "onnx_model",
        edge_threshold: float | None = None,
    ):
        """``card``: the model card's fields (default: read from the ``.json`` next to the
        model); ``pixel_size_mm`` and ``canvas_px`` switch on the physical canvas.
        ``track_gap`` (s), ``track_reach`` (m), ``track_min_overlap``,
        ``track_section_reach`` (m): how a kidney seen before, or predicted by the
        registered template, is followed (see ``ImagingConfig.track_gap``).
        ``mirror_average``: average the probability of the image and of its lateral mirror
        (:func:`mirror_average`; two model runs per frame). ``min_region_area`` (m^2):
        candidate regions smaller than this are dropped (:func:`drop_small_regions`).
        ``guided_radius`` (m, 0: off) and ``guided_eps``: the image-resolution refinement of
        the probability before the threshold (:func:`guided_filter`, the frame as guide).
        ``ensemble_model``: a second model (same input and output fields, same canvas) whose
        probability is averaged with this one's (:func:`ensemble_average`; None or "": none).
        ``model_field``: the scenario field that names the model, for error messages.
        ``edge_threshold``: the probability level at which a region's edge is drawn on the
        image grid (after the guided filter; None: ``threshold``); the regions themselves
        are found at ``threshold``."""
        self.mirror_average = bool(mirror_average)
        if edge_threshold is not None and not (0.0 < edge_threshold < 1.0):
            raise ValueError(
                f"{field_prefix}onnx_edge_threshold: expected a probability in (0, 1), or 0 "
                f"for onnx_threshold's, got {edge_threshold!r}"
            )
        if not (np.isfinite(guided_radius) and guided_radius >= 0.0):
            raise ValueError(
                f"imaging.onnx_guided_radius: expected a radius >= 0 (m), got {guided_radius!r}"
            )
        if not (np.isfinite(guided_eps) and guided_eps > 0.0):
            raise ValueError(f"imaging.onnx_guided_eps: expected a number > 0, got {guided_eps!r}")
        self.guided_radius, self.guided_eps = float(guided_radius), float(guided_eps)
        if not (np.isfinite(min_region_area) and min_region_area >= 0.0):
            raise ValueError(
                f"imaging.onnx_min_region_area: expected an area >= 0 (m^2), "
                f"got {min_region_area!r}"
            )
        self.min_region_area = float(min_region_area)
        self.track_gap, self.track_reach = float(track_gap), float(track_reach)
        self.track_min_overlap = float(track_min_overlap)
        self.track_section_reach = float(track_section_reach)
        self.geometry = geometry
        self.path = resolve_model_path(str(model_path))
        where = f"{field_prefix}{model_field}"
        if self.path.is_dir():
            raise ValueError(f"{where}: expected an .onnx model file, got a folder: {self.path}")
        if not self.path.is_file():
            raise ValueError(f"{where}: ONNX model file not found: {self.path}")
        if len(input_shape) != 4 or not all(int(d) > 0 for d in input_shape):
            raise ValueError(
                f"{field_prefix}onnx_input_shape: expected 4 positive sizes "
                f"(N, C, H, W), got {list(input_shape)}"
            )
        self.input_shape = tuple(int(d) for d in input_shape)
        card_name = self.path.with_suffix(".json").name
        self.card = read_model_card(self.path) if card is None else dict(card)
        note = int8_saturation_note(self.card, self.path.name, cpu_has_vnni())
        if note:
            _note_once(str(self.path), note)
        spec = card_canvas(self.card, f"{where}: model card {card_name}")
        #: The physical canvas (None: the plain resize of the whole image to H x W).
        self.canvas = None
        if spec is not None:
            self.canvas = PhysicalCanvas(geometry, spec["pixel_size"], spec["shape"], spec["top"])
            self.input_shape = self.input_shape[:2] + self.canvas.shape
        self._fan_at: dict = {}
        if output not in ("logits", "probability", "labels"):
            raise ValueError(
                f"{field_prefix}onnx_output: expected 'logits', 'probability' "
                f"or 'labels', got {output!r}"
            )
        self.mean, self.std, self.output = float(mean), float(std), output
        self.kidney_channel, self.threshold = int(kidney_channel), float(threshold)
        #: The probability level at which a region's edge is drawn on the image grid (the
        #: region itself is found at ``threshold``); see ``edge_threshold`` in __init__.
        self.edge_threshold = None if edge_threshold is None else float(edge_threshold)
        try:
            self.session = cpu_session(self.path, threads)
        except Exception as e:  # onnxruntime raises its own Fail/InvalidGraph types
            raise ValueError(f"{where}: cannot load ONNX model {self.path}: {e}") from None
        inputs = self.session.get_inputs()
        if len(inputs) != 1:
            raise ValueError(
                f"{where}: model {self.path.name} has {len(inputs)} inputs; "
                f"expected one image input"
            )
        declared = inputs[0].shape
        if len(declared) != 4 or any(
            isinstance(d, int) and d != want for d, want in zip(declared, self.input_shape)
        ):
            if self.canvas is not None:
                raise ValueError(
                    f"{where}: model card {card_name} declares canvas_px "
                    f"{list(self.canvas.shape)} (input {list(self.input_shape)} with N, C from "
                    f"{field_prefix}onnx_input_shape) but model {self.path.name} input "
                    f"'{inputs[0].name}' has shape {declared}"
                )
            raise ValueError(
                f"{field_prefix}onnx_input_shape: the scenario names {list(self.input_shape)} "
                f"but model {self.path.name} input '{inputs[0].name}' has shape {declared}"
            )
        if "float" not in inputs[0].type:
            raise ValueError(
                f"{where}: model input '{inputs[0].name}' has type "
                f"{inputs[0].type}; expected a float tensor"
            )
        self.input_name = inputs[0].name
        output = self.session.get_outputs()[0]
        self.output_name = output.name
        check_output_type(
            output.type, output.shape, self.output, where, self.path.name, field_prefix
        )
        # Check the output once on a blank image, so a bad model fails here, not mid-run.
        try:
            probe = self.session.run(
                [self.output_name], {self.input_name: np.zeros(self.input_shape, np.float32)}
            )[0]
        except Exception as e:
            raise ValueError(
                f"{where}: model {self.path.name} fails on an input of shape "
                f"{list(self.input_shape)}: {e}"
            ) from None
        check_output_type(
            f"tensor({np.asarray(probe).dtype.name})",
            list(np.shape(probe)),
            self.output,
            where,
            self.path.name,
            field_prefix,
        )
        self._kidney_map(probe)
        #: The second model whose probability is averaged with this one's (None: none).
        self.ensemble = None
        if ensemble_model is not None and str(ensemble_model) != "":
            self.ensemble = self._ensemble_member(ensemble_model, threads, field_prefix)

    def _ensemble_member(self, model_path, threads: int, field_prefix: str) -> "OnnxSegmenter":
        """The second model of an ensemble, loaded with this one's input and output fields;
        ValueError naming ``onnx_ensemble_model`` when its canvas or its output's grid
        differs from this model's (the probabilities are averaged pixel by pixel)."""
        where = f"{field_prefix}onnx_ensemble_model"
        other = OnnxSegmenter(
            model_path,
            self.geometry,
            self.input_shape,
            self.mean,
            self.std,
            self.output,
            self.kidney_channel,
            self.threshold,
            threads,
            field_prefix,
            model_field="onnx_ensemble_model",
        )
        if other.path.resolve() == self.path.resolve():
            raise ValueError(
                f"{where}: names the same file as {field_prefix}onnx_model ({self.path.name}); "
                'expected a second model, or "" for none'
            )

        def canvas(seg):
            c = seg.canvas
            return None if c is None else (round(c.pixel_size * 1e3, 6), c.shape, round(c.top, 9))

        blank = np.zeros(self.input_shape, np.float32)
        grids = (self._run(blank).shape, other._run(blank).shape)
        if canvas(self) != canvas(other) or grids[0] != grids[1]:
            raise ValueError(
                f"{where}: model {other.path.name} (canvas {canvas(other)}, output grid "
                f"{list(grids[1])}) does not match {field_prefix}onnx_model {self.path.name} "
                f"(canvas {canvas(self)}, output grid {list(grids[0])}); the two "
                "probabilities are averaged pixel by pixel"
            )
        return other

    @classmethod
    def from_config(cls, config: ImagingConfig, geometry: ProbeGeometry) -> "OnnxSegmenter":
        return cls(
            config.onnx_model,
            geometry,
            config.onnx_input_shape,
            config.onnx_input_mean,
            config.onnx_input_std,
            config.onnx_output,
            config.onnx_kidney_channel,
            config.onnx_threshold,
            config.onnx_threads,
            track_gap=config.track_gap,
            track_reach=config.track_reach,
            track_min_overlap=config.track_min_overlap,
            track_section_reach=config.track_section_reach,
            mirror_average=config.onnx_mirror_average,
            min_region_area=config.onnx_min_region_area,
            guided_radius=config.onnx_guided_radius,
            guided_eps=config.onnx_guided_eps,
            ensemble_model=config.onnx_ensemble_model,
            edge_threshold=config.onnx_edge_threshold or None,
        )

    @property
    def edge_level(self) -> float:
        """The level of the image-grid probability above which a region's pixel is kidney:
        ``edge_threshold``, or ``threshold`` when that is None."""
        return self.threshold if self.edge_threshold is None else self.edge_threshold

    @property
    def guided_px(self) -> tuple[int, int]:
        """The guided filter's window radius in image pixels (rows, columns): at least 1."""
        g = self.geometry
        return max(1, round(self.guided_radius / g.dz)), max(1, round(self.guided_radius / g.dx))

    @property
    def pixel_size_mm(self) -> float | None:
        """The model's physical pixel size (mm), None without a physical canvas."""
        return None if self.canvas is None else self.canvas.pixel_size * 1e3

    def preprocess(self, image: np.ndarray) -> np.ndarray:
        n, c, h, w = self.input_shape
        if self.canvas is not None:
            x = self.canvas.to_canvas(image)  # a new array: scaled in place below
        else:
            x = resize_to(np.asarray(image), h, w).astype(np.float32)
        x *= np.float32(1.0 / 255.0)
        # (x - mean) / std; subtracting 0 and multiplying by 1 change nothing (skipped).
        if self.mean != 0.0:
            x -= np.float32(self.mean)
        if self.std != 1.0:
            x *= np.float32(1.0 / self.std)
        if n == c == 1:
            return x.reshape(n, c, h, w)
        return np.broadcast_to(x, (n, c, h, w)).astype(np.float32)

    def _kidney_map(self, out: np.ndarray) -> np.ndarray:
        """(h, w) kidney probability of the first batch item of a model output."""
        out = np.asarray(out)
        if out.ndim == 3:
            out = out[:, None]
        if out.ndim != 4:
            raise ValueError(
                f"imaging.onnx_model: model {self.path.name} output has shape "
                f"{list(out.shape)}; expected (N, K, h, w) or (N, h, w)"
            )
        k = out.shape[1]
        if self.output == "labels":
            # One channel of class indices, or K score channels (argmax); kidney class index
            # = onnx_kidney_channel.
            lab = np.rint(out[0, 0]) if k == 1 else np.argmax(out[0], axis=0)
            return (lab == self.kidney_channel).astype(np.float32)
        if self.kidney_channel >= k:
            raise ValueError(
                f"imaging.onnx_kidney_channel: {self.kidney_channel} but model "
                f"{self.path.name} outputs {k} channel(s)"
            )
        if self.output == "probability":
            return out[0, self.kidney_channel].astype(np.float32)
        if k == 1:
            # 1 / (1 + exp(-x)) in place, in the output's own precision, then float32. A
            # logit far below 0 overflows exp to inf and gives the right 0: no warning.
            p = np.negative(out[0, 0])
            with np.errstate(over="ignore"):
                np.exp(p, out=p)
            p += 1.0
            np.divide(1.0, p, out=p)
            return p.astype(np.float32, copy=False)
        z = out[0] - out[0].max(axis=0, keepdims=True)
        e = np.exp(z)
        return (e[self.kidney_channel] / e.sum(axis=0)).astype(np.float32)

    def to_image(self, prob: np.ndarray) -> np.ndarray:
        """A map at the model's output resolution -> (rows, cols) on the image grid."""
        if self.canvas is not None:
            return self.canvas.to_image(prob)
        H, W = self.geometry.image_shape
        return upsample_to(prob, H, W)

    def probability(self, image: np.ndarray) -> np.ndarray:
        """Kidney probability (rows, cols) of a uint8 grey image."""
        return self.to_image(self._past_fan(self.model_probability(image)))

    def _past_fan(self, prob: np.ndarray) -> np.ndarray:
        """On the physical canvas: the canvas pixels just outside the fan take their
        neighbours' largest probability, so that the bilinear map back holds a kidney that
        touches the fan's edge up to the edge (else it would fade half a canvas pixel, 1.2
        mm, inside it). The image's fan mask crops the rest."""
        if self.canvas is None:
            return prob
        fan = self._canvas_fan(*prob.shape)
        return np.where(fan, prob, ndimage.grey_dilation(prob, size=(3, 3)))

    def _canvas_fan(self, h: int, w: int) -> np.ndarray:
        """The canvas's fan pixels at a model output resolution (h, w)."""
        hit = self._fan_at.get((h, w))
        if hit is None:
            fan = self.canvas.fan_mask
            hit = fan if fan.shape == (h, w) else resize_to(fan.astype(np.float32), h, w) >= 0.5
            self._fan_at[(h, w)] = hit
        return hit

    def _canvas_outside(self, h: int, w: int) -> np.ndarray:
        """The canvas pixels outside the fan at a model output resolution (h, w)."""
        key = ("outside", h, w)
        hit = self._fan_at.get(key)
        if hit is None:
            hit = self._fan_at[key] = ~self._canvas_fan(h, w)
        return hit

    def model_probability(self, image: np.ndarray) -> np.ndarray:
        """Kidney probability at the model's output resolution (on the physical canvas, 0
        outside the image's fan, when the card declares one)."""
        image = np.asarray(image)
        if image.shape != self.geometry.image_shape:
            raise ValueError(
                f"OnnxSegmenter: image shape {image.shape} != probe image shape "
                f"{self.geometry.image_shape}"
            )
        x = self.preprocess(image)
        run = self._run if self.ensemble is None else self._run_ensemble
        if self.mirror_average:
            prob = mirror_average(run, x)
        else:
            prob = run(x)  # a new array: zeroed outside the fan in place
        if self.canvas is not None:
            np.copyto(prob, np.float32(0.0), where=self._canvas_outside(*prob.shape))
        return prob

    def _run(self, x: np.ndarray) -> np.ndarray:
        """(h, w) kidney probability of one preprocessed model input (N, C, H, W)."""
        return self._kidney_map(self.session.run([self.output_name], {self.input_name: x})[0])

    def _run_ensemble(self, x: np.ndarray) -> np.ndarray:
        """(h, w) mean kidney probability of this model and the ensemble's second one."""
        return ensemble_average([self._run(x), self.ensemble._run(x)])

    def __call__(
        self,
        image: np.ndarray,
        prior_mask: np.ndarray | None = None,
        prior_age: float = math.inf,
        section: np.ndarray | None = None,
    ) -> np.ndarray:
        """Bool kidney mask (rows, cols) of a uint8 grey image: without a prior, the largest
        candidate region; with the kidney mask last seen ``prior_age`` s ago and / or the
        registered template's predicted ``section`` (bool, rows x cols), the region that
        continues it or agrees with the template
        (:func:`~drake_rus.imaging.segment.tracked_component`, with the ``track_gap``,
        ``track_reach``, ``track_min_overlap`` and ``track_section_reach`` this segmenter
        was built with)."""
        if section is not None and not np.any(section):
            section = None
        regions = self.candidates(image, largest_only=prior_mask is None and section is None)
        if prior_mask is None and section is None:
            return regions[0] if regions else np.zeros(self.geometry.image_shape, bool)
        k = tracked_component(
            regions,
            prior_mask,
            prior_age,
            self.geometry,
            max_gap=self.track_gap,
            reach=self.track_reach,
            min_overlap=self.track_min_overlap,
            section=section,
            section_reach=self.track_section_reach,
        )
        return regions[k] if k is not None else np.zeros(self.geometry.image_shape, bool)

    def candidates(self, image: np.ndarray, largest_only: bool = False) -> list[np.ndarray]:
        """The frame's candidate kidney regions, largest first, each a bool mask (rows,
        cols): an 8-connected component of the thresholded probability at the model's
        resolution (holes filled), mapped back to the image bilinearly (from the physical
        canvas, when there is one), thresholded, in the fan. Regions that vanish in the
        mapping back are dropped, and so are regions smaller than ``min_region_area``. With
        ``guided_radius`` > 0 each region's probability on the image grid is refined by
        :func:`guided_filter` with the frame as guide before the threshold."""
        regions = self._candidates(self.model_probability(image), largest_only, image)
        if self.min_region_area > 0.0:
            return drop_small_regions(regions, self.min_region_area / self.geometry.pixel_area)
        return regions

    def _candidates(
        self, prob: np.ndarray, largest_only: bool, image: np.ndarray | None = None
    ) -> list[np.ndarray]:
        """:meth:`candidates` of a kidney probability at the model's resolution (before
        the minimum area); ``image``: the frame (the guided filter's guide; None: no
        refinement)."""
        above = prob > self.threshold
        # Labelled on the bounding box of the pixels above the threshold: the components,
        # their raster order (hence their numbers) and sizes are those of the whole grid.
        crop = _true_box(above)
        if crop is None:
            return []
        labels, n = ndimage.label(above[crop], structure=_EIGHT)
        r0, c0 = crop[0].start, crop[1].start
        if n == 1:  # the one component is every pixel above the threshold
            mask = self._component_mask(prob, above[crop], crop, image)
            return [] if mask is None else [mask]
        sizes = np.bincount(labels.ravel())[1:]
        order = np.argsort(-sizes, kind="stable")[: 1 if largest_only else None]
        boxes = ndimage.find_objects(labels)
        out = []
        for k in order:
            b = boxes[k]
            box = (slice(b[0].start + r0, b[0].stop + r0), slice(b[1].start + c0, b[1].stop + c0))
            # The component's pixels within its own box; _component_mask grows the window.
            mask = self._component_mask(prob, labels[b] == k + 1, box, image)
            if mask is not None:
                out.append(mask)
        return out

    def _region_mask(
        self, prob: np.ndarray, labels: np.ndarray, label: int, box: tuple[slice, slice]
    ) -> np.ndarray | None:
        """Bool image mask (rows, cols) of component ``label`` of ``labels`` (its bounding
        box ``box`` on the model's grid), or None when it vanishes in the mapping back
        (:meth:`_component_mask`)."""
        return self._component_mask(prob, labels[box] == label, box)

    def _component_mask(
        self,
        prob: np.ndarray,
        component: np.ndarray,
        box: tuple[slice, slice],
        image: np.ndarray | None = None,
    ) -> np.ndarray | None:
        """Bool image mask (rows, cols) of one component of the thresholded probability,
        given as its pixels ``component`` (bool) within its bounding box ``box`` on the
        model's grid, or None when it vanishes in the mapping back.

        Only this component (and a one-pixel margin for the interpolation) survives; its
        filled holes count as kidney. The work is done on the component's box grown by two
        pixels (the margin, then the past-fan dilation), where everything that differs from
        0 lies: the result is the same, bit for bit, as on the whole grid (hole filling sees
        the ring around the box as background connected to the border, the dilations see
        the zeros beyond it)."""
        h, w = prob.shape
        r0, r1 = max(box[0].start - 2, 0), min(box[0].stop + 2, h)
        c0, c1 = max(box[1].start - 2, 0), min(box[1].stop + 2, w)
        window = (slice(r0, r1), slice(c0, c1))
        keep = np.zeros((r1 - r0, c1 - c0), bool)
        keep[box[0].start - r0 : box[0].stop - r0, box[1].start - c0 : box[1].stop - c0] = component
        keep = fill_holes(keep)
        # The probability on the component and its 4-neighbours (binary_dilation's cross),
        # 0 elsewhere; at least just above the threshold on the component itself.
        p = np.where(_dilate_cross(keep), prob[window], np.float32(0.0))
        p[keep & (p <= self.threshold)] = 1.0
        if self.canvas is None:
            full = np.zeros((h, w), np.float32)
            full[window] = p
            values = self.to_image(full)
            if self.guided_radius > 0.0 and image is not None:
                values = guided_filter(values, _grey(image), self.guided_px, self.guided_eps)
            mask = (values > self.edge_level) & self.geometry.fan_mask
            return mask if mask.any() else None
        fan = self._canvas_fan(h, w)[window]
        if not fan.all():  # as _past_fan (nothing to do in the fan's interior)
            p = np.where(fan, p, _max_3x3(p))
        rows, cols, values = self.canvas.to_image_window(p, (r0, c0), (h, w))
        if self.guided_radius > 0.0 and image is not None:
            rows, cols, values = self._guided_window(rows, cols, values, image)
        inside = values > self.edge_level
        inside &= self.geometry.fan_mask[rows, cols]
        if not inside.any():
            return None
        mask = np.zeros(self.geometry.image_shape, bool)
        mask[rows, cols] = inside
        return mask

    def _guided_window(
        self, rows: slice, cols: slice, values: np.ndarray, image: np.ndarray
    ) -> tuple[slice, slice, np.ndarray]:
        """:func:`guided_filter` of an image-grid probability that is 0 outside (rows, cols),
        with the frame as guide: on that window grown by twice the filter's radius and a
        pixel (clipped to the image), beyond which the filter's output is 0 too (a window
        of zero probability fits a = b = 0). Returns the grown (rows, cols, values)."""
        rz, rx = self.guided_px
        H, W = self.geometry.image_shape
        R0, R1 = max(rows.start - 2 * rz - 1, 0), min(rows.stop + 2 * rz + 1, H)
        C0, C1 = max(cols.start - 2 * rx - 1, 0), min(cols.stop + 2 * rx + 1, W)
        p = np.zeros((R1 - R0, C1 - C0), np.float32)
        p[rows.start - R0 : rows.stop - R0, cols.start - C0 : cols.stop - C0] = values
        q = guided_filter(p, _grey(image[R0:R1, C0:C1]), (rz, rx), self.guided_eps)
        return slice(R0, R1), slice(C0, C1), q


def _grey(image: np.ndarray) -> np.ndarray:
    """float32 grey in [0, 1] of a uint8 (0-255) image."""
    return np.asarray(image, np.float32) * np.float32(1.0 / 255.0)


def guided_filter(
    p: np.ndarray, guide: np.ndarray, radius_px: tuple[int, int], eps: float
) -> np.ndarray:
    """The guided filter (He, Sun and Tang, 2013) of a map ``p`` with the image ``guide``
    (same shape, float): in every (2 r_rows + 1) x (2 r_cols + 1) window the least-squares
    fit p ~ a guide + b with ``eps`` a^2 added (a window of flat guide gives a = 0: the
    window's mean of p), and each pixel's output is its windows' mean a times its guide
    plus their mean b. An edge of ``p`` near an edge of the guide moves onto it; elsewhere
    ``p`` is box-smoothed. Box means by ``ndimage.uniform_filter`` (the border repeated).
    float32 of ``p``'s shape."""
    p = np.asarray(p, np.float32)
    guide = np.asarray(guide, np.float32)
    if p.shape != guide.shape or p.ndim != 2:
        raise ValueError(
            f"guided_filter: p and guide must be 2-D of one shape, got {p.shape}, {guide.shape}"
        )
    size = (2 * int(radius_px[0]) + 1, 2 * int(radius_px[1]) + 1)

    def box(x):
        return ndimage.uniform_filter(x, size=size, mode="nearest")

    mean_i, mean_p = box(guide), box(p)
    var_i = box(guide * guide) - mean_i * mean_i
    cov_ip = box(guide * p) - mean_i * mean_p
    a = cov_ip / (var_i + np.float32(eps))
    b = mean_p - a * mean_i
    return box(a) * guide + box(b)


def mirror_average(run, x: np.ndarray) -> np.ndarray:
    """Test-time augmentation with the lateral mirror: the mean of ``run(x)`` and of
    ``run`` on ``x`` mirrored left-right, mirrored back. ``x`` is a model input (..., H, W)
    whose columns are symmetric about the beam axis (the physical canvas is centred on
    x_P = 0, and the probe's image grid is symmetric), so the mirror is the same fan seen
    from the array's other end: a kidney's section is as plausible either way round.
    ``run`` maps an input to a (h, w) probability; returns float32 (h, w)."""
    p = np.asarray(run(x), dtype=np.float32)
    q = np.asarray(run(np.ascontiguousarray(x[..., ::-1])), dtype=np.float32)
    out = p + q[..., ::-1]
    out *= np.float32(0.5)
    return out


def ensemble_average(probabilities: list[np.ndarray]) -> np.ndarray:
    """The pixel-wise mean (float32) of kidney probabilities of one frame from several
    models, all (h, w) on one grid: an ensemble. Where the models disagree the mean falls
    between them, so a region one model alone marks survives the 0.5 threshold only where
    the other gives it some weight too. ValueError when the maps differ in shape."""
    maps = [np.asarray(p, dtype=np.float32) for p in probabilities]
    if not maps:
        raise ValueError("ensemble_average: expected at least one probability map")
    if any(m.shape != maps[0].shape or m.ndim != 2 for m in maps):
        raise ValueError(
            "ensemble_average: expected 2-D maps of one shape, got "
            + ", ".join(str(m.shape) for m in maps)
        )
    out = maps[0].copy()
    for m in maps[1:]:
        out += m
    out *= np.float32(1.0 / len(maps))
    return out


def drop_small_regions(regions: list[np.ndarray], min_pixels: float) -> list[np.ndarray]:
    """The bool masks of ``regions`` with at least ``min_pixels`` pixels, in their order."""
    return [m for m in regions if np.count_nonzero(m) >= min_pixels]


def _true_box(mask: np.ndarray) -> tuple[slice, slice] | None:
    """(rows, cols) slices of the bounding box of a 2-D bool mask; None when it is empty."""
    rows = mask.any(axis=1).nonzero()[0]
    if rows.size == 0:
        return None
    r0, r1 = int(rows[0]), int(rows[-1]) + 1
    cols = mask[r0:r1].any(axis=0).nonzero()[0]
    return slice(r0, r1), slice(int(cols[0]), int(cols[-1]) + 1)


def _dilate_cross(mask: np.ndarray) -> np.ndarray:
    """``ndimage.binary_dilation(mask)`` (the 4-neighbour cross, one step, 0 beyond the
    border) by array shifts."""
    out = mask.copy()
    out[1:] |= mask[:-1]
    out[:-1] |= mask[1:]
    out[:, 1:] |= mask[:, :-1]
    out[:, :-1] |= mask[:, 1:]
    return out


def _max_3x3(p: np.ndarray) -> np.ndarray:
    """``ndimage.grey_dilation(p, size=(3, 3))`` by array shifts: the largest value of each
    pixel's 3 x 3 neighbourhood within the array (its 'reflect' border repeats the edge
    pixel, which the neighbourhood holds already). Maxima are exact, so any order gives
    the same values."""
    rows = p.copy()
    np.maximum(rows[1:], p[:-1], out=rows[1:])
    np.maximum(rows[:-1], p[1:], out=rows[:-1])
    out = rows.copy()
    np.maximum(out[:, 1:], rows[:, :-1], out=out[:, 1:])
    np.maximum(out[:, :-1], rows[:, 1:], out=out[:, :-1])
    return out


_EIGHT = np.ones((3, 3), bool)
_CROSS = ndimage.generate_binary_structure(2, 1)  # ndimage.label's default structure


def fill_holes(mask: np.ndarray) -> np.ndarray:
    """``mask`` with every background region that does not touch the border filled
    (one labelling of the background; faster than iterative hole filling)."""
    bg, n = ndimage.label(~mask, structure=_CROSS)
    if n == 0:
        return np.ones_like(mask)
    if n == 1 and (bg[0].any() or bg[-1].any() or bg[:, 0].any() or bg[:, -1].any()):
        return mask  # the one background region touches the border: no hole
    border = np.unique(np.concatenate([bg[0], bg[-1], bg[:, 0], bg[:, -1]]))
    outside = np.zeros(n + 1, bool)
    outside[border] = True
    outside[0] = False
    return ~outside[bg]


def largest_component(mask: np.ndarray) -> np.ndarray:
    """The largest 8-connected component of a mask, holes filled."""
    labels, n = ndimage.label(mask, structure=_EIGHT)
    if n == 0:
        return np.zeros_like(mask, bool)
    if n == 1:
        return fill_holes(labels == 1)
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    return fill_holes(labels == int(np.argmax(sizes)))
