"""The ``drake-rus`` command.

Each feature module registers its own sub-commands: a module listed in ``COMMAND_MODULES``
defines ``add_commands(subparsers)`` and gives each parser a ``func(args) -> int``.
"""

import argparse
import importlib
import sys

from drake_rus.config_schema import ScenarioError

COMMAND_MODULES = [
    "drake_rus.demo",            # demo: the station demo (pressing probe)
    "drake_rus.render",          # render-diagram: station diagram picture
    "drake_rus.hardware.cli",    # hardware check: connect, dry run, scripted motion
    "drake_rus.anatomy.cli",
    "drake_rus.template.cli",
    "drake_rus.imaging.cli",
    "drake_rus.scan.cli",        # scan: the full autonomous scan
    "drake_rus.experiments.cli",  # study: the seed paper's studies (kinematic, Dask)
    "drake_rus.reliability.cli",  # campaign: randomised faulty scans (safety figures)
    "drake_rus.rehearsal.cli",   # rehearse: software-in-the-loop rehearsal on the wire
]


class UserError(Exception):
    """An error caused by the user's input; printed without a traceback."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="drake-rus",
        description="Autonomous robotic kidney ultrasound as a Drake systems diagram.")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    subparsers.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(name).add_commands(subparsers)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ScenarioError, UserError, FileNotFoundError, ValueError) as e:
        print(f"drake-rus {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"drake-rus {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
