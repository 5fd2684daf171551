"""The controller with the imaging chain in the loop: a virtual patient's emulated images
(slice sensor at 20 Hz) and the segmenter's visibility and mask centroid drive APPROACH and
EXPLORE (eq. 17) on the simulated station."""

import numpy as np
import pytest

from pydrake.systems.analysis import Simulator

from drake_rus.control import scan
from drake_rus.control.diagram import BuildClosedLoopOnPatient
from drake_rus.scenario import LoadScenario

pytestmark = pytest.mark.slow


def test_exploration_on_a_virtual_patient_keeps_the_kidney_centred():
    s = LoadScenario(scenario_text="{patient: {source: 'test:0'}, imaging: {segmenter: oracle}}")
    cl, s = BuildClosedLoopOnPatient(s, "test:0", log_period=0.05)
    sim = Simulator(cl.diagram)
    ctx = sim.get_mutable_context()
    sup = cl.parts.supervisor
    sup_ctx = sup.GetMyContextFromRoot(ctx)
    while sup.state(sup_ctx).phase == scan.Phase.APPROACH and ctx.get_time() < 6.0:
        sim.AdvanceTo(ctx.get_time() + 0.25)
    assert sup.state(sup_ctx).phase == scan.Phase.EXPLORE, sup.state(sup_ctx).events
    t_explore = sup.state(sup_ctx).events[-1][0]
    sim.AdvanceTo(t_explore + 3.0)
    st = sup.state(sup_ctx)
    safety = cl.parts.safety.safety_state(cl.parts.safety.GetMyContextFromRoot(ctx))
    assert not safety.events
    assert st.phase == scan.Phase.EXPLORE and st.travel > 0.014
    L = {k: v.FindLog(ctx) for k, v in cl.loggers.items()}
    t = L["mask_centroid"].sample_times()
    m = t >= t_explore + 1.0
    c = L["mask_centroid"].data()[0][m]
    vis = L["kidney_visible"].data()[0][m]
    F = -L["probe_force"].data()[5][m]
    print(f"\nvirtual patient test:0 (oracle segmenter): kidney visible {vis.mean():.2f} of "
          f"frames, centroid {c.min():.3f}-{c.max():.3f}, F {F.min():.2f}-{F.max():.2f} N")
    assert np.all(vis == 1.0)
    assert np.all(np.abs(c - 0.5) <= 0.1)
    assert np.all(np.abs(F - 9.0) <= 0.5)
