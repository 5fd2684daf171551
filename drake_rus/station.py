"""The station: the robot, probe and patient seen through the ports a real setup has.

``MakeStation(scenario, meshcat=None)`` returns a Diagram. Simulated and hardware stations
export the same ports, so the controller diagram is built once and never knows which one it
drives (DESIGN.md):

- input ``joint_velocity_command`` (7, rad/s): the FR3 joint-velocity mode;
- output ``joint_position`` (7, rad), ``joint_velocity`` (7, rad/s);
- output ``X_BP`` (abstract RigidTransform): probe tip frame P in the robot base B, by forward
  kinematics of our FR3 model plus the scenario's probe calibration;
- output ``tau_external`` (7, N m): external joint torques (environment on the arm);
- output ``probe_force`` (6): spatial force ON the probe BY the environment, expressed in P,
  about P's origin, ordered [tau_x, tau_y, tau_z, f_x, f_y, f_z] (N m, N), estimated from
  ``tau_external`` through the probe Jacobian: the same formula on hardware. Pressing into
  the body gives f_z < 0; ``contact_force_along_approach`` returns the paper's F_z > 0.

Simulation only (ground truth for metrics and tests, never wired into a controller):
``probe_contact_wrench_true`` (6, same convention as ``probe_force``, from the plant's contact
results), ``contact_results``, ``plant_state``.
"""

import dataclasses
import tempfile
from pathlib import Path

import numpy as np
from pydrake.geometry import (
    AddCompliantHydroelasticProperties, AddContactMaterial, AddRigidHydroelasticProperties,
    CollisionFilterDeclaration, Ellipsoid, GeometrySet, IllustrationProperties, Meshcat,
    MeshcatVisualizer, MeshcatVisualizerParams, ProximityProperties, Role, Convex, Mesh,
    RoleAssign)
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import (
    AddMultibodyPlant, ContactResults, CoulombFriction, MultibodyPlant, MultibodyPlantConfig)
from pydrake.multibody.tree import (
    PdControllerGains, RotationalInertia, SpatialInertia, UnitInertia)
from pydrake.systems.controllers import InverseDynamics
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import Diagram, DiagramBuilder, LeafSystem
from pydrake.systems.primitives import (
    Adder, ConstantVectorSource, Demultiplexer, DiscreteTimeIntegrator, Multiplexer, PassThrough)

from drake_rus.config_schema import ScenarioError
from drake_rus.control.kinematics import TipKinematics
from drake_rus.paths import AddDrakeRusPackages
from drake_rus.scenario import CheckScenario, Scenario
from drake_rus.sim.force_estimation import contact_force_along_approach, estimate_tip_wrench

__all__ = [
    "MakeStation", "MakeControlPlant", "AddFr3AndProbe", "ProbePoseFromJoints",
    "ProbeForceEstimator", "contact_force_along_approach", "PROBE_TIP_FRAME", "NUM_JOINTS",
]

NUM_JOINTS = 7
PROBE_TIP_FRAME = "probe_tip"
FLANGE_FRAME = "fr3_link8"
PROBE_FACE_GEOMETRY = "face_collision"


@dataclasses.dataclass
class RobotAndProbe:
    robot: object          # ModelInstanceIndex of the FR3
    probe: object          # ModelInstanceIndex of the probe
    tip_frame: object      # Frame P (probe tip)
    probe_bodies: list     # bodies rigidly attached to the flange (probe + payload)


def AddFr3AndProbe(plant: MultibodyPlant, scenario: Scenario,
                   with_collision: bool = True) -> RobotAndProbe:
    """Adds the FR3 (base welded to the world) and the calibrated probe to ``plant``."""
    parser = Parser(plant)
    AddDrakeRusPackages(parser.package_map())
    try:
        (robot,) = parser.AddModelsFromUrl(_model_url(scenario.robot.model))
    except Exception as e:
        raise ScenarioError(f"field 'robot.model': cannot load {scenario.robot.model}: {e}")
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName("fr3_link0", robot))
    parser.SetAutoRenaming(True)
    try:
        (probe,) = parser.AddModelsFromUrl(_model_url(scenario.probe.model))
    except Exception as e:
        raise ScenarioError(f"field 'probe.model': cannot load {scenario.probe.model}: {e}")
    flange = plant.GetFrameByName(FLANGE_FRAME, robot)
    probe_body = plant.GetBodyByName("probe", probe)
    X_FP = scenario.probe.X_FP.GetDeterministicValue()
    plant.WeldFrames(flange, probe_body.body_frame(), X_FP)
    tip_frame = plant.AddFrame(
        _fixed_offset_frame(PROBE_TIP_FRAME, probe_body.body_frame(), RigidTransform()))

    # Lumped holder + probe inertia from the scenario, as its own body welded at the flange.
    cal = scenario.probe
    I_Cm_F = RotationalInertia(*cal.inertia_diagonal)
    M_FCm = SpatialInertia.MakeFromCentralInertia(cal.mass, np.asarray(cal.p_FCm), I_Cm_F)
    payload = plant.AddRigidBody("probe_payload", probe, M_FCm)
    plant.WeldFrames(flange, payload.body_frame(), RigidTransform())

    for i in range(NUM_JOINTS):
        actuator = plant.GetJointActuatorByName(f"fr3_motor{i + 1}", robot)
        actuator.set_controller_gains(
            PdControllerGains(p=scenario.robot.driver_kp[i], d=scenario.robot.driver_kd[i]))
    for i, q in enumerate(scenario.robot.initial_joint_positions):
        plant.GetJointByName(f"fr3_joint{i + 1}", robot).set_default_angle(q)
    if not with_collision:
        _remove_collision_geometry(plant)
    return RobotAndProbe(robot, probe, tip_frame, [probe_body, payload])


def _model_url(model: str) -> str:
    """A package:// or file:// URL as is; a plain file path as an absolute file:// URL."""
    return model if "://" in model else Path(model).resolve().as_uri()


def _fixed_offset_frame(name, parent_frame, X_PF):
    from pydrake.multibody.tree import FixedOffsetFrame
    return FixedOffsetFrame(name, parent_frame, X_PF)


def _remove_collision_geometry(plant):
    # The control plant is never connected to a SceneGraph: nothing to remove.
    return


def MakeControlPlant(scenario: Scenario) -> tuple[MultibodyPlant, object]:
    """A plant with only the FR3 and the calibrated probe, for kinematics and gravity.

    The same model serves the hardware station (FK for ``X_BP``, Jacobians for
    ``probe_force``) and the controllers. Returns ``(plant, probe_tip_frame)``.
    """
    plant = MultibodyPlant(time_step=0.0)
    parts = AddFr3AndProbe(plant, scenario, with_collision=False)
    plant.Finalize()
    return plant, plant.GetFrameByName(PROBE_TIP_FRAME, parts.probe)


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


class ProbeContactWrench(LeafSystem):
    """Ground truth (sim only): the plant's contact forces on the probe bodies.

    Input ``contact_results`` (abstract ContactResults), ``X_BP``. Output
    ``probe_contact_wrench_true`` (6): as ``probe_force``, in P about P's origin (N m, N).
    """

    def __init__(self, plant: MultibodyPlant, probe_body_indices, geometry_frames: dict):
        super().__init__()
        self._plant = plant
        self._bodies = set(int(i) for i in probe_body_indices)
        self._geometry_frames = geometry_frames  # GeometryId -> FrameId
        self.DeclareAbstractInputPort("contact_results", AbstractValue.Make(ContactResults()))
        self.DeclareAbstractInputPort("X_BP", AbstractValue.Make(RigidTransform()))
        self.DeclareVectorOutputPort("probe_contact_wrench_true", 6, self._calc)

    def _calc(self, context, output):
        results = self.get_input_port(0).Eval(context)
        X_WP = self.get_input_port(1).Eval(context)
        p_WP = X_WP.translation()
        torque_W = np.zeros(3)
        force_W = np.zeros(3)

        def accumulate(f_W, p_WC, sign):
            nonlocal torque_W, force_W
            force_W += sign * f_W
            torque_W += sign * np.cross(p_WC - p_WP, f_W)

        for i in range(results.num_point_pair_contacts()):
            info = results.point_pair_contact_info(i)
            # contact_force() is the force on body B, applied at the contact point.
            if int(info.bodyB_index()) in self._bodies:
                accumulate(info.contact_force(), info.contact_point(), +1.0)
            if int(info.bodyA_index()) in self._bodies:
                accumulate(info.contact_force(), info.contact_point(), -1.0)
        for i in range(results.num_hydroelastic_contacts()):
            info = results.hydroelastic_contact_info(i)
            F_Ac_W = info.F_Ac_W()  # on body A's geometry M, at the surface centroid C
            p_WC = info.contact_surface().centroid()
            bodyA, bodyB = self._hydro_bodies(info)
            if bodyA in self._bodies:
                accumulate(F_Ac_W.translational(), p_WC, +1.0)
                torque_W += F_Ac_W.rotational()
            if bodyB in self._bodies:
                accumulate(F_Ac_W.translational(), p_WC, -1.0)
                torque_W -= F_Ac_W.rotational()
        R_PW = X_WP.rotation().inverse().matrix()
        output.SetFromVector(np.concatenate([R_PW @ torque_W, R_PW @ force_W]))

    def _hydro_bodies(self, info):
        surface = info.contact_surface()
        body = lambda geometry_id: self._plant.GetBodyFromFrameId(  # noqa: E731
            self._geometry_frames[geometry_id])
        return int(body(surface.id_M()).index()), int(body(surface.id_N()).index())


def _patient_properties(scenario: Scenario) -> ProximityProperties:
    contact = scenario.contact
    props = ProximityProperties()
    AddCompliantHydroelasticProperties(
        contact.patient_resolution_hint, contact.hydroelastic_modulus, props)
    AddContactMaterial(contact.hunt_crossley_dissipation, contact.point_stiffness,
                       CoulombFriction(contact.friction, contact.friction), props)
    return props


def _probe_face_properties(scenario: Scenario) -> ProximityProperties:
    contact = scenario.contact
    props = ProximityProperties()
    AddRigidHydroelasticProperties(contact.probe_resolution_hint, props)
    AddContactMaterial(friction=CoulombFriction(contact.friction, contact.friction),
                       properties=props)
    return props


def AddPatientBody(plant: MultibodyPlant, scenario: Scenario, patient=None,
                   mesh_dir: Path | None = None, moving: bool = False) -> dict:
    """Adds the patient's body surface as a soft (compliant) body welded to the world, or
    with ``moving`` on a body driven along base x, y, z (see _AddMovingPatientBody;
    ``added["instance"]`` is then its model instance).

    With ``patient=None`` and ``scenario.patient.source == "placeholder"`` the body is an
    ellipsoidal torso with the scenario's semi-axes, centred on the bed at ``X_BPt``.
    Otherwise the patient's torso section (skin mesh around the kidney level) is the contact
    body (its convex hull, compliant hydroelastic) and the skin and kidney are drawn.
    Returns a dict of what was added (geometry ids, files).
    """
    X_BPt = scenario.patient.X_BPt.GetDeterministicValue()
    props = _patient_properties(scenario)
    world = plant.world_body()
    added = {}
    if moving:
        world = _AddMovingPatientBody(plant)
        added["instance"] = world.model_instance()
    if patient is None:
        a, b, c = scenario.patient.placeholder_semi_axes
        shape = Ellipsoid(a, b, c)
        added["collision"] = plant.RegisterCollisionGeometry(
            world, X_BPt, shape, "patient_body", props)
        plant.RegisterVisualGeometry(world, X_BPt, shape, "patient_body_visual",
                                     np.array([0.93, 0.78, 0.68, 0.55]))
        return added
    mesh_dir = Path(mesh_dir) if mesh_dir else Path(tempfile.gettempdir()) / "drake_rus_meshes"
    torso = ContactHull(patient.torso_section(0.20), scenario.contact.patient_hull_vertices)
    torso_path = _mesh_file(torso, mesh_dir, "torso_section")
    added["collision"] = plant.RegisterCollisionGeometry(
        world, X_BPt, Convex(str(torso_path)), "patient_body", props)
    skin_path = _mesh_file(patient.skin_mesh, mesh_dir, "skin")
    plant.RegisterVisualGeometry(world, X_BPt, Mesh(str(skin_path)), "patient_skin_visual",
                                 np.array([0.93, 0.78, 0.68, 0.35]))
    kidney_path = _mesh_file(patient.kidney_mesh, mesh_dir, "kidney")
    plant.RegisterVisualGeometry(world, X_BPt, Mesh(str(kidney_path)), "kidney_visual",
                                 np.array([0.7, 0.15, 0.15, 0.9]))
    added["files"] = [torso_path, skin_path, kidney_path]
    return added


def _mesh_file(mesh, directory: Path, name: str) -> Path:
    """``directory/name_<content hash>.obj`` holding ``mesh`` (written atomically once, then
    reused): building many stations of the same patient does not litter the disk."""
    import hashlib

    from drake_rus.io_utils import write_text_atomic
    text = mesh.export(file_type="obj")
    path = Path(directory) / f"{name}_{hashlib.sha1(text.encode()).hexdigest()[:16]}.obj"
    if not path.exists():
        write_text_atomic(path, text)
    return path


# The moving patient body (breathing / shifting patients, simulation only): a torso of
# PATIENT_MASS kg on x-y-z prismatic joints held by implicit (SAP) PD actuators. 1e5 N/m
# with critical damping tracks breathing (<= 0.05 m/s^2) to well under 0.1 mm and gives
# 0.1 mm under a 10 N probe force; gravity is fed forward.
PATIENT_MASS = 10.0
PATIENT_KP = 1.0e5
PATIENT_KD = 2.0 * (PATIENT_KP * PATIENT_MASS) ** 0.5


def _AddMovingPatientBody(plant: MultibodyPlant):
    """A "patient" model instance: world -> prismatic x -> y -> z -> patient_torso, each
    joint PD-actuated (its desired state is the patient's displacement in B). Returns the
    torso body, whose frame coincides with the world frame at zero displacement."""
    from pydrake.multibody.tree import PrismaticJoint
    instance = plant.AddModelInstance("patient")
    parent = plant.world_body()
    for axis, name in zip(np.eye(3), "xyz"):
        last = name == "z"
        mass = PATIENT_MASS if last else 0.1
        body = plant.AddRigidBody("patient_torso" if last else f"patient_slider_{name}",
                                  instance, SpatialInertia.SolidSphereWithMass(mass, 0.1))
        joint = plant.AddJoint(PrismaticJoint(f"patient_{name}", parent.body_frame(),
                                              body.body_frame(), axis))
        actuator = plant.AddJointActuator(f"patient_{name}", joint, effort_limit=1.0e4)
        actuator.set_controller_gains(PdControllerGains(p=PATIENT_KP, d=PATIENT_KD))
        parent = body
    return parent


def ContactHull(mesh, max_vertices: int):
    """Convex hull of ``mesh`` with at most ``max_vertices`` vertices (trimesh, same frame).

    Drake treats a compliant Convex/Mesh body through its convex hull; a hull of thousands of
    skin vertices makes every contact query slow for no gain in the scanning region, so the
    hull is rebuilt from a farthest-point subset of its own vertices (deviation from the full
    hull: a few mm at 300 vertices on a torso).
    """
    hull = mesh.convex_hull
    v = np.asarray(hull.vertices)
    if len(v) <= max_vertices:
        return hull
    chosen = [int(np.argmax(v[:, 2]))]
    distance = np.linalg.norm(v - v[chosen[0]], axis=1)
    for _ in range(max_vertices - 1):
        k = int(np.argmax(distance))
        chosen.append(k)
        distance = np.minimum(distance, np.linalg.norm(v - v[k], axis=1))
    import trimesh
    return trimesh.convex.convex_hull(v[chosen])


def _plant_config(scenario: Scenario) -> MultibodyPlantConfig:
    contact = scenario.contact
    return MultibodyPlantConfig(
        time_step=contact.time_step,
        discrete_contact_approximation=contact.discrete_contact_approximation,
        contact_model="hydroelastic_with_fallback" if contact.model == "hydroelastic"
        else "point",
        penetration_allowance=0.002,
        use_sampled_output_ports=True,
    )


def MakeStation(scenario: Scenario, meshcat: Meshcat | None = None, *, patient=None,
                name: str = "station") -> Diagram:
    """The station for ``scenario.hardware``: simulated (false) or the real robot (true)."""
    CheckScenario(scenario)
    if scenario.hardware:
        try:
            from drake_rus.hardware.station import MakeHardwareStation
        except ImportError:
            raise ScenarioError(
                "field 'hardware': true needs the hardware station "
                "(drake_rus.hardware.station), which is not part of this version yet; "
                "use hardware: false for simulation") from None
        return MakeHardwareStation(scenario, meshcat=meshcat)
    return MakeSimStation(scenario, meshcat=meshcat, patient=patient, name=name)


def _load_patient(scenario: Scenario):
    source = scenario.patient.source
    if source == "placeholder":
        return None
    try:
        from drake_rus.anatomy import load_patient
    except ImportError:
        raise ScenarioError(
            f"field 'patient.source': {source!r} needs the virtual patients "
            "(drake_rus.anatomy), which are not part of this version yet; use 'placeholder'"
        ) from None
    return load_patient(source, side=scenario.patient.side, posture=scenario.patient.posture)


def MakeSimStation(scenario: Scenario, meshcat: Meshcat | None = None, *, patient=None,
                   name: str = "station") -> Diagram:
    """Simulated station: discrete SAP plant (FR3 + probe + soft patient) and velocity driver."""
    if patient is None:
        patient = _load_patient(scenario)
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(_plant_config(scenario), builder)
    plant.set_name("plant")
    parts = AddFr3AndProbe(plant, scenario)
    from drake_rus.reliability.station import moves_patient_body
    patient_parts = AddPatientBody(plant, scenario, patient,
                                   moving=moves_patient_body(scenario, patient))
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
                AddContactMaterial(friction=CoulombFriction(scenario.contact.friction,
                                                            scenario.contact.friction),
                                   properties=props)
            scene_graph.AssignRole(source_id, geometry_id, props, RoleAssign.kReplace)
    # The arm and probe never collide with themselves (the FR3 guards that on its own).
    robot_bodies = plant.GetBodyIndices(parts.robot) + plant.GetBodyIndices(parts.probe)
    robot_geometries = GeometrySet()
    for index in robot_bodies:
        robot_geometries.Add(plant.GetCollisionGeometriesForBody(plant.get_body(index)))
    scene_graph.collision_filter_manager().Apply(
        CollisionFilterDeclaration().ExcludeWithin(robot_geometries))

    control_plant, tip_frame = MakeControlPlant(scenario)
    control_plant.set_name("control_plant")

    # Velocity driver: q_d = q0 + integral of the command; v_d = command; implicit joint PD
    # in the plant (stable on the light wrist at 1 ms), plus gravity compensation.
    q0 = np.asarray(scenario.robot.initial_joint_positions, dtype=float)
    command = builder.AddNamedSystem("joint_velocity_command", PassThrough(NUM_JOINTS))
    integrator = builder.AddNamedSystem(
        "command_integrator", DiscreteTimeIntegrator(NUM_JOINTS, scenario.contact.time_step))
    q0_source = builder.AddNamedSystem("q0", ConstantVectorSource(q0))
    q_desired = builder.AddNamedSystem("q_desired", Adder(2, NUM_JOINTS))
    desired_state = builder.AddNamedSystem(
        "desired_state", Multiplexer([NUM_JOINTS, NUM_JOINTS]))
    builder.Connect(command.get_output_port(), integrator.get_input_port())
    builder.Connect(integrator.get_output_port(), q_desired.get_input_port(0))
    builder.Connect(q0_source.get_output_port(), q_desired.get_input_port(1))
    builder.Connect(q_desired.get_output_port(), desired_state.get_input_port(0))
    builder.Connect(command.get_output_port(), desired_state.get_input_port(1))
    builder.Connect(desired_state.get_output_port(),
                    plant.get_desired_state_input_port(parts.robot))
    if scenario.robot.gravity_compensation:
        gravity = builder.AddNamedSystem(
            "gravity_compensation",
            InverseDynamics(control_plant, InverseDynamics.InverseDynamicsMode.kGravityCompensation))
        builder.Connect(plant.get_state_output_port(parts.robot),
                        gravity.get_input_port_estimated_state())
        builder.Connect(gravity.get_output_port_generalized_force(),
                        plant.get_actuation_input_port(parts.robot))
    else:
        zero = builder.AddNamedSystem("zero_feedforward", ConstantVectorSource(np.zeros(7)))
        builder.Connect(zero.get_output_port(), plant.get_actuation_input_port(parts.robot))

    state_split = builder.AddNamedSystem("robot_state", Demultiplexer([NUM_JOINTS, NUM_JOINTS]))
    builder.Connect(plant.get_state_output_port(parts.robot), state_split.get_input_port())
    fk = builder.AddNamedSystem("probe_pose", ProbePoseFromJoints(control_plant, tip_frame))
    builder.Connect(state_split.get_output_port(0), fk.get_input_port(0))
    estimator = builder.AddNamedSystem(
        "probe_force_estimator", ProbeForceEstimator(control_plant, tip_frame))
    builder.Connect(state_split.get_output_port(0), estimator.get_input_port(0))
    builder.Connect(plant.get_generalized_contact_forces_output_port(parts.robot),
                    estimator.get_input_port(1))

    truth = builder.AddNamedSystem(
        "probe_contact_truth",
        ProbeContactWrench(plant, [b.index() for b in parts.probe_bodies],
                           _geometry_frame_map(plant, scene_graph)))
    builder.Connect(plant.get_contact_results_output_port(), truth.get_input_port(0))
    builder.Connect(fk.get_output_port(), truth.get_input_port(1))

    if patient is not None:
        _AddImaging(builder, scenario, patient, fk)
    if "instance" in patient_parts:     # breathing / shifting patient (scenario.faults)
        from drake_rus.reliability.station import AddPatientMotionDriver
        AddPatientMotionDriver(builder, plant, scenario, patient_parts["instance"])

    if meshcat is not None:
        MeshcatVisualizer.AddToBuilder(
            builder, scene_graph, meshcat,
            MeshcatVisualizerParams(role=Role.kIllustration, prefix="station"))
        from pydrake.multibody.meshcat import ContactVisualizer, ContactVisualizerParams
        ContactVisualizer.AddToBuilder(
            builder, plant, meshcat,
            ContactVisualizerParams(newtons_per_meter=200.0, newton_meters_per_meter=20.0))

    builder.ExportInput(command.get_input_port(), "joint_velocity_command")
    builder.ExportOutput(state_split.get_output_port(0), "joint_position")
    builder.ExportOutput(state_split.get_output_port(1), "joint_velocity")
    builder.ExportOutput(fk.get_output_port(), "X_BP")
    builder.ExportOutput(plant.get_generalized_contact_forces_output_port(parts.robot),
                         "tau_external")
    builder.ExportOutput(estimator.get_output_port(), "probe_force")
    # Ground truth, simulation only.
    builder.ExportOutput(truth.get_output_port(), "probe_contact_wrench_true")
    builder.ExportOutput(plant.get_contact_results_output_port(), "contact_results")
    builder.ExportOutput(plant.get_state_output_port(), "plant_state")

    diagram = builder.Build()
    diagram.set_name(name)
    from drake_rus.reliability.station import WithSensorFaults
    return WithSensorFaults(diagram, scenario, name)   # itself unless scenario.faults asks


def _AddImaging(builder: DiagramBuilder, scenario: Scenario, patient, fk) -> None:
    """Slice sensor + ultrasound emulator on the patient's label volume (sim only).

    Exports ``us_image`` (abstract UsFrame, grey uint8, stamped with time and X_BP), and the
    ground truth ``label_image`` (abstract UsFrame, tissue labels) and ``X_BK_true``
    (abstract RigidTransform, the true canonical kidney frame in B).
    """
    from pydrake.systems.primitives import ConstantValueSource

    from drake_rus.imaging.systems import SliceSensor, UltrasoundEmulator
    from drake_rus.reliability.station import AddFaultyImaging, needs_faulty_imaging

    if needs_faulty_imaging(scenario):   # patient motion / image faults (scenario.faults)
        return AddFaultyImaging(builder, scenario, patient, fk)
    X_BPt = scenario.patient.X_BPt.GetDeterministicValue()
    volume = patient.labels
    X_BV = X_BPt @ volume.X_PtV
    sensor = builder.AddNamedSystem("slice_sensor", SliceSensor(scenario.imaging, volume, X_BV))
    builder.Connect(fk.get_output_port(), sensor.GetInputPort("X_BP"))
    emulator = builder.AddNamedSystem(
        "ultrasound_emulator", UltrasoundEmulator(scenario.imaging, scenario.random_seed))
    builder.Connect(sensor.GetOutputPort("label_image"), emulator.GetInputPort("label_image"))
    builder.ExportOutput(emulator.GetOutputPort("us_image"), "us_image")
    builder.ExportOutput(sensor.GetOutputPort("label_image"), "label_image")
    X_BK = builder.AddNamedSystem(
        "X_BK_true", ConstantValueSource(AbstractValue.Make(patient.X_BK(X_BPt))))
    builder.ExportOutput(X_BK.get_output_port(), "X_BK_true")


def _geometry_frame_map(plant, scene_graph) -> dict:
    """GeometryId -> FrameId for every collision geometry of the plant."""
    inspector = scene_graph.model_inspector()
    mapping = {}
    for geometry_id in inspector.GetAllGeometryIds(Role.kProximity):
        mapping[geometry_id] = inspector.GetFrameId(geometry_id)
    return mapping
