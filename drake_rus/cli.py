"""The ``drake-rus`` command.

Each feature module registers its own sub-commands: a module listed in ``COMMAND_MODULES``
defines ``add_commands(subparsers)`` and gives each parser a ``func(args) -> int``.

Before a command runs, ``main`` checks what every command shares: the arguments of
``ARGUMENT_RULES`` (each rule stated once, here), the outputs a parser declares with
``set_defaults(outputs={"out": "dir", "record": "file"})`` (writable, a folder where a folder
is needed; see ``drake_rus.io_utils``), the ``PREFLIGHT_CHECKS`` of the command modules (the
patient spec) and a ``--scheduler`` address. Every
user error, an OSError included, ends in one line naming the argument or field and exit
status 2; Ctrl-C in 130.
"""

import argparse
import importlib
import math
import socket
import sys
from urllib.parse import urlparse

from drake_rus.config_schema import ScenarioError
from drake_rus.io_utils import check_output_dir, check_output_file, describe_os_error

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

# How long a --scheduler address may take to accept a connection (s) before the command
# gives up (Dask's own client waits 30 s).
SCHEDULER_TIMEOUT_S = 3.0


class UserError(Exception):
    """An error caused by the user's input; printed without a traceback."""


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and math.isfinite(v)


# Arguments shared by several commands: attribute -> (accepts(value), expected form). A
# value of None (argument not given, no default) is not checked.
ARGUMENT_RULES = {
    "views": (lambda v: v >= 0, "a number of views >= 0"),
    "starts": (lambda v: v >= 1, "at least 1 start"),
    "depth": (lambda v: v >= 0, "a non-negative nesting depth"),
    "count": (lambda v: v >= 1, "at least 1"),
    "runs": (lambda v: v >= 1, "a positive number of runs"),
    "workers": (lambda v: v >= 0, "0 or more workers"),
    "seed": (lambda v: v >= 0, "a non-negative integer"),
    "n": (lambda v: v >= 1, "at least 1 subject"),
    "voxel_mm": (lambda v: _finite(v) and 0.1 <= v <= 10.0, "a voxel size of 0.1-10 mm"),
    "voxel": (lambda v: _finite(v) and 0.0 < v <= 0.01, "a voxel size in m, 0 < v <= 0.01"),
    "recon_spacing": (lambda v: _finite(v) and 0.0 < v <= 0.01,
                      "a voxel size in m, 0 < v <= 0.01"),
    "max_sim_time": (lambda v: _finite(v) and v > 0, "a positive time in s"),
    "duration": (lambda v: _finite(v) and v > 0, "a positive time in s"),
}

# More checks before any command runs, added by the command modules in add_commands (e.g.
# the patient spec, drake_rus.anatomy.cli): check(args) -> None, raising UserError.
PREFLIGHT_CHECKS: list = []

# Outputs of commands whose modules do not declare them (``outputs`` default).
DEFAULT_OUTPUTS = {
    "imaging-pictures": {"out": "dir"},
    "rehearse": {"out": "dir"},
    "breathing": {"out": "dir"},
}


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def check_arguments(args) -> None:
    """Raises UserError naming the first argument of ``args`` that breaks a rule."""
    for name, (accepts, expected) in ARGUMENT_RULES.items():
        value = getattr(args, name, None)
        if value is None or isinstance(value, (bool, str, list)):
            continue
        if not accepts(value):
            raise UserError(f"{_flag(name)}: expected {expected}, got {value}")


def check_outputs(args) -> None:
    """Checks the outputs the command declares (nothing is created)."""
    outputs = getattr(args, "outputs", None) or DEFAULT_OUTPUTS.get(args.command, {})
    for name, kind in outputs.items():
        value = getattr(args, name, None)
        if value is None:
            continue
        kind, _, suffixes = kind.partition(":")
        if kind == "dir":
            check_output_dir(value, _flag(name))
        else:
            check_output_file(value, _flag(name),
                              suffixes=tuple(suffixes.split(",")) if suffixes else ())


def check_scheduler(address: str, timeout: float = SCHEDULER_TIMEOUT_S) -> None:
    """Raises UserError unless a Dask scheduler at ``address`` (tcp://host:port) accepts a
    connection within ``timeout`` s."""
    url = urlparse(address if "://" in address else f"tcp://{address}")
    try:
        port = url.port
    except ValueError:
        port = None
    if url.scheme not in ("tcp", "tls") or not url.hostname or port is None:
        raise UserError(f"--scheduler: expected an address tcp://HOST:PORT, got {address!r}")
    try:
        with socket.create_connection((url.hostname, port), timeout=timeout):
            pass
    except OSError as e:
        why = "timed out" if isinstance(e, TimeoutError) else (e.strerror or str(e))
        raise UserError(f"--scheduler: no Dask scheduler answers at {address} within "
                        f"{timeout:g} s ({why})") from None


def preflight(args) -> None:
    """Every check that needs no work: arguments, outputs, patient spec, scheduler."""
    check_arguments(args)
    check_outputs(args)
    for check in PREFLIGHT_CHECKS:
        check(args)
    if getattr(args, "scheduler", None):
        check_scheduler(args.scheduler)


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
        preflight(args)
        return int(args.func(args) or 0)
    except (ScenarioError, UserError, ValueError) as e:
        print(f"drake-rus {args.command}: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:       # FileNotFoundError with a message, a full disk, permissions
        text = str(e) if e.errno is None else describe_os_error(e, args)
        print(f"drake-rus {args.command}: error: {text}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"drake-rus {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
