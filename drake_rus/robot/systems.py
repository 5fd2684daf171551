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

    ``kinematics``: a TipKinematics to share with other systems (it memoises the last q).

    Input ``joint_position`` (7, rad). Output ``X_BP`` (abstract RigidTransform): the tip
    frame P in the robot base B (m).
    """

    def __init__(
        self, control_plant: MultibodyPlant, tip_frame, kinematics: TipKinematics | None = None
    ):
        super().__init__()
        self._tip = kinematics or TipKinematics(control_plant, tip_frame)
        q = self.DeclareVectorInputPort("joint_position", NUM_JOINTS)
        # Depends on q only (not on time or other sources): recomputed when q changes.
        self.DeclareAbstractOutputPort(
            "X_BP",
            lambda: AbstractValue.Make(RigidTransform()),
            lambda context, output: output.set_value(
                self._tip.pose(self.get_input_port(0).Eval(context))
            ),
            prerequisites_of_calc={self.input_port_ticket(q.get_index())},
        )


class ProbeForceEstimator(LeafSystem):
    """Probe wrench from external joint torques (see ``estimate_tip_wrench``).

    Inputs ``joint_position`` (7, rad), ``tau_external`` (7, N m). Output ``probe_force``
    (6): spatial force on the probe by the environment, in P about P's origin (N m, N).
    """

    def __init__(
        self, control_plant: MultibodyPlant, tip_frame, kinematics: TipKinematics | None = None
    ):
        super().__init__()
        self._tip = kinematics or TipKinematics(control_plant, tip_frame)
        q = self.DeclareVectorInputPort("joint_position", NUM_JOINTS)
        tau = self.DeclareVectorInputPort("tau_external", NUM_JOINTS)
        self.DeclareVectorOutputPort(
            "probe_force",
            6,
            self._calc,
            prerequisites_of_calc={
                self.input_port_ticket(q.get_index()),
                self.input_port_ticket(tau.get_index()),
            },
        )

    def _calc(self, context, output):
        q = self.get_input_port(0).Eval(context)
        tau = self.get_input_port(1).Eval(context)
        R_WP = self._tip.pose(q).rotation().matrix()
        output.SetFromVector(estimate_tip_wrench(self._tip.jacobian(q), tau, R_WP))
