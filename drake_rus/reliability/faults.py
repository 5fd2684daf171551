"""Sensor-fault models as pure functions of time and frame index (the functional core).

Patient motion (breathing, shift) lives in :mod:`drake_rus.anatomy.motion`.

Everything here is deterministic: a fault's per-frame draws come from a hash of
(seed, frame index), so a run is reproducible and a system's output depends only on its
inputs and the time.
"""

from __future__ import annotations

import numpy as np

from drake_rus.anatomy.labels import KIDNEY_LABELS, Label
from drake_rus.reliability.config import SensorFaultConfig

__all__ = ["fault_active", "frame_affected", "force_offset", "remove_kidney", "add_false_kidney"]


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


def add_false_kidney(
    labels: np.ndarray, fan_mask: np.ndarray, frame_index: int, seed: int
) -> np.ndarray:
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
