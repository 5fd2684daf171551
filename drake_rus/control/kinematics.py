"""Tip kinematics on a control plant (FR3 + probe): pose and Jacobian of P as functions of q.

The controller never touches the station's plant: it owns a plant with only the arm and the
probe tip frame (``drake_rus.station.MakeControlPlant``), the same model the hardware station
uses, and a private context for it.
"""

from __future__ import annotations

import numpy as np

from pydrake.math import RigidTransform
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import JacobianWrtVariable


class TipKinematics:
    """Forward kinematics and the 6xn Jacobian [w; v] of the tip frame P in the base B.

    B is the plant's world frame (the FR3 base is welded at the world origin).
    """

    def __init__(self, plant: MultibodyPlant, tip_frame):
        self.plant = plant
        self.frame = tip_frame
        self.context = plant.CreateDefaultContext()
        self.nq = plant.num_positions()
        lower = plant.GetPositionLowerLimits()
        upper = plant.GetPositionUpperLimits()
        self.q_min = np.where(np.isfinite(lower), lower, -1e3)
        self.q_max = np.where(np.isfinite(upper), upper, 1e3)

    def _set(self, q) -> None:
        self.plant.SetPositions(self.context, np.asarray(q, dtype=float))

    def jacobian(self, q) -> np.ndarray:
        """J_BP(q): spatial velocity of P's origin in B per joint rate (6 x nq)."""
        self._set(q)
        W = self.plant.world_frame()
        return self.plant.CalcJacobianSpatialVelocity(
            self.context, JacobianWrtVariable.kV, self.frame, np.zeros(3), W, W)

    def pose(self, q) -> RigidTransform:
        """X_BP(q)."""
        self._set(q)
        return self.frame.CalcPoseInWorld(self.context)


def MakeControlPlant(scenario=None):
    """The control plant (FR3 + calibrated probe) of ``drake_rus.station.MakeControlPlant``
    for ``scenario`` (default: the default Scenario). Returns (plant, probe_tip_frame)."""
    from drake_rus.scenario import Scenario
    from drake_rus.station import MakeControlPlant as station_make
    return station_make(scenario or Scenario())


def JointsForTipPosition(plant, tip_frame, q0, p_target, *, iterations: int = 400,
                         gain: float = 0.5) -> np.ndarray:
    """Joint positions putting the tip at ``p_target`` (m, in B) with the orientation of
    ``q0``, by integrating the controller's own differential IK (eq. 10-12) kinematically.
    For choosing start configurations (e.g. the probe above a patient's kidney)."""
    from drake_rus.control import laws
    kin = TipKinematics(plant, tip_frame)
    q = np.asarray(q0, dtype=float).copy()
    R0 = kin.pose(q).rotation().matrix()
    for _ in range(iterations):
        X = kin.pose(q)
        R = X.rotation().matrix()
        w = laws.orientation_alignment(R, R0[:, 2], R0[:, 0], np.zeros(3), gain, 0.0, gain)
        v = gain * (np.asarray(p_target, dtype=float) - X.translation())
        qdot = laws.solve_joint_velocities(
            q, np.concatenate([w, v]), kin.jacobian, K_p6=1.0, epsilon=1e-4, q_min=kin.q_min,
            q_max=kin.q_max, dq_max=np.full(q.size, 2.0), joint_limit_margin=0.1)
        q = q + 0.1 * qdot
    return q
