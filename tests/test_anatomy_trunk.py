"""Arms off imported bodies (drake_rus/anatomy/trunk.py): synthetic bodies whose arms hang
beside the trunk (detached or touching it) lose them and keep the trunk's cross-sections;
label maps too; the Visible Human female, rolled onto her left side, has a free right flank."""

import numpy as np
import pytest
import SimpleITK as sitk
from conftest import HUBMAP, needs_hubmap
from pydrake.math import RigidTransform

from drake_rus.anatomy import load_patient, patient_from_label_map
from drake_rus.anatomy.generator import generate_patient
from drake_rus.anatomy.rasterize import mask_to_mesh
from drake_rus.anatomy.trunk import remove_arms, trunk_mask

VS = 0.004
A, B = 0.15, 0.10  # trunk half-width (x) and half-depth (z)
R_ARM = 0.045
KIDNEY = np.array([-0.075, 0.0, -0.03])  # a point of the trunk at the kidney's level


def _body(gap: float):
    """Voxel body in Bd (x left, y superior, z anterior): an elliptic trunk (y -0.35..0.35),
    two arm cylinders beside it (y -0.25..0.22; ``gap`` between arm and trunk, negative:
    overlapping) joined to the trunk by a shoulder block (y 0.22..0.30)."""
    lo = np.array([-0.30, -0.40, -0.14])
    n = (np.array([0.60, 0.80, 0.28]) / VS).astype(int) + 1
    x, y, z = lo[:, None] + VS * np.arange(n.max())[None, :]
    X, Y, Z = np.meshgrid(x[: n[0]], y[: n[1]], z[: n[2]], indexing="ij")
    trunk = ((X / A) ** 2 + (Z / B) ** 2 <= 1) & (np.abs(Y) <= 0.35)
    xa = A + R_ARM + gap
    arms = np.zeros_like(trunk)
    for s in (-1, 1):
        arms |= ((X - s * xa) ** 2 + Z**2 <= R_ARM**2) & (Y >= -0.25) & (Y <= 0.30)
    shoulder = (np.abs(X) <= xa) & (np.abs(Z) <= R_ARM) & (Y >= 0.22) & (Y <= 0.30)
    return trunk | arms | shoulder, trunk, X, Y, RigidTransform(lo)


def _seed(X_BdV):
    return (KIDNEY - X_BdV.translation()) / VS


@pytest.mark.parametrize("gap", [0.06, 0.02])
def test_detached_arms_are_removed_and_trunk_sections_kept(gap):
    body, trunk, X, Y, X_BdV = _body(gap)
    got = trunk_mask(body, 1, _seed(X_BdV), VS)
    below = Y[0, :, 0] < 0.21  # below the shoulder: sections exactly kept
    np.testing.assert_array_equal(got[:, below], trunk[:, below])
    assert not (got & (np.abs(X) > A + R_ARM)).any()  # nothing of the arms, shoulder cut
    # Above the shoulder block the trunk goes on (the neck/head side stays).
    assert got[:, Y[0, :, 0] > 0.31].sum() == trunk[:, Y[0, :, 0] > 0.31].sum()


def test_touching_arms_are_cut_at_the_contact():
    body, trunk, X, Y, X_BdV = _body(-0.006)  # arms sunk 6 mm into the trunk's sides
    got = trunk_mask(body, 1, _seed(X_BdV), VS)
    below = Y[0, :, 0] < 0.21
    assert not (got[:, below] & ~trunk[:, below]).any()  # nothing of the arms
    for j in np.nonzero((Y[0, :, 0] > -0.24) & (Y[0, :, 0] < 0.21))[0]:
        kept = got[:, j].sum() / trunk[:, j].sum()
        assert 0.97 <= kept <= 1.0, (j, kept)
    assert not (got & (np.abs(X) > A + 2 * VS)).any()


def test_remove_arms_on_meshes_and_bodies_without_arms():
    body, trunk, X, Y, X_BdV = _body(0.03)
    skin = mask_to_mesh(body, X_BdV, VS, sigma_vox=0.7)
    out, report = remove_arms(skin, KIDNEY, voxel_size=VS)
    assert out.is_watertight and report["resurfaced"]
    # The shoulder is cut midway between trunk and arm (the gap below it, 30 mm).
    assert np.all(np.abs(out.bounds[:, 0]) < A + 0.015 + 2 * VS)
    assert out.volume == pytest.approx(trunk.sum() * VS**3, rel=0.03)
    arm_l = 2 * np.pi * R_ARM**2 * 0.47 * 1e3
    assert report["removed_volume_l"] == pytest.approx(arm_l, rel=0.25)
    # A generated torso has no arms: its surface comes back unchanged.
    gen = generate_patient(4).skin_mesh
    same, report = remove_arms(gen, gen.vertices.mean(axis=0))
    assert same is gen and not report["resurfaced"]


def test_label_map_arms_are_not_body(tmp_path):
    """TotalSegmentator-like map (LPS, 2 mm): body ellipse with two arms beside it."""
    n = (250, 120, 80)
    ii, jj, kk = np.meshgrid(*[np.arange(s) for s in n], indexing="ij")
    x, y, z = (ii - 125) * 2.0, (jj - 60) * 2.0, (kk - 40) * 2.0
    lab = np.zeros(n, np.uint8)
    lab[(x / 150) ** 2 + (y / 100) ** 2 <= 1] = 200
    for s in (-1, 1):
        lab[(x - s * 205) ** 2 + y**2 <= 35**2] = 200
    lab[((x + 75) / 28) ** 2 + ((y - 40) / 20) ** 2 + (z / 55) ** 2 <= 1] = 2
    img = sitk.GetImageFromArray(np.ascontiguousarray(lab.transpose(2, 1, 0)))
    img.SetSpacing((2.0, 2.0, 2.0))
    path = tmp_path / "arms.nii.gz"
    sitk.WriteImage(img, str(path))
    p = patient_from_label_map(path, voxel_size=0.002)
    assert p.meta["arms_removed"]["removed_volume_l"] == pytest.approx(
        2 * np.pi * 0.035**2 * 0.16 * 1e3, rel=0.1
    )
    assert np.ptp(p.skin_mesh.vertices[:, 0]) < 0.31
    lv = p.labels
    body = np.argwhere(lv.labels > 0)
    assert np.ptp(lv.voxel_centers_in_patient(body)[:, 0]) < 0.31


@needs_hubmap
def test_real_body_in_left_lateral_decubitus_has_a_free_right_flank():
    p = load_patient(str(HUBMAP), posture="left_lateral_decubitus")
    assert 5.0 < p.meta["arms_removed"]["removed_volume_l"] < 10.0  # two arms
    k, skin = p.kidney_mesh, p.skin_mesh
    c = p.X_PtK.translation()
    # The skin nearest to the kidney is on the upper side of the rolled body (the flank).
    cp, dist, _ = skin.nearest.on_surface(k.vertices[::10])
    nearest = cp[np.argmin(dist)]
    assert nearest[2] > k.bounds[1, 2]
    # The vertical line over the kidney meets the flank first, not an arm, and nothing of
    # the body rises far above that flank within 100 mm around the kidney (an arm did:
    # 150 mm above it before the arms were removed). The waist rises towards hip and chest.
    hits, _, _ = skin.ray.intersects_location([[c[0], c[1], 2.0]], [[0, 0, -1.0]])
    flank = hits[:, 2].max()
    assert flank - k.bounds[1, 2] < 0.08
    v = skin.vertices
    near = np.hypot(v[:, 0] - c[0], v[:, 1] - c[1]) < 0.10
    assert v[near, 2].max() < flank + 0.04
    m = p.metrics()
    assert 0.03 < m["depth_vertical"] < 0.07  # through the flank (supine: 147.5 mm)


@needs_hubmap
def test_real_body_supine_contact_section_is_the_trunk():
    p = load_patient(str(HUBMAP))
    sec = p.torso_section(0.20)
    assert sec.is_watertight
    # The trunk of the VH female is about 300 mm wide at the kidney's level, about 390 mm
    # at the hips (the section's lower end) and 330 mm at the shoulders without the arms;
    # with them the section was 520 mm wide.
    assert np.ptp(sec.vertices[:, 0]) < 0.42
    assert np.ptp(p.skin_mesh.vertices[:, 0]) < 0.45  # the whole body, arms off
    assert p.metrics()["depth_vertical"] == pytest.approx(0.1475, abs=0.004)
