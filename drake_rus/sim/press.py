"""A minimal press-and-hold driver that exercises the station (demo, benchmark, tests).

It is *not* the paper's controller (that is ``drake_rus.control``): it keeps the probe's
orientation and pushes along the current approach vector with a proportional force law,
    v_z = clip(k_f (F_des - F_z), -v_max, v_max),  qdot = J_P^+ [0, 0, 0, v_z a],
so the station can be driven into steady contact with nothing but its own ports.
"""

import numpy as np
from pydrake.systems.framework import LeafSystem

from drake_rus.sim.force_estimation import contact_force_along_approach


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
        from drake_rus.control.kinematics import TipKinematics
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


class PressDiagram:
    """Station + PressDriver (+ loggers of the estimated and true probe wrench)."""

    def __init__(self, scenario, meshcat=None, desired_force: float = 9.0,
                 log_period: float = 0.01, patient=None, drive: bool = True):
        from pydrake.systems.framework import DiagramBuilder
        from pydrake.systems.primitives import ConstantVectorSource, LogVectorOutput

        from drake_rus.station import MakeControlPlant, MakeStation

        builder = DiagramBuilder()
        self.station = builder.AddNamedSystem(
            "station", MakeStation(scenario, meshcat=meshcat, patient=patient))
        if drive:
            control_plant, tip_frame = MakeControlPlant(scenario)
            self.driver = builder.AddNamedSystem(
                "press_driver", PressDriver(control_plant, tip_frame, desired_force))
            builder.Connect(self.station.GetOutputPort("joint_position"),
                            self.driver.get_input_port(0))
            builder.Connect(self.station.GetOutputPort("probe_force"),
                            self.driver.get_input_port(1))
            builder.Connect(self.driver.get_output_port(),
                            self.station.GetInputPort("joint_velocity_command"))
        else:
            self.driver = builder.AddNamedSystem("zero_command", ConstantVectorSource(np.zeros(7)))
            builder.Connect(self.driver.get_output_port(),
                            self.station.GetInputPort("joint_velocity_command"))
        self.force_log = LogVectorOutput(self.station.GetOutputPort("probe_force"), builder,
                                         log_period)
        self.truth_log = LogVectorOutput(
            self.station.GetOutputPort("probe_contact_wrench_true"), builder, log_period)
        self.diagram = builder.Build()
        self.diagram.set_name("press_demo")

    def logs(self, root_context):
        """(times (N,), estimated F_z (N,), true F_z (N,)) in s and N."""
        est = self.force_log.FindLog(root_context)
        tru = self.truth_log.FindLog(root_context)
        return est.sample_times(), -est.data()[5], -tru.data()[5]
