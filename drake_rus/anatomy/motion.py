"""Patient motion: respiration and a rigid shift of the body, as pure functions of time.

Breathing and shifting describe the patient, not a fault of the robot: the simulated station
moves the imaged anatomy, the true kidney pose and the contact body by the same displacement
(``drake_rus.patient_body``), and exports ``breath_hold`` (1 during a breath-hold, what a
respiratory belt or the operator tells a real setup). The scenario section is
``patient.motion``. Everything is deterministic: the only draw (where each breath-hold lands)
is a hash of (seed, hold index).

Published motion (docs/facts/anatomy_and_ultrasound.md): craniocaudal kidney motion with
respiration 7-11 mm on average in quiet breathing, 20-30 mm in some patients and about 40 mm
in deep breathing; breath-hold position reproducible within a few mm.
"""

import math
from dataclasses import dataclass, field

import numpy as np

from drake_rus.config_schema import BREATHING_RATE_MAX, BREATHING_RATE_MIN, physical

__all__ = [
    "BreathingConfig",
    "PatientShiftConfig",
    "PatientMotionConfig",
    "PatientMotion",
    "breath_hold",
    "hold_windows",
    "breathing_displacement",
    "shift_offset",
    "patient_offset_B",
]


@dataclass
class BreathingConfig:
    """Craniocaudal respiratory motion of the kidney and skin.

    The displacement along the patient's superior axis is
    d(t) = amplitude * (1 - cos(2 pi f t)) / 2, f = rate_per_min / 60 (0 at end-expiration,
    amplitude at end-inspiration). Every hold_period s the patient holds their breath at
    end-expiration for hold_duration s; each hold lands within hold_reproducibility of the
    reference position (a fixed per-hold draw).

    The human ranges of amplitude and rate, and the rules between the fields (a hold ends
    before the next one starts, with at least one breath between them), are stated once: the
    ranges beside the fields below, the rules in ``drake_rus.config_schema.CROSS_FIELD_RULES``.
    """

    enabled: bool = False
    # Peak-to-peak craniocaudal displacement (m).
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
    # Breaths per minute.
    rate_per_min: float = field(
        default=15.0,
        metadata=physical(
            BREATHING_RATE_MIN,
            BREATHING_RATE_MAX,
            "breaths/min",
            "patients breathed 9-27.5 times a minute during 4D-CT (Pham 2013)",
        ),
    )
    # Breath-holds: 0 disables them (free breathing only).
    hold_period: float = field(default=12.0, metadata={"min": 0.0})
    hold_duration: float = field(default=8.0, metadata={"min": 0.0})
    hold_reproducibility: float = field(default=0.002, metadata={"min": 0.0, "max": 0.01})
    # First hold starts at this time (s).
    first_hold: float = field(default=0.0, metadata={"min": 0.0})
    # Respiration-aware scanning: exploration and pivot motion advance, and the cloud
    # accumulator keeps exploration frames, only during breath-holds (the station's
    # ``breath_hold`` output drives the supervisor's ``motion_allowed`` input).
    gate_exploration: bool = False


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
    # Seed of the breath-hold draws; combined with the scenario's random_seed.
    seed: int = field(default=0, metadata={"min": 0})

    @property
    def moves(self) -> bool:
        return self.breathing.enabled or self.shift.enabled


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
    """True while the patient holds their breath at time t (s); always True without
    breathing."""
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
        return A * 0.5 * (1.0 - math.cos(2.0 * math.pi * n * (cfg.first_hold - t) / cfg.first_hold))
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


def patient_offset_B(
    t: float,
    breathing: BreathingConfig,
    shift: PatientShiftConfig,
    superior_B: np.ndarray,
    seed: int = 0,
) -> np.ndarray:
    """Total displacement (m, base frame) of the imaged anatomy at time t."""
    d = breathing_displacement(t, breathing, seed)
    return -d * np.asarray(superior_B, dtype=float) + shift_offset(t, shift)


class PatientMotion:
    """One patient's motion in the robot base frame B: ``offset_B(t)`` (m) and
    ``breath_hold(t)``, for a motion config, the patient's superior axis in B and a seed."""

    def __init__(self, config: PatientMotionConfig, superior_B, seed: int = 0):
        self.config = config
        self.superior_B = np.asarray(superior_B, dtype=float).reshape(3)
        self.seed = int(seed)

    @property
    def moves(self) -> bool:
        return self.config.moves

    def offset_B(self, t: float) -> np.ndarray:
        return patient_offset_B(
            t, self.config.breathing, self.config.shift, self.superior_B, self.seed
        )

    def velocity_B(self, t: float, h: float = 1e-4) -> np.ndarray:
        """d offset_B / dt (m/s) by a central difference (one-sided at t = 0)."""
        t0 = max(0.0, t - h)
        return (self.offset_B(t + h) - self.offset_B(t0)) / (t + h - t0)

    def breath_hold(self, t: float) -> bool:
        return breath_hold(t, self.config.breathing)
