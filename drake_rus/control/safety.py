"""Safety layer logic (pure): fault checks, command limiting, stop and retract.

The safety layer sits between the controller and the station and can stop the robot on its
own. Every control period it checks, in this order: non-finite values anywhere, a robot
fault reported by the (hardware) station, contact
force above the ceiling, tip outside the workspace box, measured tip speed and joint
velocities above their limits, a stale image, a stale robot state, the kidney lost for too
long while the supervisor needs it, and a supervisor abort. The first fault latches a stop
(the command becomes zero in the same period) and is logged as an event with its reason. A
force-ceiling stop first retracts the probe along -a (out of the body) by a short distance,
then holds zero; a non-finite input, a robot fault or a workspace exit ends the retract.
Limits: docs/facts/fr3.md (FR3 joint velocity rectangular set
[2, 1, 1.5, 1.25, 3, 1.5, 3] rad/s, Cartesian 3.0 m/s, 2.5 rad/s).
"""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np

from drake_rus.control.laws import all_finite, damped_pseudo_inverse, scale_into_bounds

LOG = logging.getLogger("drake_rus.control.safety")


class StopReason:
    """Reason codes of safety stops (strings in the run log)."""

    NAN = "non-finite value"
    FORCE = "force ceiling"
    WORKSPACE = "workspace exit"
    TIP_SPEED = "tip speed limit"
    JOINT_SPEED = "joint velocity limit"
    STALE_IMAGE = "stale image"
    STALE_STATE = "stale robot state"
    SEGMENTATION_LOST = "segmentation lost"
    SUPERVISOR_ABORT = "supervisor abort"
    ROBOT_FAULT = "robot fault"


@dataclasses.dataclass(frozen=True)
class SafetyEvent:
    """One entry of the run log."""

    time: float
    reason: str
    detail: str


@dataclasses.dataclass
class SafetyInputs:
    """Everything one safety check reads (base frame B, SI units). NaN = not available."""

    t: float
    q: np.ndarray
    v: np.ndarray
    qdot_desired: np.ndarray
    R_BP: np.ndarray
    p_BP: np.ndarray
    F_z: float  # contact force along a (N), positive pressing
    J: np.ndarray  # 6x7 tip Jacobian [w; v] in B
    image_time: float = math.nan  # time stamp (s) of the newest image; NaN: no images
    # Time stamp (s) of the station's newest frame when ``image_time`` is that of the newest
    # segmented frame (NaN: not known): tells a stopped video from perception behind it.
    frame_time: float = math.nan
    kidney_visible: bool | None = None  # None: no segmenter connected
    segmentation_required: bool = True
    supervisor_abort: bool = False
    supervisor_reason: str = ""
    robot_ok: bool = True  # the hardware station's robot_ok (True in sim)


@dataclasses.dataclass
class SafetyState:
    stopped: bool = False
    reason: str = ""
    stop_time: float = math.nan
    retract_until: float = -math.inf
    retract_direction: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    last_q: np.ndarray | None = None
    # Since when (s) the joints have not moved while motion was commanded: reset by a joint
    # change and by every period that commands no motion (rest is not a stale state).
    last_q_change: float = 0.0
    # A finite image stamp has been seen: from then on a non-finite one is a fault, not
    # "no images".
    image_seen: bool = False
    invisible_since: float = math.nan
    events: tuple = ()

    # Drake clones abstract state values with deepcopy on every update; safety_step never
    # mutates a stored state in place (it works on a replaced copy), so clones may share it.
    def __deepcopy__(self, memo):
        return self

    def __copy__(self):
        return self

    def replace(self) -> "SafetyState":
        """A shallow copy (what ``dataclasses.replace(state)`` gives, for a fraction of the
        cost: this runs every control period). safety_step only rebinds its fields."""
        new = object.__new__(SafetyState)
        new.__dict__.update(self.__dict__)
        return new


def _non_finite(u: SafetyInputs, s: SafetyState, with_command: bool = True) -> str | None:
    """The name of the first non-finite input of ``u`` (the commanded joint velocities
    only ``with_command``; the image stamp once ``s`` has seen a finite one), or None."""
    arrays = (
        ("q", u.q),
        ("v", u.v),
        ("commanded qdot", u.qdot_desired),
        ("R_BP", u.R_BP),
        ("p_BP", u.p_BP),
        ("J", u.J),
    )
    if not with_command:
        arrays = tuple(a for a in arrays if a[0] != "commanded qdot")
    # One pass over all of them (this runs every control period); which one, only on a fault.
    if not all_finite(np.concatenate([np.asarray(x, dtype=float).ravel() for _, x in arrays])):
        for name, x in arrays:
            if not np.all(np.isfinite(np.asarray(x, dtype=float))):
                return f"{name} is not finite"
    if not math.isfinite(u.F_z):
        return "contact force is not finite"
    if s.image_seen and not math.isfinite(u.image_time):
        return f"image time stamp is {u.image_time} after finite ones"
    return None


def _workspace_fault(u: SafetyInputs, cfg) -> tuple[str, str] | None:
    """The tip outside the workspace box, as (reason, detail), or None."""
    p = np.asarray(u.p_BP, dtype=float)
    if any(
        not lo <= x <= hi for x, lo, hi in zip(p.tolist(), cfg.workspace_min, cfg.workspace_max)
    ):
        return StopReason.WORKSPACE, f"p_BP = {np.round(p, 4).tolist()} m outside the box"
    return None


def check_faults(u: SafetyInputs, s: SafetyState, cfg) -> tuple[str, str] | None:
    """The first fault present in ``u`` as (reason, detail), or None. Also updates the
    watchdog bookkeeping in ``s`` (last joint change, image stamps seen, kidney invisible
    since)."""
    bad = _non_finite(u, s)
    if bad is not None:
        return StopReason.NAN, bad
    if not u.robot_ok:
        return StopReason.ROBOT_FAULT, "the station reports robot_ok = 0"
    if u.F_z > cfg.force_ceiling:
        return StopReason.FORCE, f"F_z = {u.F_z:.2f} N > {cfg.force_ceiling:.2f} N"
    fault = _workspace_fault(u, cfg)
    if fault is not None:
        return fault
    tip_speed = float(np.linalg.norm(np.asarray(u.J)[3:] @ np.asarray(u.v)))
    if tip_speed > cfg.max_tip_speed:
        return StopReason.TIP_SPEED, f"|v_BP| = {tip_speed:.3f} m/s > {cfg.max_tip_speed} m/s"
    over = np.abs(u.v) > np.asarray(cfg.joint_velocity_limits)
    if np.any(over):
        i = int(np.argmax(over))
        return StopReason.JOINT_SPEED, f"joint {i + 1}: |v| = {abs(u.v[i]):.3f} rad/s"
    if math.isfinite(u.image_time):
        s.image_seen = True
    if math.isfinite(u.image_time) and u.t - u.image_time > cfg.image_timeout + 1e-9:
        if math.isfinite(u.frame_time) and u.t - u.frame_time <= cfg.image_timeout + 1e-9:
            return StopReason.STALE_IMAGE, (
                f"the segmentation fell behind the video: its newest result is of a frame "
                f"{u.t - u.image_time:.3f} s old while the video's newest is "
                f"{u.t - u.frame_time:.3f} s old (the computer is overloaded)"
            )
        return StopReason.STALE_IMAGE, f"newest image is {u.t - u.image_time:.3f} s old"
    q = np.asarray(u.q, dtype=float)
    changed = s.last_q is None or bool(np.any(q != s.last_q))
    if changed:
        s.last_q = q.copy()
    if changed or not np.linalg.norm(u.qdot_desired) > 1e-6:
        # Joints moved, or no motion commanded: the watchdog's clock starts again (time at
        # rest is not time "unchanged while moving").
        s.last_q_change = u.t
    elif u.t - s.last_q_change >= cfg.state_timeout - 1e-9:
        return StopReason.STALE_STATE, (
            f"joint positions unchanged for {u.t - s.last_q_change:.3f} s while moving"
        )
    if u.kidney_visible is not None and u.segmentation_required and not u.kidney_visible:
        if math.isnan(s.invisible_since):
            s.invisible_since = u.t
        if u.t - s.invisible_since >= cfg.segmentation_timeout - 1e-9:
            return StopReason.SEGMENTATION_LOST, (
                f"kidney invisible for {u.t - s.invisible_since:.3f} s"
            )
    else:
        s.invisible_since = math.nan
    if u.supervisor_abort:
        return StopReason.SUPERVISOR_ABORT, u.supervisor_reason or "supervisor aborted"
    return None


def limit_command(qdot, J, joint_velocity_limits, command_tip_speed: float) -> np.ndarray:
    """Scales a joint velocity command (direction kept) into the joint velocity limits and
    the commanded tip speed limit |J_v qdot| <= command_tip_speed."""
    qdot = np.asarray(qdot, dtype=float)
    lim = np.asarray(joint_velocity_limits, dtype=float)
    qdot = scale_into_bounds(qdot, -lim, lim)
    v = float(np.linalg.norm(np.asarray(J)[3:] @ qdot))
    if v > command_tip_speed:
        qdot = qdot * (command_tip_speed / v)
    return qdot


def retract_velocity(J, direction, speed: float) -> np.ndarray:
    """Joint velocities moving the tip at ``speed`` (m/s) along ``direction`` with zero
    angular velocity (damped pseudo-inverse of the tip Jacobian)."""
    J_pinv, _, _ = damped_pseudo_inverse(J)
    d = np.asarray(direction, dtype=float)
    return J_pinv @ np.concatenate([np.zeros(3), speed * d / np.linalg.norm(d)])


def safety_step(state: SafetyState, u: SafetyInputs, cfg) -> tuple[np.ndarray, SafetyState]:
    """One period of the safety layer: returns (joint velocity command, new state).

    While running, the desired command is limited (:func:`limit_command`). On the first
    fault the stop latches: the command is zero from this period on, except after a force
    ceiling stop, which retracts along -a for retract_distance / retract_speed seconds. A
    non-finite input, a robot fault or a workspace exit during the retract ends it (zero
    from that period on, logged as an event).
    """
    s = state.replace()
    n = len(u.q)
    if s.stopped:
        if u.t < s.retract_until:
            bad = _non_finite(u, s, with_command=False)
            if bad is not None:
                fault = StopReason.NAN, bad
            elif not u.robot_ok:
                fault = StopReason.ROBOT_FAULT, "the station reports robot_ok = 0"
            else:
                fault = _workspace_fault(u, cfg)
            if fault is None:
                return _retract_command(u, s, cfg), s
            s.retract_until = -math.inf
            reason, detail = fault
            s.events = s.events + (SafetyEvent(u.t, reason, f"retract ended: {detail}"),)
            LOG.warning("safety: retract ended at t = %.3f s: %s (%s)", u.t, reason, detail)
        return np.zeros(n), s
    fault = check_faults(u, s, cfg)
    if fault is None:
        return limit_command(
            u.qdot_desired, u.J, cfg.joint_velocity_limits, cfg.command_tip_speed
        ), s
    reason, detail = fault
    s.stopped = True
    s.reason = reason
    s.stop_time = u.t
    s.events = s.events + (SafetyEvent(u.t, reason, detail),)
    LOG.warning("safety stop at t = %.3f s: %s (%s)", u.t, reason, detail)
    if reason == StopReason.FORCE and cfg.retract_distance > 0:
        s.retract_direction = -np.asarray(u.R_BP, dtype=float)[:, 2]
        s.retract_until = u.t + cfg.retract_distance / cfg.retract_speed
        return _retract_command(u, s, cfg), s
    return np.zeros(n), s


def _retract_command(u, s, cfg) -> np.ndarray:
    """Joint velocities (rad/s) backing the probe off along ``s.retract_direction`` at
    ``retract_speed``, within the joint and tip speed limits."""
    return limit_command(
        retract_velocity(u.J, s.retract_direction, cfg.retract_speed),
        u.J,
        cfg.joint_velocity_limits,
        cfg.command_tip_speed,
    )
