"""Pictures: cohort overview in the canonical frame (like seed Fig. 3b), orthogonal label
slices of a patient, and the patient's anatomy in Meshcat."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from drake_rus.anatomy.frames import R_PtBd
from drake_rus.anatomy.labels import Label
from drake_rus.anatomy.tissue_colors import (
    TISSUE_COLORS,
    label_image,
    labels_present,
    rgb,
    tissue_handles,
)
from drake_rus.io_utils import save_figure


def _save(fig, path):
    return save_figure(fig, path, dpi=110)


def label_slice_views(patient) -> list[tuple[str, int, int]]:
    """(plane, grid axis, index) of the axial, coronal and sagittal label slices through the
    kidney centroid: each plane is the slice normal to the label grid's axis nearest to the
    body's superior, anterior and left axis. The grid need not be aligned with Pt or with
    the body (a label map keeps its scanner's axes)."""
    lv = patient.labels
    c = patient.X_PtK.translation()
    R = lv.X_PtV.rotation().matrix()
    ijk = np.round(R.T @ (c - lv.X_PtV.translation()) / lv.voxel_size).astype(int)
    ijk = np.clip(ijk, 0, np.array(lv.shape) - 1)
    R_BdV = R_PtBd(patient.posture).T @ R
    views = []
    for plane, bd_axis in (("axial", 1), ("coronal", 2), ("sagittal", 0)):
        axis = int(np.argmax(np.abs(R_BdV[bd_axis])))
        views.append((plane, axis, int(ijk[axis])))
    return views


def plot_label_slices(patient, path) -> Path:
    """Three orthogonal label slices through the kidney centroid: axial, coronal and
    sagittal (:func:`label_slice_views`), drawn in label grid axes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lv = patient.labels
    vs = lv.voxel_size * 1e3
    fig, axes = plt.subplots(1, 3, figsize=(14, 4.8))
    views = []
    for plane, axis, index in label_slice_views(patient):
        a, b = [n for g, n in enumerate("ijk") if g != axis]
        sl = np.take(lv.labels, index, axis=axis)
        views.append((f"{plane} ({'ijk'[axis]} = kidney centroid)", sl, (a, b)))
    for ax, (title, sl, (a, b)) in zip(axes, views):
        ax.imshow(
            label_image(sl.T),
            origin="lower",
            interpolation="nearest",
            extent=[0, sl.shape[0] * vs, 0, sl.shape[1] * vs],
        )
        ax.set_title(title, fontsize=9)
        ax.set_xlabel(f"grid {a} (mm)")
        ax.set_ylabel(f"grid {b} (mm)")
    present = labels_present(*(sl for _, sl, _ in views))
    fig.legend(handles=tissue_handles(present), loc="lower center", ncol=6, fontsize=8)
    fig.suptitle(
        f"{patient.name}: labels ({patient.posture}, {patient.side} kidney; anatomical "
        "planes, drawn in label grid axes)",
        fontsize=10,
    )
    fig.tight_layout(rect=(0, 0.08, 1, 0.95))
    return _save(fig, path)


def plot_cohort_overview(patients, path, template=None) -> Path:
    """Kidney surfaces of a cohort in their canonical frames (x_k-y_k and x_k-z_k), one colour
    per subject, like seed Fig. 3b; the template mean in black if given."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.4))
    cmap = plt.get_cmap("tab20")
    for n, p in enumerate(patients):
        v = p.X_PtK.inverse().multiply(p.kidney_mesh.vertices.T).T[::7] * 1e3
        for ax, j in zip(axes, (1, 2)):
            ax.scatter(v[:, 0], v[:, j], s=0.3, color=cmap(n % 20), alpha=0.5)
    if template is not None:
        t = template.points * 1e3
        for ax, j in zip(axes, (1, 2)):
            ax.scatter(t[:, 0], t[:, j], s=0.3, c="k")
    for ax, lab in zip(axes, ("y_k medial->lateral (mm)", "z_k (mm)")):
        ax.set_aspect("equal")
        ax.set_xlabel("x_k inferior->superior (mm)")
        ax.set_ylabel(lab)
        ax.grid(alpha=0.3)
    fig.suptitle(
        f"{len(patients)} kidneys in their canonical frames"
        + (" (black: template)" if template is not None else "")
    )
    fig.tight_layout()
    return _save(fig, path)


def show_in_meshcat(patient, meshcat, prefix: str = "patient") -> None:
    """Skin (translucent), kidney and liver meshes and the kidney frame in a Meshcat."""
    from pydrake.geometry import Cylinder, Rgba, SurfaceTriangle, TriangleSurfaceMesh

    def tsm(m):
        return TriangleSurfaceMesh(
            [SurfaceTriangle(*map(int, f)) for f in m.faces],
            [np.asarray(v, dtype=float) for v in m.vertices],
        )

    meshcat.SetObject(
        f"{prefix}/skin", tsm(patient.skin_mesh), Rgba(*rgb(TISSUE_COLORS[Label.SOFT_TISSUE]), 0.25)
    )
    meshcat.SetObject(
        f"{prefix}/kidney",
        tsm(patient.kidney_mesh),
        Rgba(*rgb(TISSUE_COLORS[Label.KIDNEY_CORTEX]), 1.0),
    )
    if patient.liver_mesh is not None:
        meshcat.SetObject(
            f"{prefix}/liver", tsm(patient.liver_mesh), Rgba(*rgb(TISSUE_COLORS[Label.LIVER]), 0.6)
        )
    from pydrake.math import RigidTransform, RotationMatrix

    X = patient.X_PtK
    for axis, color, R in (
        ("x", Rgba(1, 0, 0, 1), RotationMatrix.MakeYRotation(np.pi / 2)),
        ("y", Rgba(0, 1, 0, 1), RotationMatrix.MakeXRotation(-np.pi / 2)),
        ("z", Rgba(0, 0, 1, 1), RotationMatrix()),
    ):
        path = f"{prefix}/X_PtK/{axis}"
        meshcat.SetObject(path, Cylinder(0.002, 0.06), color)
        meshcat.SetTransform(path, X.multiply(RigidTransform(R, R.multiply([0, 0, 0.03]))))
