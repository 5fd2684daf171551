"""Fault-injection configuration: the scenario's ``faults`` section (sensor faults).

Patient motion (breathing, a shift) is not a fault: it describes the patient
(``patient.motion``, :mod:`drake_rus.anatomy.motion`).

Every fault is off by default, so a scenario without a ``faults`` section runs exactly as
before. Times are simulated seconds from the start of the run, SI units otherwise
(m, N, s); rates say ``_per_min``.
"""

from dataclasses import dataclass, field

from drake_rus.config_schema import seed_metadata

__all__ = ["FaultConfig", "SensorFaultConfig", "FAULT_KINDS"]

# Sensor fault kinds (SensorFaultConfig.kind).
FAULT_KINDS = [
    "none",
    "image_dropout",
    "frozen_image",
    "segmentation_miss",
    "segmentation_false_positive",
    "force_spike",
    "force_bias",
    "joint_state_delay",
    "nan_joint_position",
    "nan_joint_velocity",
    "nan_force",
    "nan_pose",
    "nan_image",
]


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
class FaultConfig:
    """Sensor faults injected into the simulated station by ``drake_rus.reliability``."""

    sensor: list[SensorFaultConfig] = field(default_factory=list)
    # Seed of the fault draws (which frames drop); combined with random_seed.
    seed: int = field(default=0, metadata=seed_metadata())

    @property
    def active_sensor_faults(self) -> list:
        return [f for f in self.sensor if f.kind != "none"]
