"""The robot-side LeafSystems both stations share: probe pose from joint positions, probe
wrench from external joint torques (the same formula in simulation and on hardware)."""

from __future__ import annotations

from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.framework import LeafSystem

from drake_rus.robot.force_estimation import estimate_tip_wrench
from drake_rus.robot.kinematics import TipKinematics
from drake_rus.robot.model import NUM_JOINTS

__all__ = ["ProbePoseFromJoints", "ProbeForceEstimator"]


class ProbePoseFromJoints(LeafSystem):
    """Forward kinematics of the probe tip.

    Input ``joint_position`` (7, rad). Output ``X_BP`` (abstract RigidTransform): the tip
    frame P in the robot base B (m).
    """

    def __init__(self, control_plant: MultibodyPlant, tip_frame):
        super().__init__()
        self._tip = TipKinematics(control_plant, tip_frame)
        self.DeclareVectorInputPort("joint_position", NUM_JOINTS)
        self.DeclareAbstractOutputPort(
            "X_BP", lambda: AbstractValue.Make(RigidTransform()),
            lambda context, output: output.set_value(
                self._tip.pose(self.get_input_port(0).Eval(context))))


class ProbeForceEstimator(LeafSystem):
    """Probe wrench from external joint torques (see ``estimate_tip_wrench``).

    Inputs ``joint_position`` (7, rad), ``tau_external`` (7, N m). Output ``probe_force``
    (6): spatial force on the probe by the environment, in P about P's origin (N m, N).
    """

    def __init__(self, control_plant: MultibodyPlant, tip_frame):
        super().__init__()
        self._tip = TipKinematics(control_plant, tip_frame)
        self.DeclareVectorInputPort("joint_position", NUM_JOINTS)
        self.DeclareVectorInputPort("tau_external", NUM_JOINTS)
        self.DeclareVectorOutputPort("probe_force", 6, self._calc)

    def _calc(self, context, output):
        q = self.get_input_port(0).Eval(context)
        tau = self.get_input_port(1).Eval(context)
        R_WP = self._tip.pose(q).rotation().matrix()
        output.SetFromVector(estimate_tip_wrench(self._tip.jacobian(q), tau, R_WP))
