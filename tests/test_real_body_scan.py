"""The default scan, closed loop, on a real body: the Visible Human female's left kidney.

At 136 mm it is the longest kidney we have (her right one is 113 mm, the generated ones
89-141 mm) and the one the partial cloud's length estimate misses most (about 110 mm after
the exploration). With the paper's ER of 60% of that estimate the exploration covered 49% of
the kidney and E_trans was 13.3 mm; the default ER (70%) explores past the length the
estimate settles at, and the estimate follows (README, "Exploration ratio"). Skipped
without ../shared beside the clone.
"""

import math

from conftest import HUBMAP, needs_hubmap

from drake_rus.anatomy import load_patient
from drake_rus.localization.localize import load_registration_template
from drake_rus.scan import RunScan, ScanMetrics, Summary
from drake_rus.scenario import ApplyOverrides, LoadScenario


@needs_hubmap
def test_default_scan_localizes_the_long_real_left_kidney():
    scenario = ApplyOverrides(LoadScenario(), "{patient: {side: left}}")
    patient = load_patient(str(HUBMAP), side="left", posture="supine")
    template = load_registration_template(scenario.localization.template)
    result = RunScan(scenario, patient, template, progress=False)
    summary = Summary(result, ScanMetrics(result))
    assert summary["status"] == "DONE", result.reason
    # Issue 13's real-body target (E_trans <= 10 mm, V >= 0.9); measured 5.1 mm, V 1.00.
    assert summary["e_trans_mm"] <= 10.0
    assert summary["volume_ratio"] >= 0.9
    explore = [end - start for name, start, end in result.phases if name == "EXPLORE"]
    # 70% of an estimate that ends near 125 mm at 5 mm/s: about 17.5 s, against 13.3 s at
    # the paper's 60% (which stopped before the estimate grew past 110 mm).
    assert len(explore) == 1 and explore[0] > 15.0
    assert math.isfinite(summary["e_rot_x_deg"]) and summary["e_rot_x_deg"] < 10.0
