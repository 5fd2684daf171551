"""One default scan as a benchmark row (shared by ``real_anatomy``, ``real_kidneys`` and
``pivot``), the benchmarks' scenario from ``--scenario``/``--scenarios-file``/``--set``, and
their arguments checked against the commands' shared rules (list options without
repeats)."""

import time
import traceback

import numpy as np

from drake_rus.anatomy import load_patient
from drake_rus.cli import UserError, check_arguments, load_scenario_from_args
from drake_rus.config_schema import ScenarioError
from drake_rus.control.safety import StopReason
from drake_rus.control.supervisor import Phase
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
        in_loop = segmentation_in_loop(result)
        if in_loop is not None:
            row["segmentation_in_loop"] = in_loop
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
    min_area = result.scenario.imaging.min_kidney_area
    n = int(np.count_nonzero(true_section_areas(result, frames) >= min_area))
    return {"in_view": n >= share * len(frames), "frames": len(frames), "frames_in_view": n}


# The phases whose frames segmentation_in_loop reports apart: the landing (the probe may
# not touch the skin yet), the sweep the registration takes its
# cloud from, the registration and the move to the pivot, and the pivot the volume is
# imaged in.
IN_LOOP_PHASES = {
    "approach": Phase.APPROACH,
    "explore": Phase.EXPLORE,
    "localize": Phase.LOCALIZE,
    "transit": Phase.TRANSIT,
    "pivot": Phase.PIVOT,
}


def true_section_areas(result, frames) -> np.ndarray:
    """The true kidney section's area (m^2) in each of ``frames`` (FrameRecords of
    ``result``; simulation truth, benchmarks only): the true kidney voxels within half a
    voxel of the image plane and inside the fan, each one voxel face."""
    geometry = ProbeGeometry.from_config(result.scenario.imaging)
    voxel = round(float(np.cbrt(result.truth.voxel_volume)), 6)
    points = result.truth.kidney_points_B
    return np.array(
        [kidney_in_view(points, f.X_BP, geometry, 0.5 * voxel) * voxel**2 for f in frames]
    )


def agreement_counts(marked, areas, min_area: float) -> dict:
    """How a scan's per-frame "kidney visible" (``marked``) agrees with the true section
    areas (m^2, ``areas``): frames; ``in_view`` (a true section of at least ``min_area``,
    what the segmenter is asked to find) and ``missed_in_view`` among them; ``out_of_view``
    (no true kidney in the image at all) and ``marked_out_of_view`` among them (a false
    mark: something else taken for the kidney); ``edge`` (a true section under
    ``min_area``: either answer is right)."""
    marked = np.asarray(marked, bool)
    areas = np.asarray(areas, float)
    if marked.shape != areas.shape:
        raise ValueError(
            f"agreement_counts: one mark per frame expected, got {marked.size} marks and "
            f"{areas.size} areas"
        )
    in_view = areas >= min_area
    out = areas <= 0.0
    return {
        "frames": int(marked.size),
        "in_view": int(in_view.sum()),
        "missed_in_view": int((in_view & ~marked).sum()),
        "out_of_view": int(out.sum()),
        "marked_out_of_view": int((out & marked).sum()),
        "edge": int((~in_view & ~out).sum()),
    }


def segmentation_in_loop(result) -> dict | None:
    """How the scan's own segmentation decisions (``kidney_visible``: model, tracker and
    prior together, as the scan acted on them) agreed with the simulation truth
    (benchmarks only; the scan never reads it): :func:`agreement_counts` over every frame
    segmented after the landing, each judged at its own pose (a decision is paired with the
    frame it was segmented from, once, even when it was read on later ticks), and per phase
    (``IN_LOOP_PHASES``, the phase in which the decision was first read; the landing's
    frames, taken while the probe may not touch the skin yet, only there). None
    without truth, or when the patient moves (the truth holds the kidney where it lay at
    the start)."""
    if result.truth is None or not result.frames or result.scenario.patient.motion.moves:
        return None
    by_index = {f.frame_index: f for f in result.frames}
    decisions = {}
    for f in result.frames:
        source = by_index.get(f.mask_frame_index)
        if source is not None and f.mask_frame_index not in decisions:
            decisions[f.mask_frame_index] = (source, f.visible, f.phase)
    if not decisions:
        return None
    sources = [d[0] for d in decisions.values()]
    areas = true_section_areas(result, sources)
    marked = np.array([d[1] for d in decisions.values()], bool)
    phases = np.array([d[2] for d in decisions.values()])
    min_area = result.scenario.imaging.min_kidney_area
    landed = phases != Phase.APPROACH
    out = agreement_counts(marked[landed], areas[landed], min_area)
    out["by_phase"] = {
        name: agreement_counts(marked[phases == ph], areas[phases == ph], min_area)
        for name, ph in IN_LOOP_PHASES.items()
    }
    return out


def in_loop_totals(rows) -> dict | None:
    """The rows' ``segmentation_in_loop`` counts summed (after the landing, and per phase), with
    the shares a reader compares: ``missed_share`` (of the frames with the kidney in view,
    the share the scan did not see it in) and ``false_mark_share`` (of the frames without
    any kidney, the share it marked one in); ``scans`` counted. None when no row has
    them."""
    cells = [r["segmentation_in_loop"] for r in rows if r.get("segmentation_in_loop")]
    if not cells:
        return None

    def total(parts):
        out = {k: sum(p[k] for p in parts) for k in parts[0]}
        seen, free = out["in_view"], out["out_of_view"]
        out["missed_share"] = round(out["missed_in_view"] / seen, 4) if seen else None
        out["false_mark_share"] = round(out["marked_out_of_view"] / free, 4) if free else None
        return out

    keys = [k for k in cells[0] if k != "by_phase"]
    out = total([{k: c[k] for k in keys} for c in cells])
    out["by_phase"] = {name: total([c["by_phase"][name] for c in cells]) for name in IN_LOOP_PHASES}
    out["scans"] = len(cells)
    return out


def in_loop_line(totals: dict | None) -> str:
    """One line for a benchmark's table: the in-loop segmentation totals of the sweep and
    the pivot (the landing's frames, taken while the probe may not touch the skin yet, are
    in the JSON only)."""
    if totals is None:
        return "segmentation in the loop: no truth to compare with"

    def phase(name):
        c = totals["by_phase"][name]
        return (
            f"{name} missed {c['missed_in_view']} of {c['in_view']} frames with the kidney "
            f"in view, marked {c['marked_out_of_view']} of {c['out_of_view']} with none"
        )

    return (
        f"segmentation in the loop ({totals['scans']} scans, against the simulation truth): "
        f"{phase('explore')}; {phase('pivot')}"
    )


def scenario_from_args(args):
    """(scenario, None) from the arguments of :func:`drake_rus.cli.add_scenario_arguments`,
    or (None, the one-line error naming the argument) when the scenario name, file or
    ``--set`` text cannot be used (the benchmark then exits 2, before any scan)."""
    try:
        return load_scenario_from_args(args), None
    except (ScenarioError, ValueError) as e:
        return None, f"--scenario/--set: {e}"


def distinct(values) -> list:
    """``values`` without repeats, in the order first given: a list option's repeated value
    counts once (``--postures supine supine`` scans each body once), as the commands'
    ``--strategies`` and ``--ers`` do."""
    return list(dict.fromkeys(values))


def argument_error(args) -> str | None:
    """The one line naming the first argument of ``args`` that breaks one of the commands'
    shared rules (:data:`drake_rus.cli.ARGUMENT_RULES`: ``--max-sim-time`` and
    ``--duration`` positive, ...), or None: checked before anything is loaded or run."""
    try:
        check_arguments(args)
    except UserError as e:
        return str(e)
    return None
