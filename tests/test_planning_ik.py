"""Start-pose planning (E-ROI, skin height) and the tip-pose IK."""

import numpy as np
import pytest
import trimesh
from pydrake.math import RigidTransform

from drake_rus.robot import IkError, MakeControlPlant, SolveTipPose
from drake_rus.scan.planning import (
    R_B_TRANSVERSE,
    exploration_roi,
    exploration_start,
    skin_height_B,
)
from drake_rus.scenario import LoadScenario


class BoxPatient:
    """A stand-in patient: a box body 0.2 m tall and an ellipsoid 'kidney' inside it."""

    def __init__(self):
        self.skin_mesh = trimesh.creation.box(
            extents=[0.3, 0.6, 0.2], transform=np.diag([1, 1, 1, 1.0])
        )
        self.skin_mesh.apply_translation([0, 0, 0.1])
        kidney = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
        kidney.apply_scale([0.03, 0.055, 0.02])
        kidney.apply_translation([-0.05, 0.02, 0.09])
        self.kidney_mesh = kidney
        self.X_PtK = RigidTransform([-0.05, 0.02, 0.09])

    def X_BK(self, X_BPt):
        return X_BPt @ self.X_PtK


def test_roi_and_start_pose():
    patient = BoxPatient()
    X_BPt = RigidTransform([0.55, 0.0, 0.0])
    roi = exploration_roi(patient, X_BPt)
    assert roi.y_max == pytest.approx(0.075, abs=2e-3)
    assert roi.y_min == pytest.approx(-0.035, abs=2e-3)
    assert skin_height_B(patient, X_BPt, 0.5, 0.0) == pytest.approx(0.2)
    X = exploration_start(patient, X_BPt, scan_direction="-y", start_fraction=0.1, hover=0.01)
    np.testing.assert_allclose(
        X.translation(), [0.5, roi.y_max - 0.1 * roi.length_y, 0.21], atol=1e-6
    )
    np.testing.assert_allclose(X.rotation().matrix(), R_B_TRANSVERSE.matrix())
    with pytest.raises(ValueError, match="no body surface"):
        skin_height_B(patient, X_BPt, 2.0, 0.0)
    with pytest.raises(ValueError, match="scan_direction"):
        exploration_start(patient, X_BPt, scan_direction="x")


def test_solve_tip_pose_reaches_the_pose():
    scenario = LoadScenario()
    plant, tip = MakeControlPlant(scenario.robot, scenario.probe)
    context = plant.CreateDefaultContext()
    for p in ([0.5, 0.05, 0.3], [0.45, -0.12, 0.22]):
        q = SolveTipPose(plant, tip, RigidTransform(R_B_TRANSVERSE, p))
        plant.SetPositions(context, q)
        X = tip.CalcPoseInWorld(context)
        np.testing.assert_allclose(X.translation(), p, atol=2e-4)
        assert np.isclose(X.rotation().matrix()[:, 2] @ [0, 0, -1], 1.0, atol=1e-5)
    with pytest.raises(IkError, match="no FR3 configuration"):
        SolveTipPose(plant, tip, RigidTransform(R_B_TRANSVERSE, [2.0, 0.0, 0.3]))
