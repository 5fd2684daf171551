"""``drake-rus cohort`` and ``drake-rus patient info|export|show``."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from drake_rus.anatomy.cohort import (
    SPLIT_OFFSETS,
    check_regular_path,
    cohort_seeds,
    cohort_stats,
    load_patient,
    split_seed,
)
from drake_rus.anatomy.ct_kidney import survey_case, survey_summary
from drake_rus.anatomy.ct_patient import (
    CT_PREFIX,
    ct_label_map_path,
    kidney_definition_difference,
    parse_ct_spec,
)
from drake_rus.anatomy.export import estimated_export_bytes
from drake_rus.anatomy.generator import generate_patient
from drake_rus.anatomy.importers import LABEL_MAP_SUFFIXES
from drake_rus.anatomy.pictures import plot_cohort_overview, plot_label_slices, show_in_meshcat
from drake_rus.cli import PREFLIGHT_CHECKS, MakeMeshcat, UserError
from drake_rus.io_utils import check_output_dir, dumps_strict, output_dir
from drake_rus.template import load_template

# Voxel spacing (mm) a label map may have: CT and MR are 0.3-5 mm; outside this range the
# spacing is in other units (metres) or the file is not a body scan.
LABEL_MAP_SPACING_MM = (0.1, 10.0)
# At most this many label-map headers of a folder are checked before the load.
_MAX_HEADERS = 200


def _user_error(e):
    return UserError(str(e))


def _label_map_files(path: Path) -> list[Path]:
    if path.is_dir():
        return [
            p
            for p in sorted(path.iterdir())
            if p.is_file() and p.name.lower().endswith(LABEL_MAP_SUFFIXES)
        ][:_MAX_HEADERS]
    if path.is_file() and path.name.lower().endswith(LABEL_MAP_SUFFIXES):
        return [path]
    return []


def check_label_map_spacing(path: Path, arg: str) -> None:
    """Raises a user error naming ``arg`` if a label map's voxel spacing (read from its
    header, not its voxels) is outside ``LABEL_MAP_SPACING_MM``."""
    import SimpleITK as sitk

    lo, hi = LABEL_MAP_SPACING_MM
    for f in _label_map_files(path):
        reader = sitk.ImageFileReader()
        reader.SetFileName(str(f))
        try:
            reader.ReadImageInformation()
        except RuntimeError:
            continue  # unreadable: the importer names it
        spacing = reader.GetSpacing()
        if not all(np.isfinite(spacing)) or not all(lo <= s <= hi for s in spacing):
            shown = ", ".join(f"{s:g}" for s in spacing)
            hint = " (in metres? label maps are read in mm)" if max(spacing) < lo else ""
            raise _user_error(
                f"{arg}: label map {f}: voxel spacing ({shown}) mm is outside "
                f"{lo:g}-{hi:g} mm{hint}"
            )


# The forms of a patient spec, for messages.
PATIENT_SPEC_FORMS = "seed:N, train:K, test:K, ct:PATH[#OPTIONS], a patient folder or a label map"


def check_patient_spec(spec: str, arg: str = "--patient", phantom: bool = True) -> None:
    """Checks a patient spec before any work: ``seed:N`` / ``train:K`` / ``test:K`` have an
    index in range, ``phantom:N`` (only where ``phantom``) an integer N, a path exists, label
    maps have a plausible voxel spacing. Other problems are found by the loader."""
    head, sep, tail = spec.partition(":")
    if spec.startswith(CT_PREFIX):
        try:
            path = ct_label_map_path(parse_ct_spec(spec).path, spec)
        except (ValueError, FileNotFoundError) as e:
            raise _user_error(f"{arg}: {e}") from None
        check_label_map_spacing(path, arg)
        return
    if sep and head == "phantom":
        if not phantom:
            raise _user_error(
                f"{arg}: phantom:N (a synthetic kidney volume) is for imaging-pictures only; "
                f"expected {PATIENT_SPEC_FORMS}, got {spec!r}"
            )
        if not tail.strip().isdigit():
            raise _user_error(
                f"{arg}: expected phantom:N with a non-negative integer N, got {spec!r}"
            )
        return
    if sep and head in SPLIT_OFFSETS:
        try:
            split_seed(head, int(tail))
        except ValueError as e:
            text = str(e) if tail.strip().lstrip("+-").isdigit() else "not an integer"
            raise _user_error(
                f"{arg}: expected {head}:{'N' if head == 'seed' else 'K'} with a non-negative "
                f"integer, got {spec!r} ({text})"
            ) from None
        return
    path = Path(spec)
    if not path.exists():
        raise _user_error(
            f"{arg}: expected {PATIENT_SPEC_FORMS}, got {spec!r} (no such file or folder)"
        )
    try:
        check_regular_path(path, arg)
    except ValueError as e:
        raise _user_error(e) from None
    check_label_map_spacing(path, arg)


def check_patient_arguments(args) -> None:
    """Preflight check of every command's ``--patient`` (or patient ``spec``) argument;
    ``phantom:N`` is read by imaging-pictures only."""
    phantom = getattr(args, "command", None) == "imaging-pictures"
    for name, arg in (("patient", "--patient"), ("spec", "patient spec")):
        spec = getattr(args, name, None)
        if isinstance(spec, str):
            check_patient_spec(spec, arg, phantom=phantom)


def load_patient_for(spec: str, arg: str = "--patient", **kwargs):
    """``load_patient`` for a command: its ValueErrors become one line naming ``arg``."""
    try:
        return load_patient(spec, **kwargs)
    except ValueError as e:
        text = str(e)
        if "Surface level" in text or "marching" in text.lower():
            text = (
                f"patient {spec!r}: the kidney label is too small to make a surface of "
                f"(a few voxels at most); check the label values and the mapping"
            )
        raise _user_error(f"{arg}: {text}") from None


def _load(args):
    return load_patient_for(
        args.spec,
        "patient spec",
        side=args.side,
        posture=args.posture,
        voxel_size=args.voxel_mm / 1000.0,
        progress=_tty(),
    )


def _tty() -> bool:
    import sys

    return sys.stderr.isatty()


def patient_info(patient) -> dict:
    m = patient.metrics()
    R = patient.X_PtK.rotation().matrix()
    deg = 180.0 / np.pi
    info = {
        "name": patient.name,
        "source": patient.meta.get("source"),
        "side": patient.side,
        "posture": patient.posture,
        "X_PtK": {
            "p_mm": (patient.X_PtK.translation() * 1e3).round(1).tolist(),
            "x_k": R[:, 0].round(4).tolist(),
            "y_k": R[:, 1].round(4).tolist(),
            "z_k": R[:, 2].round(4).tolist(),
        },
        "length_mm": round(m["length"] * 1e3, 1),
        "width_mm": round(m["width"] * 1e3, 1),
        "thickness_mm": round(m["thickness"] * 1e3, 1),
        "volume_ml": round(m["volume"] * 1e6, 1),
        "depth_below_upper_skin_mm": round(m["depth_vertical"] * 1e3, 1),
        "shortest_skin_distance_mm": round(m["depth_min"] * 1e3, 1),
        "coronal_angle_deg": round(m["coronal_angle"] * deg, 1),
        "sagittal_angle_deg": round(m["sagittal_angle"] * deg, 1),
    }
    if "hilum_angle" in patient.meta:
        info["hilum_angle_deg"] = round(patient.meta["hilum_angle"] * deg, 1)
    if "size_class" in patient.meta:
        info["size_class"] = patient.meta["size_class"]
    figures = patient.anatomy_figures
    if figures is not None:
        info["anatomy_checks"] = anatomy_check_summary(figures)
    return info


def anatomy_check_summary(figures: dict) -> dict:
    """The figures of :func:`~drake_rus.anatomy.checks.check_anatomy` in report units (mm,
    ml, %), as ``patient info`` prints them."""
    out = {}
    for key, value in figures.items():
        if key in ("kidney_volume", "kidney_imaged_volume"):
            out[key + "_ml"] = round(value * 1e6, 1)
        elif key in ("kidney_air_contact", "kidney_in_liver_mesh"):
            out[key + "_pct"] = round(value * 100, 2)
        elif key == "kidney_organ_contact":
            out[key + "_pct"] = {k: round(v * 100, 2) for k, v in value.items()}
        elif isinstance(value, float):
            out[key + "_mm"] = round(value * 1e3, 1)
        else:
            out[key] = value
    out["passed"] = True
    return out


def _info(args) -> int:
    p = _load(args)
    print(dumps_strict(patient_info(p), indent=2))
    return 0


def _export(args) -> int:
    check_output_dir(args.out, "--out", need_bytes=64 * 1024)
    p = _load(args)
    need = estimated_export_bytes(p)
    with output_dir(args.out, "--out", need_bytes=need, what="patient export") as out:
        try:
            paths = p.export(out, args.format)
        except ValueError as e:
            raise _user_error(e) from None
    print(dumps_strict({"written": [str(x) for x in paths]}, indent=2))
    return 0


def _show(args) -> int:
    p = _load(args)
    out = Path(args.png)
    plot_label_slices(p, out)
    print(dumps_strict({"slices_png": str(out)}))
    if args.meshcat:
        meshcat = MakeMeshcat()
        show_in_meshcat(p, meshcat)
        print(f"Meshcat: {meshcat.web_url()} (Ctrl-C to quit)", flush=True)
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
    return 0


# Largest cohorts: the statistics of 1000 patients pin each mean to 3% of its SD
# (SD / sqrt(n)), finer than any published figure they are compared with; a full build takes
# about 1 s a patient (1000: some 20 min), the fast statistics about 0.1 s (20000: some 40
# min). The overview picture draws at most 100 kidneys (one colour per 20: more is a blur).
MAX_COHORT = {"full": 1000, "fast": 20000, "png": 100}
# Seconds per patient, to say up front how long a cohort takes (measured on a laptop core).
_SECONDS_PER_PATIENT = {"full": 1.0, "fast": 0.1}


def check_cohort_count(count, fast: bool, png: bool) -> None:
    """Refuses a ``--count`` outside 1 .. :data:`MAX_COHORT` (with the reason)."""
    if count is None:
        return
    if count < 1:
        raise _user_error(f"--count: expected at least 1, got {count}")
    kind = "fast" if fast else "full"
    if count > MAX_COHORT[kind]:
        why = (
            f"statistics of {MAX_COHORT[kind]} patients pin each mean to "
            f"{1 / np.sqrt(MAX_COHORT[kind]):.0%} of its SD"
            + (
                ""
                if fast
                else "; use --fast for up to "
                f"{MAX_COHORT['fast']} (kidney statistics without skin meshes)"
            )
        )
        raise _user_error(
            f"--count: at most {MAX_COHORT[kind]} patients"
            f"{' with --fast' if fast else ''}, got {count} ({why})"
        )
    if png and count > MAX_COHORT["png"]:
        raise _user_error(
            f"--count: the overview picture (--png) draws at most "
            f"{MAX_COHORT['png']} kidneys, got {count}"
        )


def _cohort(args) -> int:
    check_cohort_count(args.count, args.fast, bool(args.png))
    t0 = time.time()
    progress = not args.quiet and _tty()
    n = len(cohort_seeds(args.split, args.count))
    per = _SECONDS_PER_PATIENT["fast" if (args.fast and not args.png) else "full"]
    if not args.quiet and n * per > 30:
        import sys

        print(
            f"cohort {args.split}: {n} patients, about {n * per / 60:.0f} min (Ctrl-C stops)",
            file=sys.stderr,
            flush=True,
        )
    if args.stats or not args.png:
        out = cohort_stats(
            args.split, args.count, args.side, args.posture, full=not args.fast, progress=progress
        )
        out["seconds"] = round(time.time() - t0, 1)
        print(dumps_strict(out, indent=2))
    if args.png:
        template = None
        try:
            template = load_template()
        except (FileNotFoundError, ValueError):
            pass
        pats = [
            generate_patient(s, args.side, args.posture, progress=False)
            for s in cohort_seeds(args.split, args.count)
        ]
        plot_cohort_overview(pats, args.png, template)
        print(dumps_strict({"overview_png": args.png}))
    return 0


def _ct_cases(paths: list[str], limit: int | None) -> list[Path]:
    """Label maps named by ``paths``: files, case folders (one label map each) or folders
    of case folders (the KiTS layout ``DIR/case_*/segmentation.nii.gz``), sorted."""
    out = []
    for text in paths:
        p = Path(text)
        if not p.exists():
            raise _user_error(f"PATH: no such file or folder: {p}")
        if p.is_dir() and not any(
            q.is_file() and q.name.lower().endswith(LABEL_MAP_SUFFIXES) for q in p.iterdir()
        ):
            subs = [q for q in sorted(p.iterdir()) if q.is_dir()]
            for q in subs:
                try:
                    out.append(ct_label_map_path(q))
                except (ValueError, FileNotFoundError):
                    continue
            if not subs:
                raise _user_error(f"PATH: {p} holds no label map and no case folders")
        else:
            try:
                out.append(ct_label_map_path(p))
            except ValueError as e:
                raise _user_error(f"PATH: {e}") from None
    return out[:limit] if limit else out


def _ct_row_text(r: dict) -> str:
    name = (
        Path(r["source"]).parent.name
        if Path(r["source"]).name.lower().startswith("segmentation")
        else Path(r["source"]).name
    )
    if "error" in r:
        return f"{name:<14} error     {r['error']}"
    f = r["frame"]
    short = {
        "slice axis": "sl",
        "long axes": "la",
        "separation": "sep",
        "field of view": "fov",
        "poles medial": "pm",
        "poles posterior": "pp",
        "hilum": "hil",
        "posterior half": "ph",
    }
    cues = " ".join(
        f"{short.get(k, k)}:{v['agrees']}/{v['disagrees']}/{v['abstains']}"
        for k, v in f["cues"].items()
    )
    kid = " ".join(
        f"{k['side'][0].upper()}{k['parenchyma_ml']:.0f}+{k['tumour_ml']:.0f}"
        f"{'(cut)' if k['cut'] else ''}"
        for k in r["kidneys"]
    )
    rl = r.get("right_minus_left_mm")
    rl_text = "" if rl is None else f" R-L {rl:+.0f} mm"
    if "definition_dt_mm" in r:
        rl_text += (
            f"  kidney with/without tumour: {r['definition_dt_mm']:.1f} mm "
            f"{r['definition_rot_deg']:.1f} deg"
        )
    warn = f"  disagree: {', '.join(f['conflicts'])}" if f["conflicts"] else ""
    return (
        f"{name:<14} {f['status']:<9} S{f['axes']['superior']} A{f['axes']['anterior']} "
        f"L{f['axes']['left']}  {kid}  {cues}{rl_text}{warn}"
    )


def _definition_summary(rows: list[dict], side: str) -> dict:
    done = [r for r in rows if "definition_dt_mm" in r]
    out = {
        "side": side,
        "kidneys": len(done),
        "skipped": [
            f"{Path(r['source']).parent.name}: {r.get('extra_error') or r.get('error')}"
            for r in rows
            if "definition_dt_mm" not in r
        ],
    }
    for key in ("definition_dt_mm", "definition_rot_deg", "definition_rot_x_deg"):
        v = np.array([r[key] for r in done], dtype=float)
        if len(v):
            out[key[len("definition_") :]] = {
                "mean": round(float(v.mean()), 2),
                "median": round(float(np.median(v)), 2),
                "max": round(float(v.max()), 2),
            }
    return out


def _ct_frame(args) -> int:
    if args.limit is not None and args.limit < 1:
        raise _user_error(f"--limit: expected at least 1, got {args.limit}")
    files = _ct_cases(args.paths, args.limit)
    extra = None
    if args.definitions:

        def extra(case):
            return kidney_definition_difference(case, args.definitions)

    if not files:
        raise _user_error("PATH: no label maps found")
    rows = []
    print(
        "case           status    frame (grid axes)  kidneys (mL parenchyma+tumour)  "
        "cues agree/disagree/abstain",
        flush=True,
    )
    for f in files:
        r = survey_case(f, extra)
        rows.append(r)
        print(_ct_row_text(r), flush=True)
    summary = survey_summary(rows)
    if args.definitions:
        summary["kidney_definitions"] = _definition_summary(rows, args.definitions)
    if args.json:
        summary["rows"] = rows
    print(dumps_strict(summary))
    return 0


def _common(p, spec=True):
    if spec:
        p.add_argument(
            "spec",
            help="seed:N, train:K, test:K, ct:PATH[#OPTIONS] (a real CT "
            "kidney), a mesh directory or a label map",
        )
    p.add_argument("--side", default="right", choices=["right", "left"])
    p.add_argument("--posture", default="supine", choices=["supine", "left_lateral_decubitus"])


def add_commands(subparsers) -> None:
    if check_patient_arguments not in PREFLIGHT_CHECKS:
        PREFLIGHT_CHECKS.append(check_patient_arguments)
    c = subparsers.add_parser("cohort", help="virtual patient cohorts: statistics, overview")
    c.add_argument("--split", default="test", choices=["train", "test"])
    c.add_argument("--count", type=int, default=None, help="patients (default 20 train, 15 test)")
    c.add_argument("--stats", action="store_true", help="print summary statistics as JSON")
    c.add_argument(
        "--fast",
        action="store_true",
        help="statistics without skin meshes (depth from the analytic body)",
    )
    c.add_argument("--png", default=None, help="write a canonical-frame overview picture")
    c.add_argument("--quiet", action="store_true")
    _common(c, spec=False)
    c.set_defaults(func=_cohort, outputs={"png": "file:.png"})

    p = subparsers.add_parser("patient", help="one patient: info, export, show")
    sub = p.add_subparsers(dest="patient_command", metavar="ACTION")
    sub.required = True
    i = sub.add_parser("info", help="kidney frame, size, volume and depth as JSON")
    _common(i)
    i.add_argument("--voxel-mm", type=float, default=1.0)
    i.set_defaults(func=_info)
    e = sub.add_parser("export", help="label volume (NRRD/NIfTI) + STL meshes for 3D Slicer")
    _common(e)
    e.add_argument("--out", required=True, help="output directory")
    e.add_argument("--format", default="nrrd", choices=["nrrd", "nifti"])
    e.add_argument("--voxel-mm", type=float, default=1.0)
    e.set_defaults(func=_export, outputs={"out": "dir"})
    s = sub.add_parser("show", help="orthogonal label slices (PNG), optionally Meshcat 3-D")
    _common(s)
    s.add_argument("--png", required=True)
    s.add_argument("--voxel-mm", type=float, default=1.0)
    s.add_argument("--meshcat", action="store_true", help="also show in Meshcat until Ctrl-C")
    s.set_defaults(func=_show, outputs={"png": "file:.png"})
    f = sub.add_parser(
        "ct-frame",
        help="the patient frame of real CT kidney label maps "
        "(KiTS style), each cue's verdict, usable kidneys",
    )
    f.add_argument(
        "paths",
        nargs="+",
        metavar="PATH",
        help="label maps, case folders, or a folder of case folders (KiTS layout)",
    )
    f.add_argument("--limit", type=int, default=None, help="at most this many cases")
    f.add_argument("--json", action="store_true", help="every case's full report in the JSON")
    f.add_argument(
        "--definitions",
        choices=["right", "left"],
        default=None,
        help="also measure, for this side's kidney, how far the true pose of "
        "kidney+tumour lies from that of the parenchyma alone",
    )
    f.set_defaults(func=_ct_frame)
