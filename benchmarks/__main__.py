"""Runs a benchmark: ``python -m benchmarks NAME [ARGS]`` or ``python -m benchmarks all``.

A benchmark is a module ``benchmarks/NAME.py`` with ``main(argv=None)`` that prints one JSON
object as its last output line. Speeds are reported next to a reference measured in the same
run (the machines are noisy), never asserted in tests. A scenario a benchmark cannot use
(``--scenario``, ``--set``: :class:`~drake_rus.config_schema.ScenarioError`) is one line on
stderr naming the benchmark and the field, and exit status 2.
"""

import importlib
import pkgutil
import sys
from pathlib import Path


def available() -> list[str]:
    here = Path(__file__).parent
    return sorted(
        m.name
        for m in pkgutil.iter_modules([str(here)])
        if not m.name.startswith("_") and m.name != "common"
    )


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    names = available()
    if not argv or argv[0] in ("-h", "--help"):
        print(f"usage: python -m benchmarks NAME [ARGS]   (NAME: {', '.join(names)}, all)")
        return 0 if argv else 2
    name, rest = argv[0], argv[1:]
    if name == "all":
        for n in names:
            print(f"== {n}", flush=True)
            importlib.import_module(f"benchmarks.{n}").main(rest)
        return 0
    if name not in names:
        print(f"unknown benchmark {name!r}; available: {', '.join(names)}", file=sys.stderr)
        return 2
    from drake_rus.config_schema import ScenarioError

    try:
        return int(importlib.import_module(f"benchmarks.{name}").main(rest) or 0)
    except ScenarioError as e:
        print(f"python -m benchmarks {name}: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
