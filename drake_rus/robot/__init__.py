"""The FR3 with its calibrated probe: model, tip kinematics, force estimation, start-pose IK.

Both stations (simulated and hardware) and the controller import this package; it imports
nothing above the core helpers (``config_schema``, ``scenario``, ``paths``).
"""

from drake_rus.robot.force_estimation import contact_force_along_approach, estimate_tip_wrench
from drake_rus.robot.ik import NOMINAL_Q, IkError, SolveTipPose
from drake_rus.robot.kinematics import TipKinematics
from drake_rus.robot.model import (
    FLANGE_FRAME,
    NUM_JOINTS,
    PROBE_FACE_GEOMETRY,
    PROBE_TIP_FRAME,
    AddFr3AndProbe,
    MakeControlPlant,
    RobotAndProbe,
)
from drake_rus.robot.systems import ProbeForceEstimator, ProbePoseFromJoints

__all__ = [
    "AddFr3AndProbe",
    "MakeControlPlant",
    "RobotAndProbe",
    "TipKinematics",
    "SolveTipPose",
    "IkError",
    "NOMINAL_Q",
    "ProbePoseFromJoints",
    "ProbeForceEstimator",
    "estimate_tip_wrench",
    "contact_force_along_approach",
    "NUM_JOINTS",
    "PROBE_TIP_FRAME",
    "FLANGE_FRAME",
    "PROBE_FACE_GEOMETRY",
]
