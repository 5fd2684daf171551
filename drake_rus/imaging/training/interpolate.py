"""Weight-space interpolation of two fp32 ONNX models of the same network (needs ``onnx``,
the ``train`` extra).

``interpolate_models(A, B, alpha, out)`` writes the model whose every float initializer is
``(1 - alpha) * A + alpha * B``: alpha 0 is A, 1 is B. Meant for a fine-tune B warm-started
from A (``train_segmenter --init A.onnx``): the two stay in one basin of the loss, and a
point between them often keeps A's accuracy on A's data and most of B's gain on the new
data, at the cost of one model (Wortsman et al., "Robust fine-tuning of zero-shot models",
CVPR 2022, WiSE-FT). Measured on the segmenter: ``docs/results/segmenter.md``.

    python -m drake_rus.imaging.training.interpolate models/segmenter/kidney_unet.onnx \\
        /tmp/ft/kidney_unet.onnx --alpha 0.5 --out /tmp/ft_half
    python -m drake_rus.imaging.training.quantize_segmenter \\
        --model /tmp/ft_half/kidney_unet.onnx --out /tmp/ft_half/kidney_unet_int8.onnx

Initializers are paired by their place in the graph (the node and input slot that first
reads them), not by name: the shipped model was exported with batch normalisation folded
(``onnx::Conv_158``, ...) and a fine-tune of it without (``e1.0.weight``, ...), the same
convolutions under other names. The two graphs must be the same network: the same nodes in
the same order (operator, attributes, wiring), and paired initializers of equal shape and
type; non-float initializers must be equal. The written graph is B's (its names), with the
interpolated values. The card (``NAME.json`` beside the model, what the ONNX backend reads)
is B's without its ``evaluation`` (which measured B), with ``training.interpolation``: both
source files and their SHA-256, alpha, the rule. Quantized (int8) models are refused:
interpolate the fp32 models, then quantize the result.

Written whole or not at all: the model and its card are staged in a temporary folder inside
``out``, checked to load and run in ONNX Runtime, then renamed into place; on any error
nothing new is left in ``out``.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import shlex
import sys
from pathlib import Path

import numpy as np

from drake_rus.anatomy.cache import file_digest
from drake_rus.extras import MissingExtra, require
from drake_rus.imaging.onnx_backend import cpu_session, read_model_card
from drake_rus.io_utils import staged_files

#: Operators of quantized graphs (QDQ or integer operator formats).
QUANTIZED_OPS = frozenset(
    {
        "QuantizeLinear",
        "DequantizeLinear",
        "DynamicQuantizeLinear",
        "QLinearConv",
        "QLinearMatMul",
        "QLinearAdd",
        "QLinearMul",
        "ConvInteger",
        "MatMulInteger",
    }
)

#: The card fields that say how the backend feeds the model: A's and B's must agree.
CANVAS_FIELDS = ("pixel_size_mm", "canvas_px", "canvas_top_mm", "input", "output")


def _onnx():
    require("onnx", "interpolate (reading and writing ONNX models)")
    import onnx
    from onnx import numpy_helper

    return onnx, numpy_helper


def check_alpha(alpha) -> float:
    """``alpha`` as a float in [0, 1], or ValueError naming it."""
    if isinstance(alpha, bool):
        raise ValueError(f"alpha: expected a number in [0, 1], got {alpha!r}")
    try:
        a = float(alpha)
    except (TypeError, ValueError):
        raise ValueError(f"alpha: expected a number in [0, 1], got {alpha!r}") from None
    if not (math.isfinite(a) and 0.0 <= a <= 1.0):
        raise ValueError(
            f"alpha: expected a weight in [0, 1] (0: model A, 1: model B), got {alpha!r}"
        )
    return a


def load_model(path: str | Path, label: str):
    """The ONNX model at ``path`` (``label`` names the argument in errors): ValueError when
    the file is missing, is not an ONNX model, or is quantized."""
    onnx, numpy_helper = _onnx()
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{label}: ONNX model file not found: {path}")
    try:
        model = onnx.load(str(path))
    except Exception as e:  # protobuf's DecodeError and onnx's own errors
        raise ValueError(f"{label}: {path} is not an ONNX model: {e}") from None
    if not model.graph.node:
        raise ValueError(f"{label}: {path} is not an ONNX model (no graph nodes)")
    try:
        onnx.checker.check_model(model)
    except onnx.checker.ValidationError as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ValueError(f"{label}: {path} is not a valid ONNX model: {first}") from None
    ops = sorted({n.op_type for n in model.graph.node} & QUANTIZED_OPS)
    ints = sorted(
        t.name
        for t in model.graph.initializer
        if t.data_type in (onnx.TensorProto.INT8, onnx.TensorProto.UINT8)
    )
    if ops or ints:
        what = f"operators {', '.join(ops)}" if ops else f"int8 initializers {ints[0]}, ..."
        raise ValueError(
            f"{label}: {path} is a quantized (int8) model ({what}); interpolate the fp32 "
            "models, then quantize the result (quantize_segmenter)"
        )
    return model


def _attribute(attr, numpy_helper):
    """A comparable value of a node attribute (tensors as dtype, shape and bytes)."""
    from onnx import AttributeProto, helper

    if attr.type == AttributeProto.TENSOR:
        a = numpy_helper.to_array(attr.t)
        return ("tensor", str(a.dtype), a.shape, a.tobytes())
    if attr.type in (AttributeProto.GRAPH, AttributeProto.GRAPHS):
        return ("graph", attr.SerializeToString())
    value = helper.get_attribute_value(attr)
    return tuple(value) if isinstance(value, list) else value


def _wiring(graph, numpy_helper) -> tuple[list, dict, list]:
    """The graph as a list of nodes (operator, domain, attributes, inputs, output count)
    whose inputs are named by place, not by name: a graph input by its index, a node output
    by (node, slot), an initializer by the (node, slot) that first reads it. Also the map
    from that place to the initializer's name, and the graph outputs by place."""
    inits = {t.name for t in graph.initializer}
    place = {}
    k = 0
    for v in graph.input:
        if v.name not in inits:
            place[v.name] = ("input", k)
            k += 1
    init_at = {}
    nodes = []
    for i, n in enumerate(graph.node):
        ins = []
        for j, name in enumerate(n.input):
            if name == "":
                ins.append("")
                continue
            if name not in place and name in inits:
                place[name] = ("initializer", i, j)
                init_at[("initializer", i, j)] = name
            ins.append(place.get(name, ("unknown", name)))
        for j, name in enumerate(n.output):
            place[name] = ("node", i, j)
        attrs = tuple(sorted((a.name, _attribute(a, numpy_helper)) for a in n.attribute))
        nodes.append((n.op_type, n.domain, attrs, tuple(ins), len(n.output)))
    outputs = [place.get(v.name, ("unknown", v.name)) for v in graph.output]
    unused = sorted(inits - set(init_at.values()))
    for name in unused:
        init_at[("unused", name)] = name
    return nodes, init_at, outputs


def pair_initializers(model_a, model_b) -> list[tuple[str, str]]:
    """(A's name, B's name) of each pair of initializers at the same place in the two
    graphs (B's order), or ValueError saying how the graphs differ (nodes, wiring,
    attributes, initializer shapes or types)."""
    _, numpy_helper = _onnx()
    na, ia, oa = _wiring(model_a.graph, numpy_helper)
    nb, ib, ob = _wiring(model_b.graph, numpy_helper)
    if len(na) != len(nb):
        raise ValueError(f"the graphs differ: {len(na)} nodes in model A, {len(nb)} in model B")
    for i, (a, b) in enumerate(zip(na, nb)):
        label = f"the graphs differ at node {i} ({model_b.graph.node[i].name or a[0]})"
        if a[:2] != b[:2]:
            raise ValueError(f"{label}: operator {a[0]} in model A, {b[0]} in model B")
        if a[2] != b[2]:
            raise ValueError(f"{label}: the {a[0]} attributes differ")
        if a[3:] != b[3:]:
            raise ValueError(f"{label}: the {a[0]} is wired differently")
    if oa != ob:
        raise ValueError("the graphs differ: their outputs come from other nodes")
    if set(ia) != set(ib):
        only = sorted(set(ia) ^ set(ib), key=str)[0]
        raise ValueError(
            "the graphs differ: an initializer of one has no counterpart in the other "
            f"({ia.get(only) or ib.get(only)})"
        )
    ta = {t.name: t for t in model_a.graph.initializer}
    tb = {t.name: t for t in model_b.graph.initializer}
    place_b = {v: k for k, v in ib.items()}
    pairs = []
    for t in model_b.graph.initializer:
        a, b = ta[ia[place_b[t.name]]], t
        if a.data_type != b.data_type or list(a.dims) != list(b.dims):
            raise ValueError(
                f"the graphs differ: initializer {a.name} of model A is {list(a.dims)} of "
                f"type {a.data_type}, its counterpart {b.name} of model B {list(b.dims)} "
                f"of type {b.data_type}"
            )
        pairs.append((a.name, tb[b.name].name))
    return pairs


def interpolate_arrays(a: np.ndarray, b: np.ndarray, alpha: float) -> np.ndarray:
    """``(1 - alpha) * a + alpha * b`` in float64, cast back to ``b``'s type; alpha 0 and 1
    give ``a`` and ``b`` exactly."""
    if alpha == 0.0:
        return a.copy()
    if alpha == 1.0:
        return b.copy()
    mix = (1.0 - alpha) * a.astype(np.float64) + alpha * b.astype(np.float64)
    return mix.astype(b.dtype)


def interpolated_model(model_a, model_b, alpha: float):
    """B's graph with every float initializer ``(1 - alpha) * A + alpha * B`` (pairs by
    :func:`pair_initializers`); other initializers must be equal. ValueError otherwise."""
    onnx, numpy_helper = _onnx()
    alpha = check_alpha(alpha)
    pairs = pair_initializers(model_a, model_b)
    ta = {t.name: t for t in model_a.graph.initializer}
    tb = {t.name: t for t in model_b.graph.initializer}
    floats = {onnx.TensorProto.FLOAT, onnx.TensorProto.DOUBLE, onnx.TensorProto.FLOAT16}
    out = copy.deepcopy(model_b)
    new = []
    for name_a, name_b in pairs:
        a = numpy_helper.to_array(ta[name_a])
        b = numpy_helper.to_array(tb[name_b])
        if tb[name_b].data_type in floats:
            for label, x, name in (("A", a, name_a), ("B", b, name_b)):
                if not np.all(np.isfinite(x)):
                    raise ValueError(f"model {label}: initializer {name} holds NaN or inf")
            value = interpolate_arrays(a, b, alpha)
        elif np.array_equal(a, b):
            value = b
        else:
            raise ValueError(
                f"the graphs differ: initializer {name_a} of model A and {name_b} of model "
                f"B are not floats ({b.dtype}) and differ (only floats are interpolated)"
            )
        new.append(numpy_helper.from_array(np.asarray(value), name=name_b))
    del out.graph.initializer[:]
    out.graph.initializer.extend(new)
    return out


#: SHA-256 (hex) of a file's bytes, as the patient cache and the model cards record it.
sha256 = file_digest


def interpolation_record(
    path_a: Path,
    path_b: Path,
    alpha: float,
    command: str = "",
    model_b_at: Path | None = None,
    card_a: dict | None = None,
    card_b: dict | None = None,
) -> dict:
    """The card's ``training.interpolation``: both sources, their SHA-256, alpha, the rule.
    ``model_b_at``: where B will be kept when ``path_b`` is a staging copy (its bytes are
    hashed here). ``card_a`` / ``card_b``: the sources' cards; a source that was itself a mix
    (a soup of seeds, say) keeps its own record under ``model_a_interpolation`` /
    ``model_b_interpolation``, so the card traces every weight back to trained models."""
    record = {
        "model_a": str(Path(path_a).resolve()),
        "model_a_sha256": sha256(path_a),
        "model_b": str(Path(model_b_at or path_b).resolve()),
        "model_b_sha256": sha256(path_b),
        "alpha": alpha,
        "rule": (
            "every float initializer (1 - alpha) * A + alpha * B, paired by their place in "
            "the graph (the node and input slot that first reads them); the graph, its "
            "names and this card's other fields are model B's"
        ),
        "method": "drake_rus.imaging.training.interpolate (WiSE-FT, Wortsman et al. 2022)",
        "command": command,
    }
    for label, card in (("model_a", card_a), ("model_b", card_b)):
        earlier = earlier_interpolation(card)
        if earlier is not None:
            record[f"{label}_interpolation"] = earlier
    return record


def interpolated_card(
    card_a: dict, card_b: dict, path_a: Path, path_b: Path, alpha: float, model: Path, command=""
) -> dict:
    """B's card for the interpolated ``model``: ``model`` and ``scenario.onnx_model`` name
    it, no ``evaluation`` (B's figures), and ``training.interpolation`` recording the
    sources, their SHA-256 and alpha (and, under ``model_a_interpolation`` /
    ``model_b_interpolation``, the record of a source that was itself a mix). ValueError
    when A's and B's cards give another canvas or input (the backend would feed the two
    models differently)."""
    for field in CANVAS_FIELDS:
        if card_a and card_b and card_a.get(field) != card_b.get(field):
            raise ValueError(
                f"the model cards differ in {field!r} ({card_a.get(field)!r} for model A, "
                f"{card_b.get(field)!r} for model B): the backend feeds them differently"
            )
    card = copy.deepcopy(card_b)
    card.pop("evaluation", None)
    card["model"] = model.name
    if isinstance(card.get("scenario"), dict):
        card["scenario"]["onnx_model"] = str(model.resolve())
    training = card.get("training") if isinstance(card.get("training"), dict) else {}
    training["interpolation"] = interpolation_record(
        path_a, path_b, alpha, command, card_a=card_a, card_b=card_b
    )
    card["training"] = training
    return card


def earlier_interpolation(card: dict | None) -> dict | None:
    """A copy of ``card``'s ``training.interpolation`` (the record of the mix the card's model
    is), or None for a trained model's card or no card."""
    training = (card or {}).get("training")
    record = training.get("interpolation") if isinstance(training, dict) else None
    return copy.deepcopy(record) if isinstance(record, dict) else None


def _check_runs(path: Path) -> None:
    """Loads the model in ONNX Runtime and runs it once on random inputs of its declared
    shapes (symbolic dimensions 1)."""
    s = cpu_session(path)
    rng = np.random.default_rng(0)
    feed = {}
    for i in s.get_inputs():
        shape = [d if isinstance(d, int) and d > 0 else 1 for d in i.shape]
        feed[i.name] = rng.random(shape).astype(np.float32)
    s.run(None, feed)


def interpolate_models(
    model_a: str | Path,
    model_b: str | Path,
    alpha: float,
    out: str | Path,
    name: str = "kidney_unet",
    command: str = "",
) -> Path:
    """Writes ``out/NAME.onnx``, the fp32 model whose every float initializer is
    ``(1 - alpha) * A + alpha * B`` (A = ``model_a``, B = ``model_b``, the same network),
    and its card ``out/NAME.json`` (:func:`interpolated_card`; B's card, none when B has
    none). Returns the model's path. Bad arguments raise ValueError in one line naming the
    problem (alpha outside [0, 1], a missing file, a file that is not ONNX, a quantized
    model, graphs that differ, cards with another canvas); then nothing is written."""
    alpha = check_alpha(alpha)
    path_a, path_b, out = Path(model_a), Path(model_b), Path(out)
    a = load_model(path_a, "model_a")
    b = load_model(path_b, "model_b")
    if not name or "/" in name or name.startswith("."):
        raise ValueError(f"name: expected a file name without a folder, got {name!r}")
    target = out / f"{name}.onnx"
    for label, p in (("model_a", path_a), ("model_b", path_b)):
        if target.resolve() == p.resolve():
            raise ValueError(f"out: {target} is {label}, the model to read; write elsewhere")
    if out.exists() and not out.is_dir():
        raise ValueError(f"out: {out} is a file; expected a folder")
    mixed = interpolated_model(a, b, alpha)
    card = interpolated_card(
        read_model_card(path_a), read_model_card(path_b), path_a, path_b, alpha, target, command
    )
    onnx, _ = _onnx()
    with staged_files(out, f".{name}-") as stage:
        onnx.save(mixed, str(stage / target.name))
        _check_runs(stage / target.name)
        (stage / f"{name}.json").write_text(json.dumps(card, indent=2) + "\n")
    return target


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m drake_rus.imaging.training.interpolate",
        description=__doc__.split("\n")[0],
    )
    ap.add_argument("model_a", help="fp32 ONNX model A (alpha 0), e.g. the shipped model")
    ap.add_argument("model_b", help="fp32 ONNX model B (alpha 1), e.g. a fine-tune of A")
    ap.add_argument("--alpha", type=float, required=True, help="weight of B in [0, 1]")
    ap.add_argument("--out", required=True, help="folder of the new model and its card")
    ap.add_argument("--name", default="kidney_unet", help="file name of the model (no .onnx)")
    args = ap.parse_args(argv)
    command = "python -m drake_rus.imaging.training.interpolate " + " ".join(
        shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv)
    )
    try:
        path = interpolate_models(
            args.model_a, args.model_b, args.alpha, args.out, args.name, command
        )
    except (ValueError, MissingExtra) as e:
        print(f"interpolate: error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {path} and its card {path.with_suffix('.json')} (alpha {args.alpha:g})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
