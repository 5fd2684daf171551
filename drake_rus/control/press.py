"""A minimal press-and-hold driver that exercises the station (demo, benchmark, tests).

It is *not* the paper's controller (that is ``drake_rus.control``): it keeps the probe's
orientation and pushes along the current approach vector with a proportional force law,
    v_z = clip(k_f (F_des - F_z), -v_max, v_max),  qdot = J_P^+ [0, 0, 0, v_z a],
so the station can be driven into steady contact with nothing but its own ports.
"""

import numpy as np
from pydrake.systems.framework import LeafSystem

from drake_rus.robot import TipKinematics, contact_force_along_approach


def press_joint_velocity(J_WP: np.ndarray, a_W: np.ndarray, F_z: float, desired_force: float,
                         force_gain: float, max_speed: float, damping: float = 1e-2) -> np.ndarray:
    """Joint velocities (7) that push the tip along ``a_W`` to regulate F_z (N).

    ``J_WP``: 6x7 spatial-velocity Jacobian of the tip [w; v] in W. The tip's angular velocity
    is commanded to zero. Uses a damped least-squares inverse (damping in the units of J).
    """
    v_z = float(np.clip(force_gain * (desired_force - F_z), -max_speed, max_speed))
    V_WP = np.concatenate([np.zeros(3), v_z * np.asarray(a_W, dtype=float)])
    A = J_WP @ J_WP.T + damping**2 * np.eye(6)
    return J_WP.T @ np.linalg.solve(A, V_WP)


class PressDriver(LeafSystem):
    """Press the probe into the body and hold a force.

    Inputs ``joint_position`` (7, rad), ``probe_force`` (6, station convention).
    Output ``joint_velocity_command`` (7, rad/s), updated at ``rate_hz``.
    """

    def __init__(self, control_plant, tip_frame, desired_force: float = 9.0,
                 force_gain: float = 0.004, max_speed: float = 0.03, rate_hz: float = 100.0,
                 start_time: float = 0.0):
        super().__init__()
        self._tip = TipKinematics(control_plant, tip_frame)
        self._desired_force = desired_force
        self._force_gain = force_gain
        self._max_speed = max_speed
        self._start_time = start_time
        self.DeclareVectorInputPort("joint_position", 7)
        self.DeclareVectorInputPort("probe_force", 6)
        state = self.DeclareDiscreteState(7)
        self.DeclarePeriodicDiscreteUpdateEvent(1.0 / rate_hz, 0.0, self._update)
        self.DeclareStateOutputPort("joint_velocity_command", state)

    def _update(self, context, discrete_state):
        if context.get_time() < self._start_time:
            discrete_state.get_mutable_vector().SetFromVector(np.zeros(7))
            return
        q = self.get_input_port(0).Eval(context)
        F_P = self.get_input_port(1).Eval(context)
        a_W = self._tip.pose(q).rotation().matrix()[:, 2]
        qdot = press_joint_velocity(self._tip.jacobian(q), a_W, contact_force_along_approach(F_P),
                                    self._desired_force, self._force_gain, self._max_speed)
        discrete_state.get_mutable_vector().SetFromVector(qdot)
