"""Weight-space interpolation of two ONNX models (drake_rus.imaging.training.interpolate) on
tiny graphs built with onnx.helper (no torch)."""

import hashlib
import json
import os

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")
from onnx import TensorProto, helper, numpy_helper  # noqa: E402

from drake_rus.imaging.training.interpolate import (  # noqa: E402
    interpolate_models,
    main,
    pair_initializers,
)

X = np.array([[0.3, -1.2, 2.0], [1.5, 0.25, -0.7]], np.float32)


def linear_model(path, w, b, names=("W", "b"), op="Add", w_dtype=np.float32, swap=False):
    """y = reshape(x @ W + b, [-1]): linear in the weights; an int64 shape initializer."""
    wn, bn = names
    add_in = [bn, "xw"] if swap else ["xw", bn]
    nodes = [
        helper.make_node("MatMul", ["x", wn], ["xw"], name="mm"),
        helper.make_node(op, add_in, ["z"], name="add"),
        helper.make_node("Reshape", ["z", "shape"], ["y"], name="flat"),
    ]
    inits = [
        numpy_helper.from_array(np.asarray(w, w_dtype), wn),
        numpy_helper.from_array(np.asarray(b, np.float32), bn),
        numpy_helper.from_array(np.array([-1], np.int64), "shape"),
    ]
    elem = TensorProto.DOUBLE if w_dtype == np.float64 else TensorProto.FLOAT
    graph = helper.make_graph(
        nodes,
        "linear",
        [helper.make_tensor_value_info("x", elem, [2, 3])],
        [helper.make_tensor_value_info("y", elem, [8])],
        inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, str(path))
    return path


def run(path, x=X):
    s = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return s.run(None, {"x": x})[0]


def inits(path):
    return {t.name: numpy_helper.to_array(t) for t in onnx.load(str(path)).graph.initializer}


@pytest.fixture
def pair(tmp_path):
    rng = np.random.default_rng(0)
    a = linear_model(tmp_path / "a.onnx", rng.normal(size=(3, 4)), rng.normal(size=4))
    b = linear_model(
        tmp_path / "b.onnx",
        rng.normal(size=(3, 4)),
        rng.normal(size=4),
        names=("e1.0.weight", "e1.0.bias"),  # other names, the same places (BN folded / not)
    )
    card = {
        "model": "b.onnx",
        "pixel_size_mm": 2.4,
        "canvas_px": [128, 112],
        "scenario": {"onnx_model": "b.onnx"},
        "training": {"epochs": 8},
        "evaluation": {"iou": 0.9},
    }
    (tmp_path / "b.json").write_text(json.dumps(card))
    (tmp_path / "a.json").write_text(json.dumps({**card, "model": "a.onnx"}))
    return a, b


def test_alpha_0_and_1_give_a_and_b_exactly(pair, tmp_path):
    a, b = pair
    m0 = interpolate_models(a, b, 0.0, tmp_path / "o0", name="m")
    m1 = interpolate_models(a, b, 1.0, tmp_path / "o1", name="m")
    np.testing.assert_array_equal(run(m0), run(a))
    np.testing.assert_array_equal(run(m1), run(b))
    assert not np.allclose(run(a), run(b))  # the test can tell them apart


def test_alpha_half_is_the_mean_of_the_initializers_paired_by_place(pair, tmp_path):
    a, b = pair
    m = interpolate_models(a, b, 0.5, tmp_path / "o", name="m")
    ia, ib, im = inits(a), inits(b), inits(m)
    assert set(im) == {"e1.0.weight", "e1.0.bias", "shape"}  # B's names
    np.testing.assert_allclose(im["e1.0.weight"], (ia["W"] + ib["e1.0.weight"]) / 2, rtol=1e-6)
    np.testing.assert_allclose(im["e1.0.bias"], (ia["b"] + ib["e1.0.bias"]) / 2, rtol=1e-6)
    np.testing.assert_array_equal(im["shape"], [-1])  # not a float: copied
    assert im["e1.0.weight"].dtype == np.float32


@pytest.mark.parametrize("alpha", [0.25, 0.5, 0.75])
def test_outputs_of_a_linear_graph_interpolate_linearly(pair, tmp_path, alpha):
    a, b = pair
    m = interpolate_models(a, b, alpha, tmp_path / "o", name="m")
    np.testing.assert_allclose(run(m), (1 - alpha) * run(a) + alpha * run(b), rtol=1e-5, atol=1e-6)


def test_card_is_bs_with_the_interpolation_record(pair, tmp_path):
    a, b = pair
    m = interpolate_models(a, b, 0.25, tmp_path / "o", name="m", command="cmd")
    card = json.loads(m.with_suffix(".json").read_text())
    assert card["model"] == "m.onnx"
    assert card["scenario"]["onnx_model"] == str(m.resolve())
    assert "evaluation" not in card  # B's figures do not describe the new model
    assert card["training"]["epochs"] == 8
    rec = card["training"]["interpolation"]
    assert rec["alpha"] == 0.25
    assert rec["model_a"] == str(a.resolve()) and rec["model_b"] == str(b.resolve())
    assert rec["model_a_sha256"] == hashlib.sha256(a.read_bytes()).hexdigest()
    assert rec["model_b_sha256"] == hashlib.sha256(b.read_bytes()).hexdigest()
    assert rec["command"] == "cmd"


def test_a_mix_of_mixes_keeps_every_record(pair, tmp_path):
    # A soup (the mean of two fine-tunes) mixed again with the original: the second card
    # keeps the first mix's record, so the weights trace back to trained models.
    a, b = pair
    soup = interpolate_models(a, b, 0.5, tmp_path / "soup", name="m")
    mix = interpolate_models(a, soup, 0.75, tmp_path / "mix", name="m")
    rec = json.loads(mix.with_suffix(".json").read_text())["training"]["interpolation"]
    assert rec["alpha"] == 0.75 and rec["model_b"] == str(soup.resolve())
    inner = rec["model_b_interpolation"]
    assert inner["alpha"] == 0.5
    assert inner["model_a"] == str(a.resolve()) and inner["model_b"] == str(b.resolve())
    assert "model_a_interpolation" not in rec  # a has a trained model's card
    assert "model_b_interpolation" not in inner


def test_the_record_keeps_a_mixed_original_for_the_fine_tune_too(pair):
    # The fine-tune's mix passes its original's card: a mixed original keeps its record.
    from drake_rus.imaging.training.interpolate import interpolation_record

    a, b = pair
    soup_card = {"training": {"interpolation": {"alpha": 0.5, "model_a": "s0", "model_b": "s1"}}}
    rec = interpolation_record(a, b, 0.75, card_a=soup_card, card_b={"training": {}})
    assert rec["model_a_interpolation"] == {"alpha": 0.5, "model_a": "s0", "model_b": "s1"}
    assert "model_b_interpolation" not in rec
    rec["model_a_interpolation"]["alpha"] = 1.0  # a copy: the source card is untouched
    assert soup_card["training"]["interpolation"]["alpha"] == 0.5


def test_pairs_follow_the_graph_not_the_names(tmp_path):
    # B names its weight "b" and its bias "W": pairing by name would cross them.
    a = linear_model(tmp_path / "a.onnx", np.ones((3, 4)), np.zeros(4))
    b = linear_model(tmp_path / "b.onnx", np.ones((3, 4)), np.zeros(4), names=("b", "W"))
    assert pair_initializers(onnx.load(str(a)), onnx.load(str(b))) == [
        ("W", "b"),
        ("b", "W"),
        ("shape", "shape"),
    ]


def listing(folder):
    return sorted(os.listdir(folder)) if folder.exists() else None


def assert_refused(a, b, alpha, out, match):
    before = listing(out)
    with pytest.raises(ValueError, match=match):
        interpolate_models(a, b, alpha, out, name="m")
    assert listing(out) == before  # nothing half-written, no temporary left


@pytest.mark.parametrize("alpha", [-0.1, 1.5, float("nan"), float("inf"), "x", None, True])
def test_alpha_outside_0_1_is_refused(pair, tmp_path, alpha):
    a, b = pair
    assert_refused(a, b, alpha, tmp_path / "o", "alpha")


@pytest.mark.parametrize(
    "kind, match",
    [
        ("op", "operator Add in model A, Sub in model B"),
        ("shape", "initializer W of model A is \\[3, 4\\]"),
        ("dtype", "type"),
        ("wiring", "wired differently"),
        ("nodes", "5 nodes in model A, 3 in model B"),
    ],
)
def test_graphs_that_differ_are_refused(pair, tmp_path, kind, match):
    a, _ = pair
    rng = np.random.default_rng(1)
    w, bias = rng.normal(size=(3, 4)), rng.normal(size=4)
    b = tmp_path / "other.onnx"
    if kind == "op":
        linear_model(b, w, bias, op="Sub")
    elif kind == "shape":
        b = linear_model(tmp_path / "a5.onnx", rng.normal(size=(3, 5)), rng.normal(size=5))
        a, b = a, b
    elif kind == "dtype":
        linear_model(b, w, bias, w_dtype=np.float64)
    elif kind == "wiring":
        linear_model(b, w, bias, swap=True)
    elif kind == "nodes":
        m = onnx.load(str(a))
        m.graph.node.extend(
            [
                helper.make_node("Relu", ["y"], ["r"]),
                helper.make_node("Neg", ["r"], ["n"]),
            ]
        )
        a = tmp_path / "longer.onnx"
        onnx.save(m, str(a))
        linear_model(b, w, bias)
    out = tmp_path / "o"
    out.mkdir()
    (out / "keep.txt").write_text("an older file")
    assert_refused(a, b, 0.5, out, match)
    assert (out / "keep.txt").read_text() == "an older file"


def test_a_missing_file_is_refused(pair, tmp_path):
    a, b = pair
    assert_refused(
        tmp_path / "nope.onnx", b, 0.5, tmp_path / "o", "model_a: ONNX model file not found"
    )
    assert_refused(
        a, tmp_path / "nope.onnx", 0.5, tmp_path / "o", "model_b: ONNX model file not found"
    )


def test_a_file_that_is_not_onnx_is_refused(pair, tmp_path):
    a, _ = pair
    bad = tmp_path / "bad.onnx"
    bad.write_text("not a model\n")
    assert_refused(a, bad, 0.5, tmp_path / "o", "model_b: .*is not an ONNX model")


def test_a_quantized_model_is_refused(pair, tmp_path):
    a, _ = pair
    w8 = numpy_helper.from_array(np.ones((3, 4), np.int8), "W8")
    scale = numpy_helper.from_array(np.array(0.1, np.float32), "s")
    graph = helper.make_graph(
        [
            helper.make_node("DequantizeLinear", ["W8", "s"], ["W"]),
            helper.make_node("MatMul", ["x", "W"], ["y"]),
        ],
        "q",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [2, 3])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [2, 4])],
        [w8, scale],
    )
    q = tmp_path / "q.onnx"
    onnx.save(helper.make_model(graph), str(q))
    assert_refused(q, a, 0.5, tmp_path / "o", "model_a: .*quantized \\(int8\\).*then quantize")
    assert_refused(a, q, 0.5, tmp_path / "o", "model_b: .*quantized \\(int8\\)")


def test_cards_with_another_canvas_are_refused(pair, tmp_path):
    a, b = pair
    card = json.loads(a.with_suffix(".json").read_text())
    a.with_suffix(".json").write_text(json.dumps({**card, "canvas_px": [64, 64]}))
    assert_refused(a, b, 0.5, tmp_path / "o", "canvas_px")


def test_non_float_initializers_must_be_equal(pair, tmp_path):
    a, b = pair
    m = onnx.load(str(b))
    for t in m.graph.initializer:
        if t.name == "shape":
            t.CopyFrom(numpy_helper.from_array(np.array([8], np.int64), "shape"))
    other = tmp_path / "b_shape.onnx"
    onnx.save(m, str(other))
    assert_refused(a, other, 0.5, tmp_path / "o", "not floats .* and differ")


def test_out_may_not_overwrite_an_input(pair, tmp_path):
    a, b = pair
    before = b.read_bytes(), b.with_suffix(".json").read_bytes()
    with pytest.raises(ValueError, match="out: .* is model_b"):
        interpolate_models(a, b, 0.5, tmp_path, name="b")
    assert (b.read_bytes(), b.with_suffix(".json").read_bytes()) == before


def test_a_failure_while_writing_leaves_nothing(pair, tmp_path, monkeypatch):
    from drake_rus.imaging.training import interpolate

    def broken(path):
        assert path.is_file()  # staged, not yet in place
        raise RuntimeError("ONNX Runtime cannot load it")

    monkeypatch.setattr(interpolate, "_check_runs", broken)
    a, b = pair
    out = tmp_path / "o"
    out.mkdir()
    (out / "m.onnx").write_bytes(b"an older model")
    with pytest.raises(RuntimeError):
        interpolate_models(a, b, 0.5, out, name="m")
    assert listing(out) == ["m.onnx"]  # no temporary, no card
    assert (out / "m.onnx").read_bytes() == b"an older model"
    with pytest.raises(RuntimeError):
        interpolate_models(a, b, 0.5, tmp_path / "new", name="m")
    assert not (tmp_path / "new").exists()  # a folder it created is removed again


def test_command_line(pair, tmp_path, capsys):
    a, b = pair
    assert main([str(a), str(b), "--alpha", "0.75", "--out", str(tmp_path / "o")]) == 0
    assert (tmp_path / "o" / "kidney_unet.onnx").is_file()
    assert (tmp_path / "o" / "kidney_unet.json").is_file()
    assert main([str(a), str(b), "--alpha", "2", "--out", str(tmp_path / "p")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("interpolate: error: alpha") and "\n" not in err
    assert not (tmp_path / "p").exists()
