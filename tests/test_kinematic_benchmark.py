"""The localization benchmark on one patient: its last line is one JSON object with the
fields the issue asks for (mode, three methods, ms per registration, the paper's numbers)."""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_localization_benchmark_one_patient():
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "benchmarks",
            "localization",
            "--patients",
            "test:7",
            "--no-progress",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    last = proc.stdout.strip().splitlines()[-1]
    out = json.loads(last)
    assert out["mode"] == "kinematic" and out["exploration_ratio"] == 0.6
    assert out["patients"] == ["test:7"]
    for m in ("seed", "deformable", "open3d_point_to_plane"):
        s = out["methods"][m]
        assert s["e_trans_mm"]["n"] == 1 and s["ms_per_registration"]["mean"] > 0
        # A generous bound: a broken pipeline gives tens of mm.
        assert s["e_trans_mm"]["mean"] < 15 and s["e_rot_x_deg"]["mean"] < 15
    assert out["paper"]["e_trans_mm"] == {"mean": 8.73, "sd": 6.93}
    assert out["paper"]["e_rot_x_deg"] == {"mean": 12.86, "sd": 20.86}
