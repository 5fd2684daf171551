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
    return ExplorationRoi(lo[0], hi[0], lo[1], hi[1],
                          patient.X_BK(X_BPt).translation().copy())


def skin_height_B(patient, X_BPt: RigidTransform, x: float, y: float) -> float:
    """Height z (m, base frame) of the body surface above the point (x, y)."""
    mesh = patient.skin_mesh
    X_PtB = X_BPt.inverse()
    origin_B = np.array([x, y, 10.0])
    origin = X_PtB.multiply(origin_B)
    direction = X_PtB.rotation().multiply(np.array([0.0, 0.0, -1.0]))
    hits, _, _ = mesh.ray.intersects_location([origin], [direction])
    if len(hits) == 0:
        raise ValueError(f"no body surface below (x, y) = ({x:.3f}, {y:.3f}) m in the base "
                         "frame: is the patient placed under the robot (patient.X_BPt)?")
    hits_B = X_BPt.multiply(np.asarray(hits).T).T
    return float(hits_B[:, 2].max())


def exploration_start_xy(roi: ExplorationRoi, scan_direction: str = "-y",
                         start_fraction: float = 0.0) -> tuple[float, float]:
    """(x, y) of the exploration start: over the kidney centroid's x, at the E-ROI's end the
    scan leaves from, ``start_fraction`` of the E-ROI's length inside it."""
    if scan_direction == "-y":
        y = roi.y_max - start_fraction * roi.length_y
    elif scan_direction == "+y":
        y = roi.y_min + start_fraction * roi.length_y
    else:
        raise ValueError(f"scan_direction: expected '+y' or '-y', got {scan_direction!r}")
    return float(roi.centroid_B[0]), float(y)


def exploration_start(patient, X_BPt: RigidTransform, *, scan_direction: str = "-y",
                      start_fraction: float = 0.0, hover: float = 0.015) -> RigidTransform:
    """Tip pose (transverse view, pointing down) ``hover`` m above the skin at the start.

    The start lies over the kidney centroid's x, at the E-ROI's end the scan leaves from
    (its superior end for a "-y" scan when the head is at +y), moved into the E-ROI by
    ``start_fraction`` of its length (0: at the pole; randomised starts use more).
    """
    x, y = exploration_start_xy(exploration_roi(patient, X_BPt), scan_direction,
                                start_fraction)
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
    tilt_deg: float                 # signed tilt from vertical about the body's long axis
    approach_B: np.ndarray          # beam direction a (into the body)
    skin_points_B: np.ndarray       # (3, 3) skin entry points along the exploration line
    needed_depth: float             # image depth that holds the whole kidney (m, + margin)
    blocked_fraction: float         # of the fan's rays reaching the kidney, crossed bone/gas
    central_blocked: bool           # the central ray crosses bone or gas somewhere
    blockers_B: np.ndarray          # (N, 3) first bone/gas sample of each blocked ray
    preset: float | None            # shallowest preset holding the kidney (None: none does)
    reachable: bool | None = None   # None: not checked
    reason: str = ""                # why it was rejected ("" when feasible)

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
    placement_offset_B: np.ndarray   # (3,) position error applied (m)
    placement_angle: float           # tilt error applied (rad)
    pivot_depth_needed: float        # depth the vertical pivot (eq. 20) needs (m)
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
            "placement_error_mm": round(float(np.linalg.norm(self.placement_offset_B)) * 1000,
                                        2),
            "placement_error_deg": round(float(np.degrees(self.placement_angle)), 2),
            "windows_tried": len(self.candidates),
            "windows_feasible": sum(c.feasible for c in self.candidates),
        }


def _rotation_about(axis, angle: float) -> np.ndarray:
    return RotationMatrix(AngleAxis(angle, np.asarray(axis, float) / np.linalg.norm(axis))
                          ).matrix()


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


def evaluate_window(patient, X_BPt: RigidTransform, imaging, config, tilt: float,
                    superior_B, kidney_B, X_BV, start_fraction: float = 0.1,
                    scan_direction: str = "-y") -> WindowCandidate:
    """Depth, path and fan clearance of the beam tilted by ``tilt`` (rad) from vertical
    about the body's long axis, along the exploration line: transverse views at the start
    (``start_fraction`` of the kidney's length inside the end the scan leaves from), at the
    kidney's centre and near its other end (``skin_points_B`` in that order)."""
    a = _rotation_about(superior_B, tilt) @ np.array([0.0, 0.0, -1.0])
    R_BP = probe_rotation(a, superior_B).matrix()
    o = R_BP[:, 0]
    c = kidney_B.mean(axis=0)
    along = (kidney_B - c) @ superior_B
    lo, hi = float(along.min()), float(along.max())
    skin_points, needed, rays, blocked, central, blockers = [], 0.0, 0, 0, False, []
    half_fov = np.radians(imaging.field_of_view_deg) / 2
    length = hi - lo
    first = hi - start_fraction * length if scan_direction == "-y" else lo + start_fraction * length
    last = lo + 0.1 * length if scan_direction == "-y" else hi - 0.1 * length
    for s_along in (first, 0.5 * (first + last), last):
        slab = np.abs(along - s_along) < 0.01
        target = c + s_along * superior_B
        if slab.any():
            target = kidney_B[slab].mean(axis=0)
        skin = _skin_entry(patient.skin_mesh, X_BPt, target, a)
        if skin is None:
            return WindowCandidate(np.degrees(tilt), a, np.zeros((3, 3)), np.inf, 1.0, True,
                                   np.zeros((0, 3)), None, reason="beam misses the body")
        skin_points.append(skin)
        if slab.any():
            needed = max(needed, float(((kidney_B[slab] - skin) @ a).max()))
        for k, phi in enumerate(np.linspace(-half_fov, half_fov, _FAN_RAYS)):
            d = np.cos(phi) * a + np.sin(phi) * o
            labels, p_B = _labels_along(patient.labels, X_BV, skin, d, imaging.depth_presets[-1])
            hits_kidney, crossed, i = _ray_blocked(labels)
            if hits_kidney:
                rays += 1
                if crossed:
                    blocked += 1
                    blockers.append(p_B[i])
            if k == _FAN_RAYS // 2 and crossed:
                central = True
    needed += config.depth_margin
    fitting = [p for p in sorted(imaging.depth_presets) if p >= needed]
    cand = WindowCandidate(
        float(np.degrees(tilt)), a, np.array(skin_points), needed,
        blocked / rays if rays else 1.0, central,
        np.array(blockers) if blockers else np.zeros((0, 3)), fitting[0] if fitting else None)
    if not rays:
        cand.reason = "no ray of the fan reaches the kidney"
    elif cand.preset is None:
        cand.reason = (f"the kidney's far side lies {needed * 1000:.0f} mm deep (with margin), "
                       f"beyond the deepest preset {max(imaging.depth_presets) * 1000:.0f} mm")
    elif central:
        cand.reason = "the central ray crosses bone or gas"
    elif cand.blocked_fraction > config.max_blocked_fraction:
        cand.reason = (f"{cand.blocked_fraction:.0%} of the fan's rays to the kidney cross bone "
                       f"or gas (max {config.max_blocked_fraction:.0%})")
    return cand


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


def PlanStart(patient, X_BPt: RigidTransform, imaging, config, *, reachable=None,
              seed: int = 0, scan_direction: str = "-y",
              start_fraction: float | None = None) -> StartPlan:
    """The start of a scan on ``patient`` lying at ``X_BPt`` (see :mod:`drake_rus.scan.config`).

    Tries beam tilts from vertical to ``config.max_tilt_deg`` (both sides, about the body's
    long axis; the exploration runs along it with the probe's array across the body). A
    window is feasible when a depth preset holds the kidney along the whole exploration line,
    the central ray is clear of bone and gas and at most ``max_blocked_fraction`` of the
    fan's rays to the kidney cross them, and ``reachable(X_BP)`` (e.g. the FR3's IK) accepts
    the start and end poses. Among feasible windows: the shallowest preset holding both the
    window and the vertical pivot of eq. 20 over the kidney centroid, then the least tilt.
    Raises :class:`StartPlanError` naming why no window works.
    """
    superior_B = X_BPt.rotation().matrix()[:, 1]
    kidney_B = X_BPt.multiply(np.asarray(patient.kidney_mesh.vertices).T).T
    X_BV = X_BPt @ patient.labels.X_PtV
    step = max(np.radians(config.tilt_step_deg), 1e-3)
    n = int(np.floor(np.radians(config.max_tilt_deg) / step + 1e-9))
    tilts = sorted({0.0, *(k * step * s for k in range(1, n + 1) for s in (1, -1))}, key=abs)
    sf = config.start_fraction if start_fraction is None else start_fraction
    candidates = [evaluate_window(patient, X_BPt, imaging, config, t, superior_B, kidney_B,
                                  X_BV, sf, scan_direction) for t in tilts]
    # The pivot (eq. 20-23) looks straight down over the kidney centroid: its depth too.
    pivot = evaluate_window(patient, X_BPt, imaging, config, 0.0, superior_B, kidney_B, X_BV)
    pivot_depth = pivot.needed_depth
    feasible = [c for c in candidates if c.feasible]

    def overall_preset(c):
        need = max(c.needed_depth, pivot_depth)
        fitting = [p for p in sorted(imaging.depth_presets) if p >= need]
        return fitting[0] if fitting else None

    def pose(c, k):
        R_BP = probe_rotation(c.approach_B, superior_B)
        return RigidTransform(R_BP, c.skin_points_B[k] - config.hover * c.approach_B)

    ranked = sorted((c for c in feasible if overall_preset(c) is not None),
                    key=lambda c: (overall_preset(c), abs(c.tilt_deg)))
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
            reasons.append(f"the vertical pivot needs {pivot_depth * 1000:.0f} mm, beyond the "
                           f"deepest preset {max(imaging.depth_presets) * 1000:.0f} mm")
        raise StartPlanError(
            f"start planner: no acoustic window to the {patient.side} kidney within "
            f"{config.max_tilt_deg:g} deg of vertical: " + "; ".join(reasons))
    X_planned = pose(chosen, 0)
    offset, angle, R_err = _placement_error(config, seed, X_planned.rotation())
    X_start = RigidTransform(R_err @ X_planned.rotation(), X_planned.translation() + offset)
    plane = _plane_labels(patient.labels, X_BV, chosen.skin_points_B[0],
                          chosen.approach_B, X_planned.rotation().matrix()[:, 0],
                          max(imaging.depth_presets))
    return StartPlan(X_start, X_planned, overall_preset(chosen), chosen, candidates, offset,
                     angle, pivot_depth, plane)


def _plane_labels(volume, X_BV, origin_B, a, o, depth: float, step: float = 0.0015):
    """Labels on the plane through ``origin_B`` spanned by o (columns, +-0.6 depth) and a
    (rows, from 20 mm outside the skin to ``depth``)."""
    u = np.arange(-0.6 * depth, 0.6 * depth, step)
    v = np.arange(-0.02, depth, step)
    P = (np.asarray(origin_B)[None, None, :] + v[:, None, None] * np.asarray(a)[None, None, :]
         + u[None, :, None] * np.asarray(o)[None, None, :])
    p_V = X_BV.inverse().multiply(P.reshape(-1, 3).T).T / volume.voxel_size
    ijk = np.rint(p_V).astype(int)
    inside = np.all((ijk >= 0) & (ijk < np.array(volume.shape)), axis=1)
    labels = np.zeros(len(ijk), np.uint8)
    labels[inside] = volume.labels[ijk[inside, 0], ijk[inside, 1], ijk[inside, 2]]
    return labels.reshape(len(v), len(u)), u, v


def plot_start_plan(plan: StartPlan, imaging, path, title: str = "") -> None:
    """start_plan.png: the chosen window's image plane (tissue labels), the fan at the chosen
    depth preset, the central rays of the windows tried (green: feasible, red: rejected) and
    the bone/gas that blocked them, beside a table of the windows."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap
    labels, u, v = plan.plane
    colors = ["#ffffff", "#d9b8a5", "#f3e3a0", "#c98b7b", "#8b1e1e", "#a83232", "#d98c8c",
              "#7a4b2a", "#f5f5f5", "#202020", "#3050a0"]
    fig, (ax, tx) = plt.subplots(1, 2, figsize=(12, 5.6),
                                 gridspec_kw={"width_ratios": [1.4, 1.0]})
    ax.imshow(labels, cmap=ListedColormap(colors), vmin=0, vmax=len(colors) - 1,
              extent=[u[0] * 1e3, u[-1] * 1e3, v[-1] * 1e3, v[0] * 1e3], interpolation="nearest")
    half = np.radians(imaging.field_of_view_deg) / 2
    r, d = imaging.probe_radius, plan.depth_preset
    arc = np.linspace(-half, half, 50)
    # Fan (in this plane, apex r behind the face centre), chosen depth preset.
    ax.plot(np.r_[r * np.sin(arc), (r + d) * np.sin(arc[::-1]), r * np.sin(arc[0])] * 1e3,
            np.r_[r * np.cos(arc) - r, (r + d) * np.cos(arc[::-1]) - r,
                  r * np.cos(arc[0]) - r] * 1e3, color="tab:blue", lw=1.5,
            label=f"fan, depth preset {d * 1000:.0f} mm")
    origin = plan.window.skin_points_B[0]
    o = plan.X_planned.rotation().matrix()[:, 0]
    a0 = plan.window.approach_B
    for c in plan.candidates:
        end = c.approach_B * min(c.needed_depth if np.isfinite(c.needed_depth) else d, d)
        ax.plot([0, (end @ o) * 1e3], [0, (end @ a0) * 1e3],
                color="tab:green" if c.feasible else "tab:red", lw=2.5 if c is plan.window
                else 0.8, alpha=1.0 if c is plan.window else 0.6)
        if len(c.blockers_B):
            b = c.blockers_B - origin
            ax.plot((b @ o) * 1e3, (b @ a0) * 1e3, "x", color="k", ms=4)
    ax.set_xlabel("across the beam (mm)")
    ax.set_ylabel("along the chosen beam from the skin (mm)")
    ax.set_title(title or "Start planner: the chosen acoustic window")
    ax.legend(loc="lower right", fontsize=7)
    rows = [(f"{c.tilt_deg:+.0f}", f"{c.needed_depth * 1000:.0f}" if np.isfinite(c.needed_depth)
             else "-", "-" if c.preset is None else f"{c.preset * 1000:.0f}",
             f"{c.blocked_fraction:.0%}", "chosen" if c is plan.window
             else ("ok" if c.feasible else c.reason[:38])) for c in plan.candidates]
    tx.axis("off")
    table = tx.table(cellText=rows, colLabels=["tilt deg", "need mm", "preset", "blocked",
                                               "verdict"], loc="upper center")
    table.auto_set_font_size(False)
    table.set_fontsize(7)
    s = plan.summary()
    tx.set_title(f"preset {plan.depth_preset * 1000:.0f} mm, tilt {s['tilt_deg']:+.0f} deg, "
                 f"placement error {s['placement_error_mm']:.1f} mm / "
                 f"{s['placement_error_deg']:.1f} deg", fontsize=9)
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
    meshcat.SetLine(f"{prefix}/beam", np.column_stack([s0, s0 + w.approach_B * w.needed_depth]),
                    3.0, Rgba(0.1, 0.4, 1.0, 1.0))
    o = plan.X_planned.rotation().matrix()[:, 0]
    half = np.radians(20.0)
    fan = [s0 + plan.depth_preset * (np.cos(t) * w.approach_B + np.sin(t) * o)
           for t in np.linspace(-half, half, 21)]
    meshcat.SetLine(f"{prefix}/fan", np.column_stack([s0, *fan, s0]), 1.5,
                    Rgba(0.1, 0.6, 1.0, 0.8))
    for k, c in enumerate(x for x in plan.candidates if not x.feasible):
        p = c.skin_points_B[0] if len(c.skin_points_B) else s0
        meshcat.SetLine(f"{prefix}/rejected/{k}",
                        np.column_stack([p, p + c.approach_B * 0.08]), 1.0, Rgba(0.9, 0.1, 0.1, 0.7))
        for j, b in enumerate(c.blockers_B[:20]):
            meshcat.SetObject(f"{prefix}/rejected/{k}/blocker_{j}", Sphere(0.003),
                              Rgba(0.1, 0.1, 0.1, 1.0))
            meshcat.SetTransform(f"{prefix}/rejected/{k}/blocker_{j}", RigidTransform(b))
