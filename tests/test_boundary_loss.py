"""The boundary-aware training loss option (train_segmenter --boundary-band-mm)."""

import numpy as np
import pytest
from conftest import tiny_training_frames

from drake_rus.imaging.training.train_segmenter import boundary_band_weight, main

P = 2.4e-3  # canvas pixel (m)


def _square(n=16, lo=4, hi=12, shift=0):
    t = np.zeros((1, n, n), np.float32)
    t[0, lo:hi, lo + shift : hi + shift] = 1.0
    return t


def test_band_weight_marks_the_pixels_within_the_band_of_the_edge():
    t = _square()
    # 3 mm: the centres 1.2 mm from the edge (the first pixel on either side), not 3.6 mm.
    w = boundary_band_weight(t, P, 3e-3, 4.0)
    row = w[0, 8]
    assert row.tolist() == [1, 1, 1, 5, 5, 1, 1, 1, 1, 1, 1, 5, 5, 1, 1, 1]
    # 5 mm reaches the second pixel on either side; the square's centre stays at 1.
    w5 = boundary_band_weight(t, P, 5e-3, 4.0)
    assert w5[0, 8].tolist() == [1, 1, 5, 5, 5, 5, 1, 1, 1, 1, 5, 5, 5, 5, 1, 1]
    # Symmetric about the edge: as many weighted pixels inside as outside (far from corners).
    assert (w5[0] > 1)[t[0] > 0.5].sum() > 0 and (w5[0] > 1)[t[0] <= 0.5].sum() > 0


def test_band_weight_is_one_without_an_edge_and_the_canvas_border_is_no_edge():
    empty = np.zeros((2, 8, 8), np.float32)
    assert np.all(boundary_band_weight(empty, P, 5e-3, 4.0) == 1.0)
    full = np.ones((1, 8, 8), np.float32)
    assert np.all(boundary_band_weight(full, P, 5e-3, 4.0) == 1.0)
    # A kidney cut by the canvas's bottom: only its top edge is weighted.
    t = np.zeros((1, 10, 10), np.float32)
    t[0, 6:, :] = 1.0
    w = boundary_band_weight(t, P, 3e-3, 2.0)
    assert w[0, :, 5].tolist() == [1, 1, 1, 1, 1, 3, 3, 1, 1, 1]
    # A soft target (area fraction) counts as kidney above 0.5.
    soft = t * 0.4
    assert np.all(boundary_band_weight(soft, P, 3e-3, 2.0) == 1.0)


def test_band_weight_rejects_bad_arguments():
    with pytest.raises(ValueError, match="boundary band"):
        boundary_band_weight(_square(), 0.0, 5e-3, 4.0)
    with pytest.raises(ValueError, match="boundary band"):
        boundary_band_weight(_square(), P, -1e-3, 4.0)


def _loss(mask, target, weight=None):
    import torch

    from drake_rus.imaging.training.train_segmenter import segmentation_loss

    logits = torch.from_numpy((6.0 * (2 * mask - 1))[:, None])
    w = None if weight is None else torch.from_numpy(weight[:, None])
    return float(segmentation_loss(logits, torch.from_numpy(target[:, None]), w))


def test_loss_is_lower_for_the_right_edge_than_for_one_shifted_a_pixel():
    pytest.importorskip("torch")
    t = _square()
    w = boundary_band_weight(t, P, 5e-3, 4.0)
    right, shifted = _loss(t, t), _loss(_square(shift=1), t)
    right_w, shifted_w = _loss(t, t, w), _loss(_square(shift=1), t, w)
    assert right < shifted and right_w < shifted_w
    # The band weights make the one-pixel shift cost more than the plain loss does.
    assert shifted_w - right_w > shifted - right
    # With unit weights the weighted loss is the plain one (the shipped recipe).
    assert _loss(_square(shift=1), t, np.ones_like(t)) == pytest.approx(shifted)


def test_train_with_the_band_runs_and_the_cli_rejects_a_negative_band(capsys):
    pytest.importorskip("torch")
    from drake_rus.imaging.training.train_segmenter import train

    X, Y = tiny_training_frames(4)
    logs = []
    net = train(
        X,
        Y,
        width=4,
        epochs=1,
        batch=4,
        log=logs.append,
        space_to_depth=2,
        boundary=(P, 5e-3, 4.0),
    )
    assert net.epochs_run == 1 and "loss" in logs[0]
    with pytest.raises(SystemExit) as e:
        main(["--boundary-band-mm", "-1", "--data-only"])
    assert e.value.code == 2
    assert "--boundary-band-mm" in capsys.readouterr().err
