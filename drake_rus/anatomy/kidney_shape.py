"""A parametric, bean-shaped kidney with known vertex correspondences.

The surface is a fixed icosphere mapped through a chain of smooth, injective maps, so every
generated kidney has the same vertex count and vertex j is the same anatomical landmark in all
kidneys (this gives the template builder a ground truth it cannot cheat). The chain, in the
kidney's local frame L (x_L long axis towards the superior pole, y_L medial -> lateral,
z_L = x_L x y_L):

1. star-shaped radius on the unit sphere: ``r(d) = (1 - hilum dent(d)) * (1 + lobulation(d))``;
   the hilum dent is a Gaussian notch on the medial side (the renal hilum and sinus opening);
2. ellipsoid scaling by the semi-axes (a, b, c);
3. pole-length asymmetry ``x -> x (1 + beta tanh(2x/a))`` (monotone for |beta| < 0.3);
4. pole-width asymmetry: y, z scaled by ``1 + alpha x/a`` (one pole broader);
5. bending: ``y -> y - kappa b (x/a)^2`` (poles medial: the medial border is concave);
6. a final diagonal scale that calibrates length, width and thickness, measured along the
   canonical (PCA) axes, to the sampled values.

Each step has an analytic inverse, so :meth:`KidneyShape.level` tells whether any point is
inside (the label volume uses it; no mesh voxelisation needed) and how deep it lies, which
gives the cortex / medulla / sinus sub-labels.
"""

from dataclasses import asdict, dataclass, field

import numpy as np
import trimesh

from drake_rus.anatomy.canonical_frame import extents_in_frame, mesh_canonical_frame
from drake_rus.anatomy.frames import SIDES

__all__ = [
    "KidneyShapeParams",
    "KidneyShape",
    "sample_kidney_shape_params",
    "ICOSPHERE_SUBDIVISIONS",
]

ICOSPHERE_SUBDIVISIONS = 5  # 10242 vertices; chord error < 0.1 mm on a 110 mm kidney
_N_LOBES = 7


@dataclass
class KidneyShapeParams:
    """Shape parameters, SI units (m). Defaults: an average adult kidney."""

    # Glodny 2009 (CT, 1,040 adults): length right 108.5 +- 12.2 mm, left 111.3 +- 12.6 mm.
    length: float = 0.1085
    # Emamian 1993 (US, 665 volunteers): width 58 mm (10th-90th percentile 51-64 mm).
    width: float = 0.058
    # Textbook anteroposterior thickness about 30-45 mm (no SD published).
    thickness: float = 0.040
    hilum_depth: float = 0.45  # notch depth as a fraction of the local radius
    hilum_sigma_x: float = 0.28  # notch half-extent along the long axis (unit-sphere units)
    hilum_sigma_z: float = 0.45  # notch half-extent front-back
    hilum_offset_x: float = -0.03  # notch centre along the long axis (unit-sphere units)
    bend: float = 0.18  # kappa: pole shift medially as a fraction of b
    pole_width_asym: float = 0.06  # alpha: > 0 upper pole broader
    pole_length_asym: float = 0.03  # beta: > 0 upper half longer
    lobulation: list = field(default_factory=lambda: [0.0] * _N_LOBES)
    # Glodny 2009: cortex 6.6 +- 1.9 mm; parenchymal width 15.4 +- 2.8 mm (right).
    cortex_thickness: float = 0.0066
    parenchyma_thickness: float = 0.0154


def sample_kidney_shape_params(rng: np.random.Generator, side: str = "right") -> KidneyShapeParams:
    """Draws shape parameters from the published distributions (facts file, kidney size) of
    the ``side`` ("right" or "left") kidney."""
    if side not in SIDES:  # anything else used to get the left kidney's lengths
        raise ValueError(f"side: expected one of {SIDES}, got {side!r}")
    # Length: Glodny 2009 CT mean and SD, truncated to 75-145 mm (about -2.7 to +3 SD); the
    # length is drawn first and kept, so its distribution is the published one (real bodies
    # reach 127 mm: about the 93rd percentile). Width and thickness are correlated with
    # length (allometry) and redrawn until the volume is in the physiological range (Lee
    # 1996: right 129 +- 30 mL, left 137 +- 30 mL).
    mean_len, sd_len = (0.1085, 0.0122) if side == "right" else (0.1113, 0.0126)
    length = mean_len + sd_len * rng.standard_normal()
    while not 0.075 <= length <= 0.145:
        length = mean_len + sd_len * rng.standard_normal()
    for _ in range(200):
        z = rng.standard_normal(2)
        # Emamian 1993: width 58 mm, 10-90th pct 51-64 mm -> SD about 5 mm.
        width = 0.058 + 0.08 * (length - mean_len) + 0.0045 * z[0]
        # Thickness 30-45 mm (textbook): mean 39 mm, SD 3.5 mm.
        thickness = 0.039 + 0.03 * (length - mean_len) + 0.0035 * z[1]
        approx_volume = 0.48 * length * width * thickness  # bean ~ 0.92 x ellipsoid
        if width >= thickness + 0.010 and thickness >= 0.028 and 83e-6 <= approx_volume <= 230e-6:
            break
    p = KidneyShapeParams(length=float(length), width=float(width), thickness=float(thickness))
    p.hilum_depth = float(rng.uniform(0.45, 0.65))
    p.hilum_sigma_x = float(rng.uniform(0.22, 0.34))
    p.hilum_sigma_z = float(rng.uniform(0.38, 0.52))
    p.hilum_offset_x = float(rng.normal(-0.03, 0.05))
    p.bend = float(rng.uniform(0.25, 0.45))
    p.pole_width_asym = float(rng.uniform(-0.06, 0.14))
    p.pole_length_asym = float(rng.uniform(-0.05, 0.08))
    p.lobulation = [float(v) for v in rng.normal(0.0, 0.018, _N_LOBES)]
    p.cortex_thickness = float(np.clip(rng.normal(0.0066, 0.0019), 0.004, 0.010))
    p.parenchyma_thickness = float(
        np.clip(rng.normal(0.0154, 0.0028), p.cortex_thickness + 0.005, 0.022)
    )
    return p


_SPHERES = {}


def _icosphere(subdivisions: int) -> trimesh.Trimesh:
    if subdivisions not in _SPHERES:
        _SPHERES[subdivisions] = trimesh.creation.icosphere(subdivisions=subdivisions)
    return _SPHERES[subdivisions]


def _lobe_basis(d: np.ndarray) -> np.ndarray:
    """Low-order real harmonics (N, 7) on unit vectors d: gentle, lobulated shape variation."""
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    return np.column_stack(
        [
            x * y,
            y * z,
            x * z,
            x * x - y * y,
            1.5 * z * z - 0.5,
            x * (5 * z * z - 1) * 0.5,
            y * (5 * x * x - 1) * 0.5,
        ]
    )


class KidneyShape:
    """The kidney surface and inside test for one parameter set, in the local frame L (m)."""

    def __init__(self, params: KidneyShapeParams, subdivisions: int = ICOSPHERE_SUBDIVISIONS):
        self.params = params
        self._sphere = _icosphere(subdivisions)
        self._scale = np.ones(3)
        a, b, c = params.length / 2, params.width / 2, params.thickness / 2
        self._abc = np.array([a, b, c])
        # Calibrate: measured canonical extents -> sampled length, width, thickness.
        target = np.array([params.length, params.width, params.thickness])
        for _ in range(3):
            mesh = self._mesh_unscaled()
            mesh.vertices = mesh.vertices * self._scale
            X = mesh_canonical_frame(mesh, [1, 0, 0], [0, 1, 0])
            ext = extents_in_frame(mesh.vertices, X)
            self._scale = self._scale * (target / ext)
        self.mesh = self._mesh_unscaled()
        self.mesh.vertices = self.mesh.vertices * self._scale
        # Table for inverting the monotone pole-length map x -> x (1 + beta tanh(2x/a)).
        xs = np.linspace(-1.6 * a, 1.6 * a, 4001)
        self._x_tab = xs
        self._x_map_tab = self._x_map(xs)

    # --- forward chain -------------------------------------------------------------------
    def radius(self, d: np.ndarray) -> np.ndarray:
        """Star-shaped radius r(d) on unit vectors d (N, 3)."""
        p = self.params
        dent = p.hilum_depth * np.exp(
            -0.5
            * (
                ((d[:, 0] - p.hilum_offset_x) / p.hilum_sigma_x) ** 2
                + (d[:, 2] / p.hilum_sigma_z) ** 2
            )
        )
        medial = 1.0 / (1.0 + np.exp(12.0 * d[:, 1]))  # ~1 on the medial side (y < 0)
        lob = 1.0 + _lobe_basis(d) @ np.asarray(p.lobulation)
        return (1.0 - dent * medial) * lob

    def _x_map(self, x):
        a = self._abc[0]
        return x * (1.0 + self.params.pole_length_asym * np.tanh(2.0 * x / a))

    def _forward(self, d: np.ndarray) -> np.ndarray:
        p = self.params
        a, b, _ = self._abc
        q = self.radius(d)[:, None] * d * self._abc
        x = self._x_map(q[:, 0])
        s = 1.0 + p.pole_width_asym * x / a
        y = q[:, 1] * s - p.bend * b * (x / a) ** 2
        z = q[:, 2] * s
        return np.column_stack([x, y, z])

    def _mesh_unscaled(self) -> trimesh.Trimesh:
        v = self._forward(np.asarray(self._sphere.vertices))
        return trimesh.Trimesh(v, np.asarray(self._sphere.faces), process=False)

    # --- inverse chain -------------------------------------------------------------------
    def level(self, p_L: np.ndarray, return_direction: bool = False):
        """For points (N, 3) in L: (f, depth) with f = rho / r(d) (< 1 inside) and an
        estimate of the depth below the surface (m, along the ray from the centre; negative
        outside); with ``return_direction`` also the unit-sphere direction d (N, 3)."""
        p = self.params
        a, b, _ = self._abc
        q = np.asarray(p_L, dtype=float) / self._scale
        x = q[:, 0]
        y = q[:, 1] + p.bend * b * (x / a) ** 2
        s = 1.0 + p.pole_width_asym * x / a
        y = y / s
        z = q[:, 2] / s
        x0 = np.interp(x, self._x_map_tab, self._x_tab)
        v = np.column_stack([x0, y, z]) / self._abc
        rho = np.linalg.norm(v, axis=1)
        d = v / np.maximum(rho, 1e-12)[:, None]
        r = self.radius(d)
        f = rho / r
        # Physical distance to the surface along the ray, approximately.
        surf_len = r * np.linalg.norm(d * self._abc * self._scale, axis=1)
        depth = (1.0 - f) * surf_len
        if return_direction:
            return f, depth, d
        return f, depth

    def inside(self, p_L: np.ndarray) -> np.ndarray:
        return self.level(p_L)[0] <= 1.0

    def hilum_point(self) -> np.ndarray:
        """The deepest point of the hilum notch on the surface, in L (m)."""
        p = self.params
        d = np.array([[p.hilum_offset_x, -1.0, 0.0]])
        d /= np.linalg.norm(d)
        return self._forward(d)[0] * self._scale

    def hilum_vertex(self) -> int:
        """Index of the icosphere vertex at the hilum notch (same index for all kidneys with
        the same hilum offset; the nearest vertex to the notch direction)."""
        p = self.params
        d = np.array([p.hilum_offset_x, -1.0, 0.0])
        d /= np.linalg.norm(d)
        return int(np.argmax(np.asarray(self._sphere.vertices) @ d))

    def to_dict(self) -> dict:
        return asdict(self.params)
