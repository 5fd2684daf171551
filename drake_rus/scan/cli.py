"""``drake-rus scan``: the full autonomous kidney scan (seed Fig. 2) on a patient.

land -> EXPLORE (transverse sweep at v_scan with image centring, eq. 17, collecting the partial
cloud) -> LOCALIZE (template registration, eq. 18-19) -> TRANSIT (slide to the optimal pivot
pose, eq. 20-22) -> PIVOT (eq. 23, bounded by the segmentation) -> DONE, or ABORT with a
reason. Before it says DONE the scan checks its own result (summary.json "checks"; the
scenario's verdict section): the kidney left the image at both ends of the pivot, what the
segmentation saw agrees with the registered template, and the registration is sound.
Writes summary.json, the clouds, plots and a Meshcat recording to --out.

status (summary.json) and exit status:
  DONE         0    the scan finished and passed every check of its result
  INCOMPLETE   1    it finished, but a check failed (the reason names it and its figure)
  ABORT        1    stopped on the way: safety stop, localization failed, timeout of a
                    phase, kidney moved, ... (the reason says which)
  TIMEOUT      1    still scanning at --max-sim-time
  INTERRUPTED  130  stopped with Ctrl-C; a partial summary.json only
  (bad input)  2    a bad argument, scenario field, patient or template: nothing written
"""

import argparse
import contextlib
import dataclasses
import hashlib
import json
import sys
import warnings
from pathlib import Path

from drake_rus import interrupts
from drake_rus.anatomy.cli import check_patient_arguments, load_patient_for
from drake_rus.cli import (
    EXIT_STATUS_HELP,
    MakeMeshcat,
    UserError,
    add_scenario_arguments,
    check_arguments,
    load_scenario_from_args,
)
from drake_rus.config_schema import ScenarioError
from drake_rus.imaging.annotated import write_annotated_frames
from drake_rus.imaging.onnx_backend import OnnxSegmenter, resolve_model_path
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.io_utils import MB, check_output_file, dumps_strict, output_dir, write_text_atomic
from drake_rus.localization.localize import load_registration_template
from drake_rus.paths import REPO_ROOT
from drake_rus.progress import SaveMeshcatRecording, stderr_is_terminal
from drake_rus.provenance import Provenance
from drake_rus.robot import IkError
from drake_rus.scan.metrics import ScanMetrics, Summary
from drake_rus.scan.planning import StartPlanError
from drake_rus.scan.report import WriteScanOutputs
from drake_rus.scan.run import RunScan
from drake_rus.scenario import DEFAULT_SCENARIOS_FILE, ApplyOverrides, CheckScenario, Scenario
from drake_rus.template.ct import CtTemplateError, resolve_template

# About what a scan writes (bytes): summary, clouds and plots; the Meshcat recording.
SCAN_OUTPUT_BYTES = 8 * MB
RECORDING_BYTES = 40 * MB
DEFAULT_PATIENT = "test:0"
DEFAULT_MAX_SIM_TIME = 150.0
# What each recorded seed seeds (summary.json: provenance.seeds; metric_definitions-like).
SEED_USES = {
    "random_seed": "scenario.random_seed (after --seed): the emulator's speckle (frame k from "
    "(random_seed, k)), the start planner's placement-error draw (with "
    "start.placement_seed) and the breath-hold draws (with patient.motion.seed)",
    "seed_argument": "--seed as given (null: the scenario's random_seed)",
    "start_placement_seed": "start.placement_seed: the operator's placement error",
    "patient_motion_seed": "patient.motion.seed: where each breath-hold lands",
    "patient": "the patient spec (--patient)",
    "patient_generator_seed": "the anatomy generator's seed of a seed:/train:/test: patient "
    "(null: an imported patient, see provenance.inputs)",
    "cloud_thinning": "localization: the fixed seed of the partial cloud's thinning to "
    "localization.max_points",
}

RERUN_HELP = """rerun:
  --rerun DIR/summary.json repeats a recorded scan from its summary alone: the patient, the
  resolved scenario (the --set overrides and --seed already in it) and --max-sim-time; only
  --out (default DIR/rerun), --record, --no-record, --meshcat and --save-frames may be
  given with it. If
  this checkout's commit, package versions or input files differ from the recorded ones,
  one warning line says so and the run goes on."""


def add_commands(subparsers) -> None:
    p = subparsers.add_parser(
        "scan",
        help="the full autonomous kidney scan on a virtual (or real) patient",
        description=__doc__,
        epilog=RERUN_HELP + "\n\n" + EXIT_STATUS_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_scenario_arguments(p)
    p.add_argument(
        "--patient",
        default=DEFAULT_PATIENT,
        help="test:K or train:K (cohort member), seed:N (any generator seed), or a "
        "patient directory/file (default test:0)",
    )
    p.add_argument("--out", default=None, help="output directory (default runs/scan)")
    p.add_argument("--meshcat", action="store_true", help="live Meshcat (URL printed)")
    p.add_argument("--record", default=None, help="Meshcat recording file (default OUT/scan.html)")
    p.add_argument("--no-record", action="store_true", help="skip the Meshcat recording")
    p.add_argument(
        "--seed",
        type=int,
        default=None,
        help="random seed (speckle, the start's placement error, breath-holds; "
        "default the scenario's random_seed)",
    )
    p.add_argument(
        "--max-sim-time",
        type=float,
        default=DEFAULT_MAX_SIM_TIME,
        help="give up after this much simulated time in s (default 150)",
    )
    p.add_argument(
        "--rerun",
        default=None,
        metavar="SUMMARY",
        help="repeat the scan recorded in SUMMARY (its summary.json or folder); see 'rerun' below",
    )
    p.add_argument(
        "--template",
        default=None,
        metavar="SPEC",
        help="registration template: generated (the shipped template of generated "
        "kidneys), real (real CT kidneys of ../shared/anatomy/kits19, built on "
        "first use into the cache, without the scanned case), real:DIR, or a "
        "template .npz (default: the scenario's localization.template)",
    )
    p.add_argument(
        "--save-frames",
        default=None,
        metavar="DIR",
        help="also write every frame (grey image, the segmenter's kidney mask, probe pose, "
        "time) to DIR in the Open Kidney Ultrasound Data Set's mask layout, ready to "
        "annotate and to fine-tune on (docs/imaging.md, 'Bring your own frames'); DIR "
        "must not exist or be empty",
    )
    p.set_defaults(
        func=run_scan_command,
        outputs={"out": "dir", "record": "file:.html", "save_frames": "dir"},
    )


# ------------------------------------------------------------------------ reproducibility
def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _file_record(path: Path) -> dict:
    try:
        return {"path": str(path), "sha256": _sha256(path)}
    except OSError:
        return {"path": str(path), "sha256": None}


def input_files(scenario, patient_spec: str | None) -> dict:
    """{what: {"path", "sha256"}} of the files a scan reads besides its scenario: the
    registration template, the ONNX segmenter and its card, an imported patient's files."""
    files = {}
    template = scenario.localization.template
    files["localization.template"] = _file_record(
        Path(template) if str(template).startswith("/") else REPO_ROOT / template
    )
    if scenario.imaging.segmenter == "onnx":
        model = resolve_model_path(scenario.imaging.onnx_model)
        files["imaging.onnx_model"] = _file_record(model)
        if model.with_suffix(".json").is_file():
            files["imaging.onnx_model card"] = _file_record(model.with_suffix(".json"))
    path = Path(patient_spec) if patient_spec and not scenario.hardware else None
    if path is not None and path.is_file():
        files["patient"] = _file_record(path)
    elif path is not None and path.is_dir():
        for k, f in enumerate(sorted(q for q in path.iterdir() if q.is_file())):
            if k >= 500:
                break
            files[f"patient/{f.name}"] = _file_record(f)
    return files


def scan_provenance(args, scenario) -> dict:
    """summary.json's ``provenance``: the resolved scenario, how it was made, the seeds
    (completed with the patient's once loaded), versions, commit, input files and the
    arguments a rerun needs."""
    rerun = getattr(args, "rerun_record", None)
    record = Provenance(
        scenario,
        scenario_name=args.scenario,
        scenarios_file=args.scenarios_file,
        overrides=args.overrides,
        seeds=scan_seeds(scenario, args, None),
        argv=getattr(args, "argv", None),
    )
    if rerun is not None:
        for key in ("scenario_name", "scenarios_file", "overrides"):
            record[key] = rerun["provenance"].get(key)
        record["rerun_of"] = rerun["path"]
    record["command"] = "scan"
    record["arguments"] = {
        "patient": args.patient,
        "max_sim_time": args.max_sim_time,
        "seed": args.seed,
        "record": not args.no_record,
    }
    record["inputs"] = input_files(scenario, args.patient)
    record["seed_uses"] = SEED_USES
    return record


def scan_seeds(scenario, args, patient) -> dict:
    """Every seed of a scan's random draws (see SEED_USES)."""
    meta = getattr(patient, "meta", None) or {}
    return {
        "random_seed": int(scenario.random_seed),
        "seed_argument": args.seed,
        "start_placement_seed": int(scenario.start.placement_seed),
        "patient_motion_seed": int(scenario.patient.motion.seed),
        "patient": None if scenario.hardware else args.patient,
        "patient_generator_seed": (
            int(meta["seed"]) if meta.get("source") == "generator" else None
        ),
        "cloud_thinning": 0,
    }


def read_rerun(spec: str) -> dict:
    """The recorded run of ``--rerun SPEC`` (a summary.json or its folder): {"path",
    "summary", "provenance", "scenario"}; UserError naming --rerun otherwise."""
    path = Path(spec)
    if path.is_dir():
        path = path / "summary.json"
    if not path.is_file():
        raise UserError(f"--rerun: no such file {path}; expected a scan's summary.json")
    try:
        summary = json.loads(path.read_text(errors="replace"))
    except (OSError, ValueError) as e:
        raise UserError(
            f"--rerun: {path} is not a drake-rus scan summary (not JSON: {e})"
        ) from None
    if not isinstance(summary, dict) or "status" not in summary:
        raise UserError(f"--rerun: {path} is not a drake-rus scan summary (no 'status')")
    prov = summary.get("provenance")
    if not isinstance(prov, dict) or not isinstance(prov.get("scenario_yaml"), str):
        raise UserError(
            f"--rerun: {path} records no provenance (a summary of an older "
            "drake-rus, or not a scan's); it cannot be repeated"
        )
    if prov.get("command", "scan") != "scan" or not isinstance(prov.get("arguments"), dict):
        raise UserError(
            f"--rerun: {path} is the summary of 'drake-rus {prov.get('command')}'"
            "; scan --rerun repeats scans"
        )
    arguments = prov["arguments"]
    patient, max_sim_time = arguments.get("patient"), arguments.get("max_sim_time")
    if not isinstance(patient, str) or not isinstance(max_sim_time, (int, float)):
        raise UserError(f"--rerun: {path}: provenance.arguments lacks the patient or max_sim_time")
    try:
        scenario = ApplyOverrides(
            Scenario(), prov["scenario_yaml"], context=f"--rerun: {path}: provenance.scenario_yaml"
        )
        CheckScenario(scenario)
    except ScenarioError as e:
        text = str(e)
        raise UserError(
            text if text.startswith("--rerun") else f"--rerun: {path}: {text}"
        ) from None
    if scenario.hardware:
        raise UserError(
            f"--rerun: {path} records a run on hardware (hardware: true); a rerun "
            "repeats simulated runs only"
        )
    return {"path": str(path), "summary": summary, "provenance": prov, "scenario": scenario}


def _apply_rerun(args) -> None:
    """Fills ``args`` from ``--rerun`` (patient, --max-sim-time, --out default) after
    refusing arguments that would change the run; checks them as preflight checks given
    ones; warns (one line) when software or inputs differ from the recorded run's."""
    given = [
        flag
        for flag, value, default in (
            ("--scenario", args.scenario, "default"),
            ("--scenarios-file", args.scenarios_file, str(DEFAULT_SCENARIOS_FILE)),
            ("--set", args.overrides, None),
            ("--seed", args.seed, None),
            ("--template", args.template, None),
            ("--patient", args.patient, DEFAULT_PATIENT),
            ("--max-sim-time", args.max_sim_time, DEFAULT_MAX_SIM_TIME),
        )
        if value != default
    ]
    if given:
        raise UserError(
            f"--rerun: repeats the recorded run as it was; {', '.join(given)} "
            "cannot be given with it (only --out, --record, --no-record, "
            "--meshcat, --save-frames)"
        )
    rerun = read_rerun(args.rerun)
    arguments = rerun["provenance"]["arguments"]
    args.patient = arguments["patient"]
    args.max_sim_time = float(arguments["max_sim_time"])
    args.seed = arguments.get("seed")
    args.rerun_record = rerun
    recorded_dir = Path(rerun["path"]).parent
    if args.out is None:
        args.out = str(recorded_dir / "rerun")
    if Path(args.out).resolve() == recorded_dir.resolve():
        raise UserError(
            f"--out: {args.out} holds the recorded run; the rerun would overwrite "
            "it (choose another --out)"
        )
    check_arguments(args)
    check_patient_arguments(args)
    differences = rerun_differences(
        rerun["provenance"], Provenance(None, argv=[]), input_files(rerun["scenario"], args.patient)
    )
    if differences:
        print(
            f"drake-rus scan: warning: --rerun: {rerun['path']} was recorded with "
            f"{'; '.join(differences)}: the results may differ",
            file=sys.stderr,
            flush=True,
        )


def rerun_differences(recorded: dict, now: dict, files: dict) -> list[str]:
    """What differs between a recorded provenance and this process (commit, uncommitted
    changes, Python, package versions, input files), each as 'what recorded -> now'."""
    out = []
    a, b = recorded.get("commit"), now.get("commit")
    if a != b:
        out.append(f"commit {(a or 'unknown')[:12]} -> now {(b or 'unknown')[:12]}")
    if recorded.get("dirty") or now.get("dirty"):
        out.append(
            "uncommitted changes"
            + (" (then)" if recorded.get("dirty") else "")
            + (" (now)" if now.get("dirty") else "")
        )
    if recorded.get("python") != now.get("python"):
        out.append(f"Python {recorded.get('python')} -> now {now.get('python')}")
    old, new = recorded.get("packages") or {}, now.get("packages") or {}
    for name in sorted(set(old) | set(new)):
        if old.get(name) != new.get(name):
            out.append(f"{name} {old.get(name)} -> now {new.get(name)}")
    old_files = recorded.get("inputs") or {}
    for what, rec in sorted(files.items()):
        before = old_files.get(what)
        if before is not None and before.get("sha256") != rec.get("sha256"):
            out.append(f"{what} {rec['path']} changed since")
    return out


# ------------------------------------------------------------------------ the command
def run_scan_command(args) -> int:
    if args.rerun:
        _apply_rerun(args)
        scenario = args.rerun_record["scenario"]
    else:
        scenario = load_scenario_from_args(args)
        if args.seed is not None:
            scenario = dataclasses.replace(scenario, random_seed=args.seed)
        scenario = select_template(scenario, args.template, args.patient)
    if args.out is None:
        args.out = "runs/scan"
    template = load_template_for(scenario)
    check_segmenter(scenario)
    if args.save_frames is not None:
        frames_dir = Path(args.save_frames)
        if frames_dir.exists() and any(frames_dir.iterdir()):
            raise UserError(f"--save-frames: {frames_dir} is not empty; give a new folder")
    provenance = scan_provenance(args, scenario)
    record = not args.no_record
    need = SCAN_OUTPUT_BYTES + (RECORDING_BYTES if record and not args.record else 0)
    if record and args.record:
        check_output_file(args.record, "--record", need_bytes=RECORDING_BYTES, suffixes=(".html",))
    # The output folder is checked and locked before any work, and removed again if the run
    # fails before writing into it. A signal from here on leaves an INTERRUPTED summary: one
    # that arrives while the lock is taken waits (deferred) until the run can write it.
    with contextlib.ExitStack() as stack:
        with interrupts.deferred(reraise=False):
            out = stack.enter_context(
                output_dir(
                    args.out,
                    "--out",
                    need_bytes=need,
                    what="scan",
                    argv=getattr(args, "argv", None),
                )
            )
            run = _ScanRun(args, scenario, template, out, provenance)
        try:
            interrupts.check()
            return run.go()
        except BaseException as e:
            if not (isinstance(e, KeyboardInterrupt) or interrupts.pending() is not None):
                raise
            return run.interrupted(e)


def check_segmenter(scenario) -> None:
    """Loads the scenario's ONNX segmenter once before any work, so that a model that does
    not fit (file, input or output type and shape, card) is named (imaging.onnx_model) at
    once, not after the patient and the diagram are built."""
    if scenario.imaging.segmenter == "onnx":
        OnnxSegmenter.from_config(scenario.imaging, ProbeGeometry.from_config(scenario.imaging))


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
        raise UserError(
            f"--template: {path}: no such template file (expected generated, "
            f"real, real:DIR or a template .npz)"
        )
    return dataclasses.replace(
        scenario, localization=dataclasses.replace(scenario.localization, template=str(path))
    )


def _stderr_line(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def load_template_for(scenario):
    """The scenario's registration template; errors name ``localization.template``."""
    path = scenario.localization.template
    if path and (REPO_ROOT / path).is_dir():
        raise ScenarioError(
            f"field 'localization.template': {REPO_ROOT / path} is a folder; "
            "expected a template .npz file"
        )
    try:
        return load_registration_template(path)
    except FileNotFoundError as e:
        # The message already says how to build one (drake_rus.template.io).
        raise FileNotFoundError(f"localization.template: {e}") from None
    except ValueError as e:
        raise ScenarioError(f"field 'localization.template': {e}") from None


class _ScanRun:
    """One scan into a locked output folder, knowing how far it got (``stage``) so that a
    signal at any moment leaves an INTERRUPTED summary.json saying where."""

    def __init__(self, args, scenario, template, out: Path, provenance: dict):
        self.args, self.scenario, self.template, self.out = args, scenario, template, out
        self.provenance = provenance
        self.stage = "start-up (loading the patient)"
        self.summary = None

    def go(self) -> int:
        args, scenario = self.args, self.scenario
        patient = None
        if not scenario.hardware:  # on hardware the patient is the one on the bed
            print(f"patient {args.patient}: loading ...", flush=True)
            patient = load_patient_for(
                args.patient,
                "--patient",
                side=scenario.patient.side,
                posture=scenario.patient.posture,
                progress=stderr_is_terminal(),
            )
        self.provenance["seeds"] = scan_seeds(scenario, args, patient)
        self.stage = "start-up (start plan, diagram)"
        meshcat = None
        if args.meshcat or not args.no_record:
            meshcat = MakeMeshcat()
            if args.meshcat:
                print(f"Meshcat: {meshcat.web_url()}", flush=True)
            meshcat.StartRecording(frames_per_second=20.0)
        try:
            result = RunScan(
                scenario,
                patient,
                self.template,
                meshcat=meshcat,
                max_sim_time=args.max_sim_time,
                keep_frames=args.save_frames is not None,
            )
        except (IkError, StartPlanError) as e:
            raise UserError(
                f"--patient {args.patient} (patient.X_BPt, start): no start pose: {e}"
            ) from None
        self.stage = "collecting the results"
        metrics = ScanMetrics(result)
        summary = Summary(result, metrics, provenance=self.provenance)
        if result.status == "INTERRUPTED":
            # A signal during the simulation: write the partial summary only (a few ms).
            with interrupts.deferred(reraise=False):
                path = write_text_atomic(
                    self.out / "summary.json", dumps_strict(summary, indent=2, default=str) + "\n"
                )
            print(f"INTERRUPTED: {summary['reason']}; wrote {path}", flush=True)
            return interrupts.exit_status()
        self.summary = summary
        self.stage = "writing the outputs"
        written = WriteScanOutputs(result, metrics, summary, self.out)
        if meshcat is not None and not args.no_record:
            record = Path(args.record) if args.record else self.out / "scan.html"
            SaveMeshcatRecording(meshcat, record)
            written.append(record)
        if args.save_frames is not None:
            written.append(
                write_annotated_frames(
                    args.save_frames, result.saved_frames, result.scenario.imaging.depth
                )
            )
        interrupts.check()  # a signal swallowed while writing
        e_t, e_r, V = summary["e_trans_mm"], summary["e_rot_x_deg"], summary["volume_ratio"]
        print(
            f"{summary['status']}"
            f"{': ' + summary['reason'] if summary['status'] != 'DONE' else ''}"
            f" | E_trans {_r(e_t, 2)} mm, E_rot,x {_r(e_r, 2)} deg | pole to pole: eps "
            f"{_r(summary['eps_mm'], 1)} mm, n {summary['n_frames']}, V {_r(V, 3)} | whole "
            f"pivot: eps {_r(summary.get('eps_whole_pivot_mm'), 1)} mm, n "
            f"{summary.get('n_whole_pivot')}, V "
            f"{_r(summary.get('volume_ratio_whole_pivot'), 3)}"
            f" | {summary['sim_s']:.1f} sim s in {summary['wall_s']:.1f} s"
        )
        sweep = summary.get("sweep") or {}
        if sweep.get("kind") == "line" or sweep.get("pivot_pose") == "given":
            print(f"sweep: {sweep['text']}")
        print("wrote " + ", ".join(str(p) for p in written))
        return 0 if summary["status"] == "DONE" else 1

    def interrupted(self, exc: BaseException) -> int:
        """Writes the INTERRUPTED summary.json (signals held back meanwhile) and returns the
        exit status (130 Ctrl-C, 143 SIGTERM)."""
        how = f"interrupted by {interrupts.signal_text(interrupts.signal_of(exc))}"
        with interrupts.deferred(reraise=False):
            if self.summary is not None:
                summary = dict(self.summary)
                summary.update(
                    status="INTERRUPTED",
                    scan_status=self.summary["status"],
                    scan_reason=self.summary["reason"],
                    reason=f"{how} while writing the outputs (the scan itself ended "
                    f"{self.summary['status']}); the outputs are partial",
                )
            else:
                summary = {
                    "status": "INTERRUPTED",
                    "reason": f"{how} during {self.stage}; no scan ran",
                    "patient": self.args.patient,
                    "stage": self.stage,
                    "provenance": self.provenance,
                }
            path = write_text_atomic(
                self.out / "summary.json", dumps_strict(summary, indent=2, default=str) + "\n"
            )
        print(f"INTERRUPTED: {summary['reason']}; wrote {path}", flush=True)
        return interrupts.exit_status(exc)


def _r(value, digits):
    """A number rounded for the one-line report (None and NaN as None)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return round(v, digits) if v == v else None
