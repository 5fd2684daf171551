"""The ``drake-rus`` command.

Each feature module registers its own sub-commands: a module listed in ``COMMAND_MODULES``
defines ``add_commands(subparsers)`` and gives each parser a ``func(args) -> int``.

Before a command runs, ``main`` checks what every command shares: the arguments of
``ARGUMENT_RULES`` (each rule stated once, here), the outputs a parser declares with
``set_defaults(outputs={"out": "dir", "record": "file"})`` (writable, a folder where a folder
is needed; see ``drake_rus.io_utils``), the ``PREFLIGHT_CHECKS`` of the command modules (the
patient spec) and a ``--scheduler`` address. Every
user error, an OSError included, ends in one line naming the argument or field and exit
status 2. Ctrl-C (SIGINT) and SIGTERM at any moment end the command with 130 and 143
(``drake_rus.interrupts``; the program installs their handlers before its slow imports).
"""

import os
import sys

from drake_rus import interrupts

if (
    __name__ == "__main__"
    or os.path.basename(getattr(sys.modules.get("__main__"), "__file__", None) or "") == "drake-rus"
):
    # The program (``python -m drake_rus.cli`` or the ``drake-rus`` script; not a library
    # import, nor a worker process that re-imports the script): signals are caught from here.
    interrupts.install_for_startup()
if __name__ == "__main__":
    # Run as ``python -m drake_rus.cli``: this module is drake_rus.cli for the command
    # modules too (their PREFLIGHT_CHECKS and UserError are this module's, not a copy's).
    sys.modules.setdefault("drake_rus.cli", sys.modules[__name__])

import argparse  # noqa: E402  (after the signal handlers: start-up can be interrupted)
import importlib  # noqa: E402
import math  # noqa: E402
import socket  # noqa: E402
from urllib.parse import urlparse  # noqa: E402

from pydrake.geometry import Meshcat, MeshcatParams  # noqa: E402

from drake_rus.config_schema import (  # noqa: E402
    SEED_MAX,
    SEED_RANGE,
    ScenarioError,
    check_nesting_depth,
)
from drake_rus.io_utils import check_output_dir, check_output_file, describe_os_error  # noqa: E402
from drake_rus.scenario import DEFAULT_SCENARIOS_FILE, LoadScenario  # noqa: E402

COMMAND_MODULES = [
    "drake_rus.demo",  # demo: the station demo (pressing probe)
    "drake_rus.render",  # render-diagram: station diagram picture
    "drake_rus.hardware.cli",  # hardware check: connect, dry run, scripted motion
    "drake_rus.anatomy.cli",
    "drake_rus.template.cli",
    "drake_rus.imaging.cli",
    "drake_rus.imaging.training.cli",  # segmenter: fine-tune on your own frames
    "drake_rus.scan.cli",  # scan: the full autonomous scan
    "drake_rus.experiments.cli",  # study: the seed paper's studies (kinematic, Dask)
    "drake_rus.reliability.cli",  # campaign: randomised faulty scans (safety figures)
    "drake_rus.rehearsal.cli",  # rehearse: software-in-the-loop rehearsal on the wire
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
    "closed_loop": (lambda v: v >= 0, "0 or more patients (0 skips the closed-loop scans)"),
    "seed": (lambda v: 0 <= v <= SEED_MAX, SEED_RANGE),
    "n": (lambda v: v >= 1, "at least 1 subject"),
    "voxel_mm": (lambda v: _finite(v) and 0.1 <= v <= 10.0, "a voxel size of 0.1-10 mm"),
    "voxel": (lambda v: _finite(v) and 0.0 < v <= 0.01, "a voxel size in m, 0 < v <= 0.01"),
    "recon_spacing": (lambda v: _finite(v) and 0.0 < v <= 0.01, "a voxel size in m, 0 < v <= 0.01"),
    "max_sim_time": (lambda v: _finite(v) and v > 0, "a positive time in s"),
    "duration": (lambda v: _finite(v) and v > 0, "a positive time in s"),
    # hardware pivot / check / calibrate-latency: checked before the robot is connected.
    "rate": (lambda v: _finite(v) and v > 0, "a positive number of samples per s"),
    "rest": (lambda v: _finite(v) and v >= 0, "a time >= 0 s"),
    "amplitude": (lambda v: _finite(v) and v > 0, "a positive distance in m"),
    "period": (lambda v: _finite(v) and v > 0, "a positive time in s"),
    "cycles": (lambda v: _finite(v) and v > 0, "a positive number of periods"),
    "max_latency": (lambda v: _finite(v) and v > 0, "a positive time in s"),
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


# ------------------------------------------------------- helpers shared by the commands
def add_scenario_arguments(parser, default: str = "default") -> None:
    """--scenario / --scenarios-file / --set, shared by every command that builds a station
    (``default``: the scenario when none is named)."""
    parser.add_argument("--scenario", default=default, help=f"scenario name (default '{default}')")
    parser.add_argument(
        "--scenarios-file", default=str(DEFAULT_SCENARIOS_FILE), help="YAML file of named scenarios"
    )
    parser.add_argument(
        "--set",
        dest="overrides",
        default=None,
        metavar="YAML",
        help='YAML overrides, e.g. "{contact: {model: point}}"',
    )


def load_scenario_from_args(args):
    check_nesting_depth(args.overrides, "--set")
    return LoadScenario(
        filename=args.scenarios_file, scenario_name=args.scenario, scenario_text=args.overrides
    )


# The address every server of drake-rus listens on: the loopback only (Meshcat, the
# rehearsal's video stream; `make notebooks` starts JupyterLab on it too).
LOOPBACK = "127.0.0.1"


def MakeMeshcat(port: int | None = None):
    """A Meshcat server listening on the loopback only (127.0.0.1; Drake's default "*" is
    every interface, and "localhost" may resolve to an IPv6 or another address)."""
    params = MeshcatParams()
    params.host = LOOPBACK
    if port is not None:
        params.port = port
    return Meshcat(params)


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
            check_output_file(
                value, _flag(name), suffixes=tuple(suffixes.split(",")) if suffixes else ()
            )


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
        raise UserError(
            f"--scheduler: no Dask scheduler answers at {address} within {timeout:g} s ({why})"
        ) from None


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
        description="Autonomous robotic kidney ultrasound as a Drake systems diagram.",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    subparsers.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(name).add_commands(subparsers)
    return parser


# Exit statuses of the command line (docs/cli.md): 0 done, 1 not done (a scan ended ABORT,
# TIMEOUT, ...), 2 bad input, 128 + the signal (130 Ctrl-C, 143 SIGTERM).
EXIT_USER_ERROR = 2  # bad input: one line naming the argument or field, nothing written
EXIT_STATUS_HELP = """exit status (docs/cli.md):
  0    done (a scan or rehearsal: the scan ended DONE)
  1    a scan or rehearsal ended otherwise (ABORT, TIMEOUT; the summary says why)
  2    bad input: one line naming the argument or field; nothing half-written
  130  stopped by Ctrl-C (SIGINT); 143 stopped by SIGTERM: the output folder, if it
       exists, holds an INTERRUPTED summary.json, no temporary files and no lock"""


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else [str(a) for a in argv]
    with interrupts.handling():
        return _run(argv)


def _interrupted(command: str, exc: BaseException | None = None) -> int:
    print(
        f"{command}: interrupted by {interrupts.signal_text(interrupts.signal_of(exc))}",
        file=sys.stderr,
    )
    return interrupts.exit_status(exc)


def _run(argv: list) -> int:
    # The command's name for messages before the arguments are parsed (a signal during the
    # imports): the first argument, if it is a word.
    args = None
    command = "drake-rus" + (
        f" {argv[0]}"
        if argv and argv[0].replace("-", "").isalpha() and not argv[0].startswith("-")
        else ""
    )
    try:
        # The imports of every command module (a few s): a signal is raised at the next
        # import statement (raised inside a module's initialisation, libraries swallow it).
        with interrupts.importing():
            parser = build_parser()
        args = parser.parse_args(argv)
        command = f"drake-rus {args.command}"
        args.argv = ["drake-rus", *argv]
        preflight(args)
        code = int(args.func(args) or 0)
        if interrupts.pending() is not None and code != interrupts.exit_status():
            return _interrupted(command)  # a signal swallowed on the way
        return code
    except BaseException as e:
        if isinstance(e, KeyboardInterrupt) or interrupts.pending() is not None:
            return _interrupted(command, e)
        if isinstance(e, (ScenarioError, UserError, ValueError)):
            print(f"{command}: error: {e}", file=sys.stderr)
            return EXIT_USER_ERROR
        if isinstance(e, OSError):  # FileNotFoundError with a message, a full disk, permissions
            text = str(e) if e.errno is None else describe_os_error(e, args)
            print(f"{command}: error: {text}", file=sys.stderr)
            return EXIT_USER_ERROR
        raise


if __name__ == "__main__":
    sys.exit(main())
