"""Bad-input corpus, templates: a kidney template file (scenario field
``localization.template``) is validated when loaded. Each defect gives exit status 2 and one
line naming the scenario field, the file and the array field, and nothing is written to
--out (the template is read before the output folder is made)."""

import json

import numpy as np
import pytest

from drake_rus.cli import main
from drake_rus.template.io import DEFAULT_TEMPLATE_PATH, check_template_arrays, load_template


def _shipped():
    with np.load(DEFAULT_TEMPLATE_PATH, allow_pickle=False) as z:
        return {k: z[k] for k in ("points", "normals", "modes", "variances", "metadata")}


def _few(a):
    a = dict(a)
    a["points"], a["normals"], a["modes"] = (
        a["points"][:50],
        a["normals"][:50],
        a["modes"][:, :50],
    )
    return a


def _set(field, fn):
    def change(a):
        a = dict(a)
        a[field] = fn(np.array(a[field]))
        return a

    return change


def _rows(field, rows, value):
    def fn(x):
        x = x.astype(float)
        x[rows] = value
        return x

    return _set(field, fn)


def _scale_rows(field, rows, factor):
    def fn(x):
        x = x.astype(float)
        x[rows] = x[rows] * factor
        return x

    return _set(field, fn)


# (id, change of the shipped arrays, words the message must contain)
CASES = [
    (
        "zero_normals",
        _set("normals", np.zeros_like),
        ["'normals'", "2500 of 2500 are not unit vectors", "|n| = 0"],
    ),
    (
        "some_long_normals",
        _scale_rows("normals", slice(0, 12), 2.0),
        ["'normals'", "12 of 2500 are not unit vectors", "|n| = 2"],
    ),
    ("nan_normals", _rows("normals", 5, np.nan), ["'normals'", "1 of 2500 rows", "NaN"]),
    ("inf_points", _rows("points", [3, 7], np.inf), ["'points'", "2 of 2500 rows", "inf"]),
    ("points_in_mm", _set("points", lambda p: p * 1000.0), ["'points'", "metres"]),
    ("off_centre", _set("points", lambda p: p + [0.05, 0.0, 0.0]), ["'points'", "centroid"]),
    ("too_few_points", _few, ["'points'", "50 points", "at least 100"]),
    ("normals_shape", _set("normals", lambda n: n[:, :2]), ["'normals'", "(M, 3)"]),
    ("text_points", _set("points", lambda p: p.astype(str)), ["'points'", "numbers"]),
    ("inf_variance", _rows("variances", 0, np.inf), ["'variances'", "inf", "positive"]),
    ("nan_variance", _rows("variances", 2, np.nan), ["'variances'", "nan"]),
    ("negative_variance", _rows("variances", 1, -1e-4), ["'variances'", "-0.0001"]),
    ("zero_variance", _rows("variances", 3, 0.0), ["'variances'", "positive"]),
    ("huge_variance", _rows("variances", 0, 1e6), ["'variances'", "kidney's length"]),
    ("variance_count", _set("variances", lambda v: v[:4]), ["'variances'", "(6,)"]),
    ("modes_shape", _set("modes", lambda m: m[:, :2000]), ["'modes'", "(k, M, 3)"]),
    ("modes_not_unit", _scale_rows("modes", 1, 3.0), ["'modes'", "mode 1: 3"]),
    (
        "nan_modes",
        _set("modes", lambda m: np.where(np.arange(m.size).reshape(m.shape) == 7, np.nan, m)),
        ["'modes'", "NaN"],
    ),
]


@pytest.fixture(scope="module")
def shipped():
    return _shipped()


def _write(tmp_path, arrays, name="bad_template.npz"):
    path = tmp_path / name
    np.savez(path, **arrays)
    return path


@pytest.mark.parametrize("case,change,words", CASES, ids=[c[0] for c in CASES])
def test_bad_template_refused_by_the_scan(tmp_path, capsys, shipped, case, change, words):
    path = _write(tmp_path, change(shipped))
    out = tmp_path / "scan"
    code = main(
        [
            "scan",
            "--patient",
            "test:0",
            "--out",
            str(out),
            "--no-record",
            "--set",
            f"{{localization: {{template: '{path}'}}}}",
        ]
    )
    err = capsys.readouterr().err
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err  # one line, no traceback
    assert lines[0].startswith("drake-rus scan: error:")
    for w in ["localization.template", "bad_template.npz", *words]:
        assert w in lines[0], (w, lines[0])
    assert not out.exists()


def test_the_shipped_template_passes():
    a = _shipped()
    assert check_template_arrays(a["points"], a["normals"], a["modes"], a["variances"]) == ""
    t = load_template()
    assert t.points.shape == (2500, 3) and t.variances.shape == (len(t.modes),)


def test_a_template_without_modes_is_valid(tmp_path, shipped):
    arrays = dict(shipped, modes=np.zeros((0, 2500, 3)), variances=np.zeros(0))
    t = load_template(_write(tmp_path, arrays, "rigid.npz"))
    assert len(t.modes) == 0


def test_float32_template_is_valid(tmp_path, shipped):
    arrays = {k: (v.astype(np.float32) if k != "metadata" else v) for k, v in shipped.items()}
    t = load_template(_write(tmp_path, arrays, "single.npz"))
    assert t.points.dtype == np.float64 and t.normals.dtype == np.float64


def test_template_info_names_the_field(tmp_path, capsys, shipped):
    path = _write(tmp_path, _set("normals", np.zeros_like)(shipped))
    code = main(["template", "info", str(path)])
    err = capsys.readouterr().err
    assert code == 2 and "bad_template.npz" in err and "'normals'" in err, err


def test_metadata_still_checked_first(tmp_path, shipped):
    arrays = dict(shipped, metadata=json.dumps({"a": 1})[:-1])
    with pytest.raises(ValueError, match="'metadata' is not valid JSON"):
        load_template(_write(tmp_path, arrays))
