"""Fixtures shared by the test modules."""

import os

import numpy as np
import pytest

from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.paths import REPO_ROOT
from drake_rus.robot import MakeControlPlant, TipKinematics
from drake_rus.scenario import ApplyOverrides, LoadScenario

# The Visible Human female (HuBMAP) beside the clone: CI has ../shared next to the
# repository, a user's checkout does not, and the tests that need her then skip.
HUBMAP = REPO_ROOT.parent / "shared" / "anatomy" / "hubmap_vh_female"
needs_hubmap = pytest.mark.skipif(
    not (HUBMAP / "VH_F_skin.stl").is_file(), reason=f"real body not found at {HUBMAP}"
)


# KiTS19 CT kidney label maps beside the clone (CC BY-NC-SA: read there, never copied).
KITS = REPO_ROOT.parent / "shared" / "anatomy" / "kits19"
needs_kits = pytest.mark.skipif(
    not (KITS / "case_00000").is_dir(), reason=f"KiTS19 label maps not found at {KITS}"
)


def tiny_training_frames(n: int, size: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """(frames, masks), each (n, size, size) uint8: random grey frames and a square kidney
    mask (255) at rows and columns 10..19, for training-loop tests that only need the
    loop to run on something learnable."""
    rng = np.random.default_rng(0)
    X = rng.integers(0, 255, (n, size, size)).astype(np.uint8)
    Y = np.zeros_like(X)
    Y[:, 10:20, 10:20] = 255
    return X, Y


def synthetic_ct_case(
    tumour=True, left=True, spacing=(3.0, 4.0, 3.0), n=(128, 50, 128), tumour_radius=16.0
):
    """A KiTS-style label map with a known pose, on an axial grid whose axes are the
    anatomical frame A (x left, y superior, z anterior; mm): ``(labels, spacing, info)``.

    Two ellipsoidal kidneys (110 x 56 x 40 mm) with a hilum notch, tilted like real ones
    (long axis 17 deg off craniocaudal with the upper pole medial, 20 deg with the upper
    pole posterior; hilum facing anteromedially 42 deg above the horizontal); the right one
    20 mm lower than the left, both 75 mm from the midline, in the posterior half of the
    field of view; a tumour (radius ``tumour_radius`` mm) bulging from the right kidney's
    lateral border (label 2).
    ``info``: "origin" (A of voxel 0), "kidneys" {side: (centre, R_AK)}, "inside"
    {name: f(points_A) -> bool} for "right", "left" (kidney+tumour), "tumour"."""
    spacing = np.asarray(spacing, dtype=float)
    origin = np.array([-0.5 * (n[0] - 1) * spacing[0], -110.0, -120.0])
    semi = np.array([55.0, 28.0, 20.0])
    notch_semi = np.array([20.0, 14.0, 12.0])

    def pose(side):
        s = -1.0 if side == "right" else 1.0  # side sign in x
        cor, sag, hil = np.radians([17.0, 20.0, 42.0])
        u = np.array([-s * np.tan(cor), 1.0, -np.tan(sag)])
        u /= np.linalg.norm(u)
        m = np.array([-s * np.cos(hil), 0.0, np.sin(hil)])
        m -= (m @ u) * u
        m /= np.linalg.norm(m)
        R = np.column_stack([u, -m, np.cross(u, -m)])
        c = np.array([75.0 * s, -20.0 if side == "right" else 0.0, 0.0])
        return c, R

    poses = {side: pose(side) for side in ("right", "left")}
    t_c, t_R = poses["right"]
    t_centre = t_c + t_R @ np.array([15.0, 26.0, 6.0])

    def kidney(side):
        c, R = poses[side]

        def f(p):
            q = (np.asarray(p, dtype=float) - c) @ R
            body = np.sum((q / semi) ** 2, axis=1) <= 1.0
            notch = np.sum(((q - [0.0, -semi[1], 0.0]) / notch_semi) ** 2, axis=1) <= 1.0
            return body & ~notch

        return f

    def tumour_f(p):
        return np.linalg.norm(np.asarray(p, dtype=float) - t_centre, axis=1) <= tumour_radius

    grids = np.meshgrid(*[np.arange(k) for k in n], indexing="ij")
    pts = origin + spacing * np.column_stack([g.ravel() for g in grids])
    labels = np.zeros(len(pts), dtype=np.uint8)
    labels[kidney("right")(pts)] = 1
    if left:
        labels[kidney("left")(pts)] = 1
    if tumour:
        labels[tumour_f(pts)] = 2
    inside = {
        "right": (lambda p: kidney("right")(p) | (tumour_f(p) if tumour else False)),
        "left": kidney("left"),
        "tumour": tumour_f,
    }
    return (
        labels.reshape(n),
        spacing,
        {"origin": origin, "kidneys": poses, "inside": inside, "tumour_centre": t_centre},
    )


def stored_as(labels, spacing, perm, flips):
    """``labels`` (axes = A) stored with its axes permuted (``perm``: stored axis g is A
    axis perm[g]) and the stored axes in ``flips`` reversed: ``(array, spacing, R_AG)``
    with R_AG the true anatomical-from-grid rotation (directions only)."""
    a = np.transpose(labels, perm)
    sp = np.asarray(spacing, dtype=float)[list(perm)]
    R = np.zeros((3, 3))
    for g in range(3):
        R[perm[g], g] = -1.0 if g in flips else 1.0
    for g in flips:
        a = np.flip(a, axis=g)
    return np.ascontiguousarray(a), sp, R


@pytest.fixture(scope="session", autouse=True)
def _throwaway_patient_cache(tmp_path_factory):
    """Tests use their own patient cache (drake_rus.anatomy.cache), never ~/.cache; it is
    shared by the whole session, so each patient is built once per test run."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("DRAKE_RUS_CACHE_DIR", str(tmp_path_factory.mktemp("patient_cache")))
        yield


@pytest.fixture(scope="session")
def geometry() -> ProbeGeometry:
    """The default probe geometry (40 deg fan, 150 mm deep, 256 x 256 image)."""
    return ProbeGeometry.from_config(ImagingConfig())


@pytest.fixture(scope="session")
def kin() -> TipKinematics:
    """Tip kinematics on the default scenario's control plant (FR3 + probe)."""
    plant, frame = MakeControlPlant()
    return TipKinematics(plant, frame)


def hardware_scenario(fields: dict, extra: str = ""):
    """The default scenario with ``hardware: true`` and ``hardware_interface`` set to
    ``fields`` (booleans written as YAML), plus ``extra`` top-level YAML (e.g. a safety
    section), for the hardware-station tests."""
    text = ", ".join(
        f"{k}: {str(v).lower() if isinstance(v, bool) else v}" for k, v in fields.items()
    )
    return ApplyOverrides(
        LoadScenario(),
        "{hardware: true, %shardware_interface: {%s}}" % (f"{extra}, " if extra else "", text),
    )


@pytest.fixture
def moving_nearest_doubles():
    """(Counted, Plain, made): stand-ins for ``icp.MovingNearest`` in A/B tests. Counted is
    the real one, each instance appended to ``made`` (to read its query counts); Plain
    answers every query from a fresh kd-tree of the current points (the reference)."""
    from scipy.spatial import cKDTree

    from drake_rus.localization import icp

    made = []

    class Counted(icp.MovingNearest):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            made.append(self)

    class Plain(icp.MovingNearest):
        def query(self, x, points, tree_of):
            return cKDTree(points).query(x)

    return Counted, Plain, made


def write_small_label_map(path):
    """A small TotalSegmentator-like label map (4 mm voxels, LPS grid: i left, j posterior,
    k superior) written to ``path``: body 200, right kidney 2."""
    import SimpleITK as sitk

    n = (80, 60, 40)
    ii, jj, kk = np.meshgrid(*[np.arange(s) for s in n], indexing="ij")
    x, y, z = (ii - 40) * 4.0, (jj - 30) * 4.0, (kk - 20) * 4.0
    lab = np.zeros(n, np.uint8)
    lab[(x / 150) ** 2 + (y / 100) ** 2 <= 1] = 200
    lab[((x + 75) / 28) ** 2 + ((y - 40) / 20) ** 2 + (z / 55) ** 2 <= 1] = 2
    img = sitk.GetImageFromArray(np.ascontiguousarray(lab.transpose(2, 1, 0)))
    img.SetSpacing((4.0, 4.0, 4.0))
    img.SetOrigin((-160.0, -120.0, -80.0))
    sitk.WriteImage(img, str(path))


@pytest.fixture
def failing_dot(tmp_path, monkeypatch):
    """A Graphviz ``dot`` first on PATH that fails (exit 3, "Error: layout was not done"),
    as a broken install would; the real one need not be installed."""
    fake = tmp_path / "fake_bin" / "dot"
    fake.parent.mkdir()
    fake.write_text("#!/bin/sh\necho 'Error: layout was not done' >&2\nexit 3\n")
    fake.chmod(0o755)
    monkeypatch.setenv("PATH", f"{fake.parent}{os.pathsep}{os.environ['PATH']}")
    return fake
