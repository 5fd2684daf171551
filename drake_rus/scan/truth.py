"""Simulation truth: what only a simulation knows, attached to a scan as an observer.

The scan diagram never reads it (the controller and the localizer see only the ports a real
setup has). It holds the patient's true kidney pose X_BK and kidney voxels (for E_trans,
E_rot,x and the volume ratio V) and logs the true probe contact wrench when the station
exports ``probe_contact_wrench_true``, and a moving patient's displacement and breathing.
On hardware there is none (``RunScan`` gets no patient), and the metrics that need it are
reported as unknown.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from pydrake.math import RigidTransform
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import LogVectorOutput

__all__ = [
    "SimulationTruth",
    "AttachSimulationTruth",
    "kidney_voxels_B",
    "force_trace_stats",
    "FORCE_LOG_PERIOD",
]

# Voxel size (m) of the true kidney for the volume ratio V (eq. 25).
TRUTH_VOXEL = 0.002
# Period (s) of the true contact-wrench log (read at call time); None: every plant step
# (contact.time_step), where the truth is sampled, so a force oscillation up to the step's
# Nyquist rate shows in the summary's ripple instead of aliasing (a 20 ms log folded a
# 23 Hz oscillation of the 10 ms loop onto a slow wobble).
FORCE_LOG_PERIOD: float | None = None
# Period (s) of the patient-motion truth logs (breathing, shift).
MOTION_LOG_PERIOD = 0.01


@dataclasses.dataclass
class SimulationTruth:
    """The true kidney frame K in B at the start of the scan, the true kidney's voxel centres
    in B (m) and their volume (m^3 each), and the logger of the true contact wrench."""

    X_BK: RigidTransform
    kidney_points_B: np.ndarray
    voxel_volume: float
    force_log: object | None = None
    # Loggers of the moving patient's truth ports, by port name (``patient_offset_true``,
    # ``breath_hold``, ``respiratory_level_true``), when the station exports them.
    motion_logs: dict = dataclasses.field(default_factory=dict)


def kidney_voxels_B(patient, X_BPt: RigidTransform, voxel_size: float) -> np.ndarray:
    """Centres (N, 3) in B of the patient's kidney voxels at ``voxel_size`` (m)."""
    mask, X_PtV = patient.kidney_mask(voxel_size)
    ijk = np.argwhere(mask)
    p_Pt = X_PtV.multiply((ijk * voxel_size).T).T
    return X_BPt.multiply(p_Pt.T).T


def AttachSimulationTruth(
    builder: DiagramBuilder, station, patient, scenario, voxel_size: float = TRUTH_VOXEL
) -> SimulationTruth:
    """The truth of ``patient`` on the bed at ``scenario.patient.X_BPt``, with a logger of the
    station's true contact wrench added to ``builder`` when the station has one."""
    X_BPt = scenario.patient.X_BPt.GetDeterministicValue()
    force_log = None
    if station.HasOutputPort("probe_contact_wrench_true"):
        period = FORCE_LOG_PERIOD or scenario.contact.time_step
        force_log = LogVectorOutput(
            station.GetOutputPort("probe_contact_wrench_true"), builder, period
        )
    motion_logs = {
        name: LogVectorOutput(station.GetOutputPort(name), builder, MOTION_LOG_PERIOD)
        for name in ("patient_offset_true", "breath_hold", "respiratory_level_true")
        if station.HasOutputPort(name)
    }
    return SimulationTruth(
        patient.X_BK(X_BPt),
        kidney_voxels_B(patient, X_BPt, voxel_size),
        voxel_size**3,
        force_log,
        motion_logs,
    )


def force_trace_stats(result, settle: float = 0.5, landing_window: float = 1.0) -> dict:
    """The true contact force F_z (N, positive pressing; from the ``force_true`` log) over a
    finished scan: mean and ripple (standard deviation) in EXPLORE (after its first
    ``settle`` s, the landing) and in PIVOT, and the landing peak (the largest force before
    EXPLORE started plus ``landing_window`` s). Values are None when the phase did not occur
    or the scan has no truth log."""
    out = {
        "explore_mean_n": None,
        "explore_ripple_n": None,
        "pivot_mean_n": None,
        "pivot_ripple_n": None,
        "landing_peak_n": None,
    }
    if "force_true" not in result.logs:
        return out
    t, wrench = result.logs["force_true"]
    F = -np.asarray(wrench)[5]
    phases = {name: (start, end) for name, start, end in result.phases}
    for name, key, skip in (("EXPLORE", "explore", settle), ("PIVOT", "pivot", 0.0)):
        if name in phases:
            start, end = phases[name]
            sel = (t >= start + skip) & (t <= end)
            if sel.any():
                out[f"{key}_mean_n"] = float(F[sel].mean())
                out[f"{key}_ripple_n"] = float(F[sel].std())
    landing_end = phases["EXPLORE"][0] + landing_window if "EXPLORE" in phases else t[-1]
    sel = t <= landing_end
    if sel.any():
        out["landing_peak_n"] = float(F[sel].max())
    return out
