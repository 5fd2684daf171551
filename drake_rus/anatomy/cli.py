"""``drake-rus cohort`` and ``drake-rus patient info|export|show``."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from drake_rus.anatomy.cohort import cohort_seeds, cohort_stats, load_patient
from drake_rus.anatomy.generator import generate_patient
from drake_rus.anatomy.pictures import plot_cohort_overview, plot_label_slices, show_in_meshcat
from drake_rus.cli import UserError
from drake_rus.template import load_template


def _user_error(e):
    return UserError(str(e))


def _load(args):
    try:
        return load_patient(args.spec, side=args.side, posture=args.posture,
                            voxel_size=args.voxel_mm / 1000.0)
    except ValueError as e:
        raise _user_error(e) from None


def patient_info(patient) -> dict:
    m = patient.metrics()
    R = patient.X_PtK.rotation().matrix()
    deg = 180.0 / np.pi
    info = {
        "name": patient.name, "source": patient.meta.get("source"), "side": patient.side,
        "posture": patient.posture,
        "X_PtK": {"p_mm": (patient.X_PtK.translation() * 1e3).round(1).tolist(),
                  "x_k": R[:, 0].round(4).tolist(), "y_k": R[:, 1].round(4).tolist(),
                  "z_k": R[:, 2].round(4).tolist()},
        "length_mm": round(m["length"] * 1e3, 1), "width_mm": round(m["width"] * 1e3, 1),
        "thickness_mm": round(m["thickness"] * 1e3, 1), "volume_ml": round(m["volume"] * 1e6, 1),
        "depth_below_upper_skin_mm": round(m["depth_vertical"] * 1e3, 1),
        "shortest_skin_distance_mm": round(m["depth_min"] * 1e3, 1),
        "coronal_angle_deg": round(m["coronal_angle"] * deg, 1),
        "sagittal_angle_deg": round(m["sagittal_angle"] * deg, 1),
    }
    if "hilum_angle" in patient.meta:
        info["hilum_angle_deg"] = round(patient.meta["hilum_angle"] * deg, 1)
    if "size_class" in patient.meta:
        info["size_class"] = patient.meta["size_class"]
    return info


def _info(args) -> int:
    p = _load(args)
    print(json.dumps(patient_info(p), indent=2))
    return 0


def _export(args) -> int:
    p = _load(args)
    try:
        paths = p.export(args.out, args.format)
    except ValueError as e:
        raise _user_error(e) from None
    print(json.dumps({"written": [str(x) for x in paths]}, indent=2))
    return 0


def _show(args) -> int:
    p = _load(args)
    out = Path(args.png)
    plot_label_slices(p, out)
    print(json.dumps({"slices_png": str(out)}))
    if args.meshcat:
        from pydrake.geometry import Meshcat
        meshcat = Meshcat()
        show_in_meshcat(p, meshcat)
        print(f"Meshcat: {meshcat.web_url()} (Ctrl-C to quit)", flush=True)
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
    return 0


def _cohort(args) -> int:
    if args.count is not None and args.count < 1:
        raise _user_error(f"--count: expected at least 1, got {args.count}")
    t0 = time.time()
    if args.stats or not args.png:
        out = cohort_stats(args.split, args.count, args.side, args.posture, full=not args.fast,
                           progress=not args.quiet)
        out["seconds"] = round(time.time() - t0, 1)
        print(json.dumps(out, indent=2))
    if args.png:
        template = None
        try:
            template = load_template()
        except (FileNotFoundError, ValueError):
            pass
        pats = [generate_patient(s, args.side, args.posture, progress=False)
                for s in cohort_seeds(args.split, args.count)]
        plot_cohort_overview(pats, args.png, template)
        print(json.dumps({"overview_png": args.png}))
    return 0


def _common(p, spec=True):
    if spec:
        p.add_argument("spec", help="seed:N, train:K, test:K, a mesh directory or a label map")
    p.add_argument("--side", default="right", choices=["right", "left"])
    p.add_argument("--posture", default="supine", choices=["supine", "left_lateral_decubitus"])


def add_commands(subparsers) -> None:
    c = subparsers.add_parser("cohort", help="virtual patient cohorts: statistics, overview")
    c.add_argument("--split", default="test", choices=["train", "test"])
    c.add_argument("--count", type=int, default=None, help="patients (default 20 train, 15 test)")
    c.add_argument("--stats", action="store_true", help="print summary statistics as JSON")
    c.add_argument("--fast", action="store_true",
                   help="statistics without skin meshes (depth from the analytic body)")
    c.add_argument("--png", default=None, help="write a canonical-frame overview picture")
    c.add_argument("--quiet", action="store_true")
    _common(c, spec=False)
    c.set_defaults(func=_cohort)

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
    e.set_defaults(func=_export)
    s = sub.add_parser("show", help="orthogonal label slices (PNG), optionally Meshcat 3-D")
    _common(s)
    s.add_argument("--png", required=True)
    s.add_argument("--voxel-mm", type=float, default=1.0)
    s.add_argument("--meshcat", action="store_true", help="also show in Meshcat until Ctrl-C")
    s.set_defaults(func=_show)
