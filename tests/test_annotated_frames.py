"""Issue 31: bringing one's own frames. A folder of annotated frames in the Open Kidney
Ultrasound Data Set's mask layout is imported; ``scan --save-frames`` writes one that
imports again; bad folders get one line and exit status 2, and nothing is written."""

import csv
import json
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image
from pydrake.common.eigen_geometry import Quaternion
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix

from drake_rus.imaging.annotated import (
    FramesError,
    SavedFrame,
    read_annotated_frames,
    write_annotated_frames,
)
from drake_rus.paths import REPO_ROOT

SHAPE = (256, 256)


def _png(path, arr):
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.asarray(arr, np.uint8)).save(path)


def _frame(k):
    rng = np.random.default_rng(k)
    img = rng.integers(0, 255, SHAPE).astype(np.uint8)
    mask = np.zeros(SHAPE, np.uint8)
    mask[100 + k : 140 + k, 90:170] = 1  # the data set's capsule masks hold 1
    return img, mask


def make_folder(root, n=4, table=True, empty=()):
    for k in range(n):
        img, mask = _frame(k)
        if k in empty:
            mask[:] = 0
        _png(root / "images" / f"f{k:02d}.png", img)
        _png(root / "capsule" / f"f{k:02d}.png", mask)
    if table:
        with open(root / "frames.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["name", "kidney", "depth_m"])
            for k in range(n):
                w.writerow([f"f{k:02d}", 0 if k in empty else 1, 0.2])
    return root


def test_a_folder_in_the_open_kidney_layout_is_imported(tmp_path):
    root = make_folder(tmp_path / "frames", empty=(3,))
    # The data set's second mask (inner regions) may sit beside: not read.
    _png(root / "regions" / "f00.png", np.full(SHAPE, 2))
    f = read_annotated_frames(root, SHAPE)
    assert f.names == ["f00", "f01", "f02", "f03"]
    assert f.images.shape == (4,) + SHAPE and f.images.dtype == np.uint8
    for k in range(3):
        img, mask = _frame(k)
        np.testing.assert_array_equal(f.images[k], img)
        np.testing.assert_array_equal(f.masks[k], mask > 0)
    assert f.kidney.tolist() == [True, True, True, False]
    np.testing.assert_allclose(f.depth, 0.2)
    # Masks saved as 0/255 (other tools) read the same; no table: the depth is given.
    plain = tmp_path / "plain"
    img, mask = _frame(0)
    _png(plain / "images" / "a.png", np.stack([img] * 3, axis=-1))  # colour: made grey
    _png(plain / "capsule" / "a.png", mask * 255)
    g = read_annotated_frames(plain, SHAPE, depth=0.15)
    np.testing.assert_array_equal(g.masks[0], mask > 0)
    assert g.depth[0] == 0.15 and g.images[0].shape == SHAPE


@pytest.mark.parametrize(
    "spoil, expected",
    [
        (lambda r: (r / "capsule" / "f01.png").unlink(), "no mask"),
        (lambda r: _png(r / "capsule" / "f01.png", np.ones((128, 128))), "a mask has its image"),
        (lambda r: _png(r / "capsule" / "f02.png", np.zeros(SHAPE)), "no kidney pixel"),
        (lambda r: (r / "images" / "notes.txt").write_text("hello"), "not a PNG image"),
        (lambda r: (r / "images" / "f01.png").write_text("not a picture"), "not a readable PNG"),
        (
            lambda r: [_png(r / d / "f01.png", np.ones((200, 256))) for d in ("images", "capsule")],
            "on the probe's image grid, 256 x 256",
        ),
        (lambda r: (r / "frames.csv").write_text("name,kidney\nf00,maybe\n"), "must be 0 or 1"),
    ],
)
def test_bad_folders_get_one_line(tmp_path, spoil, expected):
    root = make_folder(tmp_path / "frames")
    spoil(root)
    with pytest.raises(FramesError) as e:
        read_annotated_frames(root, SHAPE)
    text = str(e.value)
    assert "\n" not in text
    assert expected in text


def test_a_spreadsheets_frames_csv_is_read(tmp_path):
    # A spreadsheet's "CSV UTF-8" starts with a byte-order mark, and a table typed by hand
    # may put a space after each comma: the columns are still known by their names, so the
    # kidney-free mark and the depths are not silently dropped.
    root = make_folder(tmp_path / "frames", table=False, empty=(3,))
    rows = "".join(f"f{k:02d}, {0 if k == 3 else 1}, 0.2\n" for k in range(4))
    (root / "frames.csv").write_text("\ufeffname, kidney, depth_m\n" + rows, encoding="utf-8")
    f = read_annotated_frames(root, SHAPE, depth=0.15)
    assert f.kidney.tolist() == [True, True, True, False]
    np.testing.assert_allclose(f.depth, 0.2)


def test_an_empty_mask_needs_the_frame_marked_kidney_free(tmp_path):
    root = make_folder(tmp_path / "frames", table=False, empty=(1,))
    with pytest.raises(FramesError, match="no kidney pixel"):
        read_annotated_frames(root, SHAPE, depth=0.15)
    with pytest.raises(FramesError, match="no imaging depth"):
        read_annotated_frames(make_folder(tmp_path / "nodepth", table=False), SHAPE)


def test_saved_frames_import_again(tmp_path):
    frames = []
    for k in range(5):
        img, mask = _frame(k)
        X = RigidTransform(RollPitchYaw(0.1 * k, 3.0, 0.2), [0.5, 0.01 * k, 0.2])
        frames.append(
            SavedFrame(img, mask > 0 if k != 2 else mask * 0, 0.05 * k, 10 + k, "PIVOT", k != 2, X)
        )
    out = write_annotated_frames(tmp_path / "saved", frames, depth=0.25)
    f = read_annotated_frames(out, SHAPE)
    assert f.names == [f"{10 + k:06d}" for k in range(5)]
    assert f.kidney.tolist() == [True, True, False, True, True]
    np.testing.assert_allclose(f.depth, 0.25)
    for k in range(5):
        np.testing.assert_array_equal(f.images[k], frames[k].image)
        np.testing.assert_array_equal(f.masks[k], np.asarray(frames[k].mask, bool))
        row = f.rows[k]
        p = [float(row[c]) for c in ("p_BP_x_m", "p_BP_y_m", "p_BP_z_m")]
        q = [float(row[c]) for c in ("q_BP_w", "q_BP_x", "q_BP_y", "q_BP_z")]
        np.testing.assert_allclose(p, frames[k].X_BP.translation(), atol=1e-6)
        R = RotationMatrix(Quaternion(np.array(q) / np.linalg.norm(q))).matrix()
        np.testing.assert_allclose(R, frames[k].X_BP.rotation().matrix(), atol=1e-6)
        assert float(row["time_s"]) == pytest.approx(0.05 * k) and row["phase"] == "PIVOT"
    # Never into a folder that holds something; nothing half-written is left behind.
    with pytest.raises(FramesError, match="not an empty folder"):
        write_annotated_frames(out, frames, depth=0.25)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["saved"]


def _cli(*args):
    return subprocess.run(
        [sys.executable, "-m", "drake_rus.cli", *args],
        capture_output=True,
        text=True,
        cwd=REPO_ROOT,
        timeout=300,
    )


def test_the_command_line_refuses_a_bad_folder_in_one_line_and_writes_nothing(tmp_path):
    root = make_folder(tmp_path / "frames")
    _png(root / "capsule" / "f01.png", np.ones((100, 100)))
    out = tmp_path / "model"
    for cmd in (
        ["segmenter", "fine-tune", "--frames", str(root), "--out", str(out)],
        ["segmenter", "check-frames", "--frames", str(root)],
    ):
        r = _cli(*cmd)
        assert r.returncode == 2, r.stderr
        lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
        assert len(lines) == 1 and "capsule/f01.png" in lines[0], r.stderr
        assert "Traceback" not in r.stderr
    assert not out.exists()
    ok = _cli("segmenter", "check-frames", "--frames", str(make_folder(tmp_path / "good")))
    assert ok.returncode == 0 and "4 frames (4 with the kidney)" in ok.stdout


def test_fine_tuning_writes_a_model_a_scenario_selects(tmp_path):
    pytest.importorskip("torch")
    pytest.importorskip("onnx")
    from drake_rus.imaging.annotated import read_annotated_frames
    from drake_rus.imaging.config import ImagingConfig
    from drake_rus.imaging.systems import Segmenter
    from drake_rus.imaging.training.fine_tune import fine_tune, held_out_split
    from drake_rus.scenario import ApplyOverrides, Scenario

    assert [x.tolist() for x in held_out_split(10, 0.2)] == [list(range(8)), [8, 9]]
    with pytest.raises(ValueError):
        held_out_split(1, 0.2)
    frames = read_annotated_frames(make_folder(tmp_path / "frames", n=5), SHAPE)
    card = fine_tune(frames, ImagingConfig(), tmp_path / "model", epochs=1, log=lambda s: None)
    ev = card["evaluation"]
    assert ev["before_model"] == "kidney_unet_int8.onnx"
    assert 0.0 <= ev["held_out_iou_before"] <= 1.0 and 0.0 <= ev["held_out_iou_after"] <= 1.0
    assert card["fine_tuning"]["held_out_frames"] == ["f04"]
    assert card["fine_tuned_from"]["model"].endswith("kidney_unet.onnx")
    model = tmp_path / "model" / "kidney_unet_finetuned.onnx"
    assert model.is_file() and model.with_suffix(".json").is_file()
    # The held-out frame shows the kidney: no false-positive rate was measured, and the card
    # (valid JSON) says null, not 0.0.
    written = json.loads(
        model.with_suffix(".json").read_text(), parse_constant=lambda c: pytest.fail(c)
    )
    assert written["evaluation"]["after"]["false_positive_rate"] is None
    assert not any(p.name.endswith(".partial") for p in tmp_path.iterdir())
    # imaging.onnx_model selects it; the card beside it gives the physical canvas.
    scenario = ApplyOverrides(Scenario(), "{imaging: {onnx_model: %s}}" % model)
    seg = Segmenter(scenario.imaging)
    assert seg.GetInputPort("kidney_surface") is not None


def test_held_out_iou_says_not_measured_without_kidney_free_frames(tmp_path):
    """frames_iou (the shipped model, no torch): the false-positive rate is NaN when every
    frame shows the kidney, and a share when some do not."""
    from drake_rus.imaging.annotated import read_annotated_frames
    from drake_rus.imaging.config import ImagingConfig
    from drake_rus.imaging.training.fine_tune import frames_iou

    model = REPO_ROOT / "models" / "segmenter" / "kidney_unet.onnx"
    all_kidney = read_annotated_frames(make_folder(tmp_path / "a", n=2), SHAPE)
    r = frames_iou(model, all_kidney, ImagingConfig())
    assert r["frames_without_kidney"] == 0 and np.isnan(r["false_positive_rate"])
    some_empty = read_annotated_frames(make_folder(tmp_path / "b", n=3, empty=(2,)), SHAPE)
    r = frames_iou(model, some_empty, ImagingConfig())
    assert r["frames_without_kidney"] == 1 and r["false_positive_rate"] in (0.0, 1.0)


def test_fine_tuning_takes_the_boundary_band(tmp_path, monkeypatch):
    """--boundary-band-mm reaches the training as (canvas pixel size, band, gain) in m and
    is named in the card's loss; 0 trains unweighted; a negative band is refused."""
    pytest.importorskip("torch")
    pytest.importorskip("onnx")
    from drake_rus.imaging.annotated import read_annotated_frames
    from drake_rus.imaging.config import ImagingConfig
    from drake_rus.imaging.training import fine_tune as ft

    seen = []
    real_train = ft.train

    def spy(*args, **kwargs):
        seen.append(kwargs.get("boundary"))
        return real_train(*args, **kwargs)

    monkeypatch.setattr(ft, "train", spy)
    frames = read_annotated_frames(make_folder(tmp_path / "frames", n=5), SHAPE)
    card = ft.fine_tune(
        frames,
        ImagingConfig(),
        tmp_path / "band",
        epochs=1,
        boundary_band_mm=5.0,
        boundary_gain=2.0,
        log=lambda s: None,
    )
    assert seen[-1] == pytest.approx((2.4e-3, 5e-3, 2.0))
    assert "within 5 mm" in card["fine_tuning"]["loss"]
    with pytest.raises(ValueError, match="--boundary-band-mm"):
        ft.fine_tune(frames, ImagingConfig(), tmp_path / "bad", boundary_band_mm=-1.0)
    assert not (tmp_path / "bad").exists()


def test_fine_tuning_can_mix_the_fine_tune_with_the_original(tmp_path):
    """--interpolate 0.5 writes the weight-by-weight mean of the original fp32 model and
    the fine-tune (written beside it as NAME_alone.onnx), and the card gives both IoUs."""
    pytest.importorskip("torch")
    onnx = pytest.importorskip("onnx")
    from onnx import numpy_helper

    from drake_rus.imaging.annotated import read_annotated_frames
    from drake_rus.imaging.config import ImagingConfig
    from drake_rus.imaging.training.fine_tune import fine_tune, trainable_source
    from drake_rus.imaging.training.interpolate import pair_initializers, sha256

    frames = read_annotated_frames(make_folder(tmp_path / "frames", n=5), SHAPE)
    for bad in (0.0, 1.5, float("nan")):
        with pytest.raises(ValueError, match="--interpolate"):
            fine_tune(frames, ImagingConfig(), tmp_path / "bad", interpolate=bad)
    assert not (tmp_path / "bad").exists()
    out = tmp_path / "mixed"
    card = fine_tune(frames, ImagingConfig(), out, epochs=1, interpolate=0.5, log=lambda s: None)
    mixed_path = out / "kidney_unet_finetuned.onnx"
    alone_path = out / "kidney_unet_finetuned_alone.onnx"
    assert alone_path.with_suffix(".json").is_file() and mixed_path.with_suffix(".json").is_file()
    source = trainable_source(ImagingConfig().onnx_model)
    rec = card["training"]["interpolation"]
    assert rec["alpha"] == 0.5 and rec["model_a_sha256"] == sha256(source)
    assert rec["model_b_sha256"] == sha256(alone_path)
    assert rec["model_b"] == str(alone_path.resolve())
    original, alone, mixed = (onnx.load(str(p)) for p in (source, alone_path, mixed_path))
    by_name = {
        m: {t.name: numpy_helper.to_array(t) for t in g.graph.initializer}
        for m, g in (("o", original), ("a", alone), ("m", mixed))
    }
    pairs = pair_initializers(original, alone)
    assert pairs and all(n_b in by_name["m"] for _, n_b in pairs)
    moved = 0
    for n_o, n_a in pairs:
        o, a, m = by_name["o"][n_o], by_name["a"][n_a], by_name["m"][n_a]
        np.testing.assert_allclose(m, 0.5 * (o + a), rtol=1e-6, atol=1e-7)
        moved += not np.allclose(o, a)
    assert moved > 0  # the fine-tune moved the weights: the mean is neither model
    ev = card["evaluation"]
    assert 0.0 <= ev["held_out_iou_fine_tune_alone"] <= 1.0
    assert ev["held_out_iou_after"] == round(ev["after"]["iou"], 4)
    alone_card = json.loads(alone_path.with_suffix(".json").read_text())
    assert alone_card["model"] == alone_path.name
    assert alone_card["evaluation"]["held_out_iou_after"] == ev["held_out_iou_fine_tune_alone"]
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [mixed_path.name, alone_path.name, "kidney_unet_finetuned.json"]
        + ["kidney_unet_finetuned_alone.json"]
    )


def test_the_command_line_refuses_a_bad_interpolation_weight(tmp_path):
    root = make_folder(tmp_path / "frames")
    out = tmp_path / "model"
    r = _cli(
        "segmenter", "fine-tune", "--frames", str(root), "--out", str(out), "--interpolate", "0"
    )
    assert r.returncode == 2
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "--interpolate" in lines[0], r.stderr
    assert not out.exists()


@pytest.mark.parametrize("name", ["sub/model", "", ".hidden"])
def test_the_command_line_refuses_a_model_name_with_a_folder_before_training(tmp_path, name):
    # --name is a file name in --out: a folder in it made the run train, then fail to move
    # the model into place and leave its temporary folders behind.
    root = make_folder(tmp_path / "frames")
    out = tmp_path / "model"
    r = _cli(
        "segmenter", "fine-tune", "--frames", str(root), "--out", str(out), "--name", name,
        "--epochs", "1",
    )  # fmt: skip
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "--name" in lines[0], r.stderr
    assert "epoch" not in r.stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames"]
