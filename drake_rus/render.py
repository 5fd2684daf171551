"""``drake-rus render-diagram``: draws the station or the whole scan diagram with Graphviz.

One picture goes to ``--out``, by default ``runs/diagrams/DIAGRAM.svg`` (beside the other
commands' runs, in the current folder; never the committed pictures, which only ``--all``
writes). ``--all`` re-draws every picture committed in ``diagrams/`` (``COMMITTED``, each with its
fixed settings); ``--all --check`` only compares them with the diagrams built now (the
names of the systems and ports, not the bytes, which depend on Graphviz's version) and exits
1 naming what a stale picture lacks or shows in excess. ``tests/test_new_user.py`` runs the
same comparison, so a change to a diagram fails CI until its picture is re-drawn.
"""

import html
import re
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

from drake_rus.anatomy.cli import load_patient_for
from drake_rus.cli import UserError, add_scenario_arguments, load_scenario_from_args
from drake_rus.io_utils import atomic_path, check_output_file
from drake_rus.paths import DIAGRAMS_DIR
from drake_rus.progress import stderr_is_terminal
from drake_rus.scan import BuildScanDiagram
from drake_rus.scan.cli import load_template_for
from drake_rus.scenario import DEFAULT_SCENARIOS_FILE, LoadScenario
from drake_rus.stations import MakeStation

# The pictures committed in diagrams/ and how each is drawn: (diagram, patient, depth), on
# the default scenario.
COMMITTED = {
    "station.svg": ("station", "test:0", 1),
    "scan.svg": ("scan", "test:0", 1),
}
GRAPHVIZ_MISSING = "Graphviz 'dot' is not installed (apt-get install graphviz)"
# Where one picture goes by default (DIAGRAM.svg in it): a user path beside the other runs,
# not diagrams/, whose committed pictures --all draws with their fixed settings.
DEFAULT_OUT_DIR = Path("runs/diagrams")


def add_commands(subparsers) -> None:
    p = subparsers.add_parser(
        "render-diagram", help="draw the station or the scan diagram (SVG or PNG)"
    )
    add_scenario_arguments(p)
    p.add_argument(
        "--diagram",
        choices=["station", "scan"],
        default=None,
        help="'station' (the station alone, the default) or 'scan' (station + "
        "segmenter, localizer, controller, safety, monitors on a virtual "
        "patient)",
    )
    p.add_argument(
        "--patient", default="test:0", help="patient of the simulated scan diagram (default test:0)"
    )
    p.add_argument(
        "--out",
        default=None,
        help=f"output file; .svg or .png (default {DEFAULT_OUT_DIR}/DIAGRAM.svg, DIAGRAM the "
        "--diagram drawn; the committed diagrams/*.svg are re-drawn with --all)",
    )
    p.add_argument(
        "--depth",
        type=int,
        default=1,
        help="subsystem nesting depth to draw (0 or more; default 1)",
    )
    p.add_argument(
        "--all",
        action="store_true",
        help="re-draw every picture committed in diagrams/ ("
        + ", ".join(COMMITTED)
        + ") with its fixed settings",
    )
    p.add_argument(
        "--check",
        action="store_true",
        help="with --all: write nothing; exit 1 if a committed picture's systems "
        "or ports differ from the diagram built now",
    )
    p.set_defaults(func=run_render, outputs={"out": "file:.svg,.png"})


def build_diagram(kind: str, scenario, patient_spec: str = "test:0"):
    """The station (``kind`` 'station') or the whole scan diagram ('scan') of ``scenario``,
    built, named as in the pictures."""
    if kind == "station":
        return MakeStation(scenario)
    template = load_template_for(scenario)
    patient = (
        None
        if scenario.hardware
        else load_patient_for(
            patient_spec,
            "--patient",
            side=scenario.patient.side,
            posture=scenario.patient.posture,
            progress=stderr_is_terminal(),
        )
    )
    station = MakeStation(scenario, patient=patient)
    builder, _ = BuildScanDiagram(scenario, station, template)
    diagram = builder.Build()
    diagram.set_name("scan")
    return diagram


def render_graphviz(dot_source: str, out: Path) -> Path:
    """Renders Graphviz ``dot_source`` to ``out`` (.svg or .png), atomically."""
    fmt = out.suffix.lower().lstrip(".")
    if fmt not in ("svg", "png"):
        raise UserError(f"--out: expected a .svg or .png file name, got {out}")
    dot = shutil.which("dot")
    if dot is None:
        raise UserError(GRAPHVIZ_MISSING)
    with atomic_path(out) as tmp:
        _run_dot([dot, f"-T{fmt}", "-o", str(tmp)], dot_source)
    return out


def _run_dot(argv: list, dot_source: str) -> bytes:
    """Graphviz's output for ``dot_source``; a failure of ``dot`` is one line (a
    UserError with the first line dot printed), not a traceback."""
    try:
        done = subprocess.run(argv, input=dot_source.encode(), capture_output=True)
    except OSError as e:
        raise UserError(f"Graphviz 'dot' could not be started ({argv[0]}): {e}") from None
    if done.returncode != 0:
        said = done.stderr.decode(errors="replace").strip().splitlines()
        raise UserError(
            f"Graphviz 'dot' failed (exit {done.returncode})" + (f": {said[0]}" if said else "")
        )
    return done.stdout


def svg_labels(svg: str) -> Counter:
    """The texts drawn in a Graphviz SVG (system classes, ``name=...``, port names), counted;
    the same for any Graphviz version that draws the same diagram."""
    return Counter(
        html.unescape(t).strip()
        for t in re.findall(r"<text\b[^>]*>([^<]*)</text>", svg)
        if t.strip()
    )


def committed_picture_drift(name: str, scenario=None) -> tuple[Counter, Counter]:
    """(missing, extra): the labels the diagram built now has that the committed picture
    ``diagrams/NAME`` lacks, and those the picture shows that the diagram no longer has;
    both empty when the picture is current. Needs Graphviz."""
    kind, patient, depth = COMMITTED[name]
    scenario = scenario if scenario is not None else LoadScenario()
    dot = shutil.which("dot")
    if dot is None:
        raise UserError(GRAPHVIZ_MISSING)
    source = build_diagram(kind, scenario, patient).GetGraphvizString(max_depth=depth)
    now = svg_labels(_run_dot([dot, "-Tsvg"], source).decode())
    path = DIAGRAMS_DIR / name
    committed = svg_labels(path.read_text()) if path.is_file() else Counter()
    return now - committed, committed - now


def _render_all(args) -> int:
    # Each committed picture has its own patient and depth, on the default scenario of the
    # default scenarios file: a setting given with --all would be silently ignored.
    given = [
        flag
        for flag, value, default in (
            ("--out", args.out, None),
            ("--diagram", args.diagram, None),
            ("--scenario", args.scenario, "default"),
            ("--set", args.overrides or None, None),
            ("--patient", args.patient, "test:0"),
            ("--depth", args.depth, 1),
        )
        if value != default
    ]
    if Path(args.scenarios_file).resolve() != DEFAULT_SCENARIOS_FILE.resolve():
        given.append("--scenarios-file")
    if given:
        raise UserError(
            f"{', '.join(given)}: --all draws the committed pictures with their own settings "
            "(diagrams/*.svg, the default scenario); leave out --out, --diagram, --scenario, "
            "--scenarios-file, --set, --patient and --depth"
        )
    scenario = load_scenario_from_args(args)
    stale = 0
    for name, (kind, patient, depth) in COMMITTED.items():
        if args.check:
            missing, extra = committed_picture_drift(name, scenario)
            if missing or extra:
                stale += 1
                print(
                    f"diagrams/{name} is stale: lacks {sorted(missing) or 'nothing'}; "
                    f"shows in excess {sorted(extra) or 'nothing'}"
                )
            else:
                print(f"diagrams/{name} is current")
            continue
        diagram = build_diagram(kind, scenario, patient)
        out = render_graphviz(diagram.GetGraphvizString(max_depth=depth), DIAGRAMS_DIR / name)
        print(f"wrote {out}")
    if stale:
        print(
            f"render-diagram: {stale} stale picture(s); re-draw them with "
            f"'drake-rus render-diagram --all' (or make diagrams)",
            file=sys.stderr,
        )
    return 1 if stale else 0


def run_render(args) -> int:
    if shutil.which("dot") is None:
        raise UserError(GRAPHVIZ_MISSING)
    if args.all:
        return _render_all(args)
    if args.check:
        raise UserError("--check: compares the committed pictures; use it with --all")
    scenario = load_scenario_from_args(args)
    kind = args.diagram or "station"
    out = check_output_file(
        args.out or DEFAULT_OUT_DIR / f"{kind}.svg", "--out", suffixes=(".svg", ".png")
    )
    diagram = build_diagram(kind, scenario, args.patient)
    out = render_graphviz(diagram.GetGraphvizString(max_depth=args.depth), out)
    print(f"wrote {out}")
    return 0
