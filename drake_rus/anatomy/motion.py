"""Patient motion: respiration and a rigid shift of the body, as plain functions.

Breathing and shifting describe the patient, not a fault of the robot: the simulated station
moves the imaged anatomy, the true kidney pose and the contact body by the same displacement
(``drake_rus.patient_body``). The scenario section is ``patient.motion``.

Breathing (docs/facts/anatomy_and_ultrasound.md, "Respiratory motion" and "Breathing
pattern"). The patient's respiratory level u (dimensionless; 0 at the reference
end-expiration, 1 at a mean tidal end-inspiration) moves the kidney craniocaudally by
``amplitude`` x u (inspiration pushes it towards the feet) and the imaged body section with the
abdominal wall by ``ap_amplitude`` x u along the bed's normal, so the probe pressing on the
wall feels every breath. Each breath k is Lujan's cos^2n shape (Lujan 1999; n =
``shape_exponent``): u = e0 + (e1 - e0) s + a_k sin^2n(pi s), s in [0, 1) over its period T_k,
with a long dwell at end-expiration; the period, the depth a_k and the end-expiration level
e vary from breath to breath (``rate_cv``, ``amplitude_cv``, ``end_expiration_sd``; Tobin
1988).

Breath-holds. A patient holds when told (``follows_prompts``: the scan's prompts, heard
``reaction_time`` s later) or on their own schedule (``hold_period``, ``hold_duration``,
``first_hold``). "Breathe in and hold" (the seed's protocol, III-B) takes the patient in one
smooth inspiration to ``hold_depth`` (plus a per-hold offset within
``hold_reproducibility``, Schwartz 1994), "breathe out and hold" to end-expiration; during a
hold the kidney drifts cranially at ``hold_drift`` (the lungs slowly deflate: Holland 1998,
Khot 2020), and the patient lets go after at most a per-hold draw around ``max_hold``
(Tibdewal 2015), or when told to breathe. Then one smooth expiration, and breathing resumes.

Everything is deterministic: every draw is a hash of (seed, what, index). The motion is a
small state machine (:class:`BreathState`, :func:`breath_advance`, :func:`breath_level`):
the simulated station steps it with the prompts it hears (``patient_body.BreathingPatient``);
:class:`BreathingProgram` evaluates it as a function of time when nobody prompts (scheduled
holds or free breathing).
"""

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from drake_rus.config_schema import (
    BREATHING_RATE_MAX,
    BREATHING_RATE_MIN,
    physical,
    seed_metadata,
)

__all__ = [
    "BreathingConfig",
    "PatientShiftConfig",
    "PatientMotionConfig",
    "PatientMotion",
    "Prompt",
    "BreathState",
    "breath_start",
    "breath_advance",
    "breath_level",
    "breath_rate",
    "breath_prompted",
    "breath_holding",
    "scheduled_prompts",
    "BreathingProgram",
    "breath_hold",
    "hold_windows",
    "breathing_displacement",
    "shift_offset",
    "patient_offset_B",
    "HOLD_LEVELS",
]

HOLD_LEVELS = ["inspiration", "expiration"]


class Prompt:
    """What the scan tells the patient (the ``breath_prompt`` value): nothing, "breathe in
    and hold", "breathe out and hold", "breathe normally"."""

    NONE = 0
    HOLD_IN = 1
    HOLD_OUT = 2
    BREATHE = 3

    TEXT = {
        NONE: "",
        HOLD_IN: "breathe in ... and hold",
        HOLD_OUT: "breathe out ... and hold",
        BREATHE: "breathe normally",
    }


@dataclass
class BreathingConfig:
    """How the simulated patient breathes (module doc). The human ranges of the fields are
    stated once, beside them; the rules between fields (scheduled holds end before the next
    one starts, with a breath between them) in ``drake_rus.config_schema.CROSS_FIELD_RULES``.
    """

    enabled: bool = False
    # Peak-to-peak craniocaudal kidney displacement of a mean tidal breath (m).
    amplitude: float = field(
        default=0.010,
        metadata=physical(
            0.0,
            0.045,
            "m",
            "craniocaudal kidney motion is 2.5-30 mm in quiet breathing "
            "(van Sornsen de Koste 2006) and up to 43 mm from deep inspiration to deep "
            "expiration (Schwartz 1994)",
        ),
    )
    # Peak-to-peak anteroposterior displacement of the imaged section and the abdominal
    # wall under the probe (m, along the bed's normal), with the same timing.
    ap_amplitude: float = field(
        default=0.004,
        metadata=physical(
            0.0,
            0.010,
            "m",
            "the kidney moves 0.6-8.0 mm anteroposteriorly with respiration (Yamashita "
            "2014); the section under the probe moves with it",
        ),
    )
    # Mean breaths per minute.
    rate_per_min: float = field(
        default=15.0,
        metadata=physical(
            BREATHING_RATE_MIN,
            BREATHING_RATE_MAX,
            "breaths/min",
            "patients breathed 9-27.5 times a minute during 4D-CT (Pham 2013)",
        ),
    )
    # n of Lujan's cos^2n breath (1: a sinusoid; larger: a longer end-expiratory dwell).
    shape_exponent: float = field(
        default=2.0,
        metadata=physical(
            1.0, 3.0, "1", "Lujan 1999's breathing model uses n = 1-3 (cos^4: n = 2)"
        ),
    )
    # Breath-to-breath coefficients of variation of the period and the depth.
    rate_cv: float = field(
        default=0.2,
        metadata=physical(
            0.0,
            0.5,
            "1",
            "resting breath-to-breath CV of the frequency 20.8 +- 11.5 % (Tobin 1988)",
        ),
    )
    amplitude_cv: float = field(
        default=0.25,
        metadata=physical(
            0.0,
            0.5,
            "1",
            "resting breath-to-breath CV of the tidal volume 33 +- 15 % (Tobin 1988)",
        ),
    )
    # Standard deviation of the end-expiration level from breath to breath (m, along the
    # craniocaudal axis).
    end_expiration_sd: float = field(
        default=0.0005,
        metadata=physical(
            0.0,
            0.004,
            "m",
            "repeated respiratory positions of the kidney agree within 4 mm (Schwartz 1994)",
        ),
    )
    # --- breath-holds ---
    # The patient holds when the scan tells them (its breath_prompt), reaction_time s later.
    follows_prompts: bool = True
    reaction_time: float = field(
        default=0.5,
        metadata=physical(0.0, 3.0, "s", "a spoken instruction is followed within seconds"),
    )
    # The level of a scheduled hold (a prompted one says which): "inspiration" holds at
    # hold_depth, "expiration" at end-expiration.
    hold_level: str = field(default="inspiration", metadata={"choices": HOLD_LEVELS})
    # Depth of an inspiratory hold in mean tidal breaths (1: a normal breath in).
    hold_depth: float = field(
        default=1.0,
        metadata=physical(
            0.3,
            4.0,
            "tidal breaths",
            "deep inspiration moves the kidney up to 39-43 mm (Schwartz 1994), about 4 "
            "tidal breaths of 10 mm",
        ),
    )
    # Each hold lands within this of its level (m, craniocaudal; a fixed draw per hold).
    hold_reproducibility: float = field(
        default=0.002,
        metadata=physical(
            0.0,
            0.007,
            "m",
            "repeat breath-holds put the kidney within 4 mm on average, 6.9 mm at most "
            "(Schwartz 1994)",
        ),
    )
    # Cranial drift of the kidney during a hold (m/s; each hold draws 0.5-1.5 x this).
    hold_drift: float = field(
        default=0.00015,
        metadata=physical(
            0.0,
            0.001,
            "m/s",
            "the diaphragm drifts up 0.15 mm/s in an end-expiratory hold (Holland 1998) and "
            "up to 5.6 mm in 24 s of inspiratory hold (Khot 2020)",
        ),
    )
    # How long the patient can hold (s; each hold draws 0.75-1.25 x this).
    max_hold: float = field(
        default=21.0,
        metadata=physical(
            5.0,
            60.0,
            "s",
            "lung cancer patients held a deep inspiration for a median 21 s (Tibdewal 2015)",
        ),
    )
    # Holds on the patient's own schedule: one every hold_period s for hold_duration s from
    # first_hold; hold_period 0: none.
    hold_period: float = field(default=0.0, metadata={"min": 0.0})
    hold_duration: float = field(default=8.0, metadata={"min": 0.0})
    first_hold: float = field(default=0.0, metadata={"min": 0.0})


@dataclass
class PatientShiftConfig:
    """The patient shifts rigidly by ``offset`` (m, in the robot base frame) at ``time``,
    ramped over ``ramp`` s. The label volume, the true kidney pose and the contact body all
    move (the station puts the torso on driven joints when the patient moves)."""

    enabled: bool = False
    time: float = field(default=10.0, metadata={"min": 0.0})
    offset: list[float] = field(
        default_factory=lambda: [0.0, 0.01, 0.0], metadata={"length": 3, "min": -0.02, "max": 0.02}
    )
    ramp: float = field(default=0.5, metadata={"positive": True})


@dataclass
class PatientMotionConfig:
    """How the patient moves during the scan (simulation; off by default)."""

    breathing: BreathingConfig = field(default_factory=BreathingConfig)
    shift: PatientShiftConfig = field(default_factory=PatientShiftConfig)
    # Seed of the breathing draws; combined with the scenario's random_seed.
    seed: int = field(default=0, metadata=seed_metadata())

    @property
    def moves(self) -> bool:
        return self.breathing.enabled or self.shift.enabled


# ----------------------------------------------------------------------------- draws
def _draw(seed: int, what: int, k: int) -> np.random.Generator:
    return np.random.default_rng([int(seed) & 0x7FFFFFFF, what, max(int(k), 0)])


_PERIOD, _DEPTH, _LEVEL, _HOLD = 1, 2, 3, 4


def _u(cfg: BreathingConfig, metres: float) -> float:
    """A craniocaudal length (m) in units of the tidal amplitude."""
    return metres / cfg.amplitude if cfg.amplitude > 0 else 0.0


def _period(cfg: BreathingConfig) -> float:
    return 60.0 / cfg.rate_per_min


def _breath_draw(cfg: BreathingConfig, seed: int, k: int) -> tuple[float, float, float]:
    """(period s, depth, end level) of breath k: the mean period and depth varied by their
    CVs (clipped to 0.5-1.5 x and 0.3-2 x), the end level by end_expiration_sd."""
    rng = _draw(seed, _PERIOD, k)
    z = rng.standard_normal(3)
    T = _period(cfg) * float(np.clip(1.0 + cfg.rate_cv * z[0], 0.5, 1.5))
    a = float(np.clip(1.0 + cfg.amplitude_cv * z[1], 0.3, 2.0))
    e = _u(cfg, cfg.end_expiration_sd) * float(np.clip(z[2], -3.0, 3.0))
    return T, a, e


def _hold_draw(cfg: BreathingConfig, seed: int, k: int) -> tuple[float, float, float]:
    """(level offset, drift rate 1/s, longest hold s) of hold k."""
    rng = _draw(seed, _HOLD, k)
    offset = _u(cfg, cfg.hold_reproducibility) * float(rng.uniform(-1.0, 1.0))
    drift = _u(cfg, cfg.hold_drift) * float(rng.uniform(0.5, 1.5))
    longest = cfg.max_hold * float(rng.uniform(0.75, 1.25))
    return offset, drift, longest


# ----------------------------------------------------------------------------- state
BREATH, MOVE_TO_HOLD, HOLD, MOVE_TO_BREATH = "breath", "to_hold", "hold", "to_breath"


@dataclass(frozen=True)
class BreathState:
    """Where the patient is in their breathing: the current segment (``kind``: a breath, a
    move to or from a hold, a hold) from ``t0`` for ``T`` s (a hold: until ``t0 + T`` at the
    latest), its levels (``u0`` start, ``u1`` end, ``a`` a breath's depth; a hold's drift
    rate ``a``), the breath and hold counters, and a heard prompt not yet acted on
    (``pending`` kind, at ``pending_t``)."""

    kind: str = BREATH
    t0: float = 0.0
    T: float = 4.0
    u0: float = 0.0
    u1: float = 0.0
    a: float = 1.0
    breath: int = 0
    hold: int = 0
    pending: int = Prompt.NONE
    pending_t: float = math.inf
    last_prompt: int = Prompt.NONE

    # Immutable: Drake's clones may share it.
    def __deepcopy__(self, memo):
        return self


def _breath_segment(cfg, seed, k: int, t0: float, u0: float) -> BreathState:
    T, a, e = _breath_draw(cfg, seed, k)
    return BreathState(kind=BREATH, t0=t0, T=T, u0=u0, u1=e, a=a, breath=k)


def _move(kind: str, t0: float, u0: float, u1: float, cfg) -> tuple:
    """(T) of a smooth move from u0 to u1: half a breath for a tidal breath's depth, in
    proportion (0.25-2 tidal breaths)."""
    return 0.5 * _period(cfg) * float(np.clip(abs(u1 - u0), 0.25, 2.0))


def breath_start(cfg: BreathingConfig, seed: int = 0) -> BreathState:
    """The patient at t = 0: starting a breath from end-expiration."""
    return _breath_segment(cfg, seed, 0, 0.0, 0.0)


def breath_level(s: BreathState, t: float, cfg: BreathingConfig) -> float:
    """Respiratory level u at time t (>= s.t0) within the segment ``s``."""
    tau = max(0.0, t - s.t0)
    if s.kind == HOLD:
        return s.u0 - s.a * tau
    x = min(1.0, tau / s.T) if s.T > 0 else 1.0
    if s.kind == BREATH:
        return s.u0 + (s.u1 - s.u0) * x + s.a * math.sin(math.pi * x) ** (2.0 * cfg.shape_exponent)
    return s.u0 + (s.u1 - s.u0) * 0.5 * (1.0 - math.cos(math.pi * x))


def breath_rate(s: BreathState, t: float, cfg: BreathingConfig) -> float:
    """du/dt (1/s) at time t within the segment ``s``."""
    tau = max(0.0, t - s.t0)
    if s.kind == HOLD:
        return -s.a
    if s.T <= 0 or tau >= s.T:
        return 0.0
    x = tau / s.T
    if s.kind == BREATH:
        n2 = 2.0 * cfg.shape_exponent
        sn = math.sin(math.pi * x)
        dshape = n2 * math.copysign(abs(sn) ** (n2 - 1.0), sn) * math.cos(math.pi * x) * math.pi
        return ((s.u1 - s.u0) + s.a * dshape) / s.T
    return (s.u1 - s.u0) * 0.5 * math.pi * math.sin(math.pi * x) / s.T


def breath_holding(s: BreathState) -> bool:
    """Whether the patient is holding their breath (the truth the estimator is judged
    against)."""
    return s.kind == HOLD


def _hold_target(cfg, seed, k: int, kind: int) -> tuple[float, float, float]:
    offset, drift, longest = _hold_draw(cfg, seed, k)
    level = cfg.hold_depth if kind == Prompt.HOLD_IN else 0.0
    return level + offset, drift, longest


def _act(s: BreathState, t: float, cfg, seed) -> BreathState:
    """The pending prompt takes effect at time t (its time)."""
    kind = s.pending
    s = dataclasses.replace(s, pending=Prompt.NONE, pending_t=math.inf)
    u = breath_level(s, t, cfg)
    if kind in (Prompt.HOLD_IN, Prompt.HOLD_OUT):
        if s.kind in (HOLD, MOVE_TO_HOLD):
            return s
        target, _, _ = _hold_target(cfg, seed, s.hold, kind)
        T = _move(MOVE_TO_HOLD, t, u, target, cfg)
        return dataclasses.replace(s, kind=MOVE_TO_HOLD, t0=t, T=T, u0=u, u1=target, a=float(kind))
    if kind == Prompt.BREATHE and s.kind in (HOLD, MOVE_TO_HOLD):
        return _release(s, t, u, cfg, seed)
    return s


def _release(s: BreathState, t: float, u: float, cfg, seed) -> BreathState:
    """End a hold (or a move into one) at time t: one smooth expiration to the next breath's
    starting level."""
    _, _, e = _breath_draw(cfg, seed, s.breath + 1)
    hold = s.hold + 1 if s.kind == HOLD else s.hold
    return dataclasses.replace(
        s, kind=MOVE_TO_BREATH, t0=t, T=_move(MOVE_TO_BREATH, t, u, e, cfg), u0=u, u1=e, hold=hold
    )


def _segment_end(s: BreathState) -> float:
    return s.t0 + s.T


def _next_segment(s: BreathState, cfg, seed) -> BreathState:
    """The segment after ``s`` ends (at its end time)."""
    t = _segment_end(s)
    if s.kind == BREATH:
        nxt = _breath_segment(cfg, seed, s.breath + 1, t, s.u1)
    elif s.kind == MOVE_TO_BREATH:
        nxt = _breath_segment(cfg, seed, s.breath + 1, t, s.u1)
    elif s.kind == MOVE_TO_HOLD:
        _, drift, longest = _hold_draw(cfg, seed, s.hold)
        nxt = BreathState(kind=HOLD, t0=t, T=longest, u0=s.u1, u1=s.u1, a=drift, breath=s.breath)
        nxt = dataclasses.replace(nxt, hold=s.hold)
    else:  # HOLD ran out: the patient lets go
        return _release(s, t, breath_level(s, t, cfg), cfg, seed)
    return dataclasses.replace(
        nxt, hold=s.hold, pending=s.pending, pending_t=s.pending_t, last_prompt=s.last_prompt
    )


def breath_prompted(s: BreathState, prompt: int, t: float, cfg: BreathingConfig) -> BreathState:
    """The patient hears ``prompt`` (a :class:`Prompt`) at time t; it takes effect
    ``reaction_time`` later (a repeated prompt changes nothing)."""
    if prompt == Prompt.NONE or prompt == s.last_prompt:
        return s
    return dataclasses.replace(
        s, pending=int(prompt), pending_t=t + cfg.reaction_time, last_prompt=int(prompt)
    )


def breath_advance(s: BreathState, t: float, cfg: BreathingConfig, seed: int = 0) -> BreathState:
    """The state at time t: every segment end and heard prompt up to t, in order."""
    for _ in range(100000):
        end = _segment_end(s)
        if s.pending_t <= t and s.pending_t <= end:
            s = _act(s, s.pending_t, cfg, seed)
        elif end <= t:
            s = _next_segment(s, cfg, seed)
        else:
            return s
    raise RuntimeError("breath_advance: no progress (a zero-length segment?)")


def scheduled_prompts(cfg: BreathingConfig, t_end: float) -> list[tuple[float, int]]:
    """[(time s, Prompt)] of the patient's own holds up to t_end: a hold at first_hold +
    k hold_period (at ``hold_level``), a release hold_duration later."""
    if not cfg.enabled or cfg.hold_period <= 0.0 or cfg.hold_duration <= 0.0:
        return []
    kind = Prompt.HOLD_IN if cfg.hold_level == "inspiration" else Prompt.HOLD_OUT
    out, start = [], cfg.first_hold
    while start < t_end:
        out.append((start, kind))
        out.append((start + min(cfg.hold_duration, cfg.hold_period), Prompt.BREATHE))
        start += cfg.hold_period
    return out


class BreathingProgram:
    """The breathing of a patient nobody prompts (free breathing and scheduled holds) as a
    function of time: ``level(t)``, ``rate(t)``, ``holding(t)``. Queries in increasing time
    reuse the last state; an earlier time starts over."""

    def __init__(self, cfg: BreathingConfig, seed: int = 0):
        self.cfg = cfg
        self.seed = int(seed)
        self._reset()

    def _reset(self):
        self._state = breath_start(self.cfg, self.seed)
        self._t = 0.0
        self._prompts = []
        self._next = 0
        self._horizon = 0.0

    def state(self, t: float) -> BreathState:
        t = max(0.0, float(t))
        if t < self._t:
            self._reset()
        if t >= self._horizon:
            self._horizon = t + 600.0
            self._prompts = scheduled_prompts(self.cfg, self._horizon)
        s = self._state
        while self._next < len(self._prompts) and self._prompts[self._next][0] <= t:
            when, kind = self._prompts[self._next]
            s = breath_advance(s, when, self.cfg, self.seed)
            # A scheduled hold is the patient's own: no reaction time.
            s = dataclasses.replace(s, pending=kind, pending_t=when, last_prompt=kind)
            self._next += 1
        s = breath_advance(s, t, self.cfg, self.seed)
        self._state, self._t = s, t
        return s

    def level(self, t: float) -> float:
        if not self.cfg.enabled:
            return 0.0
        return breath_level(self.state(t), t, self.cfg)

    def rate(self, t: float) -> float:
        if not self.cfg.enabled:
            return 0.0
        return breath_rate(self.state(t), t, self.cfg)

    def holding(self, t: float) -> bool:
        return self.cfg.enabled and breath_holding(self.state(t))


def breath_hold(t: float, cfg: BreathingConfig, seed: int = 0) -> bool:
    """True while a patient nobody prompts holds their breath at time t (s)."""
    return BreathingProgram(cfg, seed).holding(t)


def hold_windows(t_end: float, cfg: BreathingConfig, seed: int = 0, step: float = 0.01):
    """The breath-hold windows [(start, end)] up to t_end (s) of a patient nobody prompts,
    sampled every ``step`` s."""
    program = BreathingProgram(cfg, seed)
    out, start = [], None
    for t in np.arange(0.0, t_end + step / 2, step):
        h = program.holding(float(t))
        if h and start is None:
            start = float(t)
        if not h and start is not None:
            out.append((start, float(t)))
            start = None
    if start is not None:
        out.append((start, float(t_end)))
    return out


def breathing_displacement(t: float, cfg: BreathingConfig, seed: int = 0) -> float:
    """Craniocaudal kidney displacement (m, towards the feet positive) at time t of a
    patient nobody prompts."""
    return cfg.amplitude * BreathingProgram(cfg, seed).level(t)


def shift_offset(t: float, cfg: PatientShiftConfig) -> np.ndarray:
    """Rigid patient shift (m, robot base frame) at time t: 0 before cfg.time, ramped
    linearly to cfg.offset over cfg.ramp s."""
    if not cfg.enabled or t <= cfg.time:
        return np.zeros(3)
    s = min(1.0, (t - cfg.time) / cfg.ramp)
    return s * np.asarray(cfg.offset, dtype=float)


def shift_velocity(t: float, cfg: PatientShiftConfig) -> np.ndarray:
    """d shift_offset / dt (m/s)."""
    if not cfg.enabled or t <= cfg.time or t >= cfg.time + cfg.ramp:
        return np.zeros(3)
    return np.asarray(cfg.offset, dtype=float) / cfg.ramp


def patient_offset_B(
    level: float,
    t: float,
    breathing: BreathingConfig,
    shift: PatientShiftConfig,
    superior_B: np.ndarray,
    up_B: np.ndarray,
) -> np.ndarray:
    """Total displacement (m, base frame) of the imaged anatomy at respiratory level u =
    ``level`` and time t: the kidney ``amplitude`` u caudally, the section ``ap_amplitude``
    u along the bed's normal ``up_B``, plus the shift."""
    d = -breathing.amplitude * level * np.asarray(superior_B, dtype=float)
    d = d + breathing.ap_amplitude * level * np.asarray(up_B, dtype=float)
    return d + shift_offset(t, shift)


class PatientMotion:
    """One patient's motion in the robot base frame B: the config, the patient's superior
    axis and bed normal in B and a seed. ``offset_B(t)`` and ``velocity_B(t)`` (m, m/s)
    and ``breath_hold(t)`` are those of a patient nobody prompts
    (:class:`BreathingProgram`); the simulated station steps a prompted patient itself."""

    def __init__(self, config: PatientMotionConfig, superior_B, seed: int = 0, up_B=(0, 0, 1)):
        self.config = config
        self.superior_B = np.asarray(superior_B, dtype=float).reshape(3)
        self.up_B = np.asarray(up_B, dtype=float).reshape(3)
        self.seed = int(seed)
        self.program = BreathingProgram(config.breathing, self.seed)

    @property
    def moves(self) -> bool:
        return self.config.moves

    def offset_at(self, level: float, t: float) -> np.ndarray:
        """The displacement (m, B) at respiratory level ``level`` and time t."""
        return patient_offset_B(
            level, t, self.config.breathing, self.config.shift, self.superior_B, self.up_B
        )

    def velocity_at(self, level_rate: float, t: float) -> np.ndarray:
        """d offset / dt (m/s, B) at respiratory rate du/dt = ``level_rate`` and time t."""
        b = self.config.breathing
        v = -b.amplitude * level_rate * self.superior_B + b.ap_amplitude * level_rate * self.up_B
        return v + shift_velocity(t, self.config.shift)

    def offset_B(self, t: float) -> np.ndarray:
        return self.offset_at(self.program.level(t), t)

    def velocity_B(self, t: float) -> np.ndarray:
        return self.velocity_at(self.program.rate(t), t)

    def breath_hold(self, t: float) -> bool:
        return self.program.holding(t)
