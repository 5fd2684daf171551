"""Constrained plane-to-plane ICP of a partial kidney cloud onto the template (seed II-F).

The partial cloud ``P_local`` (points in the robot base B, from back-projected mask
boundaries) is registered onto the template (points q_j with normals n_j in the kidney's
canonical frame K). Each iteration maps the local points into K with the current (R, t) =
X_KB, finds every point's nearest template point (a scipy kd-tree, through
``MovingNearest``: successive iterations move the cloud little, so most points provably
keep a nearest neighbour among their previous candidates and skip the tree), and minimises
the plane-to-plane cost of eq. 18,

    sum_i ( n_j^T (R p_i + t - q_j) )^2,

linearised with R ~ (I + [dtheta]x) R into A x = b for x = [dtheta, dt] (small-angle least
squares). The rotation increment is clamped per component to [-theta_max, theta_max]
(eq. 19), so the registration keeps the global orientation of the heuristic start. The loop
stops when the change of the mean squared projection error falls below ``error_change_tol``
(the seed's 1e-5, in mm^2 = 1e-11 m^2) or an iteration's step falls below ``step_tolerance``
(``converged``, ``stop_reason`` "converged"), when the iterates cycle (``stop_reason``
"cycle", not converged), or at ``max_iterations`` ("iteration cap", not converged). The
result is T_k^b = X_BK = X_KB^-1.

Cycles: nearest-neighbour ICP is a discontinuous fixed-point map, and on real kidneys (whose
shape is not the template's) the correspondences can flip back and forth: the iterates
alternate between two (or a few) states, the error alternates with them, and neither
stopping test ever fires, so the loop used to run to the cap and report "not converged"
only by accident (or "converged" when two alternating errors happened to agree). Each
iteration is therefore compared with the ones 2..``cycle_max_period`` back: if it has
returned to an earlier iterate (kidney centre and rotation within ``step_tolerance``, shape
weights within ``step_tolerance`` standard deviations, error within ``error_change_tol``)
after moving away from it (the intermediate iterates differ by at least ten times as much),
the iteration is a cycle: it stops, returns the member of the cycle with the lowest error
and reports ``converged = False``, ``stop_reason = "cycle"``, the period and the spread of
the cycle's poses. Measured (kinematic exploration at ER 0.6, 15 test patients): the 2
(seed) and 3 (deformable) registrations that ran to the 200-iteration cap were cycles of
period 2-6 whose members lie within 0.01 mm and 0.05 deg of each other, the mean iteration
count fell from 48 to 25 (seed) and from 60 to 27 (deformable) with the same poses; on the
VH female's kidneys (ER 0.3-0.8) periods of 2-30 iterations, spread up to 0.13 mm and 1.0 deg.

Initialisation (``heuristic_initial_rotation``): the template's x-axis (inferior->superior) is
laid along the body's superior direction in B (the base y-axis for a patient lying along it)
and its y-axis (medial->lateral) along the kidney's lateral direction, both known from the
patient's placement on the bed. Translation: the seed starts from t0 = 0, which on our frames
(base origin at the robot, kidney ~0.5 m away) puts every point ~0.5 m from the template, so
the first correspondences are all on the nearest template side. Because the translation
update is not clamped, the solve still walks the cloud onto the template, but it needs
several times more iterations (synthetic partial clouds: 15-70 instead of 11-24, some at
the cap) for the same final pose. We start instead with the partial cloud's centroid on the
template's origin (``init_translation="centroid"``, the default); ``"zero"`` reproduces the
seed for comparison.
"""

import collections
import dataclasses

import numpy as np
from pydrake.math import RigidTransform, RotationMatrix
from scipy.spatial import cKDTree


@dataclasses.dataclass
class IcpResult:
    """Registration result and diagnostics."""

    X_BK: RigidTransform  # estimated kidney canonical frame in the base (T_k^b)
    iterations: int
    converged: bool  # stopped on the error-change or step test (not a cycle,
    # not the cap)
    rms_residual: float  # RMS plane-to-plane residual at the end (m)
    inlier_fraction: float  # points within ``inlier_distance`` of their match
    covariance: np.ndarray  # 6x6 covariance of [dtheta (rad), dt (m)] in K
    errors: np.ndarray  # mean squared projection error per iteration (m^2)
    max_rotation_steps: np.ndarray  # max |dtheta component| applied per iteration (rad)
    shape_coefficients: np.ndarray | None = None  # deformable fit: mode weights b
    # Deformable fit with size modes (localization/size_modes.py): the relative size changes
    # fitted along the canonical axes ``size_axes`` (0 = x_k, 1 = y_k, 2 = z_k).
    size_coefficients: np.ndarray | None = None
    size_axes: tuple = ()
    # Why the iteration ended: "converged" (error change or step below tolerance), "cycle"
    # (the iterates returned to an earlier one: a limit cycle) or "iteration cap".
    stop_reason: str = ""
    cycle_period: int = 0  # iterations per cycle (0: no cycle)
    # Largest distance between the returned pose and the other members of the cycle:
    # kidney centre (m) and rotation (rad); 0 without a cycle.
    cycle_translation_spread: float = 0.0
    cycle_rotation_spread: float = 0.0


class NearestPointGrid:
    """Nearest template point by table lookup: a regular grid around the template (in K)
    stores, for every cell centre, the index of the closest template point.

    Built once per template (one kd-tree query per cell); afterwards a query is an index
    computation, tens of times faster than a kd-tree query. Points outside the grid fall
    back to the kd-tree. The returned neighbour is exact up to half a cell diagonal
    (0.87 mm at 1 mm cells), which the plane-to-plane cost tolerates: it measures the
    residual along the neighbour's normal.
    """

    def __init__(self, points: np.ndarray, spacing: float = 0.001, margin: float = 0.03):
        self.points = np.asarray(points, dtype=float)
        self.tree = cKDTree(self.points)
        self.spacing = float(spacing)
        self.origin = self.points.min(axis=0) - margin
        self.shape = (
            np.ceil((self.points.max(axis=0) + margin - self.origin) / spacing).astype(int) + 1
        )
        axes = [self.origin[k] + spacing * np.arange(self.shape[k]) for k in range(3)]
        centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        _, index = self.tree.query(centres, workers=-1)
        self.table = index.astype(np.int32).reshape(self.shape)

    def query(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(distance (m), index) of the nearest template point of each row of ``p``."""
        ijk = np.rint((p - self.origin) / self.spacing).astype(np.int64)
        inside = np.all((ijk >= 0) & (ijk < self.shape), axis=1)
        j = np.empty(len(p), dtype=np.int64)
        i = ijk[inside]
        j[inside] = self.table[i[:, 0], i[:, 1], i[:, 2]]
        if not inside.all():
            _, j[~inside] = self.tree.query(p[~inside])
        return np.linalg.norm(p - self.points[j], axis=1), j


# Content-keyed cache of template kd-trees: (shape, hash of the bytes) -> (points, tree).
# A hit is confirmed by comparing the points, so a hash collision only costs a rebuild.
_TREE_CACHE = collections.OrderedDict()
_TREE_CACHE_SIZE = 8


def _template_tree(points: np.ndarray) -> cKDTree:
    """A kd-tree of template points, cached by content (the last ``_TREE_CACHE_SIZE``
    point sets): the same points give the same tree object, different points a new one.
    Built with sliding-midpoint splits (``balanced_tree=False``): about half the build time
    of median splits, queries a few percent slower, and the same nearest neighbours (only the
    tree's shape differs; a point exactly equidistant from two template points may get the
    other one). The tree keeps its own copy of the points."""
    points = np.ascontiguousarray(points, dtype=float)
    key = (points.shape, hash(points.tobytes()))
    hit = _TREE_CACHE.get(key)
    if hit is not None and np.array_equal(hit[0], points):
        _TREE_CACHE.move_to_end(key)
        return hit[1]
    copy = points.copy()
    tree = cKDTree(copy, balanced_tree=False)
    _TREE_CACHE[key] = (copy, tree)
    while len(_TREE_CACHE) > _TREE_CACHE_SIZE:
        _TREE_CACHE.popitem(last=False)
    return tree


# Safety margin (m) of the candidate test in ``MovingNearest``: far above the rounding
# error of mm-scale distances (~1e-19 m), far below any real gap between neighbours.
_CANDIDATE_MARGIN = 1e-12


class MovingNearest:
    """Nearest template point of every point of a cloud that moves a little between calls
    (the iterations of one registration or drift fit): the kd-tree's answer with a fraction
    of its work.

    A kd-tree query keeps each point's ``k`` nearest template points and r_k, the distance
    to the k-th. Once the point has moved by delta and every template point by at most D
    (``template_moved``), every template point outside the k is at least r_k - delta - D
    away, so when the nearest of the k candidates (at the current positions) is closer than
    that, it is the nearest of all. Only the points that fail this test are queried again:
    first in the last kd-tree built (the same test, its template having moved since by at
    most the motion since it was built), then, for those that still fail, in a new kd-tree
    of the current template (``tree_of()``). While the cloud moves by more than about half
    the typical gap between the first and the k-th candidate per call, most points would
    fail: such calls query every point's nearest neighbour directly. The neighbours and
    distances are the kd-tree's (up to exact ties).
    """

    def __init__(self, k: int = 4, fast_fraction: float = 0.5):
        if k < 1:
            raise ValueError(f"k: expected at least 1 candidate, got {k}")
        self.k = int(k)
        self.fast_fraction = float(fast_fraction)
        # Diagnostics: queries answered, points sent to a kd-tree, tree_of() calls.
        self.calls = 0
        self.queried = 0
        self.trees_built = 0
        self._motion = 0.0  # accumulated bound on the template's motion (m)
        self._n = (-1, -1)  # (cloud size, template size) of the state below
        self._stale = True  # candidates unusable (none yet, or skipped by a fast call)
        self._cand = None  # (M, k) candidate indices per point
        self._x0 = None  # (M, 3) positions when the candidates were found
        self._r = None  # (M,) distance to the k-th candidate then (inf: all points)
        self._m0 = None  # (M,) template motion accumulated then
        self._gap = None  # (M,) r_k - distance of the nearest then
        self._x_prev = None  # the previous call's cloud and motion
        self._motion_prev = 0.0
        self._tree = None  # the last kd-tree from tree_of() and the motion then
        self._tree_motion = 0.0

    def template_moved(self, bound: float) -> None:
        """Every template point moved by at most ``bound`` (m) since the previous call."""
        self._motion += float(bound)

    def query(self, x: np.ndarray, points: np.ndarray, tree_of) -> tuple[np.ndarray, np.ndarray]:
        """(distance (m), index) of the nearest row of ``points`` (the template now, (N, 3))
        to each row of ``x`` (M, 3); ``tree_of()`` returns a kd-tree of ``points`` and is
        called only when no earlier tree can answer."""
        x = np.asarray(x, dtype=float)
        m = len(x)
        k = min(self.k, len(points))
        self.calls += 1
        if self._n != (m, len(points)):
            self._n, self._stale = (m, len(points)), True
            self._cand = np.zeros((m, k), dtype=np.intp)
            self._x0, self._r, self._m0 = np.zeros((m, 3)), np.zeros(m), np.zeros(m)
            self._gap, self._x_prev = None, None
        fast = False
        if self._x_prev is not None and self._gap is not None:
            step = _norm_rows(x - self._x_prev) + (self._motion - self._motion_prev)
            fast = np.count_nonzero(self._gap <= 2.0 * step) > self.fast_fraction * m
        self._x_prev, self._motion_prev = x.copy(), self._motion
        if fast:
            self._stale = True
            self.queried += m
            return self._fresh_tree(tree_of).query(x)
        points_t = np.ascontiguousarray(np.asarray(points, dtype=float).T)
        if self._stale:
            dist, idx = np.zeros(m), np.zeros(m, dtype=np.intp)
            rows = np.arange(m)
            self._stale = False
        else:
            dist, idx, ok = self._candidates(
                x,
                self._cand,
                self._r - _norm_rows(x - self._x0) - (self._motion - self._m0),
                points_t,
            )
            rows = np.flatnonzero(~ok)
        if rows.size and self._tree is not None and self._tree_motion < self._motion:
            # The last tree, of the template as it was: the same test on its answer.
            d, j = self._tree.query(x[rows], k=k)
            d, j = d.reshape(-1, k), j.reshape(-1, k)
            r = d[:, -1] if k < len(points) else np.full(len(rows), np.inf)
            dd, jj, ok = self._candidates(
                x[rows], j, r - (self._motion - self._tree_motion), points_t
            )
            self._store(rows[ok], x, j[ok], r[ok], self._tree_motion, dd[ok], dist, jj[ok], idx)
            rows = rows[~ok]
        if rows.size:
            d, j = self._fresh_tree(tree_of).query(x[rows], k=k)
            d, j = d.reshape(-1, k), j.reshape(-1, k)
            r = d[:, -1] if k < len(points) else np.full(len(rows), np.inf)
            self._store(rows, x, j, r, self._motion, d[:, 0], dist, j[:, 0], idx)
        return dist, idx

    def _fresh_tree(self, tree_of):
        if self._tree is None or self._tree_motion < self._motion:
            self._tree, self._tree_motion = tree_of(), self._motion
            self.trees_built += 1
        return self._tree

    @staticmethod
    def _candidates(x, cand, bound, points_t):
        """(distance, index) of the nearest candidate of each point and whether it is
        provably the nearest of all (closer than ``bound``). ``points_t``: the template as
        (3, N) rows; the squares are summed x + y + z, as the kd-tree sums them."""
        d2 = None
        for axis in range(3):
            d = points_t[axis].take(cand)
            d -= x[:, axis : axis + 1]
            d *= d
            if d2 is None:
                d2 = d
            else:
                d2 += d
        best = d2.argmin(axis=1)
        rows = np.arange(len(x))
        dist = np.sqrt(d2[rows, best])
        return dist, cand[rows, best], dist < bound - _CANDIDATE_MARGIN

    def _store(self, rows, x, cand, r, motion, d_best, dist, j_best, idx):
        """Keeps the new candidates of ``rows`` and writes their answer into dist, idx."""
        if not rows.size:
            return
        self.queried += rows.size
        self._cand[rows], self._x0[rows], self._r[rows] = cand, x[rows], r
        self._m0[rows] = motion
        if self._gap is None:
            self._gap = np.full(len(x), np.inf)
        self._gap[rows] = r - d_best
        dist[rows], idx[rows] = d_best, j_best


def _norm_rows(v: np.ndarray) -> np.ndarray:
    """Euclidean norm of each row of (M, 3) ``v`` (as np.linalg.norm(v, axis=1) gives it)."""
    v = v * v
    return np.sqrt(v[:, 0] + v[:, 1] + v[:, 2])


def skew(w: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def rotation_from_vector(w: np.ndarray) -> np.ndarray:
    """Exact rotation exp([w]x) (Rodrigues)."""
    angle = float(np.linalg.norm(w))
    if angle < 1e-12:
        return np.eye(3) + skew(w)
    k = skew(w / angle)
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


def heuristic_initial_rotation(superior_B, lateral_B) -> RotationMatrix:
    """R_BK0: template x along the body's superior direction, y along the kidney's lateral.

    ``superior_B``: head direction of the patient in B (the base +y for the default bed).
    ``lateral_B``: medial->lateral direction of the target kidney in B (for the right kidney
    of a supine patient, the patient's right). ``lateral_B`` is orthogonalised against
    ``superior_B``; z = x cross y. Raises ValueError for a direction that is not a finite,
    non-zero 3-vector, or for ``lateral_B`` parallel to ``superior_B``.
    """
    x = _direction("superior_B", superior_B)
    y = _direction("lateral_B", lateral_B)
    y = y - (y @ x) * x
    norm = np.linalg.norm(y)
    if norm < 1e-9:
        raise ValueError("lateral_B: must not be parallel to superior_B")
    y = y / norm
    return RotationMatrix(np.column_stack([x, y, np.cross(x, y)]))


def _direction(name: str, v) -> np.ndarray:
    """``v`` as a unit 3-vector; ValueError naming ``name`` unless it is a finite, non-zero
    3-vector (a zero or NaN direction would make every rotation built from it NaN)."""
    v = np.asarray(v, dtype=float)
    if v.size != 3 or not np.all(np.isfinite(v)):
        raise ValueError(f"{name}: expected a finite 3-vector, got {v.tolist()}")
    v = v.reshape(3)
    norm = float(np.linalg.norm(v))
    if norm < 1e-9:
        raise ValueError(f"{name}: expected a non-zero direction, got {v.tolist()}")
    return v / norm


def _check_cloud(name: str, points) -> np.ndarray:
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(
            f"{name}: expected an (N, 3) array of points in m, got shape {points.shape}"
        )
    if not np.all(np.isfinite(points)):
        raise ValueError(f"{name}: contains NaN or infinite coordinates")
    return points


def register_plane_to_plane(
    P_local_B,
    template_points_K,
    template_normals_K,
    R_BK0: RotationMatrix,
    *,
    init_translation: str = "centroid",
    theta_max: float = np.deg2rad(2.0),
    error_change_tol: float = 1e-11,
    max_iterations: int = 200,
    inlier_distance: float = 0.003,
    max_correspondence_distance: float = np.inf,
    shape_modes_K: np.ndarray | None = None,
    shape_variances: np.ndarray | None = None,
    shape_regularization: float = 1e-6,
    template_tree=None,
    max_translation_step: float = np.inf,
    step_tolerance: float = 1e-4,
    cycle_max_period: int = 32,
    initial_X_BK: RigidTransform | None = None,
    initial_shape: np.ndarray | None = None,
) -> IcpResult:
    """Registers ``P_local_B`` onto the template; returns X_BK and diagnostics.

    Args:
        P_local_B: (M, 3) partial kidney surface points in B (m), M >= 6.
        template_points_K, template_normals_K: (N, 3) template points and unit normals in K.
        R_BK0: initial rotation (``heuristic_initial_rotation``).
        init_translation: "centroid" (our default) or "zero" (the seed's t0 = 0).
        theta_max: per-iteration clamp of each rotation increment component (rad), eq. 19.
        error_change_tol: stop when |E_k - E_{k-1}| < tol, E = mean squared residual (m^2).
        inlier_distance: residual bound (m) for the inlier fraction diagnostic.
        max_correspondence_distance: pairs farther apart are left out of the solve (m).
        max_translation_step: bound on the norm of each iteration's translation step (m).
        template_tree: without shape modes, a ``NearestPointGrid`` (approximate table
            lookup) or a scipy kd-tree of the template; None: a cached kd-tree built here.
        step_tolerance: also stop once an iteration moves the cloud by less than this: every
            rotation component below it (rad) and the translation step below it (m). The
            seed's error-change test alone often never fires on noisy partial clouds (the
            nearest neighbours keep switching), so the loop would run to the cap.
        cycle_max_period: longest cycle looked for (iterations; below 2 disables the test):
            an iterate that returns to the one 2..cycle_max_period iterations back (see the
            module docstring) ends the loop with ``stop_reason`` "cycle".
        shape_modes_K, shape_variances: optional statistical shape model, modes as
            (n_modes, N, 3) displacement fields with their variances (m^2): the template
            deforms as q_j(b) = q_j + sum_k b_k phi_kj, fitted with the pose as a MAP estimate:
            mean_i r_i^2 / s2 + sum_k b_k^2 / variance_k with s2 = ``shape_regularization``
            (m^2, the residual variance; default (1 mm)^2), each b_k kept within 3 standard
            deviations (deformable registration).
        initial_X_BK, initial_shape: a warm start: the iteration starts from this pose of K
            in B (instead of ``R_BK0`` and ``init_translation``) and these mode weights b
            (instead of 0; clipped to 3 standard deviations), e.g. a previous registration
            of part of the same cloud.
    """
    P = _check_cloud("P_local_B", P_local_B)
    Q = _check_cloud("template_points_K", template_points_K)
    N = _check_cloud("template_normals_K", template_normals_K)
    if P.shape[0] < 6:
        raise ValueError(f"P_local_B: need at least 6 points to register, got {P.shape[0]}")
    if N.shape != Q.shape:
        raise ValueError(f"template_normals_K: expected shape {Q.shape}, got {N.shape}")
    if init_translation not in ("centroid", "zero"):
        raise ValueError(
            f"init_translation: expected 'centroid' or 'zero', got {init_translation!r}"
        )
    if not theta_max > 0:
        raise ValueError(f"theta_max: expected a positive angle in rad, got {theta_max}")
    n_modes = 0
    if shape_modes_K is not None:
        shape_modes_K = np.asarray(shape_modes_K, dtype=float)
        if shape_modes_K.ndim != 3 or shape_modes_K.shape[1:] != Q.shape:
            raise ValueError(
                f"shape_modes_K: expected (n_modes, {Q.shape[0]}, 3), got {shape_modes_K.shape}"
            )
        n_modes = shape_modes_K.shape[0]
        shape_variances = np.asarray(shape_variances, dtype=float)
        if shape_variances.shape != (n_modes,) or np.any(shape_variances <= 0):
            raise ValueError("shape_variances: expected one positive variance per mode")

    sigma_b = np.sqrt(shape_variances) if n_modes else None
    # Modes as (N, n_modes, 3): the per-point gather of the Jacobian reads contiguous rows
    # (the same sums as on the (n_modes, N, 3) layout, in half the time).
    modes_by_point = np.ascontiguousarray(shape_modes_K.transpose(1, 0, 2)) if n_modes else None
    if initial_X_BK is not None:
        X_KB0 = initial_X_BK.inverse()
        R_KB, t_KB = X_KB0.rotation().matrix(), X_KB0.translation()
    else:
        R_KB = R_BK0.matrix().T
        t_KB = -R_KB @ P.mean(axis=0) if init_translation == "centroid" else np.zeros(3)
    b = np.zeros(n_modes)
    Q_current = Q
    if n_modes and initial_shape is not None:
        b0 = np.asarray(initial_shape, dtype=float).reshape(-1)
        if b0.shape != (n_modes,):
            raise ValueError(f"initial_shape: expected {n_modes} mode weights, got {b0.shape[0]}")
        b = np.clip(b0, -3 * sigma_b, 3 * sigma_b)
        Q_current = Q + np.einsum("k,kij->ij", b, shape_modes_K)
    # Correspondences: a NearestPointGrid given by the caller (a table lookup, approximate),
    # or exact nearest neighbours from a kd-tree (the caller's, or a cached one of the
    # current, possibly deformed, template) through MovingNearest, which queries the tree
    # only for the points whose candidates no longer provably hold their nearest neighbour:
    # successive iterations move the cloud (and the template) a little.
    if isinstance(template_tree, NearestPointGrid) and not n_modes:

        def nearest(p):
            return template_tree.query(p)[1]
    else:
        moving = MovingNearest()

        def tree_of():
            if not n_modes and template_tree is not None:
                return template_tree
            return _template_tree(Q_current)

        def nearest(p):
            return moving.query(p, Q_current, tree_of)[1]

    errors, steps = [], []
    states = []  # (R_KB, t_KB, b) at which errors[k] was measured
    converged = False
    stop_reason = "iteration cap"
    cycle = None  # (period, index of the returned member) once a cycle is found
    A = np.zeros((P.shape[0], 6 + n_modes))
    residual = np.zeros(P.shape[0])
    iteration = 0
    for iteration in range(1, max_iterations + 1):
        p = P @ R_KB.T + t_KB
        j = nearest(p)
        n = N[j]
        q = Q_current[j]
        residual = np.einsum("ij,ij->i", n, p - q)
        use = None  # every pair
        if max_correspondence_distance < np.inf:
            use = np.linalg.norm(p - q, axis=1) <= max_correspondence_distance
            if use.sum() < 6:
                use = None
        errors.append(float(np.mean((residual if use is None else residual[use]) ** 2)))
        states.append((R_KB, t_KB, b))
        period = _cycle_period(
            states, errors, cycle_max_period, step_tolerance, error_change_tol, sigma_b
        )
        if period:
            members = range(len(states) - period, len(states))
            best = min(members, key=lambda k: errors[k])
            cycle = (period, best, members)
            stop_reason = "cycle"
            break
        if len(errors) > 1 and abs(errors[-1] - errors[-2]) < error_change_tol:
            converged = True
            stop_reason = "converged"
            break
        # Row i: d r_i / d[dtheta, dt, b] = [(p_i x n_i), n_i, -n_i . phi_k,j].
        A = np.zeros((P.shape[0], 6 + n_modes))
        A[:, :3] = np.cross(p, n)
        A[:, 3:6] = n
        if n_modes:
            A[:, 6:] = -np.einsum("ij,ikj->ik", n, modes_by_point[j])
        Au, ru = (A, residual) if use is None else (A[use], residual[use])
        m = len(ru)
        H = Au.T @ Au / m
        g = -Au.T @ ru / m
        if n_modes:
            # MAP with the data term as a mean: mean(r^2) / s2 + sum b^2 / var, scaled by
            # s2 = shape_regularization. Boundary points of one partial view are strongly
            # correlated, so counting each as an independent observation would let the
            # shape modes absorb pose error (overfitting); the mean counts the view once.
            prior = shape_regularization / shape_variances
            H[6:, 6:] += np.diag(prior)
            g[6:] -= prior * b
        H[:6, :6] += 1e-12 * np.eye(6)
        try:
            x = np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            x = np.linalg.lstsq(H, g, rcond=None)[0]
        dtheta = np.clip(x[:3], -theta_max, theta_max)  # eq. 19
        steps.append(float(np.max(np.abs(dtheta))))
        dt = x[3:6]
        dt_norm = np.linalg.norm(dt)
        if dt_norm > max_translation_step:
            dt = dt * (max_translation_step / dt_norm)
        dR = rotation_from_vector(dtheta)
        R_KB = dR @ R_KB
        t_KB = dR @ t_KB + dt
        if (
            steps[-1] < step_tolerance
            and np.linalg.norm(dt) < step_tolerance
            and (not n_modes or np.all(np.abs(x[6:]) < step_tolerance * np.sqrt(shape_variances)))
        ):
            converged = True
            stop_reason = "converged"
            break
        if n_modes:
            # Stay within 3 standard deviations of the shape model.
            b = np.clip(b + x[6:], -3 * sigma_b, 3 * sigma_b)
            Q_current = _deformed(Q, b, shape_modes_K, Q_current, moving)
    spread_t = spread_r = 0.0
    if cycle is not None:
        # Return the cycle's member with the lowest error (the others are as good a guess
        # of the pose only up to the spread, reported with it).
        period, best, members = cycle
        R_KB, t_KB, b = states[best]
        if n_modes:
            Q_current = _deformed(Q, b, shape_modes_K, Q_current, moving)
        for k in members:
            dp, dr = _pose_distance(states[best], states[k])
            spread_t, spread_r = max(spread_t, dp), max(spread_r, dr)
    # Diagnostics at the final pose.
    p = P @ R_KB.T + t_KB
    j = nearest(p)
    residual = np.einsum("ij,ij->i", N[j], p - Q_current[j])
    A6 = np.column_stack([np.cross(p, N[j]), N[j]])
    dof = max(1, P.shape[0] - 6)
    sigma2 = float(residual @ residual) / dof
    covariance = sigma2 * np.linalg.pinv(A6.T @ A6)
    X_KB = RigidTransform(RotationMatrix(_orthonormalize(R_KB)), t_KB)
    return IcpResult(
        X_BK=X_KB.inverse(),
        iterations=iteration,
        converged=converged,
        rms_residual=float(np.sqrt(np.mean(residual**2))),
        inlier_fraction=float(np.mean(np.abs(residual) < inlier_distance)),
        covariance=covariance,
        errors=np.asarray(errors),
        max_rotation_steps=np.asarray(steps),
        shape_coefficients=b if n_modes else None,
        stop_reason=stop_reason,
        cycle_period=cycle[0] if cycle else 0,
        cycle_translation_spread=spread_t,
        cycle_rotation_spread=spread_r,
    )


def _deformed(Q, b, modes, Q_previous, moving: MovingNearest) -> np.ndarray:
    """The template deformed by mode weights ``b``; tells ``moving`` how far (at most) its
    points moved from ``Q_previous``."""
    Q_new = Q + np.einsum("k,kij->ij", b, modes)
    moving.template_moved(float(np.sqrt(np.max(np.sum((Q_new - Q_previous) ** 2, axis=1)))))
    return Q_new


# An iterate counts as back where it was m iterations earlier when it is within the
# tolerances of that iterate AND the iterates in between went at least this many times
# farther away: a slowly converging (or slowly damped) sequence is not a cycle.
_CYCLE_EXCURSION_FACTOR = 10.0


def _pose_distance(a, c) -> tuple[float, float]:
    """(distance of the kidney centres in B (m), rotation angle (rad)) of two ICP states
    (R_KB, t_KB, b); the centre p_BK = -R_KB^T t_KB, free of the lever arm of t_KB."""
    (Ra, ta, _), (Rc, tc, _) = a, c
    dp = float(np.linalg.norm(Ra.T @ ta - Rc.T @ tc))
    cos = np.clip((np.trace(Ra @ Rc.T) - 1.0) / 2.0, -1.0, 1.0)
    return dp, float(np.arccos(cos))


def _state_distance(a, c, sigma_b) -> float:
    """One number for "how far apart" (the step test's units: m, rad, and standard
    deviations of the shape weights, all compared with the same tolerance)."""
    dp, dr = _pose_distance(a, c)
    db = float(np.max(np.abs(a[2] - c[2]) / sigma_b)) if sigma_b is not None and len(a[2]) else 0.0
    return max(dp, dr, db)


def _cycle_period(
    states, errors, max_period: int, tolerance: float, error_tol: float, sigma_b
) -> int:
    """The period m (2..max_period) of a cycle the newest iterate closes, or 0: it is
    back within ``tolerance`` (and its error within ``error_tol``) of the iterate m back,
    after the iterates in between moved at least ``_CYCLE_EXCURSION_FACTOR`` times as far
    from it (and at least ``tolerance``)."""
    k = len(states) - 1
    for m in range(2, int(max_period) + 1):
        if k - m < 0:
            break
        if abs(errors[k] - errors[k - m]) >= error_tol:
            continue
        back = _state_distance(states[k], states[k - m], sigma_b)
        if back >= tolerance:
            continue
        excursion = max(_state_distance(states[k], states[k - i], sigma_b) for i in range(1, m))
        if excursion >= tolerance and excursion >= _CYCLE_EXCURSION_FACTOR * back:
            return m
    return 0


def _orthonormalize(R: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(R)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    return R
