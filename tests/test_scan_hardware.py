"""The autonomous scan on the hardware station (the unchanged scan diagram), against
franky-sim on 127.0.0.1: paced at real time, inside the zero-velocity session; in free air
(franky-sim has no patient) APPROACH ends in a clear ABORT and the arm comes to rest."""

import numpy as np
import pytest

from drake_rus.localization.localize import load_registration_template
from drake_rus.scan import RunScan, ScanMetrics, Summary

pytest.importorskip("franky")
from test_hardware_franky import franky_scenario, franky_sim, video_file  # noqa: E402,F401

pytestmark = pytest.mark.wallclock


def test_hardware_scan_in_free_air_aborts_no_contact_at_rest(franky_sim, video_file):  # noqa: F811
    scenario = franky_scenario(franky_sim.host, video_file)
    template = load_registration_template(scenario.localization.template)
    result = RunScan(scenario, None, template, max_sim_time=30.0, progress=False, settle=0.5)
    summary = Summary(result, ScanMetrics(result))
    assert result.status == "ABORT", (result.status, result.reason)
    assert result.reason.startswith("no contact"), result.reason
    assert summary["mode"].startswith("hardware: FR3 at 127.0.0.1")
    assert str(video_file) in summary["mode"]
    assert summary["e_trans_mm"] is None and summary["volume_ratio"] is None  # no truth
    # Paced at real time: the wall clock kept up with the simulated time.
    assert result.wall_s >= 0.9 * result.sim_s
    # After the stop the joints do not move: the last 0.3 s of logged positions are still.
    t, q = result.logs["q"]
    late = t >= t[-1] - 0.3
    assert late.sum() >= 5
    assert np.max(np.ptp(q[:, late], axis=1)) < 2e-3
