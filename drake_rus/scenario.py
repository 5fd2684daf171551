"""Typed scenarios: everything a run needs, loaded from ``diagrams/*.scenarios.yaml``.

One YAML file holds named scenarios (top-level keys); YAML anchors let one scenario reuse
another's sections. Loading validates the raw YAML against these dataclasses first, so a
misspelt key, a wrong type or a missing file gives one :class:`ScenarioError` that names the
file, the scenario and the field, then builds the dataclasses with Drake's
``yaml_load_typed`` (as Drake's hardware_sim example and the manipulation course do).

Units are SI (m, rad, N, s, kg) unless a field name says otherwise (``_deg``, ``_hz``).
"""

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from pydrake.common.schema import Transform
from pydrake.common.yaml import yaml_load_file, yaml_load_typed

from drake_rus.anatomy.motion import PatientMotionConfig
from drake_rus.config_schema import (
    ScenarioError,
    check_dataclass_values,
    check_duplicate_keys,
    check_nesting_depth,
    check_physical,
    physical,
    schema_transform,
    seed_metadata,
    validate,
    yaml_error_text,
)
from drake_rus.control.config import ControllerConfig, RespirationConfig, SafetyConfig
from drake_rus.hardware.config import HardwareConfig
from drake_rus.imaging.config import ImagingConfig
from drake_rus.localization.config import LocalizationConfig
from drake_rus.paths import DIAGRAMS_DIR
from drake_rus.reliability.config import FaultConfig
from drake_rus.scan.config import PerceptionConfig, StartConfig, VerdictConfig

__all__ = [
    "ContactConfig",
    "PatientConfig",
    "ProbeCalibration",
    "RobotConfig",
    "Scenario",
    "ScenarioError",
    "LoadScenario",
    "ListScenarios",
    "DEFAULT_SCENARIOS_FILE",
]

DEFAULT_SCENARIOS_FILE = DIAGRAMS_DIR / "default.scenarios.yaml"

# FR3 joint limits (rad), docs/facts/fr3.md "Limits (current FR3 specification, 2025)".
FR3_Q_MIN = [-2.9007, -1.8361, -2.9007, -3.0770, -2.8763, 0.4398, -3.0508]
FR3_Q_MAX = [2.9007, 1.8361, 2.9007, -0.1169, 2.8763, 4.6216, 3.0508]


# Mesh resolution hints, measured with the press of `benchmarks/station.py` (6 s, 9 N): the
# settled force is 9.00 +- 0.03 N at every probe hint from 20 mm (default) to 0.5 mm, while
# the simulation runs 2x slower at 2 mm, 5.6x at 1 mm and 10x at 0.5 mm than at 20 mm (the
# probe face, a 50 mm-radius arc 20 mm wide, is then ~160 / 310 / 630 facets around; at
# 1e-6 m one simulated second took 42 s). The placeholder torso (ellipsoid, 0.17 x 0.40 x
# 0.12 m semi-axes) gives the same force from 6 cm to 5 mm tetrahedra; at 1 cm its mesh takes
# 3x longer to build than at 6 cm, and it grows with the cube of 1/hint.
PROBE_HINT_WHY = (
    "the probe face is a 50 mm-radius arc 20 mm wide: the contact force is the "
    "same from 20 mm to 0.5 mm, and below 2 mm only the contact work grows"
)
PATIENT_HINT_WHY = (
    "the placeholder torso is 0.34 x 0.8 x 0.24 m; its contact force is the "
    "same from 6 cm to 5 mm tetrahedra, and below 1 cm only its mesh grows "
    "(with the cube of 1/hint)"
)


@dataclass
class RobotConfig:
    """The FR3 arm. The robot base frame B is the world frame (z up)."""

    # Model file, as a package:// URL resolved through models/package.xml.
    model: str = "package://drake_rus_models/fr3/fr3.urdf"
    # Joint configuration at t = 0 (rad): probe pointing down above the patient placeholder.
    # A scan on a patient starts at its planned start pose, in the posture closest to this
    # one (the arm's redundancy at a fixed probe pose: the elbow's split).
    initial_joint_positions: list[float] = field(
        default_factory=lambda: [0.0, 0.15, 0.0, -2.0, 0.0, 2.15, 0.785],
        metadata={
            "length": 7,
            "element_min": FR3_Q_MIN,
            "element_max": FR3_Q_MAX,
            "element_label": "the FR3 joint",
            "unit": "rad",
            "why": "docs/facts/fr3.md, 'Limits'",
        },
    )
    # Stiffness (N m/rad) and damping (N m s/rad) of the velocity driver's implicit joint PD,
    # which tracks the integrated velocity command like the FR3's joint-velocity mode.
    driver_kp: list[float] = field(
        default_factory=lambda: [3000.0, 3000.0, 3000.0, 3000.0, 800.0, 800.0, 400.0],
        metadata={"length": 7, "positive": True},
    )
    driver_kd: list[float] = field(
        default_factory=lambda: [120.0, 120.0, 120.0, 120.0, 30.0, 30.0, 15.0],
        metadata={"length": 7, "min": 0.0},
    )
    # Compensate gravity in the driver (the real robot does so in velocity mode).
    gravity_compensation: bool = True


@dataclass
class ProbeCalibration:
    """The probe holder and curvilinear probe rigidly mounted on the flange F.

    The tip frame P has its origin at the centre of the probe face, z_P along the beam (into
    the body), x_P along the transducer array (docs/design.md). On hardware these numbers come
    from pivot calibration and the holder's CAD; they live here, never in code.
    """

    # Geometry (visual and collision) of the probe, expressed in the tip frame P.
    model: str = "package://drake_rus_models/probe/curvilinear_probe.sdf"
    # Pose of the tip frame P in the flange frame F (m, deg).
    X_FP: Transform = field(default_factory=lambda: schema_transform(xyz=(0.0, 0.0, 0.20)))
    # Lumped mass of holder + probe + cable strain relief (kg).
    mass: float = field(
        default=0.55,
        metadata=physical(
            0.05,
            3.0,
            "kg",
            "a probe with its holder; the FR3's rated payload is 3 kg",
            positive=True,
        ),
    )
    # Centre of mass in the flange frame F (m).
    p_FCm: list[float] = field(
        default_factory=lambda: [0.0, 0.0, 0.09],
        metadata=physical(-0.3, 0.3, "m", "the probe's centre of mass near the flange", length=3),
    )
    # Principal moments of inertia about the centre of mass, flange axes (kg m^2).
    inertia_diagonal: list[float] = field(
        default_factory=lambda: [2.2e-3, 2.2e-3, 4.0e-4],
        metadata=physical(
            1e-7, 0.05, "kg m^2", "a hand-held probe and holder", length=3, positive=True
        ),
    )


@dataclass
class PatientConfig:
    """Which patient lies on the bed and where.

    The patient frame Pt sits on the bed surface under the body's midline: x_Pt towards the
    patient's left, y_Pt superior (head), z_Pt anterior. It is placed in the robot base frame
    by ``X_BPt``; with the default the patient lies along the base y-axis, their right side
    towards the robot.
    """

    # "placeholder" (a soft ellipsoidal torso), or a virtual/real patient once available.
    source: str = "placeholder"
    # Which kidney is the scan's target.
    side: str = field(default="right", metadata={"choices": ["right", "left"]})
    posture: str = field(
        default="supine", metadata={"choices": ["supine", "left_lateral_decubitus"]}
    )
    X_BPt: Transform = field(default_factory=lambda: schema_transform(xyz=(0.55, 0.0, 0.0)))
    # Semi-axes (m) of the placeholder torso ellipsoid: left-right, head-foot, front-back.
    placeholder_semi_axes: list[float] = field(
        default_factory=lambda: [0.17, 0.40, 0.12], metadata={"length": 3, "positive": True}
    )
    # How the patient moves during the scan: breathing, a rigid shift (simulation; off by
    # default). The station moves the imaged anatomy, the true kidney pose and the contact
    # body together (drake_rus.anatomy.motion).
    motion: PatientMotionConfig = field(default_factory=PatientMotionConfig)


@dataclass
class ContactConfig:
    """Plant time step and the probe-body contact model."""

    # "hydroelastic": compliant patient, rigid probe (point contact for the other pairs);
    # "point": point contact everywhere (faster, cruder force distribution).
    model: str = field(default="hydroelastic", metadata={"choices": ["hydroelastic", "point"]})
    discrete_contact_approximation: str = field(
        default="sap", metadata={"choices": ["sap", "tamsi", "similar", "lagged"]}
    )
    # Discrete plant period (s). 10 ms: the fastest step whose force trace (EXPLORE and
    # PIVOT mean and ripple, landing peak), E_trans and V match the 1 ms step's (the FR3's
    # 1 kHz; scenario `reference_1ms`) within issue 16's tolerances on test:0-2
    # (`python -m benchmarks scan --validate`).
    time_step: float = field(
        default=0.01,
        metadata=physical(
            1e-5,
            0.01,
            "s",
            "the plant's discrete step (default 10 ms, validated against 1 ms: "
            "python -m benchmarks scan --validate); longer steps miss contact",
            positive=True,
        ),
    )
    # Hydroelastic modulus of the soft body (Pa): soft tissue indents ~1 cm at ~9 N.
    hydroelastic_modulus: float = field(
        default=2.0e5,
        metadata=physical(1e3, 1e8, "Pa", "soft tissue is about 1e4-1e6 Pa", positive=True),
    )
    # Resolution hint of the soft body's tetrahedral mesh (m).
    patient_resolution_hint: float = field(
        default=0.06, metadata=physical(0.01, 0.2, "m", PATIENT_HINT_WHY, positive=True)
    )
    # Resolution hint of the rigid probe face mesh (m).
    probe_resolution_hint: float = field(
        default=0.02, metadata=physical(0.002, 0.05, "m", PROBE_HINT_WHY, positive=True)
    )
    # Vertices of the convex hull used as a virtual patient's contact body (see
    # patient_body.ContactHull): more is closer to the skin, fewer is faster.
    patient_hull_vertices: int = field(default=300, metadata={"min": 8})
    # The contact body is the convex hull of the torso between the kidney's level -/+ a
    # half-length: the longest of these (m) whose hull stays within patient_hull_max_gap of
    # the skin over the kidney (a convex hull bridges a waist between hips and shoulders,
    # e.g. in left lateral decubitus).
    patient_section_half_lengths: list[float] = field(
        default_factory=lambda: [0.20, 0.15, 0.12, 0.10, 0.08, 0.06],
        metadata={"positive": True, "max": 0.5, "min_length": 1},
    )
    patient_hull_max_gap: float = field(default=0.004, metadata={"positive": True, "max": 0.05})
    # Hunt-Crossley dissipation (s/m) of the soft body.
    hunt_crossley_dissipation: float = field(default=5.0, metadata={"min": 0.0})
    # Point-contact stiffness (N/m) when model == "point".
    point_stiffness: float = field(
        default=2000.0,
        metadata=physical(10.0, 1e6, "N/m", "soft tissue under a probe", positive=True),
    )
    # Coulomb friction of the gel-coupled probe on skin (static = dynamic).
    friction: float = field(
        default=0.2, metadata=physical(0.0, 2.0, "", "Coulomb friction of gel on skin")
    )


@dataclass
class Scenario:
    """A whole run: robot, probe, patient, contact, imaging, controller, safety."""

    robot: RobotConfig = field(default_factory=RobotConfig)
    probe: ProbeCalibration = field(default_factory=ProbeCalibration)
    patient: PatientConfig = field(default_factory=PatientConfig)
    contact: ContactConfig = field(default_factory=ContactConfig)
    imaging: ImagingConfig = field(default_factory=ImagingConfig)
    localization: LocalizationConfig = field(default_factory=LocalizationConfig)
    # Where the scan starts: the start planner (simulation's stand-in for the operator).
    start: StartConfig = field(default_factory=StartConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    # How the scan copes with a breathing patient (the breath-hold protocol, gating).
    respiration: RespirationConfig = field(default_factory=RespirationConfig)
    # The scan's checks of its own result before it says DONE (scan/verdict.py).
    verdict: VerdictConfig = field(default_factory=VerdictConfig)
    # Where perception runs and when its results count (beside the control loop).
    perception: PerceptionConfig = field(default_factory=PerceptionConfig)
    # false: simulated station; true: a real FR3 and ultrasound machine.
    hardware: bool = False
    hardware_interface: HardwareConfig = field(default_factory=HardwareConfig)
    # Injected sensor faults (read only by drake_rus.reliability, which wraps the simulated
    # station from outside; the product never reads this section). All off by default.
    faults: FaultConfig = field(default_factory=FaultConfig)
    # Seed of every random draw in a run (noise, speckle, starts).
    random_seed: int = field(default=0, metadata=seed_metadata())


def ListScenarios(filename: str | Path = DEFAULT_SCENARIOS_FILE) -> list[str]:
    """Names of the scenarios in ``filename``."""
    return list(_load_raw(Path(filename)).keys())


def _load_raw(path: Path) -> dict:
    if path.is_dir():
        raise ScenarioError(f"scenario file {path} is a folder; expected a YAML file")
    if not path.is_file():
        raise ScenarioError(f"scenario file not found: {path}")
    text = path.read_text(errors="replace")
    check_nesting_depth(text, f"scenario file {path}")
    try:
        check_duplicate_keys(text, scenarios_file=True)
    except ScenarioError as e:
        raise ScenarioError(f"{path}: {e}") from None
    try:
        raw = yaml_load_file(str(path))
    except Exception as e:  # yaml syntax errors
        raise ScenarioError(
            f"scenario file {path} is not valid YAML: {yaml_error_text(e)}"
        ) from None
    if not isinstance(raw, dict) or not raw:
        raise ScenarioError(
            f"scenario file {path} must map scenario names to scenarios, got {type(raw).__name__}"
        )
    return raw


def LoadScenario(
    *,
    filename: str | Path = DEFAULT_SCENARIOS_FILE,
    scenario_name: str = "default",
    scenario_text: str | None = None,
) -> Scenario:
    """Loads the scenario ``scenario_name`` from ``filename`` (plus optional YAML overrides).

    ``scenario_text`` is YAML merged on top, e.g. ``"{contact: {model: point}}"``.
    Raises ScenarioError naming the file, the scenario and the field on any problem.
    """
    path = Path(filename)
    raw = _load_raw(path)
    if scenario_name not in raw:
        raise ScenarioError(
            f"scenario '{scenario_name}' is not in {path}; available: {', '.join(raw)}"
        )
    context = f"{path}: scenario '{scenario_name}'"
    node = raw[scenario_name]
    if node is None:
        node = {}
    try:
        validate(Scenario, node)
    except ScenarioError as e:
        raise ScenarioError(f"{context}: {e}") from None
    try:
        scenario = yaml_load_typed(
            schema=Scenario, filename=str(path), child_name=scenario_name, defaults=Scenario()
        )
    except Exception as e:
        raise ScenarioError(f"{context}: {e}") from None
    if scenario_text:
        scenario = ApplyOverrides(scenario, scenario_text, context=f"{context} (overrides)")
    try:
        CheckScenario(scenario)
    except ScenarioError as e:
        raise ScenarioError(f"{context}: {e}") from None
    return scenario


def ApplyOverrides(scenario: Scenario, text: str, context: str = "overrides") -> Scenario:
    """Returns ``scenario`` with the YAML mapping ``text`` merged on top."""
    from pydrake.common.yaml import yaml_load

    check_nesting_depth(text, context)
    try:
        check_duplicate_keys(text)
    except ScenarioError as e:
        raise ScenarioError(f"{context}: {e}") from None
    try:
        node = yaml_load(data=text)
    except Exception as e:
        raise ScenarioError(f"{context}: not valid YAML: {yaml_error_text(e)}") from None
    try:
        validate(Scenario, node or {})
        return yaml_load_typed(schema=Scenario, data=text, defaults=scenario)
    except ScenarioError as e:
        raise ScenarioError(f"{context}: {e}") from None
    except Exception as e:
        raise ScenarioError(f"{context}: {e}") from None


def CheckScenario(scenario: Scenario) -> None:
    """Checks a constructed scenario: the schema's bounds, the physical ranges and the
    cross-field rules of ``drake_rus.config_schema`` (each stated once there)."""
    check_dataclass_values(scenario)
    check_physical(scenario)


def ScenarioToYaml(scenario: Scenario) -> str:
    """The scenario as YAML (for run logs)."""
    from pydrake.common.yaml import yaml_dump_typed

    return yaml_dump_typed(scenario)


def replace(obj, **changes):
    """dataclasses.replace, re-exported for notebook convenience."""
    return dataclasses.replace(obj, **changes)
