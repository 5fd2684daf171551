"""A minimal press-and-hold driver that exercises the station (demo, benchmark, tests).

It is not the scan's controller (``drake_rus.control.diagram``): no supervisor, no position
loop, no null-space task. It runs the scan's force law, eq. 6 with the scenario's gains
(``controller.K_p3``, ``K_d1``, ``force_filter_cutoff_hz``, ``rate_hz``; the same
``laws.force_pd_step``), along the current approach vector a, and holds the probe's start
orientation with eq. 1-5 (``K_p1``, ``K_p2``):
    v = clip(K_p3 e + K_d1 de/dt, -v_max, v_max) a,  e = F_des - lowpass(F_z),
    omega = K_p1 (a x a_0) + K_p2 ((o x o_0) . a) a,   qdot = J_P^+ [omega; v].
The gains are the ones ``drake_rus.control.force_loop`` shows stable over the contact
stiffness range (docs/force_loop.md); before issue 32 this driver ran an unfiltered
v = 0.004 (F_des - F_z), which oscillated once the probe stuck to the skin.
"""

import numpy as np
from pydrake.systems.framework import LeafSystem

from drake_rus.control import laws
from drake_rus.robot import TipKinematics, contact_force_along_approach


def press_joint_velocity(
    J_WP: np.ndarray, omega_W: np.ndarray, v_W: np.ndarray, damping: float = 1e-2
) -> np.ndarray:
    """Joint velocities (7) giving the tip the twist [omega_W; v_W] (rad/s, m/s, in W).

    ``J_WP``: 6x7 spatial-velocity Jacobian of the tip [w; v] in W. Uses a damped
    least-squares inverse (damping in the units of J).
    """
    V_WP = np.concatenate([np.asarray(omega_W, dtype=float), np.asarray(v_W, dtype=float)])
    A = J_WP @ J_WP.T + damping**2 * np.eye(6)
    return J_WP.T @ np.linalg.solve(A, V_WP)


class PressDriver(LeafSystem):
    """Press the probe into the body and hold a force, keeping the start orientation.

    ``controller``: a ``ControllerConfig`` (gains, rate, desired force). Inputs
    ``joint_position`` (7, rad), ``probe_force`` (6, station convention). Output
    ``joint_velocity_command`` (7, rad/s), updated every controller period (state).
    Other state: the eq. 6 filter and error state (3) and the start orientation [a_0; o_0]
    (6, in B; captured at the first update). ``hold_orientation`` False commands a zero
    angular velocity instead (the driver before issue 32; for the force-loop validation).
    """

    def __init__(
        self,
        control_plant,
        tip_frame,
        controller,
        desired_force: float | None = None,
        max_speed: float = 0.03,
        start_time: float = 0.0,
        hold_orientation: bool = True,
    ):
        super().__init__()
        self._tip = TipKinematics(control_plant, tip_frame)
        self._cfg = controller
        self._desired_force = (
            controller.desired_force if desired_force is None else float(desired_force)
        )
        self._dt = 1.0 / controller.rate_hz
        self._alpha = laws.lowpass_alpha(self._dt, controller.force_filter_cutoff_hz)
        self._max_speed = max_speed
        self._start_time = start_time
        self._hold_orientation = hold_orientation
        self.DeclareVectorInputPort("joint_position", 7)
        self.DeclareVectorInputPort("probe_force", 6)
        self._command = self.DeclareDiscreteState(7)
        self._force = self.DeclareDiscreteState(3)  # (F_filtered, e_prev, initialised)
        self._start = self.DeclareDiscreteState(7)  # (a_0, o_0, captured)
        self.DeclarePeriodicDiscreteUpdateEvent(self._dt, 0.0, self._update)
        self.DeclareStateOutputPort("joint_velocity_command", self._command)

    def _update(self, context, discrete_state):
        if context.get_time() < self._start_time:
            discrete_state.get_mutable_vector(self._command).SetFromVector(np.zeros(7))
            return
        c = self._cfg
        q = self.get_input_port(0).Eval(context)
        F_z = contact_force_along_approach(self.get_input_port(1).Eval(context))
        R = self._tip.pose(q).rotation().matrix()
        a, o = R[:, 2], R[:, 0]
        start = context.get_discrete_state(self._start).get_value()
        if start[6] < 0.5:
            start = np.concatenate([a, o, [1.0]])
        v, force_state = laws.force_pd_step(
            tuple(context.get_discrete_state(self._force).get_value()),
            F_z,
            self._desired_force,
            a,
            self._dt,
            self._alpha,
            c.K_p3,
            c.K_d1,
        )
        v = np.clip(float(v @ a), -self._max_speed, self._max_speed) * a
        omega = (
            laws.orientation_alignment(R, start[:3], start[3:6], np.zeros(3), c.K_p1, 0.0, c.K_p2)
            if self._hold_orientation
            else np.zeros(3)
        )
        discrete_state.get_mutable_vector(self._command).SetFromVector(
            press_joint_velocity(self._tip.jacobian(q), omega, v)
        )
        discrete_state.get_mutable_vector(self._force).SetFromVector(
            np.asarray(force_state, dtype=float)
        )
        discrete_state.get_mutable_vector(self._start).SetFromVector(start)
