"""The autonomous scan on any station: diagram, run, metrics, report and the ``scan`` command.

``RunScan(scenario, patient, template)`` runs the whole scan and returns a ``ScanResult``;
``ScanMetrics`` and ``Summary`` give the paper's figures; ``WriteScanOutputs`` writes what a
person looks at. The scan diagram (``BuildScanDiagram``) uses only the ports both stations
export; simulation truth is an observer (``scan.truth``) attached only in simulation.
"""

from drake_rus.scan.diagram import BuildScanDiagram, FrameRecord, PhaseIs, ScanHandles
from drake_rus.scan.metrics import ScanMetrics, Summary
from drake_rus.scan.report import WriteScanOutputs
from drake_rus.scan.run import (
    TERMINAL_PHASES, CollectScanResult, PrepareScenario, RunScan, ScanMonitor, ScanResult)
from drake_rus.scan.truth import SimulationTruth

__all__ = ["BuildScanDiagram", "ScanHandles", "PhaseIs", "FrameRecord", "RunScan",
           "PrepareScenario", "ScanResult", "ScanMonitor", "CollectScanResult",
           "TERMINAL_PHASES", "ScanMetrics", "Summary", "WriteScanOutputs", "SimulationTruth"]
