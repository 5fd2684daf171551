"""Geometry of the curvilinear probe's image: pixels <-> probe tip frame P <-> base frame B.

Frame P (docs/design.md): origin at the centre of the probe face, z_P the beam direction into the
body, x_P the transducer array direction; the image plane is the x_P-z_P plane (y_P = 0).

The convex array is an arc of radius ``R`` centred on the fan apex ``(0, 0, -R)`` (behind the
face). Scan line at angle ``theta`` (positive towards +x_P) leaves the face along
``(sin theta, 0, cos theta)``; a sample at depth ``d`` along it lies at
``p_P = (r sin theta, 0, r cos theta - R)`` with ``r = R + d``.

The scan-converted image is a regular Cartesian grid covering the fan's bounding box:
row ``v`` (0 at the top, the probe face) goes along +z_P, column ``u`` along +x_P. Pixel
``(u, v)`` (integer at pixel centres) is at ``x = x0 + u * dx``, ``z = z0 + v * dz``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from pydrake.math import RigidTransform

from drake_rus.imaging.config import ImagingConfig


def check_pose(X: RigidTransform, name: str = "X_BP") -> RigidTransform:
    """Returns ``X`` if it is a RigidTransform with finite entries, else raises ValueError."""
    if not isinstance(X, RigidTransform):
        raise ValueError(f"{name}: expected a pydrake RigidTransform, got {type(X).__name__}")
    M = X.GetAsMatrix4()
    if not np.isfinite(M).all():
        raise ValueError(f"{name}: pose has non-finite entries (NaN or inf):\n{M}")
    return X


@dataclass(frozen=True)
class ProbeGeometry:
    """Fan geometry and pixel grid of a curvilinear probe (all lengths in m, angles in rad)."""

    radius: float  # radius of curvature of the array (m)
    half_angle: float  # half the fan opening angle (rad)
    depth: float  # imaging depth along each scan line (m)
    height_px: int  # image rows (along z_P)
    width_px: int  # image columns (along x_P)
    elevation_width: float = 0.010  # elevational beam width (m)

    def __post_init__(self):
        for name in ("radius", "half_angle", "depth", "elevation_width"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"ProbeGeometry.{name}: expected a positive number, got {v}")
        if not self.half_angle < np.pi / 2:
            raise ValueError(
                f"ProbeGeometry.half_angle: expected < 90 deg, got {np.degrees(self.half_angle)}"
            )
        for name in ("height_px", "width_px"):
            v = getattr(self, name)
            # A count, not int(v): 256.5 or "256" passed and failed later, deep in numpy.
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 2:
                raise ValueError(
                    f"ProbeGeometry.{name}: expected an integer number of pixels, at least 2, "
                    f"got {v!r}"
                )

    @classmethod
    def from_config(cls, config: ImagingConfig) -> "ProbeGeometry":
        return cls(
            radius=config.probe_radius,
            half_angle=np.radians(config.field_of_view_deg) / 2,
            depth=config.depth,
            height_px=int(config.image_height_px),
            width_px=int(config.image_width_px),
            elevation_width=config.elevation_width,
        )

    # --- the pixel grid (cached: the geometry is immutable) ---------------------------------
    @cached_property
    def image_shape(self) -> tuple[int, int]:
        """(rows, columns) of the image."""
        return (self.height_px, self.width_px)

    @cached_property
    def x_min(self) -> float:
        return -(self.radius + self.depth) * np.sin(self.half_angle)

    @cached_property
    def x_max(self) -> float:
        return -self.x_min

    @cached_property
    def z_min(self) -> float:
        # The face's corners sit above the face centre.
        return self.radius * np.cos(self.half_angle) - self.radius

    @cached_property
    def z_max(self) -> float:
        return self.depth

    @cached_property
    def dx(self) -> float:
        """Pixel width along x_P (m)."""
        return (self.x_max - self.x_min) / self.width_px

    @cached_property
    def dz(self) -> float:
        """Pixel height along z_P (m)."""
        return (self.z_max - self.z_min) / self.height_px

    @cached_property
    def pixel_area(self) -> float:
        return self.dx * self.dz

    @cached_property
    def x0(self) -> float:
        """x_P of the centre of column 0."""
        return self.x_min + 0.5 * self.dx

    @cached_property
    def z0(self) -> float:
        """z_P of the centre of row 0."""
        return self.z_min + 0.5 * self.dz

    def width_at_depth(self, d: float) -> float:
        """Lateral width (m) of the fan at depth ``d`` below the face centre."""
        return 2 * (self.radius + d) * np.sin(self.half_angle)

    # --- conversions ------------------------------------------------------------------------
    def pixel_to_P(self, uv: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N, 2) as (column u, row v) -> points (N, 3) in P (m), y_P = 0."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        p = np.zeros((uv.shape[0], 3))
        p[:, 0] = self.x0 + uv[:, 0] * self.dx
        p[:, 2] = self.z0 + uv[:, 1] * self.dz
        return p

    def P_to_pixel(self, p_P: np.ndarray) -> np.ndarray:
        """Points (N, 3) in P -> continuous pixel coordinates (N, 2) (u, v); y_P is ignored
        (orthogonal projection onto the image plane)."""
        p = np.asarray(p_P, dtype=float).reshape(-1, 3)
        return np.stack([(p[:, 0] - self.x0) / self.dx, (p[:, 2] - self.z0) / self.dz], axis=1)

    def pixel_to_B(self, uv: np.ndarray, X_BP: RigidTransform) -> np.ndarray:
        """Pixel coordinates (N, 2) -> points (N, 3) in the base frame B via the probe pose."""
        check_pose(X_BP)
        p_P = self.pixel_to_P(uv)
        return p_P @ X_BP.rotation().matrix().T + X_BP.translation()

    def B_to_pixel(self, p_B: np.ndarray, X_BP: RigidTransform) -> tuple[np.ndarray, np.ndarray]:
        """Points (N, 3) in B -> (pixel coordinates (N, 2), out-of-plane distance y_P (N,))."""
        check_pose(X_BP)
        p = np.asarray(p_B, dtype=float).reshape(-1, 3)
        p_P = (p - X_BP.translation()) @ X_BP.rotation().matrix()
        return self.P_to_pixel(p_P), p_P[:, 1]

    def P_to_polar(self, p_P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Points (N, 3) in P -> (scan-line angle theta (rad), depth along the line d (m))."""
        p = np.asarray(p_P, dtype=float).reshape(-1, 3)
        zc = p[:, 2] + self.radius
        return np.arctan2(p[:, 0], zc), np.hypot(p[:, 0], zc) - self.radius

    def polar_to_P(self, theta: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Scan-line angle (rad) and depth (m) -> points (N, 3) in P."""
        theta, d = np.broadcast_arrays(
            np.asarray(theta, float).ravel(), np.asarray(d, float).ravel()
        )
        r = self.radius + d
        return np.stack(
            [r * np.sin(theta), np.zeros_like(r), r * np.cos(theta) - self.radius], axis=1
        )

    def in_fan(self, p_P: np.ndarray) -> np.ndarray:
        """Whether points (N, 3) in P lie inside the fan (in-plane test)."""
        theta, d = self.P_to_polar(p_P)
        return (np.abs(theta) <= self.half_angle) & (d >= 0) & (d <= self.depth)

    # --- precomputed per-pixel geometry ------------------------------------------------------
    @cached_property
    def fan_mask(self) -> np.ndarray:
        """(rows, cols) bool: pixel centres inside the fan."""
        m = self.in_fan(self.pixel_to_P(self._all_uv)).reshape(self.image_shape)
        m.flags.writeable = False
        return m

    @cached_property
    def _all_uv(self) -> np.ndarray:
        v, u = np.mgrid[0 : self.height_px, 0 : self.width_px]
        return np.stack([u.ravel(), v.ravel()], axis=1).astype(float)

    @cached_property
    def fan_flat_index(self) -> np.ndarray:
        """Flat (row-major) indices of the fan's pixels."""
        idx = np.flatnonzero(self.fan_mask)
        idx.flags.writeable = False
        return idx

    @cached_property
    def fan_flat_index32(self) -> np.ndarray:
        """``fan_flat_index`` as int32 (half the bytes for the slicing kernel to stream)."""
        idx = self.fan_flat_index.astype(np.int32)
        idx.flags.writeable = False
        return idx

    @cached_property
    def fan_p_P(self) -> np.ndarray:
        """(N, 3) positions in P of the fan pixels' centres, in ``fan_flat_index`` order."""
        p = self.pixel_to_P(self._all_uv[self.fan_flat_index])
        p.flags.writeable = False
        return p

    @cached_property
    def fan_polar(self) -> tuple[np.ndarray, np.ndarray]:
        """(scan-line angle theta (rad), depth along the line d (m)) (N,) each of the fan
        pixels' centres, in ``fan_flat_index`` order."""
        theta, d = self.P_to_polar(self.fan_p_P)
        theta.flags.writeable = False
        d.flags.writeable = False
        return theta, d

    def scan_line_bins(self, line_step: float) -> tuple[np.ndarray, int, int, np.ndarray]:
        """The fan's pixels binned into scan lines ``line_step`` rad wide and depth steps of
        one pixel row: (bin (N,) of each fan pixel in ``fan_flat_index`` order, row-major in
        a (lines, depths) grid; lines; depths; pixels per bin (lines, depths)). Geometry
        only, so computed once per ``line_step`` (``segment.acoustic_shadow`` runs it on
        every frame)."""
        cache = self.__dict__.setdefault("_scan_line_bins", {})
        key = float(line_step)
        if key not in cache:
            theta, d = self.fan_polar
            n_lines = max(int(np.ceil(2.0 * self.half_angle / key)), 1)
            line = ((theta + self.half_angle) * (n_lines / (2.0 * self.half_angle))).astype(int)
            np.clip(line, 0, n_lines - 1, out=line)
            n_depth = int(np.ceil(self.depth / self.dz)) + 1
            k = np.clip((d / self.dz).astype(int), 0, n_depth - 1)
            flat = line * n_depth + k
            counts = np.bincount(flat, minlength=n_lines * n_depth).reshape(n_lines, -1)
            flat.flags.writeable = False
            counts.flags.writeable = False
            cache[key] = (flat, n_lines, n_depth, counts)
        return cache[key]

    @cached_property
    def fan_x_z(self) -> tuple[np.ndarray, np.ndarray]:
        """(x_P, z_P) coordinates (N,) each of the fan pixels' centres (contiguous arrays)."""
        x = np.ascontiguousarray(self.fan_p_P[:, 0])
        z = np.ascontiguousarray(self.fan_p_P[:, 2])
        x.flags.writeable = False
        z.flags.writeable = False
        return x, z

    @cached_property
    def fan_x_z32(self) -> tuple[np.ndarray, np.ndarray]:
        """``fan_x_z`` as float32 (for the slicer's index arithmetic)."""
        x, z = (a.astype(np.float32) for a in self.fan_x_z)
        x.flags.writeable = False
        z.flags.writeable = False
        return x, z

    @cached_property
    def fan_rows(self) -> tuple[np.ndarray, np.ndarray]:
        """(z_P (rows,) float32 of each row's pixel centres, number of fan pixels in each
        row): the fan pixels are row-major, so ``fan_x_z32``'s z is each row's z repeated
        that many times."""
        v = np.arange(self.height_px, dtype=float)
        z = self.pixel_to_P(np.stack([np.zeros_like(v), v], axis=1))[:, 2].astype(np.float32)
        counts = np.bincount(self.fan_flat_index // self.width_px, minlength=self.height_px)
        z.flags.writeable = False
        counts.flags.writeable = False
        return z, counts

    def column_of_x(self, x: float) -> float:
        return (x - self.x0) / self.dx

    def horizontal_fraction(self, u: np.ndarray) -> np.ndarray:
        """Column coordinate -> horizontal position in [0, 1] across the image (c_msk's scale)."""
        return (np.asarray(u, float) + 0.5) / self.width_px
