"""``drake-rus template build|info``: build the kidney template from the training cohort."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from drake_rus.anatomy.cohort import cohort_seeds
from drake_rus.anatomy.generator import generate_patient
from drake_rus.cli import UserError
from drake_rus.io_utils import dumps_strict, save_figure
from drake_rus.progress import stderr_is_terminal
from drake_rus.template.builder import build_template, save_template, subject_from_mask
from drake_rus.template.ct import TUMOUR_POLICIES, CtTemplateError, CtTemplateOptions, ct_template
from drake_rus.template.io import DEFAULT_TEMPLATE_PATH, load_template
from drake_rus.template.population import parse_population, population_template


def subjects_from_cohort(
    split: str = "train",
    n: int = 20,
    voxel_size: float = 0.001,
    side: str = "right",
    progress: bool = True,
):
    """Template subjects from a virtual cohort: each kidney's mask (``voxel_size`` voxels, like
    a CT segmentation) -> marching cubes -> canonical frame."""
    subjects = []
    for k, seed in enumerate(
        tqdm(cohort_seeds(split, n), desc="template: subjects", disable=not progress)
    ):
        p = generate_patient(seed, side=side, name=f"{split}:{k}", progress=False)
        mask, X_PtV = p.kidney_mask(voxel_size)
        x_ref, y_ref = p.reference_axes()
        subjects.append(subject_from_mask(mask, X_PtV, voxel_size, x_ref, y_ref, name=p.name))
    return subjects


def plot_convergence(conv: dict, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = np.asarray(conv["n"])
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    ax.plot(n[1:], np.asarray(conv["change"][1:]) * 1e3, "o-", label="change when adding subject n")
    ax.plot(n, np.asarray(conv["to_final"]) * 1e3, "s--", ms=3, label="distance to final template")
    ax.set_xlabel("number of subjects N")
    ax.set_ylabel("mean per-vertex difference (mm)")
    ax.set_title("Kidney template convergence (seed Fig. 3d)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right", fontsize=8, framealpha=0.9)
    ax.set_ylim(bottom=0)
    fig.tight_layout()
    return save_figure(fig, path, dpi=120)


def plot_template_modes(template, path: Path, n_modes: int = 3) -> Path:
    """The template (top: x-y, bottom: x-z projection) with mean -/+ 2 SD of its first modes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    k = min(n_modes, len(template.variances))
    fig, axes = plt.subplots(2, k + 1, figsize=(3.2 * (k + 1), 5.2), squeeze=False)
    for col in range(k + 1):
        for row, (i, j) in enumerate(((0, 1), (0, 2))):
            ax = axes[row, col]
            if col == 0:
                p = template.points
                ax.scatter(p[:, i] * 1e3, p[:, j] * 1e3, s=1, c="0.3")
                ax.set_title("mean template" if row == 0 else "")
            else:
                for sd, color in ((-2, "tab:blue"), (2, "tab:red")):
                    b = np.zeros(len(template.variances))
                    b[col - 1] = sd
                    p = template.shape_sd(b)
                    ax.scatter(p[:, i] * 1e3, p[:, j] * 1e3, s=0.6, c=color, label=f"{sd:+d} SD")
                if row == 0:
                    frac = template.meta.get("explained", [0] * k)[col - 1]
                    ax.set_title(f"mode {col} ({100 * frac:.0f}% var.)")
                    ax.legend(markerscale=6, fontsize=7)
            ax.set_aspect("equal")
            ax.set_xlabel("x_k (mm)")
            ax.set_ylabel("y_k (mm)" if row == 0 else "z_k (mm)")
    fig.tight_layout()
    return save_figure(fig, path, dpi=110)


# Where ``template build`` writes by default: a user path beside the other runs, never the
# template shipped in models/ (``--out`` pointing at a shipped file is refused).
DEFAULT_BUILD_OUT = Path("runs/template/kidney_template.npz")


def shipped_template_files() -> list[Path]:
    """The files of the shipped template: the .npz and what a build writes beside it."""
    t = DEFAULT_TEMPLATE_PATH
    return [
        t,
        t.with_suffix(".json"),
        t.with_name(t.stem + "_convergence.png"),
        t.with_name(t.stem + "_modes.png"),
    ]


def build_outputs(out: Path, png) -> dict[str, Path]:
    """The files ``template build --out OUT [--png PNG]`` writes, by the argument naming each."""
    return {
        "--out": out,
        "--out (metadata)": out.with_suffix(".json"),
        "--png": Path(png) if png else out.with_name(out.stem + "_convergence.png"),
        "--out (modes)": out.with_name(out.stem + "_modes.png"),
    }


def check_not_shipped(out: Path, png) -> None:
    """Raises UserError naming the argument when a file the build would write is one of the
    shipped template's files (models/): a build never replaces the shipped model."""
    shipped = {f.resolve() for f in shipped_template_files()}
    for arg, path in build_outputs(out, png).items():
        if path.resolve() in shipped:
            raise UserError(
                f"{arg.split()[0]}: {path} is the template shipped with drake-rus and is never "
                f"overwritten; build into another file (default {DEFAULT_BUILD_OUT}) and use it "
                f'with --set "{{localization: {{template: FILE}}}}"'
            )


def _build(args) -> int:
    if args.n < 1:
        raise UserError(f"--n: expected at least 1 subject, got {args.n}")
    if args.points < 100:
        raise UserError(f"--points: expected at least 100, got {args.points}")
    if not 0.2 <= args.voxel_mm <= 5:
        raise UserError(f"--voxel-mm: expected 0.2-5 mm, got {args.voxel_mm}")
    if args.from_ct is not None:
        return _build_from_ct(args)
    if args.side == "both":
        raise UserError("--side both: only for --from-ct (real kidneys, the left mirrored)")
    out = Path(args.out) if args.out is not None else DEFAULT_BUILD_OUT
    if out.suffix != ".npz":
        raise UserError(f"--out: expected a .npz file name, got {out}")
    check_not_shipped(out, args.png)
    t0 = time.time()
    progress = not args.quiet and stderr_is_terminal()
    if args.population:
        try:
            parse_population(args.population)
        except ValueError as e:
            raise UserError(f"--population: {e}") from None
        population_template(
            args.population,
            n=args.n,
            side=args.side,
            n_points=args.points,
            voxel=args.voxel_mm / 1000.0,
            out=out,
            progress=progress,
        )
        t = load_template(out)
        meta = t.meta
        change = t.convergence.get("change", [])
        t1 = t0 + meta.get("subject_seconds", 0.0)
    else:
        subjects = subjects_from_cohort(
            args.split, args.n, args.voxel_mm / 1000.0, side=args.side, progress=progress
        )
        t1 = time.time()
        result = build_template(
            subjects, n_points=args.points, use_features=not args.no_features, progress=progress
        )
        extra = {
            "split": args.split,
            "side": args.side,
            "voxel_mm": args.voxel_mm,
            "subject_seconds": round(t1 - t0, 2),
            "total_seconds": round(time.time() - t0, 2),
            "source": "drake-rus virtual cohort (drake_rus.anatomy.generator)",
        }
        save_template(result, out, extra)
        meta, change = dict(result.meta, **extra), result.convergence["change"]
    t2 = time.time()
    print(dumps_strict(_summary(args, out, meta, change, t0, t1, t2), indent=2))
    return 0


def _summary(args, out: Path, meta: dict, change, t0: float, t1: float, t2: float) -> dict:
    """Plots beside ``out`` (convergence, modes) and the build's JSON summary."""
    png = Path(args.png) if args.png else out.with_name(out.stem + "_convergence.png")
    template = load_template(out)
    plot_convergence(template.convergence, png)
    modes_png = out.with_name(out.stem + "_modes.png")
    plot_template_modes(template, modes_png)
    summary = {
        "out": str(out),
        "convergence_png": str(png),
        "modes_png": str(modes_png),
        "source": meta.get("split"),
        "n_subjects": meta["n_subjects"],
        "n_points": meta["n_points"],
        "n_modes": meta["n_modes"],
        "explained_pct": [round(100 * f, 1) for f in meta["explained"]],
        "extent_mm": meta["extent_mm"],
        "ransac_used": meta["ransac_used"],
        "ransac_rejected": meta["ransac_rejected"],
        "convergence_change_mm": [
            None if c is None or not np.isfinite(c) else round(c * 1e3, 3) for c in change
        ],
        "seconds": {
            "subjects": round(t1 - t0, 1),
            "template": round(t2 - t1, 1),
            "total": round(t2 - t0, 1),
        },
    }
    if "sampled_length_mm" in meta:
        summary["sampled_length_mm"] = meta["sampled_length_mm"]
    summary["use_with"] = f'--set "{{localization: {{template: {out.resolve()}}}}}"'
    if "cases" in meta:
        summary.update(
            cases=meta["cases"],
            excluded_cases=meta["excluded_cases"],
            tumour_policy=meta["tumour_policy"],
            side=meta["side"],
            subject_extent_mm=meta["subject_extent_mm"],
        )
    return summary


def _build_from_ct(args) -> int:
    """``template build --from-ct DIR``: the template of real CT kidneys (seed II-D; see
    :mod:`drake_rus.template.ct`), into the template cache unless --out says otherwise."""
    if args.population:
        raise UserError("--population: not with --from-ct (generated or real kidneys, not both)")
    if args.case_list is not None and not Path(args.case_list).is_file():
        raise UserError(f"--case-list: {args.case_list}: file not found")
    if not Path(args.from_ct).expanduser().is_dir():
        raise UserError(f"--from-ct: {args.from_ct}: not a folder of CT label maps")
    # --cases N, else --n (the generated builds' count; default 20, as the seed's N).
    n = args.cases if args.cases is not None else args.n
    opts = CtTemplateOptions(
        n=n,
        side=args.side,
        tumour_policy=args.tumour_policy,
        max_tumour_fraction=args.max_tumour_fraction,
        n_points=args.points,
        voxel=args.voxel_mm / 1000.0,
        strict_n=args.cases is not None or args.n != 20,
    )
    case_list = None
    if args.case_list is not None:
        case_list = [
            ln.split("#")[0].strip() for ln in Path(args.case_list).read_text().splitlines()
        ]
        case_list = [c for c in case_list if c]
    t0 = time.time()
    try:
        out = ct_template(
            args.from_ct,
            opts,
            exclude=args.exclude_cases or (),
            case_list=case_list,
            out=args.out,
            progress=not args.quiet and stderr_is_terminal(),
            log=None if args.quiet else _stderr_line,
        )
    except CtTemplateError as e:
        flag = {
            "folder": "--from-ct",
            "n": "--cases",
            "cases": "--exclude-cases",
            "case_list": "--case-list",
            "side": "--side",
            "tumour_policy": "--tumour-policy",
            "max_tumour_fraction": "--max-tumour-fraction",
            "points": "--points",
            "voxel": "--voxel-mm",
            "out": "--out",
        }.get(e.field, "--from-ct")
        raise UserError(f"{flag}: {e.detail}") from None
    t1 = time.time()
    meta = load_template(out).meta
    summary = _summary(
        args,
        out,
        meta,
        meta["convergence"]["change"],
        t0,
        t0 + meta.get("survey_seconds", 0.0) + meta.get("subject_seconds", 0.0),
        t1,
    )
    print(dumps_strict(summary, indent=2))
    return 0


def _stderr_line(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _info(args) -> int:
    if args.path is not None and Path(args.path).is_dir():
        raise UserError(f"path: {args.path} is a folder; expected a template .npz file")
    try:
        t = load_template(args.path)
    except ValueError as e:
        raise UserError(str(e)) from None
    m = t.meta
    print(
        dumps_strict(
            {
                "path": str(args.path or DEFAULT_TEMPLATE_PATH),
                "n_points": len(t.points),
                "n_subjects": m.get("n_subjects"),
                "n_modes": len(t.variances),
                "mode_sd_mm": [round(float(np.sqrt(v)) * 1e3, 2) for v in t.variances],
                "extent_mm": m.get("extent_mm"),
                "build_seconds": m.get("total_seconds"),
            },
            indent=2,
        )
    )
    return 0


def add_commands(subparsers) -> None:
    p = subparsers.add_parser("template", help="kidney template (seed II-D): build, info")
    sub = p.add_subparsers(dest="template_command", metavar="ACTION")
    sub.required = True
    b = sub.add_parser("build", help="build the template from the virtual training cohort")
    b.add_argument("--n", type=int, default=20, help="number of training subjects (default 20)")
    b.add_argument(
        "--split",
        default="train",
        choices=["train", "seed"],
        help="cohort to build from (default train); the test split is reserved "
        "for evaluation and refused",
    )
    b.add_argument(
        "--side",
        default="right",
        choices=["right", "left", "both"],
        help="kidney side (default right); both: only with --from-ct, the left "
        "kidneys mirrored onto right ones",
    )
    b.add_argument(
        "--out",
        default=None,
        help=f"output .npz (default {DEFAULT_BUILD_OUT}; with --from-ct the "
        f"template cache; the shipped models/{DEFAULT_TEMPLATE_PATH.name} is "
        "never overwritten)",
    )
    b.add_argument("--points", type=int, default=2500, help="template vertices (default 2500)")
    b.add_argument("--voxel-mm", type=float, default=1.0, help="mask voxel size (default 1 mm)")
    b.add_argument("--png", default=None, help="convergence plot (default beside --out)")
    b.add_argument(
        "--no-features",
        action="store_true",
        help="skip FPFH+RANSAC (ICP from the canonical frames only)",
    )
    b.add_argument(
        "--population",
        default=None,
        help="build from N generated kidneys of another population instead of the "
        "training cohort: base, short, long, slim or length+Xsd (see "
        "drake_rus/template/population.py; the study's population:NAME)",
    )
    ct = b.add_argument_group(
        "real kidneys",
        "--from-ct DIR builds the template from CT label maps (KiTS layout "
        "DIR/case_*/segmentation.nii.gz: 1 kidney, 2 tumour), the seed's II-D on real "
        "kidneys; see docs/real_kidneys.md. A template of such data (KiTS19: CC BY-NC-SA) "
        "goes to the cache, never into the repository.",
    )
    ct.add_argument("--from-ct", default=None, metavar="DIR", help="folder of CT label maps")
    ct.add_argument(
        "--cases",
        type=int,
        default=None,
        metavar="N",
        help="number of kidneys (the seed's N; default --n, 20: fewer with a "
        "warning when the folder has fewer eligible ones), taken from the "
        "last case backwards so the first cases stay for testing",
    )
    ct.add_argument(
        "--case-list",
        default=None,
        metavar="FILE",
        help="cases to use, in order (one name or number per line)",
    )
    ct.add_argument(
        "--exclude-cases",
        default=None,
        metavar="CASES",
        help="cases never used (names, numbers, ranges: 0-29,case_00042)",
    )
    ct.add_argument(
        "--tumour-policy",
        default="exclude",
        choices=list(TUMOUR_POLICIES),
        help="exclude (default): leave out kidneys whose tumour exceeds "
        "--max-tumour-fraction; include: the tumour as part of the kidney; "
        "mask: the kidney without its tumour voxels",
    )
    ct.add_argument(
        "--max-tumour-fraction",
        type=float,
        default=0.0,
        metavar="F",
        help="with --tumour-policy exclude: largest tumour share of a kidney's "
        "volume kept (default 0: tumour-free kidneys only)",
    )
    b.add_argument("--quiet", action="store_true", help="no progress bars")
    b.set_defaults(func=_build, outputs={"out": "file:.npz", "png": "file:.png"})
    i = sub.add_parser("info", help="summary of a template file")
    i.add_argument("path", nargs="?", default=None)
    i.set_defaults(func=_info)
