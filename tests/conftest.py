"""Fixtures shared by the test modules."""

import pytest

from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.paths import REPO_ROOT
from drake_rus.robot import MakeControlPlant, TipKinematics
from drake_rus.scenario import ApplyOverrides, LoadScenario


# The Visible Human female (HuBMAP) beside the clone: CI has ../shared next to the
# repository, a user's checkout does not, and the tests that need her then skip.
HUBMAP = REPO_ROOT.parent / "shared" / "anatomy" / "hubmap_vh_female"
needs_hubmap = pytest.mark.skipif(not (HUBMAP / "VH_F_skin.stl").is_file(),
                                  reason=f"real body not found at {HUBMAP}")


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
    text = ", ".join(f"{k}: {str(v).lower() if isinstance(v, bool) else v}"
                     for k, v in fields.items())
    return ApplyOverrides(LoadScenario(), "{hardware: true, %shardware_interface: {%s}}"
                          % (f"{extra}, " if extra else "", text))


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
