"""Kidney template and statistical shape model (seed section II-D, eq. 13-15).

Per subject: kidney mask -> marching cubes surface -> canonical frame by PCA with the sign
rules (eq. 13-14) -> surface expressed in its canonical frame -> farthest-point resampling.
Across subjects: feature-based alignment to a reference, the subject of median size (FPFH
features from Open3D, then RANSAC and point-to-plane ICP here, deterministic: the pipeline of
the seed's ref. [34]), kNN re-indexing so vertex j corresponds across subjects, mean shape
(eq. 15). Two refinement passes re-align every subject to the current mean (generalised
Procrustes, rigid). The template is finally expressed in its own
canonical frame. The corresponded shapes also give a statistical shape model: PCA, keeping
the modes that explain 95% of the variance.
"""

from __future__ import annotations

import io
import json
import math
import sys
import tempfile
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from tqdm import tqdm

from drake_rus.anatomy.canonical_frame import canonical_frame, mesh_canonical_frame
from drake_rus.anatomy.rasterize import mask_to_mesh
from drake_rus.io_utils import atomic_path

__all__ = [
    "Subject",
    "subject_from_mask",
    "subject_from_mesh",
    "farthest_point_sampling",
    "align_to_reference",
    "reference_subject",
    "correspond",
    "mean_shape",
    "shape_model",
    "centred_shapes",
    "point_area_weights",
    "axis_agreement_deg",
    "convergence",
    "build_template",
    "TemplateResult",
    "save_template",
]

FORMAT_VERSION = 1
# Metadata keys that hold a build's timings (s): in the .json beside a template, not in it.
TIMING_SUFFIX = "_seconds"


@dataclass
class Subject:
    """One kidney surface in its own canonical frame K_i (m)."""

    name: str
    points: np.ndarray  # dense surface points (vertices of the MC mesh), (P, 3)
    normals: np.ndarray  # outward unit normals, (P, 3)
    X_SK: object = None  # canonical frame in the source frame S (RigidTransform)
    volume: float = float("nan")


def subject_from_mesh(mesh, x_ref, y_ref, name: str = "subject") -> Subject:
    """Eq. 13-14 on a watertight kidney surface (source frame S), then points in K."""
    X_SK = mesh_canonical_frame(mesh, x_ref, y_ref)
    X_KS = X_SK.inverse()
    R = X_KS.rotation().matrix()
    pts = X_KS.multiply(np.asarray(mesh.vertices).T).T
    nrm = np.asarray(mesh.vertex_normals) @ R.T
    return Subject(name=name, points=pts, normals=nrm, X_SK=X_SK, volume=float(mesh.volume))


def subject_from_mask(
    mask: np.ndarray,
    X_SV,
    voxel_size: float,
    x_ref,
    y_ref,
    name: str = "subject",
    sigma_vox: float = 1.0,
) -> Subject:
    """Marching cubes on a (lightly smoothed) kidney mask, then :func:`subject_from_mesh`."""
    mesh = mask_to_mesh(mask, X_SV, voxel_size, sigma_vox=sigma_vox, what=f"{name}: kidney mask")
    return subject_from_mesh(mesh, x_ref, y_ref, name)


def farthest_point_sampling(points: np.ndarray, n: int, start: int = 0) -> np.ndarray:
    """Indices of ``n`` farthest-point samples (greedy, deterministic from ``start``)."""
    p = np.asarray(points, dtype=float)
    if n >= len(p):
        return np.arange(len(p))
    idx = np.empty(n, dtype=np.int64)
    idx[0] = start
    d = np.linalg.norm(p - p[start], axis=1)
    for k in range(1, n):
        idx[k] = int(np.argmax(d))
        d = np.minimum(d, np.linalg.norm(p - p[idx[k]], axis=1))
    return idx


def _open3d():
    """Open3D, imported on first use (about 1-3 s): the scan imports this package (through
    the template selection) without registering anything."""
    import open3d

    return open3d


def _pcd(points, normals=None):
    o3d = _open3d()
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=float)))
    if normals is not None:
        pc.normals = o3d.utility.Vector3dVector(np.asarray(normals, dtype=float))
    return pc


def _rotation_angle(T: np.ndarray) -> float:
    return float(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1)))


def order_free_sum(terms) -> np.ndarray:
    """Sum of ``terms`` over axis 0, the same to the last bit whatever the order of the
    additions (a permutation of the rows, another BLAS, another memory alignment): every
    term is rounded to one fixed-point grid, 2^-40 of the largest term (about 1e-12
    relative), and the integers are added exactly. Up to 2^22 rows (2^22 terms of at most
    2^40 quanta each stay below int64's 2^63), all finite (ValueError otherwise)."""
    terms = np.asarray(terms, dtype=float)
    if len(terms) > 2**22:
        raise ValueError(f"order_free_sum: at most 2^22 rows, got {len(terms)}")
    finite = np.isfinite(terms)
    if not finite.all():
        raise ValueError(
            f"order_free_sum: terms must be finite numbers; {int((~finite).sum())} of "
            f"{terms.size} are NaN or inf"
        )
    largest = float(np.max(np.abs(terms))) if terms.size else 0.0
    if not largest > 0.0:
        return np.zeros(terms.shape[1:])
    # A power of two (exact scaling), never below the smallest double, 2^-1074 (every
    # double is a whole multiple of it, so subnormal terms are summed exactly too).
    quantum = math.ldexp(1.0, max(math.frexp(largest)[1] - 40, -1074))
    return np.rint(terms / quantum).astype(np.int64).sum(axis=0).astype(float) * quantum


def transform_points(T: np.ndarray, points: np.ndarray, *, rotate_only: bool = False):
    """``points`` (N, 3) moved by the 4x4 ``T`` (or only rotated), written out element by
    element so that every point's result is the same whatever the array's length or memory
    alignment (a BLAS product need not be)."""
    T = np.asarray(T, dtype=float)
    p = np.asarray(points, dtype=float)
    out = p[:, 0:1] * T[:3, 0] + p[:, 1:2] * T[:3, 1] + p[:, 2:3] * T[:3, 2]
    return out if rotate_only else out + T[:3, 3]


def _small_motion(x: np.ndarray) -> np.ndarray:
    """4x4 for the update x = (alpha, beta, gamma, t) of a point-to-plane step: rotation
    Rz(gamma) Ry(beta) Rx(alpha), translation t (the parameterisation of Open3D's
    TransformationEstimationPointToPlane)."""
    a, b, g = (float(v) for v in x[:3])
    ca, sa, cb, sb, cg, sg = (
        math.cos(a),
        math.sin(a),
        math.cos(b),
        math.sin(b),
        math.cos(g),
        math.sin(g),
    )
    T = np.eye(4)
    T[:3, :3] = [
        [cg * cb, cg * sb * sa - sg * ca, cg * sb * ca + sg * sa],
        [sg * cb, sg * sb * sa + cg * ca, sg * sb * ca - cg * sa],
        [-sb, cb * sa, cb * ca],
    ]
    T[:3, 3] = x[3:]
    return T


def _finite_points(name: str, a) -> np.ndarray:
    """``a`` as a float (N, 3) array of finite numbers, or one line naming ``name``."""
    p = np.asarray(a, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"point_to_plane_icp: {name}: expected an (N, 3) array, got {p.shape}")
    bad = ~np.all(np.isfinite(p), axis=1)
    if bad.any():
        raise ValueError(
            f"point_to_plane_icp: {name}: {int(bad.sum())} of {len(p)} rows contain NaN or inf"
        )
    return p


# Directions of the point-to-plane normal equations whose eigenvalue is below this fraction
# of the largest are left alone: the pairs do not determine them (a surface with a symmetry:
# a cylinder's axis, a plane's in-plane shift). Over the real 20-kidney template's 1119
# ICP steps the smallest was above 4e-5 of it: kidneys never come near.
ICP_RCOND = 1e-10


def _normal_equations_step(JTJ: np.ndarray, JTr: np.ndarray) -> np.ndarray | None:
    """The ICP step x solving JTJ x = -JTr; when JTJ is (nearly) singular, the least-squares
    step in the directions the pairs determine and none in the others (much as Open3D's LDLT
    solve zeroes a zero pivot's component), rather than no step at all or a step of metres
    along a direction only noise determines. None when no direction is determined."""
    w, V = np.linalg.eigh(JTJ)
    if not w[-1] > 0.0:
        return None
    if w[0] > ICP_RCOND * w[-1]:
        return np.linalg.solve(JTJ, -JTr)
    keep = w > ICP_RCOND * w[-1]
    Vk = V[:, keep]
    return np.sum(Vk * (np.sum(Vk * -JTr[:, None], axis=0) / w[keep]), axis=1)


def point_to_plane_icp(
    src_pts,
    ref_pts,
    ref_nrm,
    T0,
    max_corr: float,
    max_iteration: int = 60,
    relative_fitness: float = 1e-6,
    relative_rmse: float = 1e-6,
):
    """Point-to-plane ICP of the source points onto the reference surface (points and unit
    normals), from the 4x4 ``T0``; pairs farther apart than ``max_corr`` (m) are left out.
    Returns (T, fitness, inlier_rmse): fitness is the share of source points paired, the
    rmse (m) over the pairs. Open3D's iteration and stopping rule (fitness and rmse both
    changing by less than their tolerances), with nearest neighbours from one k-d tree and
    the normal equations summed by :func:`order_free_sum`: the same inputs give the same T
    to the last bit, in any process, in any order of the source points. Points, normals and
    ``T0`` must be finite (ValueError naming the argument otherwise)."""
    src = _finite_points("src_pts", src_pts)
    ref = _finite_points("ref_pts", ref_pts)
    nrm = _finite_points("ref_nrm", ref_nrm)
    if nrm.shape != ref.shape:
        raise ValueError(
            f"point_to_plane_icp: ref_nrm: expected one normal per reference point, shape "
            f"{ref.shape}, got {nrm.shape}"
        )
    T = np.array(T0, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        what = f"shape {T.shape}" if T.shape != (4, 4) else "NaN or inf"
        raise ValueError(f"point_to_plane_icp: T0: expected a finite 4x4 transform, got {what}")
    tree = cKDTree(ref)

    def pairs(T):
        moved = transform_points(T, src)
        dist, idx = tree.query(moved, distance_upper_bound=max_corr)
        ok = np.isfinite(dist)
        n_pairs = int(ok.sum())
        fitness = n_pairs / len(src) if len(src) else 0.0
        rmse = math.sqrt(float(order_free_sum(dist[ok] ** 2)) / n_pairs) if n_pairs else 0.0
        return moved[ok], idx[ok], fitness, rmse

    moved, idx, fitness, rmse = pairs(T)
    for _ in range(max_iteration):
        if len(idx) < 6:
            break
        q, n = ref[idx], nrm[idx]
        r = (moved[:, 0] - q[:, 0]) * n[:, 0]
        r = r + (moved[:, 1] - q[:, 1]) * n[:, 1] + (moved[:, 2] - q[:, 2]) * n[:, 2]
        J = np.concatenate([np.cross(moved, n), n], axis=1)  # (K, 6)
        JTJ = order_free_sum(J[:, :, None] * J[:, None, :])
        JTr = order_free_sum(J * r[:, None])
        x = _normal_equations_step(JTJ, JTr)
        if x is None or not np.all(np.isfinite(x)):
            break
        T = np.sum(_small_motion(x)[:, :, None] * T[None, :, :], axis=1)  # no BLAS
        previous = (fitness, rmse)
        moved, idx, fitness, rmse = pairs(T)
        if (
            abs(previous[0] - fitness) < relative_fitness
            and abs(previous[1] - rmse) < relative_rmse
        ):
            break
    return T, float(fitness), float(rmse)


def feature_correspondences(f_src: np.ndarray, f_ref: np.ndarray, min_mutual: float = 0.1):
    """Pairs (i, j) of source and reference points whose FPFH features (rows) are mutual
    nearest neighbours; every source point with its nearest when fewer than ``min_mutual``
    of the source points have a mutual one (Open3D's mutual filter and its fallback)."""
    j = cKDTree(f_ref).query(f_src)[1]
    i_back = cKDTree(f_src).query(f_ref)[1]
    i = np.arange(len(f_src))
    mutual = i_back[j] == i
    if mutual.sum() >= min_mutual * len(f_src):
        return i[mutual], j[mutual]
    return i, j


def _kabsch_batch(P: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotations R (K, 3, 3) and translations t (K, 3) with R P_k + t ~ Q_k, least squares,
    for point sets P, Q (K, n, 3)."""
    cp, cq = P.mean(axis=1), Q.mean(axis=1)
    H = np.einsum("kni,knj->kij", P - cp[:, None], Q - cq[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(U) * np.linalg.det(Vt))  # det(V U^T): no reflection
    d[d == 0] = 1.0
    D = np.zeros_like(H)
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    R = np.einsum("kji,kjl,klm->kim", Vt, D, U.transpose(0, 2, 1))
    t = cq - np.einsum("kij,kj->ki", R, cp)
    return R, t


def feature_ransac(
    src_pts,
    ref_pts,
    f_src,
    f_ref,
    max_dist: float,
    *,
    seed: int = 0,
    iterations: int = 20000,
    edge_ratio: float = 0.9,
    chunk: int = 500,
) -> np.ndarray:
    """Global rigid alignment (4x4, source onto reference) from FPFH feature matches
    (:func:`feature_correspondences`): RANSAC over ``iterations`` triples of matches drawn
    with numpy's generator seeded by ``seed`` (all of them: Open3D's early stop at 0.999
    confidence, tried here, stopped on wrong turns, as any rough overlay pairs most of a
    kidney's points within ``max_dist``), each kept only when its three edges agree in
    length within ``edge_ratio`` and its points land within ``max_dist`` (m) of their
    matches (Open3D's two checkers); the winner, as Open3D scores them, pairs the most
    source points with a reference point within ``max_dist`` (ties: the smaller RMS).
    Identity when no triple passes. Open3D's RANSAC (its threads race to the result) gave
    another answer from run to run; this one gives the same for the same inputs.
    ``iterations`` and ``chunk`` (triples drawn per batch) must be positive integers
    (ValueError naming the argument otherwise)."""
    for name, value in (("iterations", iterations), ("chunk", chunk)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"feature_ransac: {name}: expected a positive integer, got {value!r}")
    src = np.asarray(src_pts, dtype=float)
    ref = np.asarray(ref_pts, dtype=float)
    i, j = feature_correspondences(np.asarray(f_src, float), np.asarray(f_ref, float))
    A, B = src[i], ref[j]
    if len(A) < 3:
        return np.eye(4)
    rng = np.random.default_rng(int(seed))
    tree = cKDTree(ref)
    best = (-1, np.inf, None)
    for start in range(0, iterations, chunk):
        k = min(chunk, iterations - start)
        tri = rng.integers(0, len(A), size=(k, 3))
        tri = tri[(tri[:, 0] != tri[:, 1]) & (tri[:, 0] != tri[:, 2]) & (tri[:, 1] != tri[:, 2])]
        if len(tri) == 0:
            continue
        P, Q = A[tri], B[tri]
        ok = np.ones(len(tri), bool)
        for a, b in ((0, 1), (0, 2), (1, 2)):
            dp = np.linalg.norm(P[:, a] - P[:, b], axis=1)
            dq = np.linalg.norm(Q[:, a] - Q[:, b], axis=1)
            ok &= (dp >= edge_ratio * dq) & (dq >= edge_ratio * dp)
        if not ok.any():
            continue
        R, t = _kabsch_batch(P[ok], Q[ok])
        moved = np.einsum("kij,knj->kni", R, P[ok]) + t[:, None]
        ok_dist = np.all(np.linalg.norm(moved - Q[ok], axis=2) <= max_dist, axis=1)
        R, t = R[ok_dist], t[ok_dist]
        if len(R) == 0:
            continue
        # Scored as Open3D scores them: the whole source cloud moved, each point paired with
        # its nearest reference point within max_dist; most pairs, then the smallest RMS.
        moved = np.einsum("kij,nj->kni", R, src) + t[:, None]
        dist = tree.query(moved.reshape(-1, 3), distance_upper_bound=max_dist)[0]
        dist = dist.reshape(len(R), len(src))
        paired = np.isfinite(dist)
        count = paired.sum(axis=1)
        rms = np.sqrt(np.where(paired, dist, 0.0) ** 2 @ np.ones(len(src)) / np.maximum(count, 1))
        m = np.lexsort((rms, -count))[0]  # the first such in draw order on ties
        if count[m] > best[0] or (count[m] == best[0] and rms[m] < best[1]):
            best = (int(count[m]), float(rms[m]), (R[m], t[m]))
    if best[2] is None or best[0] < 3:
        return np.eye(4)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = best[2]
    return T


def align_to_reference(
    src_pts,
    src_nrm,
    ref_pts,
    ref_nrm,
    *,
    feature_radius=0.012,
    max_corr=0.005,
    use_features=True,
    init=None,
    max_angle=np.radians(30),
    seed=0,
):
    """Rigid T (4x4) mapping the source cloud onto the reference: FPFH + RANSAC (global),
    then point-to-plane ICP. Because both clouds are already in canonical frames, a global
    result rotating more than ``max_angle`` is treated as a symmetric flip and replaced by
    the identity start. Returns (T, info)."""
    o3d = _open3d()
    src, ref = _pcd(src_pts, src_nrm), _pcd(ref_pts, ref_nrm)
    reg = o3d.pipelines.registration
    T0 = np.eye(4) if init is None else np.asarray(init, dtype=float)
    info = {"ransac": False, "ransac_rejected": False}
    if use_features:
        param = o3d.geometry.KDTreeSearchParamHybrid(radius=feature_radius, max_nn=100)
        f_src = np.asarray(reg.compute_fpfh_feature(src, param).data).T
        f_ref = np.asarray(reg.compute_fpfh_feature(ref, param).data).T
        T = feature_ransac(src_pts, ref_pts, f_src, f_ref, 2 * max_corr, seed=seed)
        if _rotation_angle(T) <= max_angle and np.linalg.norm(T[:3, 3]) < 0.03:
            T0 = T
            info["ransac"] = True
        else:
            info["ransac_rejected"] = True
    # Point-to-plane ICP, coarse then fine, in this module (point_to_plane_icp), not
    # Open3D's: Open3D's sums differ in their last bits from call to call, and over the
    # refinement passes a poorly fitting subject then lands in another basin.
    T, _, _ = point_to_plane_icp(src_pts, ref_pts, ref_nrm, T0, 2 * max_corr, 60)
    T, fitness, rmse = point_to_plane_icp(src_pts, ref_pts, ref_nrm, T, max_corr, 60)
    info["fitness"] = fitness
    info["rmse"] = rmse
    return T, info


def correspond(ref_points: np.ndarray, points: np.ndarray, normals: np.ndarray):
    """kNN re-indexing: for every reference vertex j, the nearest subject point (aligned).
    Returns (P_i (M, 3), N_i (M, 3)): vertex j of every subject is the same landmark."""
    _, idx = cKDTree(points).query(ref_points)
    return points[idx], normals[idx]


def mean_shape(aligned: np.ndarray) -> np.ndarray:
    """Eq. 15: P_template = 1/N sum_i P_i^aligned, for aligned shapes (N, M, 3)."""
    a = np.asarray(aligned, dtype=float)
    if a.ndim != 3 or a.shape[2] != 3 or len(a) == 0:
        raise ValueError(f"aligned shapes: expected (N>=1, M, 3), got {a.shape}")
    return a.mean(axis=0)


def shape_model(aligned: np.ndarray, keep: float = 0.95):
    """PCA of corresponded shapes: (mean (M,3), modes (k, M, 3) unit-norm, variances (k,) m^2,
    explained fraction (k,)), keeping the fewest modes explaining ``keep`` of the variance."""
    a = np.asarray(aligned, dtype=float)
    n = len(a)
    mean = a.mean(axis=0)
    X = (a - mean).reshape(n, -1)
    if n < 2:
        return mean, np.zeros((0,) + mean.shape), np.zeros(0), np.zeros(0)
    _, s, Vt = np.linalg.svd(X, full_matrices=False)
    var = s**2 / (n - 1)
    frac = var / var.sum() if var.sum() > 0 else np.zeros_like(var)
    k = int(np.searchsorted(np.cumsum(frac), keep - 1e-12) + 1)
    k = min(k, len(var))
    return mean, Vt[:k].reshape(k, *mean.shape), var[:k], frac[:k]


def point_area_weights(points: np.ndarray, k: int = 6) -> np.ndarray:
    """Surface area (relative, sums to 1) each of ``points`` (M, 3), samples of a closed
    surface, stands for: the mean squared distance to its ``k`` nearest neighbours (a
    sample's share of a uniformly sampled surface is the square of the local spacing).
    Moments weighted by it are those of the surface, not of the sampling."""
    p = np.asarray(points, dtype=float)
    d, _ = cKDTree(p).query(p, k=k + 1)
    a = np.mean(d[:, 1:] ** 2, axis=1)
    return a / a.sum()


def centred_shapes(aligned: np.ndarray) -> np.ndarray:
    """The corresponded shapes (N, M, 3) each translated so that its centroid is the mean
    shape's: their mean is unchanged, and the PCA of their deviations (:func:`shape_model`)
    gives centroid-free modes (a mode deforms the kidney about its centre, it does not move
    it; the registration's translation owns that). kNN correspondence samples each subject
    at the reference's vertices, so their centroids scatter by about a millimetre, which
    the modes otherwise carry as translation."""
    a = np.asarray(aligned, dtype=float)
    return a - a.mean(axis=1, keepdims=True) + a.mean(axis=(0, 1))


def axis_agreement_deg(rotations: np.ndarray) -> np.ndarray:
    """Angle (deg) between each subject's long axis x_k (its own canonical frame, eq. 14:
    inferior -> superior) and the template's, from the rotations (N, 3, 3) that take each
    subject's canonical frame into the template's. Above 90 deg a subject was aligned
    upside down: its superior pole on the template's inferior one."""
    R = np.asarray(rotations, dtype=float).reshape(-1, 3, 3)
    return np.degrees(np.arccos(np.clip(R[:, 0, 0], -1.0, 1.0)))


def convergence(aligned: np.ndarray) -> dict:
    """Template convergence as N grows (seed Fig. 3d): mean per-vertex change of the running
    mean when subject n is added (n = 2..N), and mean distance to the final template."""
    a = np.asarray(aligned, dtype=float)
    n = len(a)
    running = np.cumsum(a, axis=0) / np.arange(1, n + 1)[:, None, None]
    change = [float("nan")] + [
        float(np.linalg.norm(running[k] - running[k - 1], axis=1).mean()) for k in range(1, n)
    ]
    to_final = [float(np.linalg.norm(running[k] - running[-1], axis=1).mean()) for k in range(n)]
    return {"n": list(range(1, n + 1)), "change": change, "to_final": to_final}


@dataclass
class TemplateResult:
    points: np.ndarray
    normals: np.ndarray
    aligned: np.ndarray  # (N, M, 3) corresponded shapes in the template frame
    modes: np.ndarray
    variances: np.ndarray
    explained: np.ndarray
    convergence: dict
    meta: dict = field(default_factory=dict)


def reference_subject(subjects: list[Subject]) -> int:
    """Index of the subject whose canonical extents (length, width, thickness) are nearest,
    relatively, to the median extents of all subjects (the first such on ties)."""
    ext = np.array([np.ptp(np.asarray(s.points), axis=0) for s in subjects])
    med = np.median(ext, axis=0)
    return int(np.argmin(np.linalg.norm((ext - med) / med, axis=1)))


def build_template(
    subjects: list[Subject],
    n_points: int = 2500,
    refine_passes: int = 2,
    use_features: bool = True,
    seed: int = 0,
    progress: bool = True,
    keep_variance: float = 0.95,
) -> TemplateResult:
    """The template pipeline on subjects already in their canonical frames (see module doc)."""
    if len(subjects) < 1:
        raise ValueError("build_template: no subjects")
    t0 = time.time()
    # Farthest-point resampling of every subject (Open3D's FPS, deterministic first point).
    fps = []
    for s in tqdm(subjects, desc="template: FPS", disable=not progress, leave=False):
        pc = _pcd(s.points, s.normals).farthest_point_down_sample(min(n_points, len(s.points)))
        fps.append((np.asarray(pc.points), np.asarray(pc.normals)))
    # The reference is the subject of median size: kNN correspondence (for every reference
    # point the nearest subject point) pulls the mean towards the reference's size, so a
    # short or long first subject would make a short or long template.
    ref = reference_subject(subjects)
    ref_pts, ref_nrm = fps[ref]
    transforms = [np.eye(4) for _ in subjects]
    infos = [{} for _ in subjects]
    # Global feature-based alignment of every subject to the reference.
    for i in tqdm(
        [i for i in range(len(subjects)) if i != ref],
        desc="template: FPFH+RANSAC+ICP",
        disable=not progress,
        leave=False,
    ):
        transforms[i], infos[i] = align_to_reference(
            fps[i][0], fps[i][1], ref_pts, ref_nrm, use_features=use_features, seed=seed + i
        )

    def gather(ref):
        shapes, normals = [], []
        for i, s in enumerate(subjects):
            T = transforms[i]
            pts = transform_points(T, s.points)
            nrm = transform_points(T, s.normals, rotate_only=True)
            P, N = correspond(ref, pts, nrm)
            shapes.append(P)
            normals.append(N)
        return np.stack(shapes), np.stack(normals)

    aligned, normals = gather(ref_pts)
    mean = mean_shape(aligned)
    for _ in range(refine_passes):
        mean_n = normals.mean(axis=0)
        mean_n /= np.linalg.norm(mean_n, axis=1, keepdims=True)
        for i in range(len(subjects)):
            T, _ = align_to_reference(
                fps[i][0], fps[i][1], mean, mean_n, use_features=False, init=transforms[i]
            )
            transforms[i] = T
        aligned, normals = gather(mean)
        mean = mean_shape(aligned)
    # Express everything in the template's own canonical frame (eq. 13-14 on the mean),
    # from its surface moments as for patients (mesh_canonical_frame is area-weighted):
    # kNN correspondence leaves the mean's points unevenly spread over its surface.
    X = canonical_frame(mean, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], point_area_weights(mean))
    R, c = X.rotation().matrix(), X.translation()
    aligned = (aligned - c) @ R
    normals = normals @ R
    mean = mean_shape(aligned)
    mean_n = normals.mean(axis=0)
    mean_n /= np.linalg.norm(mean_n, axis=1, keepdims=True)
    # Modes from the centred shapes: centroid-free and orthonormal (the mean is the same).
    _, modes, var, frac = shape_model(centred_shapes(aligned), keep_variance)
    conv = convergence(aligned)
    x_axis_deg = axis_agreement_deg([R.T @ T[:3, :3] for T in transforms])
    meta = {
        "format_version": FORMAT_VERSION,
        "equations": "seed II-D eq. 13-15",
        "n_subjects": len(subjects),
        "n_points": int(len(mean)),
        "subjects": [s.name for s in subjects],
        "reference": subjects[ref].name,
        "volumes_ml": [round(s.volume * 1e6, 2) for s in subjects],
        "ransac_used": int(sum(1 for i in infos if i.get("ransac"))),
        "ransac_rejected": int(sum(1 for i in infos if i.get("ransac_rejected"))),
        "refine_passes": refine_passes,
        "keep_variance": keep_variance,
        "n_modes": int(len(var)),
        "explained": [float(f) for f in frac],
        "convergence": conv,
        # Each subject's long axis against the template's (deg; > 90: aligned upside down).
        "x_axis_agreement_deg": [round(float(d), 2) for d in x_axis_deg],
        "extent_mm": (np.ptp(mean, axis=0) * 1e3).round(2).tolist(),
        "build_seconds": round(time.time() - t0, 2),
    }
    return TemplateResult(
        points=mean,
        normals=mean_n,
        aligned=aligned,
        modes=modes,
        variances=var,
        explained=frac,
        convergence=conv,
        meta=meta,
    )


def save_template(result: TemplateResult, path, extra_meta: dict | None = None) -> Path:
    """Writes the template npz atomically (temporary file, then rename; mode 0644 under the
    usual umask, like every written file: ``drake_rus.io_utils.atomic_path``), and its
    metadata beside it (.json). The same template gives the same .npz, byte for byte: its
    zip entries carry a fixed date and its metadata leaves out the build's timings (the
    keys ending in ``_seconds``, kept in the .json, where :func:`load_template` finds
    them), so a study's or a benchmark's digest of the file names the template, not the
    moment it was built."""
    path = Path(path)
    meta = dict(result.meta)
    meta.update(extra_meta or {})
    timeless = {k: v for k, v in meta.items() if not k.endswith(TIMING_SUFFIX)}
    arrays = {
        "points": result.points.astype(np.float64),
        "normals": result.normals,
        "mean_shape": result.points,
        "modes": result.modes,
        "variances": result.variances,
        "explained": result.explained,
        "aligned": result.aligned.astype(np.float32),
        "convergence_n": np.asarray(result.convergence["n"]),
        "convergence_change": np.asarray(result.convergence["change"]),
        "convergence_to_final": np.asarray(result.convergence["to_final"]),
        "metadata": np.asarray(json.dumps(timeless)),
    }
    json.dumps(meta)  # a value JSON cannot hold raises before anything is written
    write_npz_reproducibly(path, arrays)
    write_metadata_json(path, meta)
    return path


def write_npz_reproducibly(path, arrays: dict) -> None:
    """``arrays`` as a compressed .npz that :func:`numpy.load` reads, whose bytes depend on
    the arrays alone (``numpy.savez_compressed`` stamps every entry with the time), on any
    operating system, given numpy's .npy header and zlib's deflate (another zlib build, such
    as zlib-ng, compresses the same bytes differently). Written atomically
    (``atomic_path``): an array that cannot be stored (an object array) raises and leaves
    whatever was at ``path`` as it was, and nothing half-written."""
    with atomic_path(path) as tmp, zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
        for name, value in arrays.items():
            buffer = io.BytesIO()
            np.lib.format.write_array(buffer, np.asanyarray(value), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            info.create_system = 3  # Unix, as the mode above says (ZipInfo: 0 on Windows)
            z.writestr(info, buffer.getvalue())


def save_template_to_cache(
    result: TemplateResult, path, extra_meta: dict | None, *, asked_for: bool
) -> Path:
    """Saves the template at ``path`` and returns where it went. A path the user asked for
    (``asked_for``) must be written (OSError raised); a cache folder that cannot be written
    instead keeps the template in a temporary file, with a warning on stderr."""
    path = Path(path)
    try:
        return save_template(result, path, extra_meta)
    except OSError as e:
        if asked_for:
            raise
        tmp = Path(tempfile.mkdtemp(prefix="drake_rus_template_")) / path.name
        print(
            f"warning: template cache {path.parent} not writable ({e}); using {tmp}",
            file=sys.stderr,
        )
        return save_template(result, tmp, extra_meta)


def write_metadata_json(npz_path, meta: dict) -> Path:
    """Human-readable copy of the template metadata beside the .npz (same stem, .json)."""
    out = Path(npz_path).with_suffix(".json")
    with atomic_path(out) as tmp:
        tmp.write_text(json.dumps(meta, indent=1))
    return out
