"""Thin LeafSystems over the pure control laws (laws.py, supervisor.py, safety.py).

Timing: every system here runs at the controller rate (``ControllerConfig.rate_hz``, default
100 Hz), never per plant step. The SafetyLayer holds the joint velocity command in its
discrete state and exposes it through a state output port, so the 1 kHz plant reads it
without calling Python; its periodic update pulls the controller chain (IK <- alignment,
force, position <- supervisor) once per control period.

Frames and units: B = robot base (world), P = probe tip; SI units.
"""

from __future__ import annotations

import math

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import BasicVector, LeafSystem, ValueProducer

from drake_rus.control import kernels, laws, supervisor
from drake_rus.control.safety import SafetyInputs, SafetyState, safety_step
from drake_rus.robot import TipKinematics


def contact_force(probe_force) -> float:
    """F_z of eq. 6 (N, positive pressing) from the station's probe_force
    [tau_x, tau_y, tau_z, f_x, f_y, f_z] on the probe in P: the body pushes along -z_P."""
    return float(-np.asarray(probe_force)[5])


def _X(port, context) -> RigidTransform:
    return port.Eval(context)


def _optional_scalar(port, context, default: float) -> float:
    return float(port.Eval(context)[0]) if port.HasValue(context) else default


class OrientationAlignment(LeafSystem):
    """omega_total (eq. 1-5): tilts a towards a_des (with a_des rate feed-forward) and turns
    o towards o_des about a.

    Inputs: X_BP (RigidTransform), a_des (3, unit, in B), o_des (3, unit, in B),
    a_des_dot (3, 1/s, in B; optional, zero if unconnected).
    Output: omega_BP (3, rad/s, in B).
    """

    def __init__(self, config):
        super().__init__()
        self._cfg = config
        self._X = self.DeclareAbstractInputPort("X_BP", AbstractValue.Make(RigidTransform()))
        self._a = self.DeclareVectorInputPort("a_des", 3)
        self._o = self.DeclareVectorInputPort("o_des", 3)
        self._adot = self.DeclareVectorInputPort("a_des_dot", 3)
        self.DeclareVectorOutputPort("omega_BP", 3, self._calc)

    def _calc(self, context, output: BasicVector):
        c = self._cfg
        R = _X(self._X, context).rotation().matrix()
        adot = self._adot.Eval(context) if self._adot.HasValue(context) else np.zeros(3)
        output.SetFromVector(
            laws.orientation_alignment(
                R, self._a.Eval(context), self._o.Eval(context), adot, c.K_p1, c.K_p11, c.K_p2
            )
        )


class ForcePD(LeafSystem):
    """Force PD along the approach vector (eq. 6) on the low-pass filtered contact force,
    derivative on the filtered error.

    Inputs: probe_force (6, [N m, N], on the probe in P), X_BP (RigidTransform),
    F_des (1, N; optional, defaults to the configured desired force).
    Outputs: v_force (3, m/s, in B), F_filtered (1, N; state, positive pressing).
    State: [F_filtered, previous error, initialised], updated every control period.
    """

    def __init__(self, config):
        super().__init__()
        self._cfg = config
        self._dt = 1.0 / config.rate_hz
        self._alpha = laws.lowpass_alpha(self._dt, config.force_filter_cutoff_hz)
        self._F = self.DeclareVectorInputPort("probe_force", 6)
        self._X = self.DeclareAbstractInputPort("X_BP", AbstractValue.Make(RigidTransform()))
        self._Fdes = self.DeclareVectorInputPort("F_des", 1)
        self._state = self.DeclareDiscreteState(3)
        self._filtered = self.DeclareDiscreteState(1)
        # Unrestricted (not discrete) update so that it runs in the same phase as the safety
        # layer's and the supervisor's: one evaluation of the station's sensors per period.
        self.DeclarePeriodicUnrestrictedUpdateEvent(self._dt, 0.0, self._update)
        # The step's (v_force, next state), in the Context: the output and the update of one
        # period read it, so it is computed once.
        self._step_cache = self.DeclareCacheEntry(
            description="force PD step (v_force, next state)",
            value_producer=ValueProducer(
                allocate=lambda: AbstractValue.Make((None, None)), calc=self._calc_step
            ),
            prerequisites_of_calc={
                self.discrete_state_ticket(self._state),
                self.input_port_ticket(self._F.get_index()),
                self.input_port_ticket(self._X.get_index()),
                self.input_port_ticket(self._Fdes.get_index()),
            },
        )
        self.DeclareVectorOutputPort(
            "v_force", 3, self._calc, prerequisites_of_calc={self._step_cache.ticket()}
        )
        self.DeclareStateOutputPort("F_filtered", self._filtered)

    def _calc_step(self, context, value):
        s = tuple(context.get_discrete_state(self._state).get_value())
        F = contact_force(self._F.Eval(context))
        F_des = _optional_scalar(self._Fdes, context, self._cfg.desired_force)
        a = _X(self._X, context).rotation().matrix()[:, 2]
        if not math.isfinite(F):
            value.set_value((np.zeros(3), s))
            return
        c = self._cfg
        value.set_value(laws.force_pd_step(s, F, F_des, a, self._dt, self._alpha, c.K_p3, c.K_d1))

    def _step(self, context):
        return self._step_cache.Eval(context)

    def _calc(self, context, output):
        output.SetFromVector(self._step(context)[0])

    def _update(self, context, state):
        _, s = self._step(context)
        state.get_mutable_discrete_state(self._state).set_value(np.asarray(s, dtype=float))
        state.get_mutable_discrete_state(self._filtered).set_value([s[0]])


class PositionP(LeafSystem):
    """Tip x/y tracking (eq. 7).

    Inputs: X_BP (RigidTransform), P_des (2, m, desired tip x, y in B).
    Output: v_position (3, m/s, in B): eq. 7's [v_x, v_y, 0] in the plane normal to the
    probe's axis (``laws.position_p`` with a_curr), so it never presses along the axis.
    """

    def __init__(self, config):
        super().__init__()
        self._cfg = config
        self._X = self.DeclareAbstractInputPort("X_BP", AbstractValue.Make(RigidTransform()))
        self._P = self.DeclareVectorInputPort("P_des", 2)
        self.DeclareVectorOutputPort("v_position", 3, self._calc)

    def _calc(self, context, output):
        X = _X(self._X, context)
        output.SetFromVector(
            laws.position_p(
                self._P.Eval(context),
                X.translation(),
                self._cfg.K_p4,
                self._cfg.K_p5,
                a_curr=X.rotation().matrix()[:, 2],
            )
        )


class NullSpaceDiffIK(LeafSystem):
    """Task twist (eq. 8-9) -> joint velocities (eq. 10-12): damped pseudo-inverse of the
    tip Jacobian, null-space manipulability gradient, joint-limit margin, speed limits.

    Constructed with a control plant holding only the FR3 and the probe (``MakeControlPlant``).
    The null-space velocity K_p6 grad m(q) is state, refreshed every null_space_period.
    ``braking_acceleration`` (rad/s^2 per joint, or None): the acceleration the command may
    have on its way to the robot (the hardware's command guard); no joint is sent towards
    its limit faster than such a command can stop before it (``laws.joint_velocity_bounds``).
    Inputs: joint_position (7, rad), omega_BP (3, rad/s, in B), v_force (3, m/s, in B),
    v_position (3, m/s, in B).
    Outputs: joint_velocity_desired (7, rad/s), V_BP_desired (6, [rad/s, m/s], in B),
    manipulability (1, at the measured q).
    """

    def __init__(
        self,
        plant,
        tip_frame,
        config,
        use_null_space: bool = True,
        kinematics: TipKinematics | None = None,
        braking_acceleration=None,
    ):
        super().__init__()
        self._cfg = config
        kernels.warm_up()  # compile or load the IK kernels now, not in the first period
        # ``kinematics`` may be shared with the safety layer: one FK + Jacobian per tick.
        self._kin = kinematics or TipKinematics(plant, tip_frame)
        # Checked once here (a bad shape fails at build time, naming the field).
        self._braking = laws.braking_accelerations(braking_acceleration, self._kin.nq)
        self._K_p6 = config.K_p6 if use_null_space else 0.0
        n = self._kin.nq
        self._q = self.DeclareVectorInputPort("joint_position", n)
        self._w = self.DeclareVectorInputPort("omega_BP", 3)
        self._vf = self.DeclareVectorInputPort("v_force", 3)
        self._vp = self.DeclareVectorInputPort("v_position", 3)
        self.DeclareVectorOutputPort("joint_velocity_desired", n, self._calc_qdot)
        self.DeclareVectorOutputPort("V_BP_desired", 6, self._calc_twist)
        self.DeclareVectorOutputPort("manipulability", 1, self._calc_m)
        # qdot_null = K_p6 grad m(q) (eq. 11-12) is a slow secondary task: it is held in
        # state and refreshed every null_space_period, analytically from the Jacobian at q
        # (laws.manipulability_gradient_analytic: no extra Jacobians).
        self._null = self.DeclareDiscreteState(n)
        if self._K_p6 > 0:
            self.DeclareInitializationUnrestrictedUpdateEvent(self._update_null)
            self.DeclarePeriodicUnrestrictedUpdateEvent(
                config.null_space_period, 0.0, self._update_null
            )

    def _update_null(self, context, state):
        q = np.asarray(self._q.Eval(context), dtype=float)
        g = (
            laws.manipulability_gradient_analytic(self._kin.jacobian(q))
            if np.all(np.isfinite(q))
            else np.zeros_like(q)
        )
        state.get_mutable_discrete_state(self._null).set_value(self._K_p6 * g)

    @property
    def kinematics(self) -> TipKinematics:
        """The control plant's tip kinematics (pose and Jacobian of P as functions of q)."""
        return self._kin

    def twist(self, context) -> np.ndarray:
        c = self._cfg
        return laws.assemble_twist(
            self._w.Eval(context),
            self._vp.Eval(context),
            self._vf.Eval(context),
            c.max_tip_speed,
            c.max_angular_speed,
        )

    def _calc_twist(self, context, output):
        output.SetFromVector(self.twist(context))

    def _calc_qdot(self, context, output):
        c, k = self._cfg, self._kin
        qdot = laws.solve_joint_velocities(
            self._q.Eval(context),
            self.twist(context),
            k.jacobian,
            qdot_null=context.get_discrete_state(self._null).get_value(),
            q_min=k.q_min,
            q_max=k.q_max,
            dq_max=c.joint_velocity_limits,
            joint_limit_margin=c.joint_limit_margin,
            sigma_threshold=c.singular_value_threshold,
            damping_max=c.singular_damping_max,
            braking_acceleration=self._braking,
            period=1.0 / c.rate_hz,
        )
        output.SetFromVector(qdot)

    def _calc_m(self, context, output):
        q = self._q.Eval(context)
        m = laws.manipulability(self._kin.jacobian(q)) if np.all(np.isfinite(q)) else math.nan
        output.SetFromVector([m])


def _output_vectors(s: supervisor.SupervisorState) -> dict:
    """The ScanSupervisor's vector outputs from its state, by port name (all in B)."""
    return {
        "a_des": s.a_des,
        "o_des": s.o_des,
        "a_des_dot": s.a_des_dot,
        "P_des": s.P_des,
        "F_des": [s.F_des],
        "phase": [float(s.phase)],
        "segmentation_required": [float(supervisor.segmentation_required(s))],
        "exploring": [float(s.phase == supervisor.Phase.EXPLORE)],
        "abort": [float(s.phase == supervisor.Phase.ABORT)],
        "cloud_reset": [float(s.reorienting or s.retreating)],
        "localization_round": [float(s.localization_round)],
    }


class ScanSupervisor(LeafSystem):
    """The scan state machine (APPROACH -> EXPLORE -> LOCALIZE -> TRANSIT -> PIVOT -> DONE,
    or ABORT with a reason): ``supervisor.supervisor_step`` every control period.

    Inputs: X_BP (RigidTransform); contact_force (1, N, filtered, positive pressing);
    kidney_visible (1, 0/1; optional: visible if unconnected); mask_centroid (1, horizontal
    centroid in [0, 1]; optional); X_BK (RigidTransform: the kidney pose estimate, or a
    ground-truth stand-in until localization lands; optional); localization_ready (1, 0/1;
    optional: ready if unconnected); safety_stopped (1, 0/1; optional: a safety stop aborts
    the scan); localization_error (str; optional); exploration_sufficient (1, 0/1;
    optional); motion_allowed (1, 0/1; optional, allowed if unconnected: respiration
    gating, 0 outside breath-holds holds exploration and pivot motion); tracking_error
    (str; optional: "" while the kidney stays where localization put it, else why not);
    kidney_length_estimate (1, m; optional, NaN if unconnected: the localizer's estimate of
    the kidney's length, which ends EXPLORE with ``exploration_length: estimated``);
    breathing_error (str; optional: the breath-hold protocol cannot go on: ABORT);
    pivot_model (supervisor.PivotModel; optional: the template points and fan the
    ``predicted_end`` pivot strategy predicts the pivot's ends with; unconnected: two-leg);
    pivot_view ((time s of the newest frame covered, str why the pivot's view contradicts
    the registration, "" = it does not); optional: the pivot-view check the pivot's end
    awaits before DONE, ``controller.second_look``; unconnected: DONE at once).
    Outputs: a_des (3), o_des (3), a_des_dot (3, 1/s), P_des (2, m), F_des (1, N), all in B;
    phase (1, supervisor.Phase value, e.g. the localizer's trigger); segmentation_required (1, 0/1);
    exploring (1, 0/1: enable of the point-cloud accumulator); abort (1, 0/1);
    cloud_reset (1, 0/1: a re-localization clears the exploration cloud);
    localization_round (1: counts re-localizations; the localizer registers anew);
    supervisor_state (SupervisorState, for logs).

    What the scan does follows the config: the seed's explore-localize-pivot; a given
    ``pivot_pose`` (APPROACH, TRANSIT, PIVOT: the X_BK input is not read); or ``sweep:
    line`` (the exploration over the whole kidney, then DONE).
    """

    def __init__(self, config):
        super().__init__()
        # A bad given pose or start point fails when the diagram is built, not mid-run.
        if config.pivot_pose:
            supervisor.given_pivot_pose(config.pivot_pose)
        supervisor.given_start_xy(config.start_xy)
        self._cfg = config
        self._dt = 1.0 / config.rate_hz
        self._X = self.DeclareAbstractInputPort("X_BP", AbstractValue.Make(RigidTransform()))
        self._F = self.DeclareVectorInputPort("contact_force", 1)
        self._vis = self.DeclareVectorInputPort("kidney_visible", 1)
        self._c = self.DeclareVectorInputPort("mask_centroid", 1)
        self._XK = self.DeclareAbstractInputPort("X_BK", AbstractValue.Make(RigidTransform()))
        self._ready = self.DeclareVectorInputPort("localization_ready", 1)
        self._stopped = self.DeclareVectorInputPort("safety_stopped", 1)
        # Optional: the localizer's reason for giving no pose (abstract str; "" = none).
        self._loc_error = self.DeclareAbstractInputPort(
            "localization_error", AbstractValue.Make("")
        )
        # Optional: adaptive exploration's "estimate has settled" flag (1-vector).
        self._sufficient = self.DeclareVectorInputPort("exploration_sufficient", 1)
        self._motion = self.DeclareVectorInputPort("motion_allowed", 1)
        self._tracking = self.DeclareAbstractInputPort("tracking_error", AbstractValue.Make(""))
        self._breathing = self.DeclareAbstractInputPort("breathing_error", AbstractValue.Make(""))
        self._length = self.DeclareVectorInputPort("kidney_length_estimate", 1)
        self._pivot_model = self.DeclareAbstractInputPort(
            "pivot_model", AbstractValue.Make(supervisor.PivotModel())
        )
        self._pivot_view = self.DeclareAbstractInputPort(
            "pivot_view", AbstractValue.Make((math.nan, ""))
        )
        self._s = self.DeclareAbstractState(AbstractValue.Make(supervisor.SupervisorState()))
        self.DeclarePeriodicUnrestrictedUpdateEvent(self._dt, 0.0, self._update)
        S = lambda ctx: ctx.get_abstract_state(0).get_value()  # noqa: E731
        self._S = S
        # The vector outputs are discrete state, written by the update from the new
        # SupervisorState (_output_vectors) and exported as state output ports: the
        # controllers read them every period without a call into Python.
        self._out = {}
        for name, value in _output_vectors(supervisor.SupervisorState()).items():
            self._out[name] = self.DeclareDiscreteState(value)
            self.DeclareStateOutputPort(name, self._out[name])
        # The state itself, for logs: a function of the state alone (recomputed only when
        # the state changes, once per period).
        self.DeclareAbstractOutputPort(
            "supervisor_state",
            lambda: AbstractValue.Make(supervisor.SupervisorState()),
            lambda c, o: o.set_value(S(c)),
            prerequisites_of_calc={self.abstract_state_ticket(self._s)},
        )

    def state(self, context) -> supervisor.SupervisorState:
        return context.get_abstract_state(0).get_value()

    def _update(self, context, state):
        X = _X(self._X, context)
        R_BK = p_BK = None
        if self._XK.HasValue(context):
            X_BK = self._XK.Eval(context)
            R_BK, p_BK = X_BK.rotation().matrix(), X_BK.translation()
        c = _optional_scalar(self._c, context, 0.5)
        u = supervisor.SupervisorInputs(
            t=context.get_time(),
            R_BP=X.rotation().matrix(),
            p_BP=X.translation(),
            F_z=float(self._F.Eval(context)[0]),
            kidney_visible=_optional_scalar(self._vis, context, 1.0) > 0.5,
            c_msk=c,
            R_BK=R_BK,
            p_BK=p_BK,
            localization_ready=_optional_scalar(self._ready, context, 1.0) > 0.5,
            safety_stopped=_optional_scalar(self._stopped, context, 0.0) > 0.5,
            localization_error=(
                self._loc_error.Eval(context) if self._loc_error.HasValue(context) else ""
            ),
            exploration_sufficient=_optional_scalar(self._sufficient, context, 0.0) > 0.5,
            motion_allowed=_optional_scalar(self._motion, context, 1.0) > 0.5,
            tracking_error=(
                self._tracking.Eval(context) if self._tracking.HasValue(context) else ""
            ),
            kidney_length_estimate=_optional_scalar(self._length, context, math.nan),
            breathing_error=(
                self._breathing.Eval(context) if self._breathing.HasValue(context) else ""
            ),
            pivot_model=(
                self._pivot_model.Eval(context) if self._pivot_model.HasValue(context) else None
            ),
            pivot_view=(
                tuple(self._pivot_view.Eval(context))
                if self._pivot_view.HasValue(context)
                else None
            ),
        )
        new = supervisor.supervisor_step(self.state(context), u, self._cfg, self._dt)
        state.get_mutable_abstract_state(0).set_value(new)
        for name, value in _output_vectors(new).items():
            state.get_mutable_discrete_state(self._out[name]).set_value(value)


class SafetyLayer(LeafSystem):
    """Between controller and station; can stop the robot on its own (safety.py).

    Every control period: checks the faults, limits the desired command, latches a stop
    (zero command from this period on; a force-ceiling stop retracts along -a first) and
    logs each stop as a SafetyEvent.
    Inputs: joint_velocity_desired (7, rad/s), joint_position (7, rad), joint_velocity
    (7, rad/s), X_BP (RigidTransform), probe_force (6, on the probe in P); optional:
    image_time (1, s: stamp of the newest image), frame_time (1, s: stamp of the station's
    newest frame, when image_time is a segmentation's), kidney_visible (1, 0/1),
    segmentation_required (1, 0/1), supervisor_abort (1, 0/1), robot_ok (1, 0/1: the
    hardware station's robot/connection health).
    Outputs: joint_velocity_command (7, rad/s; state), stopped (1, 0/1; state),
    safety_events (tuple of SafetyEvent).
    """

    def __init__(
        self,
        plant,
        tip_frame,
        safety_config,
        rate_hz: float,
        kinematics: TipKinematics | None = None,
    ):
        super().__init__()
        self._cfg = safety_config
        kernels.warm_up()  # the retreat's pseudo-inverse: compiled now, not on a stop
        self._dt = 1.0 / rate_hz
        self._kin = kinematics or TipKinematics(plant, tip_frame)
        n = self._kin.nq
        self._qd = self.DeclareVectorInputPort("joint_velocity_desired", n)
        self._q = self.DeclareVectorInputPort("joint_position", n)
        self._v = self.DeclareVectorInputPort("joint_velocity", n)
        self._X = self.DeclareAbstractInputPort("X_BP", AbstractValue.Make(RigidTransform()))
        self._F = self.DeclareVectorInputPort("probe_force", 6)
        self._img = self.DeclareVectorInputPort("image_time", 1)
        self._frame = self.DeclareVectorInputPort("frame_time", 1)
        self._vis = self.DeclareVectorInputPort("kidney_visible", 1)
        self._req = self.DeclareVectorInputPort("segmentation_required", 1)
        self._abort = self.DeclareVectorInputPort("supervisor_abort", 1)
        self._ok = self.DeclareVectorInputPort("robot_ok", 1)
        self._cmd = self.DeclareDiscreteState(n)
        self._stopped = self.DeclareDiscreteState(1)
        self.DeclareAbstractState(AbstractValue.Make(SafetyState()))
        self.DeclarePeriodicUnrestrictedUpdateEvent(self._dt, 0.0, self._update)
        self.DeclareStateOutputPort("joint_velocity_command", self._cmd)
        self.DeclareStateOutputPort("stopped", self._stopped)
        self.DeclareAbstractOutputPort(
            "safety_events",
            lambda: AbstractValue.Make(()),
            lambda c, o: o.set_value(c.get_abstract_state(0).get_value().events),
        )

    def safety_state(self, context) -> SafetyState:
        return context.get_abstract_state(0).get_value()

    def _update(self, context, state):
        q = np.asarray(self._q.Eval(context), dtype=float)
        X = _X(self._X, context)
        J = self._kin.jacobian(q) if np.all(np.isfinite(q)) else np.full((6, q.size), math.nan)
        visible = bool(self._vis.Eval(context)[0] > 0.5) if self._vis.HasValue(context) else None
        u = SafetyInputs(
            t=context.get_time(),
            q=q,
            v=np.asarray(self._v.Eval(context), dtype=float),
            qdot_desired=np.asarray(self._qd.Eval(context), dtype=float),
            R_BP=X.rotation().matrix(),
            p_BP=X.translation(),
            F_z=contact_force(self._F.Eval(context)),
            J=J,
            image_time=_optional_scalar(self._img, context, math.nan),
            frame_time=_optional_scalar(self._frame, context, math.nan),
            kidney_visible=visible,
            segmentation_required=_optional_scalar(self._req, context, 1.0) > 0.5,
            supervisor_abort=_optional_scalar(self._abort, context, 0.0) > 0.5,
            robot_ok=_optional_scalar(self._ok, context, 1.0) > 0.5,
        )
        cmd, new = safety_step(self.safety_state(context), u, self._cfg)
        state.get_mutable_discrete_state(self._cmd).set_value(cmd)
        state.get_mutable_discrete_state(self._stopped).set_value([float(new.stopped)])
        state.get_mutable_abstract_state(0).set_value(new)
