"""One default scan as a benchmark row (shared by ``real_anatomy`` and ``pivot``)."""

import time
import traceback

from drake_rus.anatomy import load_patient
from drake_rus.scan import RunScan, ScanMetrics, Summary, WriteScanOutputs
from drake_rus.scenario import ApplyOverrides


def scan_row(
    row: dict,
    body: str,
    scenario,
    overrides: str,
    template,
    max_sim_time: float,
    out=None,
    fill=None,
    progress: bool = True,
) -> dict:
    """Runs the scan of ``body`` (a patient spec or path) on ``scenario`` with the YAML
    ``overrides`` and adds to ``row``: status, reason, wall_s, then ``fill(row, result,
    summary, scenario)`` (the caller's fields). ``out``: also write the scan's outputs there;
    ``progress``: progress bars while the patient is built.
    Never raises: a failure is a row with status ERROR, its reason and traceback."""
    start = time.perf_counter()
    try:
        s = ApplyOverrides(scenario, overrides)
        patient = load_patient(
            str(body), side=s.patient.side, posture=s.patient.posture, progress=progress
        )
        result = RunScan(s, patient, template, max_sim_time=max_sim_time, progress=False)
        metrics = ScanMetrics(result)
        summary = Summary(result, metrics)
        if out is not None:
            WriteScanOutputs(result, metrics, summary, out)
        row.update(status=summary["status"], reason=summary["reason"])
        if fill is not None:
            fill(row, result, summary, s)
    except Exception as e:  # noqa: BLE001 - a benchmark row, with the traceback kept
        row.update(
            status="ERROR",
            reason=f"{type(e).__name__}: {e}",
            traceback=traceback.format_exc(limit=6),
        )
    row["wall_s"] = round(time.perf_counter() - start, 1)
    return row
