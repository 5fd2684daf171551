"""The FR3 through franky-control (libfranka 0.21 and Ruckig, from PyPI).

franky runs libfranka's 1 kHz loop in its own thread; we send joint-velocity targets at the
controller rate as asynchronous ``JointVelocityMotion`` s, each of which takes over from the
previous one seamlessly and *expires* after ``command_timeout`` (franky then ramps to zero on
its own): a frozen Python process stops the robot. On top of that a watchdog thread sends
zero when no fresh command came within ``command_timeout`` (and logs the latency).

Every robot call goes through one lock (the Drake thread and the watchdog thread share the
client). Any libfranka exception becomes :class:`HardwareFault` after the command has been set
to zero.

At connection the robot's own reflexes are set (``set_collision_behavior``: contact and
collision thresholds on joint torques and on the Cartesian wrench, below the safety layer's
force ceiling), the probe's load is declared (``set_load``), and a robot with errors pending
(after a reflex or the user stop) is either refused with a message saying what to do, or
reset (``error_recovery: at_connect``); never during a run.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import socket
import threading
import time

import numpy as np

from drake_rus.extras import install_hint
from drake_rus.hardware.config import HardwareConfig
from drake_rus.hardware.core import (
    check_robot_ip,
    collision_thresholds,
    external_torque_to_drake,
    watchdog_expired,
)

LOG = logging.getLogger("drake_rus.hardware")

__all__ = [
    "HardwareFault",
    "RobotReading",
    "WatchdogEvent",
    "FrankyBackend",
    "FCI_PORT",
    "COMMAND_LOG_LENGTH",
    "TRACE_LENGTH",
    "WATCHDOG_EVENTS_LENGTH",
    "robot_error_names",
    "wait_for_port",
]

FCI_PORT = 1337  # libfranka's command port on the robot's control box
# Commands kept in FrankyBackend.command_log: the newest 60 s at a 200 Hz command rate.
COMMAND_LOG_LENGTH = 12_000
# Ticks kept in FrankyBackend.trace (one per command tick): the same 60 s at 200 Hz.
TRACE_LENGTH = 12_000
# Events kept in FrankyBackend.watchdog_events: the watchdog fires at most once per nonzero
# command, so as many as the command log holds commands.
WATCHDOG_EVENTS_LENGTH = 12_000


def robot_error_names(errors) -> list[str]:
    """Names of the active errors in a franky ``Errors`` (libfranka franka::Errors)."""
    if errors is None:
        return []
    try:
        flags = errors.__getstate__()
    except Exception:
        return [] if not errors else [str(errors)]
    if not any(flags):
        return []
    names = sorted(
        n
        for n in dir(type(errors))
        if not n.startswith("_") and isinstance(getattr(type(errors), n, None), property)
    )
    active = [n for n in names if getattr(errors, n, False) is True]
    return active or [repr(errors)]


def wait_for_port(host: str, port: int, timeout: float) -> tuple[bool, float, str]:
    """Tries a TCP connection to ``host:port`` until it is accepted or ``timeout`` s pass.
    Returns (accepted, seconds spent, last error)."""
    start = time.monotonic()
    last = ""
    while True:
        remaining = timeout - (time.monotonic() - start)
        if remaining <= 0:
            return False, time.monotonic() - start, last
        try:
            with socket.create_connection((host, port), timeout=max(0.05, min(remaining, 2.0))):
                return True, time.monotonic() - start, ""
        except OSError as e:
            last = f"{type(e).__name__}: {e}"
        time.sleep(min(0.2, max(0.0, timeout - (time.monotonic() - start))))


def call_within(fn, timeout: float):
    """``fn()``'s result, or TimeoutError after ``timeout`` s (fn then runs on in a daemon
    thread, whose late result is dropped). Exceptions of fn are raised here."""
    box: dict = {}

    def run():
        try:
            box["value"] = fn()
        except BaseException as e:  # noqa: BLE001 - handed to the caller
            box["error"] = e

    worker = threading.Thread(target=run, name="drake_rus_connect", daemon=True)
    worker.start()
    worker.join(timeout)
    if worker.is_alive():
        raise TimeoutError(f"no result within {timeout:.1f} s")
    if "error" in box:
        raise box["error"]
    return box["value"]


class HardwareFault(RuntimeError):
    """The robot, its connection or the image source failed; the command is zero."""


@dataclasses.dataclass(frozen=True)
class RobotReading:
    """One robot state: joint positions (rad), velocities (rad/s), external torques in
    Drake's sign (N m, on the arm by the environment), wall-clock time of the read (s,
    ``time.monotonic``), the robot's own clock (s) and the velocity its controller is
    currently commanded (libfranka ``dq_d``, rad/s)."""

    q: np.ndarray
    v: np.ndarray
    tau_external: np.ndarray
    wall_time: float
    robot_time: float = math.nan
    v_commanded: np.ndarray | None = None


@dataclasses.dataclass(frozen=True)
class WatchdogEvent:
    """The watchdog zeroed the command: at ``wall_time`` (s, monotonic), ``latency`` (s)
    after the last fresh command."""

    wall_time: float
    latency: float


def _import_franky():
    try:
        import franky
    except ImportError as e:
        raise HardwareFault(
            f"field 'hardware_interface.backend': 'franky' needs franky-control, part of the "
            f"'hardware' extra: {install_hint('hardware')} ({e})"
        ) from None
    return franky


class FrankyBackend:
    """A connected FR3 (or franky-sim) through franky-control.

    ``read()`` returns a :class:`RobotReading`; ``send(v)`` commands joint velocities (rad/s;
    the caller has limited them); ``stop()`` brings the robot to rest; ``close()`` stops the
    watchdog and the robot. With ``config.dry_run`` the robot is never commanded: ``send``
    only records the zero it did not send.

    ``command_log`` holds the newest :data:`COMMAND_LOG_LENGTH` commands sent, as
    (``time.monotonic`` s, joint velocities rad/s), oldest first (a deque: the commands of a
    long run would otherwise fill the memory at the command rate). ``watchdog_events``
    holds the newest :data:`WATCHDOG_EVENTS_LENGTH` :class:`WatchdogEvent` s and ``trace``,
    when tracing, the newest :data:`TRACE_LENGTH` ticks: deques too (``list()`` one to
    slice it). Tracing starts by setting ``trace`` to a list (``[]``), kept as such a deque,
    and stops with ``None``.
    """

    def __init__(self, config: HardwareConfig, load=None):
        """``load``: (mass kg, centre of mass in the flange frame (3,) m, inertia about the
        centre of mass (3, 3) kg m^2) sent to libfranka when ``config.set_load``."""
        self.config = config
        self._load = load
        self.dry_run = bool(config.dry_run)
        self._franky = _import_franky()
        self._lock = threading.RLock()
        self._robot = None
        self._fault: str | None = None
        self._last_sent = np.zeros(7)
        self._last_command_time = math.nan
        self._moving = False
        self._robot_time = math.nan
        self._robot_time_change = math.nan
        self.watchdog_events: collections.deque[WatchdogEvent] = collections.deque(
            maxlen=WATCHDOG_EVENTS_LENGTH
        )
        self.command_log: collections.deque[tuple[float, np.ndarray]] = collections.deque(
            maxlen=COMMAND_LOG_LENGTH
        )  # (monotonic s, rad/s)
        self._trace: collections.deque[tuple[float, np.ndarray, np.ndarray, float]] | None = None
        self.tau_bias = np.zeros(7)
        self.collision_thresholds: dict | None = None
        self._stop_watchdog = threading.Event()
        self._watchdog = None
        self._connect()
        self._check_errors()
        self._configure_collision()
        self._configure_load()
        self._estimate_bias()
        self._watchdog = threading.Thread(
            target=self._watchdog_loop, name="drake_rus_watchdog", daemon=True
        )
        self._watchdog.start()

    @property
    def trace(self) -> collections.deque | None:
        """The ticks traced, oldest first: (robot clock s, q rad, velocity sent right after
        that read rad/s, wall clock of the read s monotonic); None when not tracing."""
        return self._trace

    @trace.setter
    def trace(self, ticks) -> None:
        """None stops tracing; a list (``[]``) starts it, kept as a deque of the newest
        :data:`TRACE_LENGTH` ticks (a long live run would otherwise fill the memory)."""
        self._trace = None if ticks is None else collections.deque(ticks, maxlen=TRACE_LENGTH)

    # --- connection -------------------------------------------------------------------
    def _connect(self):
        cfg = self.config
        host = check_robot_ip(cfg.robot_ip)
        franky = self._franky
        start = time.monotonic()
        # libfranka's own connection attempt can block for a minute on an unreachable
        # address: probe the FCI port first, within connect_timeout.
        reachable, spent, why = wait_for_port(host, FCI_PORT, cfg.connect_timeout)
        robot, last_error = None, why
        while reachable:
            try:
                # A peer that accepts TCP on the FCI port but never answers the handshake
                # holds franky.Robot() for about a minute inside libfranka: wait for it only
                # as long as connect_timeout allows.
                left = max(cfg.connect_timeout - (time.monotonic() - start), 0.5)
                robot = call_within(
                    lambda: franky.Robot(host, realtime_config=franky.RealtimeConfig.Ignore), left
                )
                break
            except TimeoutError:
                last_error = f"no handshake on {host}:{FCI_PORT} (a peer accepts, never answers)"
                break
            except Exception as e:  # NetworkException, IncompatibleVersionException, ...
                last_error = f"{type(e).__name__}: {e}"
                if (
                    isinstance(e, getattr(franky, "IncompatibleVersionException", ()))
                    or time.monotonic() - start > cfg.connect_timeout
                ):
                    break
                time.sleep(0.2)
        if robot is None:
            elapsed = time.monotonic() - start
            where = (
                f"no answer on {host}:{FCI_PORT} (libfranka's FCI port)"
                if not reachable
                else "the connection was refused"
            )
            raise HardwareFault(
                f"field 'hardware_interface.robot_ip': cannot connect to the FR3 at {host!r}: "
                f"{where} after {elapsed:.1f} s (hardware_interface.connect_timeout "
                f"{cfg.connect_timeout:g} s): {last_error or 'no error reported'}"
            )
        robot.relative_dynamics_factor = float(cfg.relative_dynamics_factor)
        self._robot = robot
        LOG.info(
            "connected to the FR3 at %s in %.1f s (dry run: %s)",
            host,
            time.monotonic() - start,
            self.dry_run,
        )

    def _check_errors(self):
        """A robot with errors pending (a reflex, the user stop) refuses motion. Reset it
        only when the configuration says so (error_recovery: at_connect)."""
        with self._lock:
            state = self._robot.state
        mode = getattr(state, "robot_mode", None)
        errors = robot_error_names(getattr(state, "current_errors", None))
        reflex = mode is not None and getattr(mode, "name", str(mode)) == "Reflex"
        if not errors and not reflex:
            return
        what = ", ".join(errors) or "robot in Reflex mode"
        if self.config.error_recovery != "at_connect":
            raise HardwareFault(
                f"FR3 at {self.config.robot_ip}: errors pending ({what}). Check the patient "
                f"and the probe (lift it in guiding mode if it still presses), then reset: "
                f"`drake-rus hardware check --recover`, or Desk's error acknowledgement "
                f"(hardware_interface.error_recovery: operator)"
            )
        LOG.warning(
            "FR3 at %s: errors pending (%s): automatic error recovery "
            "(hardware_interface.error_recovery: at_connect)",
            self.config.robot_ip,
            what,
        )
        try:
            with self._lock:
                recovered = self._robot.recover_from_errors()
        except Exception as e:
            raise HardwareFault(
                f"FR3 at {self.config.robot_ip}: error recovery failed: {type(e).__name__}: {e}"
            ) from None
        if recovered is False:
            raise HardwareFault(
                f"FR3 at {self.config.robot_ip}: error recovery failed ({what}); reset in Desk"
            )

    def _configure_collision(self):
        """The FR3's own contact / collision thresholds (libfranka setCollisionBehavior,
        the same while accelerating and at constant velocity)."""
        if not self.config.set_collision_behavior:
            LOG.warning(
                "hardware_interface.set_collision_behavior is false: the robot keeps "
                "its previous collision thresholds (franky's default: 20 N m, 30 N)"
            )
            return
        try:
            t = collision_thresholds(self.config)
        except ValueError as e:
            raise HardwareFault(str(e)) from None
        try:
            with self._lock:
                self._robot.set_collision_behavior(
                    t["lower_torque"], t["upper_torque"], t["lower_force"], t["upper_force"]
                )
        except Exception as e:
            raise HardwareFault(
                f"FR3 at {self.config.robot_ip}: set_collision_behavior "
                f"(hardware_interface.contact_/collision_*_thresholds) failed: "
                f"{type(e).__name__}: {e}"
            ) from None
        self.collision_thresholds = t
        LOG.info(
            "FR3 collision thresholds: joints %s N m, wrench %s (N, N m)",
            [float(x) for x in t["upper_torque"]],
            [float(x) for x in t["upper_force"]],
        )

    def _configure_load(self):
        if not (self.config.set_load and self._load is not None):
            return
        mass, p_FC, inertia = self._load
        inertia = np.asarray(inertia, float).reshape(3, 3)
        try:
            with self._lock:
                self._robot.set_load(
                    float(mass),
                    [float(x) for x in p_FC],
                    [float(x) for x in inertia.flatten(order="F")],
                )
        except Exception as e:
            raise HardwareFault(
                f"FR3 at {self.config.robot_ip}: set_load (scenario probe.mass, "
                f"probe.p_FCm, probe.inertia_diagonal) failed: "
                f"{type(e).__name__}: {e}"
            ) from None
        time.sleep(0.05)  # let the estimate settle on the new load

    def _estimate_bias(self):
        duration = float(self.config.tau_external_bias_duration)
        if duration <= 0.0:
            return
        samples = []
        end = time.monotonic() + duration
        while time.monotonic() < end or not samples:
            samples.append(self._read_raw().tau_external)
            time.sleep(0.005)
        self.tau_bias = np.mean(samples, axis=0)

    # --- reading ----------------------------------------------------------------------
    def _read_raw(self) -> RobotReading:
        with self._lock:
            if self._fault:
                raise HardwareFault(self._fault)
            try:
                if self._moving:
                    self._moving = self._robot.poll_motion()
                state = self._robot.state
            except Exception as e:
                self._set_fault(f"FR3 at {self.config.robot_ip}: {type(e).__name__}: {e}")
                raise HardwareFault(self._fault) from e
            now = time.monotonic()
            robot_time = state.time.to_msec() * 1e-3
            if robot_time != self._robot_time:
                self._robot_time, self._robot_time_change = robot_time, now
            elif now - self._robot_time_change > self.config.status_timeout:
                self._set_fault(
                    f"FR3 at {self.config.robot_ip}: robot state not updated for "
                    f"{now - self._robot_time_change:.3f} s (hardware_interface.status_timeout"
                    f" {self.config.status_timeout:g} s): connection lost"
                )
                raise HardwareFault(self._fault)
        return RobotReading(
            np.array(state.q, float),
            np.array(state.dq, float),
            external_torque_to_drake(state.tau_ext_hat_filtered),
            now,
            robot_time,
            np.array(state.dq_d, float),
        )

    def read(self) -> RobotReading:
        """The robot state now; external torques with the start-up bias removed."""
        r = self._read_raw()
        return dataclasses.replace(r, tau_external=r.tau_external - self.tau_bias)

    # --- commanding -------------------------------------------------------------------
    def send(self, v) -> np.ndarray:
        """Commands joint velocities ``v`` (rad/s) now; returns what was actually sent.
        ValueError, before anything is sent, when ``v`` is not 7 numbers."""
        v = np.asarray(v, float)
        if v.shape != (7,):
            raise ValueError(
                f"FrankyBackend.send: v must be 7 joint velocities (rad/s), got shape {v.shape}"
            )
        with self._lock:
            now = time.monotonic()
            self._last_command_time = now
            if self._fault or self.dry_run or not np.all(np.isfinite(v)):
                v = np.zeros(7)
            if self.dry_run:
                self._last_sent = v
                return v
            if not np.any(v) and not np.any(self._last_sent):
                return v  # at rest and asked to stay: start no motion
            self._move(v)
            self.command_log.append((now, v.copy()))
            return v

    def _move(self, v):
        franky = self._franky
        ms = max(1, int(round(self.config.command_timeout * 1000.0)))
        try:
            self._robot.move(
                franky.JointVelocityMotion(v, duration=franky.Duration(ms)), asynchronous=True
            )
            self._moving = True
            self._last_sent = v.copy()
        except Exception as e:
            self._last_sent = np.zeros(7)
            self._set_fault(f"FR3 at {self.config.robot_ip}: {type(e).__name__}: {e}")
            raise HardwareFault(self._fault) from e

    @property
    def last_sent(self) -> np.ndarray:
        with self._lock:
            return self._last_sent.copy()

    @property
    def fault(self) -> str | None:
        return self._fault

    def _set_fault(self, message: str):
        if self._fault is None:
            LOG.error("hardware fault: %s", message)
            self._fault = message
        self._last_sent = np.zeros(7)

    def _watchdog_loop(self):
        period = max(self.config.command_timeout / 5.0, 0.002)
        while not self._stop_watchdog.wait(period):
            with self._lock:
                now = time.monotonic()
                if np.any(self._last_sent) and watchdog_expired(
                    now, self._last_command_time, self.config.command_timeout
                ):
                    latency = now - self._last_command_time
                    LOG.warning(
                        "command watchdog: no fresh command for %.3f s: zero velocity", latency
                    )
                    self.watchdog_events.append(WatchdogEvent(now, latency))
                    try:
                        if not self._fault:
                            self._move(np.zeros(7))
                    except HardwareFault:
                        pass
                    self._last_sent = np.zeros(7)

    # --- stopping ---------------------------------------------------------------------
    def stop(self, timeout: float = 2.0) -> None:
        """Zero velocity now and wait (at most ``timeout`` s) until franky's motion ended and
        the robot's commanded velocity (``dq_d``) is zero.
        Never raises: a failed stop is logged (the robot stops on its own when the
        connection is gone)."""
        with self._lock:
            self._last_command_time = time.monotonic()
            was_moving = np.any(self._last_sent) or self._moving
            self._last_sent = np.zeros(7)
            if self.dry_run or self._robot is None or not was_moving:
                return
            try:
                self._robot.move(self._franky.JointVelocityStopMotion(), asynchronous=True)
                self.command_log.append((time.monotonic(), np.zeros(7)))
            except Exception as e:
                LOG.error("stop: %s: %s", type(e).__name__, e)
                return
        deadline = time.monotonic() + timeout
        try:
            self._robot.join_motion(timeout)
            # The motion has ended; wait until the robot's own commanded velocity is zero.
            while time.monotonic() < deadline:
                with self._lock:
                    dq_d = np.asarray(self._robot.state.dq_d, float)
                if np.abs(dq_d).max() < 1e-4:
                    break
                time.sleep(0.005)
            else:
                LOG.error("stop: the robot's commanded velocity is not zero after %g s", timeout)
        except Exception as e:
            LOG.error("stop: %s: %s", type(e).__name__, e)
        with self._lock:
            self._moving = False

    def close(self) -> None:
        """Stops the robot and the watchdog; the backend cannot be used afterwards."""
        self._stop_watchdog.set()
        try:
            self.stop()
        finally:
            if self._watchdog is not None:
                self._watchdog.join(1.0)
            with self._lock:
                self._robot = None
                if self._fault is None:
                    self._fault = "backend closed"

    def __del__(self):
        try:
            self._stop_watchdog.set()
        except Exception:
            pass
