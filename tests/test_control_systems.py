"""LeafSystem-level tests: each system's ports call its pure function; timing of updates."""

import math

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource

from drake_rus.control import laws, supervisor
from drake_rus.control.config import ControllerConfig, SafetyConfig
from drake_rus.control.synthetic_view import GeometricKidneyView, kidney_section
from drake_rus.control.systems import (
    ForcePD,
    NullSpaceDiffIK,
    OrientationAlignment,
    PositionP,
    SafetyLayer,
    ScanSupervisor,
    contact_force,
)
from drake_rus.reliability.injector import FaultInjector
from drake_rus.robot import MakeControlPlant, SolveTipPose, TipKinematics

Q0 = np.array([0.0, 0.15, 0.0, -2.0, 0.0, 2.15, 0.785])
X_TILT = RigidTransform(RollPitchYaw(math.pi + 0.2, 0.1, 0.3), [0.55, 0.02, 0.11])


@pytest.fixture(scope="module")
def plant_and_frame():
    return MakeControlPlant()


def test_contact_force_sign():
    assert contact_force([0, 0, 0, 0, 0, -9.0]) == 9.0


def test_orientation_alignment_system_matches_eq_1_5():
    cfg = ControllerConfig()
    sys = OrientationAlignment(cfg)
    ctx = sys.CreateDefaultContext()
    a_des, o_des, adot = np.array([0, 0, -1.0]), np.array([1.0, 0, 0]), np.array([0.01, 0, 0])
    sys.GetInputPort("X_BP").FixValue(ctx, X_TILT)
    sys.GetInputPort("a_des").FixValue(ctx, a_des)
    sys.GetInputPort("o_des").FixValue(ctx, o_des)
    sys.GetInputPort("a_des_dot").FixValue(ctx, adot)
    expected = laws.orientation_alignment(
        X_TILT.rotation().matrix(), a_des, o_des, adot, cfg.K_p1, cfg.K_p11, cfg.K_p2
    )
    np.testing.assert_allclose(sys.GetOutputPort("omega_BP").Eval(ctx), expected)


def test_position_p_system_matches_eq_7():
    cfg = ControllerConfig()
    sys = PositionP(cfg)
    ctx = sys.CreateDefaultContext()
    sys.GetInputPort("X_BP").FixValue(ctx, X_TILT)
    sys.GetInputPort("P_des").FixValue(ctx, [0.56, 0.0])
    v_seed = np.array([cfg.K_p4 * 0.01, cfg.K_p5 * -0.02, 0.0])
    a = X_TILT.rotation().matrix()[:, 2]
    v = sys.GetOutputPort("v_position").Eval(ctx)
    # eq. 7 in the plane normal to the (tilted) probe's axis.
    np.testing.assert_allclose(v, v_seed - (v_seed @ a) * a, atol=1e-12)
    assert abs(float(v @ a)) < 1e-12 and abs(float(v_seed @ a)) > 1e-4


def test_force_pd_system_filters_at_the_control_rate():
    cfg = ControllerConfig()
    builder = DiagramBuilder()
    pd = builder.AddSystem(ForcePD(cfg))
    F = builder.AddSystem(ConstantVectorSource([0, 0, 0, 0, 0, -4.0]))  # F_z = 4 N
    builder.Connect(F.get_output_port(), pd.GetInputPort("probe_force"))
    diagram = builder.Build()
    sim = Simulator(diagram)
    ctx = sim.get_mutable_context()
    pd_ctx = pd.GetMyContextFromRoot(ctx)
    pd.GetInputPort("X_BP").FixValue(
        pd_ctx, RigidTransform(RotationMatrix.MakeXRotation(math.pi), [0.5, 0, 0.1])
    )
    sim.AdvanceTo(0.5)
    F_f = pd.GetOutputPort("F_filtered").Eval(pd_ctx)[0]
    assert F_f == pytest.approx(4.0)  # seeded with the measurement, constant input
    v = pd.GetOutputPort("v_force").Eval(pd_ctx)
    np.testing.assert_allclose(
        v, cfg.K_p3 * (cfg.desired_force - 4.0) * np.array([0, 0, -1]), atol=1e-12
    )
    pd.GetInputPort("F_des").FixValue(pd_ctx, [2.0])
    v = pd.GetOutputPort("v_force").Eval(pd_ctx)
    assert v[2] > 0  # too much force: back out of the body (+z)


def test_null_space_diff_ik_system_tracks_twist(plant_and_frame):
    plant, frame = plant_and_frame
    cfg = ControllerConfig()
    ik = NullSpaceDiffIK(plant, frame, cfg)
    ctx = ik.CreateDefaultContext()
    ik.GetInputPort("joint_position").FixValue(ctx, Q0)
    ik.GetInputPort("omega_BP").FixValue(ctx, [0.0, 0.05, 0.0])
    ik.GetInputPort("v_force").FixValue(ctx, [0.0, 0.0, -0.01])
    ik.GetInputPort("v_position").FixValue(ctx, [0.005, 0.0, 0.0])
    qdot = ik.GetOutputPort("joint_velocity_desired").Eval(ctx)
    J = TipKinematics(plant, frame).jacobian(Q0)
    np.testing.assert_allclose(J @ qdot, [0, 0.05, 0, 0.005, 0, -0.01], atol=1e-9)
    np.testing.assert_allclose(
        ik.GetOutputPort("V_BP_desired").Eval(ctx), [0, 0.05, 0, 0.005, 0, -0.01]
    )
    assert ik.GetOutputPort("manipulability").Eval(ctx)[0] == pytest.approx(laws.manipulability(J))


def test_safety_layer_system_holds_command_and_stops(plant_and_frame):
    plant, frame = plant_and_frame
    kin = TipKinematics(plant, frame)
    safety = SafetyLayer(plant, frame, SafetyConfig(), rate_hz=100.0)
    sim = Simulator(safety)
    ctx = sim.get_mutable_context()
    safety.GetInputPort("joint_velocity_desired").FixValue(ctx, np.full(7, 0.01))
    safety.GetInputPort("joint_position").FixValue(ctx, Q0)
    safety.GetInputPort("joint_velocity").FixValue(ctx, np.zeros(7))
    safety.GetInputPort("X_BP").FixValue(ctx, kin.pose(Q0))
    F = safety.GetInputPort("probe_force").FixValue(ctx, [0, 0, 0, 0, 0, -9.0])
    sim.AdvanceTo(0.015)  # ticks at 0, 0.01
    np.testing.assert_allclose(safety.GetOutputPort("joint_velocity_command").Eval(ctx), 0.01)
    F.GetMutableData().set_value(np.array([0, 0, 0, 0, 0, -25.0]))
    sim.AdvanceTo(0.025)  # the tick at 0.02 sees the fault
    assert safety.GetOutputPort("stopped").Eval(ctx)[0] == 1.0
    events = safety.GetOutputPort("safety_events").Eval(ctx)
    assert len(events) == 1 and events[0].time == pytest.approx(0.02)
    cmd = safety.GetOutputPort("joint_velocity_command").Eval(ctx)
    v = kin.jacobian(Q0) @ cmd
    assert v[3:] @ kin.pose(Q0).rotation().matrix()[:, 2] < 0  # retracting


def test_scan_supervisor_system_outputs(plant_and_frame):
    cfg = ControllerConfig()
    sup = ScanSupervisor(cfg)
    sim = Simulator(sup)
    ctx = sim.get_mutable_context()
    X = RigidTransform(RotationMatrix.MakeXRotation(math.pi), [0.55, 0.0, 0.12])
    sup.GetInputPort("X_BP").FixValue(ctx, X)
    force = sup.GetInputPort("contact_force").FixValue(ctx, [0.0])
    sim.AdvanceTo(0.005)
    assert sup.GetOutputPort("phase").Eval(ctx)[0] == supervisor.Phase.APPROACH
    np.testing.assert_allclose(sup.GetOutputPort("a_des").Eval(ctx), [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(sup.GetOutputPort("P_des").Eval(ctx), [0.55, 0.0])
    assert sup.GetOutputPort("F_des").Eval(ctx)[0] == cfg.desired_force
    force.GetMutableData().set_value(np.array([9.0]))
    sim.AdvanceTo(0.015)
    # Contact is declared once the force has held for contact_dwell.
    assert sup.GetOutputPort("phase").Eval(ctx)[0] == supervisor.Phase.APPROACH
    sim.AdvanceTo(0.015 + cfg.contact_dwell + 0.01)
    assert sup.GetOutputPort("phase").Eval(ctx)[0] == supervisor.Phase.EXPLORE
    assert sup.GetOutputPort("exploring").Eval(ctx)[0] == 1.0
    assert sup.GetOutputPort("segmentation_required").Eval(ctx)[0] == 1.0
    sup.GetInputPort("safety_stopped").FixValue(ctx, [1.0])
    sim.AdvanceTo(0.035 + cfg.contact_dwell)
    assert sup.GetOutputPort("abort").Eval(ctx)[0] == 1.0
    # Every vector output is the state's value (held in discrete state by the update).
    s = sup.state(ctx)
    expected = {
        "a_des": s.a_des,
        "o_des": s.o_des,
        "a_des_dot": s.a_des_dot,
        "P_des": s.P_des,
        "F_des": [s.F_des],
        "phase": [float(s.phase)],
        "segmentation_required": [float(supervisor.segmentation_required(s))],
        "exploring": [0.0],
        "abort": [1.0],
    }
    for name, value in expected.items():
        np.testing.assert_array_equal(sup.GetOutputPort(name).Eval(ctx), value, err_msg=name)


@pytest.mark.parametrize("estimate, explored", [(None, 0.05), (0.14, 0.07)])
def test_scan_supervisor_kidney_length_estimate_input(estimate, explored):
    """Unconnected, the estimate is NaN (EXPLORE ends at ER x L_m); connected, EXPLORE ends
    at ER x the estimate (``exploration_length: estimated``)."""
    import dataclasses

    cfg = dataclasses.replace(
        ControllerConfig(), exploration_ratio=0.5, kidney_length=0.1, exploration_length="estimated"
    )
    sup = ScanSupervisor(cfg)
    sim = Simulator(sup)
    ctx = sim.get_mutable_context()
    X = RigidTransform(RotationMatrix.MakeXRotation(math.pi), [0.55, 0.0, 0.12])
    sup.GetInputPort("X_BP").FixValue(ctx, X)
    sup.GetInputPort("contact_force").FixValue(ctx, [9.0])
    if estimate is not None:
        sup.GetInputPort("kidney_length_estimate").FixValue(ctx, [estimate])
    s = supervisor.SupervisorState()
    s.initialised, s.phase, s.P_des = True, supervisor.Phase.EXPLORE, np.array([0.55, 0.0])
    s.travel = 0.0495  # just short of 50 mm
    ctx.get_mutable_abstract_state(0).set_value(s)
    sim.AdvanceTo(0.5)
    state = sup.state(ctx)
    if estimate is None:
        assert state.phase == supervisor.Phase.LOCALIZE
        assert state.travel == pytest.approx(explored)
    else:
        assert state.phase == supervisor.Phase.EXPLORE and state.travel < explored
        sim.AdvanceTo(0.0205 / cfg.scan_speed + 0.2)  # 20.5 mm more at v_scan
        assert sup.state(ctx).phase == supervisor.Phase.LOCALIZE
        assert sup.state(ctx).travel == pytest.approx(explored)
        assert "estimated kidney length 140 mm" in sup.state(ctx).events[-1][2]


def test_kidney_section_and_view():
    X_BK = RigidTransform(RollPitchYaw(0, 0, math.pi / 2), [0.55, 0.0, 0.03])
    axes = [0.055, 0.03, 0.025]
    X_BP = RigidTransform(RotationMatrix.MakeXRotation(math.pi), [0.55, 0.0, 0.11])
    area, c = kidney_section(X_BP, X_BK, axes)
    # Transverse cut through the centre: an ellipse with semi-axes 30 mm (x) and 25 mm (z).
    assert area == pytest.approx(math.pi * 0.03 * 0.025, rel=0.08)
    assert c == pytest.approx(0.5, abs=0.01)
    shifted = RigidTransform(X_BP.rotation(), [0.53, 0.0, 0.11])  # probe 2 cm towards -x
    _, c2 = kidney_section(shifted, X_BK, axes)
    assert c2 > 0.55  # the kidney appears towards +x_P (image columns increase along x_P)
    far = RigidTransform(X_BP.rotation(), [0.55, 0.2, 0.11])
    assert kidney_section(far, X_BK, axes)[0] == 0.0
    view = GeometricKidneyView(X_BK, axes)
    ctx = view.CreateDefaultContext()
    view.GetInputPort("X_BP").FixValue(ctx, X_BP)
    sim = Simulator(view, ctx)
    sim.AdvanceTo(0.06)
    assert view.GetOutputPort("kidney_visible").Eval(sim.get_context())[0] == 1.0


def test_fault_injector_passes_through_then_corrupts():
    inj = FaultInjector("nan_pose", t_fault=0.1)
    ctx = inj.CreateDefaultContext()
    inj.GetInputPort("X_BP").FixValue(ctx, X_TILT)
    assert np.all(np.isfinite(inj.GetOutputPort("X_BP").Eval(ctx).translation()))
    ctx.SetTime(0.1)
    assert np.all(np.isnan(inj.GetOutputPort("X_BP").Eval(ctx).translation()))
    with pytest.raises(ValueError):
        FaultInjector("meteor")


def test_joints_for_tip_position(plant_and_frame):
    plant, frame = plant_and_frame
    kin = TipKinematics(plant, frame)
    target = kin.pose(Q0).translation() + [0.05, -0.05, 0.1]
    q = SolveTipPose(plant, frame, RigidTransform(kin.pose(Q0).rotation(), target), q_nominal=Q0)
    np.testing.assert_allclose(kin.pose(q).translation(), target, atol=1e-4)
    assert (
        laws.angle_between(
            kin.pose(q).rotation().matrix()[:, 2], kin.pose(Q0).rotation().matrix()[:, 2]
        )
        < 1e-3
    )
