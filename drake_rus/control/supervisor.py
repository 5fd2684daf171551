"""The scan supervisor: the motion laws of the three scan phases, exploration (eq. 17),
optimal pivot pose (eq. 20-22) and the Rodrigues pivot sweep (eq. 23), and the state machine
over them. :class:`Phase` is the project's one list of scan phases.

Beyond the seed's one workflow, the controller config may give the pivot pose
(``pivot_pose``: no exploration or localization, :func:`given_pivot_pose`) or ask for the
seed's straight-line baseline (``sweep: line``: eq. 17 over the whole kidney, no pivot).

All vectors are expressed in the robot base frame B (z up; the patient lies along y).
"""

from __future__ import annotations

import dataclasses
import enum
import math

import numpy as np

from drake_rus.control.laws import (
    angle_between,
    cross3,
    pivot_end_angles,
    template_section_area,
)


# ----------------------------------------------------------------------------- eq. 17
def exploration_update(
    P_des_xy, c_msk: float, x_p, v_scan_y: float, K_p7: float, dt: float
) -> np.ndarray:
    """Desired tip (x, y) one control interval later during exploration (eq. 17).

    P_x(t+dt) = P_x(t) + (delta_msk dt)(x_p . [1, 0, 0]), delta_msk = K_p7 (c_msk - 0.5);
    P_y(t+dt) = P_y(t) + v_scan dt. ``c_msk`` in [0, 1] is the horizontal mask centroid
    (0 at the image column of -x_P, 1 at +x_P); ``x_p`` = R_BP [1, 0, 0] is the probe x-axis
    in B; ``v_scan_y`` (m/s) is signed along base y. A NaN centroid (no mask) gives no x
    correction.
    """
    P = np.asarray(P_des_xy, dtype=float).reshape(2).copy()
    x_p = np.asarray(x_p, dtype=float).reshape(3)
    if math.isfinite(c_msk):
        delta_msk = K_p7 * (c_msk - 0.5)
        P[0] += delta_msk * dt * float(x_p[0])
    P[1] += v_scan_y * dt
    return P


# ----------------------------------------------------------------------------- eq. 20-22
def optimal_pivot_pose(R_BK, p_BK):
    """Optimal pivoting pose T* = [r1 r2 r3 p*] (eq. 20-22) from the kidney pose T_k^b.

    r3* = [0, 0, -1] (probe pointing down); r1* = unit(x_k - (x_k . r3*) r3*) with
    x_k = R_BK [1, 0, 0] (eq. 21); p* = t_k^b. The seed writes r2* = unit(r1* x r3*)
    (eq. 22), which makes [r1 r2 r3] a reflection (det = -1); a rotation needs
    r2* = r3* x r1*, used here (the same line, opposite sign). If the kidney's long axis
    is vertical (r1* undefined) the base x-axis is projected instead.

    Returns (R_BPstar (3x3), p_star (3,)).
    """
    R_BK = np.asarray(R_BK, dtype=float)
    r3 = np.array([0.0, 0.0, -1.0])
    x_k = R_BK[:, 0]
    r1 = x_k - float(x_k @ r3) * r3
    n = np.linalg.norm(r1)
    if n < 1e-6:
        r1 = np.array([1.0, 0.0, 0.0])
        n = 1.0
    r1 = r1 / n
    r2 = cross3(r3, r1)
    r2 /= np.linalg.norm(r2)
    return np.column_stack([r1, r2, r3]), np.asarray(p_BK, dtype=float).reshape(3).copy()


def _finite_number(v) -> bool:
    """``v`` is a finite real number (not a string, None or bool)."""
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        return False
    return math.isfinite(float(v))


def given_pivot_pose(pose, z: float = math.nan):
    """The pivot pose of a given ``controller.pivot_pose`` [x, y, yaw] (m, m, rad), shaped
    like eq. 20-22's T*: r3 = [0, 0, -1] (probe pointing down), r1 = [cos yaw, sin yaw, 0]
    (the array), r2 = r3 x r1 (a rotation, as :func:`optimal_pivot_pose`), the tip over
    (x, y) at height ``z`` (m; informative only: force control sets the tip's height).

    Returns (R_BPstar (3x3), p_star (3,)). Raises ValueError naming controller.pivot_pose
    unless ``pose`` holds three finite numbers."""
    values = list(pose) if pose is not None else []
    if len(values) != 3 or not all(_finite_number(v) for v in values):
        raise ValueError(
            f"controller.pivot_pose: expected [] or [x (m), y (m), yaw (rad)], "
            f"three finite numbers, got {values}"
        )
    x, y, yaw = (float(v) for v in values)
    r3 = np.array([0.0, 0.0, -1.0])
    r1 = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    return np.column_stack([r1, cross3(r3, r1), r3]), np.array([x, y, float(z)])


def pivot_pose_as_given(R_BPstar, p_star) -> list[float]:
    """[x, y, yaw] (m, m, rad) of a pivot pose shaped like T* (probe pointing down, array
    horizontal): the ``controller.pivot_pose`` that :func:`given_pivot_pose` turns back
    into it."""
    R = np.asarray(R_BPstar, dtype=float)
    p = np.asarray(p_star, dtype=float).reshape(3)
    return [float(p[0]), float(p[1]), float(math.atan2(R[1, 0], R[0, 0]))]


# ----------------------------------------------------------------------------- eq. 23
def rodrigues_pivot_update(a_des, o_des, dtheta: float) -> np.ndarray:
    """Approach vector rotated by dtheta (rad) about o_des (eq. 23).

    a(t+dt) = a cos(dtheta) + (o x a) sin(dtheta); the (a . o) term of Rodrigues' formula
    vanishes because a is kept orthogonal to o. The result is re-orthogonalised against o
    and normalised so rounding does not accumulate over thousands of steps.
    """
    a = np.asarray(a_des, dtype=float).reshape(3)
    o = np.asarray(o_des, dtype=float).reshape(3)
    a_new = a * math.cos(dtheta) + cross3(o, a) * math.sin(dtheta)
    o_hat = o / np.linalg.norm(o)
    a_new = a_new - float(a_new @ o_hat) * o_hat
    return a_new / np.linalg.norm(a_new)


def pivot_rate_vector(a_des, o_des, direction: float, rate: float) -> np.ndarray:
    """d a_des/dt of the pivot sweep (rad/s): direction * rate * (o x a), for eq. 2's K_p11."""
    return direction * rate * cross3(np.asarray(o_des, float), np.asarray(a_des, float))


def transverse_orientation(a, o_curr) -> np.ndarray:
    """Orientation vector across the patient: the base x-axis made orthogonal to a, with the
    sign closest to the current o (the smaller rotation)."""
    a = np.asarray(a, dtype=float)
    x = np.array([1.0, 0.0, 0.0])
    o = x - float(x @ a) * a
    n = np.linalg.norm(o)
    if n < 1e-6:  # a along x: keep the current orientation
        return np.asarray(o_curr, dtype=float).copy()
    o /= n
    return o if float(o @ np.asarray(o_curr)) >= 0 else -o


# ----------------------------------------------------------------------------- supervisor
class Phase(enum.IntEnum):
    """Scan phases. APPROACH (press until contact) precedes the seed's EXPLORE."""

    APPROACH = 0
    EXPLORE = 1
    LOCALIZE = 2
    TRANSIT = 3
    PIVOT = 4
    DONE = 5
    ABORT = 6


@dataclasses.dataclass
class PivotModel:
    """What the ``predicted_end`` pivot strategy needs to predict where the kidney leaves the
    image: the registration template's points in K (m) and the probe's fan (m, rad)."""

    points_K: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))
    probe_radius: float = 0.05
    half_angle: float = math.radians(20.0)
    depth: float = 0.15
    slab_half_width: float = 0.005
    # A predicted section smaller than this (m^2) puts the kidney out of view: the
    # segmenter's own visibility threshold (imaging.min_kidney_area).
    min_section_area: float = 1.0e-4

    def __deepcopy__(self, memo):  # never changed in place: clones may share it
        return self


@dataclasses.dataclass
class SupervisorState:
    """Everything the ScanSupervisor remembers between control periods."""

    phase: Phase = Phase.APPROACH
    a_des: np.ndarray = dataclasses.field(default_factory=lambda: np.array([0.0, 0.0, -1.0]))
    o_des: np.ndarray = dataclasses.field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))
    a_des_dot: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    P_des: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(2))
    F_des: float = 0.0
    initialised: bool = False
    phase_start: float = 0.0
    travel: float = 0.0  # exploration travel along y (m)
    invisible_since: float = math.nan  # time the kidney was last seen to disappear
    pivot_direction: float = 1.0
    pivot_speed: float = 0.0  # signed current tilt rate (rad/s), ramped
    expect_invisible: bool = False  # after a pivot leg ends, until the kidney is seen again
    # The registered template's predicted section (m^2) in the current image during PIVOT
    # (NaN: no prediction), and at the pivot's start (the reference of its share).
    section_area: float = math.nan
    section_reference: float = math.nan
    # PIVOT: the kidney's absence is expected now (absence_expected), not a loss.
    kidney_absence_expected: bool = False
    lag_since: float = math.nan  # since when the probe lags the pivot (pivot_follow_limit)
    pivot_angle: float = 0.0  # tilt of a_des from r3* about o_des (rad), signed
    pivot_legs_done: int = 0
    pivot_limits: tuple = ()  # tilt angles (rad) where each leg ended
    # Why each end of the sweep was declared, in order: per pivot leg (one per pivot_limits
    # entry) "kidney_left" (the segmentation lost the kidney for visibility_debounce) or
    # "tilt_cap" (max_pivot_tilt reached first); a line sweep's end "kidney_left" or
    # "max_travel" (line_sweep_max_travel). The scan's verdict reads them.
    sweep_end_causes: tuple = ()
    # predicted_end strategy: (theta_plus, theta_minus) predicted ends (rad), the pre-tilt
    # stage in TRANSIT (0 none/not yet, 1 tilting to the target, 2 at it: checking the
    # kidney is out of the image) and side (+-1) and target tilt (rad).
    pivot_ends: tuple = ()
    # The slide at the tilt cap (controller.cap_slide_max): stage 0 none, 1 sliding out
    # (the kidney still in the image at the cap), 2 sliding back to p* after the first
    # leg; the unit direction (x, y) in B, the slide so far, its limit and the template's
    # predicted slide (m; 0 without one), when stage 2
    # brought P_des back to p* (s), and each slide's (leg, distance m) so far.
    cap_slide: int = 0
    cap_slide_dir: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(2))
    cap_slide_travel: float = 0.0
    cap_slide_limit: float = 0.0
    cap_slide_predicted: float = 0.0
    cap_slide_back_at: float = math.nan
    cap_slides: tuple = ()
    pretilt_stage: int = 0
    pretilt_side: float = 1.0
    pretilt_target: float = 0.0
    # sweep line: the kidney has not been in the image yet (its absence neither ends the
    # sweep nor is a segmentation loss); it has been, since visible_since, without a gap.
    awaiting_kidney: bool = False
    visible_since: float = math.nan
    # EXPLORE: the kidney has been in the image (for visibility_debounce) while the probe
    # could move: only then can it "leave the image" (a breath-hold may carry it out of
    # view before the sweep starts).
    explore_seen: bool = False
    explore_seen_travel: float = 0.0  # the sweep's travel (m) when the kidney came into view
    paused: bool = False  # exploration/pivot motion held (outside a breath-hold)
    paused_time: float = 0.0  # total time (s) motion was held
    # Re-localization after the kidney moved (``_kidney_moved``): how many so far, the
    # localization round (the localizer registers anew when it changes), and the
    # re-exploration's first stage (holding still, turning the probe transverse; the
    # exploration cloud is cleared meanwhile).
    relocalizations: int = 0
    localization_round: int = 0
    reorienting: bool = False
    # Its second stage (``_retreat``): sweeping back against the scan direction until the
    # kidney has left the image, so the new sweep starts behind the kidney as the first did.
    retreating: bool = False
    # The re-exploration's turn (``_reorient``): the smallest angle to the target so far
    # (rad), since when (s), and whether the array's target has been flipped to the other
    # transverse direction (the turn stalled short of the first: a joint at its limit).
    reorient_best: float = math.inf
    reorient_best_since: float = math.nan
    reorient_flipped: bool = False
    # The first exploration's array direction o_des (unit, B; set by ``_start``): a
    # re-exploration turns its array back to this side of the transverse plane, the turn
    # the wrist has already made (:func:`reexploration_array`).
    o_explore: np.ndarray | None = None
    # EXPLORE: since when (s) the tip has been more than explore_follow_bound from the
    # sweep's set-point (NaN: it follows).
    explore_lag_since: float = math.nan
    # The second look (controller.second_look): the pivot's end awaits the pivot-view check
    # (``reviewing``, since ``review_since`` s); the current exploration sweeps the whole
    # kidney (:func:`whole_kidney_target`), not ER x L; the scan's one second look has been
    # taken, and why ("" none).
    reviewing: bool = False
    review_since: float = math.nan
    whole_kidney: bool = False
    second_look_used: bool = False
    second_look_reason: str = ""
    a_star: np.ndarray = dataclasses.field(default_factory=lambda: np.array([0.0, 0.0, -1.0]))
    approach_origin: np.ndarray = dataclasses.field(default_factory=lambda: np.full(3, math.nan))
    contact_since: float = math.nan  # APPROACH: when the force last reached contact
    p_star: np.ndarray = dataclasses.field(default_factory=lambda: np.full(3, math.nan))
    reason: str = ""
    events: tuple = ()  # (time, phase name, message) transitions

    # Drake clones abstract state values with deepcopy on every update; states are never
    # mutated in place (supervisor_step works on a copy), so clones may share them.
    def __deepcopy__(self, memo):
        return self

    def __copy__(self):
        return self

    def copy(self) -> "SupervisorState":
        """A copy whose arrays are the supervisor's own (tuples and scalars are immutable).
        Field by field, not ``dataclasses.replace``: this runs every control period, and
        replace's keyword round trip costs four times as much."""
        new = object.__new__(SupervisorState)
        fields = dict(self.__dict__)
        for name in _ARRAY_FIELDS:
            fields[name] = fields[name].copy()
        new.__dict__.update(fields)
        return new


# SupervisorState's array fields (copied by SupervisorState.copy; the rest are immutable).
_ARRAY_FIELDS = tuple(
    f.name
    for f in dataclasses.fields(SupervisorState)
    if isinstance(getattr(SupervisorState(), f.name), np.ndarray)
)


@dataclasses.dataclass
class SupervisorInputs:
    """What the supervisor reads each period (base frame B, SI units)."""

    t: float
    R_BP: np.ndarray
    p_BP: np.ndarray
    F_z: float  # contact force along a (N), positive pressing
    kidney_visible: bool
    c_msk: float  # horizontal mask centroid in [0, 1] (NaN when no mask)
    R_BK: np.ndarray | None = None  # kidney pose estimate (localizer or ground truth)
    p_BK: np.ndarray | None = None
    localization_ready: bool = True
    safety_stopped: bool = False  # the safety layer has stopped the robot
    localization_error: str = ""  # why the localizer could not give a pose ("" = none)
    exploration_sufficient: bool = False  # adaptive exploration: the estimate has settled
    # Respiration gating: False outside breath-holds; exploration travel and the pivot tilt
    # then hold still (force control keeps contact) until the next hold.
    motion_allowed: bool = True
    # The kidney no longer lies where localization put it ("" = consistent): TRANSIT and
    # PIVOT abort, since the pivot would image the wrong place.
    tracking_error: str = ""
    # The localizer's estimate of the kidney's length along its long axis (m; NaN until
    # known): with ``exploration_length: estimated`` EXPLORE ends at ER times it.
    kidney_length_estimate: float = math.nan
    # The template and fan for the predicted_end pivot strategy (None: two_leg).
    pivot_model: PivotModel | None = None
    # Why the breath-hold protocol cannot go on ("" = it can): the scan aborts.
    breathing_error: str = ""
    # The pivot-view check (localization.pivot_view, run beside the loop by the kidney
    # tracking monitor): (time (s) of the newest frame it covered, why the pivot's view
    # contradicts the registration, "" = it does not); None: no check connected.
    pivot_view: tuple | None = None


def _goto(s: SupervisorState, phase: Phase, t: float, message: str) -> SupervisorState:
    s.phase = phase
    s.phase_start = t
    s.invisible_since = math.nan
    s.explore_seen = False
    s.paused = False  # a pause belongs to the phase that held still
    s.events = s.events + ((t, phase.name, message),)
    return s


def _update_visibility(s: SupervisorState, u: SupervisorInputs, debounce: float) -> bool:
    """Tracks when the kidney vanished; True once it has been invisible for ``debounce``."""
    if u.kidney_visible:
        s.invisible_since = math.nan
        return False
    if math.isnan(s.invisible_since):
        s.invisible_since = u.t
    return u.t - s.invisible_since >= debounce - 1e-9


def _ramp(x: float, target: float, step: float) -> float:
    return float(np.clip(target, x - step, x + step))


def _pivot_advance(s: SupervisorState, cfg, dt: float) -> None:
    """Rotates a_des about o_des by pivot_speed dt (eq. 23), within +-max_pivot_tilt."""
    new_angle = float(
        np.clip(s.pivot_angle + s.pivot_speed * dt, -cfg.max_pivot_tilt, cfg.max_pivot_tilt)
    )
    dtheta = new_angle - s.pivot_angle
    s.a_des = rodrigues_pivot_update(s.a_des, s.o_des, dtheta)
    s.pivot_angle = new_angle
    s.a_des_dot = pivot_rate_vector(s.a_des, s.o_des, 1.0, dtheta / dt)


def absence_expected(
    after_leg_end: bool,
    section_area: float,
    section_reference: float,
    min_area: float,
    well_in_view: float,
) -> bool:
    """Whether the kidney's absence from the image is expected, not a loss of it.

    ``after_leg_end``: a pivot leg has ended (the kidney left the image) and the kidney has
    not been seen since. ``section_area`` (m^2): the registered template's predicted section
    in the current image, ``section_reference`` (m^2) that at the pivot's start (NaN: no
    registered template, e.g. a given pivot pose). With a prediction, absence is expected
    where the template puts the kidney out of view (section below ``min_area``: past a
    pivot end), and after a leg's end until the section is back to ``well_in_view`` of the
    reference (the probe has turned back over the kidney: not finding it there is a loss;
    until then the template, one length for every kidney, may overhang a shorter kidney's
    pole). Without a prediction: after a leg's end until the kidney is seen again."""
    if not (math.isfinite(section_area) and math.isfinite(section_reference)):
        return after_leg_end
    if section_area < min_area:
        return True
    return after_leg_end and section_area < well_in_view * section_reference


def segmentation_required(s: SupervisorState) -> bool:
    """Whether the kidney must be visible now (EXPLORE; PIVOT except where its absence is
    expected, :func:`absence_expected`, updated every PIVOT period); drives the safety
    layer's watchdog."""
    if s.paused or s.reorienting or s.retreating or s.reviewing:
        # Holding still outside a breath-hold: the kidney may drift away; a re-exploration
        # turning or backing out of the kidney: its leaving the image is the aim; the
        # pivot's end awaiting the pivot-view check: the sweep saw it leave.
        return False
    if s.phase == Phase.EXPLORE:
        return not s.awaiting_kidney  # a line sweep before the kidney first came into view
    return s.phase == Phase.PIVOT and not s.kidney_absence_expected


def section_in_view(model: PivotModel | None, u: SupervisorInputs, R, p) -> float:
    """The registered template's predicted section (m^2) in the image of the probe at (R,
    p) (:func:`~drake_rus.control.laws.template_section_area` with the pivot model's fan);
    NaN without a pivot model or a finite kidney pose."""
    if (
        model is None
        or len(model.points_K) == 0
        or u.R_BK is None
        or u.p_BK is None
        or not (np.all(np.isfinite(u.R_BK)) and np.all(np.isfinite(u.p_BK)))
    ):
        return math.nan
    return template_section_area(
        u.R_BK,
        u.p_BK,
        model.points_K,
        R,
        p,
        probe_radius=model.probe_radius,
        half_angle=model.half_angle,
        depth=model.depth,
        slab_half_width=model.slab_half_width,
    )


def _hold_motion(s: SupervisorState, dt: float) -> SupervisorState:
    """Respiration gating: no exploration travel or pivot leg ending while paused."""
    s.paused = True
    s.paused_time += dt
    s.invisible_since = math.nan
    return s


def _hold_pivot(s: SupervisorState, cfg, dt: float) -> SupervisorState:
    """Outside a breath-hold during the pivot: the tilt rate ramps down to zero (no jump of
    the commanded angular velocity) and the pivot holds still."""
    s.pivot_speed = _ramp(s.pivot_speed, 0.0, cfg.pivot_acceleration * dt)
    _pivot_advance(s, cfg, dt)
    return _hold_motion(s, dt)


def given_start_xy(start_xy) -> np.ndarray | None:
    """The tip (x, y) (m, base frame) APPROACH lands at from ``controller.start_xy``: None
    for [] (straight down from the start pose). Raises ValueError naming
    controller.start_xy unless it is [] or two finite numbers."""
    values = list(start_xy) if start_xy is not None else []
    if not values:
        return None
    if len(values) != 2 or not all(_finite_number(v) for v in values):
        raise ValueError(
            f"controller.start_xy: expected [] or [x (m), y (m)], two finite numbers, got {values}"
        )
    return np.array([float(v) for v in values])


def _start(s: SupervisorState, u: SupervisorInputs, R, p, cfg) -> None:
    """First period: hold the current orientation (or turn o transverse) and tip position,
    or head for ``start_xy``; press to the desired force."""
    s.a_des = R[:, 2].copy()
    s.o_des = R[:, 0].copy()
    if cfg.explore_orientation == "transverse":
        s.o_des = transverse_orientation(s.a_des, s.o_des)
    s.o_explore = s.o_des.copy()
    start_xy = given_start_xy(cfg.start_xy)
    s.P_des = p[:2].copy() if start_xy is None else start_xy
    s.F_des = float(cfg.desired_force)
    s.awaiting_kidney = cfg.sweep == "line"
    s.approach_origin = p.copy()
    s.initialised = True
    s.phase_start = u.t
    s.events = s.events + ((u.t, s.phase.name, "start"),)


def _approach(s, u, R, p, cfg, dt):
    """Press to F_des over start_xy; EXPLORE once the force has stayed at contact_fraction
    F_des or more for contact_dwell;
    ABORT ("no contact") after approach_max_travel along the approach vector or
    approach_timeout without it."""
    at_start = float(np.linalg.norm(p[:2] - s.P_des)) <= cfg.transit_position_tolerance
    if u.F_z >= cfg.contact_fraction * cfg.desired_force and at_start:
        if math.isnan(s.contact_since):
            s.contact_since = u.t
        if u.t - s.contact_since >= cfg.contact_dwell - 1e-9:
            s.P_des = p[:2].copy()
            if cfg.pivot_pose:
                R_star, p_star = given_pivot_pose(cfg.pivot_pose, p[2])
                return _to_transit(
                    s,
                    u.t,
                    R_star,
                    p_star,
                    f"contact at {u.F_z:.2f} N; given pivot pose "
                    f"(controller.pivot_pose): p* = ({p_star[0]:.4f}, "
                    f"{p_star[1]:.4f}) m, array at "
                    f"{math.degrees(cfg.pivot_pose[2]):.1f} deg from base x",
                )
            return _goto(s, Phase.EXPLORE, u.t, f"contact at {u.F_z:.2f} N")
    else:
        s.contact_since = math.nan
    travel = float((p - s.approach_origin) @ s.a_des)
    if travel > cfg.approach_max_travel:
        s.reason = (
            f"no contact: the probe moved {travel * 1e3:.0f} mm along its beam "
            f"without reaching {cfg.contact_fraction * cfg.desired_force:.1f} N"
        )
        return _goto(s, Phase.ABORT, u.t, s.reason)
    if u.t - s.phase_start > cfg.approach_timeout:
        s.reason = f"no contact after {cfg.approach_timeout:.0f} s of APPROACH ({u.F_z:.2f} N)"
        return _goto(s, Phase.ABORT, u.t, s.reason)
    return s


def exploration_kidney_length(cfg, kidney_length_estimate: float = math.nan) -> float:
    """The kidney length L (m) the exploration plans with: the reference length L_m
    (``kidney_length``) with ``exploration_length: fixed`` or while no estimate exists
    (NaN); with ``estimated`` the patient's estimated length, clipped to [L_m / f, f L_m]
    (f = ``exploration_length_factor``). An unknown length (+inf: the latest length fit
    failed its checks) is the longest allowed, f L_m."""
    L = float(cfg.kidney_length)
    estimate = float(kidney_length_estimate)
    if cfg.exploration_length == "estimated" and not math.isnan(estimate) and estimate > 0:
        f = float(cfg.exploration_length_factor)
        L = min(max(estimate, L / f), f * L)
    return L


def exploration_target(cfg, kidney_length_estimate: float = math.nan) -> float:
    """Exploration travel (m) after which EXPLORE ends: ER x L (section III-C), L from
    :func:`exploration_kidney_length`, so the travel never exceeds f ER L_m."""
    return cfg.exploration_ratio * exploration_kidney_length(cfg, kidney_length_estimate)


def whole_kidney_target(cfg, seen_travel: float) -> float:
    """Exploration travel (m) after which a whole-kidney exploration (the second look) ends
    if the kidney has not left the image by then: the longest kidney length allowed,
    ``exploration_length_factor`` x ``kidney_length`` (as
    :func:`exploration_kidney_length` bounds an unknown length), past ``seen_travel``, the
    travel where the kidney came into view (0 when it was in view where the sweep began)."""
    return float(seen_travel) + cfg.exploration_length_factor * cfg.kidney_length


def review_wanted(cfg, used: bool, relocalizations: int, pivot_view) -> bool:
    """Whether the pivot's end awaits the pivot-view check before DONE: ``second_look``
    on, no given ``pivot_pose`` (no registration to judge), the scan's one second look not
    ``used``, a re-localization still allowed
    (``relocalizations`` < ``max_relocalizations``) and a check connected (``pivot_view``
    not None)."""
    return (
        bool(cfg.second_look)
        and not cfg.pivot_pose
        and not used
        and relocalizations < cfg.max_relocalizations
        and pivot_view is not None
    )


# The pivot-view check runs beside the loop; past this wait (s) the scan says DONE and
# leaves the pivot's view to the verdict.
REVIEW_TIMEOUT = 5.0


def review_outcome(pivot_view, review_since: float, t: float) -> str:
    """What the pivot's end does next, from the check's answer ``pivot_view`` ((time of
    the newest frame covered s, error str)) awaited since ``review_since`` (s), at time
    ``t``: "second_look" (a check covering the whole pivot found its view contradicting
    the registration), "done" (it found none, or none came within REVIEW_TIMEOUT s) or
    "wait"."""
    covered, error = pivot_view if pivot_view is not None else (math.nan, "")
    if math.isfinite(covered) and covered >= review_since - 1e-9:
        return "second_look" if error else "done"
    return "done" if t - review_since >= REVIEW_TIMEOUT - 1e-9 else "wait"


def _advance_exploration(s, u, R, cfg, dt, target: float, backwards: bool = False):
    """One control period of eq. 17 towards ``target`` m of travel along the scan
    direction (against it with ``backwards``; the x correction from the mask centroid while
    the kidney is visible)."""
    sign = 1.0 if cfg.scan_direction == "+y" else -1.0
    if backwards:
        sign = -sign
    step = min(cfg.scan_speed * dt, target - s.travel)
    c = u.c_msk if u.kidney_visible else math.nan
    s.P_des = exploration_update(s.P_des, c, R[:, 0], sign * step / dt, cfg.K_p7, dt)
    s.travel += step
    return s


def _came_into_view(s: SupervisorState, u: SupervisorInputs, debounce: float) -> bool:
    """True once the kidney has been in the image for ``debounce`` without a gap (the
    mirror of :func:`_update_visibility`: a glimpse of a pole's edge does not count)."""
    if not u.kidney_visible:
        s.visible_since = math.nan
        return False
    if math.isnan(s.visible_since):
        s.visible_since = u.t
    return u.t - s.visible_since >= debounce - 1e-9


def _line_sweep(s, u, R, p, cfg, dt):
    """``sweep: line`` (the seed's SL): eq. 17 from wherever APPROACH landed; the kidney
    comes into view once it has been in the image for visibility_debounce; once it has,
    and has then left the image for visibility_debounce: DONE. At line_sweep_max_travel it
    ends too: DONE if the kidney came into view, else ABORT."""
    if s.awaiting_kidney and _came_into_view(s, u, cfg.visibility_debounce):
        s.awaiting_kidney = False
    left = (
        not s.awaiting_kidney
        and u.motion_allowed
        and _update_visibility(s, u, cfg.visibility_debounce)
    )
    if left:
        s.P_des = p[:2].copy()
        s.sweep_end_causes = ("kidney_left",)
        return _goto(
            s,
            Phase.DONE,
            u.t,
            f"line sweep complete: the kidney left the image after {s.travel * 1e3:.1f} mm",
        )
    if s.travel >= cfg.line_sweep_max_travel - 1e-12:
        s.P_des = p[:2].copy()
        if s.awaiting_kidney:
            s.reason = (
                f"line sweep: the kidney never came into view over "
                f"{s.travel * 1e3:.1f} mm (line_sweep_max_travel)"
            )
            return _goto(s, Phase.ABORT, u.t, s.reason)
        s.sweep_end_causes = ("max_travel",)
        return _goto(
            s,
            Phase.DONE,
            u.t,
            f"line sweep ended at line_sweep_max_travel "
            f"{s.travel * 1e3:.1f} mm, the kidney still seen",
        )
    if not u.motion_allowed:
        return _hold_motion(s, dt)
    s.paused = False
    return _advance_exploration(s, u, R, cfg, dt, cfg.line_sweep_max_travel)


# A normal sweep's tip lags its set-point by about 0.7 s of travel; explore_follow_bound
# allows four times that at any scan speed (s).
EXPLORE_LAG_TIME = 3.0


def lagging_since(since: float, t: float, lagging: bool) -> float:
    """Since when (s) the probe has lagged its command without a break, after a control
    period at ``t`` that ``lagging`` or not: NaN while it follows. The follow checks of
    EXPLORE and PIVOT stop the scan once ``t`` minus this reaches their time."""
    if not lagging:
        return math.nan
    return t if math.isnan(since) else since


def explore_follow_bound(cfg) -> float:
    """How far (m) the tip may lie from the sweep's x-y set-point before the sweep counts as
    not followed: ``explore_follow_limit``, or EXPLORE_LAG_TIME x ``scan_speed`` if larger."""
    return max(float(cfg.explore_follow_limit), EXPLORE_LAG_TIME * float(cfg.scan_speed))


def explore_not_followed(s, u, p, cfg) -> str:
    """ "" while the probe follows the sweep; else why not: the tip (x, y) ``p`` has been
    more than :func:`explore_follow_bound` from the set-point ``s.P_des`` for
    ``explore_follow_time`` s (updates ``s.explore_lag_since``). Not judged while the
    probe turns in place before a re-exploration or motion is held (breath-holds)."""
    lag = float(np.linalg.norm(np.asarray(p, dtype=float)[:2] - s.P_des))
    bound = explore_follow_bound(cfg)
    judged = u.motion_allowed and not s.reorienting
    s.explore_lag_since = lagging_since(s.explore_lag_since, u.t, judged and lag > bound)
    if not u.t - s.explore_lag_since >= cfg.explore_follow_time - 1e-9:  # also while NaN
        return ""
    return (
        f"the probe does not follow the sweep: its tip is {lag * 1e3:.1f} mm from the "
        f"set-point after {u.t - s.explore_lag_since:.2f} s (limit {bound * 1e3:.1f} mm; "
        "a joint at its limit?)"
    )


def _explore(s, u, R, p, cfg, dt):
    """Constant orientation, eq. 17, until ER L of travel (``exploration_target``: L_m, or
    the patient's estimated kidney length), the kidney has left the image (having been in it
    while the probe could move) or (adaptive) the pose estimate has settled; then LOCALIZE.
    With ``sweep: line``: :func:`_line_sweep`. ABORT when the probe does not follow the
    sweep (:func:`explore_not_followed`)."""
    why = explore_not_followed(s, u, p, cfg)
    if why:
        s.reason = why
        s.P_des = p[:2].copy()
        return _goto(s, Phase.ABORT, u.t, s.reason)
    if cfg.sweep == "line":
        return _line_sweep(s, u, R, p, cfg, dt)
    if s.reorienting:
        return _reorient(s, u, R, p, cfg, dt)
    if s.retreating:
        return _retreat(s, u, R, p, cfg, dt)
    if u.motion_allowed and not s.explore_seen:
        # In view where the sweep starts, or later for visibility_debounce without a gap (a
        # glimpse of an edge passing by does not count).
        s.explore_seen = (u.kidney_visible and s.travel == 0.0) or _came_into_view(
            s, u, cfg.visibility_debounce
        )
        s.explore_seen_travel = s.travel
        if s.explore_seen:
            s.awaiting_kidney = False  # a re-exploration from behind the kidney: now in view
    left = u.motion_allowed and s.explore_seen and _update_visibility(s, u, cfg.visibility_debounce)
    if left and s.travel - s.explore_seen_travel < cfg.explore_min_seen_travel:
        # Seen over too little of the sweep to localize: forget it and sweep on.
        s.explore_seen = False
        s.invisible_since = math.nan
        s.visible_since = math.nan
        left = False
    if s.whole_kidney:
        target = whole_kidney_target(cfg, s.explore_seen_travel if s.explore_seen else 0.0)
    else:
        target = exploration_target(cfg, u.kidney_length_estimate)
    if s.travel >= target - 1e-12:
        s.P_des = p[:2].copy()
        how = ""
        estimated = cfg.exploration_length == "estimated"
        if s.whole_kidney:
            how = (
                f" (second look: the longest kidney length "
                f"{cfg.exploration_length_factor * cfg.kidney_length * 1e3:.0f} mm past where "
                f"it came into view, the kidney still in the image)"
            )
        elif estimated and math.isinf(u.kidney_length_estimate):
            longest = cfg.exploration_length_factor * cfg.kidney_length
            how = (
                f" (ER {cfg.exploration_ratio:g} x the longest kidney length "
                f"{longest * 1e3:.0f} mm: the latest length fit failed its checks)"
            )
        elif estimated and math.isfinite(u.kidney_length_estimate):
            how = (
                f" (ER {cfg.exploration_ratio:g} x the estimated kidney length "
                f"{u.kidney_length_estimate * 1e3:.0f} mm)"
            )
        return _goto(s, Phase.LOCALIZE, u.t, f"explored {s.travel * 1e3:.1f} mm{how}")
    if left:
        s.P_des = p[:2].copy()
        how = " (second look: the whole kidney)" if s.whole_kidney else ""
        return _goto(
            s, Phase.LOCALIZE, u.t, f"kidney left the image after {s.travel * 1e3:.1f} mm{how}"
        )
    if u.exploration_sufficient and not s.whole_kidney:
        s.P_des = p[:2].copy()
        return _goto(
            s,
            Phase.LOCALIZE,
            u.t,
            f"pose estimate settled after {s.travel * 1e3:.1f} mm (adaptive)",
        )
    if not u.motion_allowed:
        return _hold_motion(s, dt)
    s.paused = False
    return _advance_exploration(s, u, R, cfg, dt, target)


def _to_transit(s, t, R_star, p_star, message: str) -> SupervisorState:
    """TRANSIT towards the pivot pose (R_star, p_star): a_des = r3*, o_des = r1*, the tip's
    x-y target p*."""
    s.a_star = R_star[:, 2].copy()
    s.a_des = R_star[:, 2].copy()
    s.o_des = R_star[:, 0].copy()
    s.p_star = np.asarray(p_star, dtype=float).copy()
    s.P_des = s.p_star[:2].copy()
    return _goto(s, Phase.TRANSIT, t, message)


def _localize(s, u, R, p, cfg, dt):
    """Hold (force control only) for localize_hold_time and until the localizer is ready,
    then T* (eq. 20-22) and TRANSIT; ABORT on a localization error or timeout."""
    if u.localization_error:
        s.reason = f"localization failed: {u.localization_error}"
        return _goto(s, Phase.ABORT, u.t, s.reason)
    if u.t - s.phase_start < cfg.localize_hold_time - 1e-9 or not u.localization_ready:
        if u.t - s.phase_start > cfg.localize_timeout:
            s.reason = f"LOCALIZE timeout: no kidney pose after {cfg.localize_timeout:.1f} s"
            return _goto(s, Phase.ABORT, u.t, s.reason)
        return s
    if (
        u.R_BK is None
        or u.p_BK is None
        or not (np.all(np.isfinite(u.R_BK)) and np.all(np.isfinite(u.p_BK)))
    ):
        s.reason = "no finite kidney pose from localization"
        return _goto(s, Phase.ABORT, u.t, s.reason)
    if not u.motion_allowed:
        return s  # the breath-hold protocol: TRANSIT and PIVOT start in a sensed hold
    R_star, p_star = optimal_pivot_pose(u.R_BK, u.p_BK)
    return _to_transit(
        s, u.t, R_star, p_star, f"p* = ({p_star[0]:.4f}, {p_star[1]:.4f}, {p_star[2]:.4f}) m"
    )


def predict_pivot_ends(model: PivotModel, R_BK, p_BK, pivot_point, a0, o, max_tilt: float) -> tuple:
    """(theta_plus, theta_minus) (rad): where the template of ``model`` registered at
    X_BK = (R_BK, p_BK) leaves the image on each side of a pivot about the tip
    ``pivot_point`` turning the approach ``a0`` about the array ``o``, within +-``max_tilt``
    (laws.pivot_end_angles with the model's fan). The one prediction of the
    ``predicted_end`` strategy: the supervisor and the kinematic twin both call it."""
    return pivot_end_angles(
        R_BK,
        p_BK,
        model.points_K,
        pivot_point,
        a0,
        o,
        probe_radius=model.probe_radius,
        half_angle=model.half_angle,
        depth=model.depth,
        slab_half_width=model.slab_half_width,
        max_angle=max_tilt,
    )


def predicted_pivot_ends(
    s: SupervisorState, model: PivotModel, u: SupervisorInputs, p, cfg
) -> tuple:
    """(theta_plus, theta_minus) (rad): where the registered template leaves the image on
    each side of a pivot about the tip ``p`` turning a_des about o_des
    (:func:`predict_pivot_ends`)."""
    return predict_pivot_ends(model, u.R_BK, u.p_BK, p, s.a_des, s.o_des, cfg.max_pivot_tilt)


def cap_slide_direction(o, a_star, angle: float) -> np.ndarray:
    """Unit (x, y) direction in B of the slide at the tilt cap: across the array ``o``, in
    the horizontal plane, towards the side a probe tilted by ``angle`` (rad, eq. 23's sign:
    a = a* cos + (o x a*) sin) leans to, where translating the tip moves the image plane on
    past the cap's plane. Zero when o x a* has no horizontal part."""
    b = cross3(np.asarray(o, float), np.asarray(a_star, float))[:2] * math.copysign(1.0, angle)
    n = float(np.linalg.norm(b))
    return b / n if n > 1e-9 else np.zeros(2)


def cap_slide_needed(
    model: PivotModel, R_BK, p_BK, R_BP, p_BP, direction_xy, max_slide: float, step=0.001
) -> float:
    """Slide (m) of the tip along ``direction_xy`` (unit, in B's x-y plane; orientation
    ``R_BP`` held) after which the template of ``model`` registered at (R_BK, p_BK) leaves
    the image (its section, laws.template_section_area, below ``model.min_section_area``),
    on a grid of ``step`` up to ``max_slide``; ``max_slide`` when it is still in view there.
    The tip's height is kept (force control follows the skin)."""
    d_xy = np.asarray(direction_xy, float).reshape(2)
    d = np.array([d_xy[0], d_xy[1], 0.0])
    n = max(1, int(math.ceil(max_slide / step - 1e-9)))
    for k in range(n + 1):
        slide = min(k * step, max_slide)
        area = template_section_area(
            R_BK,
            p_BK,
            model.points_K,
            R_BP,
            np.asarray(p_BP, float).reshape(3) + slide * d,
            probe_radius=model.probe_radius,
            half_angle=model.half_angle,
            depth=model.depth,
            slab_half_width=model.slab_half_width,
        )
        if area < model.min_section_area:
            return float(slide)
    return float(max_slide)


def cap_slide_limit(needed: float, margin: float, max_slide: float) -> float:
    """How far (m) the slide at the tilt cap may go: the template's predicted ``needed``
    slide plus ``margin``, at most ``max_slide``; ``max_slide`` without a prediction (NaN)."""
    if not math.isfinite(needed):
        return float(max_slide)
    return float(min(max_slide, max(0.0, needed) + margin))


def pretilt_plan(ends, margin: float, max_tilt: float) -> tuple:
    """(side, target) of the predicted_end pre-tilt from the predicted ends
    (theta_plus, theta_minus): the nearer end's side (+1 on a tie) and its end plus
    ``margin`` on that side, within +-``max_tilt`` (rad)."""
    plus, minus = ends
    side = 1.0 if plus <= -minus else -1.0
    end = plus if side > 0 else minus
    return side, float(np.clip(end + side * margin, -max_tilt, max_tilt))


def pivot_end_allowed(
    angle: float, direction: float, legs_done: int, ends=(), tolerance: float = 0.0
) -> bool:
    """Whether a loss of the kidney (or the tilt cap) may end the current pivot leg at tilt
    ``angle`` (rad) moving in ``direction`` after ``legs_done`` legs: the first leg always;
    a later leg only past the start, on its new side; and with predicted ``ends``
    (predicted_end, its single sweep counted as the second leg) only within ``tolerance``
    of the predicted other end or beyond."""
    on_new_side = legs_done == 0 or angle * direction > 0
    if on_new_side and ends and legs_done == 1:
        other = ends[0] if direction > 0 else ends[1]
        on_new_side = abs(angle) >= abs(other) - tolerance - 1e-9
    return on_new_side


def _start_pivot(s, t, message, direction=1.0):
    s.pivot_direction = direction
    return _goto(s, Phase.PIVOT, t, message)


def _pretilt(s, u, R, cfg, dt):
    """predicted_end strategy, end of TRANSIT: stage 1 tilts (pretilt_rate, decelerating
    into it) to the target past the predicted end; stage 2, there, waits until the kidney
    has been out of the image for visibility_debounce, tilting on at pivot_rate while it is
    still seen, up to the maximum tilt; then PIVOT sweeps back once (as a second leg)."""
    side = s.pretilt_side
    if s.pretilt_stage == 1:
        remaining = max(0.0, side * (s.pretilt_target - s.pivot_angle))
        v_max = min(cfg.pretilt_rate, math.sqrt(2.0 * cfg.pivot_acceleration * remaining))
        s.pivot_speed = _ramp(s.pivot_speed, side * v_max, cfg.pivot_acceleration * dt)
        if side * s.pivot_speed * dt > remaining:
            s.pivot_speed = side * remaining / dt
        _pivot_advance(s, cfg, dt)
        remaining = side * (s.pretilt_target - s.pivot_angle)
        if remaining <= 1e-6 and angle_between(R[:, 2], s.a_des) <= cfg.transit_angle_tolerance:
            s.pretilt_stage = 2
            s.invisible_since = math.nan
            s.events = s.events + (
                (u.t, "TRANSIT", f"pre-tilt at {math.degrees(s.pivot_angle):.1f} deg"),
            )
        return s
    if not u.motion_allowed:
        return _hold_pivot(s, cfg, dt)
    s.paused = False
    gone = _update_visibility(s, u, cfg.visibility_debounce)
    at_tilt = abs(s.pivot_angle) >= cfg.max_pivot_tilt - 1e-9
    if gone or at_tilt:
        why = "kidney out of the image" if gone else "maximum tilt"
        s.pivot_limits = (s.pivot_angle,)
        s.sweep_end_causes = ("kidney_left" if gone else "tilt_cap",)
        s.pivot_legs_done = 1
        s.expect_invisible = True
        return _start_pivot(
            s,
            u.t,
            f"from the predicted end at {math.degrees(s.pivot_angle):.1f} deg ({why})",
            -side,
        )
    target = side * cfg.pivot_rate if u.kidney_visible else 0.0
    s.pivot_speed = _ramp(s.pivot_speed, target, cfg.pivot_acceleration * dt)
    _pivot_advance(s, cfg, dt)
    return s


def _transit(s, u, R, p, cfg, dt):
    """Slide to (p_x*, p_y*) with a_des = r3*, o_des = r1*; PIVOT when there and aligned.
    With ``pivot_strategy: predicted_end`` (and a pivot model) the probe then tilts to the
    predicted end of the nearer side first (``_pretilt``)."""
    if s.pretilt_stage:
        if u.t - s.phase_start > 2 * cfg.transit_timeout:
            s.reason = f"TRANSIT timeout: pre-tilt at {math.degrees(s.pivot_angle):.1f} deg"
            return _goto(s, Phase.ABORT, u.t, s.reason)
        return _pretilt(s, u, R, cfg, dt)
    dist = float(np.linalg.norm(p[:2] - s.p_star[:2]))
    ang = max(angle_between(R[:, 2], s.a_des), angle_between(R[:, 0], s.o_des))
    if dist <= cfg.transit_position_tolerance and ang <= cfg.transit_angle_tolerance:
        s.pivot_speed = 0.0
        s.pivot_angle = 0.0
        model = u.pivot_model
        # The template's section at the pivot's start: the reference of absence_expected.
        s.section_reference = section_in_view(model, u, R, p)
        if cfg.pivot_strategy == "predicted_end":
            if cfg.pivot_pose:
                return _start_pivot(
                    s,
                    u.t,
                    f"at p* ({dist * 1e3:.2f} mm); given pivot pose, "
                    "no registered kidney to predict the ends from: two-leg "
                    "pivot",
                )
            if model is None or len(model.points_K) == 0:
                return _start_pivot(
                    s, u.t, f"at p* ({dist * 1e3:.2f} mm); no pivot model: two-leg pivot"
                )
            plus, minus = predicted_pivot_ends(s, model, u, p, cfg)
            s.pivot_ends = (plus, minus)
            s.pretilt_side, s.pretilt_target = pretilt_plan(
                s.pivot_ends, cfg.pivot_end_margin, cfg.max_pivot_tilt
            )
            s.pretilt_stage = 1
            s.events = s.events + (
                (
                    u.t,
                    "TRANSIT",
                    f"at p* ({dist * 1e3:.2f} mm); predicted ends "
                    f"{math.degrees(plus):.1f} / {math.degrees(minus):.1f} "
                    f"deg: pre-tilt to "
                    f"{math.degrees(s.pretilt_target):.1f} deg",
                ),
            )
            return s
        return _start_pivot(s, u.t, f"at p* ({dist * 1e3:.2f} mm)")
    if u.t - s.phase_start > cfg.transit_timeout:
        s.reason = f"TRANSIT timeout: {dist * 1e3:.1f} mm from p*"
        return _goto(s, Phase.ABORT, u.t, s.reason)
    return s


def _update_absence(s: SupervisorState, u: SupervisorInputs, R, p, cfg) -> None:
    """PIVOT: the template's section in the current image and whether the kidney's absence
    is expected now (absence_expected with ``reacquire_share``)."""
    model = u.pivot_model
    s.section_area = section_in_view(model, u, R, p)
    s.kidney_absence_expected = absence_expected(
        s.expect_invisible,
        s.section_area,
        s.section_reference,
        model.min_section_area if model is not None else 0.0,
        cfg.reacquire_share,
    )


def pivot_follow_error(R_BP, a_des) -> float:
    """Angle (rad) between the probe's axis (R_BP's z column) and the commanded a_des."""
    a = np.asarray(R_BP, dtype=float)[:, 2]
    d = np.asarray(a_des, dtype=float)
    c = float(a @ d) / max(float(np.linalg.norm(a) * np.linalg.norm(d)), 1e-12)
    return math.acos(min(1.0, max(-1.0, c)))


def _end_leg(s, u, R, p, cfg, cause: str, detail: str = ""):
    """Records the end of a pivot leg (its tilt, ``cause`` "kidney_left" or "tilt_cap");
    the DONE state after the second, else None (the next leg turns the other way)."""
    why = "kidney left the image" if cause == "kidney_left" else "maximum tilt"
    s.pivot_limits = s.pivot_limits + (s.pivot_angle,)
    s.sweep_end_causes = s.sweep_end_causes + (cause,)
    s.pivot_legs_done += 1
    s.events = s.events + (
        (
            u.t,
            "PIVOT",
            f"leg {s.pivot_legs_done} ended at {math.degrees(s.pivot_angle):.1f} deg"
            f"{detail}: {why}",
        ),
    )
    if s.pivot_legs_done >= 2:
        if review_wanted(cfg, s.second_look_used, s.relocalizations, u.pivot_view):
            s.reviewing = True
            s.review_since = u.t
            s.events = s.events + (
                (u.t, "PIVOT", "pivot sweep complete: checking its view against the fit"),
            )
            return s
        return _goto(s, Phase.DONE, u.t, "pivot sweep complete")
    s.pivot_direction = -s.pivot_direction
    s.invisible_since = math.nan
    s.expect_invisible = True
    _update_absence(s, u, R, p, cfg)
    return None


def _start_cap_slide(s, u, R, p, cfg):
    """The tilt cap reached with the kidney still in the image: hold the tilt and slide
    the tip (``cap_slide_direction``) at least the template's predicted slide
    (``cap_slide_needed``) and up to ``cap_slide_limit`` of it (without a registered
    template: up to cap_slide_max)."""
    s.pivot_speed = 0.0
    s.cap_slide = 1
    s.cap_slide_dir = cap_slide_direction(s.o_des, s.a_star, s.pivot_angle)
    s.cap_slide_travel = 0.0
    model = u.pivot_model
    needed = math.nan
    if math.isfinite(section_in_view(model, u, R, p)):
        # The commanded orientation (the probe follows it within pivot_follow_limit).
        R_cmd = np.column_stack([s.o_des, cross3(s.a_des, s.o_des), s.a_des])
        needed = cap_slide_needed(
            model, u.R_BK, u.p_BK, R_cmd, p, s.cap_slide_dir, cfg.cap_slide_max
        )
    s.cap_slide_limit = cap_slide_limit(needed, cfg.cap_slide_margin, cfg.cap_slide_max)
    s.cap_slide_predicted = 0.0 if math.isnan(needed) else min(needed, s.cap_slide_limit)
    predicted = "" if math.isnan(needed) else f"; the template predicts {needed * 1e3:.0f} mm"
    s.events = s.events + (
        (
            u.t,
            "PIVOT",
            f"tilt cap {math.degrees(s.pivot_angle):.1f} deg with the kidney in view: sliding "
            f"up to {s.cap_slide_limit * 1e3:.0f} mm{predicted}",
        ),
    )
    return s


def _cap_slide(s, u, R, p, cfg, dt, left: bool):
    """The slide at the tilt cap (tilt held): out at scan_speed until the kidney has left the
    image (debounced) and the slide has passed the template's predicted one (the
    segmentation misses a pole's last small sections; the leg's end, "kidney_left"), or
    to the limit with the kidney still seen (the leg's end at the cap, "tilt_cap"); after
    the first leg back to p* the same way, then the second leg (once the tip is within
    transit_position_tolerance of p*, or 2 s after P_des got there)."""
    s.pivot_speed = 0.0
    step = cfg.scan_speed * dt
    if s.cap_slide == 1:
        # Sliding out to find the kidney's edge: its leaving the image is what the slide
        # waits for, not a loss (the slide is bounded by cap_slide_limit).
        s.kidney_absence_expected = True
        at_limit = s.cap_slide_travel >= s.cap_slide_limit - 1e-9
        past = s.cap_slide_travel >= s.cap_slide_predicted - 1e-9
        if (left and past) or at_limit:
            s.cap_slides = s.cap_slides + ((s.pivot_legs_done + 1, s.cap_slide_travel),)
            done = _end_leg(
                s,
                u,
                R,
                p,
                cfg,
                "kidney_left" if left else "tilt_cap",
                f" and {s.cap_slide_travel * 1e3:.1f} mm of slide",
            )
            if done is not None:
                done.cap_slide = 0
                return done
            s.cap_slide = 2
            s.cap_slide_back_at = math.nan
            return s
        step = min(step, s.cap_slide_limit - s.cap_slide_travel)
        s.P_des = s.P_des + step * s.cap_slide_dir
        s.cap_slide_travel += step
        return s
    if s.cap_slide_travel > 0.0:
        step = min(step, s.cap_slide_travel)
        s.P_des = s.P_des - step * s.cap_slide_dir
        s.cap_slide_travel -= step
        if s.cap_slide_travel <= 0.0:
            s.P_des = s.p_star[:2].copy()
            s.cap_slide_back_at = u.t
        return s
    if math.isnan(s.cap_slide_back_at):
        s.cap_slide_back_at = u.t
    there = float(np.linalg.norm(p[:2] - s.p_star[:2])) <= cfg.transit_position_tolerance
    if there or u.t - s.cap_slide_back_at >= 2.0:
        s.cap_slide = 0
        s.invisible_since = math.nan
    return s


def _pivot(s, u, R, p, cfg, dt):
    """a_des rotates about o_des (eq. 23) one way until the kidney leaves the image (or the
    maximum tilt), then back through r3* to the other side; then DONE. ABORT when the probe
    lags a_des by more than pivot_follow_limit for pivot_follow_time."""
    lag = pivot_follow_error(R, s.a_des)
    s.lag_since = lagging_since(s.lag_since, u.t, lag > cfg.pivot_follow_limit)
    if u.t - s.lag_since >= cfg.pivot_follow_time - 1e-9:  # False while NaN
        s.reason = (
            f"the probe does not follow the pivot: its axis lags the commanded "
            f"one by {math.degrees(lag):.1f} deg after "
            f"{u.t - s.lag_since:.2f} s (limit {math.degrees(cfg.pivot_follow_limit):.1f}"
            f" deg; a joint at its limit?)"
        )
        return _goto(s, Phase.ABORT, u.t, s.reason)
    if s.reviewing:
        return _review(s, u, R, p, cfg, dt)
    if not u.motion_allowed:
        return _hold_pivot(s, cfg, dt)
    s.paused = False
    left = _update_visibility(s, u, cfg.visibility_debounce)
    if u.kidney_visible:
        s.expect_invisible = False
    # On the second leg, only a loss past the start (on the new side) ends the sweep;
    # predicted_end: the single sweep ends near the predicted other end or beyond.
    on_new_side = pivot_end_allowed(
        s.pivot_angle, s.pivot_direction, s.pivot_legs_done, s.pivot_ends, cfg.pivot_end_tolerance
    )
    at_tilt = abs(s.pivot_angle) >= cfg.max_pivot_tilt - 1e-9 and on_new_side
    _update_absence(s, u, R, p, cfg)
    if s.cap_slide:
        return _cap_slide(s, u, R, p, cfg, dt, left)
    if at_tilt and not left and cfg.cap_slide_max > 0.0:
        return _start_cap_slide(s, u, R, p, cfg)
    if (left and on_new_side) or at_tilt:
        done = _end_leg(s, u, R, p, cfg, "kidney_left" if (left and on_new_side) else "tilt_cap")
        if done is not None:
            return done
    # The tilt rate ramps (pivot_acceleration) to +-pivot_rate: a reversal is smooth, not a
    # jump of the commanded angular velocity (which presses the probe edge in).
    s.pivot_speed = _ramp(
        s.pivot_speed, s.pivot_direction * cfg.pivot_rate, cfg.pivot_acceleration * dt
    )
    _pivot_advance(s, cfg, dt)
    return s


def _review(s, u, R, p, cfg, dt):
    """The pivot's end awaiting the pivot-view check (:func:`review_outcome`): the tilt
    rate ramps down to zero and the probe holds; then DONE, or the second look."""
    s.pivot_speed = _ramp(s.pivot_speed, 0.0, cfg.pivot_acceleration * dt)
    _pivot_advance(s, cfg, dt)
    what = review_outcome(u.pivot_view, s.review_since, u.t)
    if what == "wait":
        return s
    s.reviewing = False
    if what == "second_look":
        return _kidney_moved(s, u, R, p, cfg, why=u.pivot_view[1], second_look=True)
    covered = u.pivot_view[0] if u.pivot_view is not None else math.nan
    how = (
        "its view agrees with the fit"
        if math.isfinite(covered) and covered >= s.review_since - 1e-9
        else f"no pivot-view check within {REVIEW_TIMEOUT:g} s"
    )
    s.pivot_speed = 0.0
    return _goto(s, Phase.DONE, u.t, f"pivot sweep complete ({how})")


_PHASE_STEP = {
    Phase.APPROACH: _approach,
    Phase.EXPLORE: _explore,
    Phase.LOCALIZE: _localize,
    Phase.TRANSIT: _transit,
    Phase.PIVOT: _pivot,
}


def supervisor_step(state: SupervisorState, u: SupervisorInputs, cfg, dt: float) -> SupervisorState:
    """One control period of the scan state machine (pure: returns a new state).

    APPROACH -> EXPLORE -> LOCALIZE -> TRANSIT -> PIVOT -> DONE (each phase's rule is its
    own function above); with a given ``pivot_pose`` APPROACH -> TRANSIT -> PIVOT -> DONE,
    with ``sweep: line`` APPROACH -> EXPLORE -> DONE. ABORT (with reason) from any phase on a
    safety stop, a non-finite
    input or pose, a missing kidney pose, a LOCALIZE or TRANSIT timeout, or (TRANSIT, PIVOT)
    a tracking error: the kidney has moved away from its registered pose. The pivot tilt
    rate ramps with pivot_acceleration. While ``motion_allowed`` is False (outside a
    breath-hold) EXPLORE and PIVOT hold still (the pivot rate ramps to zero) and the kidney
    may leave the image; LOCALIZE waits for it to start TRANSIT. A tracking error in TRANSIT
    or PIVOT re-localizes (``_kidney_moved``) up to ``max_relocalizations`` times; a
    ``breathing_error`` aborts.
    """
    s = state.copy()
    R = np.asarray(u.R_BP, dtype=float)
    p = np.asarray(u.p_BP, dtype=float)
    s.a_des_dot = np.zeros(3)
    if s.phase == Phase.DONE and s.pivot_speed != 0.0:
        # Ramp the last pivot leg's tilt rate down to zero (no jump of the command).
        s.pivot_speed = _ramp(s.pivot_speed, 0.0, cfg.pivot_acceleration * dt)
        _pivot_advance(s, cfg, dt)
        return s
    if s.phase in (Phase.DONE, Phase.ABORT):
        return s
    if u.safety_stopped:
        s.reason = "safety stop"
        return _goto(s, Phase.ABORT, u.t, s.reason)
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(p)) and math.isfinite(u.F_z)):
        s.reason = "non-finite probe pose or force"
        return _goto(s, Phase.ABORT, u.t, s.reason)
    if not s.initialised:
        _start(s, u, R, p, cfg)
    if u.breathing_error:
        return _breathing_abort(s, u)
    if s.phase in (Phase.TRANSIT, Phase.PIVOT) and u.tracking_error:
        return _kidney_moved(s, u, R, p, cfg)
    return _PHASE_STEP[s.phase](s, u, R, p, cfg, dt)


# ----------------------------------------------------------------------------- patient motion
def _breathing_abort(s: SupervisorState, u: SupervisorInputs) -> SupervisorState:
    """The breath-hold protocol cannot go on (the patient does not hold): ABORT."""
    s.reason = f"breath-hold protocol: {u.breathing_error}"
    s.pivot_speed = 0.0
    return _goto(s, Phase.ABORT, u.t, s.reason)


def _kidney_moved(
    s: SupervisorState, u: SupervisorInputs, R, p, cfg, why: str = "", second_look: bool = False
) -> SupervisorState:
    """The kidney tracking says the kidney left its registered pose during TRANSIT or PIVOT:
    re-localize (a re-exploration, then a new registration) up to ``max_relocalizations``
    times, then ABORT. The re-exploration starts still, turning the probe straight down
    (r3*) and transverse (``_reorient``), backs out of the kidney (``_retreat``), then
    explores as the first exploration did. ``second_look``: the pivot's view contradicted
    the registration (``why``): the same, but the exploration sweeps the whole kidney."""
    why = why or u.tracking_error
    if s.relocalizations >= cfg.max_relocalizations:
        s.reason = f"kidney moved: {why}"
        if s.relocalizations:
            s.reason += f" (after {s.relocalizations} re-localizations)"
        s.pivot_speed = 0.0
        return _goto(s, Phase.ABORT, u.t, s.reason)
    s.relocalizations += 1
    s.localization_round += 1
    s.reorient_best, s.reorient_best_since, s.reorient_flipped = math.inf, math.nan, False
    s.whole_kidney = bool(second_look)
    if second_look:
        s.second_look_used = True
        s.second_look_reason = why
    s.reviewing = False
    s.reorienting = True
    s.retreating = False
    s.awaiting_kidney = False
    s.pivot_speed = 0.0
    s.pivot_angle = 0.0
    s.pivot_legs_done = 0
    s.pivot_limits = ()
    s.sweep_end_causes = ()
    s.pivot_ends = ()
    s.cap_slide = 0
    s.cap_slide_travel = 0.0
    s.cap_slides = ()  # the abandoned pivot's slides are not the new one's
    s.pretilt_stage = 0
    s.expect_invisible = False
    s.lag_since = math.nan
    s.travel = 0.0
    s.a_des = np.array([0.0, 0.0, -1.0])
    s.o_des = reexploration_array(s.a_des, R[:, 0], s.o_explore)
    s.P_des = p[:2].copy()
    s.explore_lag_since = math.nan
    opening = "second look" if second_look else "kidney moved"
    return _goto(
        s,
        Phase.EXPLORE,
        u.t,
        f"{opening}: {why}; re-localizing "
        f"({s.relocalizations} of {cfg.max_relocalizations})"
        + ("; sweeping the whole kidney" if second_look else ""),
    )


# Re-exploration: a probe pressed on sloping skin may stop a few degrees short of straight
# down; after REORIENT_SETTLE s within REORIENT_ACCEPT rad it explores from there (a sweep
# a few degrees off the vertical sees the kidney as well).
REORIENT_SETTLE = 3.0
REORIENT_ACCEPT = 0.15
# The turn has stalled once it has not come this much closer (rad) for REORIENT_SETTLE s.
REORIENT_PROGRESS = math.radians(0.5)


def turn_progress(best: float, best_since: float, angle: float, t: float) -> tuple:
    """(best, best_since): the smallest angle (rad) to the turn's target so far and since
    when (s), after the angle ``angle`` at time ``t``: a new best only once it is
    REORIENT_PROGRESS closer (the probe settling on sloping skin creeps, it does not
    turn)."""
    if not math.isfinite(best) or angle < best - REORIENT_PROGRESS:
        return float(angle), float(t)
    return float(best), float(best_since)


def reexploration_array(a, o_curr, o_explore=None) -> np.ndarray:
    """The array direction (unit, B) a re-exploration turns to: transverse to ``a``
    (:func:`transverse_orientation`), on the side of the first exploration's array
    ``o_explore`` (None: the side nearer the current array ``o_curr``, the smaller turn).

    Why not the smaller turn: after a pivot the array lies along the kidney's long axis,
    which runs nearly along the base's y axis, so both transverse directions are about
    90 deg away and the "smaller" one is a coin toss. Half the time it is the turn that
    carries FR3 joint 7 further past where the pivot left it: on KiTS19 case 12 (left
    kidney) the wrist reached its limit 5-8 deg short of transverse, close enough for the
    turn to be accepted, and the joint-limit scaling of the differential IK then held the
    whole arm still for the rest of the scan. The first exploration's side is the turn
    back the way the wrist came."""
    return transverse_orientation(a, o_curr if o_explore is None else o_explore)


def turn_stalled(best: float, best_since: float, t: float, array_angle: float) -> bool:
    """Whether the re-exploration's turn has stalled with the array short of its transverse
    target: no progress (:func:`turn_progress`) for REORIENT_SETTLE s and the array
    ``array_angle`` (rad) from its target beyond REORIENT_ACCEPT. A transverse image has
    two array directions (o and -o: the same plane, mirrored); the turn goes the shorter
    way, which the wrist may not reach (FR3 joint 7 at its limit after a pivot that
    turned the array along the kidney: KiTS19 case 58, 11.8 deg short), while the other
    way it can."""
    return (
        math.isfinite(best_since)
        and t - best_since >= REORIENT_SETTLE - 1e-9
        and array_angle > REORIENT_ACCEPT
    )


def retreat_limit(cfg, kidney_length_estimate: float = math.nan) -> float:
    """The longest backing-out travel (m) of a re-exploration: the kidney length L the
    exploration plans with (:func:`exploration_kidney_length`). From anywhere over a
    kidney, one kidney length back is behind it."""
    return exploration_kidney_length(cfg, kidney_length_estimate)


def _retreat(s, u, R, p, cfg, dt):
    """Re-exploration's second stage: eq. 17 against the scan direction until the kidney
    has left the image (``visibility_debounce``) or after :func:`retreat_limit`, then the
    exploration proper from there (the cloud cleared until then, the kidney's absence not
    a loss until it comes into view).

    Why: the probe was over the kidney's middle (at p*) when the patient moved. A sweep
    from there sees the kidney from its middle to one pole only, and a half kidney leaves
    the registration free to slide along and turn about the long axis (test:0, 6 and 7 of
    the breathing study: re-registrations 10-38 mm off, or rejected). Backing out first
    makes the re-exploration sweep into the kidney from behind its near pole, as the first
    exploration did, over the same ER x L."""
    left = u.motion_allowed and _update_visibility(s, u, cfg.visibility_debounce)
    limit = retreat_limit(cfg, u.kidney_length_estimate)
    if left or s.travel >= limit - 1e-12:
        why = "the kidney left the image" if left else "one kidney length"
        back = s.travel
        s.retreating = False
        s.awaiting_kidney = True
        s.travel = 0.0
        s.invisible_since = math.nan
        s.visible_since = math.nan
        s.explore_seen = False
        s.P_des = p[:2].copy()
        s.events = s.events + (
            (u.t, "EXPLORE", f"re-exploring from {back * 1e3:.1f} mm back ({why})"),
        )
        return s
    if not u.motion_allowed:
        return _hold_motion(s, dt)
    s.paused = False
    return _advance_exploration(s, u, R, cfg, dt, limit, backwards=True)


def _reorient(s, u, R, p, cfg, dt):
    """Re-exploration's first stage: hold the tip still until the probe points along a_des
    and its array along o_des (transit_angle_tolerance, or REORIENT_ACCEPT once it has had
    REORIENT_SETTLE s), then explore."""
    array = angle_between(R[:, 0], s.o_des)
    ang = max(angle_between(R[:, 2], s.a_des), array)
    settled = u.t - s.phase_start >= REORIENT_SETTLE and ang <= REORIENT_ACCEPT
    s.reorient_best, s.reorient_best_since = turn_progress(
        s.reorient_best, s.reorient_best_since, ang, u.t
    )
    if (
        not (ang <= cfg.transit_angle_tolerance or settled)
        and not s.reorient_flipped
        and turn_stalled(s.reorient_best, s.reorient_best_since, u.t, array)
    ):
        # The same transverse plane with the array the other way round.
        s.o_des = -s.o_des
        s.reorient_flipped = True
        s.reorient_best, s.reorient_best_since = math.inf, math.nan
        s.events = s.events + (
            (
                u.t,
                "EXPLORE",
                f"the array stalled {math.degrees(array):.1f} deg short of transverse: "
                "turning it to the other transverse direction",
            ),
        )
        return s
    if ang <= cfg.transit_angle_tolerance or settled:
        s.reorienting = False
        s.retreating = True
        s.P_des = p[:2].copy()
        s.invisible_since = math.nan
        s.events = s.events + ((u.t, "EXPLORE", "backing out of the kidney to re-explore"),)
        return s
    if u.t - s.phase_start > cfg.transit_timeout:
        s.reason = (
            f"re-localization: the probe did not turn transverse ({math.degrees(ang):.1f} deg)"
        )
        return _goto(s, Phase.ABORT, u.t, s.reason)
    return s
