"""A live station (one that can ``stop()`` a robot) runs paced at real time, inside a session
that commands zero velocity on exit, and is stopped when the diagram falls
``safety.realtime_lag`` behind the wall clock: its commands would reach the robot late.

The station here is the simulated one given a ``stop()``, so RunScan treats it as live; a
monitor stalls the loop once for 0.6 s of wall time, like a busy PC. Its perception runs in
worker processes beside the loop (perception.execution: auto); the image watchdog, which
then also counts the segmentation's latency, is set to 1 s so that a busy CI machine's slow
segmentations do not end these runs first (tests/test_realtime.py covers that).
"""

import time

import pytest

from drake_rus.anatomy.cohort import load_patient
from drake_rus.localization.localize import load_registration_template
from drake_rus.scan import RunScan, ScanMonitor
from drake_rus.scenario import ApplyOverrides, LoadScenario
from drake_rus.stations import MakeStation

pytestmark = pytest.mark.wallclock

STALL_AT = 0.8  # simulated s
STALL_FOR = 0.6  # wall s


class StallOnce(ScanMonitor):
    def __init__(self):
        self.done = False

    def observe(self, root_context):
        if not self.done and root_context.get_time() >= STALL_AT:
            self.done = True
            time.sleep(STALL_FOR)


@pytest.fixture(scope="module")
def patient_and_template():
    scenario = LoadScenario()
    return load_patient("test:0", progress=False), load_registration_template(
        scenario.localization.template
    )


def _run_live(lag: float, patient, template, max_sim_time: float):
    scenario = ApplyOverrides(
        LoadScenario(), "{safety: {realtime_lag: %g, image_timeout: 1.0}}" % lag
    )
    stops = []

    def make_live_station(scenario, meshcat=None, patient=None):
        station = MakeStation(scenario, meshcat=meshcat, patient=patient)
        station.stop = lambda: stops.append(time.perf_counter())
        return station

    result = RunScan(
        scenario,
        patient,
        template,
        make_station=make_live_station,
        max_sim_time=max_sim_time,
        progress=False,
        monitors=[StallOnce()],
    )
    return result, stops


def test_a_live_run_that_falls_behind_real_time_is_stopped(patient_and_template):
    result, stops = _run_live(0.3, *patient_and_template, max_sim_time=3.0)
    assert result.status == "ABORT", (result.status, result.reason)
    assert "behind real time" in result.reason and "safety.realtime_lag 0.3 s" in result.reason
    assert STALL_AT <= result.sim_s < STALL_AT + 0.2  # stopped right after the stall
    assert len(stops) == 1  # the session's zero velocity
    # Paced at real time until then: the wall clock kept up with the simulated time.
    assert result.wall_s >= 0.9 * result.sim_s


def test_the_lag_limit_is_the_scenario_s(patient_and_template):
    # The same stall under a 1 s limit: the run goes on (the schedule slips by the stall).
    result, stops = _run_live(1.0, *patient_and_template, max_sim_time=1.5)
    assert "behind real time" not in result.reason, result.reason
    assert result.sim_s == pytest.approx(1.5, abs=0.05)
    assert len(stops) == 1
