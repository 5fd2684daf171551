"""The imaging benchmark runs and prints its JSON keys last (speeds are not asserted)."""

import json
import subprocess
import sys

from drake_rus.imaging.config import ImagingConfig
from drake_rus.paths import REPO_ROOT


def test_benchmark_prints_the_json_last():
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "benchmarks",
            "imaging",
            "--source",
            "phantom",
            "--patients",
            "1",
            "--iou-frames",
            "6",
            "--frames",
            "6",
            "--depth-patients",
            "1",
            "--depth-views",
            "3",
            "--speed-frames",
            "3",
            "--no-progress",
        ],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    ).stdout
    result = json.loads(out.strip().splitlines()[-1])
    for key in ("fps_slice", "fps_slice_emulate", "fps_full", "iou_classical", "iou_onnx"):
        assert key in result
    assert result["fps_slice"] > 0 and 0.0 <= result["iou_classical"] <= 1.0
    # The per-depth table (one row per preset), the per-preset speed; no VH body here.
    presets = [f"{d:.2f}" for d in ImagingConfig().depth_presets]
    assert sorted(result["iou_by_depth"]) == sorted(presets)
    for d in presets:  # one phantom: its interval is the point itself
        lo, hi = result["iou_by_depth_ci95"][d]
        assert lo <= result["iou_by_depth"][d] + 1e-3 and result["iou_by_depth"][d] <= hi + 1e-3
    assert sorted(result["ms_model_resample"]) == sorted(presets)
    assert all(v > 0 for v in result["ms_model_resample"].values())
    assert result["vh_female_iou"] is None
    assert "held-out generated patients" in out and "segmenter speed" in out
