"""The torso of a virtual patient: a cross-section that varies along the body, and its layers.

Body frame Bd (supine reference pose, SI units): x_Bd towards the patient's left, y_Bd
superior, z_Bd anterior; origin on the back skin plane (the bed surface when supine) under
the midline, at the level of the L1 vertebra.

Cross-section at level y: a two-part superellipse centred at (0, Zc(y)):
``|x/A|^n + |(z - Zc)/B|^n = 1`` with (n, B) = (n_top, B_top) anteriorly and
(n_back, Zc) posteriorly (n_back = 4 flattens the back on the bed). Inner layers
(subcutaneous fat, then the muscle wall) are the same superellipse inset by their thickness.
"""

from dataclasses import asdict, dataclass

import numpy as np
import trimesh

__all__ = ["TorsoParams", "Torso", "BODY_SIZES"]

# Body-size classes. P(class): WHO 2022, 43% of adults overweight (BMI >= 25) and 16% obese
# (BMI >= 30), so 27% overweight and 16% obese; the other 57% split lean/normal (modelling
# choice). Half-widths follow adult
# abdominal transverse diameters at L1-L2 (about 260-380 mm); subcutaneous fat thickness
# grows with BMI (about 5-40 mm). Vertical (anterior) skin-to-kidney depth supine, drawn
# uniformly per class: 75-165 mm over the classes; CT skin-to-kidney distances have means
# near 100 mm with SDs of 25-30 mm (lithotripsy series, facts file), and the Visible Human
# female measures 147.5 mm (inside the obese range). The class ranges are a modelling choice.
BODY_SIZES = {
    #            P(class) half-width(m) fat(m)  vertical kidney depth range (m)
    "lean": (0.17, 0.138, 0.008, (0.075, 0.095)),
    "normal": (0.40, 0.150, 0.015, (0.085, 0.112)),
    "overweight": (0.27, 0.165, 0.025, (0.098, 0.130)),
    "obese": (0.16, 0.182, 0.036, (0.118, 0.165)),
}


@dataclass
class TorsoParams:
    size_class: str = "normal"
    half_width: float = 0.150  # A at the L1 level (m)
    height: float = 0.220  # H = anteroposterior thickness at the L1 level (m)
    back_ratio: float = 0.45  # Zc / H
    n_top: float = 2.3
    n_back: float = 4.0
    fat: float = 0.015  # subcutaneous fat thickness (m)
    muscle: float = 0.012  # abdominal wall muscle thickness (m)
    width_slope: float = 0.05  # relative widening towards the chest
    width_curv: float = 0.03  # relative widening at both ends (chest, pelvis)
    height_slope: float = 0.02
    y_min: float = -0.30  # torso extent along the body (m)
    y_max: float = 0.30


class Torso:
    def __init__(self, params: TorsoParams):
        self.p = params

    # --- cross-section -------------------------------------------------------------------
    def section(self, y):
        """(A, Zc, B_top) at level(s) y."""
        p = self.p
        y = np.asarray(y, dtype=float)
        A = p.half_width * (
            1.0 + p.width_slope * np.tanh((y - 0.05) / 0.10) + p.width_curv * (y / 0.3) ** 2
        )
        H = p.height * (1.0 + p.height_slope * np.tanh((y - 0.05) / 0.10))
        Zc = p.back_ratio * H
        return A, Zc, H - Zc

    def level(self, x, y, z, inset=0.0):
        """Superellipse level s (s <= 1 inside) of points, with the outline inset by ``inset`` m."""
        A, Zc, Bt = self.section(y)
        dz = np.asarray(z, dtype=float) - Zc
        top = dz >= 0
        n = np.where(top, self.p.n_top, self.p.n_back)
        B = np.where(top, Bt, Zc) - inset
        Ai = A - inset
        return (np.abs(x / Ai) ** n + np.abs(dz / B) ** n) ** (1.0 / n)

    def inside(self, x, y, z, inset=0.0):
        return self.level(x, y, z, inset) <= 1.0

    def top_z(self, x, y, inset=0.0):
        """Height of the (inset) anterior surface above the bed at (x, y)."""
        A, Zc, Bt = self.section(y)
        u = np.clip(np.abs(x) / (A - inset), 0.0, 1.0)
        return Zc + (Bt - inset) * (1.0 - u**self.p.n_top) ** (1.0 / self.p.n_top)

    def ring(self, y, n_points=96, inset=0.0):
        """Points (n, 3) around the (inset) outline at level y, counter-clockwise in x-z."""
        A, Zc, Bt = self.section(y)
        th = np.linspace(0.0, 2 * np.pi, n_points, endpoint=False)
        c, s = np.cos(th), np.sin(th)
        top = s >= 0
        n = np.where(top, self.p.n_top, self.p.n_back)
        B = np.where(top, Bt, Zc) - inset
        x = (A - inset) * np.sign(c) * np.abs(c) ** (2.0 / n)
        z = Zc + B * np.sign(s) * np.abs(s) ** (2.0 / n)
        return np.column_stack([x, np.full_like(x, y), z])

    def outline_point(self, y, theta, side_sign, inset=0.0):
        """Point on the inset outline at level y and angle theta (superellipse parameter;
        -pi/2 is the posterior midline, 0 the flank, pi/2 the anterior midline), on the
        patient's left (side_sign=+1) or right (-1)."""
        A, Zc, Bt = self.section(y)
        c, s = np.cos(theta), np.sin(theta)
        top = s >= 0
        n = np.where(top, self.p.n_top, self.p.n_back)
        B = np.where(top, Bt, Zc) - inset
        x = side_sign * (A - inset) * np.abs(c) ** (2.0 / n)
        z = Zc + B * np.sign(s) * np.abs(s) ** (2.0 / n)
        return np.column_stack([x, np.broadcast_to(y, np.shape(x)), z])

    # --- meshes --------------------------------------------------------------------------
    def mesh(self, y_lo=None, y_hi=None, spacing=0.01, n_points=96) -> trimesh.Trimesh:
        """Watertight skin surface between levels y_lo and y_hi (Bd frame), capped flat."""
        y_lo = self.p.y_min if y_lo is None else y_lo
        y_hi = self.p.y_max if y_hi is None else y_hi
        if not y_hi > y_lo:
            raise ValueError(f"torso mesh: empty y range [{y_lo}, {y_hi}]")
        n_rings = max(2, int(np.ceil((y_hi - y_lo) / spacing)) + 1)
        ys = np.linspace(y_lo, y_hi, n_rings)
        rings = [self.ring(y, n_points) for y in ys]
        V = np.vstack(rings)
        faces = []
        for r in range(n_rings - 1):
            a0, b0 = r * n_points, (r + 1) * n_points
            for i in range(n_points):
                j = (i + 1) % n_points
                faces.append([a0 + i, a0 + j, b0 + j])
                faces.append([a0 + i, b0 + j, b0 + i])
        c_lo = len(V)
        c_hi = c_lo + 1
        V = np.vstack([V, rings[0].mean(axis=0), rings[-1].mean(axis=0)])
        last = (n_rings - 1) * n_points
        for i in range(n_points):
            j = (i + 1) % n_points
            faces.append([c_lo, j, i])
            faces.append([c_hi, last + i, last + j])
        F = np.asarray(faces)
        m = trimesh.Trimesh(V, F, process=False)
        if m.volume < 0:
            m = trimesh.Trimesh(V, F[:, ::-1], process=False)
        return m

    def to_dict(self) -> dict:
        return asdict(self.p)
