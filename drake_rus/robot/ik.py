"""The one start-pose IK: joint configurations for a desired probe tip pose (the start of a
scan, study runs, test set-ups)."""

import numpy as np
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.inverse_kinematics import InverseKinematics
from pydrake.solvers import Solve

# A comfortable FR3 posture (rad) to stay near: elbow up, wrist pointing down.
NOMINAL_Q = np.array([0.0, 0.15, 0.0, -2.0, 0.0, 2.15, 0.785])


class IkError(ValueError):
    """No joint configuration reaches the requested tip pose within the joint limits (a
    ValueError: the pose asked for, e.g. a patient placed out of reach, is the cause)."""


def SolveTipPose(
    control_plant,
    tip_frame,
    X_BP: RigidTransform,
    q_nominal=None,
    position_tolerance: float = 1e-4,
    angle_tolerance: float = 1e-3,
) -> np.ndarray:
    """Joint positions (7, rad) putting the probe tip frame at ``X_BP``.

    Solves a small nonlinear program: tip position within ``position_tolerance`` (m) and
    orientation within ``angle_tolerance`` (rad) of ``X_BP``, joint limits, closest to
    ``q_nominal``. Raises IkError if it cannot.
    """
    q_nominal = NOMINAL_Q if q_nominal is None else np.asarray(q_nominal, dtype=float)
    ik = InverseKinematics(control_plant)
    world = control_plant.world_frame()
    p = X_BP.translation()
    ik.AddPositionConstraint(
        tip_frame, np.zeros(3), world, p - position_tolerance, p + position_tolerance
    )
    ik.AddOrientationConstraint(
        tip_frame, RotationMatrix(), world, X_BP.rotation(), angle_tolerance
    )
    q = ik.q()
    prog = ik.get_mutable_prog()
    prog.AddQuadraticErrorCost(np.eye(len(q_nominal)), q_nominal, q)
    prog.SetInitialGuess(q, q_nominal)
    result = Solve(prog)
    if not result.is_success():
        raise IkError(
            f"no FR3 configuration puts the probe tip at p = {np.round(p, 4)} m "
            f"with the requested orientation (solver: "
            f"{result.get_solution_result()})"
        )
    return result.GetSolution(q)
