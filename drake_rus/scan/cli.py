"""``drake-rus scan``: the full autonomous kidney scan (seed Fig. 2) on a patient.

land -> EXPLORE (transverse sweep at v_scan with image centring, eq. 17, collecting the partial
cloud) -> LOCALIZE (template registration, eq. 18-19) -> TRANSIT (slide to the optimal pivot
pose, eq. 20-22) -> PIVOT (eq. 23, bounded by the segmentation) -> DONE, or ABORT with a
reason. Writes summary.json, the clouds, plots and a Meshcat recording to --out.
"""

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from drake_rus.anatomy import load_patient
from drake_rus.demo import MakeMeshcat, add_scenario_arguments, load_scenario_from_args
from drake_rus.localization.localize import load_registration_template
from drake_rus.progress import SaveMeshcatRecording
from drake_rus.scan.metrics import ScanMetrics, Summary
from drake_rus.scan.report import WriteScanOutputs
from drake_rus.scan.run import RunScan


def add_commands(subparsers) -> None:
    p = subparsers.add_parser(
        "scan", help="the full autonomous kidney scan on a virtual (or real) patient",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scenario_arguments(p)
    p.add_argument("--patient", default="test:0",
                   help="test:K or train:K (cohort member), seed:N (any generator seed), or a "
                        "patient directory/file (default test:0)")
    p.add_argument("--out", default="runs/scan", help="output directory (default runs/scan)")
    p.add_argument("--meshcat", action="store_true", help="live Meshcat (URL printed)")
    p.add_argument("--record", default=None,
                   help="Meshcat recording file (default OUT/scan.html)")
    p.add_argument("--no-record", action="store_true", help="skip the Meshcat recording")
    p.add_argument("--seed", type=int, default=None, help="random seed (speckle, noise)")
    p.add_argument("--max-sim-time", type=float, default=150.0,
                   help="give up after this much simulated time in s (default 150)")
    p.set_defaults(func=run_scan_command)


def run_scan_command(args) -> int:
    scenario = load_scenario_from_args(args)
    if args.seed is not None:
        if args.seed < 0:
            raise ValueError(f"--seed: expected a non-negative integer, got {args.seed}")
        scenario = dataclasses.replace(scenario, random_seed=args.seed)
    if not (np.isfinite(args.max_sim_time) and args.max_sim_time > 0):
        raise ValueError(f"--max-sim-time: expected a positive time in s, got {args.max_sim_time}")
    try:
        template = load_registration_template(scenario.localization.template)
    except FileNotFoundError as e:
        raise FileNotFoundError(
            f"localization.template: {e} (build one with 'drake-rus template build')") from None
    patient = None
    if not scenario.hardware:    # on hardware the patient is the one on the bed
        print(f"patient {args.patient}: loading ...", flush=True)
        patient = load_patient(args.patient, side=scenario.patient.side,
                               posture=scenario.patient.posture)
    meshcat = None
    if args.meshcat or not args.no_record:
        meshcat = MakeMeshcat()
        if args.meshcat:
            print(f"Meshcat: {meshcat.web_url()}", flush=True)
        meshcat.StartRecording(frames_per_second=20.0)
    result = RunScan(scenario, patient, template, meshcat=meshcat,
                     max_sim_time=args.max_sim_time)
    out = Path(args.out)
    metrics = ScanMetrics(result)
    summary = Summary(result, metrics)
    written = WriteScanOutputs(result, metrics, summary, out)
    if meshcat is not None and not args.no_record:
        record = Path(args.record) if args.record else out / "scan.html"
        SaveMeshcatRecording(meshcat, record)
        written.append(record)
    e_t, e_r, V = summary["e_trans_mm"], summary["e_rot_x_deg"], summary["volume_ratio"]
    print(f"{summary['status']}{': ' + summary['reason'] if summary['status'] != 'DONE' else ''}"
          f" | E_trans {e_t if e_t is None else round(e_t, 2)} mm, E_rot,x "
          f"{e_r if e_r is None else round(e_r, 2)} deg | eps {summary['eps_mm']:.1f} mm, "
          f"n {summary['n_frames']}, V {V if V is None else round(V, 3)} | "
          f"{summary['sim_s']:.1f} sim s in {summary['wall_s']:.1f} s")
    print("wrote " + ", ".join(str(p) for p in written))
    return 0 if summary["status"] == "DONE" else 1
