"""Fault and patient-motion models as pure functions of time (the functional core).

Everything here is deterministic: a fault's per-frame draws come from a hash of
(seed, frame index), so a run is reproducible and a system's output depends only on its
inputs and the time.
"""

from __future__ import annotations

import math

import numpy as np

from drake_rus.anatomy.labels import KIDNEY_LABELS, Label
from drake_rus.reliability.config import BreathingConfig, PatientShiftConfig, SensorFaultConfig

__all__ = ["breath_hold", "breathing_displacement", "shift_offset", "fault_active",
           "frame_affected", "force_offset", "remove_kidney", "add_false_kidney",
           "patient_offset_B", "hold_windows"]


def _hold_schedule(cfg: BreathingConfig):
    """(period, duration) of breath-holds, or None for free breathing only."""
    if cfg.hold_period <= 0.0 or cfg.hold_duration <= 0.0:
        return None
    return cfg.hold_period, min(cfg.hold_duration, cfg.hold_period)


def _hold_offset(cfg: BreathingConfig, k: int, seed: int) -> float:
    """Where hold k lands (m caudal of end-expiration): a fixed draw per hold, uniform in
    [0, hold_reproducibility]; before the first hold, 0."""
    if k < 0 or cfg.hold_reproducibility == 0.0:
        return 0.0
    rng = np.random.default_rng([seed, 7919, k])
    return float(rng.uniform(0.0, cfg.hold_reproducibility))


def breath_hold(t: float, cfg: BreathingConfig) -> bool:
    """True while the patient holds their breath at time t (s)."""
    if not cfg.enabled:
        return True
    schedule = _hold_schedule(cfg)
    if schedule is None or t < cfg.first_hold:
        return False
    period, duration = schedule
    return (t - cfg.first_hold) % period < duration


def hold_windows(t_end: float, cfg: BreathingConfig) -> list[tuple[float, float]]:
    """The breath-hold windows [(start, end)] up to t_end (s)."""
    schedule = _hold_schedule(cfg) if cfg.enabled else None
    if schedule is None:
        return []
    period, duration = schedule
    out, start = [], cfg.first_hold
    while start < t_end:
        out.append((start, min(start + duration, t_end)))
        start += period
    return out


def breathing_displacement(t: float, cfg: BreathingConfig, seed: int = 0) -> float:
    """Craniocaudal displacement d(t) (m, towards the feet is positive: inspiration pushes
    the kidney caudally). Continuous in t: free breathing between holds is a whole number
    of cycles that starts and ends at the holds' positions."""
    if not cfg.enabled:
        return 0.0
    A, f = cfg.amplitude, cfg.rate_per_min / 60.0
    schedule = _hold_schedule(cfg)
    if schedule is None:
        return A * 0.5 * (1.0 - math.cos(2.0 * math.pi * f * t))
    period, duration = schedule
    if t < cfg.first_hold:
        # Free breathing before the first hold, ending at end-expiration when it starts.
        n = max(1, round(cfg.first_hold * f))
        return A * 0.5 * (1.0 - math.cos(2.0 * math.pi * n * (cfg.first_hold - t)
                                         / cfg.first_hold))
    k = int((t - cfg.first_hold) // period)
    phase = (t - cfg.first_hold) - k * period
    if phase < duration:
        return _hold_offset(cfg, k, seed)
    free = period - duration
    s = (phase - duration) / free
    n = max(1, round(free * f))
    e0, e1 = _hold_offset(cfg, k, seed), _hold_offset(cfg, k + 1, seed)
    return A * 0.5 * (1.0 - math.cos(2.0 * math.pi * n * s)) + e0 + (e1 - e0) * s


def shift_offset(t: float, cfg: PatientShiftConfig) -> np.ndarray:
    """Rigid patient shift (m, robot base frame) at time t: 0 before cfg.time, ramped
    linearly to cfg.offset over cfg.ramp s."""
    if not cfg.enabled or t <= cfg.time:
        return np.zeros(3)
    s = min(1.0, (t - cfg.time) / cfg.ramp)
    return s * np.asarray(cfg.offset, dtype=float)


def patient_offset_B(t: float, breathing: BreathingConfig, shift: PatientShiftConfig,
                     superior_B: np.ndarray, seed: int = 0) -> np.ndarray:
    """Total displacement (m, base frame) of the imaged anatomy at time t."""
    d = breathing_displacement(t, breathing, seed)
    return -d * np.asarray(superior_B, dtype=float) + shift_offset(t, shift)


def fault_active(t: float, f: SensorFaultConfig) -> bool:
    return f.kind != "none" and f.start <= t < f.start + f.duration


def frame_affected(frame_index: int, f: SensorFaultConfig, seed: int) -> bool:
    """Whether frame ``frame_index`` is hit (a fixed draw with probability f.probability)."""
    if f.probability >= 1.0:
        return True
    if f.probability <= 0.0:
        return False
    u = np.random.default_rng([seed, 104729, max(frame_index, 0)]).random()
    return bool(u < f.probability)


def force_offset(t: float, f: SensorFaultConfig) -> float:
    """Extra pressing force (N) the force sensor reports at t for a force fault."""
    if not fault_active(t, f):
        return 0.0
    if f.kind == "force_bias":
        return f.magnitude
    if f.kind == "force_spike":
        return f.magnitude if (t - f.start) % f.spike_period < f.spike_width else 0.0
    return 0.0


def remove_kidney(labels: np.ndarray) -> np.ndarray:
    """A label image with the kidney replaced by soft tissue (a segmentation miss)."""
    out = np.array(labels, copy=True)
    out[np.isin(out, np.asarray(KIDNEY_LABELS, out.dtype))] = Label.SOFT_TISSUE
    return out


def add_false_kidney(labels: np.ndarray, fan_mask: np.ndarray, frame_index: int,
                     seed: int) -> np.ndarray:
    """A label image with a kidney-like ellipse painted at a random place inside the fan
    (a segmentation false positive). The ellipse is ~1/4 of the image wide."""
    out = np.array(labels, copy=True)
    h, w = out.shape
    rng = np.random.default_rng([seed, 15485863, max(frame_index, 0)])
    rows, cols = np.nonzero(fan_mask)
    if len(rows) == 0:
        return out
    i = rng.integers(len(rows))
    r0, c0 = rows[i], cols[i]
    a, b = 0.12 * w, 0.07 * h
    rr, cc = np.ogrid[:h, :w]
    blob = ((cc - c0) / a) ** 2 + ((rr - r0) / b) ** 2 <= 1.0
    out[blob & fan_mask] = Label.KIDNEY_CORTEX
    return out
