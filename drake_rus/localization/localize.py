"""Kidney localization: partial cloud + template -> T_k^b (seed II-F), seed or deformable.

``localize`` is the plain function (kinematic studies call it directly); ``IcpLocalizer`` is
the LeafSystem the scan supervisor triggers in its LOCALIZE phase.
"""

import dataclasses
import functools
import math

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import EventStatus, LeafSystem

from drake_rus.anatomy.frames import reference_axes_Pt
from drake_rus.executor import InlineExecutor
from drake_rus.imaging.frames import PointCloud
from drake_rus.localization.config import LocalizationConfig
from drake_rus.localization.icp import (
    IcpResult,
    NearestPointGrid,
    heuristic_initial_rotation,
    register_plane_to_plane,
)
from drake_rus.localization.size_modes import scaled_shape, size_mode_prior, size_modes_K
from drake_rus.paths import REPO_ROOT
from drake_rus.template import DEFAULT_TEMPLATE_PATH, load_template
from drake_rus.template.ct import is_template_spec, resolve_template

KIDNEY_SIDES = ("right", "left")


@dataclasses.dataclass
class RegistrationTemplate:
    """Template points/normals in the canonical frame K (m) and its shape modes; ``side``:
    the kidney side its subjects were ("right", "left"; None when its file does not say)."""

    points: np.ndarray  # (N, 3)
    normals: np.ndarray  # (N, 3) unit outward normals
    modes: np.ndarray | None = None  # (n_modes, N, 3) displacement fields (m per unit b)
    variances: np.ndarray | None = None  # (n_modes,) variances of the mode weights
    side: str | None = None

    def __post_init__(self):
        self.points = np.asarray(self.points, dtype=float)
        self.normals = np.asarray(self.normals, dtype=float)
        if self.modes is not None:
            modes = np.asarray(self.modes, dtype=float)
            self.modes = modes.reshape(modes.shape[0], -1, 3)
            self.variances = np.asarray(self.variances, dtype=float).reshape(-1)
        self._grid = None
        self._mirrored = None  # for_side's mirror image, made once

    def unexplained_sd(self, k: int) -> float:
        """Per-point RMS deviation (m) of the template's own subjects from it that its first
        ``k`` shape modes do not explain: sqrt(sum of the variances beyond k / points).
        The variances of the stored modes only (a template keeps the modes that explain 95%
        of its subjects' variance); 0 without modes."""
        if self.variances is None or len(self.variances) <= k:
            return 0.0
        return float(np.sqrt(np.sum(self.variances[k:]) / len(self.points)))

    @property
    def tree(self) -> NearestPointGrid:
        """Nearest-point lookup on the mean template (built on first use, ~1 s)."""
        if self._grid is None:
            self._grid = NearestPointGrid(self.points)
        return self._grid

    def for_side(self, side: str) -> "RegistrationTemplate":
        """This template for a ``side`` ("right" or "left") kidney: itself when it was built
        from that side (or its side is unknown), else its mirror image through the sagittal
        plane.

        The canonical frame (eq. 13-14) takes y_k medial -> lateral, so z_k = x_k x y_k
        points anteriorly for a right kidney and posteriorly for a left one: the left kidney,
        the right one's mirror image, is the right kidney's shape reflected through z_k (the
        template builder's ``--side both`` rule, ``template.ct.subject_from_ct_kidney``). No
        rotation turns a right template into that shape; the reflection does: z_k -> -z_k
        for the points, the normals and the shape modes."""
        if side not in KIDNEY_SIDES:
            raise ValueError(f"side: expected one of {KIDNEY_SIDES}, got {side!r}")
        if self.side is None or self.side == side:
            return self
        # Made once and kept (with its nearest-point lookup, ~1 s to build): every scan and
        # every kinematic fit of a left kidney asks again.
        if self._mirrored is None:
            flip = np.array([1.0, 1.0, -1.0])
            self._mirrored = RegistrationTemplate(
                self.points * flip,
                self.normals * flip,
                None if self.modes is None else self.modes * flip,
                self.variances,
                side=side,
            )
            self._mirrored._mirrored = self
        return self._mirrored


def load_registration_template(path: str | None = None) -> RegistrationTemplate:
    """Loads the kidney template (``models/kidney_template.npz`` by default); ``generated``,
    ``real`` and ``real:DIR`` name the shipped template and templates of real CT kidneys
    (built on first use into the cache, :func:`drake_rus.template.ct.resolve_template`)."""
    resolved = None
    if is_template_spec(path):
        resolved = str(resolve_template(path))
    elif path is not None:
        resolved = path if str(path).startswith("/") else str(REPO_ROOT / path)
    template = load_template(resolved)
    modes = getattr(template, "modes", None)
    variances = getattr(template, "variances", None)
    if modes is not None and len(modes) == 0:
        modes, variances = None, None
    # The side its subjects were: "both" (real kidneys, the left ones mirrored onto right
    # ones, template.ct) is a right template; a file that does not say stays None.
    side = {"right": "right", "left": "left", "both": "right"}.get(template.meta.get("side"))
    return RegistrationTemplate(template.points, template.normals, modes, variances, side=side)


def body_directions_B(X_BPt: RigidTransform, side: str, posture: str):
    """(superior_B, lateral_B): the body's head direction and the kidney's medial->lateral
    direction in the robot base, from the patient's placement and posture (known at the
    bedside, so usable on hardware)."""
    x_ref, y_ref = reference_axes_Pt(side, posture)
    R_BPt = X_BPt.rotation().matrix()
    return R_BPt @ x_ref, R_BPt @ y_ref


def thin_cloud(points: np.ndarray, max_points: int, seed: int = 0) -> np.ndarray:
    """At most ``max_points`` of ``points``, a deterministic uniform random subset."""
    points = np.asarray(points, dtype=float)
    if len(points) <= max_points:
        return points
    rng = np.random.default_rng(seed)
    return points[np.sort(rng.choice(len(points), max_points, replace=False))]


def localize(
    P_local_B: np.ndarray,
    template: RegistrationTemplate,
    config: LocalizationConfig,
    superior_B,
    lateral_B,
    warm_start: IcpResult | None = None,
) -> IcpResult:
    """T_k^b from the partial cloud with ``config.method`` ("seed" or "deformable").

    ``warm_start``: an earlier registration (of part of the same cloud, with the same
    method and modes) to start from: its pose and, when the mode counts agree, its shape
    weights, instead of the heuristic rotation and the cloud's centroid."""
    P = thin_cloud(P_local_B, config.max_points)
    R0 = heuristic_initial_rotation(superior_B, lateral_B)
    kwargs = dict(
        init_translation=config.init_translation,
        theta_max=np.deg2rad(config.theta_max_deg),
        error_change_tol=config.error_change_tol,
        max_iterations=config.max_iterations,
        max_correspondence_distance=config.max_correspondence_distance or np.inf,
        max_translation_step=config.max_translation_step,
        step_tolerance=config.step_tolerance,
        cycle_max_period=config.cycle_max_period,
        initial_X_BK=None if warm_start is None else warm_start.X_BK,
    )
    if config.method == "deformable" and template.modes is not None and config.shape_modes > 0:
        k = min(config.shape_modes, template.modes.shape[0])
        modes, variances = template.modes[:k], template.variances[:k]
        axes, size_variances = size_prior(template, config)
        if len(axes):
            modes = np.concatenate([modes, size_modes_K(template.points)[axes]])
            variances = np.concatenate([variances, size_variances])
        b0 = None
        if warm_start is not None and warm_start.shape_coefficients is not None:
            # The warm start's size changes when it fitted the same axes, else none.
            s0 = warm_start.size_coefficients
            if s0 is None or tuple(warm_start.size_axes) != tuple(int(a) for a in axes):
                s0 = np.zeros(len(axes))
            b0 = np.concatenate([warm_start.shape_coefficients, s0])
        result = register_plane_to_plane(
            P,
            template.points,
            template.normals,
            R0,
            shape_modes_K=modes,
            shape_variances=variances,
            shape_regularization=config.shape_residual_variance,
            initial_shape=b0 if b0 is not None and len(b0) == len(variances) else None,
            **kwargs,
        )
        if len(axes):
            b = result.shape_coefficients
            result = dataclasses.replace(
                result,
                shape_coefficients=b[:k],
                size_coefficients=b[k:],
                size_axes=tuple(int(a) for a in axes),
            )
        return result
    return register_plane_to_plane(
        P, template.points, template.normals, R0, template_tree=template.tree, **kwargs
    )


def size_prior(
    template: RegistrationTemplate, config: LocalizationConfig
) -> tuple[np.ndarray, np.ndarray]:
    """(axes, prior variances) of the size modes the deformable fit adds for ``template``
    (:func:`drake_rus.localization.size_modes.size_mode_prior` with the scenario's relative
    SDs, less what the template's first ``config.shape_modes`` modes explain); none
    with ``config.size_modes`` off, without shape modes or with the three SDs 0."""
    sd = (config.size_sd_length, config.size_sd_width, config.size_sd_thickness)
    if not config.size_modes or template.modes is None or not any(v > 0 for v in sd):
        return np.zeros(0, dtype=int), np.zeros(0)
    k = min(config.shape_modes, template.modes.shape[0])
    return size_mode_prior(template.points, template.modes[:k], template.variances[:k], sd)


def fitted_shape_K(template: RegistrationTemplate, result) -> np.ndarray:
    """(N, 3) the template's points in K (m) as the registration ``result`` fitted them:
    the mean shape, plus its shape modes' weights (``shape_coefficients``), plus its size
    modes' relative size changes (``size_coefficients``); a rigid result: the mean shape."""
    shape = np.asarray(template.points, dtype=float)
    b = getattr(result, "shape_coefficients", None)
    if b is not None and template.modes is not None and len(b):
        shape = shape + np.einsum("k,kij->ij", b, template.modes[: len(b)])
    s = getattr(result, "size_coefficients", None)
    if s is not None and len(s):
        shape = shape + scaled_shape(template.points, result.size_axes, s) - template.points
    return shape


def kidney_length_of(template: RegistrationTemplate, result: IcpResult) -> float:
    """Extent (m) along the kidney's long axis (K's x) of the registered template, deformed
    by the result's shape (and size) coefficients if it has them."""
    return float(np.ptp(fitted_shape_K(template, result)[:, 0]))


def estimate_kidney_length(
    P_local_B: np.ndarray,
    template: RegistrationTemplate,
    config: LocalizationConfig,
    superior_B,
    lateral_B,
    warm_start: IcpResult | None = None,
) -> tuple[float, IcpResult | None]:
    """(length (m), the fit) of the kidney along its long axis from a partial cloud: the
    template's first ``config.length_shape_modes`` shape modes fitted with the pose under
    the weak prior ``config.length_shape_residual_variance``, the length being the fitted
    shape's extent along K's x. NaN (and None) without shape modes in the template (the
    rigid template's length is the template's, not the kidney's); NaN (with the fit) when
    the fit fails the sanity checks (:func:`check_registration`, with the geometry check
    when ``config.geometry_check`` is on, as the registration's own). The seen part of a
    kidney constrains its length only through the shape model (the far pole is not seen);
    see ``LocalizationConfig`` for how well it works. ``warm_start``: the previous length
    fit of the growing cloud to start from (``localize``;
    ``LocalizationConfig.length_warm_start``)."""
    if template.modes is None or config.length_shape_modes < 1:
        return math.nan, None
    k = min(config.length_shape_modes, template.modes.shape[0])
    cfg = dataclasses.replace(
        config,
        method="deformable",
        shape_modes=k,
        shape_residual_variance=config.length_shape_residual_variance,
        size_modes=False,
    )
    P = np.asarray(P_local_B, dtype=float).reshape(-1, 3)
    result = localize(P, template, cfg, superior_B, lateral_B, warm_start)
    if check_registration(result, P, cfg, template, superior_B):
        return math.nan, result
    return kidney_length_of(template, result), result


def updated_length_estimate(
    previous: float,
    length: float,
    failed_fit: str,
    previous_reading: float = math.nan,
    confirm_tolerance: float = 0.0,
    reference: float = math.nan,
) -> float:
    """The exploration's kidney-length estimate (m) after a length check that read
    ``length`` (NaN: the fit failed its checks).

    After a failed fit: the ``previous`` estimate (``failed_fit`` "keep") or +inf
    ("unknown": the template cannot fit the kidney explored so far, so its length is not
    known; ``supervisor.exploration_target`` then explores for the longest kidney it
    allows).

    After a fit that passed: ``length`` when it is confirmed, i.e. within
    ``confirm_tolerance`` (m) of the check before it (``previous_reading``, NaN if that
    fit failed or there was none), or the confirmation is off (``confirm_tolerance`` <= 0).
    An unconfirmed reading may lengthen the exploration, never shorten it: the estimate is
    then the larger of ``length`` and the ``previous`` estimate (``reference``, the
    reference length L_m, before any). The far pole is not in the cloud: the reading is
    the shape model's extrapolation, and a reading that the next 5 mm of kidney
    contradict was not the cloud's."""
    if not math.isfinite(length):
        if failed_fit == "keep":
            return float(previous)
        if failed_fit == "unknown":
            return math.inf
        raise ValueError(f"length_failed_fit: expected 'unknown' or 'keep', got {failed_fit!r}")
    if not confirm_tolerance > 0.0 or abs(length - previous_reading) <= confirm_tolerance:
        return float(length)
    floor = reference if math.isnan(previous) else previous
    return float(length) if math.isnan(floor) else max(float(length), float(floor))


def kidney_extent_along(points: np.ndarray, direction) -> float:
    """Extent (m) of ``points`` along ``direction`` (e.g. the body's superior direction):
    how far along the body the kidney was actually seen."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(points) == 0:
        return 0.0
    d = np.asarray(direction, dtype=float)
    return float(np.ptp(points @ (d / np.linalg.norm(d))))


def exploration_travel(poses) -> float:
    """Largest tip distance (m) between any explored frame and the first one."""
    if len(poses) < 2:
        return 0.0
    p = np.array([X.translation() for X in poses])
    return float(np.max(np.linalg.norm(p - p[0], axis=1)))


@functools.lru_cache(maxsize=1)
def _shipped_template() -> RegistrationTemplate:
    return load_registration_template(str(DEFAULT_TEMPLATE_PATH))


def max_rms_residual(
    config: LocalizationConfig, template: RegistrationTemplate | None, deformable: bool
) -> float:
    """The registration's RMS-residual gate (m) for ``template``: the config's gate
    (``max_rms_residual_deformable`` for a fit with shape modes, else ``max_rms_residual``),
    measured on the shipped template, widened by the shape variability that ``template``'s
    own subjects show beyond the modes fitted and the shipped template's do not:
    sqrt(gate^2 + z^2 max(0, s_T^2 - s_shipped^2)), s the unexplained per-point SD
    (:meth:`RegistrationTemplate.unexplained_sd`), z = ``rms_shape_allowance_sd``. A kidney
    of ``template``'s population at z SD of its unexplained shape leaves that much more
    residual; the shipped template keeps the measured gate exactly."""
    gate = config.max_rms_residual_deformable if deformable else config.max_rms_residual
    z = config.rms_shape_allowance_sd
    if z <= 0 or not isinstance(template, RegistrationTemplate) or template.variances is None:
        return gate
    k = min(config.shape_modes, len(template.variances)) if deformable else 0
    excess = template.unexplained_sd(k) ** 2 - _shipped_template().unexplained_sd(k) ** 2
    return float(np.sqrt(gate**2 + z**2 * max(0.0, excess)))


def cloud_axis_offset(
    P_local_B: np.ndarray, p_B: np.ndarray, superior_B, slab: float = 0.004
) -> float:
    """Distance (m) of the point ``p_B`` from the explored cloud's axis, across the sweep:
    the line fitted (least squares) through the centroids of the cloud's ``slab``-thick
    slices along ``superior_B``, taken at ``p_B``'s height along it (the cloud's centroid
    when it spans fewer than two slices)."""
    P = np.asarray(P_local_B, dtype=float).reshape(-1, 3)
    u = np.asarray(superior_B, dtype=float)
    u = u / np.linalg.norm(u)
    h = P @ u
    across = P - np.outer(h, u)
    index = np.floor((h - h.min()) / slab).astype(int)
    slabs = np.unique(index)
    p = np.asarray(p_B, dtype=float)
    p_across = p - (p @ u) * u
    if len(slabs) < 2:
        return float(np.linalg.norm(p_across - across.mean(axis=0)))
    heights = np.array([h[index == i].mean() for i in slabs])
    centroids = np.array([across[index == i].mean(axis=0) for i in slabs])
    A = np.column_stack([np.ones_like(heights), heights])
    coefficients, *_ = np.linalg.lstsq(A, centroids, rcond=None)
    on_axis = coefficients[0] + coefficients[1] * float(p @ u)
    return float(np.linalg.norm(p_across - on_axis))


def cloud_spread(P_local_B: np.ndarray) -> float:
    """Spread (m, SD) of the points across their principal axis: the square root of the
    second-largest eigenvalue of their covariance; 0 for fewer than three points."""
    P = np.asarray(P_local_B, dtype=float).reshape(-1, 3)
    if len(P) < 3:
        return 0.0
    s = np.linalg.svd(P - P.mean(axis=0), compute_uv=False)
    return float(s[1] / np.sqrt(len(P) - 1))


def _shown(value: float, limit: float, decimals: int, above: bool) -> tuple[str, str]:
    """(value, limit) as a refusal states them: rounded to ``decimals``, with more decimals
    (up to 4 more) while the rounding hides why the value fails (``above``: the value
    exceeds the limit; else it falls short of it), e.g. an RMS of 5.02 mm against 5.0 mm
    reads "5.02 mm > 5.00 mm", not "5.0 mm > 5.0 mm"."""
    for d in range(decimals, decimals + 5):
        a, b = f"{value:.{d}f}", f"{limit:.{d}f}"
        if (float(a) > float(b)) if above else (float(a) < float(b)):
            break
    return a, b


def check_geometry(
    result: IcpResult, P_local_B: np.ndarray, config: LocalizationConfig, superior_B
) -> str:
    """Why the fit's geometry is not a kidney's ('' when it is), without the residual:
    the fitted long axis (K's x) more than ``config.max_axis_tilt_deg`` from the body's
    craniocaudal axis ``superior_B`` (the transverse sweep's direction), or the fitted
    centre more than ``config.max_centre_off_cloud_axis`` (m) from the explored cloud's
    axis (:func:`cloud_axis_offset`)."""
    u = np.asarray(superior_B, dtype=float)
    u = u / np.linalg.norm(u)
    x_k = result.X_BK.rotation().matrix()[:, 0]
    tilt = math.degrees(math.acos(min(1.0, abs(float(x_k @ u)))))
    if tilt > config.max_axis_tilt_deg:
        a, b = _shown(tilt, config.max_axis_tilt_deg, 0, above=True)
        return (
            f"registration rejected: the fitted kidney's long axis lies {a} deg from "
            f"the body's axis along which the sweep ran (limit {b} deg)"
        )
    offset = cloud_axis_offset(P_local_B, result.X_BK.translation(), u)
    if offset > config.max_centre_off_cloud_axis:
        a, b = _shown(1000 * offset, 1000 * config.max_centre_off_cloud_axis, 0, above=True)
        return (
            f"registration rejected: the fitted kidney centre is {a} mm from "
            f"the explored sections' axis (limit {b} mm)"
        )
    return ""


def check_registration(
    result: IcpResult,
    P_local_B: np.ndarray,
    config: LocalizationConfig,
    template: RegistrationTemplate | None = None,
    superior_B=None,
) -> str:
    """Why the estimate must not be used ('' when it passes the sanity checks): a
    non-finite pose, explored points along a line (:func:`cloud_spread` below
    ``config.min_cloud_spread``), too few inliers, the RMS residual, the centre's offset
    from the points. The RMS gate is :func:`max_rms_residual` for ``template`` (the
    config's own without it); with ``config.geometry_check`` and the body's
    ``superior_B`` given, also :func:`check_geometry`."""
    if not np.all(np.isfinite(result.X_BK.GetAsMatrix4())):
        return "registration produced a non-finite pose"
    spread = cloud_spread(P_local_B)
    if spread < config.min_cloud_spread:
        a, b = _shown(1000 * spread, 1000 * config.min_cloud_spread, 1, above=False)
        return (
            f"registration rejected: the explored points lie along a line ({a} mm across "
            f"it, need {b} mm), which leaves the kidney's pose undetermined"
        )
    if result.inlier_fraction < config.min_inlier_fraction:
        a, b = _shown(100 * result.inlier_fraction, 100 * config.min_inlier_fraction, 0, False)
        return (
            f"registration rejected: only {a}% of the "
            f"explored points lie within 3 mm of the registered template "
            f"(need {b}%)"
        )
    # The deformable fit absorbs part of the kidney's shape difference: its own bound.
    max_rms = max_rms_residual(config, template, result.shape_coefficients is not None)
    if result.rms_residual > max_rms:
        a, b = _shown(1000 * result.rms_residual, 1000 * max_rms, 1, above=True)
        return f"registration rejected: RMS residual {a} mm > {b} mm"
    offset = np.linalg.norm(result.X_BK.translation() - np.mean(P_local_B, axis=0))
    if offset > config.max_centroid_offset:
        a, b = _shown(1000 * offset, 1000 * config.max_centroid_offset, 0, above=True)
        return (
            f"registration rejected: the estimated kidney centre is {a} mm "
            f"from the explored points (limit {b} mm)"
        )
    if config.geometry_check and superior_B is not None:
        return check_geometry(result, P_local_B, config, superior_B)
    return ""


def register_cloud(
    P_local_B: np.ndarray,
    template: RegistrationTemplate,
    config: LocalizationConfig,
    superior_B,
    lateral_B,
) -> tuple[IcpResult, str]:
    """(the registration of ``P_local_B``, why it must not be used or ""): :func:`localize`
    and :func:`check_registration`, the LOCALIZE registration and the adaptive checks as one
    call (an executor job)."""
    result = localize(P_local_B, template, config, superior_B, lateral_B)
    return result, check_registration(result, P_local_B, config, template, superior_B)


def prepared_template(template: RegistrationTemplate) -> RegistrationTemplate:
    """``template`` with its nearest-point lookup built and the fit's code warmed up (a
    worker installs its copy with this before the scan starts)."""
    template.tree  # noqa: B018  (builds the grid)
    config = LocalizationConfig(method="seed", max_iterations=2)
    localize(template.points[::10], template, config, np.array([1.0, 0, 0]), np.array([0, 1.0, 0]))
    return template


def portable_template(template: RegistrationTemplate) -> RegistrationTemplate:
    """A copy of ``template`` without its nearest-point grid (megabytes; a worker builds its
    own), to hand to a worker process."""
    return RegistrationTemplate(
        template.points, template.normals, template.modes, template.variances
    )


@dataclasses.dataclass
class LocalizationOutcome:
    """What the localizer produced: the estimate, diagnostics and its compute time."""

    result: IcpResult | None = None
    n_points: int = 0
    compute_s: float = 0.0
    time: float = -1.0  # simulation time (s) the estimate was made
    error: str = ""  # why no estimate (too few points, rejected registration, ...)
    rejected: IcpResult | None = None  # a registration that failed the sanity checks
    round: int = 0  # the supervisor's localization round it belongs to (re-localization)
    # Simulation time (s) the result was taken (it was asked for at ``time``; -1: none).
    ready_time: float = -1.0

    # Drake clones abstract state with deepcopy on every update of the localizer (20 Hz);
    # an outcome is made once and never changed in place, so clones may share it.
    def __deepcopy__(self, memo):
        return self


@dataclasses.dataclass(frozen=True)
class LengthState:
    """Kidney length estimates during exploration (beyond the seed)."""

    last_time: float = -math.inf
    # Latest estimate (m); NaN until a check is made, +inf after a fit that failed its
    # checks (``LocalizationConfig.length_failed_fit``: "unknown"); a reading the check
    # before does not confirm cannot lower it (``updated_length_estimate``).
    length: float = math.nan
    checks: tuple = ()  # ((time s, travel m, length m read or NaN), ...)
    # The latest fit that passed the checks: the next fit's warm start.
    fit: IcpResult | None = dataclasses.field(default=None, compare=False)
    # The fit running (an executor Ticket) and the probe's travel (m) when it was asked.
    pending: object = dataclasses.field(default=None, compare=False)
    pending_travel: float = math.nan

    def __deepcopy__(self, memo):  # immutable: clones may share it
        return self


@dataclasses.dataclass
class AdaptiveState:
    """Interim estimates of adaptive exploration (beyond the seed)."""

    last_time: float = -np.inf
    last_X_BK: RigidTransform | None = None
    sufficient: bool = False
    checks: tuple = ()  # (time s, travel m, change of translation m, of x-axis angle rad)
    # The fit running (an executor Ticket) and the probe's travel (m) when it was asked.
    pending: object = None
    pending_travel: float = math.nan

    # Drake clones abstract state with deepcopy on every update of the localizer; a stored
    # state is never changed in place (the update works on a dataclasses.replace copy).
    def __deepcopy__(self, memo):
        return self


def estimate_change(X_a: RigidTransform, X_b: RigidTransform) -> tuple[float, float]:
    """(translation change (m), kidney x-axis angle change (rad)) between two estimates."""
    dp = float(np.linalg.norm(X_a.translation() - X_b.translation()))
    xa, xb = X_a.rotation().matrix()[:, 0], X_b.rotation().matrix()[:, 0]
    return dp, float(np.arctan2(np.linalg.norm(np.cross(xa, xb)), float(xa @ xb)))


@dataclasses.dataclass(frozen=True)
class PendingRegistration:
    """The LOCALIZE registration running: its executor Ticket and the number of points."""

    ticket: object = None
    n_points: int = 0

    def __deepcopy__(self, memo):
        return self


class IcpLocalizer(LeafSystem):
    """Registers the explored cloud when the supervisor enters LOCALIZE.

    Inputs: ``point_cloud`` (abstract PointCloud: points (N, 3) in B, m), ``phase``
    (1-vector, the supervisor's phase; LOCALIZE triggers one registration),
    ``localization_round`` (1-vector, optional: when it changes, the estimate is dropped
    and the next LOCALIZE registers anew: a re-localization).
    Outputs: ``X_BK`` (abstract RigidTransform: estimated canonical kidney frame in B, the
    heuristic initial guess until an estimate exists), ``localization_ready`` (1-vector: 1
    once the estimate is final), ``localization_error`` (abstract str: why there is no
    estimate, "" otherwise), ``localization`` (abstract LocalizationOutcome),
    ``exploration_sufficient`` (1-vector, adaptive exploration), ``kidney_length_estimate``
    (1-vector, m: the kidney's length along its long axis estimated from the cloud explored
    so far, every ``adaptive_period`` s of EXPLORE once ``length_min_travel`` has been
    explored (``length_estimation``); NaN until the first check, +inf while the latest fit
    failed its checks: see ``updated_length_estimate``).

    The fits (registration, length, adaptive) run on ``executor``'s ``fits`` lane
    (``drake_rus.executor``; default: inline, ready at once): asked for at an update, taken
    at the first update (every 1 / ``rate_hz`` s) at which they are ready, never waited
    for. The supervisor holds the probe in LOCALIZE until ``localization_ready``.
    """

    def __init__(
        self,
        template: RegistrationTemplate,
        config: LocalizationConfig,
        superior_B,
        lateral_B,
        localize_phase: int,
        rate_hz: float = 20.0,
        min_points: int = 50,
        explore_phase: int | None = None,
        kidney_length: float = 0.10,
        executor=None,
    ):
        super().__init__()
        self._template = template
        self._config = config
        self._superior_B = np.asarray(superior_B, dtype=float)
        self._lateral_B = np.asarray(lateral_B, dtype=float)
        self._phase = localize_phase
        self._explore_phase = explore_phase
        self._kidney_length = kidney_length
        self._min_points = min_points
        self._executor = executor if executor is not None else InlineExecutor()
        # The template as the fits see it: this object inline, a worker's own copy there.
        self._fit_template = (
            template
            if self._executor.mode == "inline"
            else self._executor.share("fits", prepared_template, portable_template(template))
        )
        self._cloud = self.DeclareAbstractInputPort("point_cloud", AbstractValue.Make(PointCloud()))
        self._phase_port = self.DeclareVectorInputPort("phase", 1)
        self._round = self.DeclareVectorInputPort("localization_round", 1)
        initial = RigidTransform(
            heuristic_initial_rotation(self._superior_B, self._lateral_B), np.zeros(3)
        )
        self._X = self.DeclareAbstractState(AbstractValue.Make(initial))
        self._outcome = self.DeclareAbstractState(AbstractValue.Make(LocalizationOutcome()))
        # Adaptive exploration: (time of the last interim estimate, its X_BK or None,
        # sufficient flag, list of (travel m, dtranslation m, dangle rad) per check).
        self._adaptive = self.DeclareAbstractState(AbstractValue.Make(AdaptiveState()))
        self._length = self.DeclareAbstractState(AbstractValue.Make(LengthState()))
        self._registration = self.DeclareAbstractState(AbstractValue.Make(PendingRegistration()))
        self.DeclarePeriodicUnrestrictedUpdateEvent(1.0 / rate_hz, 0.0, self._update)
        self.DeclareAbstractOutputPort(
            "X_BK",
            lambda: AbstractValue.Make(RigidTransform()),
            lambda c, o: o.set_value(c.get_abstract_state(self._X).get_value()),
            prerequisites_of_calc={self.abstract_state_ticket(self._X)},
        )
        self.DeclareVectorOutputPort(
            "localization_ready",
            1,
            lambda c, o: o.SetAtIndex(
                0, float(c.get_abstract_state(self._outcome).get_value().result is not None)
            ),
            prerequisites_of_calc={self.abstract_state_ticket(self._outcome)},
        )
        self.DeclareVectorOutputPort(
            "exploration_sufficient",
            1,
            lambda c, o: o.SetAtIndex(
                0, float(c.get_abstract_state(self._adaptive).get_value().sufficient)
            ),
            prerequisites_of_calc={self.abstract_state_ticket(self._adaptive)},
        )
        self.DeclareVectorOutputPort(
            "kidney_length_estimate",
            1,
            lambda c, o: o.SetAtIndex(0, c.get_abstract_state(self._length).get_value().length),
            prerequisites_of_calc={self.abstract_state_ticket(self._length)},
        )
        self.DeclareAbstractOutputPort(
            "localization_error",
            lambda: AbstractValue.Make(""),
            lambda c, o: o.set_value(c.get_abstract_state(self._outcome).get_value().error),
            prerequisites_of_calc={self.abstract_state_ticket(self._outcome)},
        )
        self.DeclareAbstractOutputPort(
            "localization",
            lambda: AbstractValue.Make(LocalizationOutcome()),
            lambda c, o: o.set_value(c.get_abstract_state(self._outcome).get_value()),
            prerequisites_of_calc={self.abstract_state_ticket(self._outcome)},
        )

    def _submit(self, fn, *args, t: float, kind: str):
        return self._executor.submit("fits", fn, *args, t=t, kind=kind)

    def _update(self, context, state):
        outcome = context.get_abstract_state(self._outcome).get_value()
        rnd = int(round(self._round.Eval(context)[0])) if self._round.HasValue(context) else 0
        if rnd != outcome.round:  # re-localization: forget the estimate, register anew
            state.get_mutable_abstract_state(self._outcome).set_value(
                LocalizationOutcome(round=rnd)
            )
            state.get_mutable_abstract_state(self._adaptive).set_value(AdaptiveState())
            # A fit still running for the old round is dropped (its result is never taken).
            state.get_mutable_abstract_state(self._registration).set_value(PendingRegistration())
            return EventStatus.Succeeded()
        if outcome.result is not None or outcome.error:
            return EventStatus.DidNothing()
        t = context.get_time()
        # Results that are ready are taken whatever the phase (the length checks are kept
        # for the record; the supervisor reads them in EXPLORE only).
        did = self._take_length(state, t)
        did |= self._take_adaptive(state, t)
        if state.get_abstract_state(self._registration).get_value().ticket is not None:
            did |= self._take_registration(state, t)
            return EventStatus.Succeeded() if did else EventStatus.DidNothing()
        phase = int(round(self._phase_port.Eval(context)[0]))
        if self._explore_phase is not None and phase == self._explore_phase:
            if self._config.length_estimation:
                did |= self._length_check(context, state)
            if self._config.adaptive_exploration:
                did |= self._adaptive_check(context, state)
            return EventStatus.Succeeded() if did else EventStatus.DidNothing()
        if phase != self._phase:
            return EventStatus.Succeeded() if did else EventStatus.DidNothing()
        cloud = self._cloud.Eval(context)
        points = cloud.points
        # The probe's travel, and how far along the body the kidney was actually seen (a
        # frame without kidney still counts for the travel).
        travel = min(exploration_travel(cloud.poses), kidney_extent_along(points, self._superior_B))
        error = ""
        if len(points) < self._min_points:
            error = (
                f"only {len(points)} kidney boundary points were explored (need {self._min_points})"
            )
        elif travel < self._config.min_exploration_travel:
            a, b = _shown(1000 * travel, 1000 * self._config.min_exploration_travel, 1, False)
            error = f"the kidney was seen over only {a} mm of exploration (need {b} mm)"
        if error:
            state.get_mutable_abstract_state(self._outcome).set_value(
                LocalizationOutcome(
                    n_points=len(points), time=t, error=error, ready_time=t, round=rnd
                )
            )
            return EventStatus.Succeeded()
        ticket = self._submit(
            register_cloud,
            points,
            self._fit_template,
            self._config,
            self._superior_B,
            self._lateral_B,
            t=t,
            kind="registration",
        )
        state.get_mutable_abstract_state(self._registration).set_value(
            PendingRegistration(ticket, len(points))
        )
        self._take_registration(state, t)  # ready at once (inline, no latency)
        return EventStatus.Succeeded()

    def _take_registration(self, state, t: float) -> bool:
        pending = state.get_abstract_state(self._registration).get_value()
        done = self._executor.poll(pending.ticket, t)
        if done is None:
            return False
        result, error = done.value
        common = dict(
            round=state.get_abstract_state(self._outcome).get_value().round,
            n_points=pending.n_points,
            compute_s=done.compute_s,
            time=done.t_request,
            ready_time=done.t_applied,
        )
        state.get_mutable_abstract_state(self._registration).set_value(PendingRegistration())
        if error:
            state.get_mutable_abstract_state(self._outcome).set_value(
                LocalizationOutcome(error=error, rejected=result, **common)
            )
            return True
        state.get_mutable_abstract_state(self._X).set_value(result.X_BK)
        state.get_mutable_abstract_state(self._outcome).set_value(
            LocalizationOutcome(result=result, **common)
        )
        return True

    def length_checks(self, context) -> tuple:
        """The kidney-length estimates made during EXPLORE so far: ((time s, probe travel m,
        estimated length m, NaN where the fit failed its checks), ...); the time is when
        the estimate was asked for (the cloud it saw)."""
        return context.get_abstract_state(self._length).get_value().checks

    def _length_check(self, context, state) -> bool:
        """During EXPLORE: every ``adaptive_period`` s (once ``length_min_travel`` has been
        explored) ask for the kidney's length from the cloud so far, starting from the
        previous estimate's fit (``length_warm_start``), unless a fit is still running.
        True if a check was asked for."""
        cfg = self._config
        s = state.get_abstract_state(self._length).get_value()
        t = context.get_time()
        if s.pending is not None or t - s.last_time < cfg.adaptive_period - 1e-9:
            return False
        cloud = self._cloud.Eval(context)
        travel = exploration_travel(cloud.poses)
        if travel < cfg.length_min_travel or len(cloud.points) < self._min_points:
            return False
        ticket = self._submit(
            estimate_kidney_length,
            cloud.points,
            self._fit_template,
            cfg,
            self._superior_B,
            self._lateral_B,
            s.fit if cfg.length_warm_start else None,
            t=t,
            kind="length_fit",
        )
        state.get_mutable_abstract_state(self._length).set_value(
            dataclasses.replace(s, last_time=t, pending=ticket, pending_travel=travel)
        )
        self._take_length(state, t)  # ready at once (inline, no latency)
        return True

    def _take_length(self, state, t: float) -> bool:
        """Takes the running length fit if it is ready (the estimate it gives:
        ``updated_length_estimate``). True if one was taken."""
        s = state.get_abstract_state(self._length).get_value()
        if s.pending is None:
            return False
        done = self._executor.poll(s.pending, t)
        if done is None:
            return False
        length, fit = done.value
        passed = math.isfinite(length)
        new = LengthState(
            last_time=s.last_time,
            length=updated_length_estimate(
                s.length,
                length,
                self._config.length_failed_fit,
                previous_reading=s.checks[-1][2] if s.checks else math.nan,
                confirm_tolerance=self._config.length_confirm_tolerance,
                reference=self._kidney_length,
            ),
            checks=s.checks + ((done.t_request, s.pending_travel, length),),
            fit=fit if passed else s.fit,
        )
        state.get_mutable_abstract_state(self._length).set_value(new)
        return True

    def _adaptive_check(self, context, state) -> bool:
        """During EXPLORE: every ``adaptive_period`` s ask for a registration of the cloud so
        far (unless one is running); once two successive estimates agree within the
        tolerances, the exploration is sufficient. True if a check was asked for."""
        cfg = self._config
        a = state.get_abstract_state(self._adaptive).get_value()
        t = context.get_time()
        if a.sufficient or a.pending is not None or t - a.last_time < cfg.adaptive_period - 1e-9:
            return False
        cloud = self._cloud.Eval(context)
        travel = exploration_travel(cloud.poses)
        if (
            travel < cfg.adaptive_min_ratio * self._kidney_length
            or len(cloud.points) < self._min_points
        ):
            return False
        ticket = self._submit(
            register_cloud,
            cloud.points,
            self._fit_template,
            cfg,
            self._superior_B,
            self._lateral_B,
            t=t,
            kind="adaptive_fit",
        )
        state.get_mutable_abstract_state(self._adaptive).set_value(
            dataclasses.replace(a, last_time=t, pending=ticket, pending_travel=travel)
        )
        self._take_adaptive(state, t)  # ready at once (inline, no latency)
        return True

    def _take_adaptive(self, state, t: float) -> bool:
        a = state.get_abstract_state(self._adaptive).get_value()
        if a.pending is None:
            return False
        done = self._executor.poll(a.pending, t)
        if done is None:
            return False
        result, error = done.value
        new = dataclasses.replace(a, pending=None, pending_travel=math.nan)
        if error:
            new.last_X_BK = None
        else:
            if a.last_X_BK is not None:
                dp, dangle = estimate_change(a.last_X_BK, result.X_BK)
                new.checks = a.checks + ((done.t_request, a.pending_travel, dp, dangle),)
                cfg = self._config
                new.sufficient = dp < cfg.adaptive_translation_tol and dangle < np.deg2rad(
                    cfg.adaptive_rotation_tol_deg
                )
            new.last_X_BK = result.X_BK
        state.get_mutable_abstract_state(self._adaptive).set_value(new)
        return True
