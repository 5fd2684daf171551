"""The controller with the imaging chain in the loop: a virtual patient's emulated images
(slice sensor at 20 Hz) and the segmenter's visibility and mask centroid drive the whole scan
(APPROACH -> EXPLORE (eq. 17) -> LOCALIZE (ground-truth X_BK stand-in) -> TRANSIT -> PIVOT
(eq. 23) -> DONE) on the simulated station."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator

from drake_rus.closed_loop import AdvanceUntilScanEnds, BuildClosedLoopOnPatient
from drake_rus.control import supervisor
from drake_rus.scenario import LoadScenario

pytestmark = pytest.mark.slow


def test_full_scan_on_a_virtual_patient_with_emulated_images_and_segmenter():
    s = LoadScenario(
        scenario_text="{patient: {source: 'test:0'}, imaging: {segmenter: oracle}, "
        "controller: {exploration_ratio: 0.3, pivot_rate: 0.15}}"
    )
    cl, s = BuildClosedLoopOnPatient(s, "test:0", log_period=0.05)
    sim = Simulator(cl.diagram)
    ctx = sim.get_mutable_context()
    sup = cl.parts.supervisor
    sup_ctx = sup.GetMyContextFromRoot(ctx)
    AdvanceUntilScanEnds(sim, sup, 40.0)
    st = sup.state(sup_ctx)
    print("\nsupervisor events:", *st.events, sep="\n  ")
    safety = cl.parts.safety.safety_state(cl.parts.safety.GetMyContextFromRoot(ctx))
    assert not safety.events
    assert [e[1] for e in st.events] == [
        "APPROACH",
        "EXPLORE",
        "LOCALIZE",
        "TRANSIT",
        "PIVOT",
        "PIVOT",
        "PIVOT",
        "DONE",
    ]
    L = {k: v.FindLog(ctx) for k, v in cl.loggers.items()}
    t = L["phase"].sample_times()
    phase = L["phase"].data()[0]
    c = L["mask_centroid"].data()[0]
    vis = L["kidney_visible"].data()[0]
    F = -L["probe_force"].data()[5]
    t_explore = [e[0] for e in st.events if e[1] == "EXPLORE"][0]
    explore = (phase == supervisor.Phase.EXPLORE) & (t >= t_explore + 1.0)
    pivot = phase == supervisor.Phase.PIVOT
    kin = cl.parts.ik.kinematics
    p = np.array([kin.pose(q).translation() for q in L["q"].data().T])
    d = np.linalg.norm(p[pivot, :2] - st.p_star[:2], axis=1)
    print(
        f"EXPLORE: kidney visible {vis[explore].mean():.2f}, centroid "
        f"{c[explore].min():.3f}-{c[explore].max():.3f}, F {F[explore].min():.2f}-"
        f"{F[explore].max():.2f} N; PIVOT: tip within {d.max() * 1e3:.2f} mm of p*, legs "
        f"{np.degrees(st.pivot_limits[0]):.1f} / {np.degrees(st.pivot_limits[1]):.1f} deg, "
        f"F {F[pivot].min():.2f}-{F[pivot].max():.2f} N"
    )
    assert np.all(vis[explore] == 1.0)
    assert np.all(np.abs(c[explore] - 0.5) <= 0.1)
    assert np.all(np.abs(F[explore] - 9.0) <= 0.5)
    assert d.max() <= 0.002
    legs = [e for e in st.events if e[1] == "PIVOT" and "leg" in e[2]]
    assert all("kidney left the image" in e[2] for e in legs)
    assert st.pivot_limits[0] * st.pivot_limits[1] < 0
    assert np.all(np.abs(F[pivot] - 9.0) <= 1.0)
