"""Fault-injection and patient-motion configuration: the scenario's ``faults`` section.

Every fault is off by default, so a scenario without a ``faults`` section runs exactly as
before. Times are simulated seconds from the start of the run, SI units otherwise
(m, N, s); rates say ``_per_min``.
"""

from dataclasses import dataclass, field

__all__ = ["FaultConfig", "BreathingConfig", "PatientShiftConfig", "SensorFaultConfig",
           "FAULT_KINDS"]

# Sensor fault kinds (SensorFaultConfig.kind).
FAULT_KINDS = ["none", "image_dropout", "frozen_image", "segmentation_miss",
               "segmentation_false_positive", "force_spike", "force_bias", "joint_state_delay",
               "nan_joint_position", "nan_joint_velocity", "nan_force", "nan_pose", "nan_image"]


@dataclass
class SensorFaultConfig:
    """One corrupted sensor stream of the simulated station, active in [start, start+duration).

    kind:
      image_dropout            frames are lost (the image stream stops updating);
      frozen_image             the same frame is delivered again with fresh time stamps;
      segmentation_miss        the kidney vanishes from the frames (all tissue -> background);
      segmentation_false_positive  a kidney-like blob appears where there is none;
      force_spike              the force sensor reads an extra magnitude N pressing force
                               in short pulses (spike_width s every spike_period s);
      force_bias               the force sensor reads a constant extra magnitude N;
      joint_state_delay        joint positions and velocities arrive delay s late;
      nan_*                    NaN in the joint positions, velocities, force, probe pose or
                               image.
    """
    kind: str = field(default="none", metadata={"choices": FAULT_KINDS})
    start: float = field(default=5.0, metadata={"min": 0.0})
    # Duration (s); a large value means "to the end of the run".
    duration: float = field(default=1.0e9, metadata={"positive": True})
    # Force faults: magnitude (N) added to the pressing force F_z.
    magnitude: float = field(default=30.0, metadata={"min": -100.0, "max": 100.0})
    spike_period: float = field(default=0.5, metadata={"positive": True})
    spike_width: float = field(default=0.02, metadata={"positive": True})
    # joint_state_delay: the delay (s).
    delay: float = field(default=0.1, metadata={"min": 0.0, "max": 1.0})
    # Image faults: the fraction of frames affected inside the window (1 = all).
    probability: float = field(default=1.0, metadata={"min": 0.0, "max": 1.0})


@dataclass
class BreathingConfig:
    """Craniocaudal respiratory motion of the kidney and skin (facts: 7-11 mm mean, up to
    20-30 mm; breath-hold reproducibility < 4 mm); the contact body moves with it.

    The displacement along the patient's superior axis is
    d(t) = amplitude * (1 - cos(2 pi f t)) / 2, f = rate_per_min / 60 (0 at end-expiration,
    amplitude at end-inspiration). Every hold_period s the patient holds their breath at
    end-expiration for hold_duration s; each hold lands within hold_reproducibility of the
    reference position (a fixed per-hold draw).
    """
    enabled: bool = False
    amplitude: float = field(default=0.010, metadata={"min": 0.0, "max": 0.03})
    rate_per_min: float = field(default=15.0, metadata={"min": 6.0, "max": 30.0})
    # Breath-holds: 0 disables them (free breathing only).
    hold_period: float = field(default=12.0, metadata={"min": 0.0})
    hold_duration: float = field(default=8.0, metadata={"min": 0.0})
    hold_reproducibility: float = field(default=0.002, metadata={"min": 0.0, "max": 0.01})
    # First hold starts at this time (s).
    first_hold: float = field(default=0.0, metadata={"min": 0.0})
    # Respiration-aware scanning: exploration and pivot motion advance, and the cloud
    # accumulator keeps exploration frames, only during breath-holds (the station exports
    # ``breath_hold``; the supervisor's ``motion_allowed`` input).
    gate_exploration: bool = False


@dataclass
class PatientShiftConfig:
    """The patient shifts rigidly by ``offset`` (m, in the robot base frame) at ``time``,
    ramped over ``ramp`` s. The label volume, the true kidney pose and the contact body all
    move (the station puts the torso on driven joints when the patient moves)."""
    enabled: bool = False
    time: float = field(default=10.0, metadata={"min": 0.0})
    offset: list[float] = field(default_factory=lambda: [0.0, 0.01, 0.0],
                                metadata={"length": 3, "min": -0.02, "max": 0.02})
    ramp: float = field(default=0.5, metadata={"positive": True})


@dataclass
class FaultConfig:
    """Faults injected into the simulated station (ignored on hardware)."""
    sensor: list[SensorFaultConfig] = field(default_factory=list)
    breathing: BreathingConfig = field(default_factory=BreathingConfig)
    patient_shift: PatientShiftConfig = field(default_factory=PatientShiftConfig)
    # Seed of the fault draws (which frames drop, hold offsets); combined with random_seed.
    seed: int = field(default=0, metadata={"min": 0})

    @property
    def active_sensor_faults(self) -> list:
        return [f for f in self.sensor if f.kind != "none"]

    @property
    def moves_patient(self) -> bool:
        return self.breathing.enabled or self.patient_shift.enabled
