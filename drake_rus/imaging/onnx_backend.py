"""ONNX Runtime kidney segmenter: any model whose input/output shapes the scenario names.

Contract (``ImagingConfig``): one float32 input of shape ``onnx_input_shape`` (N, C, H, W)
(dimensions the model leaves symbolic are accepted); the grey image (0-255) is resized to
H x W (block mean when the sizes divide, else nearest), scaled to [0, 1], normalised with
``(x - onnx_input_mean) / onnx_input_std`` and repeated over C channels. The first output is
(N, K, h, w) or (N, h, w): ``logits`` (a sigmoid is applied; with K > 1 a softmax over K),
``probability`` or ``labels`` (integer class per pixel, or K scores to argmax); channel
(or class index) ``onnx_kidney_channel`` is the kidney. The kidney probability is resized back to the image (bilinear) and thresholded.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy import ndimage

from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.paths import REPO_ROOT


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
    rows = p[r0] + (p[r1] - p[r0]) * wr              # (H, w)
    return rows[:, c0] + (rows[:, c1] - rows[:, c0]) * wc


class OnnxSegmenter:
    """A loaded ONNX model; call it on a uint8 grey image to get a bool kidney mask."""

    def __init__(self, model_path: str | Path, geometry: ProbeGeometry,
                 input_shape=(1, 1, 128, 128), mean: float = 0.0, std: float = 1.0,
                 output: str = "logits", kidney_channel: int = 0, threshold: float = 0.5,
                 threads: int = 1, field_prefix: str = "imaging."):
        import onnxruntime as ort
        self.geometry = geometry
        self.path = resolve_model_path(str(model_path))
        where = f"{field_prefix}onnx_model"
        if not self.path.is_file():
            raise ValueError(f"{where}: ONNX model file not found: {self.path}")
        if len(input_shape) != 4 or not all(int(d) > 0 for d in input_shape):
            raise ValueError(f"{field_prefix}onnx_input_shape: expected 4 positive sizes "
                             f"(N, C, H, W), got {list(input_shape)}")
        self.input_shape = tuple(int(d) for d in input_shape)
        if output not in ("logits", "probability", "labels"):
            raise ValueError(f"{field_prefix}onnx_output: expected 'logits', 'probability' "
                             f"or 'labels', got {output!r}")
        self.mean, self.std, self.output = float(mean), float(std), output
        self.kidney_channel, self.threshold = int(kidney_channel), float(threshold)
        options = ort.SessionOptions()
        options.intra_op_num_threads = int(threads)
        options.inter_op_num_threads = 1
        options.log_severity_level = 3
        try:
            self.session = ort.InferenceSession(str(self.path), sess_options=options,
                                                providers=["CPUExecutionProvider"])
        except Exception as e:  # onnxruntime raises its own Fail/InvalidGraph types
            raise ValueError(f"{where}: cannot load ONNX model {self.path}: {e}") from None
        inputs = self.session.get_inputs()
        if len(inputs) != 1:
            raise ValueError(f"{where}: model {self.path.name} has {len(inputs)} inputs; "
                             f"expected one image input")
        declared = inputs[0].shape
        if len(declared) != 4 or any(isinstance(d, int) and d != want
                                     for d, want in zip(declared, self.input_shape)):
            raise ValueError(
                f"{field_prefix}onnx_input_shape: the scenario names {list(self.input_shape)} "
                f"but model {self.path.name} input '{inputs[0].name}' has shape {declared}")
        if "float" not in inputs[0].type:
            raise ValueError(f"{where}: model input '{inputs[0].name}' has type "
                             f"{inputs[0].type}; expected a float tensor")
        self.input_name = inputs[0].name
        self.output_name = self.session.get_outputs()[0].name
        # Check the output once on a blank image, so a bad model fails here, not mid-run.
        try:
            probe = self.session.run([self.output_name], {self.input_name: np.zeros(
                self.input_shape, np.float32)})[0]
        except Exception as e:
            raise ValueError(f"{where}: model {self.path.name} fails on an input of shape "
                             f"{list(self.input_shape)}: {e}") from None
        self._kidney_map(probe)

    @classmethod
    def from_config(cls, config: ImagingConfig, geometry: ProbeGeometry) -> "OnnxSegmenter":
        return cls(config.onnx_model, geometry, config.onnx_input_shape, config.onnx_input_mean,
                   config.onnx_input_std, config.onnx_output, config.onnx_kidney_channel,
                   config.onnx_threshold, config.onnx_threads)

    def preprocess(self, image: np.ndarray) -> np.ndarray:
        n, c, h, w = self.input_shape
        x = resize_to(np.asarray(image), h, w) * np.float32(1.0 / 255.0)
        x = (x - np.float32(self.mean)) * np.float32(1.0 / self.std)
        return np.broadcast_to(x, (n, c, h, w)).astype(np.float32)

    def _kidney_map(self, out: np.ndarray) -> np.ndarray:
        """(h, w) kidney probability of the first batch item of a model output."""
        out = np.asarray(out)
        if out.ndim == 3:
            out = out[:, None]
        if out.ndim != 4:
            raise ValueError(f"imaging.onnx_model: model {self.path.name} output has shape "
                             f"{list(out.shape)}; expected (N, K, h, w) or (N, h, w)")
        k = out.shape[1]
        if self.output == "labels":
            # One channel of class indices, or K score channels (argmax); kidney class index
            # = onnx_kidney_channel.
            lab = np.rint(out[0, 0]) if k == 1 else np.argmax(out[0], axis=0)
            return (lab == self.kidney_channel).astype(np.float32)
        if self.kidney_channel >= k:
            raise ValueError(f"imaging.onnx_kidney_channel: {self.kidney_channel} but model "
                             f"{self.path.name} outputs {k} channel(s)")
        if self.output == "probability":
            return out[0, self.kidney_channel].astype(np.float32)
        if k == 1:
            return (1.0 / (1.0 + np.exp(-out[0, 0]))).astype(np.float32)
        z = out[0] - out[0].max(axis=0, keepdims=True)
        e = np.exp(z)
        return (e[self.kidney_channel] / e.sum(axis=0)).astype(np.float32)

    def probability(self, image: np.ndarray) -> np.ndarray:
        """Kidney probability (rows, cols) of a uint8 grey image."""
        H, W = self.geometry.image_shape
        return upsample_to(self.model_probability(image), H, W)

    def model_probability(self, image: np.ndarray) -> np.ndarray:
        """Kidney probability at the model's output resolution."""
        image = np.asarray(image)
        if image.shape != self.geometry.image_shape:
            raise ValueError(f"OnnxSegmenter: image shape {image.shape} != probe image shape "
                             f"{self.geometry.image_shape}")
        out = self.session.run([self.output_name], {self.input_name: self.preprocess(image)})[0]
        return self._kidney_map(out)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """Bool kidney mask (rows, cols) of a uint8 grey image: the largest component (holes
        filled) at the model's resolution, upsampled bilinearly, thresholded, in the fan."""
        prob = self.model_probability(image)
        keep = largest_component(prob > self.threshold)
        if not keep.any():
            return np.zeros(self.geometry.image_shape, bool)
        # Only the kept component (and a one-pixel margin for the interpolation) survives;
        # its filled holes count as kidney.
        prob = np.where(ndimage.binary_dilation(keep), prob, 0.0).astype(np.float32)
        prob[keep & (prob <= self.threshold)] = 1.0
        H, W = self.geometry.image_shape
        return (upsample_to(prob, H, W) > self.threshold) & self.geometry.fan_mask


_EIGHT = np.ones((3, 3), bool)


def fill_holes(mask: np.ndarray) -> np.ndarray:
    """``mask`` with every background region that does not touch the border filled
    (one labelling of the background; faster than iterative hole filling)."""
    bg, n = ndimage.label(~mask)
    if n <= 1:
        return mask if n == 1 else np.ones_like(mask)
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
