"""``drake-rus render-diagram``: draws the station or the whole scan diagram with Graphviz."""

import shutil
import subprocess
from pathlib import Path

from drake_rus.anatomy.cli import load_patient_for
from drake_rus.cli import UserError
from drake_rus.demo import add_scenario_arguments, load_scenario_from_args
from drake_rus.io_utils import atomic_path, check_output_file
from drake_rus.progress import stderr_is_terminal
from drake_rus.scan import BuildScanDiagram
from drake_rus.scan.cli import load_template_for
from drake_rus.stations import MakeStation


def add_commands(subparsers) -> None:
    p = subparsers.add_parser("render-diagram",
                              help="draw the station or the scan diagram (SVG or PNG)")
    add_scenario_arguments(p)
    p.add_argument("--diagram", choices=["station", "scan"], default="station",
                   help="'station' (the station alone) or 'scan' (station + segmenter, "
                        "localizer, controller, safety, monitors on a virtual patient)")
    p.add_argument("--patient", default="test:0",
                   help="patient of the simulated scan diagram (default test:0)")
    p.add_argument("--out", default=None,
                   help="output file; .svg or .png (default diagrams/DIAGRAM.svg)")
    p.add_argument("--depth", type=int, default=1,
                   help="subsystem nesting depth to draw (0 or more; default 1)")
    p.set_defaults(func=run_render, outputs={"out": "file:.svg,.png"})


def render_graphviz(dot_source: str, out: Path) -> Path:
    """Renders Graphviz ``dot_source`` to ``out`` (.svg or .png), atomically."""
    fmt = out.suffix.lower().lstrip(".")
    if fmt not in ("svg", "png"):
        raise UserError(f"--out: expected a .svg or .png file name, got {out}")
    dot = shutil.which("dot")
    if dot is None:
        raise UserError("Graphviz 'dot' is not installed (apt-get install graphviz)")
    with atomic_path(out) as tmp:
        subprocess.run([dot, f"-T{fmt}", "-o", str(tmp)], input=dot_source.encode(),
                       check=True, capture_output=True)
    return out


def run_render(args) -> int:
    scenario = load_scenario_from_args(args)
    out = check_output_file(args.out or f"diagrams/{args.diagram}.svg", "--out",
                            suffixes=(".svg", ".png"))
    if shutil.which("dot") is None:
        raise UserError("Graphviz 'dot' is not installed (apt-get install graphviz)")
    if args.diagram == "station":
        diagram = MakeStation(scenario)
    else:
        template = load_template_for(scenario)
        patient = None if scenario.hardware else load_patient_for(
            args.patient, "--patient", side=scenario.patient.side,
            posture=scenario.patient.posture, progress=stderr_is_terminal())
        station = MakeStation(scenario, patient=patient)
        builder, _ = BuildScanDiagram(scenario, station, template)
        diagram = builder.Build()
        diagram.set_name("scan")
    out = render_graphviz(diagram.GetGraphvizString(max_depth=args.depth), out)
    print(f"wrote {out}")
    return 0
