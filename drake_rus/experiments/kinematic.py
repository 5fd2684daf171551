"""Kinematic mode: the seed's exploration and sweeps along planned probe poses, no dynamics.

Studies that need hundreds of runs (ER sweep, random starts, sweep strategies; seed III-C..E)
call the same pure functions as the closed-loop scan (eq. 17 exploration update, eq. 20-22
optimal pivot pose, eq. 23 Rodrigues pivot, slicing, segmentation, back-projection, ICP) but
place the probe exactly where the controller asks, one frame period at a time, instead of
stepping the robot's dynamics. What is left out: contact and tracking errors of the
controller, tissue compression under the probe and the robot's joint limits. Every figure
made from these runs says "kinematic".

Conventions (docs/design.md): base frame B (z up, patient along y), tip frame P (z_P = beam, x_P =
array), SI units. The tip sits on the skin surface (the height of the body surface above
the tip's (x, y), ``skin_height_B``); orientation is held exactly.

- :func:`prepare_patient` -> :class:`KinematicPatient` (label volume, skin height map, true
  kidney pose and voxels), built once per patient and process;
- :class:`Imager`: probe pose -> kidney mask (slice the label volume, emulate and segment with
  ``oracle`` (default), ``classical`` or ``onnx``);
- :func:`explore`: transverse straight-line sweep along base y at v_scan with eq. 17
  centring, for ER x L_m of travel (II-E, III-C), collecting P_local;
- :func:`localize_cloud`: T_k^b from P_local (II-F) with the heuristic fallback at ER 0;
- :func:`pivot_sweep`: fixed-point pivot about o (eq. 23), one way until the kidney leaves the
  image (or max tilt), then back through the start to the other side (II-G);
- :func:`predicted_end_sweep`: the ``predicted_end`` pivot (beyond the seed; the scan's
  ``controller.pivot_strategy: predicted_end``): tilt without imaging to the end the
  registered template predicts (the supervisor's own ``predict_pivot_ends`` and
  ``pretilt_plan``), on while the kidney is still seen, then one sweep to the other end;
- :func:`strategy_sweep`: OP, GT-OP, NOP, SL (III-E) and OP-PE (OP's pose, predicted-end
  pivot); :func:`sweep_curves`: n, eps, V. :func:`strategy_pivot_pose` (each pivot
  strategy's pose) and :func:`sl_line` (SL's start and travel) are the one definition the
  closed-loop study gives its scans too.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from pydrake.math import RigidTransform, RotationMatrix

from drake_rus.control.supervisor import (
    PivotModel,
    exploration_update,
    optimal_pivot_pose,
    pivot_end_allowed,
    predict_pivot_ends,
    pretilt_plan,
    rodrigues_pivot_update,
)
from drake_rus.imaging.emulator import EmulatorModel, emulate
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.imaging.segment import (
    KidneyTrack,
    read_mask,
    track_prior,
    track_settings,
    track_update,
)
from drake_rus.imaging.slicing import slice_volume
from drake_rus.imaging.systems import make_segmenter_backend
from drake_rus.localization.icp import heuristic_initial_rotation
from drake_rus.localization.localize import body_directions_B, localize
from drake_rus.metrics.core import CoverageAccumulator, window_steps
from drake_rus.metrics.sweep import cumulative_eps, pole_to_pole_indices
from drake_rus.scan.diagram import PivotModelFor
from drake_rus.scan.planning import (
    R_B_TRANSVERSE,
    exploration_roi,
    exploration_start_xy,
    skin_height_B,
    vertical_depth_preset,
)

PAPER_STRATEGIES = ("OP", "GT-OP", "NOP", "SL")
# Strategies beyond the paper's III-E: OP-PE, OP's pivot pose with the predicted_end pivot
# (controller.pivot_strategy: predicted_end) instead of the paper's two-leg pivot.
BEYOND_PAPER_STRATEGIES = ("OP-PE",)
STRATEGIES = PAPER_STRATEGIES + BEYOND_PAPER_STRATEGIES
MODE = "kinematic"


# ---------------------------------------------------------------------------- skin surface
class SkinHeightMap:
    """Body-surface height z_B(x, y) (m) on a regular grid, bilinear in between.

    Heights come from one batched vertical ray cast onto the skin mesh over the rectangle
    ``x_range`` x ``y_range`` (m, base frame) at ``spacing``; points outside the grid, or on
    grid cells with a missing hit, fall back to a single ray (``skin_height_B``).
    """

    def __init__(self, patient, X_BPt: RigidTransform, x_range, y_range, spacing: float = 0.002):
        if not spacing > 0:
            raise ValueError(f"spacing: expected a positive grid spacing in m, got {spacing}")
        self._patient, self._X_BPt = patient, X_BPt
        self.xs = np.arange(x_range[0], x_range[1] + 0.5 * spacing, spacing)
        self.ys = np.arange(y_range[0], y_range[1] + 0.5 * spacing, spacing)
        gx, gy = np.meshgrid(self.xs, self.ys, indexing="ij")
        self.z = skin_heights_B(patient, X_BPt, np.column_stack([gx.ravel(), gy.ravel()])).reshape(
            gx.shape
        )
        self.spacing = float(spacing)

    def __call__(self, x: float, y: float) -> float:
        fx = (x - self.xs[0]) / self.spacing
        fy = (y - self.ys[0]) / self.spacing
        i, j = int(math.floor(fx)), int(math.floor(fy))
        if 0 <= i < len(self.xs) - 1 and 0 <= j < len(self.ys) - 1:
            c = self.z[i : i + 2, j : j + 2]
            if np.all(np.isfinite(c)):
                a, b = fx - i, fy - j
                return float(
                    (1 - a) * (1 - b) * c[0, 0]
                    + a * (1 - b) * c[1, 0]
                    + (1 - a) * b * c[0, 1]
                    + a * b * c[1, 1]
                )
        return skin_height_B(self._patient, self._X_BPt, x, y)


def skin_heights_B(patient, X_BPt: RigidTransform, xy_B: np.ndarray) -> np.ndarray:
    """Heights z (m, base frame) of the body surface above many points (N, 2); NaN where a
    vertical line misses the body. One batched ray cast (``skin_height_B`` for one point)."""
    xy = np.asarray(xy_B, dtype=float).reshape(-1, 2)
    X_PtB = X_BPt.inverse()
    origins_B = np.column_stack([xy, np.full(len(xy), 10.0)])
    origins = origins_B @ X_PtB.rotation().matrix().T + X_PtB.translation()
    direction = X_PtB.rotation().multiply(np.array([0.0, 0.0, -1.0]))
    hits, ray, _ = patient.skin_mesh.ray.intersects_location(
        origins, np.repeat(direction[None], len(xy), axis=0), multiple_hits=True
    )
    z = np.full(len(xy), -np.inf)
    if len(hits):
        hits_B = np.asarray(hits) @ X_BPt.rotation().matrix().T + X_BPt.translation()
        np.maximum.at(z, ray, hits_B[:, 2])
    z[~np.isfinite(z)] = np.nan
    return z


# ---------------------------------------------------------------------------- the patient
@dataclasses.dataclass
class KinematicPatient:
    """What kinematic runs need of one patient placed at ``X_BPt``."""

    patient: object
    X_BPt: RigidTransform
    X_BV: RigidTransform  # label volume grid in B
    X_BK_true: RigidTransform
    roi: object  # ExplorationRoi
    skin: SkinHeightMap
    kidney_points_B: np.ndarray  # (N, 3) centres of the true kidney's voxels (m)
    voxel_size: float  # of kidney_points_B (m)
    superior_B: np.ndarray
    lateral_B: np.ndarray

    @property
    def volume(self):
        return self.patient.labels

    @property
    def voxel_volume(self) -> float:
        return self.voxel_size**3

    @property
    def kidney_volume(self) -> float:
        """True kidney volume (m^3) of the kidney surface mesh."""
        return float(abs(self.patient.kidney_mesh.volume))


def kidney_voxels_B(patient, X_BPt: RigidTransform, voxel_size: float) -> np.ndarray:
    """Centres (N, 3) in B of the kidney's voxels on a ``voxel_size`` grid (m)."""
    mask, X_PtV = patient.kidney_mask(voxel_size)
    ijk = np.argwhere(mask)
    p_Pt = X_PtV.multiply((ijk * voxel_size).T).T
    return X_BPt.multiply(p_Pt.T).T


def prepare_patient(
    patient,
    X_BPt: RigidTransform,
    *,
    coverage_voxel: float = 0.002,
    skin_margin: float = 0.07,
    skin_spacing: float = 0.002,
) -> KinematicPatient:
    """Builds (once) the label volume, skin height map and true kidney voxels of ``patient``."""
    if not isinstance(X_BPt, RigidTransform):
        raise ValueError(f"X_BPt: expected a RigidTransform, got {type(X_BPt).__name__}")
    volume = patient.labels
    roi = exploration_roi(patient, X_BPt)
    m = float(skin_margin)
    skin = SkinHeightMap(
        patient, X_BPt, (roi.x_min - m, roi.x_max + m), (roi.y_min - m, roi.y_max + m), skin_spacing
    )
    superior_B, lateral_B = body_directions_B(X_BPt, patient.side, patient.posture)
    return KinematicPatient(
        patient=patient,
        X_BPt=X_BPt,
        X_BV=X_BPt.multiply(volume.X_PtV),
        X_BK_true=patient.X_BK(X_BPt),
        roi=roi,
        skin=skin,
        kidney_points_B=kidney_voxels_B(patient, X_BPt, coverage_voxel),
        voxel_size=float(coverage_voxel),
        superior_B=np.asarray(superior_B, float),
        lateral_B=np.asarray(lateral_B, float),
    )


def imaging_for(kp: "KinematicPatient", imaging, start):
    """The imaging config for this patient, as the closed-loop scan would set it: with the
    window planner (``start.planner: window``) the depth follows the shallowest preset that
    holds the kidney under the vertical probe of the kinematic sweep
    (:func:`~drake_rus.scan.planning.vertical_depth_preset`; the twin's vertical probe
    images where it is told, so a rib over the vertical window does not stop it); with
    ``vertical`` the configured depth stays."""
    if start.planner == "vertical":
        return imaging
    return dataclasses.replace(
        imaging, depth=vertical_depth_preset(kp.patient, kp.X_BPt, imaging, start)
    )


# ---------------------------------------------------------------------------- imaging
@dataclasses.dataclass
class Frame:
    """One acquired frame: probe pose, the read-outs and (optionally) the images."""

    X_BP: RigidTransform
    visible: bool
    centroid: float  # c_msk in [0, 1]
    area: float  # mask area (m^2)
    boundary_B: np.ndarray  # (N, 3) back-projected boundary points (m)
    mask: np.ndarray | None = None
    image: np.ndarray | None = None  # grey image (classical/onnx) if kept


class Imager:
    """Probe pose -> kidney mask and its read-outs, like SliceSensor + emulator + Segmenter.

    ``segmenter``: "oracle" (the default here whatever ``imaging.segmenter`` says: kidney
    labels of the label image, as in the seed's simulation), "classical" or "onnx" (emulated
    B-mode image, then that backend; the classical one keeps the previous mask as a temporal
    prior), or None for ``imaging.segmenter``. ``seed`` fixes the emulator's speckle.
    """

    def __init__(
        self, kp: KinematicPatient, imaging, segmenter: str | None = "oracle", seed: int = 0
    ):
        self.kp = kp
        self.imaging = dataclasses.replace(imaging, segmenter=segmenter or imaging.segmenter)
        self.geometry = ProbeGeometry.from_config(self.imaging)
        self.backend_name = self.imaging.segmenter
        self._backend = make_segmenter_backend(self.imaging, self.geometry)
        self._model = None
        if self.backend_name != "oracle":
            self._model = EmulatorModel.from_config(self.imaging, self.geometry)
        self.seed = int(seed)
        self.frame_index = 0
        self._prev = None
        self._track = KidneyTrack()

    def reset(self) -> None:
        """Forget the temporal prior (a new sweep)."""
        self._prev = None
        self._track = KidneyTrack()

    def __call__(self, X_BP: RigidTransform, keep: bool = False) -> Frame:
        g = self.geometry
        labels = slice_volume(
            g,
            self.kp.volume,
            self.kp.X_BV,
            X_BP,
            int(self.imaging.elevation_planes),
            self.imaging.elevation_combine,
        )
        us = None
        if self._model is not None:
            us = emulate(labels, self._model, self.seed, self.frame_index)
        self.frame_index += 1
        # The classical prior: the previous frame's visible mask; the onnx backend follows
        # the kidney (a KidneyTrack, as the Segmenter system does; frames at
        # imaging.frame_rate_hz).
        t = self.frame_index / self.imaging.frame_rate_hz
        if self.backend_name == "onnx":
            prev, age = track_prior(self._track, t, self.imaging.track_confirm)
        else:
            prev, age = self._prev, math.inf
        mask = np.asarray(self._backend(us, labels, prev, age), bool) & g.fan_mask
        readout = read_mask(mask, g, self.imaging.min_kidney_area)
        self._prev = mask if readout.visible else None
        if self.backend_name == "onnx":
            self._track = track_update(
                self._track,
                mask,
                readout.visible,
                t,
                g,
                **track_settings(self.imaging),
            )
        boundary = (
            g.pixel_to_B(readout.boundary, X_BP) if len(readout.boundary) else np.zeros((0, 3))
        )
        return Frame(
            X_BP=X_BP,
            visible=bool(readout.visible),
            centroid=float(readout.centroid),
            area=float(readout.area),
            boundary_B=boundary,
            mask=mask if keep else None,
            image=us if keep else None,
        )


# ---------------------------------------------------------------------------- sweeps
@dataclasses.dataclass
class Sweep:
    """Frames of one probe motion, in acquisition order; ``kind`` "explore", "line" or
    "pivot"; ``angles`` (rad, pivot tilt from r3*) or ``travel`` (m, along y) per frame;
    ``leg`` (pivot: 1 or 2) per frame; ``events`` human-readable notes."""

    kind: str
    frames: list
    angles: np.ndarray | None = None
    travel: np.ndarray | None = None
    leg: np.ndarray | None = None
    events: list = dataclasses.field(default_factory=list)
    # What happened outside the sweep's frames (predicted_end: the predicted ends, the
    # pre-tilt's target and end, its check frames and window path).
    info: dict = dataclasses.field(default_factory=dict)

    @property
    def poses(self) -> list:
        return [f.X_BP for f in self.frames]

    @property
    def visible(self) -> np.ndarray:
        return np.array([f.visible for f in self.frames], bool)

    def point_cloud(self) -> np.ndarray:
        """P_local: all frames' back-projected boundary points (N, 3) in B (m)."""
        parts = [f.boundary_B for f in self.frames if len(f.boundary_B)]
        return np.concatenate(parts) if parts else np.zeros((0, 3))

    def prefix(self, travel: float) -> "Sweep":
        """The frames acquired within the first ``travel`` m of an exploration: exactly the
        sweep a shorter exploration (same start, same controller) would have produced,
        because eq. 17 only looks back."""
        if self.travel is None:
            raise ValueError("prefix: only an exploration sweep (with travel) has a prefix")
        k = int(np.searchsorted(self.travel, travel + 1e-9, side="right"))
        return dataclasses.replace(
            self,
            frames=self.frames[:k],
            travel=self.travel[:k],
            events=list(self.events) if k == len(self.frames) else [],
        )

    def pole_to_pole(self) -> "Sweep":
        """The part that images the kidney from one pole to the other: for a pivot, the
        second leg; then from its first to its last frame with the kidney visible (what
        the seed records, III-E). Empty if the kidney was never visible."""
        sel = pole_to_pole_indices(self.visible, self.leg)  # the one definition
        return dataclasses.replace(
            self,
            frames=[self.frames[i] for i in sel],
            angles=_take(self.angles, sel),
            travel=_take(self.travel, sel),
            leg=_take(self.leg, sel),
        )


def _take(a, idx):
    return None if a is None else np.asarray(a)[np.asarray(idx, dtype=int)]


def tip_pose(kp: KinematicPatient, R_BP, x: float, y: float) -> RigidTransform:
    """Probe pose with orientation R_BP and the tip on the skin above (x, y)."""
    R = R_BP if isinstance(R_BP, RotationMatrix) else RotationMatrix(np.asarray(R_BP, float))
    return RigidTransform(R, [x, y, kp.skin(x, y)])


def start_xy(
    kp: KinematicPatient,
    start_fraction: float = 0.0,
    scan_direction: str = "-y",
    x_offset: float = 0.0,
) -> np.ndarray:
    """Exploration start (x, y) (III-C, ``exploration_start``): over the kidney centroid's x
    (+ ``x_offset``), at the E-ROI end the scan leaves from, ``start_fraction`` of the
    E-ROI's length inside it."""
    x, y = exploration_start_xy(kp.roi, scan_direction, start_fraction)
    return np.array([x + x_offset, y])


def explore(
    kp: KinematicPatient,
    imager: Imager,
    controller,
    *,
    exploration_ratio: float,
    start_fraction: float = 0.0,
    x_offset: float = 0.0,
    travel: float | None = None,
    stop_when_lost: bool = True,
    keep_images: bool = False,
    start: np.ndarray | None = None,
) -> Sweep:
    """Transverse straight-line sweep (II-E): the seed's exploration in kinematic mode.

    The tip starts at ``start`` (x, y) or :func:`start_xy` and advances along
    ``controller.scan_direction`` at ``controller.scan_speed`` with one frame every
    1 / frame rate, for ``travel`` m (default ``exploration_ratio`` x
    ``controller.kidney_length``, the ER of III-C). Between frames x is re-centred on the
    kidney with eq. 17 (gain ``controller.K_p7``) from the mask centroid; z follows the skin.
    With ``stop_when_lost`` the sweep ends once the kidney, having been seen (in the image
    for ``controller.visibility_debounce`` without a gap: a glimpse of a pole's edge does
    not count), has been out of the image for the same time (the supervisor's line-sweep
    rule).
    """
    if not 0.0 <= exploration_ratio <= 1.0:
        raise ValueError(f"exploration_ratio: expected a value in [0, 1], got {exploration_ratio}")
    fps = float(imager.imaging.frame_rate_hz)
    dt = 1.0 / fps
    sign = 1.0 if controller.scan_direction == "+y" else -1.0
    target = exploration_ratio * controller.kidney_length if travel is None else float(travel)
    step = controller.scan_speed * dt
    n_steps = int(math.floor(target / step + 1e-9))
    P = (
        start_xy(kp, start_fraction, controller.scan_direction, x_offset)
        if start is None
        else np.asarray(start, float).reshape(2).copy()
    )
    R = R_B_TRANSVERSE
    x_p = R.matrix()[:, 0]
    debounce = max(1, int(math.ceil(controller.visibility_debounce * fps - 1e-9)))
    imager.reset()
    frames, travelled, seen, invisible_run, visible_run = [], [], False, 0, 0
    events = []
    for k in range(n_steps + 1):
        frame = imager(tip_pose(kp, R, P[0], P[1]), keep=keep_images)
        frames.append(frame)
        travelled.append(k * step)
        visible_run = visible_run + 1 if frame.visible else 0
        seen |= visible_run > debounce
        invisible_run = 0 if frame.visible else invisible_run + 1
        if stop_when_lost and seen and invisible_run >= debounce:
            events.append(f"kidney left the image after {k * step * 1e3:.1f} mm")
            break
        c = frame.centroid if frame.visible else math.nan
        P = exploration_update(P, c, x_p, sign * controller.scan_speed, controller.K_p7, dt)
    return Sweep("explore", frames, travel=np.asarray(travelled), events=events)


def pivot_sweep(
    kp: KinematicPatient,
    imager: Imager,
    R_BPstar,
    p_xy,
    *,
    pivot_rate: float,
    max_tilt: float,
    keep_images: bool = False,
    start_angle: float = 0.0,
    direction: float = 1.0,
    legs=(1, 2),
    ends=(),
    end_tolerance: float = 0.0,
    reset: bool = True,
) -> Sweep:
    """Fixed-point pivot sweep (II-G, eq. 23) at tip (x, y) = ``p_xy`` on the skin.

    The array o = R_BP*[:, 0] stays fixed; the approach a starts at R_BP*[:, 2] (turned by
    ``start_angle``) and turns about o by ``direction`` x pivot_rate / frame rate per frame
    (eq. 23). Leg 1 runs until the kidney, having been seen on this leg, leaves the image,
    or to ``max_tilt``; leg 2 runs back through the start to the other side under the same
    rule. (The closed-loop supervisor also ends a leg when the kidney is not seen at all for
    the debounce time; here an unseen kidney is searched for up to the tilt limit.) Which
    frames may end a leg is the supervisor's rule (``pivot_end_allowed``): ``legs=(2,)``
    with ``ends`` (predicted ends, rad) and ``end_tolerance`` is the predicted_end
    strategy's single sweep, from ``start_angle`` (its first frame one step past it).
    """
    o = np.asarray(R_BPstar, float)[:, 0].copy()
    a = np.asarray(R_BPstar, float)[:, 2].copy()
    angle = float(start_angle)
    if angle:
        a = rodrigues_pivot_update(a, o, angle)
    fps = float(imager.imaging.frame_rate_hz)
    dtheta = pivot_rate / fps
    p = np.asarray(p_xy, float).reshape(-1)[:2]
    z = kp.skin(p[0], p[1])
    if reset:
        imager.reset()
    frames, angles, leg_of, events = [], [], [], []
    direction = float(direction)

    def advance(a, angle):
        new_angle = float(np.clip(angle + direction * dtheta, -max_tilt, max_tilt))
        return rodrigues_pivot_update(a, o, new_angle - angle), new_angle

    for leg in legs:
        seen = False
        if leg == 2:  # the reversal frame is not acquired twice
            a, angle = advance(a, angle)
        while True:
            R = np.column_stack([o, np.cross(a, o), a])
            frame = imager(RigidTransform(RotationMatrix(R), [p[0], p[1], z]), keep=keep_images)
            frames.append(frame)
            angles.append(angle)
            leg_of.append(leg)
            new_side = pivot_end_allowed(angle, direction, leg - 1, ends, end_tolerance)
            seen |= frame.visible
            if seen and not frame.visible and new_side:
                events.append(
                    f"leg {leg} ended at {math.degrees(angle):.1f} deg: kidney left the image"
                )
                break
            if abs(angle) >= max_tilt - 1e-9 and new_side:
                events.append(f"leg {leg} ended at {math.degrees(angle):.1f} deg: maximum tilt")
                break
            a, angle = advance(a, angle)
        direction = -direction
    return Sweep("pivot", frames, angles=np.asarray(angles), leg=np.asarray(leg_of), events=events)


def pivot_model_for(template, imaging) -> PivotModel:
    """The predicted_end strategy's model of the scan (``PivotModelFor``: the template's
    points and the fan at ``imaging.depth``)."""
    return PivotModelFor(template, imaging)


def predicted_end_sweep(
    kp: KinematicPatient,
    imager: Imager,
    R_BPstar,
    p_xy,
    X_BK_estimated,
    model: PivotModel,
    controller,
    keep_images: bool = False,
) -> Sweep:
    """The ``predicted_end`` pivot (beyond the seed; ``controller.pivot_strategy:
    predicted_end``) at T* = (``R_BPstar``, tip (x, y) ``p_xy`` on the skin), as the
    supervisor runs it:

    1. the ends where the registered template (``model``, placed at ``X_BK_estimated``)
       leaves the image on each side (``predict_pivot_ends``, the supervisor's function);
    2. without imaging, tilt to the nearer end plus ``pivot_end_margin``
       (``pretilt_plan``); there, tilt on at ``pivot_rate`` while the kidney is still in the
       image (check frames, the supervisor's TRANSIT: not part of the sweep);
    3. one sweep back to the other side (the second leg, ``legs`` 2), ended by the kidney
       leaving the image within ``pivot_end_tolerance`` of the predicted other end or beyond,
       or by the tilt cap (``pivot_end_allowed``).

    ``Sweep.info`` holds the predicted ends, the pre-tilt's target and end (rad), the check
    frames and the pre-tilt's own window path (``eps_pretilt``, m, eq. 24 over poses one
    frame's tilt apart from T* to the sweep's start: the image moves there unrecorded).
    """
    c = controller
    R = np.asarray(R_BPstar, float)
    o, a0 = R[:, 0].copy(), R[:, 2].copy()
    p = np.asarray(p_xy, float).reshape(-1)[:2]
    z = kp.skin(p[0], p[1])
    tip = np.array([p[0], p[1], z])
    ends = predict_pivot_ends(
        model,
        X_BK_estimated.rotation().matrix(),
        X_BK_estimated.translation(),
        tip,
        a0,
        o,
        c.max_pivot_tilt,
    )
    side, target = pretilt_plan(ends, c.pivot_end_margin, c.max_pivot_tilt)
    dtheta = c.pivot_rate / float(imager.imaging.frame_rate_hz)

    def pose(angle):
        a = rodrigues_pivot_update(a0, o, angle) if angle else a0
        return RigidTransform(RotationMatrix(np.column_stack([o, np.cross(a, o), a])), tip)

    imager.reset()
    angle, checks = target, 0
    while True:  # at the target: tilt on while the kidney is seen (no sweep frames)
        frame = imager(pose(angle))
        checks += 1
        if not frame.visible or abs(angle) >= c.max_pivot_tilt - 1e-9:
            break
        angle = float(np.clip(angle + side * dtheta, -c.max_pivot_tilt, c.max_pivot_tilt))
    steps = max(1, int(math.ceil(abs(angle) / dtheta - 1e-9)))
    eps_pretilt = float(
        cumulative_eps([pose(angle * k / steps) for k in range(steps + 1)], imager.geometry.depth)[
            -1
        ]
    )
    sweep = pivot_sweep(
        kp,
        imager,
        R,
        p,
        pivot_rate=c.pivot_rate,
        max_tilt=c.max_pivot_tilt,
        keep_images=keep_images,
        start_angle=angle,
        direction=-side,
        legs=(2,),
        ends=ends,
        end_tolerance=c.pivot_end_tolerance,
        reset=False,
    )
    sweep.events.insert(
        0,
        f"predicted ends {math.degrees(ends[0]):.1f} / "
        f"{math.degrees(ends[1]):.1f} deg; pre-tilt to "
        f"{math.degrees(target):.1f} deg, kidney out of the image at "
        f"{math.degrees(angle):.1f} deg after {checks} check frame(s)",
    )
    sweep.info = {
        "predicted_ends": [float(ends[0]), float(ends[1])],
        "pretilt_target": float(target),
        "pretilt_end": float(angle),
        "pretilt_check_frames": int(checks),
        "eps_pretilt": eps_pretilt,
    }
    return sweep


# The exploration's array direction in B (the transverse view): NOP's array sign follows it.
NOP_ARRAY_REFERENCE = np.asarray(R_B_TRANSVERSE.matrix()[:, 0], float)


def nop_pose(R_BK: np.ndarray, p_BK: np.ndarray, o_ref=NOP_ARRAY_REFERENCE):
    """Non-optimal pivot pose (III-E, NOP): probe down, array along the kidney's y-axis
    projected on the horizontal, tip over the kidney centroid. The paper fixes the array's
    line, not its sign (either sign images the same plane): the sign whose horizontal part
    points along ``o_ref``'s (default the exploration's transverse array, base x), as a
    sonographer holds the probe in a transverse view, so the probe turns less than 90 deg
    from its exploration orientation (a 180 deg turn drives the FR3's wrist, joint 7, into
    its limit and the closed-loop pivot then stalls). Returns (R_BP, p)."""
    R_BK = np.asarray(R_BK, float)
    y, x = R_BK[:, 1], R_BK[:, 0]
    if float(y[:2] @ np.asarray(o_ref, float).reshape(3)[:2]) < 0:
        y, x = -y, -x  # a rotation by pi about z_k: the same plane, array flipped
    swapped = np.column_stack([y, -x, R_BK[:, 2]])
    return optimal_pivot_pose(swapped, p_BK)


# SL (III-E): the straight line starts this far (m) beyond the E-ROI's end and may run
# this much (m) beyond the E-ROI's other end plus the margin before it is stopped.
SL_MARGIN = 0.01
SL_EXTRA_TRAVEL = 0.03


def strategy_pivot_pose(
    strategy: str, X_BK_true: RigidTransform, X_BK_estimated: RigidTransform | None = None
):
    """(R_BP, p) of a pivot strategy's pivot pose (III-E), the one definition both modes
    use: OP and OP-PE T* of the registered pose ``X_BK_estimated`` (eq. 20-22); GT-OP T*
    of the true pose; NOP :func:`nop_pose` of the true pose (the in-vivo NOP was
    expert-placed)."""
    if strategy in ("OP", "OP-PE"):
        if X_BK_estimated is None:
            raise ValueError(
                f"strategy {strategy}: needs X_BK_estimated (the registered kidney pose)"
            )
        X = X_BK_estimated
        return optimal_pivot_pose(X.rotation().matrix(), X.translation())
    if strategy == "GT-OP":
        return optimal_pivot_pose(X_BK_true.rotation().matrix(), X_BK_true.translation())
    if strategy == "NOP":
        return nop_pose(X_BK_true.rotation().matrix(), X_BK_true.translation())
    raise ValueError(
        f"strategy {strategy!r} has no pivot pose (pivot strategies: OP, OP-PE, GT-OP, NOP)"
    )


def sl_line(kp: KinematicPatient, scan_direction: str, margin: float = SL_MARGIN):
    """(start (x, y) in B (m), longest travel (m)) of the SL straight line (III-E): from
    ``margin`` beyond the E-ROI's end the scan leaves from, over the kidney centroid's x,
    for at most the E-ROI's length plus twice the margin plus ``SL_EXTRA_TRAVEL`` (it ends
    once the kidney has left the image)."""
    sign = 1.0 if scan_direction == "+y" else -1.0
    start = start_xy(kp, 0.0, scan_direction) - np.array([0.0, sign * margin])
    return start, float(kp.roi.length_y + 2 * margin + SL_EXTRA_TRAVEL)


def strategy_sweep(
    kp: KinematicPatient,
    imager: Imager,
    strategy: str,
    controller,
    X_BK_estimated: RigidTransform | None = None,
    keep_images: bool = False,
    sl_margin: float = SL_MARGIN,
    pivot_model: PivotModel | None = None,
) -> Sweep:
    """The sweep of one strategy (III-E):

    - ``OP``: pivot at T* of the estimated kidney pose (eq. 20-22);
    - ``OP-PE`` (beyond the paper): OP's pose with the predicted_end pivot
      (:func:`predicted_end_sweep`; needs ``pivot_model``, :func:`pivot_model_for`);
    - ``GT-OP``: pivot at T* of the true kidney pose;
    - ``NOP``: pivot with the array along the true kidney's y-axis at the projected true
      centroid (the in-vivo NOP was expert-placed, so ground truth here too);
    - ``SL``: transverse straight line (exploration controller, eq. 17) from ``sl_margin``
      beyond the E-ROI's superior end until the kidney has left the image (ER 100%).
    """
    c = controller
    if strategy == "SL":
        start, travel = sl_line(kp, c.scan_direction, sl_margin)
        sweep = explore(
            kp,
            imager,
            c,
            exploration_ratio=1.0,
            travel=travel,
            start=start,
            keep_images=keep_images,
        )
        sweep.kind = "line"
        return sweep
    if strategy not in STRATEGIES:
        raise ValueError(f"strategy: expected one of {', '.join(STRATEGIES)}, got {strategy!r}")
    R, p = strategy_pivot_pose(strategy, kp.X_BK_true, X_BK_estimated)
    if strategy == "OP-PE":
        if pivot_model is None or len(pivot_model.points_K) == 0:
            raise ValueError(
                "strategy OP-PE: needs pivot_model (the registration "
                "template and fan, pivot_model_for)"
            )
        return predicted_end_sweep(
            kp, imager, R, p[:2], X_BK_estimated, pivot_model, c, keep_images=keep_images
        )
    return pivot_sweep(
        kp,
        imager,
        R,
        p[:2],
        pivot_rate=c.pivot_rate,
        max_tilt=c.max_pivot_tilt,
        keep_images=keep_images,
    )


# ---------------------------------------------------------------------------- localization
@dataclasses.dataclass
class Localization:
    X_BK: RigidTransform
    n_points: int
    compute_s: float
    result: object | None  # IcpResult, None for the heuristic fallback
    note: str = ""


def heuristic_pose(kp: KinematicPatient, p_xy, depth: float = 0.09) -> RigidTransform:
    """Initial alignment alone (ER 0, III-C): heuristic rotation, centroid ``depth`` below
    the skin at the probe's (x, y)."""
    R0 = heuristic_initial_rotation(kp.superior_B, kp.lateral_B)
    x, y = float(p_xy[0]), float(p_xy[1])
    return RigidTransform(R0, [x, y, kp.skin(x, y) - depth])


def localize_cloud(
    kp: KinematicPatient, P_local_B: np.ndarray, template, config, fallback_xy, min_points: int = 50
) -> Localization:
    """T_k^b from the explored cloud (II-F, ``localize``), or the heuristic initial alignment
    at ``fallback_xy`` when fewer than ``min_points`` points were explored."""
    import time

    P = np.asarray(P_local_B, float).reshape(-1, 3)
    if len(P) < min_points:
        return Localization(
            heuristic_pose(kp, fallback_xy),
            len(P),
            0.0,
            None,
            f"only {len(P)} boundary points: initial alignment only",
        )
    t = time.perf_counter()
    # As the scan does: a template of the other side's kidneys is mirrored.
    template = template.for_side(kp.patient.side)
    result = localize(P, template, config, kp.superior_B, kp.lateral_B)
    return Localization(result.X_BK, len(P), time.perf_counter() - t, result)


# ---------------------------------------------------------------------------- metrics
def sweep_curves(
    kp: KinematicPatient, sweep: Sweep, geometry: ProbeGeometry, image_depth: float | None = None
) -> dict:
    """n, cumulative eps (m, eq. 24) and V (eq. 25) frame by frame of ``sweep`` (use
    ``sweep.pole_to_pole()`` for the seed's curves). Keys: n (1..N), eps (N,), V (N,),
    n_frames, eps_total, V_final."""
    L = geometry.depth if image_depth is None else image_depth
    poses = sweep.poses
    if not poses:
        return {
            "n": np.zeros(0, int),
            "eps": np.zeros(0),
            "V": np.zeros(0),
            "n_frames": 0,
            "eps_total": 0.0,
            "V_final": 0.0,
        }
    acc = CoverageAccumulator(
        kp.kidney_points_B, kp.voxel_volume, geometry.in_fan, geometry.elevation_width
    )
    V = np.asarray([acc.add_frame(X) for X in poses])
    eps = np.concatenate([[0.0], np.cumsum(window_steps(poses, L))])
    return {
        "n": np.arange(1, len(poses) + 1),
        "eps": eps,
        "V": V,
        "n_frames": len(poses),
        "eps_total": float(eps[-1]),
        "V_final": float(V[-1]),
    }
