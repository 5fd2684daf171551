"""Real CT kidneys from KiTS-style label maps: the patient frame from anatomy, one or both
kidneys with their tumours.

A KiTS-style label map holds 0 (background), 1 (kidney) and 2 (tumour) on a CT voxel grid
(NIfTI, NRRD, anything SimpleITK reads). Its header's direction matrix is not a reliable
patient frame (the KiTS19 issue tracker, neheller/kits19#9), so the frame is established
from anatomy, each cue stated and checked against the others (docs/real_kidneys.md):

Grid frame G: the label array's axes as numpy gives them (``SimpleITK.GetArrayFromImage``:
ITK index order reversed), in mm (index times spacing). Anatomical frame A: the body frame's
axes (:mod:`drake_rus.anatomy.frames`: x_A left, y_A superior, z_A anterior) with the grid's
origin, so ``p_A = R_AG p_G`` with ``R_AG`` a signed permutation: the CT's own axes are the
body's axes (an axial CT of a supine patient), and the kidneys keep their real tilt.

Which grid axis is which:

- *slice axis*: of an axial CT, the axis whose spacing and size differ from the other two
  (equal in-plane) is superior-inferior (abstains when no axis stands out);
- *long axes*: the kidneys' long (first principal) axes run mostly craniocaudally (15-20 deg
  off in the coronal plane; Acta Radiol 1961: from "dorsal, cranial and medial" to "ventral,
  caudal and lateral"): the grid axis nearest to their mean is superior-inferior;
- *separation*: two kidneys lie either side of the spine: the axis along which their
  centroids differ most (after superior-inferior) is right-left;
- *field of view* (one kidney only): a kidney's centroid lies further from the field of
  view's centre right-left (about 75 mm from the midline) than anteroposteriorly.

Which way each points (each kidney votes separately):

- *poles medial*: upper poles medial, lower poles lateral: along its long axis each kidney
  moves laterally towards the feet (superior-inferior sign);
- *poles posterior*: upper poles posterior, lower poles anterior (sagittal tilt): couples
  the superior-inferior and anteroposterior signs;
- *hilum*: the hilum faces anteromedially, about 42 deg above the horizontal (Sakate
  2009); it is found as the largest concavity of the kidney surface (convex hull minus
  kidney and tumour), and is only used when it lies medially (anteroposterior sign);
- *posterior half*: retroperitoneal kidneys lie in the posterior half of a field of view
  centred on the body (anteroposterior sign; abstains within 10 mm of the centre).

Right-left then follows from the chirality of the voxel grid: with superior and anterior
set, left = superior x anterior in a right-handed grid, reversed in a left-handed one. The
grid's handedness is the sign of the header's direction-matrix determinant (a permuted or
mirrored array written with a matching header keeps it; the direction's axis labels are not
used). A per-case check is impossible from kidney labels alone; the dataset-level check is
the published right-kidney-lower statistic (McClellan 1956: the left kidney was lower in
7.1% of 1,500 urograms; :func:`right_lower_statistic`).

A kidney whose tumour is at least as large as its parenchyma does not vote on axes or
signs (its shape no longer follows normal anatomy). A case whose sign cues disagree gets
status ``conflict`` (the majority decides, the disagreeing cues are listed as a warning); a
tie, or an undetermined axis, is an error.
Errors name the file in one line: unreadable, no kidney labels, labels other than 0/1/2,
the requested kidney missing, a kidney cut by the field of view. A kidney that reaches
the border only with the tip of a closing pole (``CLOSING_POLE_MAX_SHARE``) is whole.
"""

from __future__ import annotations

import gzip
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from pydrake.math import RigidTransform
from scipy import ndimage

from drake_rus.anatomy.rasterize import rasterize_mesh

__all__ = [
    "KIDNEY_VALUE",
    "TUMOUR_VALUE",
    "LabelGrid",
    "KidneyComponent",
    "FrameEstimate",
    "CTKidneys",
    "read_label_grid",
    "kidney_components",
    "pole_closes_on_border",
    "CLOSING_POLE_MAX_SHARE",
    "estimate_frame",
    "import_ct_kidneys",
    "select_kidney",
    "kidney_fields_A",
    "KidneyFields",
    "right_lower_statistic",
    "largest_concavity",
    "concavities",
    "survey_case",
    "survey_summary",
    "MIN_KIDNEY_ML",
    "LEVEL_TOLERANCE_MM",
]

KIDNEY_VALUE = 1
TUMOUR_VALUE = 2
# A connected component of kidney/tumour labels smaller than this is a fragment, not a
# kidney (adult kidneys: 129 +- 30 mL, Lee 1996; 20 mL lies beyond 3 SD).
MIN_KIDNEY_ML = 20.0
# A kidney whose tumour is at least this large relative to its parenchyma is distorted: its
# axes and concavities no longer follow normal anatomy, so it does not vote on the frame
# (its centroid still counts).
DISTORTED_TUMOUR_RATIO = 1.0
# Tumour-only components of at least this volume join the nearest kidney (a tumour whose
# contact with its kidney the segmentation left open).
MIN_TUMOUR_ML = 0.5
# Kidneys whose centroids differ by less than this along superior-inferior are "level"
# (modelling choice: about a third of a vertebral body).
LEVEL_TOLERANCE_MM = 10.0
# A kidney on the volume's border is whole when its section in the border plane is the tip
# of a closing pole: at most this share of its largest section parallel to that face, and
# at most half the section one voxel inside (shrinking at that rate, the sections close
# within one more voxel, so what lies outside is under half a voxel layer of the border
# section). A pole cut across its body, or a kidney cut lengthwise, fails both.
CLOSING_POLE_MAX_SHARE = 0.10
# Thresholds below which a sign cue abstains (modelling choices, well inside the published
# angles: coronal 15-20 deg, hilum 40-45 deg above the horizontal).
_MIN_TILT_DEG = 3.0
_MIN_HILUM_ELEVATION_DEG = 10.0
_MIN_POSTERIOR_MM = 10.0
_MIN_HILUM_ML = 1.0
_HILUM_GRID_MM = 2.0
# Two in-plane axes are "equal" when spacing and size agree within this relative tolerance.
_SAME_SPACING = 0.01
_SI, _LR, _AP = "superior-inferior", "right-left", "anterior-posterior"


def _fail(msg: str):
    raise ValueError(msg)


# --- reading -----------------------------------------------------------------------------
@dataclass
class LabelGrid:
    """A label map as read: ``labels`` (uint8, numpy axis order), ``spacing`` (mm, per
    array axis), ``handedness`` (+1/-1: the chirality of the array axes in the patient, from
    the sign of the header's direction-matrix determinant) and where it came from."""

    labels: np.ndarray
    spacing: np.ndarray
    handedness: int
    source: str = "array"
    # What the header's direction matrix claims (anatomical from grid axes, rounded to a
    # signed permutation): reported beside the anatomical frame, never used for it.
    header_R_AG: np.ndarray | None = None


def _nifti_payload_end(header: bytes) -> int | None:
    """The byte where a NIfTI-1 or NIfTI-2 file's voxels end (vox_offset + voxels x bytes),
    from its first 540 bytes; None when they are no NIfTI header."""
    for order in "<>":
        if len(header) >= 348 and struct.unpack(order + "i", header[:4])[0] == 348:
            dims = struct.unpack(order + "8h", header[40:56])
            bitpix = struct.unpack(order + "h", header[72:74])[0]
            offset = int(struct.unpack(order + "f", header[108:112])[0])
        elif len(header) >= 540 and struct.unpack(order + "i", header[:4])[0] == 540:
            bitpix = struct.unpack(order + "h", header[14:16])[0]
            dims = struct.unpack(order + "8q", header[16:80])
            offset = struct.unpack(order + "q", header[168:176])[0]
        else:
            continue
        n = 1
        for d in dims[1 : 1 + max(0, min(int(dims[0]), 7))]:
            n *= max(int(d), 1)
        return offset + n * max(int(bitpix), 0) // 8
    return None


def check_complete(path: Path) -> None:
    """Refuses a label map file cut short (an interrupted copy or download), which SimpleITK
    reads without complaint, the missing voxels as background (a half kidney would pass as
    whole): a gzip stream that ends early, or a NIfTI file (plain or gzipped) shorter than
    its header says. Raises ValueError naming the file."""
    path = Path(path)
    where = f"label map {path}"
    name = path.name.lower()
    if not (name.endswith(".gz") or name.endswith(".nii")):
        return
    if name.endswith(".gz"):
        with open(path, "rb") as f:
            if f.read(2) != b"\x1f\x8b":
                return  # no gzip stream at all: SimpleITK's own error says so
    try:
        if name.endswith(".gz"):
            with gzip.open(path, "rb") as f:
                header = f.read(540)
                size = len(header)
                while chunk := f.read(1 << 22):
                    size += len(chunk)
        else:
            with open(path, "rb") as f:
                header = f.read(540)
            size = path.stat().st_size
    except (EOFError, OSError, zlib.error) as e:
        _fail(f"{where}: the file is truncated or corrupt ({e}); copy it again")
    end = _nifti_payload_end(header) if ".nii" in name else None
    if end is not None and size < end:
        _fail(
            f"{where}: the file is truncated: its header promises {end} bytes, it holds "
            f"{size}; copy it again"
        )


def read_label_image(path: Path):
    """The SimpleITK image of a label map file (any SimpleITK-readable 3-D file, one label
    per voxel). A missing, unreadable, truncated (:func:`check_complete`), non-3-D or
    multi-component file raises an error naming the file (FileNotFoundError, ValueError)."""
    import SimpleITK as sitk

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"label map: file not found: {path}")
    where = f"label map {path}"
    check_complete(path)
    try:
        img = sitk.ReadImage(str(path))
    except Exception as e:
        _fail(f"{where}: cannot read it ({(str(e).strip().splitlines() or ['?'])[-1].strip()})")
    if img.GetDimension() != 3:
        _fail(f"{where}: expected a 3-D image, got {img.GetDimension()}-D")
    if img.GetNumberOfComponentsPerPixel() != 1:
        _fail(
            f"{where}: expected one label per voxel, got "
            f"{img.GetNumberOfComponentsPerPixel()} components"
        )
    return img


def read_label_grid(path) -> LabelGrid:
    """Reads a KiTS-style label map (any SimpleITK-readable 3-D file). Errors name the file."""
    import SimpleITK as sitk

    path = Path(path)
    where = f"label map {path}"
    img = read_label_image(path)
    spacing = np.array(img.GetSpacing(), dtype=float)[::-1]
    if not (np.all(np.isfinite(spacing)) and np.all(spacing > 0)):
        _fail(f"{where}: voxel spacing {tuple(spacing[::-1])} is not positive")
    D = np.array(img.GetDirection(), dtype=float).reshape(3, 3)
    det = float(np.linalg.det(D))
    if not abs(abs(det) - 1.0) < 1e-3:
        _fail(f"{where}: the direction matrix is not orthonormal (determinant {det:.3g})")
    # numpy order reverses the ITK index order: a swap of the first and last axes, which
    # flips the handedness.
    handedness = -1 if det > 0 else 1
    # A copy: a view would outlive the image's buffer.
    labels = _as_label_array(sitk.GetArrayFromImage(img), where)
    # Header claim: ITK index axes in LPS (columns of D), numpy order, in A (L, S, A).
    R_A_LPS = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
    M = R_A_LPS @ D[:, ::-1]
    header = np.zeros((3, 3))
    for g in range(3):
        a = int(np.argmax(np.abs(M[:, g])))
        header[a, g] = np.sign(M[a, g])
    return LabelGrid(
        labels=labels,
        spacing=spacing,
        handedness=handedness,
        source=str(path),
        header_R_AG=header if abs(abs(np.linalg.det(header)) - 1) < 1e-9 else None,
    )


def _as_label_array(a: np.ndarray, where: str) -> np.ndarray:
    if a.dtype != np.uint8:
        if not np.issubdtype(a.dtype, np.integer):
            if not np.all(np.isfinite(a)) or np.any(a != np.round(a)):
                _fail(f"{where}: voxel values are not integer labels (dtype {a.dtype})")
        lo, hi = float(a.min()), float(a.max())
        if lo < 0 or hi > 255:
            _fail(
                f"{where}: labels other than 0/1/2 (found values {lo:g} to {hi:g}); "
                "expected a KiTS-style map: 0 background, 1 kidney, 2 tumour"
            )
        a = a.astype(np.uint8)
    high = a > TUMOUR_VALUE
    other = (
        [int(v) for v in np.flatnonzero(np.bincount(a[high], minlength=256))] if high.any() else []
    )
    if other:
        shown = ", ".join(str(v) for v in other[:6]) + (", ..." if len(other) > 6 else "")
        _fail(
            f"{where}: labels other than 0/1/2 (found {shown}); expected a KiTS-style map: "
            "0 background, 1 kidney, 2 tumour"
        )
    if not a.any():
        _fail(f"{where}: no kidney labels (no voxel is 1 or 2)")
    return a


# --- kidneys ------------------------------------------------------------------------------
@dataclass
class KidneyComponent:
    """One kidney: a connected component of labels 1|2 with its tumour, cropped from the
    grid. ``labels`` (uint8, 0 outside this kidney) starts at voxel ``lo`` of the full grid;
    ``touches``: the grid faces that cut it ("axis 0 low", ...), i.e. cut by the field of
    view; ``pole_on_border``: the faces it reaches only with the tip of a closing pole
    (:func:`pole_closes_on_border`: whole, not cut)."""

    labels: np.ndarray
    lo: np.ndarray
    spacing: np.ndarray
    touches: list = field(default_factory=list)
    pole_on_border: list = field(default_factory=list)
    side: str | None = None

    @property
    def voxel_ml(self) -> float:
        return float(np.prod(self.spacing)) / 1000.0

    @property
    def parenchyma_ml(self) -> float:
        return float((self.labels == KIDNEY_VALUE).sum()) * self.voxel_ml

    @property
    def tumour_ml(self) -> float:
        return float((self.labels == TUMOUR_VALUE).sum()) * self.voxel_ml

    def points_G(self, which: str = "parenchyma") -> np.ndarray:
        """Voxel centres (N, 3) in G (mm) of the parenchyma, the tumour or both ("all")."""
        if which == "parenchyma":
            m = self.labels == KIDNEY_VALUE
            if m.sum() < 10:  # a kidney replaced by its tumour: use everything
                m = self.labels > 0
        elif which == "tumour":
            m = self.labels == TUMOUR_VALUE
        else:
            m = self.labels > 0
        return (np.argwhere(m) + self.lo) * self.spacing

    def principal_axes(self):
        """Centroid (G, mm), eigenvalues (descending) and eigenvectors (columns) of the
        parenchyma's voxel centres."""
        p = self.points_G("parenchyma")
        c = p.mean(axis=0)
        C = np.cov((p - c).T)
        w, V = np.linalg.eigh(C)
        order = np.argsort(w)[::-1]
        return c, w[order], V[:, order]


def pole_closes_on_border(sections) -> bool:
    """True when a kidney's sections parallel to a border face (voxel counts, inside out:
    the border plane's last) end in the tip of a closing pole (``CLOSING_POLE_MAX_SHARE``)."""
    a = np.asarray(sections, dtype=float)
    if a.size < 2 or a.max() <= 0:
        return False
    return bool(a[-1] <= CLOSING_POLE_MAX_SHARE * a.max() and 2.0 * a[-1] <= a[-2])


def kidney_components(grid: LabelGrid) -> tuple[list[KidneyComponent], dict]:
    """The kidneys of a label grid (components of labels 1|2 of at least ``MIN_KIDNEY_ML``,
    26-connected; tumour-only components joined to the nearest kidney) and what was left
    out: ``{"fragments": n, "fragments_ml": v}``."""
    a = grid.labels
    nz = [np.flatnonzero(a.any(axis=tuple(x for x in range(3) if x != ax))) for ax in range(3)]
    lo = np.array([n[0] for n in nz])
    hi = np.array([n[-1] + 1 for n in nz])
    sub = a[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
    comp, n = ndimage.label(sub > 0, structure=np.ones((3, 3, 3), dtype=bool))
    voxel_ml = float(np.prod(grid.spacing)) / 1000.0
    sizes = np.bincount(comp.ravel(), minlength=n + 1)
    kid_counts = np.bincount(comp.ravel(), weights=(sub == KIDNEY_VALUE).ravel(), minlength=n + 1)
    slices = ndimage.find_objects(comp)
    kidneys, tumours, left_out = [], [], [0, 0.0]
    for k in range(1, n + 1):
        ml = sizes[k] * voxel_ml
        if ml >= MIN_KIDNEY_ML and kid_counts[k] > 0:
            kidneys.append(k)
        elif kid_counts[k] == 0 and ml >= MIN_TUMOUR_ML:
            tumours.append(k)
        else:
            left_out[0] += 1
            left_out[1] += ml
    if not kidneys:
        _fail(
            f"label map {grid.source}: no kidney labels (no connected kidney of at least "
            f"{MIN_KIDNEY_ML:g} mL; {n} fragment(s), {sizes[1:].sum() * voxel_ml:.1f} mL)"
        )
    centroids = {}
    for k in kidneys + tumours if tumours else []:
        box = slices[k - 1]
        idx = np.argwhere(comp[box] == k).mean(axis=0) + [s.start for s in box]
        centroids[k] = (idx + lo) * grid.spacing
    owner = {k: k for k in kidneys}
    for t in tumours:
        owner[t] = min(kidneys, key=lambda k: np.linalg.norm(centroids[k] - centroids[t]))
    out = []
    for k in kidneys:
        members = [m for m, o in owner.items() if o == k]
        b_lo = np.min([[s.start for s in slices[m - 1]] for m in members], axis=0)
        b_hi = np.max([[s.stop for s in slices[m - 1]] for m in members], axis=0)
        box = tuple(slice(int(b_lo[i]), int(b_hi[i])) for i in range(3))
        keep = np.isin(comp[box], members)
        labels = np.where(keep, sub[box], 0).astype(np.uint8)
        g_lo = lo + b_lo
        g_hi = lo + b_hi
        touches, poles = [], []
        for ax in range(3):
            for end, hit in (("low", g_lo[ax] == 0), ("high", g_hi[ax] == a.shape[ax])):
                if not hit:
                    continue
                sections = (labels > 0).sum(axis=tuple(x for x in range(3) if x != ax))
                closes = pole_closes_on_border(sections if end == "high" else sections[::-1])
                (poles if closes else touches).append(f"axis {ax} {end}")
        out.append(
            KidneyComponent(
                labels=labels,
                lo=g_lo,
                spacing=grid.spacing.copy(),
                touches=touches,
                pole_on_border=poles,
            )
        )
    out.sort(key=lambda c: -(c.labels > 0).sum())
    extra = {"fragments": left_out[0], "fragments_ml": round(left_out[1], 2)}
    if len(out) > 2:
        extra["extra_kidney_components"] = len(out) - 2
        extra["extra_kidney_ml"] = round(
            sum(float((c.labels > 0).sum()) * c.voxel_ml for c in out[2:]), 1
        )
        out = out[:2]
    return out, extra


# --- the frame ------------------------------------------------------------------------------
@dataclass
class FrameEstimate:
    """The patient frame of a label grid.

    ``R_AG``: anatomical axes (x left, y superior, z anterior) from grid axes (a signed
    permutation); ``axes``: the grid axis of each anatomical direction; ``cues``: one dict
    per cue and kidney ({"cue", "kidney", "verdict": agrees/disagrees/abstains, "value",
    "note"}); ``status``: "agree" (no cue disagrees) or "conflict" (the majority decided;
    ``conflicts`` lists the disagreeing cues); ``sides``: "right"/"left" per kidney."""

    R_AG: np.ndarray
    axes: dict
    cues: list
    status: str
    conflicts: list
    sides: list
    handedness: int

    def summary(self) -> dict:
        counts = {}
        for c in self.cues:
            counts.setdefault(c["cue"], {"agrees": 0, "disagrees": 0, "abstains": 0})
            counts[c["cue"]][c["verdict"]] += 1
        return {
            "status": self.status,
            "axes": self.axes,
            "sides": self.sides,
            "cues": counts,
            "conflicts": self.conflicts,
        }


def _unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def largest_concavity(hull_of: np.ndarray, solid: np.ndarray, spacing):
    """The largest concavity of a shape: the largest connected part (after a one-voxel
    opening) of the convex hull of ``hull_of``'s voxels minus ``solid`` (both boolean, same
    grid of ``spacing`` mm). Returns (centroid as fractional voxel index, volume mL), or
    (None, 0.0)."""
    found = concavities(hull_of, solid, spacing)
    return found[0] if found else (None, 0.0)


def concavities(hull_of: np.ndarray, solid: np.ndarray, spacing) -> list:
    """The concavities of :func:`largest_concavity`, largest first: [(centroid as
    fractional voxel index, volume mL), ...]."""
    from scipy.spatial import ConvexHull, QhullError

    sp = np.asarray(spacing, dtype=float)
    edge = hull_of & ~ndimage.binary_erosion(hull_of)
    # The hull in index units (an affine image of the hull in mm), rasterised by ray parity.
    hp = np.argwhere(edge).astype(float)
    if len(hp) < 8:
        return []
    try:
        hull = ConvexHull(hp)
    except QhullError:
        return []
    lo = hp.min(axis=0).astype(int)
    hi = hp.max(axis=0).astype(int) + 1
    box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi))
    mesh = trimesh.Trimesh(hp - lo, hull.simplices, process=False)
    trimesh.repair.fix_normals(mesh)
    inside = rasterize_mesh(mesh, tuple(hi - lo), RigidTransform(), 1.0)
    deficit = inside & ~solid[box]
    deficit = ndimage.binary_opening(deficit)
    lab, n = ndimage.label(deficit)
    if n == 0:
        return []
    sizes = np.bincount(lab.ravel())[1:]
    centres = ndimage.center_of_mass(deficit, lab, range(1, n + 1))
    voxel_ml = float(np.prod(sp)) / 1000.0
    return [
        (np.asarray(centres[i]) + lo, float(sizes[i]) * voxel_ml) for i in np.argsort(sizes)[::-1]
    ]


def _hilum_direction(k: KidneyComponent, c: np.ndarray, v1: np.ndarray):
    """Direction (G, unit, perpendicular to the long axis ``v1``) from the parenchyma
    centroid ``c`` to the kidney's largest concavity (convex hull of the parenchyma minus
    kidney and tumour, on a grid of about ``_HILUM_GRID_MM``), and that concavity's volume
    (mL); (None, volume) when there is none of at least ``_MIN_HILUM_ML``."""
    par = k.labels == KIDNEY_VALUE
    if par.sum() < 50:
        return None, 0.0
    step = np.maximum(1, np.round(_HILUM_GRID_MM / k.spacing).astype(int))
    par_s = par[:: step[0], :: step[1], :: step[2]]
    solid_s = (k.labels > 0)[:: step[0], :: step[1], :: step[2]]
    sp = k.spacing * step
    centroid, ml = largest_concavity(par_s, solid_s, sp)
    if centroid is None or ml < _MIN_HILUM_ML:
        return None, ml
    h = centroid * sp + k.lo * k.spacing - c
    h = h - (h @ v1) * v1
    if np.linalg.norm(h) < 1e-6:
        return None, ml
    return _unit(h), ml


def _vote(cues, cue, kidney, value, prediction, note=""):
    """A cue's prediction: a dict of sign constraints ({"S": +1} means the +SI grid axis is
    superior; {"SA": +1} means the S and A signs are equal), or None (abstains)."""
    cues.append(
        {"cue": cue, "kidney": kidney, "value": value, "prediction": prediction, "note": note}
    )


def estimate_frame(
    components: list[KidneyComponent], shape, spacing, handedness: int, source: str = "label map"
) -> FrameEstimate:
    """The anatomical frame of a grid of ``shape`` and ``spacing`` (mm) holding the kidney
    ``components``; ``handedness`` is the grid's chirality in the patient (+1: right-handed).
    Pure: no file is read. Raises ValueError (naming ``source``) when an axis cannot be
    determined or the sign cues tie."""
    shape = np.asarray(shape)
    spacing = np.asarray(spacing, dtype=float)
    if handedness not in (1, -1):
        raise ValueError(f"handedness: expected +1 or -1, got {handedness}")
    ks = list(components)
    pcs = [k.principal_axes() for k in ks]
    cents = [p[0] for p in pcs]
    v1s = [p[2][:, 0] for p in pcs]
    cues: list[dict] = []
    axis_notes: list[dict] = []

    # 1. Superior-inferior axis.
    slice_axis = None
    for ax in range(3):
        o = [b for b in range(3) if b != ax]
        same = (
            abs(spacing[o[0]] - spacing[o[1]]) <= _SAME_SPACING * spacing[o].max()
            and shape[o[0]] == shape[o[1]]
        )
        differs = (
            abs(spacing[ax] - spacing[o[0]]) > _SAME_SPACING * spacing[o].max()
            or shape[ax] != shape[o[0]]
        )
        if same and differs:
            slice_axis = ax
    distorted = [k.tumour_ml >= DISTORTED_TUMOUR_RATIO * k.parenchyma_ml for k in ks]
    voters = [i for i in range(len(ks)) if not distorted[i]] or list(range(len(ks)))
    mean_abs = np.mean([np.abs(v1s[i]) for i in voters], axis=0)
    order = np.argsort(mean_abs)[::-1]
    long_axis = int(order[0]) if mean_abs[order[0]] - mean_abs[order[1]] >= 0.2 else None
    axis_notes.append(
        {
            "cue": "slice axis",
            "axis": slice_axis,
            "note": (
                "odd spacing/size: "
                + ", ".join(f"{spacing[a]:.2f} mm x {shape[a]}" for a in range(3))
            ),
        }
    )
    axis_notes.append(
        {
            "cue": "long axes",
            "axis": long_axis,
            "note": "mean |long axis| per grid axis " + ", ".join(f"{m:.2f}" for m in mean_abs),
        }
    )
    if slice_axis is not None and long_axis is not None and slice_axis != long_axis:
        _fail(
            f"{source}: superior-inferior axis undetermined: the slice axis is grid axis "
            f"{slice_axis} but the kidneys' long axes run along grid axis {long_axis} "
            "(a coronal or sagittal acquisition, a horseshoe kidney?)"
        )
    si = slice_axis if slice_axis is not None else long_axis
    if si is None:
        _fail(
            f"{source}: superior-inferior axis undetermined: no slice axis (isotropic "
            f"grid) and the kidneys' long axes are oblique "
            f"({', '.join(f'{m:.2f}' for m in mean_abs)})"
        )

    # 2. Right-left axis among the other two.
    rest = [a for a in range(3) if a != si]
    centre = (shape - 1) * spacing / 2.0
    if len(ks) == 2:
        d = np.abs(cents[0] - cents[1])
        lr = rest[int(np.argmax(d[rest]))]
        axis_notes.append(
            {
                "cue": "separation",
                "axis": lr,
                "note": f"centroids {d[rest[0]]:.0f} / {d[rest[1]]:.0f} mm apart "
                f"along grid axes {rest[0]} / {rest[1]}",
            }
        )
        if d[lr] < 1.5 * d[[a for a in rest if a != lr][0]] or d[lr] < 40.0:
            _fail(
                f"{source}: right-left axis undetermined: the two kidneys lie "
                f"{d[rest[0]]:.0f} and {d[rest[1]]:.0f} mm apart along grid axes "
                f"{rest[0]} and {rest[1]}"
            )
        midline = 0.5 * (cents[0] + cents[1])
    else:
        off = np.abs(cents[0] - centre)
        lr = rest[int(np.argmax(off[rest]))]
        axis_notes.append(
            {
                "cue": "field of view",
                "axis": lr,
                "note": f"one kidney {off[rest[0]]:.0f} / {off[rest[1]]:.0f} mm "
                f"from the centre along grid axes {rest[0]} / {rest[1]}",
            }
        )
        midline = centre.copy()
    ap = [a for a in rest if a != lr][0]

    # 3. Signs. Predictions as constraints on sS (+1: +SI grid axis is superior) and sA
    # (+1: +AP grid axis is anterior).
    names = [f"kidney {i}" for i in range(len(ks))]
    for i, k in enumerate(ks):
        if distorted[i]:
            for cue in ("poles medial", "poles posterior", "hilum"):
                _vote(
                    cues,
                    cue,
                    names[i],
                    None,
                    None,
                    f"distorted by its tumour ({k.tumour_ml:.0f} mL, parenchyma "
                    f"{k.parenchyma_ml:.0f} mL)",
                )
            continue
        v = v1s[i] * (1.0 if v1s[i][si] >= 0 else -1.0)  # oriented along +SI grid
        lat = 1.0 if cents[i][lr] - midline[lr] >= 0 else -1.0  # +LR grid is lateral?
        if len(ks) == 1 and abs(cents[i][lr] - midline[lr]) < 20.0:
            lat = 0.0
        coronal = np.degrees(np.arctan2(abs(v[lr]), v[si]))
        sagittal = np.degrees(np.arctan2(abs(v[ap]), v[si]))
        # Poles medial: moving along +SI the axis goes lateral -> +SI is inferior.
        slope = lat * v[lr]
        if lat == 0.0 or coronal < _MIN_TILT_DEG:
            _vote(
                cues,
                "poles medial",
                names[i],
                round(float(coronal), 1),
                None,
                "coronal tilt too small or kidney on the midline",
            )
        else:
            _vote(
                cues,
                "poles medial",
                names[i],
                round(float(coronal), 1),
                {"S": -1 if slope > 0 else 1},
            )
        # Poles posterior: superior is posterior: sS * v[ap] * sA < 0.
        if sagittal < _MIN_TILT_DEG:
            _vote(
                cues,
                "poles posterior",
                names[i],
                round(float(sagittal), 1),
                None,
                "sagittal tilt too small",
            )
        else:
            _vote(
                cues,
                "poles posterior",
                names[i],
                round(float(sagittal), 1),
                {"SA": -1 if v[ap] > 0 else 1},
            )
        # Hilum: anteromedial.
        h, h_ml = _hilum_direction(k, cents[i], _unit(v1s[i]))
        if h is None:
            _vote(cues, "hilum", names[i], None, None, f"no concavity found ({h_ml:.1f} mL)")
        else:
            medial = -lat * h[lr] if lat != 0.0 else 0.0
            elev = np.degrees(np.arctan2(abs(h[ap]), max(medial, 1e-9)))
            if lat != 0.0 and medial <= 0:
                _vote(
                    cues,
                    "hilum",
                    names[i],
                    round(float(h_ml), 1),
                    None,
                    "largest concavity is not medial (not the hilum)",
                )
            elif lat != 0.0 and elev < _MIN_HILUM_ELEVATION_DEG:
                _vote(
                    cues, "hilum", names[i], round(float(elev), 1), None, "hilum nearly horizontal"
                )
            else:
                _vote(
                    cues,
                    "hilum",
                    names[i],
                    round(float(elev), 1) if lat else None,
                    {"A": 1 if h[ap] > 0 else -1},
                    f"concavity {h_ml:.1f} mL",
                )
    off_ap = float(np.mean([c[ap] for c in cents]) - centre[ap])
    if abs(off_ap) < _MIN_POSTERIOR_MM:
        _vote(
            cues,
            "posterior half",
            "all",
            round(off_ap, 1),
            None,
            "kidneys near the field of view's centre",
        )
    else:
        _vote(cues, "posterior half", "all", round(off_ap, 1), {"A": -1 if off_ap > 0 else 1})

    def agrees(pred, sS, sA):
        val = {"S": sS, "A": sA, "SA": sS * sA}
        return all(val[key] == s for key, s in pred.items())

    scores = {}
    for sS in (1, -1):
        for sA in (1, -1):
            scores[(sS, sA)] = sum(
                (1 if agrees(c["prediction"], sS, sA) else -1)
                for c in cues
                if c["prediction"] is not None
            )
    ranked = sorted(scores.items(), key=lambda kv: -kv[1])
    (best, s_best), (_, s_next) = ranked[0], ranked[1]
    if s_best == s_next:

        def support(h):
            return ", ".join(
                f"{c['cue']} ({c['kidney']})"
                for c in cues
                if c["prediction"] is not None and agrees(c["prediction"], *h)
            )

        (h1, _), (h2, _) = ranked[0], ranked[1]
        _fail(
            f"{source}: patient frame undetermined: the anatomical cues tie between "
            f"superior {'+' if h1[0] > 0 else '-'}{si}/anterior {'+' if h1[1] > 0 else '-'}{ap} "
            f"({support(h1) or 'none'}) and superior {'+' if h2[0] > 0 else '-'}{si}/anterior "
            f"{'+' if h2[1] > 0 else '-'}{ap} ({support(h2) or 'none'})"
        )
    sS, sA = best
    conflicts = []
    for c in cues:
        pred = c.pop("prediction")
        if pred is None:
            c["verdict"] = "abstains"
        elif agrees(pred, sS, sA):
            c["verdict"] = "agrees"
        else:
            c["verdict"] = "disagrees"
            conflicts.append(f"{c['cue']} ({c['kidney']})")
    e_S = np.zeros(3)
    e_S[si] = sS
    e_A = np.zeros(3)
    e_A[ap] = sA
    e_L = handedness * np.cross(e_S, e_A)
    R_GA = np.column_stack([e_L, e_S, e_A])  # columns: anatomical axes in G
    R_AG = R_GA.T
    sides = []
    for c in cents:
        x = (c - midline) @ e_L
        sides.append("left" if x > 0 else "right")
    if len(ks) == 2 and sides[0] == sides[1]:
        _fail(f"{source}: both kidneys on one side of the midline")
    decided = {"slice axis": si, "long axes": si, "separation": lr, "field of view": lr}
    for note in axis_notes[::-1]:
        verdict = (
            "abstains"
            if note["axis"] is None
            else "agrees"
            if note["axis"] == decided[note["cue"]]
            else "disagrees"
        )
        cues.insert(
            0,
            {
                "cue": note["cue"],
                "kidney": "all",
                "value": note["axis"],
                "verdict": verdict,
                "note": note["note"],
            },
        )
    axes = {
        "superior": f"{'+' if sS > 0 else '-'}{si}",
        "anterior": f"{'+' if sA > 0 else '-'}{ap}",
        "left": f"{'+' if e_L[lr] > 0 else '-'}{lr}",
    }
    return FrameEstimate(
        R_AG=R_AG,
        axes=axes,
        cues=cues,
        status="conflict" if conflicts else "agree",
        conflicts=conflicts,
        sides=sides,
        handedness=int(handedness),
    )


# --- a case ------------------------------------------------------------------------------
@dataclass
class CTKidneys:
    """The kidneys of one label map in its established frame."""

    source: str
    grid_shape: tuple
    spacing: np.ndarray
    kidneys: list  # KidneyComponent, with .side set
    frame: FrameEstimate
    extra: dict

    def by_side(self, side: str):
        return next((k for k in self.kidneys if k.side == side), None)

    def right_minus_left_mm(self) -> float | None:
        """Superior-inferior height of the right kidney's parenchyma centroid above the
        left's (mm; negative: the right kidney lies lower); None without both kidneys."""
        right, left = self.by_side("right"), self.by_side("left")
        if right is None or left is None:
            return None
        e_S = self.frame.R_AG[1]
        return float((right.principal_axes()[0] - left.principal_axes()[0]) @ e_S)

    def report(self) -> dict:
        out = {
            "source": self.source,
            "frame": self.frame.summary(),
            "kidneys": [
                {
                    "side": k.side,
                    "parenchyma_ml": round(k.parenchyma_ml, 1),
                    "tumour_ml": round(k.tumour_ml, 1),
                    "cut": k.touches,
                    "pole_on_border": k.pole_on_border,
                }
                for k in self.kidneys
            ],
            **self.extra,
        }
        d = self.right_minus_left_mm()
        if d is not None:
            out["right_minus_left_mm"] = round(d, 1)
        return out


def import_ct_kidneys(grid: LabelGrid) -> CTKidneys:
    """Kidneys and frame of a label grid (see the module docstring)."""
    comps, extra = kidney_components(grid)
    frame = estimate_frame(
        comps, grid.labels.shape, grid.spacing, grid.handedness, source=f"label map {grid.source}"
    )
    for k, s in zip(comps, frame.sides):
        k.side = s
    return CTKidneys(
        source=grid.source,
        grid_shape=tuple(grid.labels.shape),
        spacing=grid.spacing,
        kidneys=comps,
        frame=frame,
        extra=extra,
    )


def select_kidney(case: CTKidneys, side: str) -> KidneyComponent:
    """The ``side`` kidney of a case; errors (naming the file) when it is missing or cut by
    the field of view."""
    if side not in ("right", "left"):
        raise ValueError(f"side: expected 'right' or 'left', got {side!r}")
    k = case.by_side(side)
    if k is None:
        present = ", ".join(x.side for x in case.kidneys)
        _fail(f"label map {case.source}: no {side} kidney (found: {present}; after a nephrectomy?)")
    if k.touches:
        _fail(
            f"label map {case.source}: the {side} kidney is cut by the field of view "
            f"(kidney voxels on the volume's border, more than a pole's closing tip: "
            f"{', '.join(k.touches)})"
        )
    return k


def right_lower_statistic(differences_mm, tolerance_mm: float = LEVEL_TOLERANCE_MM) -> dict:
    """Counts of cases whose right kidney lies lower / level / higher than the left, from
    the right-minus-left heights (mm), and the right-lower share of the non-level cases
    (published: about 93%, McClellan 1956)."""
    d = np.asarray([x for x in differences_mm if x is not None], dtype=float)
    lower = int((d < -tolerance_mm).sum())
    higher = int((d > tolerance_mm).sum())
    level = int(len(d) - lower - higher)
    share = lower / (lower + higher) if lower + higher else None
    return {
        "cases": int(len(d)),
        "right_lower": lower,
        "level": level,
        "right_higher": higher,
        "right_lower_share_of_unequal": None if share is None else round(share, 3),
        "median_right_minus_left_mm": None if len(d) == 0 else round(float(np.median(d)), 1),
        "tolerance_mm": tolerance_mm,
    }


# --- resampling into the anatomical frame -----------------------------------------------------
@dataclass
class KidneyFields:
    """A kidney on an isotropic grid in A (origin ``origin_A`` (m), ``voxel`` (m), axes of
    A): the signed distance (m, > 0 inside) to the surface of kidney and tumour
    (``sdf_union``) and the tumour label of the nearest CT voxel (``tumour``, bool)."""

    origin_A: np.ndarray
    voxel: float
    sdf_union: np.ndarray
    tumour: np.ndarray

    def points_A(self, ijk) -> np.ndarray:
        return self.origin_A + self.voxel * np.asarray(ijk, dtype=float)


def _sdf(mask: np.ndarray, spacing) -> np.ndarray:
    """Signed distance (same unit as ``spacing``; > 0 inside) between voxel centres and the
    mask boundary: linear interpolation puts its zero half-way between an inside and an
    outside voxel."""
    inside = ndimage.distance_transform_edt(mask, sampling=spacing)
    outside = ndimage.distance_transform_edt(~mask, sampling=spacing)
    return (inside - outside).astype(np.float32)


def kidney_fields_A(
    k: KidneyComponent,
    frame: FrameEstimate,
    voxel: float = 0.001,
    mirror: bool = False,
    margin: float = 0.004,
) -> KidneyFields:
    """Resamples a kidney into A on an isotropic grid of ``voxel`` (m): the signed distance
    to the kidney+tumour surface is interpolated linearly (shape-based interpolation across
    thick slices; axes sampled finer than half the voxel are thinned first), the tumour
    label by nearest voxel. ``mirror``: reflect through the sagittal plane (x_A -> -x_A),
    to use a left kidney as a right one or vice versa."""
    pad = 2
    stride = np.maximum(1, np.floor(voxel * 1000.0 / (2.0 * k.spacing)).astype(int))
    lab = k.labels[:: stride[0], :: stride[1], :: stride[2]]
    sp_mm = k.spacing * stride
    union = np.pad(lab > 0, pad)
    tumour_G = np.pad(lab == TUMOUR_VALUE, pad)
    sdf_G = _sdf(union, sp_mm)
    lo_G = k.lo * k.spacing - pad * sp_mm  # mm, G, of padded voxel (0,0,0)
    n_G = np.array(union.shape)
    R = frame.R_AG * (np.array([-1.0, 1.0, 1.0])[:, None] if mirror else 1.0)
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)]) * (n_G - 1)
    c_A = (R @ ((corners * sp_mm + lo_G).T)).T / 1000.0
    lo_A = c_A.min(axis=0) - margin
    hi_A = c_A.max(axis=0) + margin
    n_A = np.ceil((hi_A - lo_A) / voxel).astype(int) + 1
    grids = np.meshgrid(*[np.arange(n) for n in n_A], indexing="ij")
    p_A = lo_A + voxel * np.column_stack([g.ravel() for g in grids])
    idx = (((R.T @ (p_A * 1000.0).T).T - lo_G) / sp_mm).T
    far = -float(np.max(n_G * sp_mm))
    sdf = ndimage.map_coordinates(sdf_G, idx, order=1, mode="constant", cval=far)
    tum = ndimage.map_coordinates(tumour_G.astype(np.uint8), idx, order=0, mode="constant", cval=0)
    sdf = (sdf.reshape(tuple(n_A)) / 1000.0).astype(np.float32)
    return KidneyFields(
        origin_A=lo_A, voxel=voxel, sdf_union=sdf, tumour=(tum.reshape(tuple(n_A)) > 0) & (sdf > 0)
    )


# --- surveys of many cases ----------------------------------------------------------------
def survey_case(grid_or_path, extra=None) -> dict:
    """One case's report for a survey: the frame, its cues, the kidneys, per side whether
    the kidney is usable ("ok") or why not, and whether the header's axis labels agree with
    the anatomical frame; ``{"source", "error"}`` when the case cannot be imported.
    ``extra(case)``: more fields from the imported :class:`CTKidneys` (a ValueError becomes
    ``"extra_error"``)."""
    source = getattr(grid_or_path, "source", str(grid_or_path))
    try:
        grid = (
            grid_or_path if isinstance(grid_or_path, LabelGrid) else read_label_grid(grid_or_path)
        )
        case = import_ct_kidneys(grid)
    except (ValueError, FileNotFoundError) as e:
        return {"source": source, "error": str(e)}
    out = case.report()
    if grid.header_R_AG is not None:
        out["header_agrees"] = {
            name: bool(np.allclose(grid.header_R_AG[row], case.frame.R_AG[row]))
            for row, name in enumerate(("left", "superior", "anterior"))
        }
    out["cue_verdicts"] = [
        {k: c[k] for k in ("cue", "kidney", "verdict", "value")} for c in case.frame.cues
    ]
    usable = {}
    for side in ("right", "left"):
        k = case.by_side(side)
        usable[side] = "missing" if k is None else "cut" if k.touches else "ok"
    out["usable"] = usable
    if extra is not None:
        try:
            out.update(extra(case))
        except ValueError as e:
            out["extra_error"] = str(e)
    return out


def survey_summary(rows: list[dict]) -> dict:
    """Totals of :func:`survey_case` rows: statuses, errors, per-cue verdicts, usable
    kidneys per side, the kidneys whole with a pole's tip on the border ("source side:
    faces"), the header's axes against anatomy, and the right-kidney-lower statistic."""
    cues: dict = {}
    status = {"agree": 0, "conflict": 0, "error": 0}
    usable = {s: {"ok": 0, "missing": 0, "cut": 0} for s in ("right", "left")}
    errors, poles = [], []
    header: dict = {}
    for r in rows:
        if "error" in r:
            status["error"] += 1
            errors.append(r["error"])
            continue
        status[r["frame"]["status"]] += 1
        poles.extend(
            f"{r['source']} {k['side']}: {', '.join(k['pole_on_border'])}"
            for k in r.get("kidneys", [])
            if k.get("pole_on_border")
        )
        for c in r["cue_verdicts"]:
            cues.setdefault(c["cue"], {"agrees": 0, "disagrees": 0, "abstains": 0})
            cues[c["cue"]][c["verdict"]] += 1
        for side, u in r["usable"].items():
            usable[side][u] += 1
        for axis, same in r.get("header_agrees", {}).items():
            header.setdefault(axis, {"agrees": 0, "disagrees": 0})
            header[axis]["agrees" if same else "disagrees"] += 1
    return {
        "cases": len(rows),
        "status": status,
        "cues": cues,
        "usable": usable,
        "pole_on_border": poles,
        "errors": errors,
        "header_axes_vs_anatomy": header,
        "right_lower": right_lower_statistic(
            [r.get("right_minus_left_mm") for r in rows if "error" not in r]
        ),
    }
