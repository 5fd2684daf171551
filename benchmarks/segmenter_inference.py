"""What the segmenter's inference side gains, on the validation split (``python -m benchmarks
segmenter_inference``).

No retraining: the scenario's model (``--onnx-model``, default ``imaging.onnx_model``) as it
is, without the guided filter (``imaging.onnx_guided_radius`` 0; this study came first), with
three inference-side choices measured per frame on the same probability maps:

- ``mirror``: test-time augmentation with the lateral mirror (``onnx_backend.mirror_average``:
  the probability of the frame and of its mirror about the beam axis, averaged);
- ``threshold``: the probability threshold (``imaging.onnx_threshold``);
- post-processing of the mask: ``raw`` (every pixel above the threshold in the fan), ``lcc``
  (the segmenter's own: the largest 8-connected region, holes filled), ``lcc+minN`` (and no
  mask when that region is under N cm^2: ``imaging.onnx_min_region_area``).

Sources: the validation split only, generated patients the shipped model was not fitted on
(``train:22..29`` by default; it was trained on ``train:0..19``, chose its epochs on
``train:20..21`` and was calibrated for int8 on ``train:0..19``), in both postures, each as
generated and as an imported-like volume (no perirenal fat, a layered kidney: how the VH
female's and every imported body's kidney look; ``train_segmenter.randomised_anatomy``).
Never a test patient nor the VH female. ``--views`` views per source and posture at every
depth preset (``evaluation.depth_study``'s views and emulator), scored against the target
kidney. Shadowed frames: under half the kidney out of acoustic shadow.

Choice (fixed before any measurement): the variant with the highest worst-preset mean IoU
over all validation frames (generated and imported-like), among those whose false-positive
rate on kidney-free frames exceeds the plain segmenter's (no mirror, 0.5, ``lcc``) by at
most 0.01 at every preset; a variant within 0.001 of a simpler one (fewer changes from the
plain segmenter) does not count as better: the simplest variant within 0.001 of the best
is chosen. The last line is one JSON object.

With ``--ensemble-model M`` it runs the test-time study instead: the scenario's segmenter as
it ships (guided filter included) against the lateral mirror average, the ensemble of the
scenario's model with ``M`` (``imaging.onnx_ensemble_model``) and both, each a whole segment
call per frame, timed in the same run (the mean time per frame, and its ratio to the
default's). Choice (:func:`choose_test_time`, written in docs/results/segmenter.md before it
was scored): on the generated and on the imported-like frames no preset more than 0.001
below the default, at least +0.002 at 100 mm on the generated frames, no more false
positives at any preset, at most 3 times the default's time; then the highest 100 mm gain,
a cheaper variant within 0.001 of it taken instead; none: the default.

With ``--edge-thresholds T1,T2,..`` it runs the edge study instead: the scenario's segmenter
as it ships against the same with each value as ``imaging.onnx_edge_threshold`` (the regions
found at ``onnx_threshold`` as before, their edge drawn where the probability crosses T),
on the same frames, with the mean mask area over the true section's per kind and preset.
Choice (:func:`choose_edge_threshold`, written in docs/results/segmenter.md before it was
scored): on the generated and on the imported-like frames no preset more than 0.001 below
the default, the imported-like frames' mean over the presets at least +0.002, no more false
positives at any preset; then the highest imported-like gain, a value nearer the default
within 0.001 of it taken instead; none: the default.

With ``--compare-models M1,M2,..`` it runs the comparison instead: the scenario's segmenter
as it ships against the same with each other model (``imaging.onnx_model``), on the same
frames. It chooses nothing: a rule written beforehand reads its figures.

Every study takes ``--draws N``: N independent draws of views (the first is the draw every
earlier rule was scored on), pooled. The test-time, edge and comparison studies print each
draw's kidney-free and marked frames (how far the counts move with the draw alone), the
share of kidney-free frames each setting marks, and each setting's paired difference to
the default, in IoU per kind and preset and in that share, with 95% intervals that
resample whole patient-postures (a patient's generated and imported-like volumes are one
cluster; ``evaluation.cluster_bootstrap_ci``). The variant study prints the share's
interval for the plain and the chosen variant.
"""

from __future__ import annotations

import argparse
import itertools
import os
import sys
import time
from dataclasses import dataclass, field, replace

import numpy as np

from drake_rus.io_utils import dumps_strict

TEST_TIME = ("default", "mirror", "ensemble", "ensemble+mirror")
THRESHOLDS = (0.3, 0.35, 0.4, 0.45, 0.5, 0.55, 0.6, 0.65, 0.7)
MIN_AREAS_CM2 = (0.5, 1.0, 2.0)
PLAIN = ("off", 0.5, "lcc")


def variant_masks(seg, prob: np.ndarray, thresholds, min_areas_m2) -> dict:
    """{(threshold, post): bool image mask} of one kidney probability ``prob`` at the
    model's resolution (``seg``: the :class:`OnnxSegmenter` that made it): ``raw``, ``lcc``
    and ``lcc+min{cm2:g}`` per threshold. The segmenter's threshold is restored after."""
    g = seg.geometry
    image_prob = seg.to_image(seg._past_fan(prob))
    keep = seg.threshold
    out = {}
    try:
        for t in thresholds:
            out[(t, "raw")] = (image_prob > t) & g.fan_mask
            seg.threshold = float(t)
            regions = seg._candidates(prob, largest_only=True)
            lcc = regions[0] if regions else np.zeros(g.image_shape, bool)
            out[(t, "lcc")] = lcc
            area = np.count_nonzero(lcc) * g.pixel_area
            for a in min_areas_m2:
                out[(t, f"lcc+min{a * 1e4:g}")] = lcc if area >= a else np.zeros_like(lcc)
    finally:
        seg.threshold = keep
    return out


def score_variants(records: list[dict], key) -> dict:
    """{group: {variant: {iou, frames, fp_rate}}} of per-frame records (``scores``:
    {variant: iou or false positive}) grouped by ``key(record)`` (None: left out)."""
    out: dict = {}
    for r in records:
        k = key(r)
        if k is None:
            continue
        g = out.setdefault(k, {})
        for v, s in r["scores"].items():
            cell = g.setdefault(v, {"ious": [], "fp": 0, "empty": 0})
            if r["has_kidney"]:
                cell["ious"].append(s)
            else:
                cell["empty"] += 1
                cell["fp"] += int(s)
    return {
        k: {
            v: {
                "iou": float(np.mean(c["ious"])) if c["ious"] else float("nan"),
                "frames": len(c["ious"]),
                "fp_rate": c["fp"] / c["empty"] if c["empty"] else 0.0,
            }
            for v, c in g.items()
        }
        for k, g in out.items()
    }


def changes(variant) -> int:
    """How many of the three choices differ from the plain segmenter's."""
    return sum(a != b for a, b in zip(variant, PLAIN))


def choose(by_depth: dict, fp_margin: float = 0.01, tie: float = 0.001):
    """The variant (mirror, threshold, post) by the module's rule from ``{depth: {variant:
    {iou, fp_rate}}}``: highest worst-preset mean IoU, false positives at most
    ``fp_margin`` above the plain segmenter's at every preset, a simpler variant kept
    unless beaten by more than ``tie``."""
    variants = sorted(next(iter(by_depth.values())).keys(), key=lambda v: (changes(v), str(v)))
    worst = {v: min(by_depth[d][v]["iou"] for d in by_depth) for v in variants}
    allowed = [
        v
        for v in variants
        if all(
            by_depth[d][v]["fp_rate"] <= by_depth[d][PLAIN]["fp_rate"] + fp_margin for d in by_depth
        )
    ]
    top = max(worst[v] for v in allowed)
    # The simplest of the variants within ``tie`` of the best (the plain one if it is).
    best = min((v for v in allowed if worst[v] >= top - tie), key=lambda v: (changes(v), -worst[v]))
    return best, worst


def validation_sources(a: int, b: int, imported_like: bool = True, log: str | None = None):
    """[(kind, Source)] of the validation patients ``train:a..b`` in both postures, each as
    generated (kind "generated") and, with ``imported_like``, as an imported-like volume (no
    perirenal fat, a layered kidney; kind "imported_like", seeded per patient and posture).
    ``log``: a name for one progress line per source on stderr."""
    from drake_rus.imaging.training.evaluation import POSTURES, Source, load_source
    from drake_rus.imaging.training.train_segmenter import randomised_anatomy

    t0 = time.perf_counter()
    sources = []
    for k in range(a, b + 1):
        for posture in POSTURES:
            src = load_source(f"train:{k}", posture=posture)
            sources.append(("generated", src))
            if imported_like:
                rng = np.random.default_rng(1000 + 2 * k + POSTURES.index(posture))
                vol = randomised_anatomy(src.volume, rng, True, "layered")
                sources.append(
                    (
                        "imported_like",
                        Source(src.name, posture, vol, src.up_V, src.target, src.size_class),
                    )
                )
            if log:
                print(
                    f"[{log} {time.perf_counter() - t0:5.0f} s] loaded train:{k} {posture}",
                    file=sys.stderr,
                    flush=True,
                )
    return sources


def parse_patients(text: str) -> tuple[int, int] | None:
    """(A, B) of ``--patients A..B`` (0 <= A <= B), None when malformed."""
    try:
        a, b = (int(x) for x in text.split(".."))
    except ValueError:
        return None
    return (a, b) if 0 <= a <= b else None


def patients_and_draws(args) -> tuple[tuple[int, int] | None, str | None]:
    """((A, B), None) of ``args.patients`` (``A..B``), or (None, the one line naming the bad
    argument) when it, or ``args.draws`` where the command has one, is malformed."""
    ab = parse_patients(args.patients)
    if ab is None:
        return None, f"--patients: expected A..B with 0 <= A <= B, got {args.patients!r}"
    if getattr(args, "draws", 1) < 1:
        return None, f"--draws: expected 1 or more, got {args.draws}"
    return ab, None


def validation_arguments(prog: str, description: str, argv=None, ensemble: bool = False):
    """The arguments of the validation-split benchmarks (this one and segmenter_boundary):
    (args, (A, B)), or None after one line on stderr naming the bad argument. ``ensemble``:
    also ``--ensemble-model`` (this one's test-time study)."""
    ap = argparse.ArgumentParser(prog=prog, description=description)
    if ensemble:
        ap.add_argument(
            "--ensemble-model",
            default=None,
            help="run the test-time study: mirror and ensemble with this second model",
        )
        ap.add_argument(
            "--compare-models",
            default=None,
            help="run the comparison: the scenario's model against these (M1,M2,..), "
            "paired, with intervals",
        )
        ap.add_argument(
            "--draws",
            type=int,
            default=1,
            help="independent draws of views, pooled (default 1: the draw every earlier rule used)",
        )
        ap.add_argument(
            "--edge-thresholds",
            default=None,
            help="run the edge study: these imaging.onnx_edge_threshold values (T1,T2,..)",
        )
    ap.add_argument("--patients", default="22..29", help="validation patients train:A..B")
    ap.add_argument("--views", type=int, default=30, help="views per source and posture")
    ap.add_argument("--onnx-model", default=None, help="default: imaging.onnx_model")
    ap.add_argument("--no-imported-like", action="store_true", help="generated volumes only")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    ab, error = patients_and_draws(args)
    if error is None and args.views < 1:
        error = f"--views: expected 1 or more, got {args.views}"
    if error:
        print(error, file=sys.stderr)
        return None
    if getattr(args, "edge_thresholds", None) is not None:
        edges = parse_edge_thresholds(args.edge_thresholds)
        if edges is None:
            print(
                "--edge-thresholds: expected comma-separated probabilities in (0, 1), got "
                f"{args.edge_thresholds!r}",
                file=sys.stderr,
            )
            return None
        args.edge_thresholds = edges
    if getattr(args, "compare_models", None) is not None:
        models = [m.strip() for m in args.compare_models.split(",")]
        if not all(models):
            print(
                "--compare-models: expected comma-separated ONNX model paths, got "
                f"{args.compare_models!r}",
                file=sys.stderr,
            )
            return None
        args.compare_models = models
    return args, ab


def parse_edge_thresholds(text: str) -> list[float] | None:
    """[T, ..] of ``--edge-thresholds T1,T2,..`` (each in (0, 1)), None when malformed."""
    try:
        values = [float(x) for x in text.split(",")]
    except ValueError:
        return None
    return values if values and all(0.0 < v < 1.0 for v in values) else None


def choose_edge_threshold(
    iou: dict, fp: dict, default: float, loss: float = 0.001, gain: float = 0.002
):
    """The edge threshold by the rule of the module's docstring, and why each other value
    failed: (chosen, {value: reason or ""}). ``iou``: {(kind, depth): {value: mean IoU}}
    with kinds "generated" and "imported_like" and ``default`` among the values; ``fp``:
    {depth: {value: false-positive frames}}."""
    values = [v for v in next(iter(fp.values())) if v != default]
    depths = sorted(fp)
    verdict = {}

    def imported_gain(v):
        return float(
            np.mean(
                [iou[("imported_like", d)][v] - iou[("imported_like", d)][default] for d in depths]
            )
        )

    for v in values:
        why = []
        for (kind, d), cell in sorted(iou.items()):
            if cell[v] < cell[default] - loss:
                why.append(f"{kind} {d * 1000:.0f} mm {cell[v] - cell[default]:+.4f}")
        if imported_gain(v) < gain:
            why.append(f"imported-like gain {imported_gain(v):+.4f} < {gain}")
        for d in depths:
            if fp[d][v] > fp[d][default]:
                why.append(f"false positives {d * 1000:.0f} mm {fp[d][v]} > {fp[d][default]}")
        verdict[v] = "; ".join(why)
    passed = [v for v in values if not verdict[v]]
    if not passed:
        return default, verdict
    top = max(imported_gain(v) for v in passed)
    near = [v for v in passed if imported_gain(v) >= top - loss]
    return min(near, key=lambda v: abs(v - default)), verdict


def choose_test_time(
    iou: dict, fp: dict, ms: dict, loss: float = 0.001, gain: float = 0.002, cost: float = 3.0
):
    """The test-time variant by the rule of the module's docstring, and why each other one
    failed: (chosen, {variant: reason or ""}). ``iou``: {(kind, depth): {variant: mean IoU}}
    with kinds "generated" and "imported_like"; ``fp``: {depth: {variant: false-positive
    frames}}; ``ms``: {variant: mean segment time per frame}. The variants are compared
    with ``"default"``; the shallowest depth is the 100 mm preset."""
    depths = sorted(fp)
    first = depths[0]
    verdict = {}
    for v in ms:
        if v == "default":
            continue
        why = []
        for (kind, d), cell in sorted(iou.items()):
            if cell[v] < cell["default"] - loss:
                why.append(f"{kind} {d * 1000:.0f} mm {cell[v] - cell['default']:+.4f}")
        g100 = iou[("generated", first)][v] - iou[("generated", first)]["default"]
        if g100 < gain:
            why.append(f"100 mm gain {g100:+.4f} < {gain}")
        for d in depths:
            if fp[d][v] > fp[d]["default"]:
                why.append(f"false positives {d * 1000:.0f} mm {fp[d][v]} > {fp[d]['default']}")
        if ms[v] > cost * ms["default"]:
            why.append(f"cost x{ms[v] / ms['default']:.2f} > x{cost:g}")
        verdict[v] = "; ".join(why)
    passed = [v for v in verdict if not verdict[v]]
    if not passed:
        return "default", verdict

    def g(v):
        return iou[("generated", first)][v]

    top = max(g(v) for v in passed)
    return min((v for v in passed if g(v) >= top - loss), key=lambda v: ms[v]), verdict


# The views of draw k are drawn and emulated from VIEW_SEED + DRAW_STRIDE * k (the first
# draw is the one every earlier rule in docs/results/segmenter.md was scored on). The stride
# keeps the per-source seeds of emulated_views (seed + 7919 * source, seed + source) of
# different draws apart.
VIEW_SEED = 9150
DRAW_STRIDE = 100_003
# The variant study's first draw (its own, older seed).
VARIANT_SEED = 5150


def draw_seeds(draws: int, first: int = VIEW_SEED) -> list[int]:
    """The view seeds of ``draws`` independent draws of views, the first one ``first``."""
    if draws < 1:
        raise ValueError(f"draws: expected 1 or more, got {draws}")
    return [first + DRAW_STRIDE * k for k in range(draws)]


@dataclass
class SettingScores:
    """Every setting's whole segment call on the same validation frames (all draws pooled).

    ``iou``: {(kind, depth): {setting: [IoU per frame with a kidney]}} with the frames'
    source clusters in ``iou_clusters`` {(kind, depth): [cluster]} (patient and posture:
    the unit the intervals resample; a patient's generated and imported-like volumes share
    its anatomy, so they are one cluster); ``false_positive``: {depth: {setting:
    [marked, per kidney-free frame]}} with ``free_clusters`` {depth: [cluster]};
    ``free_by_draw`` {depth: [kidney-free frames per draw]} and ``marked_by_draw``
    {depth: {setting: [marked frames per draw]}}; ``seconds``: {setting: s} over ``calls``
    frames; ``area``: {(kind, depth): {setting: [mask area / true section area]}}."""

    iou: dict = field(default_factory=dict)
    iou_clusters: dict = field(default_factory=dict)
    false_positive: dict = field(default_factory=dict)
    free_clusters: dict = field(default_factory=dict)
    free_by_draw: dict = field(default_factory=dict)
    marked_by_draw: dict = field(default_factory=dict)
    seconds: dict = field(default_factory=dict)
    calls: int = 0
    area: dict = field(default_factory=dict)

    @property
    def fp(self) -> dict:
        """{depth: {setting: kidney-free frames marked as kidney}} (the rules' counts)."""
        return {d: {v: int(sum(x)) for v, x in c.items()} for d, c in self.false_positive.items()}

    @property
    def empty(self) -> dict:
        """{depth: kidney-free frames}."""
        return {d: len(c) for d, c in self.free_clusters.items()}


def paired_intervals(values: dict, clusters, reference) -> dict:
    """{setting: {mean, ci95, difference, difference_ci95}} of per-frame ``values``
    ({setting: [value]}, every setting on the same frames, whose clusters are
    ``clusters``): each setting's mean and the mean of its frame-by-frame difference to
    ``reference``'s, each with its 95% interval resampling whole clusters
    (``evaluation.cluster_bootstrap_ci``). The paired difference is what tells two
    settings apart: both means move together with the draw of sources."""
    from drake_rus.imaging.training.evaluation import cluster_bootstrap_ci

    if reference not in values:
        raise ValueError(f"reference setting {reference!r} not among {sorted(map(str, values))}")
    ref = np.asarray(values[reference], float)
    out = {}
    for v, x in values.items():
        x = np.asarray(x, float)
        if x.shape != ref.shape or len(clusters) != len(ref):
            raise ValueError(
                f"setting {v!r}: expected {len(ref)} values on the reference's frames and "
                f"{len(ref)} clusters, got {x.size} values and {len(clusters)} clusters"
            )
        diff = x - ref
        out[v] = {
            "mean": float(np.mean(x)) if x.size else float("nan"),
            "ci95": cluster_bootstrap_ci(x, clusters),
            "difference": float(np.mean(diff)) if x.size else float("nan"),
            "difference_ci95": cluster_bootstrap_ci(diff, clusters),
        }
    return out


def interval_tables(scores: SettingScores, reference) -> dict:
    """The intervals of a :class:`SettingScores` against the ``reference`` setting:
    {"iou": {(kind, depth): paired_intervals}, "false_positive": {depth: paired_intervals}}."""
    return {
        "iou": {
            k: paired_intervals(cell, scores.iou_clusters[k], reference)
            for k, cell in scores.iou.items()
        },
        "false_positive": {
            d: paired_intervals(cell, scores.free_clusters[d], reference)
            for d, cell in scores.false_positive.items()
        },
    }


def share_text(cell: dict) -> str:
    """A share of kidney-free frames with its 95% interval, as "4.3% (0.6-16.4)", or
    "no frames"."""
    if np.isnan(cell["mean"]):
        return "no frames"
    lo, hi = cell["ci95"]
    return f"{100 * cell['mean']:.1f}% ({100 * lo:.1f}-{100 * hi:.1f})"


def setting_key(v) -> str:
    """A setting's JSON key: an edge threshold as "0.45", anything else as its text."""
    return f"{v:g}" if isinstance(v, float) else str(v)


def round4(x: float) -> float:
    """``x`` rounded to 4 decimals for the JSON; a NaN (a preset without frames) stays NaN,
    written as null by :func:`drake_rus.io_utils.dumps_strict` (JSON has no NaN)."""
    return round(float(x), 4)


def print_intervals(tables: dict, settings, reference, presets, draws: int) -> None:
    """Print the kidney-free share and the IoU difference to ``reference`` with their 95%
    intervals (whole patient-postures resampled), per setting and preset."""

    def fmt(x, lo, hi):
        return "no frames" if np.isnan(x) else f"{x:+.4f} ({lo:+.4f}..{hi:+.4f})"

    print(
        f"\n95% intervals resampling patient and posture ({draws} draw(s) of views "
        f"pooled); differences are paired against {reference!r}"
    )
    for v in settings:
        shares = "  ".join(share_text(tables["false_positive"][d][v]) for d in presets)
        line = f"  {v!s:>16} kidney-free marked: {shares}"
        if v != reference:
            diffs = "  ".join(
                fmt(c[v]["difference"], *c[v]["difference_ci95"])
                for c in (tables["false_positive"][d] for d in presets)
            )
            line += f" | difference {diffs}"
        print(line)
    kinds = sorted({k for k, _ in tables["iou"]})
    for v in settings:
        if v == reference:
            continue
        for k in kinds:
            cells = "  ".join(
                fmt(
                    tables["iou"][(k, d)][v]["difference"],
                    *tables["iou"][(k, d)][v]["difference_ci95"],
                )
                for d in presets
            )
            print(f"  {v!s:>16} IoU difference, {k}: {cells}")


def intervals_json(tables: dict) -> dict:
    """The JSON form of :func:`interval_tables` (keys "kind|depth" and "depth"), for
    :func:`drake_rus.io_utils.dumps_strict` (which writes a preset's NaN as null)."""

    def pack(cell):
        return {
            setting_key(v): {
                "mean": round4(c["mean"]),
                "ci95": [round4(x) for x in c["ci95"]],
                "difference": round4(c["difference"]),
                "difference_ci95": [round4(x) for x in c["difference_ci95"]],
            }
            for v, c in cell.items()
        }

    return {
        "iou": {f"{k}|{d:.2f}": pack(c) for (k, d), c in sorted(tables["iou"].items())},
        "false_positive_share": {
            f"{d:.2f}": pack(c) for d, c in sorted(tables["false_positive"].items())
        },
    }


def print_draws(scores: SettingScores, settings, presets, seeds) -> None:
    """One line per draw of views: its seed, kidney-free frames per preset, and each
    setting's marked frames per preset (how much the counts move with the draw alone)."""
    for k, seed in enumerate(seeds):
        free = "/".join(str(scores.free_by_draw[d][k]) for d in presets)
        marked = "  ".join(
            f"{v}: " + "/".join(str(scores.marked_by_draw[d][v][k]) for d in presets)
            for v in settings
        )
        print(f"  draw {k} (seed {seed}): kidney-free {free} | marked {marked}")


def draws_json(scores: SettingScores, seeds, presets) -> dict:
    """The per-draw counts of :func:`print_draws` as JSON."""
    return {
        "seeds": list(seeds),
        "kidney_free_frames": {f"{d:.2f}": scores.free_by_draw[d] for d in presets},
        "marked": {
            f"{d:.2f}": {setting_key(v): n for v, n in scores.marked_by_draw[d].items()}
            for d in presets
        },
    }


def score_settings(
    segs: dict, sources, views: int, seeds, no_progress: bool = False
) -> SettingScores:
    """Every setting's whole segment call on the same validation frames. ``segs``: {depth:
    (config, geometry, {setting: segmenter})}; ``sources``: [(kind, Source)]; ``views``
    per source at every depth, drawn and emulated from each of ``seeds`` (one draw of views
    per seed, pooled)."""
    from tqdm import tqdm

    from drake_rus.imaging.segment import iou
    from drake_rus.imaging.training.evaluation import emulated_views

    settings = list(next(iter(segs.values()))[2])
    out = SettingScores(seconds=dict.fromkeys(settings, 0.0))
    for d in segs:
        out.false_positive[d] = {v: [] for v in settings}
        out.free_clusters[d] = []
        out.free_by_draw[d] = [0] * len(seeds)
        out.marked_by_draw[d] = {v: [0] * len(seeds) for v in settings}
    bar = tqdm(
        total=len(sources) * views * len(segs) * len(seeds),
        desc="validation frames",
        disable=no_progress,
        mininterval=2.0,
    )
    for k, seed in enumerate(seeds):
        frames = emulated_views([src for _, src in sources], segs, views, seed)
        for si, d, c, g, by_variant, us, gt, has in frames:
            kind, src = sources[si]
            cluster = f"{src.name}|{src.posture}"
            out.calls += 1
            if has:
                out.iou_clusters.setdefault((kind, d), []).append(cluster)
            else:
                out.free_clusters[d].append(cluster)
                out.free_by_draw[d][k] += 1
            for v, seg in by_variant.items():
                t = time.perf_counter()
                m = seg(us)
                out.seconds[v] += time.perf_counter() - t
                if has:
                    out.iou.setdefault((kind, d), {}).setdefault(v, []).append(iou(m, gt))
                    ratio = np.count_nonzero(m) / np.count_nonzero(gt)
                    out.area.setdefault((kind, d), {}).setdefault(v, []).append(ratio)
                else:
                    marked = bool(np.count_nonzero(m) * g.pixel_area >= c.min_kidney_area)
                    out.false_positive[d][v].append(marked)
                    out.marked_by_draw[d][v][k] += marked
            bar.update()
    bar.close()
    return out


def segmenters_for_settings(base, settings: dict) -> dict:
    """{depth: (config, geometry, {setting: OnnxSegmenter})}: every setting's imaging
    overrides ({setting: {field: value}}) applied to ``base`` at each depth preset. A bad
    model raises ValueError (``OnnxSegmenter.from_config``'s, naming the field)."""
    from drake_rus.imaging.onnx_backend import OnnxSegmenter
    from drake_rus.imaging.probe import ProbeGeometry

    segs = {}
    for d in (float(p) for p in base.depth_presets):
        c = replace(base, depth=d)
        g = ProbeGeometry.from_config(c)
        segs[d] = (
            c,
            g,
            {v: OnnxSegmenter.from_config(replace(c, **kw), g) for v, kw in settings.items()},
        )
    return segs


def score_study(args, a: int, b: int, base, settings: dict, model_field=None, flag=None):
    """(SettingScores, seeds) of the settings (:func:`segmenters_for_settings`) on the
    validation frames of ``train:a..b`` over ``args.draws`` draws; None after one line on
    stderr when a model named by the imaging ``model_field`` cannot be loaded (the message
    names the command-line ``flag`` instead)."""
    try:
        segs = segmenters_for_settings(base, settings)
    except ValueError as e:
        if model_field is None:
            raise
        print(str(e).replace(model_field, flag), file=sys.stderr)
        return None
    sources = validation_sources(a, b, not args.no_imported_like, "segmenter_inference")
    seeds = draw_seeds(args.draws)
    return score_settings(segs, sources, args.views, seeds, args.no_progress), seeds


def edge_study(args, a: int, b: int) -> int:
    """The ``--edge-thresholds`` study (see the module docstring); prints its table and one
    JSON line."""
    from drake_rus.imaging.config import ImagingConfig

    t0 = time.perf_counter()
    base = ImagingConfig() if args.onnx_model is None else ImagingConfig(onnx_model=args.onnx_model)
    default = base.onnx_edge_threshold or base.onnx_threshold
    values = [default] + [v for v in args.edge_thresholds if v != default]
    presets = [float(p) for p in base.depth_presets]
    scores, seeds = score_study(args, a, b, base, {v: {"onnx_edge_threshold": v} for v in values})
    iou_acc, fp, empty, area = scores.iou, scores.fp, scores.empty, scores.area
    mean_iou = {k: {v: float(np.mean(x)) for v, x in cell.items()} for k, cell in iou_acc.items()}
    # The mask's area over the true section's, on the frames where the mask meets it.
    mean_area = {
        k: {
            v: float(np.mean([r for r, j in zip(x, iou_acc[k][v]) if j > 0] or [np.nan]))
            for v, x in cell.items()
        }
        for k, cell in area.items()
    }
    chosen, verdict = choose_edge_threshold(mean_iou, fp, default)
    kinds = sorted({k for k, _ in mean_iou})
    print(
        f"\nvalidation: train:{a}..{b}, both postures, {args.views} views each per preset"
        f" and draw, {args.draws} draw(s); frames with a kidney per preset and kind: "
        + ", ".join(
            f"{k} {d * 1000:.0f} mm {len(iou_acc[(k, d)][default])}" for k in kinds for d in presets
        )
        + "; kidney-free per preset: "
        + "/".join(str(empty[d]) for d in presets)
    )
    for v in values:
        cells = "   ".join(
            f"{k} " + " ".join(f"{mean_iou[(k, d)][v]:.4f}" for d in presets) for k in kinds
        )
        areas = "   ".join(
            f"{k} " + " ".join(f"{mean_area[(k, d)][v]:.3f}" for d in presets) for k in kinds
        )
        fps = "/".join(str(fp[d][v]) for d in presets)
        print(
            f"edge {v:.2f}: IoU {cells} | area {areas} | FP {fps}"
            + ("" if v == default else f" | {'passes' if not verdict[v] else verdict[v]}")
        )
    print_draws(scores, values, presets, seeds)
    tables = interval_tables(scores, default)
    print_intervals(tables, values, default, presets, args.draws)
    print(f"chosen: edge threshold {chosen}")
    print(
        dumps_strict(
            {
                "validation": f"train:{a}..{b}",
                "views": args.views,
                "draws": draws_json(scores, seeds, presets),
                "intervals": intervals_json(tables),
                "onnx_model": base.onnx_model,
                "iou": {
                    f"{k}|{d:.2f}": {f"{v:g}": round(x, 4) for v, x in cell.items()}
                    for (k, d), cell in sorted(mean_iou.items())
                },
                "area_ratio": {
                    f"{k}|{d:.2f}": {f"{v:g}": round(x, 4) for v, x in cell.items()}
                    for (k, d), cell in sorted(mean_area.items())
                },
                "false_positives": {
                    f"{d:.2f}": {f"{v:g}": n for v, n in fp[d].items()} for d in presets
                },
                "kidney_free_frames": {f"{d:.2f}": empty[d] for d in presets},
                "verdict": {f"{v:g}": why for v, why in verdict.items()},
                "chosen": chosen,
                "seconds": round(time.perf_counter() - t0, 1),
                "load_average": [round(x, 2) for x in os.getloadavg()],
            }
        )
    )
    return 0


def compare_study(args, a: int, b: int) -> int:
    """The ``--compare-models`` study (see the module docstring): the scenario's segmenter
    as it ships against the same with each other model, on the same frames; prints the
    means, the paired differences with their intervals and one JSON line. A measurement:
    it chooses nothing (a rule written beforehand reads its intervals)."""
    from drake_rus.imaging.config import ImagingConfig

    t0 = time.perf_counter()
    base = ImagingConfig() if args.onnx_model is None else ImagingConfig(onnx_model=args.onnx_model)
    models = [base.onnx_model] + [m for m in args.compare_models if m != base.onnx_model]
    presets = [float(p) for p in base.depth_presets]
    settings = {m: {"onnx_model": m} for m in models}
    done = score_study(args, a, b, base, settings, "imaging.onnx_model", "--compare-models")
    if done is None:
        return 2
    scores, seeds = done
    kinds = sorted({k for k, _ in scores.iou})
    print(
        f"\nvalidation: train:{a}..{b}, both postures, {args.views} views each per preset"
        f" and draw, {args.draws} draw(s); frames with a kidney per preset and kind: "
        + ", ".join(
            f"{k} {d * 1000:.0f} mm {len(scores.iou[(k, d)][models[0]])}"
            for k in kinds
            for d in presets
        )
        + "; kidney-free per preset: "
        + "/".join(str(scores.empty[d]) for d in presets)
    )
    for m in models:
        cells = "   ".join(
            f"{k} " + " ".join(f"{np.mean(scores.iou[(k, d)][m]):.4f}" for d in presets)
            for k in kinds
        )
        fps = "/".join(str(scores.fp[d][m]) for d in presets)
        print(f"{m}: IoU {cells} | FP {fps}")
    print_draws(scores, models, presets, seeds)
    tables = interval_tables(scores, models[0])
    print_intervals(tables, models, models[0], presets, args.draws)
    print(
        dumps_strict(
            {
                "validation": f"train:{a}..{b}",
                "views": args.views,
                "reference": models[0],
                "models": models,
                "draws": draws_json(scores, seeds, presets),
                "intervals": intervals_json(tables),
                "kidney_free_frames": {f"{d:.2f}": scores.empty[d] for d in presets},
                "seconds": round(time.perf_counter() - t0, 1),
                "load_average": [round(x, 2) for x in os.getloadavg()],
            }
        )
    )
    return 0


def test_time_study(args, a: int, b: int) -> int:
    """The ``--ensemble-model`` study (see the module docstring); prints its table and one
    JSON line."""
    from drake_rus.imaging.config import ImagingConfig

    t0 = time.perf_counter()
    base = ImagingConfig() if args.onnx_model is None else ImagingConfig(onnx_model=args.onnx_model)
    base = replace(base, onnx_mirror_average=False, onnx_ensemble_model="")
    settings = {
        "default": {},
        "mirror": {"onnx_mirror_average": True},
        "ensemble": {"onnx_ensemble_model": args.ensemble_model},
        "ensemble+mirror": {
            "onnx_mirror_average": True,
            "onnx_ensemble_model": args.ensemble_model,
        },
    }
    presets = [float(p) for p in base.depth_presets]
    done = score_study(
        args, a, b, base, settings, "imaging.onnx_ensemble_model", "--ensemble-model"
    )
    if done is None:
        return 2
    scores, seeds = done
    iou_acc, fp, empty = scores.iou, scores.fp, scores.empty
    seconds, calls = scores.seconds, scores.calls
    mean_iou = {k: {v: float(np.mean(x)) for v, x in cell.items()} for k, cell in iou_acc.items()}
    ms = {v: 1e3 * s / calls for v, s in seconds.items()}
    chosen, verdict = choose_test_time(mean_iou, fp, ms)
    kinds = sorted({k for k, _ in mean_iou})
    print(
        f"\nvalidation: train:{a}..{b}, both postures, {args.views} views each per preset"
        f" and draw, {args.draws} draw(s); ensemble with {args.ensemble_model}; frames with a "
        "kidney per preset and kind: "
        + ", ".join(
            f"{k} {d * 1000:.0f} mm {len(iou_acc[(k, d)]['default'])}"
            for k in kinds
            for d in presets
        )
        + "; kidney-free per preset: "
        + "/".join(str(empty[d]) for d in presets)
    )
    for v in settings:
        cells = "   ".join(
            f"{k} " + " ".join(f"{mean_iou[(k, d)][v]:.4f}" for d in presets) for k in kinds
        )
        fps = "/".join(str(fp[d][v]) for d in presets)
        print(
            f"{v:>16}: {cells} | FP {fps} | {ms[v]:.2f} ms x{ms[v] / ms['default']:.2f}"
            + ("" if v == "default" else f" | {'passes' if not verdict[v] else verdict[v]}")
        )
    print_draws(scores, list(settings), presets, seeds)
    tables = interval_tables(scores, "default")
    print_intervals(tables, list(settings), "default", presets, args.draws)
    print(f"chosen: {chosen}")
    print(
        dumps_strict(
            {
                "validation": f"train:{a}..{b}",
                "views": args.views,
                "draws": draws_json(scores, seeds, presets),
                "intervals": intervals_json(tables),
                "onnx_model": base.onnx_model,
                "ensemble_model": args.ensemble_model,
                "iou": {
                    f"{k}|{d:.2f}": {v: round(x, 4) for v, x in cell.items()}
                    for (k, d), cell in sorted(mean_iou.items())
                },
                "frames_with_kidney": {
                    f"{k}|{d:.2f}": len(cell["default"]) for (k, d), cell in sorted(iou_acc.items())
                },
                "false_positives": {f"{d:.2f}": fp[d] for d in presets},
                "kidney_free_frames": {f"{d:.2f}": empty[d] for d in presets},
                "ms_segment": {v: round(x, 3) for v, x in ms.items()},
                "ratio_to_default": {v: round(ms[v] / ms["default"], 2) for v in ms},
                "verdict": verdict,
                "chosen": chosen,
                "seconds": round(time.perf_counter() - t0, 1),
                "load_average": [round(x, 2) for x in os.getloadavg()],
            }
        )
    )
    return 0


def main(argv=None) -> int:
    parsed = validation_arguments(
        "python -m benchmarks segmenter_inference", __doc__, argv, ensemble=True
    )
    if parsed is None:
        return 2
    args, (a, b) = parsed
    studies = [
        f
        for f, x in (
            ("--ensemble-model", args.ensemble_model),
            ("--edge-thresholds", args.edge_thresholds),
            ("--compare-models", args.compare_models),
        )
        if x is not None
    ]
    if len(studies) > 1:
        print(f"{' and '.join(studies)}: expected one study, got {len(studies)}", file=sys.stderr)
        return 2
    if args.compare_models is not None:
        return compare_study(args, a, b)
    if args.ensemble_model is not None:
        return test_time_study(args, a, b)
    if args.edge_thresholds is not None:
        return edge_study(args, a, b)

    from pydrake.math import RigidTransform
    from tqdm import tqdm

    from drake_rus.imaging.config import ImagingConfig
    from drake_rus.imaging.emulator import EmulatorModel, emulate
    from drake_rus.imaging.segment import iou
    from drake_rus.imaging.slicing import slice_volume
    from drake_rus.imaging.training.evaluation import (
        VISIBLE_GREY,
        sample_views,
        segmenters_by_depth,
    )

    t0 = time.perf_counter()
    cfg = ImagingConfig() if args.onnx_model is None else ImagingConfig(onnx_model=args.onnx_model)
    cfg = replace(
        cfg,
        onnx_mirror_average=False,
        onnx_min_region_area=0.0,
        onnx_threshold=0.5,
        onnx_guided_radius=0.0,
    )
    presets = [float(p) for p in cfg.depth_presets]
    segmenters = segmenters_by_depth(presets, cfg)
    min_areas = [c * 1e-4 for c in MIN_AREAS_CM2]

    sources = validation_sources(a, b, not args.no_imported_like, "segmenter_inference")

    records = []
    seeds = draw_seeds(args.draws, VARIANT_SEED)
    total = len(sources) * args.views * len(presets) * len(seeds)
    bar = tqdm(total=total, desc="validation frames", disable=args.no_progress, mininterval=2.0)
    for seed, (si, (kind, src)) in itertools.product(seeds, enumerate(sources)):
        poses = sample_views(src, args.views, seed + 7919 * si)
        for depth, (c, g, seg) in segmenters.items():
            model = EmulatorModel.from_config(c, g)
            for i, X_VP in enumerate(poses):
                labels = slice_volume(g, src.volume, RigidTransform(), X_VP)
                us = emulate(labels, model, seed + si, i)
                gt = src.kidney_mask(labels, g, X_VP)
                has = bool(gt.sum() * g.pixel_area >= c.min_kidney_area)
                seg.mirror_average = False
                p_plain = seg.model_probability(us)
                seg.mirror_average = True
                p_mirror = seg.model_probability(us)
                seg.mirror_average = False
                scores = {}
                for mirror, prob in (("off", p_plain), ("on", p_mirror)):
                    for (t, post), m in variant_masks(seg, prob, THRESHOLDS, min_areas).items():
                        scores[(mirror, t, post)] = (
                            iou(m, gt)
                            if has
                            else bool(np.count_nonzero(m) * g.pixel_area >= c.min_kidney_area)
                        )
                records.append(
                    {
                        "kind": kind,
                        "cluster": f"{src.name}|{src.posture}",
                        "posture": src.posture,
                        "depth": depth,
                        "has_kidney": has,
                        "shadowed": has and float(np.mean(us[gt] > VISIBLE_GREY)) < 0.5,
                        "scores": scores,
                    }
                )
                bar.update()
    bar.close()

    by_depth = score_variants(records, lambda r: r["depth"])
    best, worst = choose(by_depth)
    groups = {
        "generated": score_variants(records, lambda r: (r["kind"] == "generated") or None),
        "imported_like": score_variants(records, lambda r: (r["kind"] == "imported_like") or None),
        "shadowed": score_variants(
            records, lambda r: (r["shadowed"] or not r["has_kidney"]) or None
        ),
        "all": score_variants(records, lambda r: True),
    }
    groups = {k: v.get(True, {}) for k, v in groups.items()}

    def row(v):
        cells = "  ".join(f"{by_depth[d][v]['iou']:.3f}" for d in presets)
        fps = "/".join(f"{100 * by_depth[d][v]['fp_rate']:.0f}" for d in presets)
        extra = "  ".join(
            f"{groups[k][v]['iou']:.3f}" for k in ("generated", "imported_like", "shadowed")
        )
        return f"{v[0]:>6} {v[1]:5.2f} {v[2]:>10} | {cells} | {worst[v]:.3f} | {extra} | {fps}"

    n_frames = {d: by_depth[d][PLAIN]["frames"] for d in presets}
    print(
        f"\nvalidation: train:{a}..{b}, both postures"
        + ("" if args.no_imported_like else ", generated and imported-like")
        + f", {args.views} views each per preset; frames with a kidney per preset: "
        + ", ".join(f"{d * 1000:.0f} mm {n}" for d, n in n_frames.items())
    )
    head = (
        f"{'mirror':>6} {'thr':>5} {'post':>10} | "
        + "  ".join(f"{d * 1000:3.0f}mm" for d in presets)
        + " | worst | generated  imp-like  shadowed | FP % per preset"
    )
    print(head)
    print("-" * len(head))
    variants = sorted(by_depth[presets[0]].keys(), key=lambda v: -worst[v])
    shown = [PLAIN] + [v for v in variants if v != PLAIN][:24]
    for v in shown:
        print(row(v) + ("   <- chosen" if v == best else "") + ("   (plain)" if v == PLAIN else ""))
    for mirror in ("off", "on"):
        for post in ("raw", "lcc"):
            v = (mirror, 0.5, post)
            if v not in shown:
                print(row(v))
    free = [r for r in records if not r["has_kidney"]]
    fp_tables = {
        d: paired_intervals(
            {v: [r["scores"][v] for r in free if r["depth"] == d] for v in (PLAIN, best)},
            [r["cluster"] for r in free if r["depth"] == d],
            PLAIN,
        )
        for d in presets
    }
    print(
        f"kidney-free frames marked, 95% interval resampling patient and posture "
        f"({args.draws} draw(s) of views pooled), "
        + ", ".join(f"{d * 1000:.0f}mm" for d in presets)
    )
    for v in dict.fromkeys([PLAIN, best]):
        print(
            f"  {v[0]:>3} {v[1]:4.2f} {v[2]:>10}: "
            + "  ".join(share_text(fp_tables[d][v]) for d in presets)
        )
    print(f"\nchosen: mirror {best[0]}, threshold {best[1]}, post-processing {best[2]}")
    # Per preset and kind of volume: the plain, the chosen, the best by worst preset
    # whatever its false positives, and the mirror average alone.
    by_depth_kind = score_variants(records, lambda r: (r["depth"], r["kind"]))
    kinds = sorted({r["kind"] for r in records})
    print("per preset and volume kind (" + ", ".join(f"{d * 1000:.0f}mm" for d in presets) + ")")
    for v in dict.fromkeys([PLAIN, best, variants[0], ("on", 0.5, "lcc")]):
        cells = "   ".join(
            f"{k} " + " ".join(f"{by_depth_kind[(d, k)][v]['iou']:.3f}" for d in presets)
            for k in kinds
        )
        print(f"  {v[0]:>3} {v[1]:4.2f} {v[2]:>10}: {cells}")

    def pack(v):
        return {
            "iou_by_depth": {f"{d:.2f}": round(by_depth[d][v]["iou"], 4) for d in presets},
            "fp_by_depth": {f"{d:.2f}": round(by_depth[d][v]["fp_rate"], 4) for d in presets},
            "worst": round(worst[v], 4),
            **{k: round(groups[k][v]["iou"], 4) for k in groups},
        }

    result = {
        "validation": f"train:{a}..{b}",
        "imported_like": not args.no_imported_like,
        "views": args.views,
        "draws": args.draws,
        "seeds": seeds,
        "onnx_model": cfg.onnx_model,
        "frames_with_kidney": {f"{d:.2f}": n for d, n in n_frames.items()},
        "frames_shadowed": groups["shadowed"][PLAIN]["frames"],
        "chosen": {"mirror": best[0], "threshold": best[1], "post": best[2]},
        "false_positive_share": {
            f"{v[0]}|{v[1]}|{v[2]}": {
                f"{d:.2f}": {
                    "mean": round4(fp_tables[d][v]["mean"]),
                    "ci95": [round4(x) for x in fp_tables[d][v]["ci95"]],
                }
                for d in presets
            }
            for v in dict.fromkeys([PLAIN, best])
        },
        "variants": {f"{v[0]}|{v[1]}|{v[2]}": pack(v) for v in variants},
        "iou_by_depth_kind": {
            f"{v[0]}|{v[1]}|{v[2]}": {
                k: {f"{d:.2f}": round(by_depth_kind[(d, k)][v]["iou"], 4) for d in presets}
                for k in kinds
            }
            for v in dict.fromkeys([PLAIN, best, variants[0], ("on", 0.5, "lcc")])
        },
        "seconds": round(time.perf_counter() - t0, 1),
        "load_average": [round(x, 2) for x in os.getloadavg()],
    }
    print(dumps_strict(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
