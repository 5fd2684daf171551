"""The autonomous scan on any station: diagram, run, metrics, report and the ``scan`` command.

``RunScan(scenario, patient, template)`` runs the whole scan and returns a ``ScanResult``;
``ScanMetrics`` and ``Summary`` give the paper's figures; ``WriteScanOutputs`` writes what a
person looks at. The scan diagram (``BuildScanDiagram``) uses only the ports both stations
export; simulation truth is an observer (``scan.truth``) attached only in simulation.

The names below load on first use, so the light ``drake_rus.scan.config`` (the scenario's
``start`` section) can be imported by the scenario schema without the whole scan.
"""

import importlib

_EXPORTS = {
    "BuildScanDiagram": "diagram",
    "ScanHandles": "diagram",
    "PhaseIs": "diagram",
    "FrameRecord": "diagram",
    "ScanMetrics": "metrics",
    "Summary": "metrics",
    "WriteScanOutputs": "report",
    "RunScan": "run",
    "PrepareScenario": "run",
    "ScanResult": "run",
    "ScanMonitor": "run",
    "CollectScanResult": "run",
    "TERMINAL_PHASES": "run",
    "SimulationTruth": "truth",
    "StartPlan": "planning",
    "PlanStart": "planning",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"drake_rus.scan.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module 'drake_rus.scan' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + __all__)
