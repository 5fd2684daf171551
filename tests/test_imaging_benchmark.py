"""The imaging benchmark runs and prints its JSON keys last (speeds are not asserted)."""

import json
import subprocess
import sys

from drake_rus.paths import REPO_ROOT


def test_benchmark_prints_the_json_last():
    out = subprocess.run(
        [sys.executable, "-m", "benchmarks", "imaging", "--source", "phantom", "--patients",
         "1", "--iou-frames", "6", "--frames", "6"],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=300, check=True).stdout
    result = json.loads(out.strip().splitlines()[-1])
    for key in ("fps_slice", "fps_slice_emulate", "fps_full", "iou_classical", "iou_onnx"):
        assert key in result
    assert result["fps_slice"] > 0 and 0.0 <= result["iou_classical"] <= 1.0
