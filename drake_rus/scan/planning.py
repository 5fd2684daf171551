"""Where a scan starts: the exploration region of interest (E-ROI), the start pose, and the
start planner that chooses the acoustic window and the depth preset like a sonographer.

The seed places the probe by hand where the kidney is visible (II-E) and, in simulation,
defines the E-ROI by projecting the kidney's bounding box onto the body along the base z-axis
(III-C, Fig. 6b); exploration runs along the base y-axis. We do the same from the true kidney
mesh: this stands in for the operator's placement and is the only use of ground truth before
the scan's metrics.
"""

import dataclasses

import numpy as np
from pydrake.common.eigen_geometry import AngleAxis
from pydrake.geometry import Rgba, Sphere
from pydrake.math import RigidTransform, RotationMatrix

from drake_rus.anatomy.labels import KIDNEY_LABELS, Label
from drake_rus.anatomy.tissue_colors import label_image, labels_present, tissue_handles
from drake_rus.io_utils import save_figure

# Probe pointing down (z_P = -z_B) with its array across the body (x_P = +x_B): a transverse
# image, the seed's exploration view.
R_B_TRANSVERSE = RotationMatrix(np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]))


@dataclasses.dataclass
class ExplorationRoi:
    """The kidney's x-y bounding box in the base frame (m) and its centroid."""

    x_min: float
    x_max: float
    y_min: float
    y_max: float
    centroid_B: np.ndarray

    @property
    def length_y(self) -> float:
        return self.y_max - self.y_min


def exploration_roi(patient, X_BPt: RigidTransform) -> ExplorationRoi:
    """E-ROI of ``patient`` lying at ``X_BPt`` (III-C)."""
    v = patient.kidney_mesh.vertices
    p_B = v @ X_BPt.rotation().matrix().T + X_BPt.translation()
    lo, hi = p_B.min(axis=0), p_B.max(axis=0)
    return ExplorationRoi(lo[0], hi[0], lo[1], hi[1], patient.X_BK(X_BPt).translation().copy())


def skin_height_B(patient, X_BPt: RigidTransform, x: float, y: float) -> float:
    """Height z (m, base frame) of the body surface above the point (x, y)."""
    mesh = patient.skin_mesh
    X_PtB = X_BPt.inverse()
    origin_B = np.array([x, y, 10.0])
    origin = X_PtB.multiply(origin_B)
    direction = X_PtB.rotation().multiply(np.array([0.0, 0.0, -1.0]))
    hits, _, _ = mesh.ray.intersects_location([origin], [direction])
    if len(hits) == 0:
        raise ValueError(
            f"no body surface below (x, y) = ({x:.3f}, {y:.3f}) m in the base "
            "frame: is the patient placed under the robot (patient.X_BPt)?"
        )
    hits_B = X_BPt.multiply(np.asarray(hits).T).T
    return float(hits_B[:, 2].max())


def exploration_start_xy(
    roi: ExplorationRoi, scan_direction: str = "-y", start_fraction: float = 0.0
) -> tuple[float, float]:
    """(x, y) of the exploration start: over the kidney centroid's x, at the E-ROI's end the
    scan leaves from, ``start_fraction`` of the E-ROI's length inside it."""
    if scan_direction == "-y":
        y = roi.y_max - start_fraction * roi.length_y
    elif scan_direction == "+y":
        y = roi.y_min + start_fraction * roi.length_y
    else:
        raise ValueError(f"scan_direction: expected '+y' or '-y', got {scan_direction!r}")
    return float(roi.centroid_B[0]), float(y)


def exploration_start(
    patient,
    X_BPt: RigidTransform,
    *,
    scan_direction: str = "-y",
    start_fraction: float = 0.0,
    hover: float = 0.015,
) -> RigidTransform:
    """Tip pose (transverse view, pointing down) ``hover`` m above the skin at the start.

    The start lies over the kidney centroid's x, at the E-ROI's end the scan leaves from
    (its superior end for a "-y" scan when the head is at +y), moved into the E-ROI by
    ``start_fraction`` of its length (0: at the pole; randomised starts use more).
    """
    x, y = exploration_start_xy(exploration_roi(patient, X_BPt), scan_direction, start_fraction)
    z = skin_height_B(patient, X_BPt, x, y) + hover
    return RigidTransform(R_B_TRANSVERSE, [x, y, z])


# ------------------------------------------------------------------------ the start planner
# Tissue that blocks the beam: bone reflects almost all energy and shadows what lies behind,
# gas reflects nearly all of it (docs/facts/anatomy_and_ultrasound.md, "Tissue acoustics").
BLOCKING_LABELS = (int(Label.BONE), int(Label.GAS))
# Fan rays checked across the image, and positions along the exploration line.
_FAN_RAYS = 9
_RAY_STEP = 0.002


class StartPlanError(ValueError):
    """No acoustic window: the message says why (depth, blocked path, reach)."""


@dataclasses.dataclass
class WindowCandidate:
    """One beam direction tried by the planner (B frame, SI units)."""

    tilt_deg: float  # signed tilt from vertical about the body's long axis
    approach_B: np.ndarray  # beam direction a (into the body)
    skin_points_B: np.ndarray  # (3, 3) skin entry points along the exploration line
    needed_depth: float  # image depth that holds the whole kidney (m, + margin)
    blocked_fraction: float  # of the fan's rays reaching the kidney, crossed bone/gas
    central_blocked: bool  # the central ray crosses bone or gas somewhere
    blockers_B: np.ndarray  # (N, 3) first bone/gas sample of each blocked ray
    preset: float | None  # shallowest preset holding the kidney (None: none does)
    reachable: bool | None = None  # None: not checked
    reason: str = ""  # why it was rejected ("" when feasible)
    # Where exploration starts: this fraction of the kidney's length inside its end.
    start_fraction: float = 0.1
    sweep_length: float = 0.0  # the exploration sweep checked (m along the body)
    clear_length: float = 0.0  # how far into it every view is clear of shadows (m)
    sweep_shadowed: float = 0.0  # fraction of the sweep's views shadowed by bone or gas
    # The clear length that counts as a covered sweep (m): the sweep, or
    # start.min_sweep_fraction of the kidney if shorter (0: the whole sweep).
    covered_length: float = 0.0
    # Why a usable window is worse ("" when it is not): a shadow within the placement error
    # of the start, or across the sweep before ``min_clear_sweep``.
    warning: str = ""

    @property
    def feasible(self) -> bool:
        return not self.reason


@dataclasses.dataclass
class StartPlan:
    """The planner's choice: the start pose (after the placement error), the planned pose
    (before it), the depth preset, the chosen window and every window it tried."""

    X_start: RigidTransform
    X_planned: RigidTransform
    depth_preset: float
    window: WindowCandidate
    candidates: list
    placement_offset_B: np.ndarray  # (3,) position error applied (m)
    placement_angle: float  # tilt error applied (rad)
    pivot_depth_needed: float  # depth the vertical pivot (eq. 20) needs (m)
    # Labels on the chosen window's image plane (rows along the beam from the planned skin
    # point, columns across it), for the picture: (labels (H, W) uint8, u (W,) m, v (H,) m).
    plane: tuple = ()

    def summary(self) -> dict:
        """JSON-ready description (mm and degrees) for the scan's summary."""
        w = self.window
        return {
            "planner": "window",
            "tilt_deg": w.tilt_deg,
            "approach_B": [round(float(v), 4) for v in w.approach_B],
            "skin_point_mm": [round(float(v) * 1000, 1) for v in w.skin_points_B[0]],
            "depth_preset_m": self.depth_preset,
            "needed_depth_mm": round(w.needed_depth * 1000, 1),
            "pivot_depth_needed_mm": round(self.pivot_depth_needed * 1000, 1),
            "blocked_fraction": round(w.blocked_fraction, 3),
            "start_fraction": round(w.start_fraction, 3),
            "sweep_checked_mm": round(w.sweep_length * 1000, 1),
            "sweep_clear_mm": round(w.clear_length * 1000, 1),
            "sweep_shadowed_fraction": round(w.sweep_shadowed, 3),
            "warning": w.warning,
            "placement_error_mm": round(float(np.linalg.norm(self.placement_offset_B)) * 1000, 2),
            "placement_error_deg": round(float(np.degrees(self.placement_angle)), 2),
            "windows_tried": len(self.candidates),
            "windows_feasible": sum(c.feasible for c in self.candidates),
        }


def _rotation_about(axis, angle: float) -> np.ndarray:
    return RotationMatrix(AngleAxis(angle, np.asarray(axis, float) / np.linalg.norm(axis))).matrix()


def probe_rotation(approach_B, superior_B) -> RotationMatrix:
    """R_BP of a transverse view along ``approach_B``: z_P = a, x_P across the body (the base
    x-axis made orthogonal to a, or superior x a when a lies along x), y_P = z_P x x_P."""
    a = np.asarray(approach_B, float) / np.linalg.norm(approach_B)
    x = np.array([1.0, 0.0, 0.0]) - a[0] * a
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(np.asarray(superior_B, float), a)
    x /= np.linalg.norm(x)
    return RotationMatrix(np.column_stack([x, np.cross(a, x), a]))


def _skin_entry(skin_mesh, X_BPt: RigidTransform, target_B, approach_B) -> np.ndarray | None:
    """Where the line through ``target_B`` along ``approach_B`` enters the body: the skin
    hit farthest back along -a from the target (None when the line misses the skin)."""
    X_PtB = X_BPt.inverse()
    origin = X_PtB.multiply(np.asarray(target_B, float))
    direction = X_PtB.rotation().multiply(-np.asarray(approach_B, float))
    hits, _, _ = skin_mesh.ray.intersects_location([origin], [direction])
    if len(hits) == 0:
        return None
    distance = (np.asarray(hits) - origin) @ direction
    return X_BPt.multiply(np.asarray(hits)[int(np.argmax(distance))])


def _labels_along(volume, X_BV: RigidTransform, start_B, direction_B, length: float):
    """Labels (uint8) sampled every 2 mm from ``start_B`` along ``direction_B`` for
    ``length`` m (outside the volume: OUTSIDE), and the sample positions in B."""
    s = np.arange(0.0, length, _RAY_STEP)
    p_B = np.asarray(start_B, float) + np.outer(s, direction_B)
    p_V = X_BV.inverse().multiply(p_B.T).T / volume.voxel_size
    ijk = np.rint(p_V).astype(int)
    inside = np.all((ijk >= 0) & (ijk < np.array(volume.shape)), axis=1)
    labels = np.zeros(len(s), np.uint8)
    labels[inside] = volume.labels[ijk[inside, 0], ijk[inside, 1], ijk[inside, 2]]
    return labels, p_B


def _ray_blocked(labels) -> tuple[bool, bool, int]:
    """(reaches the kidney, crossed bone/gas before it, index of the first blocker)."""
    kidney = np.isin(labels, [int(v) for v in KIDNEY_LABELS])
    blocking = np.isin(labels, BLOCKING_LABELS)
    first_kidney = int(np.argmax(kidney)) if kidney.any() else len(labels)
    before = blocking[:first_kidney]
    if before.any():
        return kidney.any(), True, int(np.argmax(before))
    return kidney.any(), False, -1


@dataclasses.dataclass
class ViewCheck:
    """The fan of one transverse view along the exploration line (B frame, SI units)."""

    along: float  # position along the body's superior axis (m, kidney-centred)
    skin_B: np.ndarray  # skin entry point of the beam (3,)
    needed_depth: float  # depth of the kidney's far side in this view (m; 0: none)
    rays_to_kidney: int  # fan rays that reach the kidney
    blocked_rays: int  # of those, the ones crossing bone or gas first
    central_blocked: bool  # the central ray crosses bone or gas before the kidney
    blockers_B: np.ndarray  # (N, 3) first bone/gas sample of each blocked ray

    def shadowed(self, max_blocked_fraction: float) -> bool:
        """The kidney cannot be seen in this view: no ray reaches it, the central ray is
        blocked, or more than ``max_blocked_fraction`` of the rays to it are."""
        return (
            self.skin_B is None
            or self.rays_to_kidney == 0
            or self.central_blocked
            or self.blocked_rays / self.rays_to_kidney > max_blocked_fraction
        )


def fan_rays(
    skin_B, approach_B, across_B, probe_radius: float, field_of_view_deg: float, n_rays: int = 0
):
    """(origins, directions), each (n_rays, 3): the rays of a curvilinear probe whose face
    centre touches ``skin_B``, beam along ``approach_B``, array along ``across_B``: rays
    leave the face arc (radius ``probe_radius`` about the apex behind the face centre) at
    angles spread over the field of view, so they cross the skin over the face's width."""
    n = int(n_rays or _FAN_RAYS)
    a = np.asarray(approach_B, float)
    o = np.asarray(across_B, float)
    phi = np.radians(field_of_view_deg) / 2 * np.linspace(-1.0, 1.0, n)
    d = np.cos(phi)[:, None] * a + np.sin(phi)[:, None] * o
    apex = np.asarray(skin_B, float) - probe_radius * a
    return apex + probe_radius * d, d


def check_view(
    volume,
    X_BV: RigidTransform,
    skin_B,
    approach_B,
    across_B,
    imaging,
    kidney_slab_B: np.ndarray,
    along: float,
) -> ViewCheck:
    """Fan clearance and kidney depth of the transverse view entering at ``skin_B`` (None:
    the beam misses the body): every fan ray (:func:`fan_rays`) sampled every 2 mm to the
    deepest preset through the label volume; ``kidney_slab_B`` the kidney points near this
    view (their depth along the beam gives ``needed_depth``)."""
    if skin_B is None:
        return ViewCheck(along, None, np.inf, 0, 0, False, np.zeros((0, 3)))
    origins, dirs = fan_rays(
        skin_B, approach_B, across_B, imaging.probe_radius, imaging.field_of_view_deg
    )
    length = max(imaging.depth_presets)
    s = np.arange(0.0, length, _RAY_STEP)
    p_B = origins[:, None, :] + s[None, :, None] * dirs[:, None, :]  # (K, S, 3)
    p_V = X_BV.inverse().multiply(p_B.reshape(-1, 3).T).T / volume.voxel_size
    ijk = np.rint(p_V).astype(int)
    inside = np.all((ijk >= 0) & (ijk < np.array(volume.shape)), axis=1)
    labels = np.zeros(len(ijk), np.uint8)
    labels[inside] = volume.labels[ijk[inside, 0], ijk[inside, 1], ijk[inside, 2]]
    labels = labels.reshape(len(dirs), len(s))
    kidney = np.isin(labels, [int(v) for v in KIDNEY_LABELS])
    blocking = np.isin(labels, BLOCKING_LABELS)
    reaches = kidney.any(axis=1)
    first_kidney = np.where(reaches, np.argmax(kidney, axis=1), len(s))
    before = blocking & (np.arange(len(s))[None, :] < first_kidney[:, None])
    crossed = before.any(axis=1)
    blocked = reaches & crossed
    blockers = (
        p_B[blocked, np.argmax(before[blocked], axis=1)] if blocked.any() else np.zeros((0, 3))
    )
    mid = len(dirs) // 2
    needed = float(((kidney_slab_B - skin_B) @ approach_B).max()) if len(kidney_slab_B) else 0.0
    return ViewCheck(
        along,
        np.asarray(skin_B, float),
        needed,
        int(reaches.sum()),
        int(blocked.sum()),
        bool(crossed[mid]),
        blockers,
    )


def _window_from_views(
    tilt: float,
    a,
    views: list,
    start: int,
    sweep_end: int,
    start_zone: list,
    config,
    imaging,
    start_fraction: float,
    step: float,
) -> WindowCandidate:
    """One candidate: the beam tilt ``tilt`` with exploration starting at view ``start`` and
    sweeping to view ``sweep_end`` (indices into ``views`` along the scan direction);
    ``start_zone``: the views within the placement error of the start."""
    sweep = views[start : sweep_end + 1]
    mid = sweep[len(sweep) // 2]
    key = [views[start], mid, sweep[-1]]
    checked = start_zone + sweep
    needed = max(v.needed_depth for v in checked) + config.depth_margin
    at_start = views[start]
    clear = 0
    for v in sweep[1:]:
        if v.shadowed(config.max_blocked_fraction):
            break
        clear += 1
    fitting = [p for p in sorted(imaging.depth_presets) if p >= needed]
    blockers = [v.blockers_B for v in checked if len(v.blockers_B)]
    cand = WindowCandidate(
        float(np.degrees(tilt)),
        a,
        np.array([v.skin_B if v.skin_B is not None else np.full(3, np.nan) for v in key]),
        needed,
        at_start.blocked_rays / at_start.rays_to_kidney if at_start.rays_to_kidney else 1.0,
        at_start.central_blocked,
        np.concatenate(blockers) if blockers else np.zeros((0, 3)),
        fitting[0] if fitting else None,
        start_fraction=start_fraction,
        sweep_length=step * (len(sweep) - 1),
        clear_length=step * clear,
        sweep_shadowed=sum(v.shadowed(config.max_blocked_fraction) for v in sweep[1:])
        / max(len(sweep) - 1, 1),
    )
    if any(v.skin_B is None for v in key):
        cand.reason = "beam misses the body"
    elif not at_start.rays_to_kidney:
        cand.reason = "no ray of the fan reaches the kidney"
    elif not np.isfinite(needed) or cand.preset is None:
        cand.reason = (
            f"the kidney's far side lies {needed * 1000:.0f} mm deep (with margin), "
            f"beyond the deepest preset {max(imaging.depth_presets) * 1000:.0f} mm"
        )
    elif at_start.central_blocked:
        cand.reason = "the central ray crosses bone or gas at the start"
    elif cand.blocked_fraction > config.max_blocked_fraction:
        cand.reason = (
            f"{cand.blocked_fraction:.0%} of the fan's rays to the kidney cross bone "
            f"or gas at the start (max {config.max_blocked_fraction:.0%})"
        )
    # Usable but worse: a shadow within the placement error of the start, or crossing the
    # sweep early (ranked after the windows without, see window_rank).
    if any(v.shadowed(config.max_blocked_fraction) for v in start_zone):
        cand.warning = (
            f"bone or gas shadows the kidney within the placement error "
            f"({config.placement_error * 1000:.0f} mm) of the start"
        )
    elif cand.clear_length < min(config.min_clear_sweep, cand.sweep_length) - 1e-9:
        cand.warning = (
            f"bone or gas shadows the kidney {cand.clear_length * 1000:.0f} mm into "
            f"the sweep (want {config.min_clear_sweep * 1000:.0f} mm clear)"
        )
    return cand


def evaluate_windows(
    patient,
    X_BPt: RigidTransform,
    imaging,
    config,
    tilt: float,
    superior_B,
    kidney_B,
    X_BV,
    start_fraction: float = 0.1,
    scan_direction: str = "-y",
    exploration_ratio: float | None = None,
) -> list:
    """The candidates of the beam tilted by ``tilt`` (rad) from vertical about the body's
    long axis, one per exploration start tried (``start_fraction`` of the kidney's length
    inside the end the scan leaves from, then later starts in ``config.start_shift_step``
    steps up to ``config.max_start_shift``): transverse views every
    ``config.sweep_check_step`` along the exploration line give the kidney's depth and the
    fan's clearance at the start (within the placement error of it) and how far the sweep of
    ``exploration_ratio`` x the kidney's length (None: to 10% inside the far end) stays
    clear of bone and gas shadows."""
    a = _rotation_about(superior_B, tilt) @ np.array([0.0, 0.0, -1.0])
    R_BP = probe_rotation(a, superior_B).matrix()
    o = R_BP[:, 0]
    c = kidney_B.mean(axis=0)
    along = (kidney_B - c) @ superior_B
    lo, hi = float(along.min()), float(along.max())
    length = hi - lo
    sign = -1.0 if scan_direction == "-y" else 1.0  # along the superior axis
    end_near = hi if sign < 0 else lo  # the end the scan leaves from
    step = float(config.sweep_check_step)
    zone = float(config.placement_error)
    # View positions from the placement error behind the first start to 5% inside the far
    # end, every ``step``, in scan order.
    first = end_near + sign * start_fraction * length - sign * zone
    far = end_near + sign * 0.95 * length
    n = int(np.floor(abs(far - first) / step + 1e-9)) + 1
    positions = first + sign * step * np.arange(n)
    views = []
    for s_along in positions:
        slab = np.abs(along - s_along) < 0.01
        target = kidney_B[slab].mean(axis=0) if slab.any() else c + s_along * superior_B
        skin = _skin_entry(patient.skin_mesh, X_BPt, target, a)
        views.append(
            check_view(patient.labels, X_BV, skin, a, o, imaging, kidney_B[slab], float(s_along))
        )
    sweep_fraction = 0.9 - start_fraction if exploration_ratio is None else float(exploration_ratio)
    n_zone = int(round(zone / step))
    out = []
    shifts = (
        np.arange(0.0, config.max_start_shift + 1e-9, config.start_shift_step)
        if config.start_shift_step > 0
        else np.zeros(1)
    )
    for shift in shifts:
        sf = start_fraction + float(shift)
        start = n_zone + int(round(shift * length / step))
        if start >= len(views):
            break
        sweep_end = min(start + int(round(sweep_fraction * length / step)), len(views) - 1)
        if shift > 0 and sf + min(sweep_fraction, config.min_sweep_fraction) > 0.95 + 1e-9:
            break  # a later start would see too little of the kidney
        zone_views = views[max(start - n_zone, 0) : start + n_zone + 1]
        cand = _window_from_views(
            tilt, a, views, start, sweep_end, zone_views, config, imaging, sf, step
        )
        cand.covered_length = min(cand.sweep_length, config.min_sweep_fraction * length)
        out.append(cand)
    return out


def vertical_depth_preset(patient, X_BPt: RigidTransform, imaging, config) -> float:
    """The shallowest depth preset holding the kidney (far side + ``config.depth_margin``)
    under a vertical probe anywhere along the exploration line (the kinematic twin's probe;
    bone and gas shadows are not checked: the twin images where it is told). Raises
    :class:`StartPlanError` when no preset is deep enough."""
    superior_B = X_BPt.rotation().matrix()[:, 1]
    kidney_B = X_BPt.multiply(np.asarray(patient.kidney_mesh.vertices).T).T
    X_BV = X_BPt @ patient.labels.X_PtV
    c = evaluate_windows(patient, X_BPt, imaging, config, 0.0, superior_B, kidney_B, X_BV)[0]
    if c.preset is None:
        raise StartPlanError(
            f"start planner: the {patient.side} kidney's far side lies "
            f"{c.needed_depth * 1000:.0f} mm under a vertical probe (with margin), beyond the "
            f"deepest preset {max(imaging.depth_presets) * 1000:.0f} mm"
        )
    return c.preset


def window_rank(c: WindowCandidate, preset: float) -> tuple:
    """Order of feasible windows: without a warning (clear within the placement error of the
    start and for ``min_clear_sweep`` of the sweep) first, then a sweep clear of shadows for
    its whole length, or for ``min_sweep_fraction`` of the kidney if that is shorter (a
    sonographer keeps the kidney in view; a later start's sweep, cut at the far pole, is
    not preferred for being short), then the shallowest preset, the longest clear sweep,
    the least tilt and the earliest start."""
    needed = c.covered_length if c.covered_length > 0 else c.sweep_length
    covered = c.clear_length >= needed - 1e-9
    return (
        bool(c.warning),
        not covered,
        preset,
        -round(c.clear_length, 4),
        abs(c.tilt_deg),
        c.start_fraction,
    )


def _placement_error(config, seed: int, R_BP: RotationMatrix):
    """A placement offset (m, across the beam) and a tilt (rotation about an axis across the
    beam) of the configured sizes, in seeded random directions."""
    rng = np.random.default_rng([int(seed), 6007, int(config.placement_seed)])
    x, y = R_BP.matrix()[:, 0], R_BP.matrix()[:, 1]
    phi, psi = rng.uniform(0.0, 2 * np.pi, 2)
    offset = config.placement_error * (np.cos(phi) * x + np.sin(phi) * y)
    angle = np.radians(config.placement_error_angle_deg)
    axis = np.cos(psi) * x + np.sin(psi) * y
    return offset, angle, RotationMatrix(AngleAxis(angle, axis))


def PlanStart(
    patient,
    X_BPt: RigidTransform,
    imaging,
    config,
    *,
    reachable=None,
    seed: int = 0,
    scan_direction: str = "-y",
    start_fraction: float | None = None,
    exploration_ratio: float | None = None,
) -> StartPlan:
    """The start of a scan on ``patient`` lying at ``X_BPt`` (see :mod:`drake_rus.scan.config`).

    Tries beam tilts from vertical to ``config.max_tilt_deg`` (both sides, about the body's
    long axis; the exploration runs along it with the probe's array across the body) and,
    for each, exploration starts from ``start_fraction`` of the kidney's length inside its
    end to ``config.max_start_shift`` later. Transverse views every
    ``config.sweep_check_step`` along the exploration line are ray-cast through the label
    volume with the curvilinear fan (:func:`check_view`). A window is feasible when a depth
    preset holds the kidney along the whole exploration line, at the start the central ray
    is clear of bone and gas and at most ``max_blocked_fraction`` of the fan's rays to the
    kidney cross them, and ``reachable(X_BP)`` (e.g. the FR3's IK) accepts the start, middle
    and end poses. A feasible window carries a warning when a shadow lies within the
    placement error of the start or crosses the sweep of ``exploration_ratio`` x the
    kidney's length before ``config.min_clear_sweep`` (a rib shadow hides the kidney from
    the segmenter mid-sweep). Among feasible windows (:func:`window_rank`): no warning
    first, then a sweep clear for its whole length, the shallowest preset holding both the
    window and the vertical pivot of eq. 20 over the kidney centroid, the longest clear
    sweep, the least tilt, the earliest start.
    Raises :class:`StartPlanError` naming why no window works.
    """
    superior_B = X_BPt.rotation().matrix()[:, 1]
    kidney_B = X_BPt.multiply(np.asarray(patient.kidney_mesh.vertices).T).T
    X_BV = X_BPt @ patient.labels.X_PtV
    step = max(np.radians(config.tilt_step_deg), 1e-3)
    n = int(np.floor(np.radians(config.max_tilt_deg) / step + 1e-9))
    tilts = sorted({0.0, *(k * step * s for k in range(1, n + 1) for s in (1, -1))}, key=abs)
    sf = config.start_fraction if start_fraction is None else start_fraction
    # The pivot (eq. 20-23) looks straight down over the kidney centroid: its depth too.
    pivot_depth = evaluate_windows(
        patient, X_BPt, imaging, config, 0.0, superior_B, kidney_B, X_BV
    )[0].needed_depth

    def overall_preset(c):
        need = max(c.needed_depth, pivot_depth)
        fitting = [p for p in sorted(imaging.depth_presets) if p >= need]
        return fitting[0] if fitting else None

    def pose(c, k):
        R_BP = probe_rotation(c.approach_B, superior_B)
        return RigidTransform(R_BP, c.skin_points_B[k] - config.hover * c.approach_B)

    def rank(c):
        return window_rank(c, overall_preset(c))

    # One candidate per tilt: its best start (the first when none is feasible).
    candidates = []
    for t in tilts:
        options = evaluate_windows(
            patient,
            X_BPt,
            imaging,
            config,
            t,
            superior_B,
            kidney_B,
            X_BV,
            sf,
            scan_direction,
            exploration_ratio,
        )
        good = [c for c in options if c.feasible and overall_preset(c) is not None]
        candidates.append(min(good, key=rank) if good else options[0])
    feasible = [c for c in candidates if c.feasible]
    ranked = sorted((c for c in feasible if overall_preset(c) is not None), key=rank)
    chosen = None
    for c in ranked:
        if reachable is not None:
            c.reachable = all(reachable(pose(c, k)) for k in range(len(c.skin_points_B)))
            if not c.reachable:
                c.reason = "the FR3 cannot reach the start or end pose from the bed placement"
                continue
        chosen = c
        break
    if chosen is None:
        reasons = sorted({c.reason for c in candidates if c.reason})
        if feasible and not ranked:
            reasons.append(
                f"the vertical pivot needs {pivot_depth * 1000:.0f} mm, beyond the "
                f"deepest preset {max(imaging.depth_presets) * 1000:.0f} mm"
            )
        raise StartPlanError(
            f"start planner: no acoustic window to the {patient.side} kidney within "
            f"{config.max_tilt_deg:g} deg of vertical: " + "; ".join(reasons)
        )
    X_planned = pose(chosen, 0)
    offset, angle, R_err = _placement_error(config, seed, X_planned.rotation())
    X_start = RigidTransform(R_err @ X_planned.rotation(), X_planned.translation() + offset)
    plane = _plane_labels(
        patient.labels,
        X_BV,
        chosen.skin_points_B[0],
        chosen.approach_B,
        X_planned.rotation().matrix()[:, 0],
        max(imaging.depth_presets),
    )
    return StartPlan(
        X_start,
        X_planned,
        overall_preset(chosen),
        chosen,
        candidates,
        offset,
        angle,
        pivot_depth,
        plane,
    )


def _plane_labels(volume, X_BV, origin_B, a, o, depth: float, step: float = 0.0015):
    """Labels on the plane through ``origin_B`` spanned by o (columns, +-0.6 depth) and a
    (rows, from 20 mm outside the skin to ``depth``)."""
    u = np.arange(-0.6 * depth, 0.6 * depth, step)
    v = np.arange(-0.02, depth, step)
    P = (
        np.asarray(origin_B)[None, None, :]
        + v[:, None, None] * np.asarray(a)[None, None, :]
        + u[None, :, None] * np.asarray(o)[None, None, :]
    )
    p_V = X_BV.inverse().multiply(P.reshape(-1, 3).T).T / volume.voxel_size
    ijk = np.rint(p_V).astype(int)
    inside = np.all((ijk >= 0) & (ijk < np.array(volume.shape)), axis=1)
    labels = np.zeros(len(ijk), np.uint8)
    labels[inside] = volume.labels[ijk[inside, 0], ijk[inside, 1], ijk[inside, 2]]
    return labels.reshape(len(v), len(u)), u, v


def _short(text: str, n: int = 34) -> str:
    """``text`` cut to ``n`` characters for a table cell (the whole reason is in
    summary.json)."""
    return text if len(text) <= n else text[: n - 3].rstrip() + "..."


def plot_start_plan(plan: StartPlan, imaging, path, title: str = "") -> None:
    """start_plan.png: the chosen window's image plane (tissue labels, the colours of
    ``drake_rus.anatomy.tissue_colors``), the fan at the chosen depth preset, the central rays
    of the windows tried (green: usable, orange dashed: rejected) and the bone/gas that
    shadows the kidney in them (x), beside a table of the windows and the legend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import patheffects
    from matplotlib.lines import Line2D

    labels, u, v = plan.plane
    fig, (ax, tx) = plt.subplots(1, 2, figsize=(12, 6.2), gridspec_kw={"width_ratios": [1.4, 1.0]})
    ax.imshow(
        label_image(labels),
        extent=[u[0] * 1e3, u[-1] * 1e3, v[-1] * 1e3, v[0] * 1e3],
        interpolation="nearest",
    )
    half = np.radians(imaging.field_of_view_deg) / 2
    r, d = imaging.probe_radius, plan.depth_preset
    arc = np.linspace(-half, half, 50)
    # Fan (in this plane, apex r behind the face centre), chosen depth preset.
    ax.plot(
        np.r_[r * np.sin(arc), (r + d) * np.sin(arc[::-1]), r * np.sin(arc[0])] * 1e3,
        np.r_[r * np.cos(arc) - r, (r + d) * np.cos(arc[::-1]) - r, r * np.cos(arc[0]) - r] * 1e3,
        color="tab:blue",
        lw=1.5,
    )
    origin = plan.window.skin_points_B[0]
    o = plan.X_planned.rotation().matrix()[:, 0]
    a0 = plan.window.approach_B
    shadows = 0
    halo = [patheffects.withStroke(linewidth=2.5, foreground="white")]  # visible on gas
    for c in plan.candidates:
        end = c.approach_B * min(c.needed_depth if np.isfinite(c.needed_depth) else d, d)
        chosen = c is plan.window
        ax.plot(
            [0, (end @ o) * 1e3],
            [0, (end @ a0) * 1e3],
            color="tab:green" if c.feasible else "tab:orange",
            ls="-" if c.feasible else "--",
            lw=2.5 if chosen else 0.8,
            alpha=1.0 if chosen else 0.7,
        )
        if len(c.blockers_B):
            b = c.blockers_B - origin
            ax.plot((b @ o) * 1e3, (b @ a0) * 1e3, "x", color="k", ms=4, path_effects=halo)
            shadows += len(b)
    ax.set_xlabel("across the beam (mm)")
    ax.set_ylabel("along the chosen beam from the skin (mm)")
    ax.set_title(title or "Start planner: the chosen acoustic window")
    rows = [
        (
            f"{c.tilt_deg:+.0f}",
            f"{c.needed_depth * 1000:.0f}" if np.isfinite(c.needed_depth) else "-",
            "-" if c.preset is None else f"{c.preset * 1000:.0f}",
            f"{c.blocked_fraction:.0%}",
            f"{c.start_fraction:.2f}",
            f"{c.clear_length * 1000:.0f}/{c.sweep_length * 1000:.0f}",
            "chosen" if c is plan.window else ("ok" if c.feasible else _short(c.reason)),
        )
        for c in plan.candidates
    ]
    tx.axis("off")
    table = tx.table(
        cellText=rows,
        colLabels=["tilt deg", "need mm", "preset", "blocked", "start", "clear mm", "verdict"],
        loc="upper center",
        colWidths=[0.1, 0.11, 0.1, 0.1, 0.08, 0.12, 0.39],
    )
    table.auto_set_font_size(False)
    table.set_fontsize(7)
    for (row, col), cell in table.get_celld().items():
        if col == 6 and row > 0:
            cell.set_text_props(ha="left")
            cell.PAD = 0.02
    s = plan.summary()
    tx.set_title(
        f"preset {plan.depth_preset * 1000:.0f} mm, tilt {s['tilt_deg']:+.0f} deg, "
        f"placement error {s['placement_error_mm']:.1f} mm / "
        f"{s['placement_error_deg']:.1f} deg",
        fontsize=9,
    )
    marks = [
        Line2D(
            [], [], color="tab:blue", lw=1.5, label=f"image fan, depth preset {d * 1000:.0f} mm"
        ),
        Line2D([], [], color="tab:green", lw=2.5, label="chosen window's central ray"),
    ]
    if sum(c.feasible for c in plan.candidates) > 1:
        marks.append(Line2D([], [], color="tab:green", lw=0.8, label="other usable windows"))
    if any(not c.feasible for c in plan.candidates):
        marks.append(
            Line2D(
                [],
                [],
                color="tab:orange",
                lw=0.8,
                ls="--",
                label="rejected windows (why: the table, summary.json)",
            )
        )
    if shadows:
        marks.append(
            Line2D(
                [],
                [],
                color="k",
                marker="x",
                ls="",
                ms=5,
                path_effects=halo,
                label="bone or gas shadowing the kidney: where a fan ray\n"
                "meets it before the kidney, in any view along a\n"
                "window's sweep (projected onto this plane)",
            )
        )
    lines = tx.legend(
        handles=marks, loc="upper left", bbox_to_anchor=(0.0, 0.42), fontsize=7, frameon=False
    )
    tx.add_artist(lines)
    tx.legend(
        handles=tissue_handles(labels_present(labels)),
        loc="lower left",
        bbox_to_anchor=(0.0, 0.0),
        ncol=3,
        fontsize=7,
        title="tissues in the plane",
        title_fontsize=8,
        frameon=False,
    )
    fig.tight_layout()
    save_figure(fig, path)


def DrawStartPlan(meshcat, plan: StartPlan, prefix: str = "start_plan") -> None:
    """Draws the planner's choice in Meshcat: the skin point, the beam to the needed depth,
    the fan outline at the chosen preset, the rejected windows' central rays (red) and the
    bone/gas that blocked them."""
    w = plan.window
    s0 = w.skin_points_B[0]
    meshcat.SetObject(f"{prefix}/skin_point", Sphere(0.006), Rgba(0.1, 0.4, 1.0, 1.0))
    meshcat.SetTransform(f"{prefix}/skin_point", RigidTransform(s0))
    meshcat.SetLine(
        f"{prefix}/beam",
        np.column_stack([s0, s0 + w.approach_B * w.needed_depth]),
        3.0,
        Rgba(0.1, 0.4, 1.0, 1.0),
    )
    o = plan.X_planned.rotation().matrix()[:, 0]
    half = np.radians(20.0)
    fan = [
        s0 + plan.depth_preset * (np.cos(t) * w.approach_B + np.sin(t) * o)
        for t in np.linspace(-half, half, 21)
    ]
    meshcat.SetLine(f"{prefix}/fan", np.column_stack([s0, *fan, s0]), 1.5, Rgba(0.1, 0.6, 1.0, 0.8))
    for k, c in enumerate(x for x in plan.candidates if not x.feasible):
        p = c.skin_points_B[0] if len(c.skin_points_B) else s0
        if not np.all(np.isfinite(p)):
            p = s0
        meshcat.SetLine(
            f"{prefix}/rejected/{k}",
            np.column_stack([p, p + c.approach_B * 0.08]),
            1.0,
            Rgba(0.9, 0.1, 0.1, 0.7),
        )
        for j, b in enumerate(c.blockers_B[:20]):
            meshcat.SetObject(
                f"{prefix}/rejected/{k}/blocker_{j}", Sphere(0.003), Rgba(0.1, 0.1, 0.1, 1.0)
            )
            meshcat.SetTransform(f"{prefix}/rejected/{k}/blocker_{j}", RigidTransform(b))
