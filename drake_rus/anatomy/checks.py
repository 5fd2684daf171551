"""Anatomy that can exist: the checks every patient passes before a simulation uses it.

:func:`check_anatomy` is called by :func:`drake_rus.anatomy.load_patient` on every patient,
generated or imported, fresh or from the cache. It measures (figures in SI units):

- the kidney's size: length, width, thickness and volume (its canonical frame, eq. 13-14);
- the body's size: width (left-right) and depth (anteroposterior) of the skin's
  cross-section through the kidney's centroid;
- the kidney inside the body: the share of the voxels around the kidney (a one-voxel shell
  of the label volume) that is air (label 0, outside the skin);
- the kidney wholly inside the label volume: kidney voxels on the volume's border (the
  kidney is cut there, and the imaged part is all a scan could find);
- the kidney not inside another organ: the share of the shell that is one organ (liver,
  bone, vessel, gas) and, where the patient has a liver mesh, the kidney volume inside it;
- the kidney's depth below the skin: vertical (what a probe above it looks through) and
  shortest distance.

Each figure has a range (:data:`ANATOMY_RANGES`): the published values of
``docs/facts/anatomy_and_ultrasound.md`` ("Checks on every patient") with a wide margin: the
checks refuse what cannot be a human body (a unit mistake, a kidney cut in half or lying in
the liver or in air), not an unusual one. The first failed check raises
:class:`AnatomyError`, one line naming the patient (spec or file) and the check with its
figure.

The same rules also run inside the importers on the raw inputs, before their heavy work:
:func:`check_mesh_units` (kidney and skin mesh in one unit) and
:func:`check_label_map_body_size` (a label map's spacing gives a human-sized body).
"""

from __future__ import annotations

import numpy as np
from pydrake.math import RigidTransform
from scipy import ndimage

from drake_rus.anatomy.canonical_frame import extents_in_frame
from drake_rus.anatomy.frames import R_PtBd
from drake_rus.anatomy.labels import Label, LabelVolume, is_kidney
from drake_rus.anatomy.rasterize import rasterize_mesh

__all__ = [
    "AnatomyError",
    "ANATOMY_RANGES",
    "AIR_CONTACT_MAX",
    "ORGAN_ENCLOSURE_MAX",
    "ORGAN_OVERLAP_MAX",
    "check_anatomy",
    "anatomy_figures",
    "kidney_surroundings",
    "body_section_size",
    "check_mesh_units",
    "check_label_map_body_size",
    "describe_patient",
]


class AnatomyError(ValueError):
    """A patient whose anatomy cannot exist; the message names the patient and the check."""


# Figure -> (min, max, unit shown, scale from SI to the unit, why). Published values:
# docs/facts/anatomy_and_ultrasound.md, section "Checks on every patient".
ANATOMY_RANGES = {
    "kidney_length": (
        0.050,
        0.250,
        "mm",
        1e3,
        "adult kidneys are 108.5 +- 12.2 mm long (Glodny 2009); tumour "
        "kidneys of KiTS19 reach about 200 mm",
    ),
    "kidney_width": (
        0.025,
        0.180,
        "mm",
        1e3,
        "adult kidneys are 58 mm wide, 10-90th percentile 51-64 mm (Emamian 1993)",
    ),
    "kidney_thickness": (0.015, 0.160, "mm", 1e3, "adult kidneys are about 30-45 mm thick"),
    "kidney_volume": (
        20e-6,
        1500e-6,
        "ml",
        1e6,
        "adult kidneys hold 129 +- 30 ml (Lee 1996); tumour kidneys of KiTS19 up to about 1 l",
    ),
    "body_width": (
        0.180,
        0.800,
        "mm",
        1e3,
        "adult trunks at the kidneys are about 260-380 mm wide",
    ),
    "body_depth": (
        0.120,
        0.600,
        "mm",
        1e3,
        "adult trunks at the kidneys are about 180-300 mm deep (sagittal "
        "abdominal diameter under 25 cm at normal weight, over 30 cm in "
        "obesity)",
    ),
    "depth_vertical": (
        0.015,
        0.320,
        "mm",
        1e3,
        "CT skin-to-kidney distances are 78-108 mm on average with SDs of "
        "12-30 mm (lithotripsy series)",
    ),
    "depth_min": (
        0.008,
        0.300,
        "mm",
        1e3,
        "skin, subcutaneous fat and the muscle wall lie between the kidney and the skin",
    ),
}

# The kidney inside the body: at most this share of the voxels around it may be air (the
# voxelised surfaces of skin and kidney may touch at a voxel or two).
AIR_CONTACT_MAX = 0.002
# The kidney not inside another organ: at most this share of the voxels around it may be
# one organ (the liver covers the right kidney's upper pole; the Visible Human female's
# liver takes 9% of the shell around her right kidney).
ORGAN_ENCLOSURE_MAX = 0.5
# ... and at most this share of its volume may lie inside another organ's mesh (two organs
# segmented separately overlap by a voxel at their contact).
ORGAN_OVERLAP_MAX = 0.05
_ORGANS = {Label.LIVER: "liver", Label.BONE: "bone", Label.VESSEL: "vessel", Label.GAS: "gas"}
_INSIDE = {
    Label.LIVER: "the liver",
    Label.BONE: "bone",
    Label.VESSEL: "a vessel",
    Label.GAS: "bowel gas",
}


def describe_patient(patient) -> str:
    """The patient as a user named it: the spec, or the files it was read from."""
    meta = patient.meta
    if meta.get("source") in ("label_map", "mask_folder"):
        return f"{patient.name} ({meta.get('path')})"
    return patient.name


def _fail(patient, what: str | None, text: str):
    raise AnatomyError(f"patient {what or describe_patient(patient)}: {text}")


def _check_range(patient, what, key: str, value: float, label: str, extra: str = ""):
    lo, hi, unit, scale, why = ANATOMY_RANGES[key]
    if not (np.isfinite(value) and lo <= value <= hi):
        shown = f"{value * scale:.4g}" if np.isfinite(value) else "not measurable"
        _fail(
            patient,
            what,
            f"{label} {shown} {unit} is outside {lo * scale:g}-{hi * scale:g} "
            f"{unit} ({why}){extra}",
        )


# --- pure measurements ---------------------------------------------------------------------
def body_section_size(skin_mesh, point_Pt, posture: str) -> tuple[float, float]:
    """(width, depth) in m of the skin's cross-section at the level (y_Pt) of ``point_Pt``:
    its extent along the body's left-right (x_Bd) and anteroposterior (z_Bd) axes. The loop
    that contains the point is measured (else the largest): the trunk, not an arm."""
    p = np.asarray(point_Pt, dtype=float)
    sec = skin_mesh.section(plane_origin=[0.0, p[1], 0.0], plane_normal=[0.0, 1.0, 0.0])
    if sec is None:
        return 0.0, 0.0
    R = R_PtBd(posture)
    best = None
    for e in sec.entities:
        pts = sec.vertices[e.points]
        if len(pts) < 3:
            continue
        xz = pts[:, [0, 2]]
        area = abs(0.5 * np.sum(xz[:-1, 0] * xz[1:, 1] - xz[1:, 0] * xz[:-1, 1]))
        inside = _point_in_polygon(xz, (p[0], p[2]))
        key = (inside, area if not inside else -area)  # the smallest loop containing p
        if best is None or key > best[0]:
            best = (key, pts)
    if best is None:
        return 0.0, 0.0
    p_Bd = best[1] @ R  # rows: R^T p_Pt
    return float(np.ptp(p_Bd[:, 0])), float(np.ptp(p_Bd[:, 2]))


def _point_in_polygon(xz: np.ndarray, q) -> bool:
    x, z = xz[:, 0], xz[:, 1]
    x2, z2 = np.roll(x, -1), np.roll(z, -1)
    cross = (z > q[1]) != (z2 > q[1])
    with np.errstate(divide="ignore", invalid="ignore"):
        xi = x + (q[1] - z) * (x2 - x) / (z2 - z)
    return bool(np.count_nonzero(cross & (q[0] < xi)) % 2)


_FACE_NAMES = {
    (0, 1): "left",
    (0, -1): "right",
    (1, 1): "superior",
    (1, -1): "inferior",
    (2, 1): "anterior",
    (2, -1): "posterior",
}


def kidney_surroundings(volume: LabelVolume, bounds_Pt, R_BdPt=None, margin: float = 0.02) -> dict:
    """What lies around the target kidney in a label volume: the kidney component nearest to
    the centre of ``bounds_Pt`` (lo, hi corners in Pt of the kidney, e.g. its mesh's bounds;
    only the grid within ``margin`` of them is read). Returns ``voxels`` and ``volume``
    (m^3) of the kidney, ``shell`` (voxels one step outside it, inside the grid), ``air`` and
    ``organs`` ({label: share of the shell}), ``border_voxels`` (its voxels on the grid's
    faces), ``border_area`` (m^2) and ``border_faces`` (anatomical names of those faces,
    given ``R_BdPt``)."""
    lab = volume.labels
    vs = float(volume.voxel_size)
    shape = np.array(lab.shape)
    lo_Pt, hi_Pt = (np.asarray(b, dtype=float) for b in bounds_Pt)
    corners = np.array(
        [
            [x, y, z]
            for x in (lo_Pt[0], hi_Pt[0])
            for y in (lo_Pt[1], hi_Pt[1])
            for z in (lo_Pt[2], hi_Pt[2])
        ]
    )
    c_V = volume.X_PtV.inverse().multiply(corners.T).T / vs
    m = margin / vs
    lo = np.clip(np.floor(c_V.min(axis=0) - m).astype(int), 0, shape)
    hi = np.clip(np.ceil(c_V.max(axis=0) + m).astype(int) + 1, 0, shape)
    empty = {
        "voxels": 0,
        "volume": 0.0,
        "shell": 0,
        "air": 0.0,
        "organs": {},
        "border_voxels": 0,
        "border_area": 0.0,
        "border_faces": [],
    }
    if np.any(hi <= lo):
        return empty
    box = tuple(slice(a, b) for a, b in zip(lo, hi))
    sub = lab[box]
    kid_all = is_kidney(sub)
    idx = np.argwhere(kid_all)
    if len(idx) == 0:
        return empty
    # The component nearest to the centre (the other kidney may be in the volume too).
    comp, _ = ndimage.label(kid_all)
    centre = c_V.mean(axis=0) - lo
    nearest = idx[np.argmin(((idx - centre) ** 2).sum(axis=1))]
    kid = comp == comp[tuple(nearest)]
    shell = ndimage.binary_dilation(kid) & ~kid
    n_shell = int(shell.sum())
    counts = np.bincount(sub[shell].astype(np.int64), minlength=int(max(Label)) + 1)
    share = counts / max(n_shell, 1)
    organs = {Label(v): float(share[v]) for v in _ORGANS if share[v] > 0}
    # Kidney voxels on the faces of the whole grid (the box reaches a face only there).
    border = np.zeros(6, dtype=np.int64)
    for axis in range(3):
        for end, at_face in ((0, lo[axis] == 0), (1, hi[axis] == shape[axis])):
            if at_face:
                face = [slice(None)] * 3
                face[axis] = -1 if end else 0
                border[2 * axis + end] = int(kid[tuple(face)].sum())
    faces = []
    if R_BdPt is not None:
        R_BdV = np.asarray(R_BdPt) @ volume.X_PtV.rotation().matrix()
        for f in np.nonzero(border)[0]:
            axis, end = divmod(int(f), 2)
            n_Bd = R_BdV[:, axis] * (1.0 if end else -1.0)
            a = int(np.argmax(np.abs(n_Bd)))
            faces.append(_FACE_NAMES[(a, 1 if n_Bd[a] > 0 else -1)])
    return {
        "voxels": int(kid.sum()),
        "volume": float(kid.sum()) * vs**3,
        "shell": n_shell,
        "air": float(share[Label.OUTSIDE]),
        "organs": organs,
        "border_voxels": int(border.sum()),
        "border_area": float(border.sum()) * vs**2,
        "border_faces": faces,
    }


def mesh_overlap(kidney_mesh, organ_mesh, voxel_size: float = 0.002) -> float:
    """Share of the kidney's volume inside ``organ_mesh`` (both watertight, one frame): both
    rasterised on a grid around the kidney."""
    lo = kidney_mesh.bounds[0] - voxel_size
    hi = kidney_mesh.bounds[1] + voxel_size
    shape = np.ceil((hi - lo) / voxel_size).astype(int) + 1
    X = RigidTransform(lo)
    k = rasterize_mesh(kidney_mesh, shape, X, voxel_size)
    if not k.any():
        return 0.0
    o = rasterize_mesh(organ_mesh, shape, X, voxel_size)
    return float((k & o).sum() / k.sum())


# --- checks on raw inputs (importers) ------------------------------------------------------
# Largest extents (m) of a kidney, of a body (a torso section at least, a whole body at
# most) and of a liver, and how many times a kidney's each may be: the unit a mesh is in is
# read from these (ANATOMY_RANGES, with margin; the liver: about 150-200 mm across).
_EXTENTS = {"kidney": (0.03, 0.30), "skin": (0.15, 2.6), "liver": (0.06, 0.45)}
_RATIO_TO_KIDNEY = {"skin": (1.5, 60.0), "liver": (0.4, 10.0)}


def _unit_guess(extent: float, expected: tuple) -> str | None:
    for name, scale in (("mm", 1e-3), ("m", 1.0), ("cm", 1e-2)):
        if expected[0] <= extent * scale <= expected[1]:
            return name
    return None


def check_mesh_units(
    kidney_extent: float,
    other_extent: float,
    kidney_file: str,
    other_file: str,
    scale: float,
    units: str,
    other: str = "skin",
) -> None:
    """Refuses a kidney mesh and the ``other`` mesh ("skin" or "liver") in different units
    (a kidney 1000 times smaller or larger than the body, or a body the size of a kidney),
    naming the files and the unit each seems to be in; meshes in one unit that ``units``
    reads wrongly (mm read as m, or cm) are refused naming the unit they seem to be in.
    Extents are the meshes' largest extent in file units; ``scale`` is the file-unit -> m
    factor chosen for ``units``."""
    k_m, o_m = kidney_extent * scale, other_extent * scale
    ratio = other_extent / kidney_extent if kidney_extent > 0 else float("inf")
    lo_r, hi_r = _RATIO_TO_KIDNEY[other]
    if (
        lo_r <= ratio <= hi_r
        and _EXTENTS["kidney"][0] <= k_m <= _EXTENTS["kidney"][1]
        and _EXTENTS[other][0] <= o_m <= _EXTENTS[other][1]
    ):
        return
    k_unit = _unit_guess(kidney_extent, _EXTENTS["kidney"])
    o_unit = _unit_guess(other_extent, _EXTENTS[other])
    if lo_r <= ratio <= hi_r:
        # One unit for both (their ratio is human): the unit read is wrong, not the files.
        fix = {"mm": "units='mm' or 'auto'", "m": "units='m' or 'auto'"}.get(
            k_unit, "give the meshes in mm or m"
        )
        seems = f"; the meshes seem to be in {k_unit}: {fix}" if k_unit else ""
        raise AnatomyError(
            f"kidney mesh {kidney_file}: {kidney_extent:.4g} across (file units), which "
            f"units={units!r} reads as {k_m:.4g} m, a kidney is "
            f"{_EXTENTS['kidney'][0] * 1e3:g}-{_EXTENTS['kidney'][1] * 1e3:g} mm (the {other} "
            f"mesh {other_file} is in the same unit: {ratio:.3g} times the kidney){seems}"
        )
    seems = []
    if k_unit:
        seems.append(f"the kidney mesh seems to be in {k_unit}")
    if o_unit:
        seems.append(f"the {other} mesh in {o_unit}")
    hint = ("; " + " and ".join(seems) + "; give all meshes in one unit") if seems else ""
    what = "a body" if other == "skin" else "a liver"
    raise AnatomyError(
        f"{other} mesh {other_file}: {other_extent:.4g} across against the kidney mesh "
        f"{kidney_file}'s {kidney_extent:.4g} (file units): {ratio:.3g} times the kidney, "
        f"{what} is {lo_r:g}-{hi_r:g} times (units={units!r} reads them as {o_m:.4g} m and "
        f"{k_m:.4g} m){hint}"
    )


def check_label_map_body_size(body: np.ndarray, spacing_mm, sup_axis: int, path) -> None:
    """Refuses a label map whose voxel spacing makes a body of other than human size: the
    body mask's extent across (the two grid axes other than ``sup_axis``) and along the body,
    at the file's spacing, before any resampling."""
    idx = np.argwhere(body)
    if len(idx) == 0:
        return
    ext = (np.ptp(idx, axis=0) + 1) * np.asarray(spacing_mm, dtype=float) / 1000.0
    across = [float(ext[a]) for a in range(3) if a != sup_axis]
    width, depth = max(across), min(across)
    length = float(ext[sup_axis])
    shown = ", ".join(f"{s:g}" for s in spacing_mm)
    lo_w, hi_w, _, _, why_w = ANATOMY_RANGES["body_width"]
    lo_d, hi_d, _, _, _ = ANATOMY_RANGES["body_depth"]
    problems = []
    if not lo_w <= width <= hi_w:
        problems.append(f"{width * 1e3:.4g} mm wide (expected {lo_w * 1e3:g}-{hi_w * 1e3:g} mm)")
    elif not lo_d <= depth <= hi_d:
        problems.append(f"{depth * 1e3:.4g} mm deep (expected {lo_d * 1e3:g}-{hi_d * 1e3:g} mm)")
    elif length > _EXTENTS["skin"][1]:
        problems.append(
            f"{length * 1e3:.4g} mm long (a body is at most {_EXTENTS['skin'][1] * 1e3:g} mm)"
        )
    if problems:
        raise AnatomyError(
            f"label map {path}: with its voxel spacing ({shown}) mm the body is "
            f"{problems[0]}; {why_w}: is the spacing in mm?"
        )


# --- the check of a patient ----------------------------------------------------------------
def anatomy_figures(patient, what: str | None = None) -> dict:
    """Measures and checks ``patient`` (see the module doc); returns the figures (SI), or
    raises :class:`AnatomyError` at the first check that fails."""
    fig = {}
    # Sizes first: a unit mistake shows here, and would break the measurements below. The
    # body first: a wrong scale of the whole patient (a label map's spacing) is named so.
    centroid = patient.kidney_mesh.vertices.mean(axis=0)
    width, depth = body_section_size(patient.skin_mesh, centroid, patient.posture)
    fig["body_width"], fig["body_depth"] = width, depth
    spacing = patient.meta.get("spacing_mm")
    hint = (
        (f"; the label map's voxel spacing is {', '.join(f'{s:g}' for s in spacing)} mm")
        if spacing
        else ""
    )
    _check_range(
        patient, what, "body_width", width, "body width (left-right, at the kidney's level)", hint
    )
    _check_range(
        patient,
        what,
        "body_depth",
        depth,
        "body depth (front to back, at the kidney's level)",
        hint,
    )
    ext = extents_in_frame(patient.kidney_mesh.vertices, patient.X_PtK)
    fig["kidney_length"], fig["kidney_width"], fig["kidney_thickness"] = map(float, ext)
    fig["kidney_volume"] = float(patient.kidney_mesh.volume)
    _check_range(patient, what, "kidney_length", fig["kidney_length"], "kidney length")
    _check_range(patient, what, "kidney_volume", fig["kidney_volume"], "kidney volume")
    _check_range(patient, what, "kidney_width", fig["kidney_width"], "kidney width")
    _check_range(patient, what, "kidney_thickness", fig["kidney_thickness"], "kidney thickness")
    # The label volume: air and organs around the kidney, the volume's border.
    sur = kidney_surroundings(patient.labels, patient.kidney_mesh.bounds, R_PtBd(patient.posture).T)
    fig["kidney_air_contact"] = sur["air"]
    fig["kidney_border_voxels"] = sur["border_voxels"]
    fig["kidney_imaged_volume"] = sur["volume"]
    fig["kidney_organ_contact"] = {_ORGANS[k]: round(v, 4) for k, v in sur["organs"].items()}
    if sur["voxels"] == 0:
        _fail(patient, what, "no kidney voxel in the label volume")
    if sur["air"] > AIR_CONTACT_MAX:
        _fail(
            patient,
            what,
            f"the kidney is not inside the body: {sur['air']:.1%} of the voxels around it "
            f"are air, outside the skin (at most {AIR_CONTACT_MAX:.1%}); check the "
            f"kidney's position and the files' axes",
        )
    if sur["border_voxels"] > 0:
        faces = "/".join(dict.fromkeys(sur["border_faces"])) or "a"
        _fail(
            patient,
            what,
            f"the kidney is cut by the label volume's edge: {sur['border_voxels']} kidney "
            f"voxels ({sur['border_area'] * 1e4:.3g} cm2) lie on its {faces} face, only "
            f"{sur['volume'] * 1e6:.0f} ml of the kidney is imaged (a whole kidney holds "
            f"129 +- 30 ml, Lee 1996); use a volume that contains the whole kidney",
        )
    for label, share in sorted(sur["organs"].items(), key=lambda kv: -kv[1]):
        if share > ORGAN_ENCLOSURE_MAX:
            _fail(
                patient,
                what,
                f"the kidney lies inside {_INSIDE[label]}: {share:.0%} of the voxels around "
                f"it are {_ORGANS[label]} (at most {ORGAN_ENCLOSURE_MAX:.0%}; a kidney "
                f"lies in the retroperitoneum, in its own fat)",
            )
    if patient.liver_mesh is not None:
        overlap = mesh_overlap(patient.kidney_mesh, patient.liver_mesh)
        fig["kidney_in_liver_mesh"] = overlap
        if overlap > ORGAN_OVERLAP_MAX:
            src = patient.meta.get("liver") or "the liver mesh"
            _fail(
                patient,
                what,
                f"the kidney overlaps the liver: {overlap:.0%} of its volume "
                f"({overlap * fig['kidney_volume'] * 1e6:.0f} ml) lies inside {src} "
                f"(at most {ORGAN_OVERLAP_MAX:.0%})",
            )
    m = patient.metrics()
    fig["depth_vertical"], fig["depth_min"] = float(m["depth_vertical"]), float(m["depth_min"])
    _check_range(patient, what, "depth_min", fig["depth_min"], "shortest skin-to-kidney distance")
    _check_range(
        patient, what, "depth_vertical", fig["depth_vertical"], "kidney depth below the upper skin"
    )
    return fig


def check_anatomy(patient, what: str | None = None) -> dict:
    """Checks that ``patient`` can exist (module doc) before any simulation; ``what`` names
    it in the error (default: its name and file). Returns the figures (SI); raises
    :class:`AnatomyError`, one line, at the first failed check. The figures are kept in
    ``patient.anatomy_figures``: a patient is checked once."""
    if getattr(patient, "anatomy_figures", None) is not None:
        return patient.anatomy_figures
    fig = anatomy_figures(patient, what)
    patient.anatomy_figures = fig
    return fig
