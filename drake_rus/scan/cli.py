"""``drake-rus scan``: the full autonomous kidney scan (seed Fig. 2) on a patient.

land -> EXPLORE (transverse sweep at v_scan with image centring, eq. 17, collecting the partial
cloud) -> LOCALIZE (template registration, eq. 18-19) -> TRANSIT (slide to the optimal pivot
pose, eq. 20-22) -> PIVOT (eq. 23, bounded by the segmentation) -> DONE, or ABORT with a
reason. Writes summary.json, the clouds, plots and a Meshcat recording to --out.
"""

import argparse
import dataclasses
import sys
import warnings
from pathlib import Path

from drake_rus.anatomy.cli import load_patient_for
from drake_rus.cli import UserError
from drake_rus.config_schema import ScenarioError
from drake_rus.demo import MakeMeshcat, add_scenario_arguments, load_scenario_from_args
from drake_rus.io_utils import MB, check_output_file, dumps_strict, output_dir, write_text_atomic
from drake_rus.localization.localize import load_registration_template
from drake_rus.paths import REPO_ROOT
from drake_rus.progress import SaveMeshcatRecording, stderr_is_terminal
from drake_rus.robot import IkError
from drake_rus.scan.metrics import ScanMetrics, Summary
from drake_rus.scan.planning import StartPlanError
from drake_rus.scan.report import WriteScanOutputs
from drake_rus.scan.run import RunScan
from drake_rus.template.ct import CtTemplateError, resolve_template

# About what a scan writes (bytes): summary, clouds and plots; the Meshcat recording.
SCAN_OUTPUT_BYTES = 8 * MB
RECORDING_BYTES = 40 * MB
# Exit status of a scan stopped with Ctrl-C (128 + SIGINT), after its partial outputs.
EXIT_INTERRUPTED = 130


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
    p.add_argument("--template", default=None, metavar="SPEC",
                   help="registration template: generated (the shipped template of generated "
                        "kidneys), real (real CT kidneys of ../shared/anatomy/kits19, built on "
                        "first use into the cache, without the scanned case), real:DIR, or a "
                        "template .npz (default: the scenario's localization.template)")
    p.set_defaults(func=run_scan_command, outputs={"out": "dir", "record": "file:.html"})


def run_scan_command(args) -> int:
    scenario = load_scenario_from_args(args)
    if args.seed is not None:
        scenario = dataclasses.replace(scenario, random_seed=args.seed)
    scenario = select_template(scenario, args.template, args.patient)
    template = load_template_for(scenario)
    record = not args.no_record
    need = SCAN_OUTPUT_BYTES + (RECORDING_BYTES if record and not args.record else 0)
    if record and args.record:
        check_output_file(args.record, "--record", need_bytes=RECORDING_BYTES,
                          suffixes=(".html",))
    # The output folder is checked and locked before any work, and removed again if the run
    # fails before writing into it.
    with output_dir(args.out, "--out", need_bytes=need, what="scan") as out:
        return _scan(args, scenario, template, out)


def select_template(scenario, spec, patient: str):
    """The scenario with ``localization.template`` resolved to a file: ``spec`` (--template)
    or else the scenario's value (:func:`drake_rus.template.ct.resolve_template`). A real
    template is built without the patient's case; a template file that the patient's case
    helped build is used with a warning."""
    value = spec if spec is not None else scenario.localization.template
    where = "--template" if spec is not None else "field 'localization.template'"
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            path = resolve_template(value, exclude_cases=[patient], log=_stderr_line)
    except CtTemplateError as e:
        if spec is not None:
            raise UserError(f"--template: {e.detail if e.field == 'template' else e}") from None
        raise ScenarioError(f"{where}: {e}") from None
    for w in caught:
        print(f"warning: {w.message}", file=sys.stderr, flush=True)
    if spec is not None and not path.is_file():
        raise UserError(f"--template: {path}: no such template file (expected generated, "
                        f"real, real:DIR or a template .npz)")
    return dataclasses.replace(scenario, localization=dataclasses.replace(
        scenario.localization, template=str(path)))


def _stderr_line(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def load_template_for(scenario):
    """The scenario's registration template; errors name ``localization.template``."""
    path = scenario.localization.template
    if path and (REPO_ROOT / path).is_dir():
        raise ScenarioError(f"field 'localization.template': {REPO_ROOT / path} is a folder; "
                            "expected a template .npz file")
    try:
        return load_registration_template(path)
    except FileNotFoundError as e:
        raise FileNotFoundError(
            f"localization.template: {e} (build one with 'drake-rus template build')") from None
    except ValueError as e:
        raise ScenarioError(f"field 'localization.template': {e}") from None


def _scan(args, scenario, template, out: Path) -> int:
    patient = None
    if not scenario.hardware:    # on hardware the patient is the one on the bed
        print(f"patient {args.patient}: loading ...", flush=True)
        patient = load_patient_for(args.patient, "--patient", side=scenario.patient.side,
                                   posture=scenario.patient.posture,
                                   progress=stderr_is_terminal())
    meshcat = None
    if args.meshcat or not args.no_record:
        meshcat = MakeMeshcat()
        if args.meshcat:
            print(f"Meshcat: {meshcat.web_url()}", flush=True)
        meshcat.StartRecording(frames_per_second=20.0)
    try:
        result = RunScan(scenario, patient, template, meshcat=meshcat,
                         max_sim_time=args.max_sim_time)
    except (IkError, StartPlanError) as e:
        raise UserError(f"--patient {args.patient} (patient.X_BPt, start): no start pose: "
                        f"{e}") from None
    metrics = ScanMetrics(result)
    summary = Summary(result, metrics)
    if result.status == "INTERRUPTED":
        # Ctrl-C: the user wants to stop; write the partial summary only (a few ms).
        path = write_text_atomic(out / "summary.json",
                                 dumps_strict(summary, indent=2, default=str) + "\n")
        print(f"INTERRUPTED: {summary['reason']}; wrote {path}", flush=True)
        return EXIT_INTERRUPTED
    written = WriteScanOutputs(result, metrics, summary, out)
    if meshcat is not None and not args.no_record:
        record = Path(args.record) if args.record else out / "scan.html"
        SaveMeshcatRecording(meshcat, record)
        written.append(record)
    e_t, e_r, V = summary["e_trans_mm"], summary["e_rot_x_deg"], summary["volume_ratio"]
    print(f"{summary['status']}{': ' + summary['reason'] if summary['status'] != 'DONE' else ''}"
          f" | E_trans {_r(e_t, 2)} mm, E_rot,x {_r(e_r, 2)} deg | pole to pole: eps "
          f"{_r(summary['eps_mm'], 1)} mm, n {summary['n_frames']}, V {_r(V, 3)} | whole "
          f"pivot: eps {_r(summary.get('eps_whole_pivot_mm'), 1)} mm, n "
          f"{summary.get('n_whole_pivot')}, V {_r(summary.get('volume_ratio_whole_pivot'), 3)}"
          f" | {summary['sim_s']:.1f} sim s in {summary['wall_s']:.1f} s")
    sweep = summary.get("sweep") or {}
    if sweep.get("kind") == "line" or sweep.get("pivot_pose") == "given":
        print(f"sweep: {sweep['text']}")
    print("wrote " + ", ".join(str(p) for p in written))
    return 0 if summary["status"] == "DONE" else 1


def _r(value, digits):
    """A number rounded for the one-line report (None and NaN as None)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return round(v, digits) if v == v else None
