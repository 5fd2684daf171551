"""The Patient: label volume, kidney and skin meshes and the true kidney pose, in the patient
frame Pt (the bed frame, see :mod:`drake_rus.anatomy.frames`).

Generated patients (:mod:`drake_rus.anatomy.generator`) and imported ones
(:func:`drake_rus.anatomy.importers.patient_from_meshes`,
:func:`~drake_rus.anatomy.importers.patient_from_label_map`) give the same object.
The label volume is built lazily, on first access of ``patient.labels`` (a few seconds at 1 mm),
so cohort statistics and the template builder never pay for it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
import trimesh
from pydrake.math import RigidTransform
from scipy.spatial import cKDTree

from drake_rus.anatomy.body_section import crop_body_section
from drake_rus.anatomy.canonical_frame import extents_in_frame, mesh_canonical_frame
from drake_rus.anatomy.export import export_patient
from drake_rus.anatomy.frames import R_PtBd, check_side_posture, reference_axes_Pt, transform_mesh
from drake_rus.anatomy.labels import LabelVolume
from drake_rus.anatomy.rasterize import mesh_mask_on_aligned_grid

__all__ = ["Patient", "vertical_depth", "kidney_metrics"]


def _check_mesh(mesh, what: str) -> trimesh.Trimesh:
    if not isinstance(mesh, trimesh.Trimesh):
        raise ValueError(f"{what}: expected a trimesh.Trimesh, got {type(mesh).__name__}")
    if len(mesh.faces) == 0:
        raise ValueError(f"{what}: the mesh is empty")
    if not mesh.is_watertight:
        raise ValueError(f"{what}: the mesh is not watertight (holes or non-manifold edges)")
    return mesh


def vertical_depth(kidney_mesh: trimesh.Trimesh, skin_mesh: trimesh.Trimesh, point=None) -> float:
    """Depth (m) of the kidney below the upper skin surface, along the vertical (-z_Pt) line
    through ``point`` (default: the mean of the kidney mesh's vertices, not its surface
    centroid, which lies 2-2.5 mm away on generated kidneys): top skin hit minus top kidney
    hit. This is what a probe on the upper surface pointing straight down must see through."""
    if point is None:
        point = kidney_mesh.vertices.mean(axis=0)
    p = np.asarray(point, dtype=float)
    top = max(skin_mesh.bounds[1, 2], kidney_mesh.bounds[1, 2]) + 1.0
    origin = np.array([[p[0], p[1], top]])
    direction = np.array([[0.0, 0.0, -1.0]])
    hits_s, _, _ = skin_mesh.ray.intersects_location(origin, direction, multiple_hits=True)
    hits_k, _, _ = kidney_mesh.ray.intersects_location(origin, direction, multiple_hits=True)
    if len(hits_s) == 0 or len(hits_k) == 0:
        return float("nan")
    return float(hits_s[:, 2].max() - hits_k[:, 2].max())


def _min_distance_to_surface(points: np.ndarray, mesh: trimesh.Trimesh, n_exact: int = 16) -> float:
    """Shortest distance (m) from any of ``points`` to the surface ``mesh``: a k-d tree on
    triangle centroids picks the closest candidates, exact point-triangle distances decide."""
    tri = mesh.triangles
    cent = tri.mean(axis=1)
    tree = cKDTree(cent)
    d, _ = tree.query(points)
    best = np.inf
    edge = float(np.linalg.norm(tri[:, 0] - tri[:, 1], axis=1).max())
    for p in points[np.argsort(d)[:n_exact]]:
        ids = tree.query_ball_point(p, float(d.min()) + edge)
        if not ids:
            continue
        cp = trimesh.triangles.closest_point(tri[ids], np.repeat(p[None], len(ids), axis=0))
        best = min(best, float(np.linalg.norm(cp - p, axis=1).min()))
    return best


def kidney_metrics(
    kidney_mesh, skin_mesh, X_PtK: RigidTransform, posture: str, upper_body_mesh=None
) -> dict:
    """Length, width, thickness (canonical extents), volume, depths and axis angles (SI)."""
    ext = extents_in_frame(kidney_mesh.vertices, X_PtK)
    R = X_PtK.rotation().matrix()
    x_k = R[:, 0]
    # Angles of the long axis in the body frame (supine reference pose).
    x_Bd = R_PtBd(posture).T @ x_k
    coronal = np.arctan2(abs(x_Bd[0]), x_Bd[1])  # off craniocaudal, in the coronal plane
    sagittal = np.arctan2(-x_Bd[2], x_Bd[1])  # > 0: upper pole posterior
    dist = _min_distance_to_surface(kidney_mesh.vertices, skin_mesh)
    return {
        "length": float(ext[0]),
        "width": float(ext[1]),
        "thickness": float(ext[2]),
        "volume": float(kidney_mesh.volume),
        "depth_vertical": vertical_depth(
            kidney_mesh, skin_mesh if upper_body_mesh is None else upper_body_mesh
        ),
        "depth_min": dist,
        "coronal_angle": float(coronal),
        "sagittal_angle": float(sagittal),
        "centroid_Pt": X_PtK.translation().tolist(),
    }


class Patient:
    """A virtual or imported patient, everything in the patient frame Pt (m).

    Attributes: ``name``, ``side`` ("right"/"left": the target kidney), ``posture``
    ("supine"/"left_lateral_decubitus"), ``kidney_mesh`` and ``skin_mesh`` (watertight
    trimesh, Pt, m), ``X_PtK`` (true canonical kidney frame, eq. 13-14 on the kidney surface),
    ``labels`` (:class:`LabelVolume`, lazily built), ``meta`` (parameters, provenance).

    Without a ``torso_builder`` the torso section is cut from the skin mesh around
    ``torso_center_Pt`` (default: the kidney frame's origin), see :meth:`torso_section`.
    """

    def __init__(
        self,
        *,
        name: str,
        side: str,
        posture: str,
        kidney_mesh,
        skin_mesh,
        labels: LabelVolume | None = None,
        label_builder: Callable[[], LabelVolume] | None = None,
        torso_builder: Callable[[float], trimesh.Trimesh] | None = None,
        kidney_mask_builder: Callable[[float], tuple] | None = None,
        liver_mesh=None,
        meta: dict | None = None,
        X_PtK: RigidTransform | None = None,
        torso_center_Pt=None,
    ):
        check_side_posture(side, posture)
        self.name = name
        self.side = side
        self.posture = posture
        self.kidney_mesh = _check_mesh(kidney_mesh, f"{name}: kidney mesh")
        self.skin_mesh = _check_mesh(skin_mesh, f"{name}: skin mesh")
        self.liver_mesh = liver_mesh
        self.meta = dict(meta or {})
        if labels is None and label_builder is None:
            raise ValueError(f"{name}: a Patient needs labels or a label builder")
        self._labels = labels
        self._label_builder = label_builder
        self._torso_builder = torso_builder
        self._kidney_mask_builder = kidney_mask_builder
        self._label_listeners: list[Callable[[LabelVolume], None]] = []
        self._torso_sections: dict[float, trimesh.Trimesh] = {}
        x_ref, y_ref = reference_axes_Pt(side, posture)
        self.X_PtK = (
            X_PtK if X_PtK is not None else mesh_canonical_frame(self.kidney_mesh, x_ref, y_ref)
        )
        self.torso_center_Pt = (
            None if torso_center_Pt is None else np.asarray(torso_center_Pt, dtype=float).reshape(3)
        )
        # The figures of the anatomy checks once they passed (drake_rus.anatomy.checks).
        self.anatomy_figures: dict | None = None

    # --- lazily built parts ----------------------------------------------------------------
    @property
    def labels(self) -> LabelVolume:
        if self._labels is None:
            self._labels = self._label_builder()
            listeners, self._label_listeners = self._label_listeners, []
            for listener in listeners:
                listener(self._labels)
        return self._labels

    @property
    def has_labels(self) -> bool:
        return self._labels is not None

    def on_labels_built(self, listener: Callable[[LabelVolume], None]) -> None:
        """Calls ``listener(labels)`` once, when the lazily built label volume is built (not
        at all if it already is: check :attr:`has_labels`). The patient cache
        (:mod:`drake_rus.anatomy.cache`) stores the volume then."""
        if self._labels is None:
            self._label_listeners.append(listener)

    def reference_axes(self):
        """(x_ref, y_ref) in Pt for the canonical-frame sign rules."""
        return reference_axes_Pt(self.side, self.posture)

    def X_BK(self, X_BPt: RigidTransform) -> RigidTransform:
        """True kidney pose in the robot base frame for the patient placement X_BPt."""
        return X_BPt.multiply(self.X_PtK)

    def torso_section(self, half_length_m: float = 0.15) -> trimesh.Trimesh:
        """Watertight body surface between the kidney centroid's level -/+ ``half_length_m``
        (along y_Pt): the compliant contact body of the simulated station."""
        if not (np.isfinite(half_length_m) and half_length_m > 0):
            raise ValueError(f"half_length_m: expected a positive length in m, got {half_length_m}")
        if self._torso_builder is not None:
            return self._torso_builder(half_length_m)
        if half_length_m not in self._torso_sections:
            center = (
                self.X_PtK.translation() if self.torso_center_Pt is None else self.torso_center_Pt
            )
            self._torso_sections[half_length_m] = crop_body_section(
                self.skin_mesh, center, half_length_m
            )
        return self._torso_sections[half_length_m]

    def kidney_mask(self, voxel_size: float = 0.001):
        """Binary mask of the target kidney on a Pt-aligned grid around it: (mask, X_PtV), voxel
        (i, j, k) centred at X_PtV * (voxel_size * [i, j, k]) like :class:`LabelVolume`."""
        if self._kidney_mask_builder is not None:
            return self._kidney_mask_builder(voxel_size)
        return mesh_mask_on_aligned_grid(self.kidney_mesh, voxel_size, margin=3 * voxel_size)

    def metrics(self) -> dict:
        """Kidney length, width, thickness, volume, depths below the skin surface ``skin_mesh``
        (vertical: :func:`vertical_depth`; shortest distance), long-axis angles (SI)."""
        if "_metrics" not in self.__dict__:
            # The vertical depth is measured to the torso around the kidney (arms excluded: on
            # a real body lying on its side the upper arm rests on the flank); the shortest
            # distance to the whole skin (the torso section has artificial flat caps).
            half = float(np.ptp(self.kidney_mesh.vertices[:, 1])) / 2 + 0.03
            body = self.torso_section(half)
            self._metrics = kidney_metrics(
                self.kidney_mesh, self.skin_mesh, self.X_PtK, self.posture, upper_body_mesh=body
            )
            for key in ("hilum_angle",):
                if key in self.meta:
                    self._metrics[key] = self.meta[key]
        return self._metrics

    def transformed(self, X: RigidTransform):
        """Meshes expressed in another frame F given X_FPt (for pictures)."""
        return transform_mesh(self.kidney_mesh, X), transform_mesh(self.skin_mesh, X)

    # --- export -------------------------------------------------------------------------
    def export(self, out_dir, fmt: str = "nrrd") -> list[Path]:
        """Writes the label volume (NRRD or NIfTI) and kidney/skin meshes (STL, mm) for 3D
        Slicer. Returns the written paths (:func:`drake_rus.anatomy.export.export_patient`)."""
        return export_patient(self, out_dir, fmt)

    def __repr__(self):
        return f"Patient({self.name!r}, side={self.side}, posture={self.posture})"
