"""Respiration from what any station senses, and the breath-hold protocol: plain functions.

The probe presses on the abdominal wall under constant-force control, so every breath moves
it along its beam and modulates the force. The wall's level is the tip's height plus the
tissue's indentation, w = z_P - (F / k) a_z (a: the beam, into the body; k: the contact
stiffness): whether the force loop has already followed the wall (the tip moved) or not yet
(the force changed), w moves with it. While the probe slides (EXPLORE) or tilts (PIVOT) the
skin's own shape adds to w; within a still segment of the wall the estimator fits that part
as a function of the probe's travel and keeps only the rest.

:func:`respiration_update` classifies every control period as BREATHING, HOLDING (a
breath-hold: the wall still for ``hold_confirm`` s above the end-expiration band, or still
for ``still_long`` s anywhere) or END_EXPIRATION (still in the band just above the recent
end-expiration level); each change of state carries the estimated time it happened (the
start of the stillness, the start of the motion), not just when it was decided.

:func:`protocol_step` is the seed's breath-hold protocol (III-B) on top of it: it decides
what the patient is told (``motion.Prompt``) and when the scan may move
(``motion_allowed``): only during a sensed hold, each at most ``hold_limit`` s, with
``recovery_time`` s of free breathing before the first and between two; a phase that needs
longer is split, the probe held still under force control in between. :func:`gate_step` is
gated free breathing: motion only in the end-expiration windows (and holds).

Frames, units: the base frame B (z up), SI.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

__all__ = [
    "UNKNOWN",
    "BREATHING",
    "HOLDING",
    "END_EXPIRATION",
    "STATE_NAMES",
    "wall_level",
    "own_motion_speed",
    "probe_moving",
    "hinge_change_point",
    "RespirationState",
    "respiration_update",
    "ProtocolState",
    "protocol_step",
    "gate_step",
    "phase_needs_hold",
    "HOLD_PHASES",
]

UNKNOWN, BREATHING, HOLDING, END_EXPIRATION = 0, 1, 2, 3
STATE_NAMES = {
    UNKNOWN: "unknown",
    BREATHING: "breathing",
    HOLDING: "holding",
    END_EXPIRATION: "end-expiration",
}
# The wall's tidal range below which breathing is not visible (m): stillness is then a hold.
MIN_TIDAL = 0.0005
# Learning the patient's breathing takes this long (s) of contact: until then only a long
# stillness counts as a hold.
CALIBRATION = 6.0
# Travel (m) outside still segments after which the breathing is learnt again.
RELEARN_TRAVEL = 0.01
# A wall within this (m) of its still segment's line has not left it yet.
DEPARTURE_NOISE = 0.00005
# The travel is counted in steps of at least this (m).
TRAVEL_STEP = 0.0005
# The probe face's radius of curvature (m): tilting rolls the contact along the skin.
FACE_RADIUS = 0.05
# A still segment ends when the wall leaves the line fitted over it by this much (m), or
# moves faster than still_speed on two successive periods.
END_DEVIATION = 0.0003
# A hold's end is dated by a change point over the segment's last this many s (the decision
# comes 0.15-0.3 s after the wall starts to move; the hold's course before it needs the
# rest), with at least HINGE_MIN_SAMPLES samples on either side of the break.
DEPARTURE_WINDOW = 0.8
HINGE_MIN_SAMPLES = 3
# The probe moves of its own accord when the scan commands it faster than this (m/s: its
# commanded speed across the beam plus FACE_RADIUS x its commanded angular speed). Breathing
# alone makes the tip-position loop command at most 2.2 mm/s (99th percentile over the
# free breathing of recorded protocol scans); EXPLORE slides at 5 mm/s, TRANSIT and PIVOT
# reach 10-140 mm/s.
OWN_MOTION_SPEED = 0.003
# After the command falls below OWN_MOTION_SPEED the force loop settles for this long (s):
# the contact force swings by up to 0.6 N for 0.4-0.5 s after a PIVOT tilt stops.
OWN_MOTION_SETTLE = 0.6
# While the probe moves of its own accord, a still segment ends only on a departure larger
# than this (m) from its fitted line: a slide, a tilt or a turn about the beam changes the
# wall's reading by up to 2.2 mm within a hold (TRANSIT and PIVOT of recorded protocol
# scans), which no speed test tells from a breath; the fit starts anew once it stops.
MOTION_DEPARTURE = 0.003


def wall_level(p_BP, a_B, force: float, stiffness: float) -> float:
    """The abdominal wall's level under the probe (m, along B's z): the tip's height plus the
    indentation ``force`` / ``stiffness`` along the beam ``a_B`` (unit, into the body;
    ``force`` N, positive pressing)."""
    return float(p_BP[2]) - float(force) / float(stiffness) * float(a_B[2])


def _slope(t: np.ndarray, x: np.ndarray) -> float:
    """Least-squares slope of x(t); 0 for fewer than 3 samples."""
    if len(t) < 3:
        return 0.0
    tc = t - t.mean()
    den = float(tc @ tc)
    return float(tc @ (x - x.mean())) / den if den > 0 else 0.0


@dataclasses.dataclass(frozen=True)
class RespirationState:
    """The estimator's memory: the recent samples (time s, wall level m, the probe's
    travel m (slide plus roll), whether the sample was in a hold), the current state and the
    estimated time it began, the start of the current stillness, the still segment's
    geometry fit, and the transitions so far ((estimated time, decided time, from, to),
    ...)."""

    t: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    w: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    d: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    held: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, bool))
    geom: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    state: int = UNKNOWN
    since: float = math.nan
    contact_since: float = math.nan
    learning_since: float = math.nan  # the breathing history starts here (contact, relearn)
    # The skin's shape under the probe as it moved (m): fitted within still segments
    # (geom_seg0 at the segment's start, travel d_seg0), unmodelled travel in between.
    geom_now: float = 0.0
    geom_seg0: float = 0.0
    d_seg0: float = 0.0
    unmodelled: float = 0.0
    still_since: float = math.nan  # the stillness's estimated start (the speed window's centre)
    still_seen: float = math.nan  # when the stillness was first seen
    segment_start: float = math.nan  # the current still segment (HOLDING/END_EXPIRATION)
    # The probe's own motion: the last time its command exceeded OWN_MOTION_SPEED, and the
    # start of the segment's samples its line is fitted to (after the last such motion).
    own_until: float = -math.inf
    fit_since: float = -math.inf
    # Which way the wall leaves it: -1 down (an expiration: from a hold breathed in), +1 up
    # (an inspiration: from end-expiration or a hold breathed out), 0 either.
    segment_exit: int = 0
    moving_count: int = 0
    travel: float = 0.0
    last_xy: tuple = ()
    ee_level: float = math.nan
    tidal: float = math.nan
    transitions: tuple = ()

    def __deepcopy__(self, memo):  # never changed in place: clones may share it
        return self


def _history_levels(s: RespirationState, t: float, cfg) -> tuple[float, float]:
    """(end-expiration level, tidal range) of the breathing (not the holds) of the last
    ``history`` s: the 10th percentile and the 90th minus it; NaN before CALIBRATION s of
    contact."""
    if not math.isfinite(s.learning_since) or t - s.learning_since < CALIBRATION:
        return math.nan, math.nan
    use = (~s.held) & (s.t >= t - cfg.history)
    if np.count_nonzero(use) < 20:
        return s.ee_level, s.tidal
    lo, hi = np.percentile(s.w[use] - s.geom[use], [10.0, 90.0])
    return float(lo), float(hi - lo)


def _fit_start(s: RespirationState) -> float:
    """The start of the current still segment's samples its line is fitted to: the segment's
    start, or the end of the probe's last own motion within it (plus the settling)."""
    return max(s.segment_start, s.fit_since)


def _segment_residual(s: RespirationState, t: float, lag: float) -> tuple[float, float]:
    """(residual m, geometric slope m/m) of the wall's newest samples (the last ``lag`` s)
    against a line in the probe's travel fitted over the rest of the current still segment
    since the probe's last own motion (the skin's shape under a sliding probe;
    ridge-regularised towards no slope)."""
    seg = s.t >= _fit_start(s)
    old = seg & (s.t < t - lag)
    new = seg & (s.t >= t - lag)
    if np.count_nonzero(old) < 3 or not new.any():
        return 0.0, 0.0
    d, w = s.d[old], s.w[old]
    dc = d - d.mean()
    # The slope is trusted once the probe has travelled a few mm (ridge 1e-6 m^2).
    g = float(dc @ (w - w.mean())) / (float(dc @ dc) + 1e-6)
    g = float(np.clip(g, -1.0, 1.0))
    pred = w.mean() + g * (s.d[new] - d.mean())
    return float(np.mean(s.w[new] - pred)), g


def _still_segment_update(s, t, w, v_w, v_d, ee, tidal, half, cfg) -> RespirationState:
    """HOLDING or END_EXPIRATION: has the wall left its still segment? Its speed beyond the
    part the skin's shape explains under a sliding probe (a line in the travel fitted over
    the segment), in the direction it is expected to leave (``segment_exit``) on three
    successive periods, or once with the wall END_DEVIATION off the line. Until the probe
    has slid 3 mm the fit is young: up to 0.3 x the sliding speed is tolerated as skin
    slope. A long END_EXPIRATION becomes a hold; one that rises becomes one too. A hold
    breathed in that rises END_DEVIATION on ends: a breath's top, not a hold."""
    residual, g = _segment_residual(s, t, min(0.15, half))
    s = dataclasses.replace(s, geom_now=s.geom_seg0 + g * (s.travel - s.d_seg0))
    seg = s.t >= _fit_start(s)
    seg_travel = float(s.d[seg][-1] - s.d[seg][0]) if seg.any() else 0.0
    v = v_w - g * v_d
    tol = cfg.still_speed + (0.3 * abs(v_d) if seg_travel < 0.003 else 0.0)
    sign = s.segment_exit
    toward = (sign * v if sign else abs(v)) > tol
    moving = s.moving_count + 1 if toward else 0
    off = (sign * residual if sign else abs(residual)) > END_DEVIATION
    s = dataclasses.replace(s, moving_count=moving)
    left_band = (
        s.state == END_EXPIRATION
        and math.isfinite(tidal)
        and residual > 0.2 * tidal
        and moving >= 1
    )
    if s.state == HOLDING and cfg.mode == "breath_hold" and t - s.own_until < OWN_MOTION_SETTLE:
        # The probe moves of its own accord (or its force loop settles): the wall's reading
        # follows the skin under it. Only a departure no motion makes ends the hold. Only
        # in the breath-hold protocol, where the hold was asked for and the scan stops the
        # probe before it says "breathe normally". Gating asks for none: a hold it senses
        # (a long end-expiration) and an end-expiration window end with the next breath
        # in, which must stop the probe at once, whatever it does.
        gross = (sign * residual if sign else abs(residual)) > MOTION_DEPARTURE
        if not (gross and moving >= 1):
            return dataclasses.replace(s, moving_count=0)
    # A hold breathed in that rises on: the patient was still breathing in (a breath's top,
    # still for a moment, taken for a hold); the hold comes when the wall stops again.
    deeper = s.state == HOLDING and sign < 0 and residual > END_DEVIATION and v > tol
    if moving >= 3 or (off and moving >= 1) or left_band or deeper:
        when = _departure(s, t, g, sign)
        s = dataclasses.replace(
            s, still_since=math.nan, still_seen=math.nan, segment_start=math.nan
        )
        return _transition(s, BREATHING, when, t)
    if s.state == END_EXPIRATION and t - s.still_seen >= cfg.still_long:
        return _transition(s, HOLDING, s.still_since, t)
    return s


def _departure(s: RespirationState, t: float, g: float, sign: int) -> float:
    """When the wall left its still segment (s): a change point. Over the segment's samples
    of the last DEPARTURE_WINDOW s (the skin's shape along the travel, slope ``g``, taken
    out), the break of the continuous two-piece line (the hold's course, then the breath's)
    that fits them best. Each piece has its own slope: the hold's slow drift, or what the
    skin's shape fit left of a slide that stopped, before; the breath after."""
    # From the probe's last own motion on: its force loop's settling may hold the break.
    since = max(s.segment_start, s.fit_since - OWN_MOTION_SETTLE)
    seg = (s.t >= since) & (s.t >= t - DEPARTURE_WINDOW)
    ts, ws = s.t[seg], s.w[seg] - g * s.d[seg]
    if len(ts) < 2 * HINGE_MIN_SAMPLES:
        return float(ts[0]) if len(ts) else float(t)
    return hinge_change_point(ts, ws)


def hinge_change_point(t: np.ndarray, x: np.ndarray) -> float:
    """The time tau (one of ``t``) whose continuous two-piece line x = c + b (t - tau) +
    d max(0, t - tau) fits the samples best (least squares); at least HINGE_MIN_SAMPLES
    samples on either side."""
    t = np.asarray(t, dtype=float)
    x = np.asarray(x, dtype=float)
    best, when = math.inf, float(t[0])
    for k in range(HINGE_MIN_SAMPLES, len(t) - HINGE_MIN_SAMPLES + 1):
        dt = t - t[k]
        A = np.column_stack([np.ones_like(t), dt, np.maximum(dt, 0.0)])
        coef, *_ = np.linalg.lstsq(A, x, rcond=None)
        sse = float(np.sum((A @ coef - x) ** 2))
        if sse < best:
            best, when = sse, float(t[k])
    return when


def _transition(s: RespirationState, new: int, when: float, t: float) -> RespirationState:
    return dataclasses.replace(
        s,
        state=new,
        since=when,
        transitions=s.transitions + ((float(when), float(t), s.state, new),),
    )


def probe_moving(s: RespirationState) -> bool:
    """Whether, at its latest sample, the estimator took the probe as moving of its own
    accord (or its force loop as settling after such motion)."""
    return bool(len(s.t)) and float(s.t[-1]) - s.own_until < OWN_MOTION_SETTLE


def own_motion_speed(v_B, omega_B) -> float:
    """The speed (m/s) the scan commands the probe at of its own accord: its commanded tip
    velocity ``v_B`` (m/s, across the beam: the tip-position loop's) plus FACE_RADIUS x its
    commanded angular velocity ``omega_B`` (rad/s; a tilt rolls the face, a turn about the
    beam swings its contact line over curved skin)."""
    return float(np.linalg.norm(v_B)) + FACE_RADIUS * float(np.linalg.norm(omega_B))


def respiration_update(
    s: RespirationState,
    t: float,
    p_BP,
    a_B,
    force: float,
    in_contact: bool,
    cfg,
    own_speed: float = math.nan,
) -> RespirationState:
    """One control period of the respiration-phase estimator (module doc) at time t (s),
    from the probe tip position ``p_BP`` and beam ``a_B`` (in B) and the contact ``force``
    (N, positive pressing); ``own_speed`` (m/s, :func:`own_motion_speed`; NaN: unknown) is
    how fast the scan commands the probe to move. ``cfg``: the scenario's ``respiration``
    section. Out of contact the estimator forgets and says UNKNOWN."""
    if not in_contact or not (np.all(np.isfinite(p_BP)) and math.isfinite(force)):
        if s.state == UNKNOWN and not len(s.t):
            return s
        out = RespirationState(transitions=s.transitions)
        return _transition(out, UNKNOWN, t, t) if s.state != UNKNOWN else out
    w = wall_level(p_BP, a_B, force, cfg.contact_stiffness)
    # The probe's travel: the tip's slide in x-y plus the face's roll on the skin as the
    # probe tilts (FACE_RADIUS x the tilt).
    xy = tuple(float(v) for v in (*p_BP, *a_B))
    travel, last_xy = s.travel, s.last_xy or xy
    # Across the beam only: the force loop moves the tip along it with every breath.
    dp = np.subtract(xy[:3], last_xy[:3])
    a = np.asarray(xy[3:])
    cos = float(a @ np.asarray(last_xy[3:]))
    step = float(np.linalg.norm(dp - (dp @ a) * a))
    step += FACE_RADIUS * math.acos(min(1.0, max(-1.0, cos)))
    if step >= TRAVEL_STEP:  # counted in steps: the pose's jitter adds up to no travel
        travel += step
        last_xy = xy
    keep = s.t >= t - max(cfg.history, 3.0 + cfg.speed_window)
    held = s.state == HOLDING
    unmodelled = s.unmodelled
    if s.state not in (HOLDING, END_EXPIRATION):
        unmodelled += travel - s.travel
    learning = s.learning_since if math.isfinite(s.learning_since) else t
    if unmodelled > RELEARN_TRAVEL:
        # The probe moved far outside a still segment: the breathing seen before was under
        # other skin. Learn it again.
        keep = np.zeros(len(s.t), bool)
        learning, unmodelled = t, 0.0
    own_until, fit_since = s.own_until, s.fit_since
    if math.isfinite(own_speed) and own_speed > OWN_MOTION_SPEED:
        own_until = t
    elif t - own_until >= OWN_MOTION_SETTLE and own_until + OWN_MOTION_SETTLE > fit_since:
        fit_since = own_until + OWN_MOTION_SETTLE  # the motion ended: fit the wall anew
    s = dataclasses.replace(
        s,
        own_until=own_until,
        fit_since=fit_since,
        t=np.append(s.t[keep], t),
        w=np.append(s.w[keep], w),
        d=np.append(s.d[keep], travel),
        held=np.append(s.held[keep], held),
        geom=np.append(s.geom[keep], s.geom_now),
        travel=travel,
        last_xy=last_xy,
        contact_since=s.contact_since if math.isfinite(s.contact_since) else t,
        learning_since=learning,
        unmodelled=unmodelled,
    )
    if t - s.contact_since < cfg.speed_window + 0.05:
        return s
    recent = s.t >= t - cfg.speed_window
    v_w = _slope(s.t[recent], s.w[recent])
    v_d = _slope(s.t[recent], s.d[recent])
    ee, tidal = _history_levels(s, t, cfg)
    s = dataclasses.replace(s, ee_level=ee, tidal=tidal)
    half = 0.5 * cfg.speed_window

    if s.state in (HOLDING, END_EXPIRATION):
        return _still_segment_update(s, t, w, v_w, v_d, ee, tidal, half, cfg)

    still = abs(v_w) < cfg.still_speed
    if not still:
        s = dataclasses.replace(s, still_since=math.nan, still_seen=math.nan)
        if s.state != BREATHING:
            s = _transition(s, BREATHING, t - half, t)
        return s
    if not math.isfinite(s.still_since):
        # Dated from when the speed fell below still_speed (a breath in slows down into a
        # hold; the speed window's lag roughly cancels the slow end of that breath).
        s = dataclasses.replace(s, still_since=t, still_seen=t)
    still_since = s.still_since
    # Confirmed from when the stillness was seen (a breath's turning point is still for a
    # moment), dated from when it began.
    duration = t - s.still_seen
    visible = math.isfinite(tidal) and tidal >= MIN_TIDAL
    calibrated = math.isfinite(tidal)
    level = w - s.geom_now
    high = calibrated and (not visible or level > ee + 0.5 * tidal)
    segment = dict(segment_start=still_since, moving_count=0, geom_seg0=s.geom_now, d_seg0=travel)
    if (high and duration >= cfg.hold_confirm) or duration >= cfg.still_long:
        exit_sign = (-1 if level > ee + 0.5 * tidal else 1) if visible else 0
        s = dataclasses.replace(s, segment_exit=exit_sign, **segment)
        return _transition(s, HOLDING, still_since, t)
    if visible and level <= ee + cfg.end_expiration_band * tidal:
        s = dataclasses.replace(s, segment_exit=1, **segment)
        return _transition(s, END_EXPIRATION, still_since, t)
    if s.state == UNKNOWN and calibrated:
        return _transition(s, BREATHING, t, t)
    return s


# ----------------------------------------------------------------------------- protocol
# Supervisor phases (control.supervisor.Phase values; imported as ints to keep this module
# free of the supervisor): EXPLORE 1, LOCALIZE 2, TRANSIT 3, PIVOT 4, DONE 5, ABORT 6.
_EXPLORE, _LOCALIZE, _TRANSIT, _PIVOT, _DONE, _ABORT = 1, 2, 3, 4, 5, 6
HOLD_PHASES = (_EXPLORE, _TRANSIT, _PIVOT)

# A hold the estimator stops sensing counts as let go after this long (s) without it coming
# back (a wall that only seemed to move; after a long slide the estimator needs still_long
# to sense a hold again).
REGAIN_TIME = 3.5
# A hold sensed as begun before the prompt counts only once it has lasted this long (s) past
# the prompt: a patient told to hold answers after a reaction time (0.5 s in the simulated
# patient) and a breath in, so a stillness at the prompt may be a breath's turning point
# (test:9: the top of a breath, still for hold_confirm just as the prompt came, let TRANSIT
# start 1.3 s before the patient held). A patient already holding is still holding by then.
ALREADY_HOLDING_CONFIRM = 1.0

# Prompt values (anatomy.motion.Prompt).
_NONE, _HOLD_IN, _HOLD_OUT, _BREATHE = 0, 1, 2, 3


def phase_needs_hold(phase: int, localization_ready: bool) -> bool:
    """Whether the protocol holds the breath for ``phase``: EXPLORE, TRANSIT and PIVOT, and
    the end of LOCALIZE (the registration is ready: the hold the pivot needs starts
    before TRANSIT)."""
    return phase in HOLD_PHASES or (phase == _LOCALIZE and localization_ready)


@dataclasses.dataclass(frozen=True)
class ProtocolState:
    """What the protocol remembers: the current prompt and when it was given, unanswered
    prompts in a row, the sensed onset of the hold in use, the holds used, free breathing
    until ``rest_until``, an error that ends the scan, and the prompts given ((time,
    prompt), ...)."""

    prompt: int = _NONE
    prompted_at: float = -math.inf
    attempts: int = 0
    hold_since: float = math.nan
    holds: int = 0
    rest_until: float = math.nan
    lost_at: float = math.nan  # the estimator stopped sensing the hold in use at this time
    error: str = ""
    prompts: tuple = ()
    allowed: bool = False

    def __deepcopy__(self, memo):
        return self


def _prompt(s: ProtocolState, prompt: int, t: float, **changes) -> ProtocolState:
    return dataclasses.replace(
        s, prompt=prompt, prompted_at=t, prompts=s.prompts + ((float(t), int(prompt)),), **changes
    )


def _rest(s: ProtocolState, t: float, cfg) -> ProtocolState:
    """End the hold in use (if any): "breathe normally", free breathing for recovery_time."""
    changes = dict(hold_since=math.nan, rest_until=t + cfg.recovery_time, allowed=False)
    if s.prompt in (_HOLD_IN, _HOLD_OUT):
        return _prompt(s, _BREATHE, t, **changes)
    return dataclasses.replace(s, **changes)


def protocol_step(
    s: ProtocolState,
    t: float,
    phase: int,
    localization_ready: bool,
    resp_state: int,
    resp_since: float,
    cfg,
) -> ProtocolState:
    """One control period of the breath-hold protocol (module doc). ``resp_state`` and
    ``resp_since``: the estimator's state and when it began. The result's ``allowed`` says
    whether the scan may move (the supervisor's ``motion_allowed``), ``prompt`` what the
    patient is told, ``error`` why the scan must stop ("" while it may go on)."""
    if s.error:
        return dataclasses.replace(s, allowed=False)
    if phase in (_DONE, _ABORT):
        if s.prompt in (_HOLD_IN, _HOLD_OUT):
            return _prompt(s, _BREATHE, t, allowed=False, hold_since=math.nan)
        return s
    if not phase_needs_hold(phase, localization_ready):
        if s.prompt in (_HOLD_IN, _HOLD_OUT) or math.isfinite(s.hold_since):
            return _rest(s, t, cfg)
        return dataclasses.replace(s, allowed=True)
    if not math.isfinite(s.rest_until):
        # The first hold: the patient breathes freely first while the estimator learns.
        return dataclasses.replace(s, rest_until=t + cfg.recovery_time, allowed=False)
    if math.isfinite(s.hold_since):  # a hold is in use
        if t - s.hold_since >= cfg.hold_limit:
            return _rest(s, t, cfg)  # split: breathe, then another hold
        if resp_state != HOLDING and phase != _TRANSIT:
            # Stop at once; the patient let go unless the hold is sensed again soon. (In
            # TRANSIT the probe slides and turns too much to tell: the hold is trusted.)
            lost = s.lost_at if math.isfinite(s.lost_at) else t
            if t - lost >= REGAIN_TIME:
                return _rest(dataclasses.replace(s, lost_at=math.nan), t, cfg)
            return dataclasses.replace(s, lost_at=lost, allowed=False)
        return dataclasses.replace(s, allowed=True, lost_at=math.nan)
    if t < s.rest_until:
        return dataclasses.replace(s, allowed=False)
    hold_prompt = _HOLD_IN if cfg.hold_level == "in" else _HOLD_OUT
    if s.prompt != hold_prompt:
        return _prompt(s, hold_prompt, t, attempts=1, allowed=False)
    if resp_state == HOLDING:
        if float(resp_since) < s.prompted_at and t - s.prompted_at < ALREADY_HOLDING_CONFIRM:
            return dataclasses.replace(s, allowed=False)  # a hold, or a breath's top?
        # The hold counts from the prompt at the earliest (a patient already still).
        since = max(float(resp_since), s.prompted_at)
        return dataclasses.replace(s, hold_since=since, holds=s.holds + 1, attempts=0, allowed=True)
    if t - s.prompted_at >= cfg.hold_wait:
        if s.attempts >= cfg.max_prompts:
            return dataclasses.replace(
                s,
                allowed=False,
                error=(
                    f"no breath-hold sensed after {s.attempts} prompts "
                    f"({cfg.hold_wait:g} s each; respiration.max_prompts)"
                ),
            )
        # Ask again: breathe, then hold.
        s = _prompt(s, _BREATHE, t, allowed=False)
        return _prompt(s, hold_prompt, t, attempts=s.attempts + 1)
    return dataclasses.replace(s, allowed=False)


def gate_step(phase: int, resp_state: int) -> bool:
    """Gated free breathing: EXPLORE and PIVOT move (and the exploration cloud takes frames)
    only at end-expiration or during a hold; the other phases are not held."""
    if phase in (_EXPLORE, _PIVOT):
        return resp_state in (END_EXPIRATION, HOLDING)
    return True
