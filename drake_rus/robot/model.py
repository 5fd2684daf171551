"""The FR3 arm and the calibrated probe as a MultibodyPlant model.

``AddFr3AndProbe`` adds both to any plant (the simulated station's, or a control plant);
``MakeControlPlant`` builds the arm-and-probe-only plant that the hardware station, the
controller and every kinematic computation share. The FR3 model is ours
(``models/fr3/fr3.urdf``, generated from the published kinematics and limits in
``docs/facts/fr3.md``); the probe's flange-to-tip transform ``X_FP``, mass, centre of mass and
inertia come from the scenario's ``probe`` section (the calibration lives there, never in
code).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from pydrake.math import RigidTransform
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import (
    FixedOffsetFrame,
    PdControllerGains,
    RotationalInertia,
    SpatialInertia,
)

from drake_rus.config_schema import ScenarioError
from drake_rus.paths import AddDrakeRusPackages
from drake_rus.scenario import ProbeCalibration, RobotConfig

__all__ = [
    "AddFr3AndProbe",
    "MakeControlPlant",
    "RobotAndProbe",
    "NUM_JOINTS",
    "PROBE_TIP_FRAME",
    "FLANGE_FRAME",
    "PROBE_FACE_GEOMETRY",
]

# The FR3 has seven revolute joints (docs/facts/fr3.md).
NUM_JOINTS = 7
PROBE_TIP_FRAME = "probe_tip"
FLANGE_FRAME = "fr3_link8"
PROBE_FACE_GEOMETRY = "face_collision"


@dataclasses.dataclass
class RobotAndProbe:
    """What ``AddFr3AndProbe`` added."""

    robot: object  # ModelInstanceIndex of the FR3
    probe: object  # ModelInstanceIndex of the probe
    tip_frame: object  # Frame P (probe tip)
    probe_bodies: list  # bodies rigidly attached to the flange (probe + payload)


def model_url(model: str) -> str:
    """A package:// or file:// URL as is; a plain file path as an absolute file:// URL."""
    return model if "://" in model else Path(model).resolve().as_uri()


def AddFr3AndProbe(
    plant: MultibodyPlant, robot_config: RobotConfig, probe_config: ProbeCalibration
) -> RobotAndProbe:
    """Adds the FR3 (base welded to the world, the scenario's ``robot`` section) and the
    calibrated probe (its ``probe`` section) to ``plant``.

    Collision and visual geometry are registered only when ``plant`` is registered as a
    SceneGraph source (the simulated station's plant); a control plant gets none.
    """
    parser = Parser(plant)
    AddDrakeRusPackages(parser.package_map())
    try:
        (robot,) = parser.AddModelsFromUrl(model_url(robot_config.model))
    except Exception as e:
        raise ScenarioError(f"field 'robot.model': cannot load {robot_config.model}: {e}")
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName("fr3_link0", robot))
    parser.SetAutoRenaming(True)
    try:
        (probe,) = parser.AddModelsFromUrl(model_url(probe_config.model))
    except Exception as e:
        raise ScenarioError(f"field 'probe.model': cannot load {probe_config.model}: {e}")
    flange = plant.GetFrameByName(FLANGE_FRAME, robot)
    probe_body = plant.GetBodyByName("probe", probe)
    X_FP = probe_config.X_FP.GetDeterministicValue()
    plant.WeldFrames(flange, probe_body.body_frame(), X_FP)
    tip_frame = plant.AddFrame(
        FixedOffsetFrame(PROBE_TIP_FRAME, probe_body.body_frame(), RigidTransform())
    )

    # Lumped holder + probe inertia from the scenario, as its own body welded at the flange.
    cal = probe_config
    I_Cm_F = RotationalInertia(*cal.inertia_diagonal)
    M_FCm = SpatialInertia.MakeFromCentralInertia(cal.mass, np.asarray(cal.p_FCm), I_Cm_F)
    payload = plant.AddRigidBody("probe_payload", probe, M_FCm)
    plant.WeldFrames(flange, payload.body_frame(), RigidTransform())

    for i in range(NUM_JOINTS):
        actuator = plant.GetJointActuatorByName(f"fr3_motor{i + 1}", robot)
        actuator.set_controller_gains(
            PdControllerGains(p=robot_config.driver_kp[i], d=robot_config.driver_kd[i])
        )
    for i, q in enumerate(robot_config.initial_joint_positions):
        plant.GetJointByName(f"fr3_joint{i + 1}", robot).set_default_angle(q)
    return RobotAndProbe(robot, probe, tip_frame, [probe_body, payload])


def MakeControlPlant(
    robot_config: RobotConfig | None = None, probe_config: ProbeCalibration | None = None
) -> tuple[MultibodyPlant, object]:
    """A continuous plant with only the FR3 and the calibrated probe, for kinematics and
    gravity: no SceneGraph, so no geometry. The same model serves the hardware station (FK for
    ``X_BP``, Jacobians for ``probe_force``), both stations' force estimators and the
    controllers. The scenario's ``robot`` and ``probe`` sections default to the dataclasses'.
    Returns ``(plant, probe_tip_frame)``.
    """
    plant = MultibodyPlant(time_step=0.0)
    parts = AddFr3AndProbe(plant, robot_config or RobotConfig(), probe_config or ProbeCalibration())
    plant.Finalize()
    return plant, plant.GetFrameByName(PROBE_TIP_FRAME, parts.probe)
