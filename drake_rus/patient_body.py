"""The patient's body in the simulated station: the soft contact body, its drawing, and the
systems that move it with the patient (breathing, a shift; :mod:`drake_rus.anatomy.motion`).

Simulation only; the hardware station has a real patient.

Contact geometry, stated plainly. A virtual (or imported) patient's contact body is a
``Convex`` shape: the convex hull of the torso section around the kidney, at most
``contact.patient_hull_vertices`` (300) vertices. Drake makes a compliant convex body's
volume mesh by joining the enclosed volume's centroid to every hull triangle (a fan of
tetrahedra, one interior vertex), so ``contact.patient_resolution_hint`` has no effect on it:
the hint only sets the tetrahedra of the placeholder ellipsoid torso (``patient: {source:
placeholder}``). The hull's triangles (a few cm across over the kidney) and the probe face's
(``contact.probe_resolution_hint``) set the contact polygons; the hull lies within
``contact.patient_hull_max_gap`` (4 mm) of the skin along the kidney.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import tempfile
from pathlib import Path

import numpy as np
import trimesh
from pydrake.common.value import AbstractValue
from pydrake.geometry import (
    AddCompliantHydroelasticProperties,
    AddContactMaterial,
    Convex,
    Ellipsoid,
    Mesh,
    ProximityProperties,
)
from pydrake.math import RigidTransform
from pydrake.multibody.plant import CoulombFriction, MultibodyPlant
from pydrake.multibody.tree import PdControllerGains, PrismaticJoint, SpatialInertia
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ConstantVectorSource

from drake_rus.anatomy.motion import (
    PatientMotion,
    Prompt,
    breath_advance,
    breath_holding,
    breath_level,
    breath_prompted,
    breath_rate,
    breath_start,
    scheduled_prompts,
)
from drake_rus.io_utils import write_text_atomic
from drake_rus.scenario import Scenario

__all__ = [
    "AddPatientBody",
    "ContactHull",
    "ContactSection",
    "hull_gap_over_kidney",
    "AddPatientMotionDriver",
    "PatientMotionFor",
    "MovingPose",
    "BreathingPatient",
    "PatientMotionDesiredState",
]

LOG = logging.getLogger("drake_rus.patient_body")

# The moving patient body (breathing / shifting patients): a torso of PATIENT_MASS kg on
# x-y-z prismatic joints held by implicit (SAP) PD actuators. 1e5 N/m with critical damping
# tracks breathing (<= 0.05 m/s^2) to well under 0.1 mm and gives 0.1 mm under a 10 N probe
# force; gravity is fed forward.
PATIENT_MASS = 10.0
PATIENT_KP = 1.0e5
PATIENT_KD = 2.0 * (PATIENT_KP * PATIENT_MASS) ** 0.5


def PatientMotionFor(scenario: Scenario) -> PatientMotion:
    """The patient's motion in B for ``scenario``: ``patient.motion`` along the patient's
    superior axis (y of the patient frame Pt) and the bed's normal (its z), seeded by
    (random_seed, motion.seed)."""
    X_BPt = scenario.patient.X_BPt.GetDeterministicValue()
    R = X_BPt.rotation().matrix()
    cfg = scenario.patient.motion
    seed = int(scenario.random_seed) * 1000003 + int(cfg.seed)
    return PatientMotion(cfg, R[:, 1], seed, up_B=R[:, 2])


def _patient_properties(scenario: Scenario) -> ProximityProperties:
    """Compliant hydroelastic properties of the patient's body. The resolution hint reaches
    only the placeholder ellipsoid; a patient's convex hull is meshed without it (module
    doc)."""
    contact = scenario.contact
    props = ProximityProperties()
    AddCompliantHydroelasticProperties(
        contact.patient_resolution_hint, contact.hydroelastic_modulus, props
    )
    AddContactMaterial(
        contact.hunt_crossley_dissipation,
        contact.point_stiffness,
        CoulombFriction(contact.friction, contact.friction),
        props,
    )
    return props


def AddPatientBody(
    plant: MultibodyPlant,
    scenario: Scenario,
    patient=None,
    mesh_dir: Path | None = None,
    moving: bool = False,
) -> dict:
    """Adds the patient's body surface as a soft (compliant) body welded to the world, or
    with ``moving`` on a body driven along base x, y, z (``added["instance"]`` is then its
    model instance; drive it with :func:`AddPatientMotionDriver`).

    With ``patient=None`` the body is an ellipsoidal torso with the scenario's semi-axes,
    centred on the bed at ``X_BPt``. Otherwise the patient's torso section (skin mesh around
    the kidney level) is the contact body (its convex hull, compliant hydroelastic) and the
    skin and kidney are drawn. Returns a dict of what was added (geometry ids, files).
    """
    X_BPt = scenario.patient.X_BPt.GetDeterministicValue()
    props = _patient_properties(scenario)
    body = plant.world_body()
    added = {}
    if moving:
        body = _AddMovingPatientBody(plant)
        added["instance"] = body.model_instance()
    if patient is None:
        a, b, c = scenario.patient.placeholder_semi_axes
        shape = Ellipsoid(a, b, c)
        added["collision"] = plant.RegisterCollisionGeometry(
            body, X_BPt, shape, "patient_body", props
        )
        plant.RegisterVisualGeometry(
            body, X_BPt, shape, "patient_body_visual", np.array([0.93, 0.78, 0.68, 0.55])
        )
        return added
    mesh_dir = Path(mesh_dir) if mesh_dir else Path(tempfile.gettempdir()) / "drake_rus_meshes"
    torso, half_length, gap = ContactSection(patient, scenario.contact)
    added["section_half_length"], added["hull_gap"] = half_length, gap
    torso_path = _mesh_file(torso, mesh_dir, "torso_section")
    added["collision"] = plant.RegisterCollisionGeometry(
        body, X_BPt, Convex(str(torso_path)), "patient_body", props
    )
    skin_path = _mesh_file(patient.skin_mesh, mesh_dir, "skin")
    plant.RegisterVisualGeometry(
        body, X_BPt, Mesh(str(skin_path)), "patient_skin_visual", np.array([0.93, 0.78, 0.68, 0.35])
    )
    kidney_path = _mesh_file(patient.kidney_mesh, mesh_dir, "kidney")
    plant.RegisterVisualGeometry(
        body, X_BPt, Mesh(str(kidney_path)), "kidney_visual", np.array([0.7, 0.15, 0.15, 0.9])
    )
    added["files"] = [torso_path, skin_path, kidney_path]
    return added


def _mesh_file(mesh, directory: Path, name: str) -> Path:
    """``directory/name_<content hash>.obj`` holding ``mesh`` (written atomically once, then
    reused): building many stations of the same patient does not litter the disk."""
    text = mesh.export(file_type="obj")
    path = Path(directory) / f"{name}_{hashlib.sha1(text.encode()).hexdigest()[:16]}.obj"
    if not path.exists():
        write_text_atomic(path, text)
    return path


def _AddMovingPatientBody(plant: MultibodyPlant):
    """A "patient" model instance: world -> prismatic x -> y -> z -> patient_torso, each
    joint PD-actuated (its desired state is the patient's displacement in B). Returns the
    torso body, whose frame coincides with the world frame at zero displacement."""
    instance = plant.AddModelInstance("patient")
    parent = plant.world_body()
    for axis, name in zip(np.eye(3), "xyz"):
        last = name == "z"
        mass = PATIENT_MASS if last else 0.1
        body = plant.AddRigidBody(
            "patient_torso" if last else f"patient_slider_{name}",
            instance,
            SpatialInertia.SolidSphereWithMass(mass, 0.1),
        )
        joint = plant.AddJoint(
            PrismaticJoint(f"patient_{name}", parent.body_frame(), body.body_frame(), axis)
        )
        actuator = plant.AddJointActuator(f"patient_{name}", joint, effort_limit=1.0e4)
        actuator.set_controller_gains(PdControllerGains(p=PATIENT_KP, d=PATIENT_KD))
        parent = body
    return parent


def hull_gap_over_kidney(patient, hull, samples: int = 9, width: float = 0.02) -> float:
    """How far (m) ``hull`` lies above the skin where the probe travels: the largest
    difference of their top surfaces along z of the patient frame (the bed's up) on a strip
    ``width`` wide along the body's long axis over the kidney's centroid, as long as the
    kidney. 0 when the hull follows the skin there."""
    v = np.asarray(patient.kidney_mesh.vertices)
    c = v.mean(axis=0)
    xs, ys = np.meshgrid(
        np.linspace(c[0] - width / 2, c[0] + width / 2, 3),
        np.linspace(v[:, 1].min(), v[:, 1].max(), samples),
    )
    top = max(float(patient.skin_mesh.bounds[1, 2]), float(hull.bounds[1, 2])) + 1.0
    origins = np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, top)])
    down = np.tile([0.0, 0.0, -1.0], (len(origins), 1))

    def first_hits(mesh):
        z = np.full(len(origins), np.nan)
        locations, index, _ = mesh.ray.intersects_location(origins, down)
        for p, i in zip(locations, index):
            z[i] = p[2] if np.isnan(z[i]) else max(z[i], p[2])
        return z

    gaps = first_hits(hull) - first_hits(patient.skin_mesh)
    gaps = gaps[np.isfinite(gaps)]
    return float(max(0.0, gaps.max())) if len(gaps) else 0.0


def ContactSection(patient, contact):
    """The patient's contact body: the convex hull (``ContactHull``) of the torso section
    with the longest half-length in ``contact.patient_section_half_lengths`` whose hull lies
    within ``contact.patient_hull_max_gap`` of the skin over the kidney (else the shortest).
    Returns (hull mesh, half-length m, gap m)."""
    half_lengths = list(contact.patient_section_half_lengths)
    if not half_lengths:
        raise ValueError(
            "field 'contact.patient_section_half_lengths': expected a list of "
            "at least 1 half-length (m), got []"
        )
    best = None
    for half_length in sorted(half_lengths, reverse=True):
        hull = ContactHull(patient.torso_section(half_length), contact.patient_hull_vertices)
        gap = hull_gap_over_kidney(patient, hull)
        if best is None or gap < best[2]:
            best = (hull, half_length, gap)
        if gap <= contact.patient_hull_max_gap:
            return hull, half_length, gap
    LOG.warning(
        "the patient's contact hull lies %.1f mm above the skin over the kidney even "
        "with a %.0f mm torso section (contact.patient_hull_max_gap %.1f mm)",
        best[2] * 1000,
        best[1] * 2000,
        contact.patient_hull_max_gap * 1000,
    )
    return best


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
    return trimesh.convex.convex_hull(v[chosen])


class BreathingPatient(LeafSystem):
    """The simulated patient's motion: breathing (a :class:`~drake_rus.anatomy.motion.
    BreathState` stepped every ``period`` s, hearing the scan's prompts when
    ``follows_prompts``) plus the rigid shift.

    Input ``breath_prompt`` (1-vector, optional: a :class:`Prompt` value, what the scan
    says to the patient). Outputs ``offset_B`` and ``velocity_B`` (3-vectors, m and m/s in
    B: the displacement of the imaged anatomy, the true kidney and the contact body),
    ``breath_hold`` (1-vector: 1 while holding) and ``respiratory_level`` (1-vector: u,
    0 at end-expiration, 1 at a mean tidal inspiration). Simulation truth, all of them."""

    def __init__(self, motion: PatientMotion, period: float = 0.01):
        super().__init__()
        self._motion = motion
        self._cfg = motion.config.breathing
        self._prompt = self.DeclareVectorInputPort("breath_prompt", 1)
        self._schedule, self._horizon = [], 0.0  # the patient's own holds (hold_period)
        self._state = self.DeclareAbstractState(
            AbstractValue.Make(breath_start(self._cfg, motion.seed))
        )
        self.DeclarePeriodicUnrestrictedUpdateEvent(period, 0.0, self._update)
        deps = {self.abstract_state_ticket(self._state), self.time_ticket()}
        self.DeclareVectorOutputPort(
            "offset_B",
            3,
            lambda c, o: o.SetFromVector(self._motion.offset_at(self.level(c), c.get_time())),
            prerequisites_of_calc=deps,
        )
        self.DeclareVectorOutputPort(
            "velocity_B",
            3,
            lambda c, o: o.SetFromVector(self._motion.velocity_at(self.rate(c), c.get_time())),
            prerequisites_of_calc=deps,
        )
        self.DeclareVectorOutputPort(
            "breath_hold",
            1,
            lambda c, o: o.SetAtIndex(0, float(self._enabled and breath_holding(self.state(c)))),
            prerequisites_of_calc=deps,
        )
        self.DeclareVectorOutputPort(
            "respiratory_level",
            1,
            lambda c, o: o.SetAtIndex(0, self.level(c)),
            prerequisites_of_calc=deps,
        )

    @property
    def _enabled(self) -> bool:
        return self._cfg.enabled

    def state(self, context):
        """The breathing state, advanced to the context's time."""
        s = context.get_abstract_state(self._state).get_value()
        return breath_advance(s, context.get_time(), self._cfg, self._motion.seed)

    def level(self, context) -> float:
        if not self._enabled:
            return 0.0
        return breath_level(self.state(context), context.get_time(), self._cfg)

    def rate(self, context) -> float:
        if not self._enabled:
            return 0.0
        return breath_rate(self.state(context), context.get_time(), self._cfg)

    def _update(self, context, state):
        if not self._enabled:
            return
        t = context.get_time()
        s = self.state(context)
        if self._cfg.follows_prompts and self._prompt.HasValue(context):
            s = breath_prompted(s, int(round(self._prompt.Eval(context)[0])), t, self._cfg)
        elif self._cfg.hold_period > 0.0:
            # Nobody prompts (or the patient does not listen): holds on their own schedule,
            # acted on at the scheduled time (no reaction time), as BreathingProgram does.
            when, kind = self._scheduled(t)
            if kind != Prompt.NONE and kind != s.last_prompt:
                s = dataclasses.replace(s, pending=kind, pending_t=when, last_prompt=kind)
        state.get_mutable_abstract_state(self._state).set_value(s)

    def _scheduled(self, t: float) -> tuple[float, int]:
        """(time, Prompt) of the patient's latest own prompt at or before t ((0, NONE) if
        none yet)."""
        if t >= self._horizon:
            self._horizon = t + 600.0
            self._schedule = scheduled_prompts(self._cfg, self._horizon)
        latest = (0.0, Prompt.NONE)
        for when, kind in self._schedule:
            if when > t + 1e-9:
                break
            latest = (when, kind)
        return latest


class MovingPose(LeafSystem):
    """Output ``X`` (abstract RigidTransform): translate(offset_B) * X0, a pose moving with
    the patient (the true kidney pose of a breathing patient). Input ``offset_B`` (3-vector,
    m in B; optional: unconnected, ``motion.offset_B(t)`` of a patient nobody prompts)."""

    def __init__(self, X0: RigidTransform, motion: PatientMotion):
        super().__init__()
        self._X0 = RigidTransform(X0)
        self._motion = motion
        self._offset = self.DeclareVectorInputPort("offset_B", 3)
        self.DeclareAbstractOutputPort(
            "X",
            lambda: AbstractValue.Make(RigidTransform()),
            lambda c, o: o.set_value(RigidTransform(self._offset_of(c)) @ self._X0),
            prerequisites_of_calc={self.time_ticket(), self.all_input_ports_ticket()},
        )

    def _offset_of(self, context):
        if self._offset.HasValue(context):
            return np.asarray(self._offset.Eval(context), float)
        return self._motion.offset_B(context.get_time())


class PatientMotionDesiredState(LeafSystem):
    """Output ``desired_state`` (6-vector): [offset_B, d offset_B/dt] (m, m/s), the desired
    state of the patient body's x-y-z prismatic joints (base frame axes). Inputs
    ``offset_B``, ``velocity_B`` (3-vectors; optional: unconnected, those of a patient
    nobody prompts)."""

    def __init__(self, motion: PatientMotion):
        super().__init__()
        self._motion = motion
        self._offset = self.DeclareVectorInputPort("offset_B", 3)
        self._velocity = self.DeclareVectorInputPort("velocity_B", 3)
        self.DeclareVectorOutputPort(
            "desired_state",
            6,
            self._calc,
            prerequisites_of_calc={self.time_ticket(), self.all_input_ports_ticket()},
        )

    def _calc(self, context, output):
        t = context.get_time()
        if self._offset.HasValue(context):
            x = np.concatenate([self._offset.Eval(context), self._velocity.Eval(context)])
        else:
            x = np.concatenate([self._motion.offset_B(t), self._motion.velocity_B(t)])
        output.SetFromVector(x)


def AddPatientMotionDriver(
    builder: DiagramBuilder,
    plant: MultibodyPlant,
    motion: PatientMotion,
    instance,
    patient: BreathingPatient | None = None,
) -> None:
    """Drives the moving patient body: desired state = the patient displacement of the
    imaging chain (``patient``'s outputs, or the same PatientMotion nobody prompts), gravity
    fed forward."""
    desired = builder.AddNamedSystem("patient_motion", PatientMotionDesiredState(motion))
    if patient is not None:
        builder.Connect(patient.GetOutputPort("offset_B"), desired.GetInputPort("offset_B"))
        builder.Connect(patient.GetOutputPort("velocity_B"), desired.GetInputPort("velocity_B"))
    builder.Connect(desired.get_output_port(), plant.get_desired_state_input_port(instance))
    mass = sum(plant.get_body(b).default_mass() for b in plant.GetBodyIndices(instance))
    g = float(np.linalg.norm(plant.gravity_field().gravity_vector()))
    weight = builder.AddNamedSystem("patient_weight", ConstantVectorSource([0.0, 0.0, mass * g]))
    builder.Connect(weight.get_output_port(), plant.get_actuation_input_port(instance))
