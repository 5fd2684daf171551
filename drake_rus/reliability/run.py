"""One closed-loop scan with faults, watched for safety at every plant step.

:func:`RunFaultyScan` runs ``drake_rus.scan.RunScan`` on the faulty station
(:func:`~drake_rus.reliability.station.MakeFaultyStation`) with a :class:`SafetyWatch`
monitor that records the TRUE probe contact force (simulation ground truth, at every plant
step: ``contact.time_step``, 10 ms by default): its peak, the total time above the force
ceiling and the longest continuous stretch above it. After the scan ends it keeps
simulating ``settle`` s and checks the robot has come to rest.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from drake_rus.control.safety import StopReason
from drake_rus.reliability.station import MakeFaultyStation
from drake_rus.robot import NUM_JOINTS
from drake_rus.scan import RunScan, ScanMonitor

# A run whose contact force exceeds the ceiling for longer than this (s) is a violation.
FORCE_VIOLATION_S = 0.050
# Joint speed (rad/s) below which the robot counts as stopped after an ABORT.
REST_SPEED = 0.02


@dataclasses.dataclass
class ForceWatch:
    """Running statistics of the true contact force F_z (N, pressing positive)."""

    ceiling: float
    peak: float = 0.0
    time_above: float = 0.0
    longest_above: float = 0.0
    _run_start: float | None = None
    _last_t: float | None = None

    def add(self, t: float, F: float) -> None:
        dt = 0.0 if self._last_t is None else max(0.0, t - self._last_t)
        self._last_t = t
        if math.isfinite(F):
            self.peak = max(self.peak, F)
        if F > self.ceiling:
            self.time_above += dt
            if self._run_start is None:
                self._run_start = t - dt
            self.longest_above = max(self.longest_above, t - self._run_start)
        else:
            self._run_start = None

    @property
    def violation(self) -> bool:
        return self.longest_above > FORCE_VIOLATION_S


class SafetyWatch(ScanMonitor):
    """A scan monitor: the TRUE probe contact force at every plant step (simulation truth,
    ``contact.time_step`` resolution, 10 ms by default) through a :class:`ForceWatch`, and,
    once the run is over, whether the stopped robot is at rest (true joint speed from the
    plant state, and a zero command)."""

    def __init__(self, ceiling: float):
        self.watch = ForceWatch(ceiling)
        self.check: dict = {}

    def attach(self, diagram, handles, root_context) -> None:
        self._station = handles.station
        self._safety = handles.parts.safety
        self._station_context = self._station.GetMyContextFromRoot(root_context)
        self._wrench = self._station.GetOutputPort("probe_contact_wrench_true")

    def observe(self, root_context) -> None:
        self.watch.add(root_context.get_time(), -float(self._wrench.Eval(self._station_context)[5]))

    def finish(self, root_context) -> None:
        x = np.asarray(self._station.GetOutputPort("plant_state").Eval(self._station_context))
        # [q (robot first, then a moving patient's joints), v (likewise)]
        v = x[len(x) // 2 :][:NUM_JOINTS]
        safety_context = self._safety.GetMyContextFromRoot(root_context)
        cmd = np.asarray(self._safety.GetOutputPort("joint_velocity_command").Eval(safety_context))
        stopped = bool(self._safety.GetOutputPort("stopped").Eval(safety_context)[0])
        w = self.watch
        self.check = {
            "peak_force_n": w.peak,
            "time_above_ceiling_s": w.time_above,
            "longest_above_ceiling_s": w.longest_above,
            "force_violation": w.violation,
            "final_joint_speed": float(np.max(np.abs(v))) if v.size else 0.0,
            "final_command_norm": float(np.linalg.norm(cmd)),
            "safety_stopped": stopped,
            "at_rest": bool(np.max(np.abs(v)) < REST_SPEED and np.linalg.norm(cmd) == 0.0)
            if stopped
            else None,
        }


def RunFaultyScan(
    scenario,
    patient,
    template,
    *,
    max_sim_time: float = 150.0,
    settle: float | None = None,
    start_fraction: float | None = None,
):
    """Runs one scan on the faulty station (``MakeFaultyStation``) under a
    :class:`SafetyWatch`; returns (ScanResult, safety dict). ``settle`` (s) defaults to the
    force-stop retract time plus 0.3 s."""
    if settle is None:
        cfg = scenario.safety
        settle = cfg.retract_distance / cfg.retract_speed + 0.3
    watch = SafetyWatch(scenario.safety.force_ceiling)
    result = RunScan(
        scenario,
        patient,
        template,
        make_station=MakeFaultyStation,
        max_sim_time=max_sim_time,
        progress=False,
        start_fraction=start_fraction,
        monitors=[watch],
        settle=settle,
    )
    return result, watch.check


def outcome_reason(result) -> str:
    """The most specific reason of an ABORT: the first safety stop's reason and detail when
    the safety layer stopped on its own, else the supervisor's reason (a stop the
    supervisor asked for carries no detail of its own)."""
    if result.status == "DONE":
        return ""
    for e in result.safety_events[:1]:
        if e.reason != StopReason.SUPERVISOR_ABORT:
            return f"{e.reason}: {e.detail}" if e.detail else str(e.reason)
    return result.reason or result.status
