"""Our FR3 model against published numbers and an independent FK implementation (frankik)."""

import numpy as np
import pytest
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import MultibodyPlant

from drake_rus.paths import MODELS_DIR, AddDrakeRusPackages

frankik = pytest.importorskip("frankik", reason="frankik is in the test extra")

# facts/fr3.md, current FR3 specification (2025).
Q_MIN = [-2.9007, -1.8361, -2.9007, -3.0770, -2.8763, 0.4398, -3.0508]
Q_MAX = [2.9007, 1.8361, 2.9007, -0.1169, 2.8763, 4.6216, 3.0508]
DQ_MAX = [2.62, 2.62, 2.62, 2.62, 5.26, 4.18, 5.26]
TAU_MAX = [87, 87, 87, 87, 12, 12, 12]
MASSES = [2.3966, 2.9275, 2.9355, 2.2449, 2.6156, 2.3271, 1.8170, 0.6271]


@pytest.fixture(scope="module")
def fr3():
    plant = MultibodyPlant(0.0)
    parser = Parser(plant)
    AddDrakeRusPackages(parser.package_map())
    (robot,) = parser.AddModelsFromUrl("package://drake_rus_models/fr3/fr3.urdf")
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName("fr3_link0"))
    plant.Finalize()
    return plant, robot


def hand_tcp(plant, context, q):
    """Our flange * Rz(-pi/4) * tz(0.1034): the hand TCP that frankik.fk returns."""
    plant.SetPositions(context, q)
    X_WF = plant.GetFrameByName("fr3_link8").CalcPoseInWorld(context)
    X_FH = RigidTransform(RotationMatrix.MakeZRotation(-np.pi / 4), [0, 0, 0]) @ RigidTransform(
        [0, 0, 0.1034]
    )
    return X_WF @ X_FH


def test_forward_kinematics_matches_frankik(fr3):
    plant, _ = fr3
    context = plant.CreateDefaultContext()
    rng = np.random.default_rng(7)
    worst_position, worst_angle = 0.0, 0.0
    for _ in range(200):
        q = rng.uniform(Q_MIN, Q_MAX)
        X_ours = hand_tcp(plant, context, q)
        X_ref = frankik.fk(q)
        worst_position = max(worst_position, np.linalg.norm(X_ours.translation() - X_ref[:3, 3]))
        R_err = X_ours.rotation().matrix().T @ X_ref[:3, :3]
        # atan2 form: accurate for tiny angles, unlike arccos of the trace.
        skew = (
            np.array(
                [R_err[2, 1] - R_err[1, 2], R_err[0, 2] - R_err[2, 0], R_err[1, 0] - R_err[0, 1]]
            )
            / 2
        )
        angle = np.arctan2(np.linalg.norm(skew), (np.trace(R_err) - 1) / 2)
        worst_angle = max(worst_angle, angle)
    assert worst_position < 1e-9
    assert worst_angle < 1e-9


def test_published_check_value(fr3):
    plant, _ = fr3
    context = plant.CreateDefaultContext()
    X = hand_tcp(plant, context, np.array([0, 0, 0, -1.57, 0, 1.57, 0.785]))
    np.testing.assert_allclose(X.translation(), [0.5544, 0.0, 0.5214], atol=1e-4)


def test_limits_and_inertials(fr3):
    plant, robot = fr3
    for i in range(7):
        joint = plant.GetJointByName(f"fr3_joint{i + 1}")
        assert joint.position_lower_limits()[0] == pytest.approx(Q_MIN[i])
        assert joint.position_upper_limits()[0] == pytest.approx(Q_MAX[i])
        assert joint.velocity_upper_limits()[0] == pytest.approx(DQ_MAX[i])
        actuator = plant.GetJointActuatorByName(f"fr3_motor{i + 1}")
        assert actuator.effort_limit() == pytest.approx(TAU_MAX[i])
    for i, mass in enumerate(MASSES):
        assert plant.GetBodyByName(f"fr3_link{i}").default_mass() == pytest.approx(mass)


def test_committed_urdf_is_generated():
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "generate_fr3_urdf", MODELS_DIR / "fr3" / "generate_fr3_urdf.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert (MODELS_DIR / "fr3" / "fr3.urdf").read_text() == module.build_urdf(), (
        "models/fr3/fr3.urdf is stale: run python models/fr3/generate_fr3_urdf.py"
    )
