"""Wall time of the full closed-loop scan (``python -m benchmarks scan``).

Runs ``drake-rus scan``'s pipeline on one test patient (patient generation is not timed) and
reports the simulated time over the wall time, next to the free-motion real-time rate of the
bare station measured in the same run (the machines are noisy: compare ratios). The last line
is one JSON object.
"""

import argparse
import json

from drake_rus.scenario import LoadScenario


def main(argv=None) -> int:
    from benchmarks.station import _free_run
    from drake_rus.anatomy import load_patient
    from drake_rus.localization.localize import load_registration_template
    from drake_rus.scan import RunScan, ScanMetrics, Summary

    parser = argparse.ArgumentParser(prog="python -m benchmarks scan")
    parser.add_argument("--patient", default="test:0")
    parser.add_argument("--scenario", default="default")
    args = parser.parse_args(argv)
    scenario = LoadScenario(scenario_name=args.scenario)
    patient = load_patient(args.patient)
    _ = patient.labels  # build the label volume outside the timed part
    template = load_registration_template(scenario.localization.template)
    free = _free_run(scenario, 5.0)
    result = RunScan(scenario, patient, template, progress=False)
    summary = Summary(result, ScanMetrics(result))
    rtf = result.sim_s / result.wall_s
    print(json.dumps({
        "status": summary["status"], "patient": args.patient,
        "scan_sim_s": round(result.sim_s, 2), "scan_wall_s": round(result.wall_s, 2),
        "rtf_scan": round(rtf, 3), "rtf_free_station": round(free["rtf"], 3),
        "ratio_scan_to_free_station": round(rtf / free["rtf"], 3),
        "phases": {p["phase"]: round(p["duration_s"], 2) for p in summary["phases"]},
        "volume_ratio": round(summary["volume_ratio"], 3),
        "e_trans_mm": summary["e_trans_mm"], "e_rot_x_deg": summary["e_rot_x_deg"],
    }))
    return 0
