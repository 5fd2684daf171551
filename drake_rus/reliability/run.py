"""One closed-loop scan with faults, watched for safety at every plant step.

:func:`RunFaultyScan` builds the scan diagram (``scan.BuildScanDiagram``, faults from
``scenario.faults``), runs it to DONE, ABORT or a time limit while a simulator monitor
records the TRUE probe contact force (simulation ground truth, 1 ms resolution): its peak,
the total time above the force ceiling and the longest continuous stretch above it. After
the scan ends it keeps simulating ``settle`` s and checks the robot has come to rest.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import EventStatus

from drake_rus.control.safety import StopReason
from drake_rus.scan import PHASE_NAMES, BuildScanDiagram, PrepareScenario, _collect

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


def _robot_velocity(station, station_context) -> np.ndarray:
    """The robot's true joint velocities from the plant state (not the faulty sensor)."""
    from drake_rus.station import NUM_JOINTS
    x = np.asarray(station.GetOutputPort("plant_state").Eval(station_context))
    # [q (robot first, then a moving patient's joints), v (likewise)]
    return x[len(x) // 2:][:NUM_JOINTS]


def RunFaultyScan(scenario, patient, template, *, max_sim_time: float = 150.0,
                  settle: float | None = None, start_fraction: float = 0.1):
    """Runs one scan; returns (ScanResult, safety dict). ``settle`` (s) defaults to the
    force-stop retract time plus 0.3 s."""
    if settle is None:
        cfg = scenario.safety
        settle = cfg.retract_distance / cfg.retract_speed + 0.3
    scenario, _ = PrepareScenario(scenario, patient, start_fraction)
    diagram, h = BuildScanDiagram(scenario, patient, template)
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    station, supervisor, safety = h["station"], h["supervisor"], h["parts"].safety
    st_ctx = station.GetMyContextFromRoot(context)
    sup_ctx = supervisor.GetMyContextFromRoot(context)
    terminal = {PHASE_NAMES.index("DONE"), PHASE_NAMES.index("ABORT")}
    watch = ForceWatch(scenario.safety.force_ceiling)
    wrench = station.GetOutputPort("probe_contact_wrench_true")
    phase_port = supervisor.GetOutputPort("phase")
    stop_at_terminal = [True]

    def monitor(root_context):
        watch.add(root_context.get_time(), -float(wrench.Eval(st_ctx)[5]))
        if stop_at_terminal[0] and int(round(phase_port.Eval(sup_ctx)[0])) in terminal:
            return EventStatus.ReachedTermination(diagram, "scan finished")
        return EventStatus.Succeeded()

    simulator.set_monitor(monitor)
    simulator.Initialize()
    start = time.perf_counter()
    simulator.AdvanceTo(max_sim_time)
    t_end = context.get_time()
    # Keep the (stopped or finished) robot in the loop a little longer: it must be at rest.
    stop_at_terminal[0] = False
    simulator.AdvanceTo(t_end + settle)
    wall = time.perf_counter() - start
    v = _robot_velocity(station, st_ctx)
    cmd = np.asarray(safety.GetOutputPort("joint_velocity_command").Eval(
        safety.GetMyContextFromRoot(context)))
    stopped = bool(safety.GetOutputPort("stopped").Eval(safety.GetMyContextFromRoot(context))[0])
    # The scan result as of the end of the scan proper (before settling).
    result = _collect(scenario, patient, template, diagram, h, simulator, wall, end_time=t_end)
    result.sim_s = t_end
    check = {
        "peak_force_n": watch.peak, "time_above_ceiling_s": watch.time_above,
        "longest_above_ceiling_s": watch.longest_above, "force_violation": watch.violation,
        "final_joint_speed": float(np.max(np.abs(v))) if v.size else 0.0,
        "final_command_norm": float(np.linalg.norm(cmd)),
        "safety_stopped": stopped,
        "at_rest": bool(np.max(np.abs(v)) < REST_SPEED and np.linalg.norm(cmd) == 0.0)
        if stopped else None,
    }
    return result, check


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
