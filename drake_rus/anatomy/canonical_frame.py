"""The canonical kidney frame (seed section II-D, eq. 13-14).

PCA of a kidney surface gives its principal axes; the sign rules make the frame unique:

- x_k = sgn(v1 . x_ref) v1   (long axis, inferior -> superior),
- y_k = sgn(v2 . y_ref) v2   (medial -> lateral),
- z_k = x_k x y_k, then y_k re-orthonormalised (y_k = z_k x x_k).

The frame's origin is the centroid. ``X_SK`` (pose of the canonical frame K in the frame S of
the points) maps canonical coordinates to S; its inverse maps the points into K (eq. 14).

Both the template builder and the virtual-patient ground truth (``Patient.X_PtK``) use these
functions, on surface samples of the kidney: the template on marching-cubes meshes of masks,
the patients on their kidney meshes, both through :func:`mesh_canonical_frame` (area-weighted
exact surface moments, so the frame does not depend on how the surface was triangulated).
"""

import numpy as np
from pydrake.math import RigidTransform, RotationMatrix

__all__ = [
    "canonical_frame",
    "canonical_frame_from_moments",
    "covariance_eigen",
    "mesh_surface_moments",
    "mesh_canonical_frame",
    "extents_in_frame",
]


def covariance_eigen(points: np.ndarray, weights: np.ndarray | None = None):
    """Centroid c, eigenvalues (descending) and eigenvectors (columns) of the covariance (eq. 13).

    ``C = 1/(M-1) sum (p_j - c)(p_j - c)^T = V D V^T``; with ``weights`` the weighted
    covariance (weights normalised to sum 1) is used instead.
    """
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 4:
        raise ValueError(f"points: expected an (M>=4, 3) array, got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("points: contains NaN or inf")
    if weights is None:
        c = p.mean(axis=0)
        d = p - c
        C = d.T @ d / (len(p) - 1)
    else:
        w = np.asarray(weights, dtype=float)
        w = w / w.sum()
        c = w @ p
        d = p - c
        C = (d * w[:, None]).T @ d
    evals, evecs = np.linalg.eigh(C)
    order = np.argsort(evals)[::-1]
    return c, evals[order], evecs[:, order]


def _signed_basis(v1, v2, x_ref, y_ref) -> np.ndarray:
    x_ref = np.asarray(x_ref, dtype=float)
    y_ref = np.asarray(y_ref, dtype=float)
    s1 = np.sign(v1 @ x_ref) or 1.0
    x_k = s1 * v1
    s2 = np.sign(v2 @ y_ref) or 1.0
    y_k = s2 * v2
    z_k = np.cross(x_k, y_k)
    z_k /= np.linalg.norm(z_k)
    y_k = np.cross(z_k, x_k)  # re-orthonormalise y_k
    x_k = x_k / np.linalg.norm(x_k)
    y_k = y_k / np.linalg.norm(y_k)
    return np.column_stack([x_k, y_k, z_k])


def canonical_frame_from_moments(centroid, evecs, x_ref, y_ref) -> RigidTransform:
    """Eq. 14 from a centroid and eigenvectors (columns, descending eigenvalues)."""
    R = _signed_basis(evecs[:, 0], evecs[:, 1], x_ref, y_ref)
    return RigidTransform(RotationMatrix(R), np.asarray(centroid, dtype=float))


def canonical_frame(
    points: np.ndarray, x_ref, y_ref, weights: np.ndarray | None = None
) -> RigidTransform:
    """Pose X_SK of the canonical kidney frame K in the points' frame S (eq. 13-14).

    ``x_ref``: the body's inferior -> superior direction in S; ``y_ref``: the kidney's
    medial -> lateral direction in S. Applying ``X_SK.inverse()`` to the points gives the
    centred, principal-axes-aligned kidney of eq. 14.
    """
    c, _, V = covariance_eigen(points, weights)
    return canonical_frame_from_moments(c, V, x_ref, y_ref)


def mesh_surface_moments(vertices: np.ndarray, faces: np.ndarray):
    """Area, centroid and covariance of the uniform distribution on a triangle surface.

    Exact for a triangle mesh: for a triangle (a, b, c) with area A,
    E[p] = (a+b+c)/3 and E[p p^T] = (a a^T + b b^T + c c^T + s s^T)/12 with s = a+b+c.
    """
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces, dtype=np.int64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    areas = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    total = areas.sum()
    if not total > 0:
        raise ValueError("mesh has zero surface area")
    w = areas / total
    s = a + b + c
    centroid = w @ (s / 3.0)
    second = sum((q * w[:, None]).T @ q for q in (a, b, c, s)) / 12.0
    cov = second - np.outer(centroid, centroid)
    return total, centroid, cov


def mesh_canonical_frame(mesh, x_ref, y_ref) -> RigidTransform:
    """Canonical frame (eq. 13-14) of a kidney surface mesh, from its exact surface moments."""
    _, c, C = mesh_surface_moments(mesh.vertices, mesh.faces)
    evals, evecs = np.linalg.eigh(C)
    order = np.argsort(evals)[::-1]
    return canonical_frame_from_moments(c, evecs[:, order], x_ref, y_ref)


def extents_in_frame(points: np.ndarray, X_SK: RigidTransform) -> np.ndarray:
    """Extents (3,) of ``points`` (in S) along the axes of K: length, width, thickness."""
    p_K = X_SK.inverse().multiply(np.asarray(points, dtype=float).T).T
    return p_K.max(axis=0) - p_K.min(axis=0)
