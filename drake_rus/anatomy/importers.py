"""Real data: patients from surface meshes (STL/OBJ/PLY) or integer label maps (NIfTI/NRRD).

Both routes express everything in the body frame Bd (x left, y superior, z anterior), then
place the patient frame Pt like the generator: origin on the bed surface (the lowest skin
point of the torso cross-section at the kidney centroid's level), under the centre of that
cross-section, at the kidney centroid's level (y_Pt = 0); axes by posture
(:mod:`drake_rus.anatomy.frames`).

Label volumes of mesh patients: skin -> body (soft tissue), a subcutaneous fat layer and a
muscle wall measured in-plane from the skin (modelling choice, 15 mm and 12 mm by default:
real meshes carry no layers), liver, both kidneys; the target kidney's cortex and sinus
sub-labels are set by depth below its surface (Glodny 2009: cortex 6.6 mm, parenchyma
15.4 mm). No ribs or gas: the HuBMAP body has none (its README).

The arms are removed from the body before the posture roll, for both postures
(:mod:`drake_rus.anatomy.trunk`): an arm beside the trunk would otherwise lie over the
right flank in left lateral decubitus and join the contact body's hull. The roll itself is
rigid: organs do not shift under gravity (see :mod:`drake_rus.anatomy.trunk`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from matplotlib.path import Path as MplPath
from pydrake.math import RigidTransform, RotationMatrix
from scipy import ndimage

from drake_rus.anatomy.body_section import crop_body_section
from drake_rus.anatomy.canonical_frame import mesh_surface_moments
from drake_rus.anatomy.checks import (
    AIR_CONTACT_MAX,
    AnatomyError,
    check_label_map_body_size,
    check_mesh_units,
)
from drake_rus.anatomy.ct_kidney import read_label_image
from drake_rus.anatomy.frames import R_BdS, R_PtBd, check_side_posture, transform_mesh
from drake_rus.anatomy.labels import Label, LabelVolume
from drake_rus.anatomy.patient import Patient
from drake_rus.anatomy.rasterize import grid_around, mask_to_mesh, rasterize_mesh
from drake_rus.anatomy.trunk import remove_arms, trunk_mask

# crop_body_section (body_section) and mask_to_mesh (rasterize) are re-exported here.
__all__ = [
    "patient_from_meshes",
    "patient_from_label_map",
    "patient_from_mask_folder",
    "crop_body_section",
    "mask_to_mesh",
    "TOTALSEGMENTATOR_MAPPING",
    "MAPPING_NAMES",
    "find_mesh_files",
    "totalsegmentator_mask_files",
    "LABEL_MAP_SUFFIXES",
    "MESH_SUFFIXES",
]

MESH_SUFFIXES = (".stl", ".obj", ".ply", ".off", ".glb")
LABEL_MAP_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".mha", ".mhd")

# Names a mapping may use, and the label each becomes (kidneys decided by side).
MAPPING_NAMES = {
    "body": Label.SOFT_TISSUE,
    "soft_tissue": Label.SOFT_TISSUE,
    "fat": Label.FAT,
    "muscle": Label.MUSCLE,
    "liver": Label.LIVER,
    "bone": Label.BONE,
    "rib": Label.BONE,
    "gas": Label.GAS,
    "vessel": Label.VESSEL,
    "kidney": Label.KIDNEY_CORTEX,
    "kidney_right": Label.KIDNEY_CORTEX,
    "kidney_left": Label.KIDNEY_CORTEX,
    "kidney_cortex": Label.KIDNEY_CORTEX,
    "kidney_medulla": Label.KIDNEY_MEDULLA,
    "kidney_sinus": Label.KIDNEY_SINUS,
    "ignore": None,
}

# TotalSegmentator v2, task 'total' class indices (the package's class map), for the labels
# the ultrasound scene needs. TotalSegmentator has no whole-body label in this task: merge
# its 'body' task output in as value 200 (or give your own mapping with a 'body' entry).
TOTALSEGMENTATOR_MAPPING = {
    2: "kidney_right",
    3: "kidney_left",
    5: "liver",
    23: "kidney_left",
    24: "kidney_right",
    18: "gas",
    19: "soft_tissue",
    20: "gas",  # bowel: small bowel, duodenum, colon
    52: "vessel",
    63: "vessel",
    64: "vessel",  # aorta, IVC, portal/splenic vein
    86: "muscle",
    87: "muscle",
    88: "muscle",
    89: "muscle",  # autochthon, iliopsoas
    **{v: "bone" for v in range(25, 51)},  # sacrum, vertebrae
    **{v: "rib" for v in range(92, 118)},  # ribs 1-12 both sides, sternum, cartilage
    200: "body",
}


def _fail(msg: str):
    raise ValueError(msg)


def load_mesh(obj, what: str) -> trimesh.Trimesh:
    """A watertight triangle mesh from a path or trimesh object, with clear errors."""
    if isinstance(obj, trimesh.Trimesh):
        m = obj.copy()
        where = what
    else:
        path = Path(obj)
        where = f"{what} {path}"
        if not path.is_file():
            raise FileNotFoundError(f"{what}: file not found: {path}")
        try:
            m = trimesh.load(str(path), force="mesh")
        except Exception as e:
            _fail(f"{where}: cannot read the mesh ({e})")
    if not isinstance(m, trimesh.Trimesh) or len(m.faces) == 0:
        _fail(f"{where}: no triangles in the file")
    if not m.is_watertight:
        m.merge_vertices()
        trimesh.repair.fill_holes(m)
    if not m.is_watertight:
        _fail(
            f"{where}: the mesh is not watertight (holes or non-manifold edges); "
            "a closed solid surface is needed (e.g. the *_solid.stl files)"
        )
    faces = np.asarray(m.faces)
    if m.volume < 0:
        faces = faces[:, ::-1]
    return trimesh.Trimesh(np.asarray(m.vertices), faces, process=False)


def find_mesh_files(directory: Path, side: str) -> dict:
    """Kidney/skin/liver mesh files in a directory, by name (e.g. the HuBMAP folder)."""
    files = [
        p
        for p in sorted(Path(directory).iterdir())
        if p.is_file() and p.name.lower().endswith(MESH_SUFFIXES[:-1])
    ]

    def pick(*keys, avoid=()):
        for p in files:
            n = p.name.lower()
            if all(k in n for k in keys) and not any(a in n for a in avoid):
                return p
        return None

    other = "left" if side == "right" else "right"
    return {
        "kidney": pick("kidney", side) or pick("kidney", f"_{side[0]}", avoid=(other,)),
        "other_kidney": pick("kidney", other),
        "skin": pick("skin") or pick("body"),
        "liver": pick("liver"),
    }


def _torso_loop(skin_Bd: trimesh.Trimesh, p: np.ndarray):
    """The skin cross-section loop (in x-z) at level p[1] that contains p: (N, 2) points."""
    sec = skin_Bd.section(plane_origin=[0, p[1], 0], plane_normal=[0, 1, 0])
    if sec is None:
        _fail("skin mesh: no cross-section at the kidney's level (the skin does not reach it)")
    best = None
    for e in sec.entities:
        xz = sec.vertices[e.points][:, [0, 2]]
        if len(xz) >= 3 and MplPath(xz).contains_point((p[0], p[2])):
            area = abs(0.5 * np.sum(xz[:-1, 0] * xz[1:, 1] - xz[1:, 0] * xz[:-1, 1]))
            if best is None or area < best[0]:
                best = (area, xz)
    if best is None:
        _fail(
            "skin mesh: the kidney is not inside the body surface at its own level "
            "(check the axes/units of the meshes)"
        )
    return best[1]


def _X_PtBd(skin_Bd, kidney_centroid_Bd, posture) -> RigidTransform:
    xz = _torso_loop(skin_Bd, kidney_centroid_Bd)
    y0 = kidney_centroid_Bd[1]
    R = R_PtBd(posture)
    if posture == "supine":
        p = -np.array([0.5 * (xz[:, 0].min() + xz[:, 0].max()), y0, xz[:, 1].min()])
    else:  # left flank (max x_Bd) on the bed, centre of the section above the origin
        p = np.array([-0.5 * (xz[:, 1].min() + xz[:, 1].max()), -y0, xz[:, 0].max()])
    return RigidTransform(RotationMatrix(R), p)


def _wall_layers(
    body: np.ndarray, voxel_size: float, fat: float, muscle: float, axis: int = 1
) -> np.ndarray:
    """Depth (m) below the skin measured in-plane (slices normal to ``axis``) for body voxels."""
    depth = np.zeros(body.shape, dtype=np.float32)
    for j in range(body.shape[axis]):
        sl = [slice(None)] * 3
        sl[axis] = j
        b = body[tuple(sl)]
        if b.any():
            depth[tuple(sl)] = ndimage.distance_transform_edt(np.pad(b, 1))[1:-1, 1:-1] * voxel_size
    return depth


def _kidney_sublabels(labels, kidney_mask, voxel_size, cortex=0.0066, parenchyma=0.0154):
    idx = np.argwhere(kidney_mask)
    lo = np.maximum(idx.min(axis=0) - 2, 0)
    hi = idx.max(axis=0) + 3
    sub = kidney_mask[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
    depth = ndimage.distance_transform_edt(sub) * voxel_size
    lab = labels[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
    lab[sub] = Label.KIDNEY_CORTEX
    lab[sub & (depth >= parenchyma)] = Label.KIDNEY_SINUS
    # Medulla: between cortex and sinus (pyramids are not resolved in surface meshes).
    lab[sub & (depth >= cortex) & (depth < parenchyma)] = Label.KIDNEY_MEDULLA


def _mesh_labels(kidney, skin_section, liver, other_kidney, voxel_size, fat, muscle):
    """Label volume (Pt-aligned grid) of a mesh patient, meshes in Pt."""
    lo, hi = skin_section.bounds
    shape, X_PtV = grid_around((lo - 0.003, hi + 0.003), voxel_size)
    body = rasterize_mesh(skin_section, shape, X_PtV, voxel_size)
    labels = np.zeros(shape, dtype=np.uint8)
    depth = _wall_layers(body, voxel_size, fat, muscle, axis=1)
    labels[body] = Label.SOFT_TISSUE
    labels[body & (depth <= fat + muscle)] = Label.MUSCLE
    labels[body & (depth <= fat)] = Label.FAT
    if liver is not None:
        labels[rasterize_mesh(liver, shape, X_PtV, voxel_size) & body] = Label.LIVER
    if other_kidney is not None:
        labels[rasterize_mesh(other_kidney, shape, X_PtV, voxel_size) & body] = Label.KIDNEY_CORTEX
    kmask = rasterize_mesh(kidney, shape, X_PtV, voxel_size)
    if not kmask.any():
        _fail("kidney mesh: no voxel of the label grid lies inside it")
    _kidney_sublabels(labels, kmask, voxel_size)
    return LabelVolume(labels=labels, voxel_size=voxel_size, X_PtV=X_PtV)


def _assemble(
    name,
    side,
    posture,
    kidney_Bd,
    skin_Bd,
    liver_Bd,
    other_Bd,
    meta,
    voxel_size,
    fat,
    muscle,
    label_volume_Bd=None,
) -> Patient:
    _, c, _ = mesh_surface_moments(kidney_Bd.vertices, kidney_Bd.faces)
    X_PtBd = _X_PtBd(skin_Bd, c, posture)
    kidney = transform_mesh(kidney_Bd, X_PtBd)
    skin = transform_mesh(skin_Bd, X_PtBd)
    liver = transform_mesh(liver_Bd, X_PtBd) if liver_Bd is not None else None
    other = transform_mesh(other_Bd, X_PtBd) if other_Bd is not None else None
    meta = dict(meta)
    meta["X_PtBd"] = X_PtBd.GetAsMatrix4().tolist()
    # The torso section (Patient.torso_section) is cut around the kidney's surface centroid.
    torso_center_Pt = X_PtBd.multiply(c)

    if label_volume_Bd is not None:
        labels_Bd, X_BdV, vs = label_volume_Bd

        def label_builder():
            return LabelVolume(labels=labels_Bd, voxel_size=vs, X_PtV=X_PtBd.multiply(X_BdV))
    else:

        def label_builder():
            extent = float(np.ptp(kidney.vertices[:, 1])) / 2 + 0.07
            return _mesh_labels(
                kidney, torso_builder_fine(extent), liver, other, voxel_size, fat, muscle
            )

        def torso_builder_fine(h):
            return crop_body_section(skin, torso_center_Pt, h, voxel_size=max(voxel_size, 0.002))

    return Patient(
        name=name,
        side=side,
        posture=posture,
        kidney_mesh=kidney,
        skin_mesh=skin,
        liver_mesh=liver,
        label_builder=label_builder,
        torso_center_Pt=torso_center_Pt,
        meta=meta,
    )


def _name(obj) -> str:
    return "(a trimesh)" if isinstance(obj, trimesh.Trimesh) else str(obj)


def patient_from_meshes(
    kidney,
    skin,
    *,
    liver=None,
    other_kidney=None,
    side="right",
    posture="supine",
    axes="LSA",
    units="auto",
    name=None,
    voxel_size=0.001,
    fat=0.015,
    muscle=0.012,
) -> Patient:
    """A patient from surface meshes (STL/OBJ/PLY paths or trimesh objects) given in a
    body-fixed frame whose axes point to the anatomical directions ``axes`` (default
    "LSA": +x left, +y superior, +z anterior, the glTF/HuBMAP body frame). ``units``: "mm",
    "m" or "auto" (from the kidney's size). ``fat``/``muscle``: thickness (m) of the layers
    under the skin in the label volume (meshes carry none)."""
    check_side_posture(side, posture)
    km = load_mesh(kidney, "kidney mesh")
    sm = load_mesh(skin, "skin mesh")
    lm = load_mesh(liver, "liver mesh") if liver is not None else None
    om = load_mesh(other_kidney, "other kidney mesh") if other_kidney is not None else None
    if units == "auto":
        scale = 0.001 if float(np.ptp(km.vertices, axis=0).max()) > 1.0 else 1.0
    elif units in ("mm", "m"):
        scale = 0.001 if units == "mm" else 1.0
    else:
        _fail(f"units: expected 'auto', 'mm' or 'm', got {units!r}")
    # One unit for all meshes (a kidney in m with the skin in mm would be read as a body
    # 1.7 km tall), checked before any voxel grid is made.
    check_mesh_units(
        float(np.ptp(km.vertices, axis=0).max()),
        float(np.ptp(sm.vertices, axis=0).max()),
        _name(kidney),
        _name(skin),
        scale,
        units,
    )
    if lm is not None:
        check_mesh_units(
            float(np.ptp(km.vertices, axis=0).max()),
            float(np.ptp(lm.vertices, axis=0).max()),
            _name(kidney),
            _name(liver),
            scale,
            units,
            other="liver",
        )
    R = R_BdS(axes)
    X = np.eye(4)
    X[:3, :3] = R * scale

    def to_Bd(m):
        if m is None:
            return None
        m = m.copy()
        m.apply_transform(X)
        return m

    km, sm, lm, om = to_Bd(km), to_Bd(sm), to_Bd(lm), to_Bd(om)
    ext = float(np.ptp(km.vertices, axis=0).max())
    if not 0.03 < ext < 0.3:
        _fail(
            f"kidney mesh: largest extent {ext * 1e3:.0f} mm after unit conversion "
            f"(units={units!r}); expected a kidney of 30-300 mm"
        )
    _, c_kidney, _ = mesh_surface_moments(km.vertices, km.faces)
    sm, arms = remove_arms(sm, c_kidney)
    name = name or (
        Path(kidney).parent.name if not isinstance(kidney, trimesh.Trimesh) else "meshes"
    )
    meta = {
        "source": "meshes",
        "kidney": str(kidney) if not isinstance(kidney, trimesh.Trimesh) else "mesh",
        "skin": str(skin) if not isinstance(skin, trimesh.Trimesh) else "mesh",
        "liver": None if liver is None else _name(liver),
        "axes": axes,
        "units_scale": scale,
        "arms_removed": arms,
        "layers": {"fat": fat, "muscle": muscle, "note": "modelling choice (no layers in meshes)"},
    }
    return _assemble(name, side, posture, km, sm, lm, om, meta, voxel_size, fat, muscle)


def _read_label_map(path: Path, voxel_size: float, check_native=None):
    """(labels (i, j, k) resampled to ``voxel_size``, direction D, origin (m), spacing (mm)
    of the file). ``check_native(array, spacing_mm, sup_axis)`` sees the file's own voxels
    (array axes k, j, i, their spacing, the axis nearest to superior) before the resampling,
    which a spacing in the wrong unit would make allocate without bound: it checks that the
    body is of human size (:func:`~drake_rus.anatomy.checks.check_label_map_body_size`)."""
    import SimpleITK as sitk

    img = read_label_image(path)
    arr = sitk.GetArrayViewFromImage(img)
    if not np.issubdtype(arr.dtype, np.integer):
        a = np.asarray(arr)
        if not np.all(np.isfinite(a)) or np.any(a != np.round(a)):
            _fail(f"label map {path}: voxel values are not integer labels (dtype {a.dtype})")
        img = sitk.Cast(img, sitk.sitkInt32)
    spacing = np.array(img.GetSpacing())
    if check_native is not None:
        D0 = np.array(img.GetDirection()).reshape(3, 3)
        sup_axis = int(np.argmax(np.abs(D0[2])))  # grid axis nearest S
        check_native(sitk.GetArrayViewFromImage(img), spacing[::-1], 2 - sup_axis)
    target = voxel_size * 1000.0
    if np.any(np.abs(spacing - target) > 1e-6):
        size = np.round(np.array(img.GetSize()) * spacing / target).astype(int).tolist()
        img = sitk.Resample(
            img,
            size,
            sitk.Transform(),
            sitk.sitkNearestNeighbor,
            img.GetOrigin(),
            [target] * 3,
            img.GetDirection(),
            0,
            img.GetPixelID(),
        )
    labels = sitk.GetArrayFromImage(img).transpose(2, 1, 0)  # (i, j, k)
    D = np.array(img.GetDirection()).reshape(3, 3)  # columns: index axes in LPS
    origin = np.array(img.GetOrigin()) / 1000.0
    if np.linalg.det(D) < 0:  # make the grid right-handed
        labels = labels[:, :, ::-1]
        origin = origin + D[:, 2] * voxel_size * (labels.shape[2] - 1)
        D[:, 2] *= -1
    return np.ascontiguousarray(labels), D, origin, tuple(float(x) for x in spacing)


def patient_from_label_map(
    path,
    mapping="totalsegmentator",
    *,
    side="right",
    posture="supine",
    name=None,
    voxel_size=0.001,
    fat=0.015,
    muscle=0.012,
) -> Patient:
    """A patient from a NIfTI/NRRD (any SimpleITK-readable) integer label map.

    ``mapping``: "totalsegmentator" (v2 'total' class indices; needs a body label from
    the 'body' task merged in as value 200, or pass a dict), or a dict
    {label value: name}, names from :data:`MAPPING_NAMES`.
    """
    check_side_posture(side, posture)
    path = Path(path)
    if isinstance(mapping, str):
        if mapping.lower() != "totalsegmentator":
            _fail(
                f"mapping: unknown preset {mapping!r}; use 'totalsegmentator' or a dict "
                "{label value: name}"
            )
        mapping = TOTALSEGMENTATOR_MAPPING
    mapping = {int(k): str(v).lower() for k, v in dict(mapping).items()}
    for k, v in mapping.items():
        if v not in MAPPING_NAMES:
            _fail(
                f"mapping: unknown label name {v!r} for value {k}; known names: "
                f"{', '.join(sorted(MAPPING_NAMES))}"
            )
    target = (f"kidney_{side}", "kidney")

    def check_native(native, spacing_mm, sup_axis):
        # The body's size, for a map with a kidney and a body that is not inside-out; a
        # map without them (or inverted) gets the error naming that instead.
        kidney = np.isin(native, [k for k, v in mapping.items() if v in target])
        if (
            not kidney.any()
            or not np.isin(native, [k for k, v in mapping.items() if v == "body"]).any()
        ):
            return
        if all(kidney.take(i, axis=a).any() for a in range(3) for i in (0, -1)):
            return
        body = np.isin(native, [k for k, v in mapping.items() if v != "ignore"])
        check_label_map_body_size(body, spacing_mm, sup_axis, path)

    raw, D, origin, spacing = _read_label_map(path, voxel_size, check_native)
    return _patient_from_raw(
        raw,
        D,
        origin,
        mapping,
        path,
        side=side,
        posture=posture,
        name=name or path.name,
        voxel_size=voxel_size,
        fat=fat,
        muscle=muscle,
        meta={"source": "label_map", "path": str(path), "spacing_mm": list(spacing)},
    )


# TotalSegmentator's per-structure output files (<class>.nii.gz) -> class index, for the
# classes in TOTALSEGMENTATOR_MAPPING; the 'body' task's body / body_trunc become 200.
TOTALSEGMENTATOR_FILES = {
    "kidney_right": 2,
    "kidney_left": 3,
    "liver": 5,
    "small_bowel": 18,
    "duodenum": 19,
    "colon": 20,
    "kidney_cyst_left": 23,
    "kidney_cyst_right": 24,
    "sacrum": 25,
    "aorta": 52,
    "inferior_vena_cava": 63,
    "portal_vein_and_splenic_vein": 64,
    "autochthon_left": 86,
    "autochthon_right": 87,
    "iliopsoas_left": 88,
    "iliopsoas_right": 89,
    **{
        f"vertebrae_{v}": 26 + i
        for i, v in enumerate(
            [
                "S1",
                "L5",
                "L4",
                "L3",
                "L2",
                "L1",
                "T12",
                "T11",
                "T10",
                "T9",
                "T8",
                "T7",
                "T6",
                "T5",
                "T4",
                "T3",
                "T2",
                "T1",
                "C7",
                "C6",
                "C5",
                "C4",
                "C3",
                "C2",
                "C1",
            ]
        )
    },
    **{f"rib_left_{i}": 91 + i for i in range(1, 13)},
    **{f"rib_right_{i}": 103 + i for i in range(1, 13)},
    "sternum": 116,
    "costal_cartilages": 117,
    "body": 200,
    "body_trunc": 200,
    "skin": 200,
}


def _stem(p: Path) -> str:
    n = p.name
    for suf in LABEL_MAP_SUFFIXES:
        if n.lower().endswith(suf):
            return n[: -len(suf)]
    return p.stem


def totalsegmentator_mask_files(directory: Path) -> dict:
    """{class name: path} of TotalSegmentator per-structure masks in a directory."""
    out = {}
    for p in sorted(Path(directory).iterdir()):
        if p.is_file() and p.name.lower().endswith(LABEL_MAP_SUFFIXES):
            stem = _stem(p)
            if stem in TOTALSEGMENTATOR_FILES:
                out[stem] = p
    return out


def patient_from_mask_folder(
    directory,
    *,
    side="right",
    posture="supine",
    name=None,
    voxel_size=0.001,
    fat=0.015,
    muscle=0.012,
) -> Patient:
    """A patient from TotalSegmentator's default output: one binary mask per structure
    (kidney_right.nii.gz, liver.nii.gz, rib_right_11.nii.gz, ...) plus the body mask of its
    'body' task (body.nii.gz or body_trunc.nii.gz). All masks must share one grid."""
    check_side_posture(side, posture)
    directory = Path(directory)
    files = totalsegmentator_mask_files(directory)
    if f"kidney_{side}" not in files:
        _fail(f"mask folder {directory}: no kidney_{side} mask (kidney_{side}.nii.gz)")
    body_files = [k for k in ("body", "body_trunc", "skin") if k in files]
    if not body_files:
        _fail(
            f"mask folder {directory}: no body mask (body.nii.gz or body_trunc.nii.gz from "
            "TotalSegmentator's 'body' task); the skin surface cannot be found without it"
        )
    order = body_files + [k for k in files if k not in body_files]
    raw = D = origin = spacing = None
    for key in order:
        size_check = (
            (lambda a, sp, sup, f=files[key]: check_label_map_body_size(a != 0, sp, sup, f))
            if key == order[0]
            else None
        )
        m, D_k, o_k, spacing_k = _read_label_map(files[key], voxel_size, size_check)
        if raw is None:
            raw, D, origin, spacing = np.zeros(m.shape, dtype=np.int32), D_k, o_k, spacing_k
        elif m.shape != raw.shape or not np.allclose(D_k, D) or not np.allclose(o_k, origin):
            _fail(
                f"mask folder {directory}: {files[key].name} is not on the same grid as "
                f"{files[order[0]].name}"
            )
        raw[m > 0] = TOTALSEGMENTATOR_FILES[key]
    return _patient_from_raw(
        raw,
        D,
        origin,
        TOTALSEGMENTATOR_MAPPING,
        directory,
        side=side,
        posture=posture,
        name=name or directory.name,
        voxel_size=voxel_size,
        fat=fat,
        muscle=muscle,
        meta={
            "source": "mask_folder",
            "path": str(directory),
            "files": sorted(files),
            "spacing_mm": list(spacing),
        },
    )


class _TooSmall(ValueError):
    """A label too small (a few voxels) for marching cubes to find its surface."""


def _label_surface(mask, X_BdV, voxel_size, what: str, **kw) -> trimesh.Trimesh:
    """:func:`mask_to_mesh` of a label's mask; a label of a few stray voxels, which the
    smoothing leaves without a surface, raises :class:`_TooSmall` naming ``what`` (the
    file and the structure) instead of the marching-cubes error."""
    try:
        return mask_to_mesh(mask, X_BdV, voxel_size, what=what, **kw)
    except ValueError as e:
        if str(e).startswith(what):
            raise
        n = int(np.count_nonzero(mask))
        raise _TooSmall(
            f"{what}: the label holds only {n} voxel{'s' if n != 1 else ''} "
            f"({n * voxel_size**3 * 1e6:.3g} ml at {voxel_size * 1e3:g} mm), too few for a "
            f"surface ({e})"
        ) from None


def _air_around(mask: np.ndarray, body: np.ndarray) -> float:
    """Share of the voxels one step outside ``mask`` (within the grid) not in ``body``."""
    idx = np.argwhere(mask)
    lo = np.maximum(idx.min(axis=0) - 1, 0)
    hi = idx.max(axis=0) + 2
    box = tuple(slice(a, b) for a, b in zip(lo, hi))
    m = mask[box]
    shell = ndimage.binary_dilation(m) & ~m
    n = int(shell.sum())
    return float((shell & ~body[box]).sum() / n) if n else 0.0


def _patient_from_raw(
    raw, D, origin, mapping, path, *, side, posture, name, voxel_size, fat, muscle, meta
) -> Patient:
    present = set(np.unique(raw).tolist()) - {0}
    if not present:
        _fail(f"label map {path}: empty (no nonzero labels)")
    target_names = (f"kidney_{side}", "kidney")
    kid_vals = [k for k, v in mapping.items() if v in target_names and k in present]
    if not kid_vals:
        _fail(
            f"label map {path}: no voxels of the {side} kidney (values mapped to "
            f"{' or '.join(target_names)}: "
            f"{[k for k, v in mapping.items() if v in target_names] or 'none'})"
        )
    body_vals = [k for k, v in mapping.items() if v == "body" and k in present]
    if not body_vals:
        _fail(
            f"label map {path}: no body label (a value mapped to 'body'); the skin surface "
            "cannot be found without it (TotalSegmentator: merge the 'body' task as 200)"
        )
    kidney_mask = np.isin(raw, kid_vals)
    faces = [
        kidney_mask[0],
        kidney_mask[-1],
        kidney_mask[:, 0],
        kidney_mask[:, -1],
        kidney_mask[:, :, 0],
        kidney_mask[:, :, -1],
    ]
    if all(f.any() for f in faces):
        _fail(
            f"label map {path}: the {side} kidney touches all six faces of the grid; the "
            "label volume is inside-out (kidney and background swapped?)"
        )
    # The body: every mapped label but the target kidney, holes filled (a kidney inside the
    # body is such a hole). A kidney that is not wholly inside is refused here, before the
    # arms are looked for around it (checks.check_anatomy measures the same on the patient).
    body = np.isin(
        raw, [k for k, v in mapping.items() if v != "ignore" and k in present and k not in kid_vals]
    )
    body = ndimage.binary_fill_holes(body)
    air = _air_around(kidney_mask, body)
    if air > AIR_CONTACT_MAX:
        raise AnatomyError(
            f"label map {path}: the {side} kidney is not inside the body: {air:.1%} of the "
            f"voxels around it are outside the body label (at most {AIR_CONTACT_MAX:.1%})"
        )
    body |= kidney_mask
    # The arms off (module docstring): slices normal to the grid axis nearest to superior.
    sup_axis = int(np.argmax(np.abs(D[2])))
    trunk = trunk_mask(body, sup_axis, np.argwhere(kidney_mask).mean(axis=0), voxel_size)
    arms = {
        "method": "axial-slice trunk tracking (anatomy/trunk.py)",
        "removed_volume_l": round(float((body & ~trunk).sum()) * voxel_size**3 * 1e3, 3),
    }
    body = trunk
    labels = np.zeros(raw.shape, dtype=np.uint8)
    labels[body] = Label.SOFT_TISSUE
    depth = _wall_layers(body, voxel_size, fat, muscle, axis=sup_axis)
    labels[body & (depth <= fat + muscle)] = Label.MUSCLE
    labels[body & (depth <= fat)] = Label.FAT
    for k, v in mapping.items():
        lab = MAPPING_NAMES[v]
        if (
            k in present
            and lab is not None
            and v not in ("body", "soft_tissue")
            and k not in kid_vals
        ):
            labels[(raw == k) & body] = lab
    if not any(v in ("kidney_medulla", "kidney_sinus") for v in mapping.values()):
        _kidney_sublabels(labels, kidney_mask, voxel_size)
    else:
        labels[kidney_mask] = Label.KIDNEY_CORTEX
    # Grid frame V in LPS, then in Bd.
    R_BdLPS = R_BdS("LPS")
    X_BdV = RigidTransform(RotationMatrix(R_BdLPS @ D), R_BdLPS @ origin)
    kidney_Bd = _label_surface(
        kidney_mask, X_BdV, voxel_size, f"label map {path}: the {side} kidney", sigma_vox=1.0
    )
    coarse = max(1, int(round(0.003 / voxel_size)))
    body_c = body[::coarse, ::coarse, ::coarse]
    skin_Bd = mask_to_mesh(
        body_c, X_BdV, voxel_size * coarse, sigma_vox=0.7, keep_point=None, what=f"{path}: body"
    )
    liver_vals = [k for k, v in mapping.items() if v == "liver" and k in present]
    liver_Bd = None
    if liver_vals:
        # A liver the volume only grazes (a few voxels) has no surface: no liver mesh then
        # (its voxels stay in the label volume), as for a patient without a liver label.
        try:
            liver_Bd = _label_surface(
                np.isin(raw, liver_vals), X_BdV, voxel_size, f"label map {path}: the liver"
            )
        except _TooSmall:
            liver_Bd = None
    meta = dict(meta)
    meta.update(
        {
            "mapping_values_present": sorted(present),
            "arms_removed": arms,
            "layers": {"fat": fat, "muscle": muscle, "note": "modelling choice"},
        }
    )
    return _assemble(
        name,
        side,
        posture,
        kidney_Bd,
        skin_Bd,
        liver_Bd,
        None,
        meta,
        voxel_size,
        fat,
        muscle,
        label_volume_Bd=(labels, X_BdV, voxel_size),
    )
