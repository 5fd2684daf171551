"""The simulated station: the robot, probe and patient seen through the ports a real setup has.

``MakeSimStation(scenario, meshcat=None, patient=None)`` returns a Diagram exporting the same
ports as the hardware station (``drake_rus.hardware.station``), so the controller and the scan
are built once and never know which one they drive; ``drake_rus.stations.MakeStation`` picks
one of the two from ``scenario.hardware`` (the two stations never import each other):

The ports (name, size, unit, frame, which station) are listed once, in
``drake_rus.station_interface.STATION_PORTS``; the station checks itself against them when
built. Notes on this station's side of them: a ``joint_velocity_command`` takes effect at the
plant's next step (one step of command latency, 10 ms by default); ``probe_force`` is
estimated from ``tau_external`` through the probe Jacobian, the same formula as on hardware
(pressing into the body gives f_z < 0; ``drake_rus.robot.contact_force_along_approach``
returns the paper's F_z > 0); ``us_image`` exists when a patient with a label volume is on the
bed. Simulation truth (``label_image``, ``X_BK_true``, ``probe_contact_wrench_true``,
``contact_results``, ``plant_state``, ``breath_hold``, ``respiratory_level_true``,
``patient_offset_true``) is for metrics and tests and is never wired into a controller. A
breathing patient hears the scan through the input ``breath_prompt`` (a real patient hears
the operator or the spoken prompt).

Fault injection wraps this station from outside (``drake_rus.reliability.station``): the only
hook is ``label_image_hook``, a filter on the label frames before the ultrasound emulator.
"""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.geometry import (
    AddContactMaterial,
    AddRigidHydroelasticProperties,
    CollisionFilterDeclaration,
    GeometrySet,
    Meshcat,
    MeshcatVisualizer,
    MeshcatVisualizerParams,
    ProximityProperties,
    Role,
    RoleAssign,
)
from pydrake.math import RigidTransform
from pydrake.multibody.meshcat import ContactVisualizer, ContactVisualizerParams
from pydrake.multibody.plant import (
    AddMultibodyPlant,
    ContactResults,
    CoulombFriction,
    MultibodyPlant,
    MultibodyPlantConfig,
)
from pydrake.systems.controllers import InverseDynamics
from pydrake.systems.framework import Diagram, DiagramBuilder, LeafSystem
from pydrake.systems.primitives import (
    Adder,
    ConstantValueSource,
    ConstantVectorSource,
    Demultiplexer,
    DiscreteTimeIntegrator,
    Multiplexer,
    PassThrough,
    ZeroOrderHold,
)

from drake_rus.anatomy import load_patient
from drake_rus.imaging.chain import AddImagingChain, LabelImageHook
from drake_rus.patient_body import (
    AddPatientBody,
    AddPatientMotionDriver,
    BreathingPatient,
    MovingPose,
    PatientMotionFor,
)
from drake_rus.robot import (
    NUM_JOINTS,
    PROBE_FACE_GEOMETRY,
    AddFr3AndProbe,
    MakeControlPlant,
    ProbeForceEstimator,
    ProbePoseFromJoints,
    TipKinematics,
)
from drake_rus.scenario import CheckScenario, Scenario
from drake_rus.station_interface import CheckStationPorts

__all__ = ["MakeSimStation", "ProbeContactWrench", "LoadScenarioPatient"]


class ProbeContactWrench(LeafSystem):
    """Ground truth (sim only): the plant's contact forces on the probe bodies.

    Input ``contact_results`` (abstract ContactResults), ``X_BP``. Output
    ``probe_contact_wrench_true`` (6): as ``probe_force``, in P about P's origin (N m, N).

    With ``sample_period`` (the plant's step), the wrench is sampled in a discrete update at
    the plant's own update times, where it reads the contact solve the plant's step has
    already made (the force applied over the step that starts there), and the output is the
    held sample: a logger reading it costs no contact solve. Without it, the output is
    computed whenever read, which on a discrete plant with unsampled output ports costs one
    more contact solve per read (measured: a quarter of the scan's solves for a 50 Hz log).
    """

    def __init__(
        self,
        plant: MultibodyPlant,
        probe_body_indices,
        geometry_frames: dict,
        sample_period: float | None = None,
    ):
        super().__init__()
        self._plant = plant
        self._bodies = set(int(i) for i in probe_body_indices)
        # GeometryId -> is it on the probe (looked up once, not per contact per call).
        self._on_probe = {
            g: int(plant.GetBodyFromFrameId(f).index()) in self._bodies
            for g, f in geometry_frames.items()
        }
        results = self.DeclareAbstractInputPort(
            "contact_results", AbstractValue.Make(ContactResults())
        )
        X = self.DeclareAbstractInputPort("X_BP", AbstractValue.Make(RigidTransform()))
        if sample_period is None:
            self.DeclareVectorOutputPort(
                "probe_contact_wrench_true",
                6,
                self._calc,
                prerequisites_of_calc={
                    self.input_port_ticket(results.get_index()),
                    self.input_port_ticket(X.get_index()),
                },
            )
        else:
            state = self.DeclareDiscreteState(6)
            self.DeclarePeriodicDiscreteUpdateEvent(float(sample_period), 0.0, self._sample)
            self.DeclareStateOutputPort("probe_contact_wrench_true", state)

    def _sample(self, context, discrete_state):
        discrete_state.set_value(0, self._wrench(context))

    def _calc(self, context, output):
        output.SetFromVector(self._wrench(context))

    def _wrench(self, context) -> np.ndarray:
        results = self.get_input_port(0).Eval(context)
        X_WP = self.get_input_port(1).Eval(context)
        p_WP = X_WP.translation()
        torque_W = np.zeros(3)
        force_W = np.zeros(3)

        def accumulate(f_W, p_WC, sign):
            nonlocal torque_W, force_W
            force_W += sign * f_W
            r = p_WC - p_WP  # the cross product r x f written out (np.cross is slow here)
            torque_W += sign * np.array(
                [
                    r[1] * f_W[2] - r[2] * f_W[1],
                    r[2] * f_W[0] - r[0] * f_W[2],
                    r[0] * f_W[1] - r[1] * f_W[0],
                ]
            )

        for i in range(results.num_point_pair_contacts()):
            info = results.point_pair_contact_info(i)
            # contact_force() is the force on body B, applied at the contact point.
            if int(info.bodyB_index()) in self._bodies:
                accumulate(info.contact_force(), info.contact_point(), +1.0)
            if int(info.bodyA_index()) in self._bodies:
                accumulate(info.contact_force(), info.contact_point(), -1.0)
        for i in range(results.num_hydroelastic_contacts()):
            info = results.hydroelastic_contact_info(i)
            surface = info.contact_surface()
            onA, onB = self._on_probe[surface.id_M()], self._on_probe[surface.id_N()]
            if not (onA or onB):
                continue
            F_Ac_W = info.F_Ac_W()  # on body A's geometry M, at the surface centroid C
            p_WC = surface.centroid()
            if onA:
                accumulate(F_Ac_W.translational(), p_WC, +1.0)
                torque_W += F_Ac_W.rotational()
            if onB:
                accumulate(F_Ac_W.translational(), p_WC, -1.0)
                torque_W -= F_Ac_W.rotational()
        R_PW = X_WP.rotation().matrix().T
        return np.concatenate([R_PW @ torque_W, R_PW @ force_W])


def _probe_face_properties(scenario: Scenario) -> ProximityProperties:
    contact = scenario.contact
    props = ProximityProperties()
    AddRigidHydroelasticProperties(contact.probe_resolution_hint, props)
    AddContactMaterial(
        friction=CoulombFriction(contact.friction, contact.friction), properties=props
    )
    return props


def _plant_config(scenario: Scenario) -> MultibodyPlantConfig:
    contact = scenario.contact
    return MultibodyPlantConfig(
        time_step=contact.time_step,
        discrete_contact_approximation=contact.discrete_contact_approximation,
        contact_model="hydroelastic_with_fallback" if contact.model == "hydroelastic" else "point",
        penetration_allowance=0.002,
        # Unsampled: the contact forces the robot senses (tau_external, hence probe_force)
        # are those of the current state, not of the step that led to it. On a 5-10 ms step
        # the sampled ports' one-step-old force doubles the force ripple in PIVOT (measured
        # with `python -m benchmarks scan --validate`); unsampled, the ripple at 10 ms matches
        # the 1 ms step's. Cost: one more contact solve per controller period (the command
        # changes after the controller has read the force).
        use_sampled_output_ports=False,
    )


def LoadScenarioPatient(scenario: Scenario):
    """The patient named by ``scenario.patient.source`` (None for the placeholder torso)."""
    source = scenario.patient.source
    if source == "placeholder":
        return None
    return load_patient(source, side=scenario.patient.side, posture=scenario.patient.posture)


def MakeSimStation(
    scenario: Scenario,
    meshcat: Meshcat | None = None,
    *,
    patient=None,
    name: str = "station",
    label_image_hook: LabelImageHook | None = None,
    slice_frames: bool = True,
) -> Diagram:
    """Simulated station: discrete SAP plant (FR3 + probe + soft patient), velocity driver,
    force estimator and, with a patient, the imaging chain (see the module doc).

    ``patient``: a :class:`drake_rus.anatomy.Patient` (default: ``scenario.patient.source``;
    the placeholder torso has no images). ``label_image_hook``: see
    :func:`drake_rus.imaging.chain.AddImagingChain` (fault injection from outside).
    ``slice_frames=False``: no ultrasound frames inside the diagram (``label_image`` and
    ``us_image`` stay empty); a renderer beside the simulation makes them from the subsystem
    ``slice_sensor``'s poses (the rehearsal's video process).
    """
    CheckScenario(scenario)
    if patient is None:
        patient = LoadScenarioPatient(scenario)
    motion = PatientMotionFor(scenario)
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(_plant_config(scenario), builder)
    plant.set_name("plant")
    parts = AddFr3AndProbe(plant, scenario.robot, scenario.probe)
    patient_parts = AddPatientBody(
        plant, scenario, patient, moving=patient is not None and motion.moves
    )
    plant.Finalize()

    # Probe contact: the face is rigid hydroelastic at the scenario's resolution, all probe
    # geometries get the gel-on-skin friction.
    inspector = scene_graph.model_inspector()
    source_id = plant.get_source_id()
    for body in parts.probe_bodies:
        for geometry_id in plant.GetCollisionGeometriesForBody(body):
            if inspector.GetName(geometry_id).endswith(PROBE_FACE_GEOMETRY):
                props = _probe_face_properties(scenario)
            else:
                props = ProximityProperties()
                AddContactMaterial(
                    friction=CoulombFriction(scenario.contact.friction, scenario.contact.friction),
                    properties=props,
                )
            scene_graph.AssignRole(source_id, geometry_id, props, RoleAssign.kReplace)
    # The arm and probe never collide with themselves (the FR3 guards that on its own).
    robot_bodies = plant.GetBodyIndices(parts.robot) + plant.GetBodyIndices(parts.probe)
    robot_geometries = GeometrySet()
    for index in robot_bodies:
        robot_geometries.Add(plant.GetCollisionGeometriesForBody(plant.get_body(index)))
    scene_graph.collision_filter_manager().Apply(
        CollisionFilterDeclaration().ExcludeWithin(robot_geometries)
    )

    control_plant, tip_frame = MakeControlPlant(scenario.robot, scenario.probe)
    control_plant.set_name("control_plant")

    # Velocity driver: q_d = q0 + integral of the command; v_d = command; implicit joint PD
    # in the plant (stable on the light wrist at 1 ms), plus gravity compensation.
    # The command takes effect at the plant's next step (a zero-order hold at the plant
    # step: the robot's own command latency, one step). The controllers read the contact
    # force of the state they act on (unsampled ports) and, because their command does not
    # change the actuation of the step already under way, that force comes from the contact
    # solve the step itself makes: one contact solve per step, not two.
    q0 = np.asarray(scenario.robot.initial_joint_positions, dtype=float)
    command_in = builder.AddNamedSystem("joint_velocity_command", PassThrough(NUM_JOINTS))
    command = builder.AddNamedSystem(
        "command_hold", ZeroOrderHold(scenario.contact.time_step, NUM_JOINTS)
    )
    builder.Connect(command_in.get_output_port(), command.get_input_port())
    integrator = builder.AddNamedSystem(
        "command_integrator", DiscreteTimeIntegrator(NUM_JOINTS, scenario.contact.time_step)
    )
    q0_source = builder.AddNamedSystem("q0", ConstantVectorSource(q0))
    q_desired = builder.AddNamedSystem("q_desired", Adder(2, NUM_JOINTS))
    desired_state = builder.AddNamedSystem("desired_state", Multiplexer([NUM_JOINTS, NUM_JOINTS]))
    builder.Connect(command.get_output_port(), integrator.get_input_port())
    builder.Connect(integrator.get_output_port(), q_desired.get_input_port(0))
    builder.Connect(q0_source.get_output_port(), q_desired.get_input_port(1))
    builder.Connect(q_desired.get_output_port(), desired_state.get_input_port(0))
    builder.Connect(command.get_output_port(), desired_state.get_input_port(1))
    builder.Connect(
        desired_state.get_output_port(), plant.get_desired_state_input_port(parts.robot)
    )
    if scenario.robot.gravity_compensation:
        gravity = builder.AddNamedSystem(
            "gravity_compensation",
            InverseDynamics(
                control_plant, InverseDynamics.InverseDynamicsMode.kGravityCompensation
            ),
        )
        builder.Connect(
            plant.get_state_output_port(parts.robot), gravity.get_input_port_estimated_state()
        )
        builder.Connect(
            gravity.get_output_port_generalized_force(), plant.get_actuation_input_port(parts.robot)
        )
    else:
        zero = builder.AddNamedSystem(
            "zero_feedforward", ConstantVectorSource(np.zeros(NUM_JOINTS))
        )
        builder.Connect(zero.get_output_port(), plant.get_actuation_input_port(parts.robot))

    state_split = builder.AddNamedSystem("robot_state", Demultiplexer([NUM_JOINTS, NUM_JOINTS]))
    builder.Connect(plant.get_state_output_port(parts.robot), state_split.get_input_port())
    # One tip-kinematics object (memoised on q) for the pose and the force estimate.
    tip_kinematics = TipKinematics(control_plant, tip_frame)
    fk = builder.AddNamedSystem(
        "probe_pose", ProbePoseFromJoints(control_plant, tip_frame, tip_kinematics)
    )
    builder.Connect(state_split.get_output_port(0), fk.get_input_port(0))
    estimator = builder.AddNamedSystem(
        "probe_force_estimator", ProbeForceEstimator(control_plant, tip_frame, tip_kinematics)
    )
    builder.Connect(state_split.get_output_port(0), estimator.get_input_port(0))
    builder.Connect(
        plant.get_generalized_contact_forces_output_port(parts.robot), estimator.get_input_port(1)
    )

    truth = builder.AddNamedSystem(
        "probe_contact_truth",
        ProbeContactWrench(
            plant,
            [b.index() for b in parts.probe_bodies],
            _geometry_frame_map(plant, scene_graph),
            sample_period=scenario.contact.time_step,
        ),
    )
    builder.Connect(plant.get_contact_results_output_port(), truth.get_input_port(0))
    builder.Connect(fk.get_output_port(), truth.get_input_port(1))

    # The patient's motion (breathing, hearing the scan's prompts, and a shift): one system
    # every moving part reads.
    breathing = None
    if motion.moves:
        breathing = builder.AddNamedSystem(
            "breathing_patient", BreathingPatient(motion, scenario.contact.time_step)
        )
    if patient is not None:
        X_BPt = scenario.patient.X_BPt.GetDeterministicValue()
        volume = patient.labels
        chain = AddImagingChain(
            builder,
            scenario.imaging,
            volume,
            X_BPt @ volume.X_PtV,
            fk.get_output_port(),
            seed=scenario.random_seed,
            motion=motion if motion.moves else None,
            label_image_hook=label_image_hook,
            offset_port=None if breathing is None else breathing.GetOutputPort("offset_B"),
            slice_frames=slice_frames,
        )
        builder.ExportOutput(chain.us_image, "us_image")
        builder.ExportOutput(chain.label_image, "label_image")
        X_BK = patient.X_BK(X_BPt)
        kidney_pose = builder.AddNamedSystem(
            "X_BK_true",
            MovingPose(X_BK, motion)
            if motion.moves
            else ConstantValueSource(AbstractValue.Make(X_BK)),
        )
        if breathing is not None:
            builder.Connect(
                breathing.GetOutputPort("offset_B"), kidney_pose.GetInputPort("offset_B")
            )
        builder.ExportOutput(kidney_pose.get_output_port(), "X_BK_true")
        if "instance" in patient_parts:
            AddPatientMotionDriver(
                builder, plant, motion, patient_parts["instance"], patient=breathing
            )
    if breathing is not None:
        # Simulation truth: the patient's displacement and breathing. The prompt input is
        # what the patient hears (the scan's breath_prompt; a real patient hears the
        # operator or the spoken prompt).
        builder.ExportOutput(breathing.GetOutputPort("offset_B"), "patient_offset_true")
        if scenario.patient.motion.breathing.enabled:
            builder.ExportOutput(breathing.GetOutputPort("breath_hold"), "breath_hold")
            builder.ExportOutput(
                breathing.GetOutputPort("respiratory_level"), "respiratory_level_true"
            )
            builder.ExportInput(breathing.GetInputPort("breath_prompt"), "breath_prompt")

    if meshcat is not None:
        MeshcatVisualizer.AddToBuilder(
            builder,
            scene_graph,
            meshcat,
            MeshcatVisualizerParams(role=Role.kIllustration, prefix="station"),
        )
        ContactVisualizer.AddToBuilder(
            builder,
            plant,
            meshcat,
            ContactVisualizerParams(newtons_per_meter=200.0, newton_meters_per_meter=20.0),
        )

    builder.ExportInput(command_in.get_input_port(), "joint_velocity_command")
    builder.ExportOutput(state_split.get_output_port(0), "joint_position")
    builder.ExportOutput(state_split.get_output_port(1), "joint_velocity")
    builder.ExportOutput(fk.get_output_port(), "X_BP")
    builder.ExportOutput(
        plant.get_generalized_contact_forces_output_port(parts.robot), "tau_external"
    )
    builder.ExportOutput(estimator.get_output_port(), "probe_force")
    # Ground truth, simulation only.
    builder.ExportOutput(truth.get_output_port(), "probe_contact_wrench_true")
    builder.ExportOutput(plant.get_contact_results_output_port(), "contact_results")
    builder.ExportOutput(plant.get_state_output_port(), "plant_state")

    diagram = builder.Build()
    diagram.set_name(name)
    CheckStationPorts(diagram, "sim")
    return diagram


def _geometry_frame_map(plant, scene_graph) -> dict:
    """GeometryId -> FrameId for every collision geometry of the plant."""
    inspector = scene_graph.model_inspector()
    mapping = {}
    for geometry_id in inspector.GetAllGeometryIds(Role.kProximity):
        mapping[geometry_id] = inspector.GetFrameId(geometry_id)
    return mapping
