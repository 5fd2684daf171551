"""Virtual patients from published statistics, deterministic per seed.

Every number below comes from ``docs/facts/anatomy_and_ultrasound.md`` unless marked as a
modelling choice. Placement (body frame Bd, see :mod:`drake_rus.anatomy.body`):

- kidney size and shape: :mod:`drake_rus.anatomy.kidney_shape` (Glodny 2009, Emamian 1993);
- axial (hilum) angle: hilum faces anteromedially about 40-45 deg to the horizontal (Sakate
  2009): N(42.5, 5) deg, clipped to 30-55 deg;
- coronal angle: long axis 15-20 deg off craniocaudal, upper pole medial: N(17.5, 3) deg,
  clipped to 10-26 deg;
- sagittal angle: upper pole posterior, 10-25 deg sampled uniformly (no published angle);
- craniocaudal position: right kidney T12-L3, one vertebra lower than the left: centroid at
  N(-22, 12) mm (right) or N(+5, 12) mm (left) from the L1 level (y_Bd = 0);
- medial-lateral position: centroid N(75, 6) mm from the midline (modelling choice: hilum
  about 45-50 mm from the midline); moved medially if the kidney would leave the cavity;
- depth: the kidney's posterior surface lies N(35, 5) mm in front of the back fat (posterior
  muscles and perirenal fat), and the body's anteroposterior size is set so that the vertical
  depth from the upper skin above the kidney centroid to the kidney is drawn uniformly in the
  body-size class's range (:data:`~drake_rus.anatomy.body.BODY_SIZES`: 75-95 mm lean up to
  118-165 mm obese; CT skin-to-kidney distances, facts file; the Visible Human female's
  147.5 mm lies near the 94th percentile of the cohort). This is the depth a probe on the
  upper surface pointing down (-z_Pt) must see through when supine; in left lateral
  decubitus the upper surface is the right flank and the depth is smaller (reported, not set).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
import trimesh
from pydrake.math import RigidTransform, RotationMatrix
from tqdm import tqdm

from drake_rus.anatomy.body import BODY_SIZES, Torso, TorsoParams
from drake_rus.anatomy.canonical_frame import mesh_canonical_frame, mesh_surface_moments
from drake_rus.anatomy.frames import R_PtBd, check_side_posture, reference_axes_Pt, transform_mesh
from drake_rus.anatomy.kidney_shape import (
    KidneyShape,
    KidneyShapeParams,
    sample_kidney_shape_params,
)
from drake_rus.anatomy.labels import Label, LabelVolume
from drake_rus.anatomy.patient import Patient

__all__ = [
    "PatientParams",
    "sample_patient_params",
    "generate_patient",
    "patient_builders",
    "generate_patient_with_kidney",
    "KidneyDoesNotFit",
    "VERTEBRA_Y",
]

# Levels (m, y_Bd) of vertebral centres relative to L1 (modelling choice: about 27-30 mm per
# thoracolumbar vertebra + disc).
VERTEBRA_Y = {"T10": 0.083, "T11": 0.057, "T12": 0.030, "L1": 0.0, "L2": -0.030, "L3": -0.061}
# Vertebral body (modelling choice): centre this far above the back fat, semi-axes (x, z).
VERTEBRAL_BODY_Z = 0.083
VERTEBRAL_BODY_SEMI_AXES = (0.022, 0.016)
# A kidney given to the generator (generate_patient_with_kidney) keeps at least this much
# from the vertebral body (modelling choice: the psoas lies between them).
SPINE_CLEARANCE = 0.005


class KidneyDoesNotFit(ValueError):
    """A given kidney has no room in this body between the spine and the flank."""


@dataclass
class PatientParams:
    seed: int
    side: str
    posture: str
    torso: TorsoParams
    kidney: KidneyShapeParams
    hilum_angle: float  # rad, axial rotation of the hilum towards anterior
    coronal_angle: float  # rad, upper pole medial
    sagittal_angle: float  # rad, upper pole posterior
    centroid_x: float  # |x| of the kidney centroid from the midline (m)
    centroid_y: float  # y_Bd of the kidney centroid (m)
    posterior_gap: float  # kidney bottom above the back fat (m)
    depth_target: float  # vertical skin-to-kidney depth (m)
    ribs: list = field(default_factory=list)  # (name, y0, theta_span, drop, radius)
    gas: list = field(default_factory=list)  # (dx, dy, dz, radius) relative placement
    liver_offset: list = field(default_factory=lambda: [0.0, 0.0, 0.0])

    def to_dict(self) -> dict:
        return asdict(self)


def _check_seed(seed) -> None:
    """A generator seed is a non-negative integer (1.7 was read as seed 1, -1 failed deep in
    numpy)."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed: expected a non-negative integer, got {seed!r}")


def sample_patient_params(seed: int, side: str = "right", posture: str = "supine") -> PatientParams:
    _check_seed(seed)
    check_side_posture(side, posture)
    rng = np.random.default_rng(np.random.SeedSequence([20240, int(seed)]))
    names = list(BODY_SIZES)
    probs = np.array([BODY_SIZES[n][0] for n in names])
    size = names[int(rng.choice(len(names), p=probs / probs.sum()))]
    _, half_width, fat, depth_range = BODY_SIZES[size]
    torso = TorsoParams(
        size_class=size,
        half_width=float(half_width + rng.normal(0, 0.007)),
        fat=float(max(0.004, fat + rng.normal(0, 0.003))),
        muscle=float(np.clip(rng.normal(0.012, 0.002), 0.008, 0.018)),
        n_top=float(rng.uniform(2.1, 2.6)),
        width_slope=float(rng.uniform(0.02, 0.08)),
        width_curv=float(rng.uniform(0.0, 0.06)),
        height_slope=float(rng.uniform(-0.03, 0.05)),
    )
    kidney = sample_kidney_shape_params(rng, side)
    hilum = np.deg2rad(np.clip(rng.normal(42.5, 5.0), 30.0, 55.0))
    coronal = np.deg2rad(np.clip(rng.normal(17.5, 3.0), 10.0, 26.0))
    sagittal = np.deg2rad(rng.uniform(10.0, 25.0))
    cx = float(np.clip(rng.normal(0.075, 0.006), 0.060, 0.092))
    cy = float(rng.normal(-0.022, 0.012) if side == "right" else rng.normal(0.005, 0.012))
    gap = float(np.clip(rng.normal(0.035, 0.005), 0.025, 0.048))
    depth = float(rng.uniform(*depth_range))
    ribs = []
    for name, span, drop in (
        ("rib_12", 1.00, 0.030),
        ("rib_11", 1.45, 0.050),
        ("rib_10", 2.10, 0.075),
    ):
        level = {"rib_12": "T12", "rib_11": "T11", "rib_10": "T10"}[name]
        ribs.append(
            [
                name,
                float(VERTEBRA_Y[level] + rng.normal(0, 0.004)),
                float(span + rng.normal(0, 0.08)),
                float(drop * rng.uniform(0.85, 1.15)),
                float(rng.uniform(0.0050, 0.0062)),
            ]
        )
    gas = [[0.035, 0.010, 0.030, float(rng.uniform(0.010, 0.017))]]  # hepatic/splenic flexure
    for _ in range(int(rng.integers(2, 5))):
        gas.append(
            [
                float(rng.uniform(0.05, 0.13)),
                float(rng.uniform(-0.10, 0.0)),
                float(rng.uniform(0.04, 0.08)),
                float(rng.uniform(0.006, 0.014)),
            ]
        )
    liver = [float(rng.normal(0, 0.008)), float(rng.normal(0, 0.008)), float(rng.normal(0, 0.005))]
    return PatientParams(
        seed=int(seed),
        side=side,
        posture=posture,
        torso=torso,
        kidney=kidney,
        hilum_angle=float(hilum),
        coronal_angle=float(coronal),
        sagittal_angle=float(sagittal),
        centroid_x=cx,
        centroid_y=cy,
        posterior_gap=gap,
        depth_target=depth,
        ribs=ribs,
        gas=gas,
        liver_offset=liver,
    )


class _Layout:
    """Everything placed in the body frame Bd for one parameter set."""

    def __init__(self, prm: PatientParams, shape=None, R_BdL=None):
        """``shape``: the kidney (default: the parametric one of ``prm.kidney``); any object
        with ``mesh`` and ``inside`` in its frame L, ``hilum_point()``, and optionally
        ``placement_mesh`` / ``inside_placement`` (the extent that is placed, e.g. kidney and
        tumour when ``mesh`` is the parenchyma), ``reference_axes`` (superior and lateral in
        L for the canonical frame, default x_L and y_L) and ``label_codes`` (labels of the
        kidney region, see :func:`_build_labels`). ``R_BdL``: its orientation in Bd
        (default: the sampled angles below)."""
        self.prm = prm
        self.s = -1.0 if prm.side == "right" else 1.0  # side sign in x_Bd
        custom = shape is not None
        self.shape = shape if custom else KidneyShape(prm.kidney)
        self.torso = Torso(prm.torso)
        # Orientation. Target canonical axes in Bd: the long axis x_k has the sampled coronal
        # (upper pole medial) and sagittal (upper pole posterior) projection angles; the
        # medial axis -y_k is raised anteriorly by the hilum angle in the axial plane. The
        # shape's own canonical frame in L (R_LK) then gives R_BdL = R_BdK R_LK^T, so the
        # PCA frame of the placed kidney has exactly these angles.
        medial_x = -self.s
        u = np.array([medial_x * np.tan(prm.coronal_angle), 1.0, -np.tan(prm.sagittal_angle)])
        u /= np.linalg.norm(u)
        m = np.array([medial_x * np.cos(prm.hilum_angle), 0.0, np.sin(prm.hilum_angle)])
        m -= (m @ u) * u
        m /= np.linalg.norm(m)
        y_k = -m
        R_BdK = np.column_stack([u, y_k, np.cross(u, y_k)])
        if R_BdL is None:
            refs = getattr(self.shape, "reference_axes", ([1, 0, 0], [0, 1, 0]))
            R_LK = mesh_canonical_frame(self.shape.mesh, *refs).rotation().matrix()
            self.R_BdL = R_BdK @ R_LK.T
        else:
            self.R_BdL = np.asarray(R_BdL, dtype=float)
        placed = getattr(self.shape, "placement_mesh", self.shape.mesh)
        self._inside_placed = getattr(self.shape, "inside_placement", self.shape.inside)
        _, c_L, _ = mesh_surface_moments(placed.vertices, placed.faces)
        self.c_L = c_L
        v_rel = (self.R_BdL @ (self.shape.mesh.vertices - c_L).T).T  # about the centroid
        outer_rel = (self.R_BdL @ (placed.vertices - c_L).T).T
        cx = prm.centroid_x
        cavity = prm.torso.fat + prm.torso.muscle + 0.003
        for _ in range(40):
            self._place(v_rel, outer_rel, cx)
            v = self.outer_vertices_Bd
            leaves = not np.all(self.torso.level(v[:, 0], v[:, 1], v[:, 2], inset=cavity) <= 1.0)
            # A given kidney (e.g. a real one with a tumour) may reach the spine: moved
            # laterally, never into the bone. Generated kidneys never do (unchanged).
            spine = custom and self.spine_overlap(v)
            if leaves and spine:
                raise KidneyDoesNotFit(
                    f"kidney does not fit this body (seed {prm.seed}): between the spine and "
                    f"the flank there is no room for its {np.ptp(v[:, 0]) * 1e3:.0f} mm "
                    "width; try another body"
                )
            if not leaves and not spine:
                break
            cx += 0.002 if spine else -0.002
        self.centroid_x = cx

    def spine_overlap(self, v_Bd) -> bool:
        """Whether points (N, 3) in Bd lie within ``SPINE_CLEARANCE`` of the vertebral body."""
        a, b = (r + SPINE_CLEARANCE for r in VERTEBRAL_BODY_SEMI_AXES)
        z_vb = 0.8 * self.prm.torso.fat + VERTEBRAL_BODY_Z
        return bool(np.any((v_Bd[:, 0] / a) ** 2 + ((v_Bd[:, 2] - z_vb) / b) ** 2 <= 1.0))

    def _place(self, v_rel, outer_rel, cx):
        prm = self.prm
        back_fat = 0.8 * prm.torso.fat
        z_c = back_fat + prm.torso.muscle + prm.posterior_gap - outer_rel[:, 2].min()
        self.p_c = np.array([self.s * cx, prm.centroid_y, z_c])
        self.p_BdL = self.p_c - self.R_BdL @ self.c_L
        self.kidney_vertices_Bd = v_rel + self.p_c
        self.outer_vertices_Bd = outer_rel + self.p_c
        # Top of the kidney on the vertical line through its centroid (bisection on the
        # analytic inside test).
        zs = np.linspace(z_c, z_c + 0.08, 801)
        pts = np.column_stack([np.full_like(zs, self.p_c[0]), np.full_like(zs, self.p_c[1]), zs])
        inside = self._inside_placed(self.L_from_Bd(pts))
        self.kidney_top_z = float(zs[np.nonzero(inside)[0].max()]) if inside.any() else z_c
        # Body height so that the vertical depth above the kidney is the target depth.
        t = self.torso
        A, Zc, Bt = t.section(self.p_c[1])
        f = (1.0 - (abs(self.p_c[0]) / A) ** prm.torso.n_top) ** (1.0 / prm.torso.n_top)
        hy = 1.0 + prm.torso.height_slope * np.tanh((self.p_c[1] - 0.05) / 0.10)
        rho = prm.torso.back_ratio
        target = self.kidney_top_z + prm.depth_target
        prm.torso.height = float(target / (hy * (rho + (1 - rho) * f)))

    def L_from_Bd(self, p_Bd):
        return (np.asarray(p_Bd) - self.p_BdL) @ self.R_BdL

    def inside_kidney_Bd(self, p_Bd):
        return self.shape.inside(self.L_from_Bd(p_Bd))

    def X_BdL(self) -> RigidTransform:
        return RigidTransform(RotationMatrix(self.R_BdL), self.p_BdL)

    def hilum_angle_measured(self, x_k: np.ndarray) -> float:
        """Angle (rad) above the horizontal of the centroid -> hilum notch direction, taken
        perpendicular to the long axis ``x_k`` (Bd) and with its horizontal part measured
        medially: the axial-plane hilum angle of Sakate 2009, on the placed geometry."""
        h = self.R_BdL @ self.shape.hilum_point() + self.p_BdL
        d = h - self.p_c
        d = d - (d @ x_k) * x_k
        medial = -self.s * d[0]
        return float(np.arctan2(d[2], medial))


def _ball_offsets(radius_vox: float) -> np.ndarray:
    r = int(np.ceil(radius_vox))
    g = np.mgrid[-r : r + 1, -r : r + 1, -r : r + 1].reshape(3, -1).T
    return g[(g**2).sum(axis=1) <= radius_vox**2]


def _stamp(labels, origin, vs, centers, radius, value, allowed=None):
    """Sets voxels within ``radius`` of any of ``centers`` (Bd, m) to ``value``."""
    offs = _ball_offsets(radius / vs)
    ijk0 = np.round((np.asarray(centers) - origin) / vs).astype(np.int64)
    ijk = (ijk0[:, None, :] + offs[None, :, :]).reshape(-1, 3)
    ijk = np.unique(ijk, axis=0)
    ok = np.all((ijk >= 0) & (ijk < np.array(labels.shape)), axis=1)
    i, j, k = ijk[ok].T
    if allowed is not None:
        sel = np.isin(labels[i, j, k], np.asarray(allowed, dtype=labels.dtype))
        i, j, k = i[sel], j[sel], k[sel]
    labels[i, j, k] = value


def _polyline(points: np.ndarray, step: float) -> np.ndarray:
    """Resamples a polyline to about ``step`` spacing."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0], np.cumsum(seg)])
    t = np.linspace(0, s[-1], max(2, int(s[-1] / step) + 1))
    return np.column_stack([np.interp(t, s, points[:, k]) for k in range(3)])


def _build_labels(lay: _Layout, voxel_size: float, margin: float, progress: bool) -> LabelVolume:
    prm, t, vs = lay.prm, lay.torso, voxel_size
    tp = prm.torso
    L = prm.kidney.length
    y_lo = lay.p_c[1] - L / 2 - margin
    y_hi = lay.p_c[1] + L / 2 + margin
    if hasattr(lay.shape, "label_codes"):  # a given kidney: its own extent along y
        y_lo = min(y_lo, float(lay.outer_vertices_Bd[:, 1].min()) - margin)
        y_hi = max(y_hi, float(lay.outer_vertices_Bd[:, 1].max()) + margin)
    ys_probe = np.linspace(y_lo, y_hi, 50)
    A, Zc, Bt = t.section(ys_probe)
    x_max = float(A.max()) + 0.005
    z_max = float((Zc + Bt).max()) + 0.005
    origin = np.array([-x_max, y_lo, -0.003])
    shape = (
        int(np.ceil(2 * x_max / vs)) + 1,
        int(np.ceil((y_hi - y_lo) / vs)) + 1,
        int(np.ceil((z_max + 0.003) / vs)) + 1,
    )
    labels = np.zeros(shape, dtype=np.uint8)
    xs = origin[0] + vs * np.arange(shape[0])
    zs = origin[2] + vs * np.arange(shape[2])
    wall = tp.fat + tp.muscle
    back_fat = 0.8 * tp.fat
    z_vb = back_fat + VERTEBRAL_BODY_Z  # vertebral body centre (modelling choice)
    # Liver: right upper quadrant, over the anterior surface of the right kidney's upper pole.
    y_up_right = (lay.p_c[1] if prm.side == "right" else lay.p_c[1] - 0.027) + L / 2
    lo = prm.liver_offset
    liver_c = np.array(
        [-0.055 + lo[0], y_up_right + 0.045 + lo[1], lay.kidney_top_z + 0.055 + lo[2]]
    )
    liver_r = np.array([0.105, 0.090, 0.068])
    gas = []
    for k, (dx, dy, dz, r) in enumerate(prm.gas):
        if k == 0:  # colonic flexure: anterior, medial and inferior to the lower pole
            c = np.array([lay.p_c[0] - lay.s * dx, lay.p_c[1] - L / 2 + dy, lay.kidney_top_z + dz])
        else:  # small bowel gas in the anterior mid-abdomen
            c = np.array([lay.s * (0.02 - dx) + lay.s * 0.06, -0.02 + dy, dz + 0.06])
        gas.append((c, r))
    chunk = 8
    it = range(0, shape[1], chunk)
    if progress:
        it = tqdm(it, desc=f"labels seed:{prm.seed}", unit="slab", leave=False)
    for j0 in it:
        j1 = min(shape[1], j0 + chunk)
        yv = origin[1] + vs * np.arange(j0, j1)
        X, Y, Z = np.meshgrid(xs, yv, zs, indexing="ij")
        lab = np.zeros(X.shape, dtype=np.uint8)
        lab[t.inside(X, Y, Z)] = Label.FAT
        lab[t.inside(X, Y, Z, inset=tp.fat)] = Label.MUSCLE
        cavity = t.inside(X, Y, Z, inset=wall)
        lab[cavity] = Label.SOFT_TISSUE
        # Back muscles (erector spinae, quadratus lumborum) and psoas.
        for sx in (-1, 1):
            es = ((X - sx * 0.042) / 0.032) ** 2 + ((Z - back_fat - 0.036) / 0.030) ** 2 <= 1
            ql = ((X - sx * 0.078) / 0.022) ** 2 + ((Z - back_fat - 0.030) / 0.013) ** 2 <= 1
            r_ps = 0.010 + 0.12 * np.clip(-Y, 0, 0.1)
            ps = ((X - sx * 0.040) ** 2 + (Z - z_vb) ** 2) <= r_ps**2
            lab[cavity & (es | ql | ps)] = Label.MUSCLE
        # Spine: vertebral body and posterior arch.
        vb = (X / VERTEBRAL_BODY_SEMI_AXES[0]) ** 2 + (
            (Z - z_vb) / VERTEBRAL_BODY_SEMI_AXES[1]
        ) ** 2 <= 1
        arch = (np.abs(X) <= 0.010) & (Z >= back_fat + 0.012) & (Z <= z_vb - 0.014)
        lab[vb | (arch & (lab > 0))] = Label.BONE
        # Great vessels: aorta left-anterior of the spine, IVC right-anterior.
        ao = (X - 0.018) ** 2 + (Z - z_vb - 0.030) ** 2 <= 0.011**2
        ivc = ((X + 0.024) / 0.013) ** 2 + ((Z - z_vb - 0.027) / 0.009) ** 2 <= 1
        lab[cavity & (ao | ivc)] = Label.VESSEL
        liv = (
            ((X - liver_c[0]) / liver_r[0]) ** 2
            + ((Y - liver_c[1]) / liver_r[1]) ** 2
            + ((Z - liver_c[2]) / liver_r[2]) ** 2
        ) <= 1
        lab[liv & (lab == Label.SOFT_TISSUE)] = Label.LIVER
        for c, r in gas:
            g = (X - c[0]) ** 2 + (Y - c[1]) ** 2 + (Z - c[2]) ** 2 <= r**2
            lab[g & (lab == Label.SOFT_TISSUE)] = Label.GAS
        labels[:, j0:j1, :] = lab
    # Ribs 10-12 on both sides: tubes along the inset outline, descending laterally.
    for sx in (-1.0, 1.0):
        for name, y0, span, drop, radius in prm.ribs:
            th = np.linspace(-np.pi / 2 + 0.25, -np.pi / 2 + 0.25 + span, 200)
            u = (th - th[0]) / (th[-1] - th[0])
            yy = y0 - drop * u**1.2
            pts = np.vstack(
                [
                    t.outline_point(yy[i], th[i], sx, inset=tp.fat + 0.5 * tp.muscle)
                    for i in range(len(th))
                ]
            )
            _stamp(
                labels,
                origin,
                vs,
                _polyline(pts, 0.5 * vs),
                radius,
                Label.BONE,
                allowed=[Label.FAT, Label.MUSCLE, Label.SOFT_TISSUE, Label.LIVER],
            )
    # Renal vein: hilum -> IVC at the hilum's level.
    h = lay.R_BdL @ lay.shape.hilum_point() + lay.p_BdL
    ivc = np.array([-0.024, h[1], z_vb + 0.027])
    _stamp(
        labels,
        origin,
        vs,
        _polyline(np.vstack([h, ivc]), 0.5 * vs),
        0.005,
        Label.VESSEL,
        allowed=[Label.SOFT_TISSUE, Label.FAT, Label.MUSCLE],
    )
    # Kidney with perirenal fat (Gerota's fascia, modelling choice 7 mm) and sub-labels.
    v = lay.outer_vertices_Bd
    lo_i = np.maximum(np.floor((v.min(axis=0) - 0.012 - origin) / vs).astype(int), 0)
    hi_i = np.minimum(
        np.ceil((v.max(axis=0) + 0.012 - origin) / vs).astype(int) + 1, np.array(shape)
    )
    ii, jj, kk = np.meshgrid(*[np.arange(lo_i[a], hi_i[a]) for a in range(3)], indexing="ij")
    P = origin + vs * np.column_stack([ii.ravel(), jj.ravel(), kk.ravel()])
    sub = labels[lo_i[0] : hi_i[0], lo_i[1] : hi_i[1], lo_i[2] : hi_i[2]].reshape(-1)
    carved = [Label.SOFT_TISSUE, Label.LIVER, Label.MUSCLE, Label.GAS, Label.VESSEL]
    if hasattr(lay.shape, "label_codes"):
        # A given kidney labels its own region (sub-labels, tumour) and its perirenal zone;
        # everything in the kidney is overwritten (organs carved, bone never reached: the
        # placement keeps it off the spine).
        codes, peri_zone = lay.shape.label_codes(lay.L_from_Bd(P))
        sub[peri_zone & np.isin(sub, carved)] = Label.FAT
        sub[codes > 0] = codes[codes > 0]
    else:
        f, depth, d = lay.shape.level(lay.L_from_Bd(P), return_direction=True)
        peri = (depth > -0.007) & np.isin(sub, carved)
        sub[peri] = Label.FAT
        kid = f <= 1.0
        kp = prm.kidney
        cortex = depth < kp.cortex_thickness
        sinus = depth >= kp.parenchyma_thickness
        pyramids = (np.cos(4.0 * np.pi * d[:, 0]) > -0.35) & (np.abs(d[:, 2]) < 0.85)
        sub[kid] = Label.KIDNEY_CORTEX
        sub[kid & ~cortex & ~sinus & pyramids] = Label.KIDNEY_MEDULLA
        sub[kid & sinus] = Label.KIDNEY_SINUS
    labels[lo_i[0] : hi_i[0], lo_i[1] : hi_i[1], lo_i[2] : hi_i[2]] = sub.reshape(ii.shape)
    X_PtV = _X_PtBd(lay).multiply(RigidTransform(origin))
    return LabelVolume(labels=labels, voxel_size=vs, X_PtV=X_PtV)


def _X_PtBd(lay: _Layout) -> RigidTransform:
    prm = lay.prm
    if prm.posture == "supine":
        return RigidTransform()
    A, Zc, _ = lay.torso.section(lay.p_c[1])
    # Left lateral decubitus: roll onto the left side (frames.R_PtBd), the section's centre
    # above the origin, the left flank on the bed.
    return RigidTransform(RotationMatrix(R_PtBd(prm.posture)), [-float(Zc), 0.0, float(A)])


def _kidney_mask_builder(lay: _Layout, X_PtBd: RigidTransform):
    def build(voxel_size: float):
        R = X_PtBd.rotation().matrix()
        v_Pt = lay.kidney_vertices_Bd @ R.T + X_PtBd.translation()
        lo = v_Pt.min(axis=0) - 3 * voxel_size
        shape = np.ceil((v_Pt.max(axis=0) + 3 * voxel_size - lo) / voxel_size).astype(int) + 1
        ii, jj, kk = np.meshgrid(*[np.arange(n) for n in shape], indexing="ij")
        P_Pt = lo + voxel_size * np.column_stack([ii.ravel(), jj.ravel(), kk.ravel()])
        P_Bd = (P_Pt - X_PtBd.translation()) @ R
        mask = lay.inside_kidney_Bd(P_Bd).reshape(tuple(shape))
        return mask, RigidTransform(lo)

    return build


def _builders(layout, voxel_size: float, margin: float, progress: bool) -> dict:
    """The lazily built parts of a generated patient (Patient's label, torso and kidney mask
    builders) from ``layout()``, which returns the patient's :class:`_Layout`."""

    def label_builder():
        return _build_labels(layout(), voxel_size, margin, progress)

    def torso_builder(half_length):
        lay = layout()
        y_c = float(lay.p_c[1])
        m = lay.torso.mesh(y_c - half_length, y_c + half_length, spacing=0.01, n_points=96)
        return transform_mesh(m, _X_PtBd(lay))

    def kidney_mask_builder(vs):
        lay = layout()
        return _kidney_mask_builder(lay, _X_PtBd(lay))(vs)

    return {
        "label_builder": label_builder,
        "torso_builder": torso_builder,
        "kidney_mask_builder": kidney_mask_builder,
    }


def patient_builders(
    seed: int,
    side: str = "right",
    posture: str = "supine",
    *,
    voxel_size: float = 0.001,
    margin: float = 0.07,
    progress: bool = True,
) -> dict:
    """The builders (``label_builder``, ``torso_builder``, ``kidney_mask_builder``) that
    :func:`generate_patient` gives its Patient, for a Patient rebuilt from stored meshes (the
    patient cache): the body layout is recomputed from the seed on first use (about 30 ms)."""
    _check_seed(seed)
    check_side_posture(side, posture)
    holder = []

    def layout():
        if not holder:
            holder.append(_Layout(sample_patient_params(seed, side, posture)))
        return holder[0]

    return _builders(layout, voxel_size, margin, progress)


def generate_patient(
    seed: int,
    side: str = "right",
    posture: str = "supine",
    *,
    name: str | None = None,
    voxel_size: float = 0.001,
    margin: float = 0.07,
    progress: bool = True,
) -> Patient:
    """The virtual patient of ``seed`` (deterministic). The label volume (``voxel_size``
    voxels, covering the torso cross-section and the kidney's length plus ``margin`` on each
    side along the body) is built on first access of ``patient.labels``."""
    prm = sample_patient_params(seed, side, posture)
    lay = _Layout(prm)
    X_PtBd = _X_PtBd(lay)
    kidney_Bd = trimesh.Trimesh(lay.kidney_vertices_Bd, lay.shape.mesh.faces, process=False)
    kidney = transform_mesh(kidney_Bd, X_PtBd)
    skin = transform_mesh(lay.torso.mesh(spacing=0.01, n_points=128), X_PtBd)
    X_PtK = mesh_canonical_frame(kidney, *reference_axes_Pt(side, posture))
    patient_X_PtK_x = X_PtK.rotation().matrix()[:, 0]
    meta = {
        "source": "generator",
        "seed": int(seed),
        "size_class": prm.torso.size_class,
        "hilum_angle": lay.hilum_angle_measured(X_PtBd.rotation().matrix().T @ patient_X_PtK_x),
        "params": prm.to_dict(),
        "centroid_x_final": lay.centroid_x,
        "X_PtBd": X_PtBd.GetAsMatrix4().tolist(),
        "hilum_vertex": lay.shape.hilum_vertex(),
    }
    return Patient(
        name=name or f"seed:{seed}",
        side=side,
        posture=posture,
        kidney_mesh=kidney,
        skin_mesh=skin,
        meta=meta,
        X_PtK=X_PtK,
        **_builders(lambda: lay, voxel_size, margin, progress),
    )


def generate_patient_with_kidney(
    prm: PatientParams,
    shape,
    *,
    R_BdL=None,
    name: str,
    voxel_size: float = 0.001,
    margin: float = 0.07,
    progress: bool = True,
    meta: dict | None = None,
) -> Patient:
    """The generated body of ``prm`` (e.g. :func:`sample_patient_params`) carrying a given
    kidney ``shape`` (see :class:`_Layout`; e.g. a real CT kidney,
    :mod:`drake_rus.anatomy.ct_patient`) instead of its own: placed at the body's kidney
    position (craniocaudal level, distance from the midline, posterior gap) with the body's
    depth, oriented by ``R_BdL`` (default: the sampled angles), kept off the spine, and the
    organs it overlaps carved (perirenal fat, then the kidney's own labels).

    The true pose ``X_PtK`` is the canonical frame of ``shape.mesh`` as placed. The torso
    section and the kidney mask are the Patient defaults (from the meshes), so the patient
    rebuilt from its cached meshes is the same; ``meta`` is added to the patient's meta."""
    check_side_posture(prm.side, prm.posture)
    lay = _Layout(prm, shape=shape, R_BdL=R_BdL)
    X_PtBd = _X_PtBd(lay)
    kidney_Bd = trimesh.Trimesh(lay.kidney_vertices_Bd, shape.mesh.faces, process=False)
    kidney = transform_mesh(kidney_Bd, X_PtBd)
    skin = transform_mesh(lay.torso.mesh(spacing=0.01, n_points=128), X_PtBd)
    X_PtK = mesh_canonical_frame(kidney, *reference_axes_Pt(prm.side, prm.posture))
    x_k_Bd = X_PtBd.rotation().matrix().T @ X_PtK.rotation().matrix()[:, 0]
    info = {
        "source": "generator+kidney",
        "seed": int(prm.seed),
        "size_class": prm.torso.size_class,
        "hilum_angle": lay.hilum_angle_measured(x_k_Bd),
        "params": prm.to_dict(),
        "centroid_x_final": lay.centroid_x,
        "X_PtBd": X_PtBd.GetAsMatrix4().tolist(),
        **(meta or {}),
    }
    label_builder = _builders(lambda: lay, voxel_size, margin, progress)["label_builder"]
    return Patient(
        name=name,
        side=prm.side,
        posture=prm.posture,
        kidney_mesh=kidney,
        skin_mesh=skin,
        meta=info,
        X_PtK=X_PtK,
        label_builder=label_builder,
        torso_center_Pt=X_PtBd.multiply(lay.p_c),
    )
