"""The kidney template from real CT kidneys beside the generated one
(``python -m benchmarks real_template [--cases DIR] [--test 0-39] [--policies ...]``).

Builds (or reads from the cache) the template of real CT kidneys (:mod:`drake_rus.template.ct`,
the seed's II-D: N = 20 tumour-free right kidneys by default, from the last cases backwards,
never the test cases), then measures, for the shipped template of generated kidneys and for
the real one side by side:

- each template's extents along its principal axes (length, width, thickness);
- the distance of every real kidney of the test cases (both sides, left ones mirrored onto
  right ones; the tumour as part of the kidney) and of the 15 generated test kidneys
  (``test:0..14``) to each template: surface points aligned on their principal axes (the
  canonical frame, eq. 13-14), no scaling, no ICP, symmetric mean nearest-point distance
  (the template study's measure);
- the real template's convergence over N (seed Fig. 3d; a plot with ``--out``) and its build
  time.

``--policies`` also builds the templates of the other tumour policies (``include``:
tumour-bearing kidneys with their tumours; ``mask``: without their tumour voxels) and
measures them the same way. Prints a table and, last, one JSON line. Needs the CT label maps
(``../shared/anatomy/kits19`` beside the repository by default): without them it says so
and prints ``{"skipped": ...}``.
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from drake_rus.anatomy.cohort import cohort_seeds
from drake_rus.anatomy.generator import sample_patient_params
from drake_rus.anatomy.kidney_shape import KidneyShape
from drake_rus.io_utils import dumps_strict
from drake_rus.template.builder import subject_from_mesh
from drake_rus.template.ct import (
    DEFAULT_CT_DIR,
    TUMOUR_POLICIES,
    CtTemplateError,
    CtTemplateOptions,
    ct_template,
    find_label_maps,
    kidney_masks,
    match_cases,
    principal_extents,
    subject_from_ct_kidney,
    template_distance,
)
from drake_rus.template.io import DEFAULT_TEMPLATE_PATH, load_template


def generated_test_kidneys(n: int = 15) -> list[tuple[str, np.ndarray]]:
    """(name, surface points in the canonical frame) of the generated test kidneys."""
    out = []
    for k, seed in enumerate(cohort_seeds("test", n)):
        mesh = KidneyShape(sample_patient_params(seed).kidney).mesh
        # The shape's local frame: x towards the superior pole, y medial -> lateral.
        out.append((f"test:{k}", subject_from_mesh(mesh, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]).points))
    return out


def real_test_kidneys(ct_dir: Path, cases, log) -> list[dict]:
    """Every kidney of the test cases: canonical points (tumour included, left mirrored),
    side, tumour fraction; kidneys cut by the field of view or anomalous, and cases whose
    body frame the importer cannot establish, are left out (as the builder leaves them out)."""
    maps = dict(find_label_maps(ct_dir))
    out = []
    for case in cases:
        try:
            kidneys = kidney_masks(maps[case])
        except ValueError as e:
            log(f"  {case}: skipped ({e})")
            continue
        for k in kidneys:
            why = k.cut or k.anomaly
            if why:
                log(f"  {k.name}: skipped ({why})")
                continue
            pts = subject_from_ct_kidney(k, "include", mirror=(k.side == "left")).points
            out.append(
                {
                    "name": k.name,
                    "side": k.side,
                    "points": pts,
                    "tumour_fraction": k.tumour_fraction,
                    "volume_ml": k.volume_ml,
                }
            )
    return out


def _stats(values) -> dict:
    v = np.asarray(values, float)
    return {
        "n": int(len(v)),
        "mean": round(float(v.mean()), 2),
        "sd": round(float(v.std(ddof=1)), 2) if len(v) > 1 else 0.0,
        "min": round(float(v.min()), 2),
        "max": round(float(v.max()), 2),
    }


def _fmt(s: dict) -> str:
    return f"{s['mean']:.1f} +- {s['sd']:.1f} mm ({s['min']:.1f} to {s['max']:.1f}, n {s['n']})"


def plot_convergence_pair(real, generated, path: Path) -> Path:
    """Fig. 3d for both templates: mean per-point distance of the template of the first n
    subjects to that of all N."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from drake_rus.io_utils import save_figure

    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    for t, label, style in (
        (real, "real CT kidneys", "o-"),
        (generated, "generated kidneys (shipped)", "s--"),
    ):
        c = t.convergence
        if c:
            ax.plot(c["n"], np.asarray(c["to_final"]) * 1e3, style, ms=4, label=label)
    ax.set_xlabel("number of subjects n")
    ax.set_ylabel("mean per-point distance to\nthe template of all N (mm)")
    ax.set_title("Template convergence (seed Fig. 3d)")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path, dpi=120)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks real_template",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--cases", default=str(DEFAULT_CT_DIR), help="folder of CT label maps (KiTS layout)"
    )
    parser.add_argument(
        "--test", default="0-39", help="test cases: never used to build, measured (default 0-39)"
    )
    parser.add_argument("--n", type=int, default=20, help="kidneys in the real template")
    parser.add_argument("--side", default="right", choices=["right", "left", "both"])
    parser.add_argument(
        "--policies",
        default="exclude",
        help="tumour policies to build and measure, comma-separated "
        "(exclude, include, mask; default exclude)",
    )
    parser.add_argument("--out", default=None, help="folder for the plots")
    args = parser.parse_args(argv)
    policies = [p.strip() for p in args.policies.split(",") if p.strip()]
    if not policies or any(p not in TUMOUR_POLICIES for p in policies):
        print(
            f"--policies: expected comma-separated {', '.join(TUMOUR_POLICIES)}, got "
            f"{args.policies!r}",
            file=sys.stderr,
        )
        return 2
    if args.n < 1:
        print(f"--n: expected 1 or more kidneys, got {args.n}", file=sys.stderr)
        return 2
    ct_dir = Path(args.cases).expanduser()
    if not ct_dir.is_dir():
        print(f"real_template: no CT label maps at {ct_dir}; skipped")
        print(dumps_strict({"skipped": f"no CT label maps at {ct_dir}"}))
        return 0

    def log(line):
        print(line, flush=True)

    try:
        names = [c for c, _ in find_label_maps(ct_dir)]
    except CtTemplateError as e:
        print(f"--cases: {e}", file=sys.stderr)
        return 2
    try:
        test = match_cases(names, args.test)
    except CtTemplateError as e:
        print(f"--test: {e}", file=sys.stderr)
        return 2
    if not test:
        print(
            f"--test: {args.test!r} selects none of the {len(names)} cases of {ct_dir}",
            file=sys.stderr,
        )
        return 2
    generated = load_template(DEFAULT_TEMPLATE_PATH)
    templates = {"generated": generated}
    builds = {}
    for policy in policies:
        opts = CtTemplateOptions(n=args.n, side=args.side, tumour_policy=policy)
        t0 = time.time()
        try:
            path = ct_template(ct_dir, opts, exclude=test, log=log)
        except CtTemplateError as e:  # e.g. no eligible kidney outside the test cases
            print(f"real_template: {e}", file=sys.stderr)
            return 2
        wall = time.time() - t0
        t = load_template(path)
        templates[f"real:{policy}"] = t
        builds[f"real:{policy}"] = {
            "path": str(path),
            "cases": t.meta["cases"],
            "n_subjects": t.meta["n_subjects"],
            "build_s_first": t.meta.get("total_seconds"),
            "this_call_s": round(wall, 1),
            "subject_extent_mm": t.meta.get("subject_extent_mm"),
            "convergence_to_final_mm": [round(v * 1e3, 2) for v in t.convergence["to_final"]],
            "convergence_change_mm": [
                None if not np.isfinite(v) else round(v * 1e3, 2) for v in t.convergence["change"]
            ],
            "n_modes": int(len(t.variances)),
            "mode_sd_mm": [round(float(np.sqrt(v)) * 1e3, 2) for v in t.variances[:5]],
            "frame_status": t.meta.get("frame", {}).get("status"),
        }
        used = set(t.meta["cases"]) & set(test)
        if used:
            raise AssertionError(f"test cases {sorted(used)} built the template")
    log(f"measuring {len(test)} test cases of {ct_dir} ...")
    t0 = time.time()
    real = real_test_kidneys(ct_dir, test, log)
    gen = generated_test_kidneys()
    measure_s = time.time() - t0
    rows = {}
    for name, t in templates.items():
        d_real = [template_distance(k["points"], t.points) * 1e3 for k in real]
        d_healthy = [d for d, k in zip(d_real, real) if k["tumour_fraction"] == 0]
        d_tumour = [d for d, k in zip(d_real, real) if k["tumour_fraction"] > 0]
        d_gen = [template_distance(p, t.points) * 1e3 for _, p in gen]
        rows[name] = {
            "extent_mm": (principal_extents(t.points) * 1e3).round(1).tolist(),
            "real_kidneys_mm": _stats(d_real),
            "real_healthy_mm": _stats(d_healthy) if d_healthy else None,
            "real_with_tumour_mm": _stats(d_tumour) if d_tumour else None,
            "generated_kidneys_mm": _stats(d_gen),
            "per_kidney_mm": {k["name"]: round(d, 2) for k, d in zip(real, d_real)},
        }
    ext_real = np.array([principal_extents(k["points"]) for k in real]) * 1e3
    ext_gen = np.array([principal_extents(p) for _, p in gen]) * 1e3
    print()
    print(
        f"{len(real)} real kidneys of {len(test)} test cases "
        f"({sum(k['tumour_fraction'] > 0 for k in real)} with tumour), "
        f"{len(gen)} generated test kidneys"
    )
    print(
        f"real kidneys' extents:      {ext_real.mean(0).round(0)} +- "
        f"{ext_real.std(0, ddof=1).round(0)} mm"
    )
    print(
        f"generated kidneys' extents: {ext_gen.mean(0).round(0)} +- "
        f"{ext_gen.std(0, ddof=1).round(0)} mm"
    )
    print(f"{'template':16s} {'extent (mm)':22s} {'real kidneys':36s} {'generated kidneys':36s}")
    for name, r in rows.items():
        print(
            f"{name:16s} {str(r['extent_mm']):22s} {_fmt(r['real_kidneys_mm']):36s} "
            f"{_fmt(r['generated_kidneys_mm']):36s}"
        )
        if r["real_healthy_mm"] and r["real_with_tumour_mm"]:
            print(
                f"{'':16s} {'':22s} healthy {_fmt(r['real_healthy_mm'])}; with tumour "
                f"{_fmt(r['real_with_tumour_mm'])}"
            )
    for name, b in builds.items():
        print(
            f"{name}: {b['n_subjects']} kidneys of {b['cases'][0]}..{b['cases'][-1]}, first "
            f"build {b['build_s_first']} s; convergence (to all N, mm): "
            f"{b['convergence_to_final_mm']}"
        )
    if args.out:
        out = Path(args.out)
        first = next(k for k in templates if k.startswith("real:"))
        png = plot_convergence_pair(
            templates[first], generated, out / "real_template_convergence.png"
        )
        print(f"wrote {png}")
    print(
        dumps_strict(
            {
                "ct_dir": str(ct_dir),
                "test_cases": [test[0], test[-1]],
                "n_real_kidneys": len(real),
                "n_generated_kidneys": len(gen),
                "real_extent_mm": {
                    "mean": ext_real.mean(0).round(1).tolist(),
                    "sd": ext_real.std(0, ddof=1).round(1).tolist(),
                },
                "generated_extent_mm": {
                    "mean": ext_gen.mean(0).round(1).tolist(),
                    "sd": ext_gen.std(0, ddof=1).round(1).tolist(),
                },
                "templates": rows,
                "builds": builds,
                "measure_s": round(measure_s, 1),
            }
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
