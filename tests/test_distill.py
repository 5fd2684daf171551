"""Self-distillation targets of ``train_segmenter --distill-from``: a model's own kidney
probability on the canvas, and one-line errors for a wrong model."""

import numpy as np
import onnxruntime as ort
import pytest

from drake_rus.imaging.training.train_segmenter import main, teacher_targets
from drake_rus.paths import REPO_ROOT

MODEL = REPO_ROOT / "models" / "segmenter" / "kidney_unet.onnx"


def _canvases(n: int, shape=(128, 112)) -> np.ndarray:
    """Grey speckle canvases with a kidney-like ellipse: a dark inside in a bright rim (the
    shipped model marks part of it, so its probability is not a constant)."""
    rng = np.random.default_rng(0)
    rows, cols = np.mgrid[: shape[0], : shape[1]]
    out = np.clip(rng.normal(110, 25, (n, *shape)), 0, 255)
    for k in range(n):
        r = ((rows - 0.43 * shape[0] - 4 * k) / 16) ** 2 + ((cols - 0.5 * shape[1]) / 26) ** 2
        out[k][r <= 1.6] = np.clip(rng.normal(220, 25, int((r <= 1.6).sum())), 0, 255)
        out[k][r <= 1] = np.clip(rng.normal(80, 20, int((r <= 1).sum())), 0, 255)
    out[:, :6] = 0  # above the probe face
    return out.astype(np.uint8)


def test_teacher_targets_are_the_models_probability():
    images = _canvases(3)
    targets = teacher_targets(MODEL, images)
    assert targets.dtype == np.uint8 and targets.shape == images.shape
    session = ort.InferenceSession(str(MODEL), providers=["CPUExecutionProvider"])
    name = session.get_inputs()[0].name
    for image, target in zip(images, targets):
        logits = session.run(None, {name: (image / 255.0).astype(np.float32)[None, None]})[0]
        expected = np.rint(255.0 / (1.0 + np.exp(-logits[0, 0].astype(np.float64))))
        assert np.abs(target.astype(int) - expected.astype(int)).max() <= 1
    # Not a constant: the model tells the blob from the rest somewhere on the canvas.
    assert targets.max() - targets.min() > 50


def test_teacher_targets_refuse_another_canvas_and_a_non_model(tmp_path):
    with pytest.raises(ValueError, match=r"\[128, 112\] px canvases, the data are \[64, 64\]"):
        teacher_targets(MODEL, _canvases(1, (64, 64)))
    bad = tmp_path / "model.onnx"
    bad.write_text("not a model")
    with pytest.raises(ValueError, match="not a readable ONNX model"):
        teacher_targets(bad, _canvases(1))


def test_distill_from_a_missing_file_is_one_line(capsys, tmp_path):
    with pytest.raises(SystemExit):
        main(["--data-only", "--distill-from", str(tmp_path / "nosuch.onnx")])
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].endswith(f"--distill-from: no such ONNX model file: {tmp_path / 'nosuch.onnx'}")
