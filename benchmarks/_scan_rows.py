"""One default scan as a benchmark row (shared by ``real_anatomy``, ``real_kidneys`` and
``pivot``), and the benchmarks' scenario from ``--scenario``/``--scenarios-file``/``--set``."""

import time
import traceback

import numpy as np

from drake_rus.anatomy import load_patient
from drake_rus.cli import load_scenario_from_args
from drake_rus.config_schema import ScenarioError
from drake_rus.control.safety import StopReason
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.localization.tracking import kidney_in_view
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
    skip: tuple = (),
) -> dict:
    """Runs the scan of ``body`` (a patient spec or path) on ``scenario`` with the YAML
    ``overrides`` and adds to ``row``: status, reason, wall_s, then ``fill(row, result,
    summary, scenario)`` (the caller's fields). ``out``: also write the scan's outputs there;
    ``progress``: progress bars while the patient is built; ``skip``: exception types that
    make the case SKIPPED with the exception's message as reason (no scan is possible, e.g.
    a patient that cannot be built). Never raises: any other failure is a row with status
    ERROR, its reason and traceback."""
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
        lost = segmentation_lost_in_view(result)
        if lost is not None:
            row["segmentation_lost_in_view"] = lost
        if fill is not None:
            fill(row, result, summary, s)
    except skip as e:
        row.update(status="SKIPPED", reason=str(e))
    except Exception as e:  # noqa: BLE001 - a benchmark row, with the traceback kept
        row.update(
            status="ERROR",
            reason=f"{type(e).__name__}: {e}",
            traceback=traceback.format_exc(limit=6),
        )
    row["wall_s"] = round(time.perf_counter() - start, 1)
    return row


def segmentation_lost_in_view(result, share: float = 0.5) -> dict | None:
    """For a scan the safety layer stopped on "segmentation lost": whether the true kidney
    was in the image meanwhile (simulation truth, benchmarks only): over the frames of the
    watchdog's window before the stop, the share whose image held a true kidney section of
    at least ``imaging.min_kidney_area`` (true kidney voxels within half a voxel of the
    image plane, inside the fan). ``{"in_view": share of frames >= ``share``, "frames",
    "frames_in_view"}``; None when the scan did not stop that way or has no truth."""
    events = [e for e in result.safety_events if e.reason == StopReason.SEGMENTATION_LOST]
    if not events or result.truth is None:
        return None
    stop = events[0].time
    window = result.scenario.safety.segmentation_timeout
    frames = [f for f in result.frames if stop - window <= f.time <= stop]
    if not frames:
        return None
    imaging = result.scenario.imaging
    geometry = ProbeGeometry.from_config(imaging)
    voxel = round(float(np.cbrt(result.truth.voxel_volume)), 6)
    need = imaging.min_kidney_area / voxel**2
    seen = [
        kidney_in_view(result.truth.kidney_points_B, f.X_BP, geometry, 0.5 * voxel) >= need
        for f in frames
    ]
    n = int(sum(seen))
    return {"in_view": n >= share * len(frames), "frames": len(frames), "frames_in_view": n}


def scenario_from_args(args):
    """(scenario, None) from the arguments of :func:`drake_rus.cli.add_scenario_arguments`,
    or (None, the one-line error naming the argument) when the scenario name, file or
    ``--set`` text cannot be used (the benchmark then exits 2, before any scan)."""
    try:
        return load_scenario_from_args(args), None
    except (ScenarioError, ValueError) as e:
        return None, f"--scenario/--set: {e}"
