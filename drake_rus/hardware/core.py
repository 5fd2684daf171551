"""Pure functions of the hardware interface (numpy in, numpy out; no I/O, no Drake systems).

- sign conventions: libfranka's and drake-franka-driver's external torque estimate is the
  torque the robot applies TO the environment; Drake's (``tau_external``) is the generalized
  force ON the arm BY the environment: the two differ by a sign;
- stamps: drake-franka-driver compares a command's ``utime`` with its wall clock
  (microseconds since the Unix epoch) and drops old commands;
- the client-side command guard: non-finite -> zero, velocity scaled into the client limits,
  acceleration limited against the previous command, zero when dry-running or stopped;
- the command watchdog test;
- frame grabber: crop rectangle checks, crop, grey conversion, resize to the probe's image;
- the weight of an undeclared probe as joint torques; the robot's collision thresholds;
  control-loop timing statistics.
"""

from __future__ import annotations

import math
import time

import numpy as np

from drake_rus.extras import require

__all__ = [
    "external_torque_to_drake",
    "wall_clock_utime",
    "utime_age",
    "is_command_fresh",
    "limit_joint_velocity",
    "guard_command",
    "watchdog_expired",
    "check_crop",
    "crop_image",
    "to_grey",
    "fit_image",
    "check_robot_ip",
    "weight_torque",
    "load_declaration",
    "collision_thresholds",
    "period_statistics",
]


def external_torque_to_drake(tau_ext_robot) -> np.ndarray:
    """libfranka ``tau_ext_hat_filtered`` (or drake-franka-driver's ``joint_torque_external``)
    -> Drake's ``tau_external`` (N m): the generalized force on the arm by the environment.

    libfranka reports the external torque as the robot's action on the environment (its
    Cartesian estimate O_F_ext_hat_K: "forces applied by the robot to the environment are
    positive"), so the sign flips. The map is its own inverse.
    """
    return -np.asarray(tau_ext_robot, dtype=float).copy()


def wall_clock_utime(now_s: float | None = None) -> int:
    """Wall-clock microseconds since the Unix epoch (``time.time()`` unless given)."""
    if now_s is None:
        now_s = time.time()
    return int(round(float(now_s) * 1e6))


def utime_age(utime: int, now_s: float | None = None) -> float:
    """Age (s) of a message stamped ``utime`` (wall-clock microseconds) at ``now_s``."""
    return (wall_clock_utime(now_s) - int(utime)) * 1e-6


def is_command_fresh(utime: int, now_s: float, max_age: float) -> bool:
    """True when a command stamped ``utime`` is usable at ``now_s``: not older than
    ``max_age`` (s) and not from the future by more than ``max_age`` (a clock mix-up, e.g.
    a simulation-time stamp, is never fresh)."""
    return abs(utime_age(utime, now_s)) <= max_age


def limit_joint_velocity(v, v_max) -> np.ndarray:
    """Scales ``v`` (rad/s) uniformly so that |v_i| <= v_max_i for all i (direction kept)."""
    v = np.asarray(v, dtype=float)
    v_max = np.asarray(v_max, dtype=float)
    ratio = np.max(np.abs(v) / v_max) if v.size else 0.0
    return v / ratio if ratio > 1.0 else v.copy()


def guard_command(
    v_desired, v_previous, dt: float, v_max, a_max, *, enabled: bool = True
) -> np.ndarray:
    """The velocity (rad/s) actually sent to the robot this period.

    Zero when ``enabled`` is false (dry run, stopped, fault) or when ``v_desired`` has a
    non-finite entry; otherwise ``v_desired`` scaled into ``v_max`` and moved from
    ``v_previous`` by at most ``a_max * dt`` per joint (rad/s^2, s). Going to zero is not
    rate limited: a stop always takes effect at once (the robot's own generator then ramps
    within its limits).
    """
    v_desired = np.asarray(v_desired, dtype=float)
    v_previous = np.asarray(v_previous, dtype=float)
    if not enabled or not np.all(np.isfinite(v_desired)):
        return np.zeros_like(v_desired)
    if not np.all(np.isfinite(v_previous)):
        v_previous = np.zeros_like(v_desired)
    v = limit_joint_velocity(v_desired, v_max)
    if not np.any(v):
        return v
    step = np.asarray(a_max, dtype=float) * max(float(dt), 0.0)
    return v_previous + np.clip(v - v_previous, -step, step)


def watchdog_expired(now: float, last_command_time: float, timeout: float) -> bool:
    """True when no command arrived for longer than ``timeout`` (s) before ``now`` (s).
    A watchdog that never got a command (``last_command_time`` NaN) has expired."""
    if not math.isfinite(last_command_time):
        return True
    return now - last_command_time > timeout


def check_crop(crop, shape, field_name: str = "hardware_interface.video_crop") -> tuple:
    """Validates a crop rectangle [x, y, width, height] (pixels) against an image ``shape``
    (rows, cols[, channels]). Width = height = 0 means the whole image. Returns the
    rectangle as ints; raises ValueError naming ``field_name`` when it does not fit."""
    if len(crop) != 4:
        raise ValueError(f"field '{field_name}': expected [x, y, width, height], got {crop!r}")
    x, y, w, h = (int(c) for c in crop)
    rows, cols = int(shape[0]), int(shape[1])
    if w == 0 and h == 0 and x == 0 and y == 0:
        return 0, 0, cols, rows
    if min(x, y) < 0 or w <= 0 or h <= 0:
        raise ValueError(
            f"field '{field_name}': {list(crop)} needs x, y >= 0 and width, height > 0 (pixels)"
        )
    if x + w > cols or y + h > rows:
        raise ValueError(
            f"field '{field_name}': {list(crop)} reaches past the grabbed "
            f"picture of {cols} x {rows} pixels (width x height)"
        )
    return x, y, w, h


def crop_image(image: np.ndarray, crop) -> np.ndarray:
    """The part [y:y+h, x:x+w] of ``image`` for a crop rectangle [x, y, w, h] (see
    :func:`check_crop`)."""
    x, y, w, h = check_crop(crop, np.shape(image))
    return np.asarray(image)[y : y + h, x : x + w]


def to_grey(image: np.ndarray) -> np.ndarray:
    """uint8 grey (rows, cols) from a grabbed picture: grey, BGR or BGRA (OpenCV order);
    ITU-R BT.601 luma weights."""
    a = np.asarray(image)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if a.ndim == 3:
        if a.shape[2] not in (3, 4):
            raise ValueError(f"to_grey: expected 1, 3 or 4 channels, got {a.shape[2]}")
        b, g, r = (a[:, :, i].astype(float) for i in range(3))
        a = 0.114 * b + 0.587 * g + 0.299 * r
    elif a.ndim != 2:
        raise ValueError(
            f"to_grey: expected an image (rows, cols[, channels]), got shape {a.shape}"
        )
    if a.dtype != np.uint8:
        a = np.clip(np.rint(a), 0, 255).astype(np.uint8)
    return a


def fit_image(grey: np.ndarray, shape) -> np.ndarray:
    """Resamples a uint8 grey image to ``shape`` (rows, cols) by area averaging when
    shrinking, bilinear when growing (OpenCV); returns it unchanged when it fits already."""
    rows, cols = int(shape[0]), int(shape[1])
    if grey.shape == (rows, cols):
        return grey
    cv2 = require("cv2", "resampling the ultrasound picture")
    shrinking = grey.shape[0] >= rows and grey.shape[1] >= cols
    return cv2.resize(
        grey, (cols, rows), interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR
    )


def check_robot_ip(robot_ip: str, field_name: str = "hardware_interface.robot_ip") -> str:
    """A robot address: an IPv4 address or a host name. Raises ValueError naming the field."""
    import ipaddress
    import re

    text = str(robot_ip).strip()
    if not text:
        raise ValueError(f"field '{field_name}': empty robot address")
    if re.fullmatch(r"[0-9.]+", text):
        try:
            ipaddress.IPv4Address(text)
        except ValueError:
            raise ValueError(f"field '{field_name}': {robot_ip!r} is not an IPv4 address") from None
        return text
    if not re.fullmatch(
        r"[A-Za-z0-9]([A-Za-z0-9-]*[A-Za-z0-9])?"
        r"(\.[A-Za-z0-9]([A-Za-z0-9-]*[A-Za-z0-9])?)*",
        text,
    ):
        raise ValueError(
            f"field '{field_name}': {robot_ip!r} is neither an IPv4 address nor a host name"
        )
    return text


def weight_torque(J_v_WCm, mass: float, gravity) -> np.ndarray:
    """Generalized force (N m, Drake's sign: on the arm by the environment) of the weight of
    a body of ``mass`` (kg) hanging at a point whose translational Jacobian in the world is
    ``J_v_WCm`` (3, nv), in a ``gravity`` field (3, m/s^2): ``J^T m g``. A robot that was not
    told about the body reports this as external torque."""
    J = np.asarray(J_v_WCm, float)
    return J.T @ (float(mass) * np.asarray(gravity, float).reshape(3))


def load_declaration(tau_at_rest, tau_load, min_weight_torque: float = 0.5) -> str:
    """Which load model external torques measured at rest (Drake's sign, N m, no bias
    removed, nothing touching the probe) fit: "declared" (about zero: the robot knows the
    probe), "undeclared" (about ``tau_load``, the probe's weight as joint torques) or
    "unclear" (neither by a clear margin, or a weight too small to tell)."""
    tau = np.asarray(tau_at_rest, float)
    load = np.asarray(tau_load, float)
    w = float(np.linalg.norm(load))
    if w < min_weight_torque:
        return "unclear"
    r_declared = float(np.linalg.norm(tau))
    r_undeclared = float(np.linalg.norm(tau - load))
    if r_declared < 0.5 * w and r_declared < 0.5 * r_undeclared:
        return "declared"
    if r_undeclared < 0.5 * w and r_undeclared < 0.5 * r_declared:
        return "undeclared"
    return "unclear"


def collision_thresholds(config) -> dict:
    """libfranka ``setCollisionBehavior`` arguments (lower = contact, upper = collision;
    joint torques N m, Cartesian wrench N and N m) from a HardwareConfig; a contact threshold
    above its collision threshold is a ValueError naming the field."""
    out = {}
    for kind, n in (("torque", 7), ("force", 6)):
        lower = np.asarray(getattr(config, f"contact_{kind}_thresholds"), float)
        upper = np.asarray(getattr(config, f"collision_{kind}_thresholds"), float)
        if lower.shape != (n,) or upper.shape != (n,):
            raise ValueError(
                f"field 'hardware_interface.contact_{kind}_thresholds': expected {n} values"
            )
        if not (
            np.all(np.isfinite(lower))
            and np.all(np.isfinite(upper))
            and np.all(lower > 0)
            and np.all(upper > 0)
        ):
            raise ValueError(
                f"field 'hardware_interface.collision_{kind}_thresholds': "
                f"thresholds must be finite and positive"
            )
        if np.any(lower > upper):
            i = int(np.argmax(lower > upper))
            raise ValueError(
                f"field 'hardware_interface.contact_{kind}_thresholds': entry {i} "
                f"({lower[i]:g}) is above collision_{kind}_thresholds[{i}] ({upper[i]:g}): a "
                f"contact must be flagged before the robot stops"
            )
        out[f"lower_{kind}"], out[f"upper_{kind}"] = lower, upper
    return out


def period_statistics(times) -> dict:
    """Wall-clock gaps between consecutive ticks at ``times`` (s, increasing): count, mean,
    standard deviation, median, 99th and 99.9th percentiles and maximum (all s)."""
    t = np.asarray(times, float)
    gaps = np.diff(t) if t.size > 1 else np.zeros(0)
    if gaps.size == 0:
        return {
            "count": 0,
            "mean": math.nan,
            "std": math.nan,
            "p50": math.nan,
            "p99": math.nan,
            "p999": math.nan,
            "max": math.nan,
        }
    return {
        "count": int(gaps.size),
        "mean": float(gaps.mean()),
        "std": float(gaps.std()),
        "p50": float(np.percentile(gaps, 50)),
        "p99": float(np.percentile(gaps, 99)),
        "p999": float(np.percentile(gaps, 99.9)),
        "max": float(gaps.max()),
    }
