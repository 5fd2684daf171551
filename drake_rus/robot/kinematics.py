"""Tip kinematics on a control plant (FR3 + probe): pose and Jacobian of P as functions of q.

The controller never touches the station's plant: it owns a control plant
(``drake_rus.robot.MakeControlPlant``), the same model the hardware station uses, and a
private context for it.
"""

from __future__ import annotations

import numpy as np
from pydrake.math import RigidTransform
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import JacobianWrtVariable

__all__ = ["TipKinematics"]


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

        # The last q and what was computed at it: every system sharing this object (the
        # controller chain, the safety layer) reads one set of kinematics per tick.
        self._q_key = None
        self._X = None
        self._J = None

    def _set(self, q) -> None:
        q = np.asarray(q, dtype=float)
        key = q.tobytes()
        if key != self._q_key:
            self.plant.SetPositions(self.context, q)
            self._q_key, self._X, self._J = key, None, None

    def jacobian(self, q) -> np.ndarray:
        """J_BP(q): spatial velocity of P's origin in B per joint rate (6 x nq). The array is
        shared with later calls at the same q: do not modify it."""
        self._set(q)
        if self._J is None:
            W = self.plant.world_frame()
            self._J = self.plant.CalcJacobianSpatialVelocity(
                self.context, JacobianWrtVariable.kV, self.frame, np.zeros(3), W, W
            )
        return self._J

    def pose(self, q) -> RigidTransform:
        """X_BP(q)."""
        self._set(q)
        if self._X is None:
            self._X = self.frame.CalcPoseInWorld(self.context)
        return self._X
