"""``drake-rus render-diagram``: draws the station diagram with Graphviz."""

import shutil
import subprocess
from pathlib import Path

from drake_rus.cli import UserError
from drake_rus.io_utils import atomic_path


def add_commands(subparsers) -> None:
    from drake_rus.demo import add_scenario_arguments
    p = subparsers.add_parser("render-diagram", help="draw the station diagram (SVG or PNG)")
    add_scenario_arguments(p)
    p.add_argument("--out", default="diagrams/station.svg",
                   help="output file; .svg or .png (default diagrams/station.svg)")
    p.add_argument("--depth", type=int, default=1, help="subsystem nesting depth to draw")
    p.set_defaults(func=run_render)


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
    from drake_rus.demo import load_scenario_from_args
    from drake_rus.station import MakeStation
    scenario = load_scenario_from_args(args)
    station = MakeStation(scenario)
    out = render_graphviz(station.GetGraphvizString(max_depth=args.depth), Path(args.out))
    print(f"wrote {out}")
    return 0
