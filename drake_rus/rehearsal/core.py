"""Pure functions of the rehearsal (numbers in, numbers out; no processes, no Drake systems).

- command ages at the simulated driver: statistics;
- the robot's reaction to a stop: when the last moving command arrived, when the joints
  came to rest, from the simulator's logs and the moment of the signal;
- PIVOT-like motion from the probe's poses (the tip stays, the probe turns slowly while in
  contact): how the simulated robot can tell, from outside the scan, that it is pivoting;
- the scan side's scenario overrides from what the simulated robot announced;
- poses to and from JSON; the errors of the scan's kidney estimate against the truth;
- the simulated robot's status stalls: what else was running while a status was late;
- network isolation: is this process in a network namespace with only the loopback?
"""

from __future__ import annotations

import json
import math
import os
import socket
from pathlib import Path

import numpy as np
from pydrake.math import RigidTransform, RotationMatrix

from drake_rus.metrics import e_rot_x, e_trans
from drake_rus.metrics.core import geodesic_angle

__all__ = [
    "age_statistics",
    "stall_causes",
    "stop_reaction",
    "PivotDetector",
    "scan_overrides",
    "pose_to_json",
    "pose_from_json",
    "kidney_errors",
    "loopback_only",
    "NETNS_SETUP",
    "netns_argv",
    "raise_priority",
    "realtime_scheduling",
]

# Inside a fresh network namespace: bring the loopback up and route multicast (LCM's udpm)
# over it, so nothing leaves the namespace.
NETNS_SETUP = "ip link set lo up && ip route add 224.0.0.0/4 dev lo"


def age_statistics(ages_s) -> dict:
    """Count, median, 95th percentile, max and min (ms) of command ages (s)."""
    a = np.asarray([x for x in ages_s if math.isfinite(x)], float)
    if a.size == 0:
        return {"count": 0, "median_ms": None, "p95_ms": None, "max_ms": None, "min_ms": None}
    return {
        "count": int(a.size),
        "median_ms": float(np.median(a) * 1e3),
        "p95_ms": float(np.percentile(a, 95) * 1e3),
        "max_ms": float(a.max() * 1e3),
        "min_ms": float(a.min() * 1e3),
    }


def stall_causes(times, threshold: float, activities: dict, *, worst: int = 10) -> dict:
    """What overlapped each stall of a periodic stream.

    ``times`` (s, one clock): when each message went out; a stall is a gap between
    successive messages longer than ``threshold`` s. ``activities``: name -> intervals
    ``(start, end)`` (s, the same clock) of what else ran (a garbage collection, a physics
    tick holding a frame, a picture rendered). Returns ``stalls`` (count), ``by_cause``
    (name -> stalls it overlapped; "none" when nothing did), ``busy_fraction`` (name -> the
    share of the stream's time it ran: the overlap chance alone gives) and ``worst`` (the
    ``worst`` longest: start s, gap ms, the names overlapping)."""
    t = np.asarray(times, float)
    gaps = np.diff(t) if t.size > 1 else np.zeros(0)
    spans = {name: np.asarray(v, float).reshape(-1, 2) for name, v in activities.items()}
    found = []
    for i in np.flatnonzero(gaps > threshold):
        a, b = t[i], t[i + 1]
        names = sorted(name for name, s in spans.items() if np.any((s[:, 0] < b) & (s[:, 1] > a)))
        found.append((float(a), float(1e3 * gaps[i]), names))
    by_cause = {name: 0 for name in activities}
    by_cause["none"] = 0
    for _, _, names in found:
        for name in names or ["none"]:
            by_cause[name] += 1
    found.sort(key=lambda s: -s[1])
    # The share of the stream's time each activity ran: what chance alone would overlap.
    duration = float(t[-1] - t[0]) if t.size > 1 else 0.0
    busy = {
        name: (float(np.sum(s[:, 1] - s[:, 0])) / duration if duration > 0 else None)
        for name, s in spans.items()
    }
    return {
        "threshold_ms": 1e3 * float(threshold),
        "stalls": len(found),
        "by_cause": by_cause,
        "busy_fraction": busy,
        "worst": [
            {"start_s": a, "gap_ms": round(g, 2), "during": names} for a, g, names in found[:worst]
        ],
    }


def stop_reaction(t_signal: float, commands, speeds, *, rest_speeds=(1e-2, 1e-3)) -> dict:
    """How fast the simulated robot stopped after a stop signal at wall time ``t_signal`` (s).

    ``commands``: [(wall time s it arrived at the robot, max |v| commanded rad/s)], in
    order; ``speeds``: [(wall time s, max |joint velocity| rad/s, max |applied command|
    rad/s)] as sampled by the simulator. Returns times (s) relative to ``t_signal`` (None
    when it never happened): ``last_moving_command`` (the last non-zero command to arrive),
    ``first_zero_command`` (the first zero command after the signal), ``command_zero`` (the
    applied command zero for good), ``at_rest`` {threshold rad/s: the max |joint velocity|
    below it for good}; and ``speed_at_signal`` (rad/s)."""
    out = {
        "last_moving_command": None,
        "first_zero_command": None,
        "command_zero": None,
        "at_rest": {},
        "speed_at_signal": None,
    }
    moving = [t for t, v in commands if v > 0.0]
    if moving:
        out["last_moving_command"] = moving[-1] - t_signal
    zeros = [t for t, v in commands if v == 0.0 and t >= t_signal]
    if zeros:
        out["first_zero_command"] = zeros[0] - t_signal
    s = np.asarray(speeds, float).reshape(-1, 3)
    after = s[s[:, 0] >= t_signal]
    before = s[s[:, 0] < t_signal]
    if before.size:
        out["speed_at_signal"] = float(before[-1, 1])

    def settled(column: int, limit: float):
        bad = np.nonzero(after[:, column] > limit)[0]
        k = 0 if bad.size == 0 else int(bad[-1]) + 1
        return float(after[k, 0] - t_signal) if k < len(after) else None

    if after.size:
        out["command_zero"] = settled(2, 0.0)
        out["at_rest"] = {repr(float(v)): settled(1, float(v)) for v in rest_speeds}
    return out


class PivotDetector:
    """Tells PIVOT-like motion from the probe poses sampled over time: in contact (force
    above ``min_force`` N), the tip nearly still (below ``max_tip_speed`` m/s) while the
    probe turns at ``rate_range`` rad/s, over a ``window`` s. ``update`` returns how long
    (s) the motion has been PIVOT-like without a break (0 when it is not)."""

    def __init__(
        self,
        *,
        window: float = 0.2,
        max_tip_speed: float = 0.002,
        rate_range=(0.08, 0.4),
        min_force: float = 2.0,
    ):
        self.window = float(window)
        self.max_tip_speed = float(max_tip_speed)
        self.rate_range = (float(rate_range[0]), float(rate_range[1]))
        self.min_force = float(min_force)
        self._samples: list = []
        self._since: float | None = None
        self.tip_speed = math.nan
        self.turn_rate = math.nan

    def update(self, t: float, X_BP: RigidTransform, force: float) -> float:
        self._samples.append((float(t), RigidTransform(X_BP)))  # a copy: ports reuse theirs
        while len(self._samples) > 2 and self._samples[1][0] <= t - self.window:
            self._samples.pop(0)
        t0, X0 = self._samples[0]
        dt = t - t0
        if dt < 0.5 * self.window:
            return 0.0 if self._since is None else t - self._since
        self.tip_speed = float(np.linalg.norm(X_BP.translation() - X0.translation()) / dt)
        self.turn_rate = geodesic_angle(X0.rotation().matrix(), X_BP.rotation().matrix()) / dt
        pivoting = (
            force >= self.min_force
            and self.tip_speed <= self.max_tip_speed
            and self.rate_range[0] <= self.turn_rate <= self.rate_range[1]
        )
        if not pivoting:
            self._since = None
            return 0.0
        if self._since is None:
            self._since = t0
        return t - self._since


def scan_overrides(ready: dict, *, compensate_load: bool = True) -> str:
    """The scan side's scenario overrides (YAML) for a simulated robot that announced
    ``ready`` (its ``lcm_url``, channels, ``video_url`` and the depth preset ``depth`` the
    operator sets on the machine): the hardware station on the LCM route, moving."""
    hw = {
        "backend": "lcm",
        "lcm_url": ready["lcm_url"],
        "lcm_command_channel": ready["command_channel"],
        "lcm_status_channel": ready["status_channel"],
        "video_source": ready["video_url"],
        "dry_run": False,
        "lcm_compensate_load": bool(compensate_load),
    }
    return json.dumps(
        {"hardware": True, "imaging": {"depth": float(ready["depth"])}, "hardware_interface": hw}
    )


def pose_to_json(X: RigidTransform) -> dict:
    return {
        "translation": [float(v) for v in X.translation()],
        "rotation": [[float(v) for v in row] for row in X.rotation().matrix()],
    }


def pose_from_json(d: dict) -> RigidTransform:
    R = np.asarray(d["rotation"], float)
    return RigidTransform(RotationMatrix(R), np.asarray(d["translation"], float))


def kidney_errors(X_BK_estimated: RigidTransform | None, X_BK_true: RigidTransform) -> dict:
    """E_trans (mm) and E_rot,x (deg) of the scan's estimate against the truth (None
    without an estimate)."""
    if X_BK_estimated is None:
        return {"e_trans_mm": None, "e_rot_x_deg": None}
    return {
        "e_trans_mm": e_trans(X_BK_estimated, X_BK_true) * 1e3,
        "e_rot_x_deg": math.degrees(e_rot_x(X_BK_estimated, X_BK_true)),
    }


def loopback_only() -> bool:
    """True when the only network interface this process sees is the loopback (a private
    network namespace). Asks the kernel for this process's namespace (``if_nameindex``;
    ``/sys/class/net`` shows the namespace /sys was mounted in)."""
    try:
        names = {name for _, name in socket.if_nameindex()}
    except OSError:
        return False
    return names <= {"lo"}


def netns_argv(argv: list[str]) -> list[str]:
    """``argv`` run in a new private network namespace with only the loopback, multicast
    routed over it (needs root, or unprivileged user namespaces)."""
    return ["unshare", "-n", "bash", "-c", NETNS_SETUP + ' && exec "$@"', "drake-rus-netns", *argv]


def raise_priority(nice: int) -> str:
    """Gives this process (and, with autogroup scheduling, its session) the scheduling
    priority ``nice`` (-20..19; below 0 needs root). Both sides of a rehearsal must keep up
    with the wall clock; on a shared machine whose other sessions keep the cores busy, the
    kernel's per-session fair share alone may not leave them enough. Returns what was done
    (or why not); never raises."""
    if nice == 0:
        return "priority unchanged"
    done = []
    try:
        os.setpriority(os.PRIO_PROCESS, 0, int(nice))
        done.append(f"nice {nice}")
    except OSError as e:
        return f"cannot set nice {nice}: {e}"
    try:
        Path("/proc/self/autogroup").write_text(f"{int(nice)}\n")
        done.append("session group too")
    except OSError:
        pass  # no autogroup scheduling: the process nice is enough
    return ", ".join(done)


def realtime_scheduling(priority: int) -> str:
    """Puts the calling thread in SCHED_FIFO at ``priority``; says what it got ("SCHED_FIFO
    10", or "normal (why not)": it needs root or CAP_SYS_NICE)."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(int(priority)))
    except (AttributeError, OSError, ValueError) as e:
        return f"normal ({type(e).__name__}: {e})"
    return f"SCHED_FIFO {int(priority)}"


def stop_process(process, timeout: float = 2.0) -> None:
    """Terminates a helper ``multiprocessing.Process`` if it still runs, waiting up to
    ``timeout`` s for it to end."""
    if process.is_alive():
        process.terminate()
        process.join(timeout)


def await_ready(process, conn, timeout: float, name: str):
    """Waits up to ``timeout`` s for a started helper ``process`` to send ("ready", value)
    on ``conn`` and returns the value; on silence or any other message stops it and raises
    RuntimeError naming the ``name`` process."""
    if not conn.poll(timeout):
        stop_process(process)
        raise RuntimeError(f"the {name} process was not ready within {timeout:g} s")
    kind, value = conn.recv()
    if kind != "ready":
        stop_process(process)
        raise RuntimeError(f"the {name} process failed: {value}")
    return value
