"""A benchmark's JSON is strict JSON: NaN and infinities (a scan without a registration, a
CPU time not measured, a mean over no frames) are written as null, through the package's
``io_utils.dumps_strict``; Python's ``json.dumps`` writes ``NaN``, which JSON parsers
refuse."""

import ast
import json
import math
from pathlib import Path

import pytest

from benchmarks import real_anatomy

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def _refuse(constant):
    pytest.fail(f"the benchmark wrote {constant}, which is not JSON")


def plain_json_writes(folder: Path = BENCHMARKS) -> list[str]:
    """``json.dumps`` / ``json.dump`` calls in the modules of ``folder``."""
    out = []
    for path in sorted(folder.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            f = node.func if isinstance(node, ast.Call) else None
            if (
                isinstance(f, ast.Attribute)
                and f.attr in ("dumps", "dump")
                and isinstance(f.value, ast.Name)
                and f.value.id == "json"
            ):
                out.append(f"{path.name}:{node.lineno}")
    return out


def test_benchmarks_write_json_through_dumps_strict():
    assert plain_json_writes() == []


def test_the_plain_json_check_can_fail(tmp_path):
    (tmp_path / "b.py").write_text("import json\n\nprint(json.dumps({'x': 1}))\n")
    assert plain_json_writes(tmp_path) == ["b.py:3"]


def test_real_anatomy_writes_nan_as_null(tmp_path, monkeypatch, capsys):
    def fake_run_one(body, posture, *args):
        return {
            "body": str(body),
            "posture": posture,
            "status": "FAILED",
            "e_trans_mm": math.nan,
            "e_rot_x_deg": math.inf,
        }

    monkeypatch.setattr(real_anatomy, "run_one", fake_run_one)
    body = tmp_path / "body"
    body.mkdir()
    assert real_anatomy.main(["--patients", str(body), "--postures", "supine"]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    scan = json.loads(last, parse_constant=_refuse)["scans"][0]
    assert scan["e_trans_mm"] is None and scan["e_rot_x_deg"] is None
