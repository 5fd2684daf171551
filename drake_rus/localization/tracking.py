"""Kidney tracking after localization: has the kidney moved away from its registered pose?

The pivot (seed II-G) trusts one registration made at the end of exploration. If the
patient shifts afterwards, the probe pivots about the wrong point and the "whole-kidney"
sweep images the wrong place while reporting success. The monitor re-checks the estimate
on the frames acquired after localization: it back-projects their kidney boundary pixels
into the kidney frame K and fits the one translation that best lays them on the registered
template (trimmed point-to-plane ICP, translation only). That translation is the kidney's
apparent drift since localization.

A still kidney already drifts apparently: the registration's own error, seen through the
current view. Its largest part lies along the registered long axis: the exploration saw one
pole, the template's length is not the kidney's (108 mm against 88-140 mm), and long-axis
pivot frames that reach the poles pull the template along the axis by half the difference
(16.6 mm on a still 140 mm kidney). ``judged_drift`` therefore counts the component along
the registered long axis only beyond ``tracking_axial_allowance``, and ``tracking_limits``
sets the limit from the registration's residual, max(``tracking_max_drift``,
``tracking_rms_factor`` x RMS). A judged drift above the limit on
``tracking_confirmations`` successive checks is reported on ``tracking_error`` and the
supervisor aborts the scan. (Neither the normal-equation covariance, 0.06-0.46 mm for
registrations 0.3-21 mm off, nor the drift of the first checks after localization, 1.5 mm
on a registration that later reads 17 mm while still, predicts that error; see
``LocalizationConfig``.)

Segmentation outliers are not motion: a frame is compared with the registration only where
the registered kidney crosses its view (``kidney_in_view``), and the fit leaves out the
frames whose points lie far from the template while the window's other frames fit it (a
moved kidney moves in every frame; a muscle band the segmenter takes for the kidney shows in
a few).

A shift along the kidney's long axis barely moves a longitudinal section (test:3: 11.2 mm
along the axis read 2.6 mm), but the patient sliding under the probe drags it by friction:
the tangential part of the probe's force jumps (``tangential_force_change``,
``slip_update``; ``tracking_slip_force``), which no registration error does.

``estimate_drift``, ``kidney_in_view``, ``tracking_limits``, ``judged_drift``,
``tracking_update``, ``tangential_force_change`` and ``slip_update`` are the plain
functions; ``KidneyTrackingMonitor`` is the LeafSystem.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import EventStatus, LeafSystem
from scipy.spatial import cKDTree

from drake_rus.executor import InlineExecutor
from drake_rus.imaging.backprojection import backproject_pixels
from drake_rus.imaging.frames import BoundaryPixels, KidneySurface, PointCloud
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.localization.icp import MovingNearest, _template_tree
from drake_rus.localization.localize import (
    LocalizationOutcome,
    fitted_shape_K,
    max_rms_residual,
)
from drake_rus.localization.pivot_view import pivot_residual_bound, pivot_view_error

__all__ = [
    "estimate_drift",
    "kidney_in_view",
    "DriftEstimate",
    "TrackingLimits",
    "tracking_limits",
    "judged_drift",
    "TrackingState",
    "tracking_update",
    "KidneyTrackingMonitor",
    "registered_shape_K",
    "RegisteredKidneySurface",
    "drift_fit",
    "registered_tree",
    "tangential_force_change",
    "changed_across_stretches",
    "slip_update",
    "same_view",
    "window_view",
]


@dataclasses.dataclass(frozen=True)
class DriftEstimate:
    """The kidney's apparent displacement since localization."""

    drift_B: np.ndarray  # (3,) m, in the base frame
    rms_residual: float  # m, point-to-plane residual of the kept pairs after the fit
    n_points: int
    n_frames_used: int = 0  # frames kept by the consensus gate (0: frames not given)
    n_frames: int = 0

    @property
    def magnitude(self) -> float:
        return float(np.linalg.norm(self.drift_B))


def group_medians(values: np.ndarray, groups: np.ndarray, n_groups: int) -> np.ndarray:
    """(n_groups,) median of ``values`` over each group (``groups``: (N,) ints in
    [0, n_groups), every group non-empty), as ``np.median`` gives it (the mean of the two
    middle values for an even count), with one sort instead of one median per group."""
    values = np.asarray(values, dtype=float).reshape(-1)
    groups = np.asarray(groups).reshape(-1)
    return _sorted_group_medians(values, groups, *_middle_ranks(groups, n_groups))


def _middle_ranks(groups: np.ndarray, n_groups: int) -> tuple[np.ndarray, np.ndarray]:
    """(low, high): where each group's two middle values (the same one for an odd count)
    sit once the values are sorted by group, then value."""
    counts = np.bincount(groups, minlength=n_groups)
    if np.any(counts == 0):
        raise ValueError("group_medians: every group needs at least one value")
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    return start + (counts - 1) // 2, start + counts // 2


def _sorted_group_medians(values, groups, low, high) -> np.ndarray:
    """group_medians with the groups' middle ranks (``_middle_ranks``) given."""
    ranked = values[np.lexsort((values, groups))]
    return 0.5 * (ranked[low] + ranked[high])


def estimate_drift(
    points_B: np.ndarray,
    X_BK: RigidTransform,
    shape_K: np.ndarray,
    normals_K: np.ndarray,
    *,
    tree: cKDTree | None = None,
    iterations: int = 15,
    keep_fraction: float = 0.7,
    regularization: float = 0.05,
    frame_ids: np.ndarray | None = None,
    frame_gate_factor: float = 3.0,
    frame_gate_floor: float = 0.010,
) -> DriftEstimate:
    """Translation (m, frame B) that moves the registered template onto ``points_B``.

    points_B (N, 3): kidney boundary points seen after localization (m, B); X_BK: the
    registered kidney pose; shape_K (M, 3) and normals_K (M, 3): the registered template
    surface in K. Each iteration pairs every point with its nearest template point, keeps
    the ``keep_fraction`` smallest point-to-plane residuals (boundary pixels where the fan
    cuts the kidney are not on its surface) and solves the regularised least squares
    (A^T A + regularization N I) t = A^T b. Directions the points do not constrain (one
    flat cross-section) stay near zero instead of drifting.

    frame_ids (N,): which frame each point came from. A moved kidney moves in every frame,
    a segmentation outlier (a muscle band taken for the kidney) in a few: each iteration
    leaves out the frames whose median distance to the template exceeds
    max(``frame_gate_factor`` x the median over frames, ``frame_gate_floor`` m).

    tree: a scipy kd-tree of ``shape_K`` (None: a cached one is built); the iterations ask
    it only for the points whose earlier candidates no longer provably hold their nearest
    template point (``MovingNearest``), with the same neighbours as a query every time.
    """
    points_B = np.asarray(points_B, dtype=float).reshape(-1, 3)
    if len(points_B) == 0:
        return DriftEstimate(np.zeros(3), math.nan, 0)
    shape_K = np.asarray(shape_K, dtype=float)
    if tree is None:
        tree = _template_tree(shape_K)
    # The points only slide by the small steps of t: most keep provably the same nearest
    # template point between iterations (MovingNearest: the kd-tree's answer, fewer queries).
    nearest = MovingNearest()
    X_KB = X_BK.inverse()
    p_K = X_KB.multiply(points_B.T).T
    t = np.zeros(3)
    rms = math.nan
    frames_used = n_frames = 0
    if frame_ids is not None:
        _, inverse = np.unique(np.asarray(frame_ids).reshape(-1), return_inverse=True)
        n_frames = int(inverse.max()) + 1
        middle = _middle_ranks(inverse, n_frames)  # the frames stay: rank them once
    for _ in range(iterations):
        x = p_K + t
        dist, idx = nearest.query(x, shape_K, lambda: tree)
        n = normals_K[idx]
        r = np.einsum("ij,ij->i", n, x - shape_K[idx])
        use = np.ones(len(r), bool)
        if frame_ids is not None:
            median = _sorted_group_medians(dist, inverse, *middle)
            gate = max(frame_gate_factor * float(np.median(median)), frame_gate_floor)
            use = (median <= gate)[inverse]
            frames_used = int(np.count_nonzero(median <= gate))
        abs_r = np.abs(r)
        cutoff = np.quantile(abs_r[use], keep_fraction)
        keep = use & (abs_r <= cutoff)
        A, b = n[keep], -r[keep]
        rms = float(np.sqrt(np.mean(r[keep] ** 2)))
        H = A.T @ A + regularization * len(A) * np.eye(3)
        dt = np.linalg.solve(H, A.T @ b)
        t = t + dt
        if np.linalg.norm(dt) < 1e-5:
            break
    # p_K + t lies on the template: the kidney sits at -t in K relative to its estimate.
    drift_B = -(X_BK.rotation().matrix() @ t)
    return DriftEstimate(drift_B, rms, len(points_B), frames_used, n_frames)


def registered_shape_K(template, result) -> np.ndarray:
    """(M, 3) the registration template's points in K (m) with the shape modes the
    registration ``result`` fitted (its ``shape_coefficients``; none: the mean shape)."""
    return fitted_shape_K(template, result)


def kidney_in_view(
    shape_B: np.ndarray, X_BP: RigidTransform, geometry: ProbeGeometry, slab: float
) -> int:
    """How many points of the registered kidney surface ``shape_B`` (M, 3; m, B) lie in the
    image of a probe at X_BP: within ``slab`` (m) of the image plane and inside the fan.
    Where the registered kidney does not cross the view (past its registered pole, or the
    fan beside it), a segmented region cannot be compared with it."""
    p_P = (np.asarray(shape_B, float).reshape(-1, 3) - X_BP.translation()) @ (
        X_BP.rotation().matrix()
    )
    near = np.abs(p_P[:, 1]) <= slab
    return int(np.count_nonzero(geometry.in_fan(p_P[near]))) if near.any() else 0


@dataclasses.dataclass(frozen=True)
class TrackingLimits:
    """How a drift is judged for one registration: ``limit`` (m) on the judged drift, the
    ``axial_allowance`` (m) along ``axis_B`` (the registered long axis in B, unit; None:
    the whole drift is judged)."""

    limit: float
    axial_allowance: float = 0.0
    axis_B: np.ndarray | None = None


def tracking_limits(result, config) -> TrackingLimits:
    """The limits of the kidney tracking for a registration ``result`` (IcpResult; None:
    the plain ``tracking_max_drift``): limit = max(tracking_max_drift, tracking_rms_factor
    x RMS residual), the component along the registered long axis allowed
    ``tracking_axial_allowance`` beyond it."""
    if result is None:
        return TrackingLimits(float(config.tracking_max_drift))
    rms = float(result.rms_residual) if math.isfinite(result.rms_residual) else 0.0
    limit = max(float(config.tracking_max_drift), float(config.tracking_rms_factor) * rms)
    axis = np.asarray(result.X_BK.rotation().matrix()[:, 0], dtype=float)
    return TrackingLimits(limit, float(config.tracking_axial_allowance), axis)


def judged_drift(drift_B: np.ndarray, limits: TrackingLimits) -> float:
    """Magnitude (m) of the drift with its component along the registered long axis reduced
    by the axial allowance (a dead zone: within it the axial part counts as zero)."""
    d = np.asarray(drift_B, dtype=float).reshape(3)
    if limits.axis_B is None:
        return float(np.linalg.norm(d))
    along = float(d @ limits.axis_B)
    across = d - along * limits.axis_B
    excess = max(0.0, abs(along) - limits.axial_allowance)
    return float(math.hypot(float(np.linalg.norm(across)), excess))


@dataclasses.dataclass(frozen=True)
class TrackingState:
    """The monitor's memory: recent post-localization frames and the check history."""

    # ((time s, points (N, 3) in B, view: (normal y_P (3,), probe origin (3,) m)), ...)
    # within the window
    frames: tuple = ()
    last_index: int = -1  # index of the newest frame taken
    last_check: float = -math.inf
    exceed_count: int = 0  # successive checks above the drift limit
    drift_m: float = math.nan  # latest drift magnitude (m)
    history: tuple = ()  # ((time s, drift m), ...) of every check
    error: str = ""  # latched once the kidney is judged to have moved
    judged_m: float = math.nan  # latest judged drift (m, see judged_drift)
    limit_m: float = math.nan  # the limit the judged drift was compared with (m)
    registered_at: float = math.nan  # time of the registration being checked
    # The drift vectors of the checks ((time s, drift_B (3,) m), ...), and the reference
    # drift: the mean of the first ``tracking_reference_checks`` of them after the
    # registration (its own error seen through the view); ``change_m``: the latest drift's
    # distance from it (m).
    vectors: tuple = ()
    reference: tuple = ()
    change_m: float = math.nan
    # Stretches of motion (breath-holds, end-expiration windows) since the registration:
    # the reference belongs to the first; a later one may hold the kidney elsewhere by the
    # breath-hold's reproducibility (``tracking_hold_allowance``).
    segment: int = 0
    reference_segment: int = 0
    # The stretches the current run of over-the-limit change checks came from: in a later
    # stretch than the reference's, a change must show in two of them (two breaths) to count.
    exceed_segments: tuple = ()
    # The supervisor phase of the checks the reference is taken from (-1: none yet), and of
    # the fit running: a new phase (TRANSIT's slide, then PIVOT about one point) views
    # another part of the kidney, and takes its own reference.
    reference_phase: int = -1
    phase_start_check: int = 0  # index in ``vectors`` of the reference phase's first check
    pending_phase: int = -1
    # The view of each check in ``vectors`` ((image-plane normal y_P (3,), probe origin
    # (3,) m, stretch), ...; the normal None: not known): a check is compared only with
    # reference checks of the same view (``same_view``), and the view of the fit running.
    views: tuple = ()
    pending_view: object = None
    was_allowed: bool = True
    pending: object = None  # the drift fit running (an executor Ticket), or None
    # The slip check (slip_update): the probe's tangential force ((time s, f_x N, f_y N),
    # ...) of the current stretch (one phase, motion allowed, no gap), the stretch's start
    # (s), its phase, and the latest change (N) over tracking_slip_lag.
    forces: tuple = ()
    stretch_start: float = math.nan
    stretch_phase: int = -1
    slip_N: float = math.nan
    # The pivot-view check (localization.pivot_view): the boundary points (N, 3) in B of
    # each PIVOT frame taken while motion was allowed, the check running (an executor
    # Ticket, or None), when the latest was asked for (s), and its answer ((time s of the
    # newest frame it covered, error str): the ``pivot_view`` output).
    pivot_points: tuple = ()
    pivot_pending: object = None
    pivot_last_check: float = -math.inf
    pivot_view: tuple = (math.nan, "")

    # Drake clones abstract state with deepcopy on every update (the frames hold point
    # arrays); the state is immutable, so clones may share it.
    def __deepcopy__(self, memo):
        return self

    def __copy__(self):
        return self


def same_view(view_a, view_b, max_angle: float, max_offset: float) -> bool:
    """Whether two checks' views (image-plane normal y_P (3,), probe origin (3,) m, ...;
    a normal None: not known, taken as the same) image the same section of the kidney:
    the image planes within ``max_angle`` (rad; a plane and its flip are one plane) and the
    probe origins within ``max_offset`` (m)."""
    if view_a is None or view_b is None or view_a[0] is None or view_b[0] is None:
        return True
    n_a, n_b = np.asarray(view_a[0], float), np.asarray(view_b[0], float)
    cos = abs(float(n_a @ n_b)) / max(float(np.linalg.norm(n_a) * np.linalg.norm(n_b)), 1e-12)
    offset = float(np.linalg.norm(np.asarray(view_a[1], float) - np.asarray(view_b[1], float)))
    return math.acos(min(1.0, cos)) <= max_angle + 1e-12 and offset <= max_offset + 1e-12


def window_view(views) -> tuple:
    """The view of a drift fit over a window of frames, from the frames' views ((image-plane
    normal y_P (3,), probe origin (3,) m in B), ...): the mean normal (each flipped to the
    first's side; a plane and its flip are one plane), unit, and the mean origin."""
    normals = np.array([np.asarray(v[0], float) for v in views])
    normals = normals * np.where(normals @ normals[0] < 0, -1.0, 1.0)[:, None]
    n = normals.mean(axis=0)
    origin = np.mean([np.asarray(v[1], float) for v in views], axis=0)
    return n / max(float(np.linalg.norm(n)), 1e-12), origin


def tracking_update(
    state: TrackingState,
    t: float,
    drift: DriftEstimate | None,
    config,
    limits: TrackingLimits | None = None,
    phase: int = -1,
    view=None,
) -> TrackingState:
    """One check: records the drift at time t and latches an error after
    ``tracking_confirmations`` checks where the judged drift is above the limit
    (``limits``, by default the plain ``tracking_max_drift`` on the whole drift) or the
    drift has changed by more than ``tracking_change_limit`` from the reference: the mean
    of the first ``tracking_reference_checks`` drifts of the check's ``phase`` (the
    supervisor's) after the registration taken from the same ``view`` (image-plane normal
    y_P (3,), probe origin (3,) m, both in B; None: every view is the same): a shift in
    any direction, along the kidney's long axis too. The drift a registration's own error
    shows depends on the view (the long-axis part of a transverse section's fit swings by
    16 mm as TRANSIT turns the probe, a 10 mm registration error reads 14 mm at a 17 deg
    pivot tilt), so a check with no reference of its own view is not judged for a change,
    and does not break a run of over-the-limit checks either."""
    if state.error or drift is None:
        return dataclasses.replace(state, last_check=t)
    limits = limits or TrackingLimits(float(config.tracking_max_drift))
    d = drift.magnitude
    judged = judged_drift(drift.drift_B, limits)
    vectors = state.vectors + ((t, np.asarray(drift.drift_B, float)),)
    this_view = (None, None) if view is None else (view[0], view[1])
    views = state.views + ((*this_view, state.segment),)
    reference, change = state.reference, math.nan
    n_ref = int(getattr(config, "tracking_reference_checks", 0))
    reference_segment = state.reference_segment
    reference_phase, phase_start = state.reference_phase, state.phase_start_check
    if int(phase) != reference_phase:
        reference_phase, phase_start = int(phase), len(vectors) - 1
    max_angle = float(getattr(config, "tracking_reference_view_angle", math.pi))
    max_offset = float(getattr(config, "tracking_reference_view_offset", math.inf))
    # The phase's first n_ref checks of this view (none looked for with the rule off).
    matching = [
        k
        for k in range(phase_start, len(vectors) if n_ref > 0 else phase_start)
        if same_view(views[k], views[-1], max_angle, max_offset)
    ][:n_ref]
    judgeable = n_ref > 0 and len(matching) == n_ref and matching[-1] != len(vectors) - 1
    if n_ref > 0 and len(matching):
        reference = tuple(np.mean([vectors[k][1] for k in matching], axis=0))
        reference_segment = int(views[matching[-1]][2])
    if judgeable:
        change = float(np.linalg.norm(drift.drift_B - np.asarray(reference)))
    change_limit = float(config.tracking_change_limit)
    if state.segment != reference_segment:
        change_limit += float(config.tracking_hold_allowance)
    moved = math.isfinite(change) and change > change_limit
    # The phase has its first checks, none of this view: neither a change nor its absence.
    other_view = n_ref > 0 and not judgeable and len(vectors) - 1 - phase_start >= n_ref
    if other_view and judged <= limits.limit:
        count, exceed_segments = state.exceed_count, state.exceed_segments
    else:
        count = state.exceed_count + 1 if (judged > limits.limit or moved) else 0
        exceed_segments = state.exceed_segments + (state.segment,) if moved else ()
    error = ""
    # Within gated motion, a change counts once it showed in two breaths' stretches.
    shifted = moved and changed_across_stretches(exceed_segments, reference_segment)
    if count >= config.tracking_confirmations and shifted and judged <= limits.limit:
        v = (drift.drift_B - np.asarray(reference)) * 1000
        error = (
            f"the frames since localization put the kidney {change * 1000:.1f} mm from "
            f"where the first checks after it saw it ([{v[0]:.1f}, {v[1]:.1f}, {v[2]:.1f}] "
            f"mm in B; limit {change_limit * 1000:.1f} mm)"
        )
    elif count >= config.tracking_confirmations and (shifted or judged > limits.limit):
        v = drift.drift_B * 1000
        judged_how = ""
        if limits.axis_B is not None:
            along = float(drift.drift_B @ limits.axis_B)
            judged_how = (
                f"{along * 1000:.1f} mm of it along the kidney's long axis, where "
                f"{limits.axial_allowance * 1000:.0f} mm are allowed for the "
                f"registration's uncertainty: judged {judged * 1000:.1f} mm; "
            )
        error = (
            f"the frames since localization put the kidney {d * 1000:.1f} mm "
            f"from its registered pose ({judged_how}drift [{v[0]:.1f}, {v[1]:.1f}, "
            f"{v[2]:.1f}] mm in B; limit {limits.limit * 1000:.1f} mm)"
        )
    return dataclasses.replace(
        state,
        last_check=t,
        exceed_count=count,
        drift_m=d,
        history=state.history + ((t, d),),
        error=error,
        judged_m=judged,
        limit_m=limits.limit,
        vectors=vectors,
        reference=reference,
        change_m=change,
        reference_segment=reference_segment,
        exceed_segments=exceed_segments,
        reference_phase=reference_phase,
        phase_start_check=phase_start,
        views=views,
    )


def changed_across_stretches(exceed_segments, reference_segment: int) -> bool:
    """Whether a run of over-the-limit drift changes, seen in the stretches of motion
    ``exceed_segments`` (one per check: breath-holds or end-expiration windows, counted
    from the registration), is a shift rather than one breath's window: all in the
    reference's own stretch (continuous motion: the scan's view of one kidney), or in at
    least two different later stretches. A patient who moved stays moved across breaths; a
    window caught at another point of the breath, or a short window's fit over a few
    frames, does not repeat in the next one."""
    segs = set(int(k) for k in exceed_segments)
    if not segs:
        return False
    if segs == {int(reference_segment)}:
        return True
    return len(segs - {int(reference_segment)}) >= 2


def tangential_force_change(forces, lag: float) -> float:
    """Change (N) of the probe's tangential force from the newest sample of ``forces``
    ((time s, f_x N, f_y N), ..., oldest first) back to the newest one at least ``lag`` s
    older; NaN when no sample is that old."""
    if not forces:
        return math.nan
    t, fx, fy = forces[-1]
    for t0, fx0, fy0 in reversed(forces[:-1]):
        if t - t0 >= lag - 1e-9:
            return float(math.hypot(fx - fx0, fy - fy0))
    return math.nan


def slip_update(
    state: TrackingState,
    t: float,
    force_P,
    phase: int,
    config,
    max_gap: float,
) -> TrackingState:
    """One sample of the slip check: ``force_P`` is the probe's force f (3,) on it by the
    environment in P (N; ``probe_force``'s last three), sampled at time t during a checked
    ``phase`` while the scan may move. A stretch is one phase without a gap over
    ``max_gap`` s between samples; once it has lasted ``tracking_slip_settle`` s, a
    tangential (x_P, y_P) change above ``tracking_slip_force`` N within
    ``tracking_slip_lag`` s latches the error: the patient slid under the probe."""
    if state.error or float(config.tracking_slip_force) <= 0.0:
        return state
    f = np.asarray(force_P, dtype=float).reshape(3)
    if not np.all(np.isfinite(f)):
        return state
    lag = float(config.tracking_slip_lag)
    forces, start = state.forces, state.stretch_start
    if int(phase) != state.stretch_phase or not forces or t - forces[-1][0] > max_gap:
        forces, start = (), t
    forces = tuple(x for x in forces if t - x[0] <= lag + max_gap) + ((t, f[0], f[1]),)
    change = tangential_force_change(forces, lag)
    error = ""
    settled = t - start >= float(config.tracking_slip_settle) - 1e-9
    if settled and math.isfinite(change) and change > float(config.tracking_slip_force):
        error = (
            f"the patient slid under the probe: its tangential force changed by "
            f"{change:.1f} N within {lag:.2f} s (limit {config.tracking_slip_force:.1f} N)"
        )
    return dataclasses.replace(
        state,
        forces=forces,
        stretch_start=start,
        stretch_phase=int(phase),
        slip_N=change,
        error=error,
    )


# kd-trees of registered template shapes, by content (the newest few): the monitor's drift
# fits, in this process or a worker's, share one tree per registration.
_SHAPE_TREES: dict = {}


def registered_tree(shape_K: np.ndarray) -> cKDTree:
    """The kd-tree of a registered template shape (M, 3), built once per shape."""
    shape_K = np.ascontiguousarray(shape_K, dtype=float)
    key = (shape_K.shape, hash(shape_K.tobytes()))
    hit = _SHAPE_TREES.get(key)
    if hit is not None and np.array_equal(hit[0], shape_K):
        return hit[1]
    while len(_SHAPE_TREES) >= 4:
        _SHAPE_TREES.pop(next(iter(_SHAPE_TREES)))
    tree = cKDTree(shape_K)
    _SHAPE_TREES[key] = (shape_K.copy(), tree)
    return tree


def drift_fit(
    points_B, X_BK, shape_K, normals_K, frame_ids, gate_factor: float, gate_floor: float
) -> DriftEstimate:
    """:func:`estimate_drift` with the registered shape's kd-tree (:func:`registered_tree`):
    the tracking check as an executor job."""
    return estimate_drift(
        points_B,
        X_BK,
        shape_K,
        normals_K,
        tree=registered_tree(shape_K),
        frame_ids=frame_ids,
        frame_gate_factor=gate_factor,
        frame_gate_floor=gate_floor,
    )


# The pivot-view check's largest set of pivot boundary points, taken evenly from all of
# them: its percentile is the whole set's to a fraction of a millimetre, at a bounded cost
# per check.
PIVOT_VIEW_MAX_POINTS = 20000


class KidneyTrackingMonitor(LeafSystem):
    """Checks, during the phases after localization, that the kidney is still where the
    registration put it (see the module docstring).

    Inputs: ``boundary_pixels`` (abstract BoundaryPixels from the Segmenter: pixels, frame
    time, X_BP, index); ``localization`` (abstract LocalizationOutcome from IcpLocalizer);
    ``phase`` (1-vector, the supervisor's phase); ``motion_allowed`` (1-vector, optional:
    frames acquired while it is 0, outside a breath-hold, are not used); ``probe_force``
    (6-vector [tau; f], N m and N, on the probe by the environment in P, optional: the
    slip check, :func:`slip_update`, needs it; ``slip_check`` False turns it off).
    Outputs: ``tracking_error`` (abstract str: "" while consistent); ``kidney_drift``
    (1-vector, m: the latest drift magnitude, NaN before the first check).
    Frames are collected at the imaging frame rate; a check is asked for every
    ``tracking_period`` s over the frames of the last ``tracking_window`` s and runs on
    ``executor``'s ``fits`` lane (``drake_rus.executor``; default: inline, ready at once);
    its result is judged when it is ready, stamped with the time it was asked for.

    With ``pivot_view`` ((percentile, excess, respiration mode): the scan's
    ``verdict.pivot_residual_percentile`` and ``pivot_residual_excess`` and
    ``respiration.mode``), the monitor also keeps the boundary points of every PIVOT frame
    and every ``tracking_period`` s during PIVOT asks the same lane whether the pivot's
    view contradicts the registration (``pivot_view.pivot_view_error``, the verdict's
    rule) against the explored cloud (input ``partial_cloud``, abstract PointCloud in B);
    output ``pivot_view``: (time s of the newest frame the latest answer covered, NaN
    none; why the view contradicts the fit, "" = it does not).
    """

    def __init__(
        self,
        template,
        config,
        imaging_config,
        check_phases,
        executor=None,
        slip_check=True,
        pivot_view=None,
        pivot_phase=None,
    ):
        super().__init__()
        self._pivot_view = None if pivot_view is None else tuple(pivot_view)
        self._pivot_phase = None if pivot_phase is None else int(pivot_phase)
        # False: the patient breathes while the scan moves (gated free breathing), so the
        # skin slides under the probe at every end-expiration window's edge.
        self._slip_check = bool(slip_check)
        self._template = template
        self._executor = executor if executor is not None else InlineExecutor()
        self._cfg = config
        self._geometry = ProbeGeometry.from_config(imaging_config)
        self._phases = {int(p) for p in check_phases}
        self._shape_key = None
        self._shape = None
        self._shape_B = None
        self._boundary = self.DeclareAbstractInputPort(
            "boundary_pixels", AbstractValue.Make(BoundaryPixels(np.zeros((0, 2))))
        )
        self._outcome = self.DeclareAbstractInputPort(
            "localization", AbstractValue.Make(LocalizationOutcome())
        )
        self._phase = self.DeclareVectorInputPort("phase", 1)
        self._motion = self.DeclareVectorInputPort("motion_allowed", 1)
        self._force = self.DeclareVectorInputPort("probe_force", 6)
        self._cloud = self.DeclareAbstractInputPort(
            "partial_cloud", AbstractValue.Make(PointCloud())
        )
        self._max_gap = 2.5 / imaging_config.frame_rate_hz  # s: a missed sample or two
        self._state = self.DeclareAbstractState(AbstractValue.Make(TrackingState()))
        period = 1.0 / imaging_config.frame_rate_hz
        self.DeclarePeriodicUnrestrictedUpdateEvent(period, 0.5 * period, self._update)
        ticket = {self.abstract_state_ticket(self._state)}
        self.DeclareAbstractOutputPort(
            "tracking_error",
            lambda: AbstractValue.Make(""),
            lambda c, o: o.set_value(c.get_abstract_state(self._state).get_value().error),
            prerequisites_of_calc=ticket,
        )
        self.DeclareVectorOutputPort(
            "kidney_drift",
            1,
            lambda c, o: o.SetAtIndex(0, c.get_abstract_state(self._state).get_value().drift_m),
            prerequisites_of_calc=ticket,
        )
        self.DeclareAbstractOutputPort(
            "pivot_view",
            lambda: AbstractValue.Make((math.nan, "")),
            lambda c, o: o.set_value(c.get_abstract_state(self._state).get_value().pivot_view),
            prerequisites_of_calc=ticket,
        )

    def state(self, context) -> TrackingState:
        return context.get_abstract_state(self._state).get_value()

    def _registered_shape(self, outcome):
        """(shape_K, shape_B) of the registered template, cached per estimate."""
        key = (outcome.time, id(outcome.result))
        if key != self._shape_key:
            shape = registered_shape_K(self._template, outcome.result)
            self._shape_key, self._shape = key, shape
            self._shape_B = outcome.result.X_BK.multiply(shape.T).T
        return self._shape, self._shape_B

    def _update(self, context, state):
        cfg = self._cfg
        if not cfg.tracking_check:
            return EventStatus.DidNothing()
        s = self.state(context)
        outcome = self._outcome.Eval(context)
        # The checks belong to one registration: whatever the phase, a dropped estimate (a
        # re-localization under way) or a new one clears them (a latched error too, so the
        # new registration does not start with the old one's error); the history stays.
        registered_at = outcome.time if outcome.result is not None else math.nan
        same = registered_at == s.registered_at or (
            math.isnan(registered_at) and math.isnan(s.registered_at)
        )
        if not same:
            s = TrackingState(history=s.history, registered_at=registered_at)
            state.get_mutable_abstract_state(self._state).set_value(s)
        if outcome.result is None or s.error:
            return EventStatus.Succeeded() if not same else EventStatus.DidNothing()
        phase = int(round(self._phase.Eval(context)[0]))
        if phase not in self._phases:
            return EventStatus.Succeeded() if not same else EventStatus.DidNothing()
        t = context.get_time()
        allowed = (not self._motion.HasValue(context)) or self._motion.Eval(context)[0] > 0.5
        frames = tuple(f for f in s.frames if t - f[0] <= cfg.tracking_window)
        boundary = self._boundary.Eval(context)
        new_index = s.last_index
        shape, shape_B = self._registered_shape(outcome)
        if (
            allowed
            and boundary.frame_index > s.last_index
            and len(boundary.pixels)
            and np.all(np.isfinite(boundary.X_BP.GetAsMatrix4()))
        ):
            new_index = boundary.frame_index
            if self._pivot_view is not None and phase == self._pivot_phase:
                points = backproject_pixels(self._geometry, boundary.pixels, boundary.X_BP)
                s = dataclasses.replace(s, pivot_points=s.pivot_points + (points,))
            if (
                kidney_in_view(shape_B, boundary.X_BP, self._geometry, cfg.tracking_view_slab)
                >= cfg.tracking_min_view_points
            ):
                points = backproject_pixels(self._geometry, boundary.pixels, boundary.X_BP)
                X_BP = boundary.X_BP
                view = (X_BP.rotation().matrix()[:, 1].copy(), X_BP.translation().copy())
                frames = frames + ((boundary.time, points, view),)
        if self._slip_check and allowed and self._force.HasValue(context):
            s = slip_update(s, t, self._force.Eval(context)[3:6], phase, cfg, max_gap=self._max_gap)
        segment = s.segment + (1 if allowed and not s.was_allowed else 0)
        if segment != s.segment:
            frames = ()  # a new breath-hold or window: no frames of the last one
        s = dataclasses.replace(
            s, frames=frames, last_index=new_index, segment=segment, was_allowed=allowed
        )
        s = self._take(s, t, outcome)
        s = self._pivot_check(context, s, t, phase, outcome, shape_B)
        if s.pending is None and t - s.last_check >= cfg.tracking_period - 1e-9:
            if len(frames) >= cfg.tracking_min_frames:
                points = np.concatenate([f[1] for f in frames])
                ids = np.repeat(np.arange(len(frames)), [len(f[1]) for f in frames])
                if len(points) > cfg.tracking_max_points:
                    pick = np.linspace(0, len(points) - 1, cfg.tracking_max_points).astype(int)
                    points, ids = points[pick], ids[pick]
                ticket = self._executor.submit(
                    "fits",
                    drift_fit,
                    points,
                    outcome.result.X_BK,
                    shape,
                    self._template.normals,
                    ids,
                    cfg.tracking_frame_gate_factor,
                    cfg.tracking_frame_gate_floor,
                    t=t,
                    kind="tracking_fit",
                )
                view = window_view([f[2] for f in frames])
                s = dataclasses.replace(s, pending=ticket, pending_phase=phase, pending_view=view)
                s = self._take(s, t, outcome)
            else:
                s = tracking_update(s, t, None, cfg, tracking_limits(outcome.result, cfg))
        state.get_mutable_abstract_state(self._state).set_value(s)
        return EventStatus.Succeeded()

    def _pivot_check(self, context, s: TrackingState, t, phase, outcome, shape_B):
        """``s`` with the pivot-view check's answer taken if it is ready, and a new one asked
        for every ``tracking_period`` s during PIVOT (on the frames so far)."""
        if self._pivot_view is None:
            return s
        if s.pivot_pending is not None:
            done = self._executor.poll(s.pivot_pending, t)
            if done is None:
                return s
            s = dataclasses.replace(
                s, pivot_pending=None, pivot_view=(float(done.t_request), str(done.value))
            )
        if (
            phase != self._pivot_phase
            or not s.pivot_points
            or t - s.pivot_last_check < self._cfg.tracking_period - 1e-9
            or not self._cloud.HasValue(context)
        ):
            return s
        percentile, excess, mode = self._pivot_view
        result = outcome.result
        has_shape = getattr(result, "shape_coefficients", None) is not None
        max_rms = max_rms_residual(self._cfg, self._template, has_shape)
        bound = pivot_residual_bound(excess, max_rms, mode, self._cfg.tracking_hold_allowance)
        pivot_B = np.concatenate(s.pivot_points)
        if len(pivot_B) > PIVOT_VIEW_MAX_POINTS:  # evenly over the sweep's frames
            pivot_B = pivot_B[np.linspace(0, len(pivot_B) - 1, PIVOT_VIEW_MAX_POINTS).astype(int)]
        ticket = self._executor.submit(
            "fits",
            pivot_view_error,
            shape_B,
            np.asarray(self._cloud.Eval(context).points),
            pivot_B,
            bound,
            percentile,
            t=t,
            kind="pivot_view",
        )
        s = dataclasses.replace(s, pivot_pending=ticket, pivot_last_check=t)
        return self._pivot_check(context, s, t, -1, outcome, shape_B)

    def _take(self, s: TrackingState, t: float, outcome) -> TrackingState:
        """``s`` with the running drift fit judged, if it is ready (as of the time it was
        asked for)."""
        if s.pending is None:
            return s
        done = self._executor.poll(s.pending, t)
        if done is None:
            return s
        s = dataclasses.replace(s, pending=None)
        return tracking_update(
            s,
            done.t_request,
            done.value,
            self._cfg,
            tracking_limits(outcome.result, self._cfg),
            phase=s.pending_phase,
            view=s.pending_view,
        )


class RegisteredKidneySurface(LeafSystem):
    """The registered kidney's surface in B, for the Segmenter's template prior.

    Input ``localization`` (abstract LocalizationOutcome from IcpLocalizer). Output
    ``kidney_surface`` (abstract KidneySurface): the template's points in K with the fitted
    shape modes (:func:`registered_shape_K`) mapped by the estimate's X_BK (m, in B), with
    the estimate's time (s); empty while there is no estimate. Computed once per estimate."""

    def __init__(self, template):
        super().__init__()
        self._template = template
        self._outcome = self.DeclareAbstractInputPort(
            "localization", AbstractValue.Make(LocalizationOutcome())
        )
        self._cache = [None, KidneySurface()]  # (estimate key, surface)
        self.DeclareAbstractOutputPort(
            "kidney_surface", lambda: AbstractValue.Make(KidneySurface()), self._calc
        )

    def _calc(self, context, output):
        outcome = self._outcome.Eval(context)
        if outcome.result is None:
            output.set_value(KidneySurface())
            return
        key = (outcome.time, id(outcome.result))
        if key != self._cache[0]:
            shape = registered_shape_K(self._template, outcome.result)
            self._cache[:] = [
                key,
                KidneySurface(outcome.result.X_BK.multiply(shape.T).T, outcome.time),
            ]
        output.set_value(self._cache[1])
