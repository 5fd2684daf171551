"""The pivot-view benchmark (benchmarks/segmenter_pivot.py): the pivot's angles and legs,
where the true kidney leaves the image, the registration draw, the per-frame scores, the
paired totals, the Segmenter's own work on a sweep, and bad arguments."""

import json
import math
import shutil

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw

from benchmarks.segmenter_pivot import (
    PivotFrame,
    frame_scores,
    in_view_ends,
    perturbed_pose,
    pivot_angles,
    segment_sweep,
    summarise,
)
from benchmarks.segmenter_pivot import main as segmenter_pivot_main
from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.emulator import EmulatorModel
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.imaging.training.evaluation import make_source_frames
from drake_rus.paths import REPO_ROOT


def test_pivot_angles_two_legs_past_each_end_and_through_the_start():
    angles, leg = pivot_angles(0.2, -0.1, 0.01, 0.05, 0.6)
    assert angles[0] == 0.0 and leg[0] == 1
    first = angles[leg == 1]
    second = angles[leg == 2]
    assert first[-1] == pytest.approx(0.25)  # the end plus the margin
    assert second[-1] == pytest.approx(-0.15)
    assert np.all(np.diff(first) > 0) and np.all(np.diff(second) < 0)
    np.testing.assert_allclose(np.abs(np.diff(angles)), 0.01, atol=1e-12)
    # The reversal frame is not taken twice, and leg 2 passes the start.
    assert second[0] == pytest.approx(first[-1] - 0.01)
    assert np.any(np.isclose(second, 0.0))


def test_pivot_angles_stop_at_the_maximum_tilt():
    angles, _ = pivot_angles(0.58, -0.7, 0.01, 0.05, 0.6)
    assert angles.max() == pytest.approx(0.6) and angles.min() == pytest.approx(-0.6)
    assert np.all(np.abs(angles) <= 0.6 + 1e-12)


@pytest.mark.parametrize(
    "args, field",
    [((0.2, -0.1, 0.0, 0.05, 0.6), "step"), ((-0.1, -0.1, 0.01, 0.05, 0.6), "first_end")],
)
def test_pivot_angles_refuses_bad_input(args, field):
    with pytest.raises(ValueError, match=field):
        pivot_angles(*args)


def test_in_view_ends_walk_out_from_the_start():
    angles = np.round(np.arange(-0.5, 0.5001, 0.1), 10)
    #          -0.5 -0.4 -0.3 -0.2 -0.1  0  0.1  0.2  0.3  0.4  0.5
    areas = np.array([5, 0, 0, 3, 4, 9, 8, 2, 0, 7, 7], float)
    # The section beyond the gap on either side (another organ's, or the far kidney's) is not
    # this pivot's: the walk stops at the first angle without kidney.
    assert in_view_ends(angles, areas) == (pytest.approx(0.2), pytest.approx(-0.2))
    assert in_view_ends(angles, np.where(angles == 0, 0.0, areas)) is None


def test_perturbed_pose_is_a_draw_of_the_stated_size():
    X = RigidTransform(RollPitchYaw(0.1, -0.2, 0.3), [0.1, 0.2, 0.3])
    same = perturbed_pose(X, np.random.default_rng(1), (0.0, 0.0))
    assert np.allclose(same.GetAsMatrix4(), X.GetAsMatrix4())
    a = perturbed_pose(X, np.random.default_rng(2))
    b = perturbed_pose(X, np.random.default_rng(2))
    assert np.allclose(a.GetAsMatrix4(), b.GetAsMatrix4())
    moves, turns = [], []
    for s in range(400):
        Y = perturbed_pose(X, np.random.default_rng(s), (0.002, math.radians(3.0)))
        moves.append(Y.translation() - X.translation())
        turns.append(X.rotation().inverse().multiply(Y.rotation()).ToAngleAxis().angle())
    assert np.std(np.asarray(moves)) == pytest.approx(0.002, rel=0.15)
    # Three axes of 3 deg each: a Maxwell-distributed angle, mean 2 sqrt(2/pi) x 3 deg.
    assert np.mean(turns) == pytest.approx(math.radians(3.0) * 2 * math.sqrt(2 / math.pi), rel=0.1)


def test_frame_scores_kinds_and_iou():
    truth = np.zeros((10, 10), bool)
    mask = np.zeros((10, 10), bool)
    assert frame_scores(False, mask, truth, 4) == {"kind": "free", "marked": False, "iou": None}
    truth[0, :2] = True
    assert frame_scores(True, mask, truth, 4)["kind"] == "edge"
    truth[:2, :4] = True  # 8 pixels
    mask[:2, 2:6] = True  # 4 of them and 4 more
    s = frame_scores(True, mask, truth, 4)
    assert s["kind"] == "in_view" and s["iou"] == pytest.approx(4 / 12)


def test_summarise_pairs_the_models_frame_by_frame():
    kinds = ["free"] * 4 + ["in_view"] * 4 + ["edge"]
    a = [
        {"kind": k, "marked": k == "in_view", "iou": 0.8 if k == "in_view" else None} for k in kinds
    ]
    b = [dict(r) for r in a]
    b[0]["marked"] = True  # one more false mark
    b[4]["marked"], b[4]["iou"] = False, 0.0  # one miss
    clusters = ["p1"] * 2 + ["p2"] * 2 + ["p1"] * 2 + ["p2"] * 3
    t = summarise({"A": a, "B": b}, clusters, ["A", "B"])
    assert t["A"]["kidney_free"] == t["B"]["kidney_free"] == 4
    assert (t["A"]["marked"], t["B"]["marked"]) == (0, 1)
    assert (t["A"]["missed"], t["B"]["missed"]) == (0, 1)
    assert t["B"]["false_mark_share"]["difference"] == pytest.approx(0.25)
    assert t["B"]["miss_share"]["difference"] == pytest.approx(0.25)
    assert t["B"]["iou"]["difference"] == pytest.approx(-0.2)
    assert t["A"]["iou"]["difference"] == 0.0


def test_segment_sweep_marks_the_kidney_and_not_an_empty_frame():
    """The Segmenter's own work on a short sweep: a frame with a kidney is marked with a
    mask that overlaps it; blank frames are not; with the kidney's true section as the
    template's prior the same kidney is kept."""
    cfg = ImagingConfig(depth=0.15, segmenter="onnx")
    g = ProbeGeometry.from_config(cfg)
    views = make_source_frames("phantom:5001", EmulatorModel.from_config(cfg, g), 6, seed=1)
    us, truth = max(views, key=lambda v: v[1].sum())[:2]
    blank = np.zeros(g.image_shape, np.uint8)
    frames = [
        PivotFrame(image, t, i / cfg.frame_rate_hz, RigidTransform())
        for i, (image, t) in enumerate([(us, truth), (blank, np.zeros_like(truth)), (us, truth)])
    ]
    out = segment_sweep(frames, cfg, g, None)
    assert [v for v, _ in out] == [True, False, True]
    iou = np.count_nonzero(out[0][1] & truth) / np.count_nonzero(out[0][1] | truth)
    assert iou > 0.5
    assert not out[1][1].any()


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--patients", "5"], "--patients: expected A..B"),
        (["--draws", "0"], "--draws: expected 1 or more"),
        (["--margin", "0.9"], "--margin: expected 0 to 0.5 rad"),
        (["--compare-models", "/nonexistent.onnx"], "ONNX model file not found: /nonexistent"),
        (["--compare-models", "a,,b"], "--compare-models: expected comma-separated"),
    ],
)
def test_bad_arguments_give_one_line(argv, message, capsys):
    assert segmenter_pivot_main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


@pytest.mark.slow
def test_one_patient_two_copies_of_a_model_pair_exactly(tmp_path, capsys):
    """The whole benchmark on one validation patient, the scenario's model against a copy
    of itself: the same frames, so the same counts and zero paired differences; the pivot
    sees both kidney-free frames and frames with the kidney."""
    model = REPO_ROOT / "models/segmenter/kidney_unet_int8.onnx"
    copy = tmp_path / "copy.onnx"
    shutil.copy(model, copy)
    shutil.copy(model.with_suffix(".json"), copy.with_suffix(".json"))  # its card
    assert (
        segmenter_pivot_main(
            ["--patients", "30..30", "--compare-models", str(copy), "--no-progress"]
        )
        == 0
    )
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    rows = out["models"]
    assert len(rows) == 2 and out["pivots"] == 2
    ref, other = rows[out["reference"]], rows[str(copy)]
    for key in ("kidney_free", "marked", "in_view", "missed"):
        assert ref[key] == other[key]
    assert ref["kidney_free"] > 10 and ref["in_view"] > 100
    assert other["iou"]["difference"] == 0.0 and other["false_mark_share"]["difference"] == 0.0
    assert ref["iou"]["mean"] > 0.7
