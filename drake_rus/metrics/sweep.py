"""One definition of each sweep-cost metric of the seed's efficiency study (III-E), as plain
functions shared by the closed-loop scan (``drake_rus.scan.metrics``) and the kinematic
studies (``drake_rus.experiments``).

Definitions (the names every output uses):

- **pole to pole** (the paper's eps, n and V: "recorded when the probe is pivoting from one
  pole of the kidney to the other", III-E): for the two-leg pivot (II-G: out one way until the
  kidney leaves the image, then back through the start until it leaves on the other side),
  the frames of the second leg from its first to its last frame showing the kidney; for a
  one-way sweep (straight line), from its first to its last frame showing the kidney.
  Keys ``n``, ``eps`` (``eps_mm``), ``V``.
- **whole pivot** (beyond the paper: what the robot actually spends): every frame of the
  sweep, both legs of a pivot. Keys ``n_whole_pivot``, ``eps_whole_pivot`` (mm:
  ``eps_whole_pivot_mm``), ``V_whole_pivot``.
- **at matched coverage**: n and eps (pole to pole, counted from the pole-to-pole span's first
  frame) needed to first reach a given V (e.g. 0.9); None when the sweep never reaches it.
- **tilt cap**: a pivot leg that ended at the controller's tilt limit (``max_pivot_tilt``)
  instead of where the kidney left the image.

eps is eq. 24 (:func:`drake_rus.metrics.core.window_steps`, L = image depth); V is eq. 25 on
the frames in question (a fresh :class:`~drake_rus.metrics.core.CoverageAccumulator`).
"""

from __future__ import annotations

import math

import numpy as np

from drake_rus.metrics.core import window_steps

POLE_TO_POLE = (
    "pole to pole (the paper's eps, n, V, III-E): the pivot's second leg from its "
    "first to its last frame showing the kidney (a straight line: its first to its "
    "last frame showing the kidney)"
)
WHOLE_PIVOT = (
    "whole pivot: every frame of the sweep, both pivot legs (out to one end, back "
    "through the start, to the other end)"
)
MATCHED_V = (
    "at matched coverage: pole-to-pole n and eps (from the span's first frame) needed "
    "to first reach V"
)

__all__ = [
    "MATCHED_V",
    "POLE_TO_POLE",
    "WHOLE_PIVOT",
    "cumulative_eps",
    "pivot_legs",
    "pole_to_pole_indices",
    "signed_pivot_angles",
    "sweep_efficiency",
    "tilt_cap_legs",
    "to_reach",
]


def signed_pivot_angles(R_BP_list, o: np.ndarray | None = None) -> np.ndarray:
    """Signed tilt (rad) of each frame's approach z_P from the first frame's, about the array
    axis ``o`` (default: the first frame's x_P), the pivot angle of eq. 23 measured on the
    probe poses (3x3 matrices or RotationMatrix)."""
    Rs = [np.asarray(R.matrix() if hasattr(R, "matrix") else R, float) for R in R_BP_list]
    if not Rs:
        return np.zeros(0)
    axis = Rs[0][:, 0] if o is None else np.asarray(o, float)
    axis = axis / np.linalg.norm(axis)
    a0 = Rs[0][:, 2]
    out = []
    for R in Rs:
        a = R[:, 2]
        out.append(np.arctan2(float(np.cross(a0, a) @ axis), float(a0 @ a)))
    return np.asarray(out)


def pivot_legs(
    angles,
    tol: float = 1e-9,
    direction_fraction: float = 0.25,
    direction_tilt: float = math.radians(2.0),
) -> np.ndarray:
    """The leg (1 or 2) of each frame of a two-leg pivot from its signed tilt angles: leg 1
    runs to the first frame of the largest tilt in its direction (the reversal), leg 2 is
    every later frame. Leg 1's direction is the sign of the first tilt beyond
    ``direction_tilt`` (rad, 2 deg) or ``direction_fraction`` of the largest tilt, whichever
    is smaller: a closed-loop pivot starts with a residual tilt of either sign (the
    alignment's error, a fraction of a degree), which must not decide it, and a short first
    leg (a pivot point off the kidney's middle: leg 1 may reach under a quarter of leg 2's
    extent) must still be leg 1. A sweep that never tilts beyond ``tol`` is all leg 1."""
    th = np.asarray(angles, float)
    legs = np.ones(len(th), int)
    if len(th) == 0 or np.max(np.abs(th)) <= tol:
        return legs
    beyond = min(direction_tilt, direction_fraction * np.max(np.abs(th)))
    moved = np.flatnonzero(np.abs(th) > max(tol, beyond))
    direction = np.sign(th[moved[0]])
    turn = int(np.argmax(direction * th))
    legs[turn + 1 :] = 2
    return legs


def pole_to_pole_indices(visible, legs=None) -> np.ndarray:
    """Indices of the pole-to-pole frames: within leg 2 when the sweep has one (else every
    frame), from the first to the last frame showing the kidney; empty if none shows it."""
    vis = np.asarray(visible, bool)
    keep = np.ones(len(vis), bool)
    if legs is not None:
        legs = np.asarray(legs)
        if np.any(legs == 2):
            keep = legs == 2
    idx = np.flatnonzero(keep & vis)
    if len(idx) == 0:
        return np.zeros(0, int)
    return np.arange(idx[0], idx[-1] + 1)


def cumulative_eps(poses, image_depth: float) -> np.ndarray:
    """eps (m, eq. 24) after each pose, starting at 0 at the first one (len(poses) values)."""
    if len(poses) == 0:
        return np.zeros(0)
    return np.concatenate([[0.0], np.cumsum(window_steps(list(poses), image_depth))])


def to_reach(V_curve, eps_curve, target: float) -> dict | None:
    """{"n": frames, "eps": m} at the first frame where V >= ``target``; None if never."""
    V = np.asarray(V_curve, float)
    hit = np.flatnonzero(V >= target - 1e-12)
    if len(hit) == 0:
        return None
    k = int(hit[0])
    return {"n": k + 1, "eps": float(np.asarray(eps_curve, float)[k])}


def tilt_cap_legs(angles, legs, max_tilt: float, tol: float = np.deg2rad(0.5)) -> list[int]:
    """The legs (1, 2) whose largest tilt on their own side reached ``max_tilt`` (rad)
    within ``tol``: there the tilt cap, not the kidney leaving the image, ended the leg."""
    th = np.asarray(angles, float)
    legs = np.asarray(legs)
    out = []
    for leg in (1, 2):
        sel = th[legs == leg]
        if len(sel) and np.max(np.abs(sel)) >= max_tilt - tol:
            out.append(leg)
    return out


def sweep_efficiency(
    poses,
    visible,
    image_depth: float,
    *,
    legs=None,
    coverage=None,
    V_targets=(0.9,),
    angles=None,
    max_tilt: float | None = None,
) -> dict:
    """The sweep-cost metrics of one sweep (module docstring), SI units (m, rad).

    ``poses``: RigidTransform per acquired frame in order; ``visible``: kidney seen in each;
    ``legs``: pivot leg per frame (None: a straight line, or derived from ``angles`` when
    given); ``coverage``: a callable returning a fresh CoverageAccumulator (None: no V, e.g.
    on hardware); ``angles``: signed tilt per frame (for the tilt cap, with ``max_tilt``).

    Returns n, eps, V, eps_curve, V_curve (pole to pole), n_whole_pivot, eps_whole_pivot,
    V_whole_pivot, eps_whole_pivot_curve, V_whole_pivot_curve, pole_to_pole (indices),
    at_V {target: to_reach or None} and at_V_whole_pivot, tilt_cap_legs.
    """
    poses = list(poses)
    visible = np.asarray(visible, bool)
    if len(visible) != len(poses):
        raise ValueError(f"visible: expected {len(poses)} flags (one per pose), got {len(visible)}")
    if legs is None and angles is not None:
        legs = pivot_legs(angles)
    idx = pole_to_pole_indices(visible, legs)
    p2p = [poses[i] for i in idx]
    eps_curve = cumulative_eps(p2p, image_depth)
    eps_whole = cumulative_eps(poses, image_depth)
    V_curve = V_whole = None
    if coverage is not None:
        acc = coverage()
        V_curve = np.asarray([acc.add_frame(X) for X in p2p])
        acc = coverage()
        V_whole = np.asarray([acc.add_frame(X) for X in poses])
    targets = tuple(float(t) for t in V_targets)
    out = {
        "n": len(p2p),
        "eps": float(eps_curve[-1]) if len(p2p) else 0.0,
        "V": (float(V_curve[-1]) if len(V_curve) else 0.0) if V_curve is not None else None,
        "eps_curve": eps_curve,
        "V_curve": V_curve,
        "pole_to_pole": idx,
        "n_whole_pivot": len(poses),
        "eps_whole_pivot": float(eps_whole[-1]) if poses else 0.0,
        "V_whole_pivot": (
            (float(V_whole[-1]) if len(V_whole) else 0.0) if V_whole is not None else None
        ),
        "eps_whole_pivot_curve": eps_whole,
        "V_whole_pivot_curve": V_whole,
        "at_V": {
            t: (to_reach(V_curve, eps_curve, t) if V_curve is not None else None) for t in targets
        },
        "at_V_whole_pivot": {
            t: (to_reach(V_whole, eps_whole, t) if V_whole is not None else None) for t in targets
        },
        "tilt_cap_legs": [],
    }
    if angles is not None and max_tilt is not None:
        out["tilt_cap_legs"] = tilt_cap_legs(
            angles, legs if legs is not None else np.ones(len(poses), int), max_tilt
        )
    return out
