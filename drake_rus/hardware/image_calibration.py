"""Image-to-probe calibration: grabbed pixels <-> the probe frame P, per depth preset.

The ultrasound machine draws the B-mode sector into its video picture at a scale that
depends on the depth preset. A calibration file (YAML, :class:`ImageCalibration`, loaded with
Drake's ``yaml_load_typed``) holds, for each preset:

- ``crop``: the sector's rectangle in the grabbed picture (pixels outside are never used);
- ``mm_per_pixel``: [x, y], the size of a grabbed pixel along the picture's columns and rows;
- ``origin_px``: [column, row] of the probe-face centre (the origin of P) in the picture;

and, for all presets, the image-to-probe transform ``X_PI``: the picture frame I (origin at
``origin_px``, x_I along the columns, y_I along the rows, i.e. down the picture, z_I = x_I x
y_I) in P. Nominally x_I = x_P (the array), y_I = z_P (the beam): rotation rpy
[90, 0, 0] deg. ``mirror_x`` is true when the display shows the array reversed (the
probe's orientation mark on the right).

:class:`ImageToProbeMap` resamples each grabbed picture onto the probe's image grid
(``drake_rus.imaging.probe.ProbeGeometry``), so segmentation and back-projection work in
metres. :func:`fit_image_calibration` fits the scale, origin and in-plane angle to images of
a point target at known positions in P (the water-bath or wire-phantom procedure in
docs/hardware_bringup.md), ``drake-rus hardware calibrate-image`` runs it on a target file
(:class:`TargetSet`).
"""

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydrake.common.schema import Transform
from pydrake.common.yaml import yaml_dump_typed, yaml_load_file, yaml_load_typed
from pydrake.math import RigidTransform, RotationMatrix

from drake_rus.config_schema import ScenarioError, schema_transform, validate, yaml_error_text
from drake_rus.extras import require
from drake_rus.hardware.core import check_crop, to_grey
from drake_rus.io_utils import write_text_atomic
from drake_rus.robot import MakeControlPlant

__all__ = [
    "DepthPresetCalibration",
    "ImageCalibration",
    "TargetImage",
    "TargetSet",
    "load_image_calibration",
    "save_image_calibration",
    "preset_for_depth",
    "ImageToProbeMap",
    "find_point_target",
    "ImageFit",
    "fit_image_calibration",
    "targets_in_probe_frame",
    "load_target_set",
    "TargetFitReport",
    "fit_target_set",
    "with_preset",
]

CALIBRATION_FIELD = "hardware_interface.image_calibration"


@dataclass
class DepthPresetCalibration:
    # The depth preset (m) this entry is for: one of imaging.depth_presets.
    depth: float = field(default=0.15, metadata={"positive": True, "max": 0.4})
    # The sector's rectangle in the grabbed picture: [x, y, width, height] (pixels); all
    # zeros: the whole picture.
    crop: list[int] = field(default_factory=lambda: [0, 0, 0, 0], metadata={"length": 4, "min": 0})
    # Size of one grabbed pixel (mm) along the picture's columns (x) and rows (y).
    mm_per_pixel: list[float] = field(
        default_factory=lambda: [0.3, 0.3], metadata={"length": 2, "positive": True}
    )
    # The probe-face centre (origin of P) in the picture: [column, row] (pixels, continuous,
    # pixel centres at integers).
    origin_px: list[float] = field(default_factory=lambda: [0.0, 0.0], metadata={"length": 2})
    # Written by calibrate-image (informative): targets used, RMS and largest residual (mm).
    targets: int = field(default=0, metadata={"min": 0})
    rms_mm: float = field(default=0.0, metadata={"min": 0.0})
    max_residual_mm: float = field(default=0.0, metadata={"min": 0.0})


@dataclass
class ImageCalibration:
    # The picture frame I in the probe frame P (see the module doc). Nominal: rpy
    # [90, 0, 0] deg (x_I = x_P, y_I = z_P), no translation.
    X_PI: Transform = field(default_factory=lambda: schema_transform(rpy_deg=(90.0, 0.0, 0.0)))
    # The display shows the array reversed: x_I = -x_P.
    mirror_x: bool = False
    # One entry per depth preset.
    presets: list[DepthPresetCalibration] = field(default_factory=list)


def load_image_calibration(path, field_name: str = CALIBRATION_FIELD) -> ImageCalibration:
    """Reads a calibration file; a missing file or a bad field is a ScenarioError naming
    ``field_name``, the file and the field."""
    path = Path(path)
    where = f"field '{field_name}': {path}"
    if not path.is_file():
        raise ScenarioError(f"{where}: image calibration file not found")
    try:
        raw = yaml_load_file(str(path))
    except Exception as e:
        raise ScenarioError(f"{where}: not valid YAML: {yaml_error_text(e)}") from None
    _check_mapping(where, raw, "presets: [{depth, mm_per_pixel, origin_px, ...}]")
    try:
        validate(ImageCalibration, raw or {})
        cal = yaml_load_typed(
            schema=ImageCalibration, filename=str(path), defaults=ImageCalibration()
        )
    except ScenarioError as e:
        raise ScenarioError(f"{where}: {e}") from None
    except Exception as e:
        raise ScenarioError(f"{where}: {e}") from None
    depths = [p.depth for p in cal.presets]
    if len(set(round(d, 6) for d in depths)) != len(depths):
        raise ScenarioError(f"{where}: two entries for the same depth in {depths}")
    return cal


def save_image_calibration(cal: ImageCalibration, path) -> None:
    """Writes ``cal`` as YAML (entries sorted by depth), atomically: a write that fails
    leaves the file as it was, never a cut-off file whose last entry would load with
    default values."""
    cal = dataclasses.replace(cal, presets=sorted(cal.presets, key=lambda p: p.depth))
    write_text_atomic(
        path,
        "# Image-to-probe calibration (drake_rus/hardware/image_calibration.py); written by\n"
        "# `drake-rus hardware calibrate-image`. Lengths: mm per pixel; pixels: [column, row].\n"
        + yaml_dump_typed(cal),
    )


def preset_for_depth(
    cal: ImageCalibration, depth: float, source: str = "", field_name: str = CALIBRATION_FIELD
) -> DepthPresetCalibration:
    """The entry for ``depth`` (m); a ScenarioError listing the entries if there is none."""
    for p in cal.presets:
        if abs(p.depth - depth) < 1e-6:
            return p
    have = ", ".join(f"{p.depth:g}" for p in cal.presets) or "none"
    raise ScenarioError(
        f"field '{field_name}': {source or 'the calibration'} has no entry for "
        f"imaging.depth {depth:g} m (entries for: {have} m); run "
        f"`drake-rus hardware calibrate-image` at this depth preset"
    )


def with_preset(
    cal: ImageCalibration,
    preset: DepthPresetCalibration,
    *,
    angle_deg: float | None = None,
    mirror_x: bool | None = None,
) -> ImageCalibration:
    """``cal`` with ``preset`` added (replacing an entry for the same depth) and, if given,
    the in-plane angle (deg, rotation of I about z_I from nominal) and mirror set."""
    presets = [p for p in cal.presets if abs(p.depth - preset.depth) >= 1e-6] + [preset]
    X_PI = cal.X_PI
    if angle_deg is not None:
        old = X_PI.GetDeterministicValue()
        R = RotationMatrix.MakeXRotation(math.pi / 2) @ RotationMatrix.MakeZRotation(
            math.radians(angle_deg)
        )
        X_PI = Transform(RigidTransform(R, old.translation()))
    return dataclasses.replace(
        cal,
        presets=sorted(presets, key=lambda p: p.depth),
        X_PI=X_PI,
        mirror_x=cal.mirror_x if mirror_x is None else bool(mirror_x),
    )


class ImageToProbeMap:
    """Grabbed picture -> grey uint8 image on a ProbeGeometry's pixel grid.

    For every pixel of the probe grid: its point in P -> the picture frame I (``X_PI``,
    ``mirror_x``) -> the picture's (column, row) through the preset's scale and origin; the
    picture (grey, cropped, first shrunk by area averaging when its pixels are much finer than
    the grid's) is sampled there bilinearly (OpenCV ``remap``). Grid pixels outside the crop
    are 0."""

    def __init__(
        self, cal: ImageCalibration, preset: DepthPresetCalibration, geometry, picture_shape=None
    ):
        self.geometry = geometry
        self.preset = preset
        self.mirror = -1.0 if cal.mirror_x else 1.0
        self.X_PI = cal.X_PI.GetDeterministicValue()
        self._sx, self._sy = (float(v) for v in preset.mm_per_pixel)
        self._c0, self._r0 = (float(v) for v in preset.origin_px)
        self._crop = list(preset.crop)
        self._maps = None
        self._picture_shape = None
        if picture_shape is not None:
            self._prepare(picture_shape)

    # --- geometry (pure) ----------------------------------------------------------------
    def P_to_picture(self, p_P) -> np.ndarray:
        """Points (N, 3) in P (m) -> picture (column, row) (N, 2); y_I is dropped."""
        p = np.asarray(p_P, float).reshape(-1, 3)
        R = self.X_PI.rotation().matrix()
        p_I = (p - self.X_PI.translation()) @ R  # rows: R^T (p - t)
        col = self._c0 + self.mirror * 1e3 * p_I[:, 0] / self._sx
        row = self._r0 + 1e3 * p_I[:, 1] / self._sy
        return np.stack([col, row], axis=1)

    def picture_to_P(self, pixels) -> np.ndarray:
        """Picture (column, row) (N, 2) -> points (N, 3) in P (m), on the image plane."""
        c = np.asarray(pixels, float).reshape(-1, 2)
        p_I = np.zeros((c.shape[0], 3))
        p_I[:, 0] = self.mirror * (c[:, 0] - self._c0) * self._sx * 1e-3
        p_I[:, 1] = (c[:, 1] - self._r0) * self._sy * 1e-3
        return p_I @ self.X_PI.rotation().matrix().T + self.X_PI.translation()

    # --- resampling ---------------------------------------------------------------------
    def _prepare(self, shape):
        cv2 = require("cv2", "the image calibration")
        x, y, w, h = check_crop(
            self._crop,
            shape,
            field_name=f"{CALIBRATION_FIELD} (depth {self.preset.depth:g} m).crop",
        )
        g = self.geometry
        # Shrink the crop when a grid pixel spans more than 1.5 picture pixels.
        fx = min(1.0, 1.5 * self._sx / (1e3 * g.dx))
        fy = min(1.0, 1.5 * self._sy / (1e3 * g.dz))
        small = (max(2, int(round(w * fx))), max(2, int(round(h * fy))))
        v, u = np.mgrid[0 : g.height_px, 0 : g.width_px]
        uv = np.stack([u.ravel(), v.ravel()], axis=1).astype(float)
        cols_rows = self.P_to_picture(g.pixel_to_P(uv))
        map_x = ((cols_rows[:, 0] - x + 0.5) * small[0] / w - 0.5).reshape(g.image_shape)
        map_y = ((cols_rows[:, 1] - y + 0.5) * small[1] / h - 0.5).reshape(g.image_shape)
        self._maps = (cv2, (x, y, w, h), small, map_x.astype(np.float32), map_y.astype(np.float32))
        self._picture_shape = tuple(shape[:2])

    def __call__(self, picture) -> np.ndarray:
        picture = np.asarray(picture)
        if self._maps is None or tuple(picture.shape[:2]) != self._picture_shape:
            self._prepare(picture.shape)
        cv2, (x, y, w, h), small, map_x, map_y = self._maps
        part = picture[y : y + h, x : x + w]
        if part.ndim == 3 and part.shape[2] in (3, 4):
            grey = cv2.cvtColor(
                np.ascontiguousarray(part),
                cv2.COLOR_BGR2GRAY if part.shape[2] == 3 else cv2.COLOR_BGRA2GRAY,
            )
        else:
            grey = to_grey(part)
        if small != (w, h):
            grey = cv2.resize(grey, small, interpolation=cv2.INTER_AREA)
        return cv2.remap(
            grey, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
        )


def find_point_target(
    picture, crop=(0, 0, 0, 0), radius: int = 12, min_contrast: float = 30.0, blur_px: float = 2.0
):
    """The image position (column, row) of a bright point target (a wire's or a bead's
    echo) in a grabbed picture, or None when there is none.

    Grey, inside ``crop``; smoothed (Gaussian, ``blur_px``) against speckle; the brightest
    spot, then the intensity-weighted centroid of the pixels within ``radius`` of it that
    are brighter than halfway between the background (median) and the peak. None when the
    peak stands less than ``min_contrast`` grey levels above the background."""
    cv2 = require("cv2", "the image calibration")
    a = np.asarray(picture)
    x, y, w, h = check_crop(crop, a.shape)
    grey = to_grey(a[y : y + h, x : x + w]).astype(np.float32)
    if blur_px > 0:
        grey = cv2.GaussianBlur(grey, (0, 0), blur_px)
    background = float(np.median(grey))
    r, c = np.unravel_index(int(np.argmax(grey)), grey.shape)
    peak = float(grey[r, c])
    if peak - background < min_contrast:
        return None
    r0, r1 = max(0, r - radius), min(grey.shape[0], r + radius + 1)
    c0, c1 = max(0, c - radius), min(grey.shape[1], c + radius + 1)
    window = grey[r0:r1, c0:c1]
    weight = np.clip(window - 0.5 * (background + peak), 0.0, None)
    total = float(weight.sum())
    if total <= 0:
        return None
    rows, cols = np.mgrid[r0:r1, c0:c1]
    return (float((weight * cols).sum() / total) + x, float((weight * rows).sum() / total) + y)


@dataclasses.dataclass(frozen=True)
class ImageFit:
    """A fitted calibration: mm per pixel [x, y], origin [column, row] (px), in-plane angle
    (deg, I rotated about z_I from nominal), mirror, skew (deg: how far the fitted picture
    axes are from perpendicular), residual distance per target (mm), their RMS and max."""

    mm_per_pixel: tuple
    origin_px: tuple
    angle_deg: float
    mirror_x: bool
    skew_deg: float
    residuals_mm: np.ndarray
    rms_mm: float
    max_residual_mm: float

    def preset(self, depth: float, crop) -> DepthPresetCalibration:
        return DepthPresetCalibration(
            depth=float(depth),
            crop=[int(c) for c in crop],
            mm_per_pixel=[float(v) for v in self.mm_per_pixel],
            origin_px=[float(v) for v in self.origin_px],
            targets=len(self.residuals_mm),
            rms_mm=float(self.rms_mm),
            max_residual_mm=float(self.max_residual_mm),
        )


def _model(params, pixels, mirror):
    sx, sy, theta, c0, r0 = params
    d = pixels - np.array([c0, r0])
    xi, yi = mirror * sx * d[:, 0], sy * d[:, 1]  # mm in I
    ct, st = math.cos(theta), math.sin(theta)
    return np.stack([ct * xi - st * yi, st * xi + ct * yi], axis=1)  # (x_P, z_P) mm


def fit_image_calibration(
    pixels, p_P, *, min_spread_px: float = 10.0, min_spread_mm: float = 2.0
) -> ImageFit:
    """Least-squares fit of the picture-to-probe map to point targets.

    Args:
        pixels: (N, 2) picture positions (column, row) of the target in N images.
        p_P: (N, 3) target positions in P (m) (y_P, the distance from the image plane, is
            ignored), or (N, 2) as (x_P, z_P).

    Model: (x_P, z_P) = R(angle) diag(m s_x, s_y) ((column, row) - origin), m = -1 when the
    display is mirrored. A linear (affine) fit gives the start and the mirror; the model's
    5 parameters are then refined (scipy least_squares). Raises ValueError for fewer than 3
    targets, non-finite values, or targets that do not span both directions (in the picture
    by ``min_spread_px``, in P by ``min_spread_mm``): a line of targets fixes no scale
    across it.
    """
    c = np.asarray(pixels, float)
    p = np.asarray(p_P, float)
    if c.ndim != 2 or c.shape[1] != 2:
        raise ValueError(f"fit_image_calibration: pixels must be (N, 2), got {c.shape}")
    if p.ndim != 2 or p.shape[1] not in (2, 3) or p.shape[0] != c.shape[0]:
        raise ValueError(
            f"fit_image_calibration: target positions must be ({c.shape[0]}, 3) "
            f"or ({c.shape[0]}, 2), got {p.shape}"
        )
    n = c.shape[0]
    if n < 3:
        raise ValueError(
            f"fit_image_calibration: needs at least 3 target images, got {n} "
            f"(6 or more, spread across the sector and in depth, recommended)"
        )
    xz = 1e3 * (p[:, [0, 2]] if p.shape[1] == 3 else p)  # mm
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(xz))):
        raise ValueError("fit_image_calibration: non-finite pixel or target position")
    for name, pts, least, unit in (
        ("picture", c, min_spread_px, "px"),
        ("probe frame", xz, min_spread_mm, "mm"),
    ):
        spread = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False) / math.sqrt(n)
        if spread[-1] < least:
            raise ValueError(
                f"fit_image_calibration: the targets lie on a line (or one spot) in the "
                f"{name} (spread {spread[0]:.1f} {unit} along it, {spread[-1]:.2f} {unit} "
                f"across < {least:g} {unit}): place the target at different depths AND "
                f"lateral positions"
            )
    # Affine start: xz = A c + b.
    M = np.column_stack([c, np.ones(n)])
    coef, *_ = np.linalg.lstsq(M, xz, rcond=None)
    A, b = coef[:2].T, coef[2]
    det = float(np.linalg.det(A))
    if abs(det) < 1e-12:
        raise ValueError("fit_image_calibration: degenerate fit (singular scale)")
    mirror = -1.0 if det < 0 else 1.0
    origin = -np.linalg.solve(A, b)
    B = A @ np.diag([mirror, 1.0])
    sx, sy = np.linalg.norm(B[:, 0]), np.linalg.norm(B[:, 1])
    theta_x = math.atan2(B[1, 0], B[0, 0])
    theta_y = math.atan2(-B[0, 1], B[1, 1])
    skew = math.degrees(math.remainder(theta_x - theta_y, 2 * math.pi))
    theta = theta_y + 0.5 * math.radians(skew)
    x0 = np.array([sx, sy, theta, origin[0], origin[1]])
    if n >= 4:
        from scipy.optimize import least_squares

        sol = least_squares(lambda q: (_model(q, c, mirror) - xz).ravel(), x0, method="lm")
        x0 = sol.x
    residuals = np.linalg.norm(_model(x0, c, mirror) - xz, axis=1)
    sx, sy, theta, c0, r0 = (float(v) for v in x0)
    if sx <= 0 or sy <= 0:
        raise ValueError(
            "fit_image_calibration: the fit gave a non-positive scale; check the "
            "target positions' units (m) and the pictures' order"
        )
    return ImageFit(
        (sx, sy),
        (c0, r0),
        math.degrees(theta),
        mirror < 0,
        skew,
        residuals,
        float(np.sqrt(np.mean(residuals**2))),
        float(residuals.max()),
    )


def targets_in_probe_frame(X_BP_list, p_B_target) -> np.ndarray:
    """A fixed target at ``p_B_target`` (3,) in the base, seen from each probe pose X_BP:
    (N, 3) positions in P (m)."""
    p = np.asarray(p_B_target, float).reshape(3)
    return np.array([X.inverse().multiply(p) for X in X_BP_list])


# --- the target file of `drake-rus hardware calibrate-image` ------------------------------
@dataclass
class TargetImage:
    # A grabbed picture (PNG, ...), relative to the target file's folder.
    image: str = ""
    # The target's position in P (m); or leave empty and give q (with TargetSet.target_B).
    p_P: list[float] = field(default_factory=list)
    # Joint positions (rad) when the picture was grabbed (`drake-rus hardware grab`).
    q: list[float] = field(default_factory=list)


@dataclass
class TargetSet:
    # The depth preset (m) the pictures were taken at.
    depth: float = field(default=0.15, metadata={"positive": True, "max": 0.4})
    # The sector's rectangle [x, y, width, height] in the pictures (pixels; zeros: all).
    crop: list[int] = field(default_factory=lambda: [0, 0, 0, 0], metadata={"length": 4, "min": 0})
    # The target's position in the base frame (m), for pictures given with q: touch the
    # target with the pivot-calibrated probe tip and read p_BP (`hardware check --dry-run`).
    target_B: list[float] = field(default_factory=list)
    # Target detection: search radius (px) and least contrast (grey levels).
    search_radius_px: int = field(default=12, metadata={"min": 1})
    min_contrast: float = field(default=30.0, metadata={"min": 0.0})
    targets: list[TargetImage] = field(default_factory=list)


def _check_mapping(where: str, raw, fields: str) -> None:
    """ScenarioError naming ``where`` unless the file's YAML is a mapping (an empty file,
    a list or a scalar otherwise fail inside Drake's loader with "YAML root was a ...")."""
    if raw is None:
        raise ScenarioError(f"{where}: the file is empty; expected a YAML mapping of {fields}")
    if not isinstance(raw, dict):
        raise ScenarioError(
            f"{where}: expected a YAML mapping of {fields}, got a {type(raw).__name__}"
        )


def load_target_set(path) -> TargetSet:
    path = Path(path)
    if not path.is_file():
        raise ScenarioError(f"target file not found: {path}")
    try:
        raw = yaml_load_file(str(path))
    except Exception as e:
        raise ScenarioError(f"{path}: not valid YAML: {yaml_error_text(e)}") from None
    _check_mapping(str(path), raw, "depth, crop and targets: [{image, p_P or q}]")
    try:
        validate(TargetSet, raw or {})
        return yaml_load_typed(schema=TargetSet, filename=str(path), defaults=TargetSet())
    except ScenarioError as e:
        raise ScenarioError(f"{path}: {e}") from None
    except Exception as e:
        raise ScenarioError(f"{path}: {e}") from None


@dataclasses.dataclass(frozen=True)
class TargetFitReport:
    """What :func:`fit_target_set` did: the fit, each image's name, target pixel and
    position in P (m)."""

    fit: ImageFit
    names: list
    pixels: np.ndarray
    p_P: np.ndarray


def fit_target_set(targets: TargetSet, base_dir, scenario=None) -> TargetFitReport:
    """Finds the target in each picture of ``targets`` and fits the calibration. Pictures
    given with ``q`` need ``targets.target_B`` and ``scenario`` (our FR3 model's FK with the
    scenario's probe calibration). Raises ValueError naming the picture that failed."""
    cv2 = require("cv2", "the image calibration")
    base_dir = Path(base_dir)
    if not targets.targets:
        raise ValueError("calibrate-image: the target file lists no pictures (targets: [])")
    fk = None
    pixels, p_P, names = [], [], []
    for k, t in enumerate(targets.targets):
        where = f"targets[{k}] ({t.image})"
        path = base_dir / t.image
        picture = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if picture is None:
            raise ValueError(f"calibrate-image: {where}: cannot read the picture {path}")
        found = find_point_target(
            picture, targets.crop, targets.search_radius_px, targets.min_contrast
        )
        if found is None:
            raise ValueError(
                f"calibrate-image: {where}: no point target (nothing "
                f"{targets.min_contrast:g} grey levels above the background "
                f"inside the crop {list(targets.crop)})"
            )
        if len(t.p_P) == 3:
            p = np.asarray(t.p_P, float)
        elif len(t.q) == 7:
            if len(targets.target_B) != 3 or scenario is None:
                raise ValueError(
                    f"calibrate-image: {where} gives joint positions q: the "
                    f"target file needs target_B [x, y, z] (m)"
                )
            if fk is None:
                plant, tip = MakeControlPlant(scenario.robot, scenario.probe)
                fk = (plant, tip, plant.CreateDefaultContext())
            plant, tip, ctx = fk
            plant.SetPositions(ctx, np.asarray(t.q, float))
            p = targets_in_probe_frame([tip.CalcPoseInWorld(ctx)], targets.target_B)[0]
        else:
            raise ValueError(
                f"calibrate-image: {where}: give p_P (3 values, m) or q (7 joint positions, rad)"
            )
        pixels.append(found)
        p_P.append(p)
        names.append(t.image)
    fit = fit_image_calibration(np.array(pixels), np.array(p_P))
    return TargetFitReport(fit, names, np.array(pixels), np.array(p_P))
