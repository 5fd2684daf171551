"""Issue 17: the notebooks show their figures when executed headless (the inline backend, as
in Jupyter) and guide the user when the data they need are missing."""

import json
import os
import shutil
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = Path(__file__).resolve().parent.parent / "notebooks"

pytestmark = pytest.mark.slow


def _execute(name: str) -> nbformat.NotebookNode:
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    NotebookClient(
        nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(NOTEBOOKS)}}
    ).execute()
    return nb


def _outputs(nb, kind: str) -> list:
    return [
        o
        for c in nb.cells
        if c.cell_type == "code"
        for o in c.get("outputs", [])
        if kind in o.get("data", {})
    ]


def test_controller_notebook_shows_its_figures(monkeypatch):
    monkeypatch.setenv("DRAKE_RUS_NOTEBOOK_INTERACTIVE", "0")
    monkeypatch.setenv("DRAKE_RUS_NOTEBOOK_HORIZON", "0.5")
    nb = _execute("controller_tuning.ipynb")
    figures = _outputs(nb, "image/png")
    # The live-run figure (force, approach error) and the step responses.
    assert len(figures) >= 2, [c.get("outputs") for c in nb.cells if c.cell_type == "code"]
    assert all(len(o["data"]["image/png"]) > 1000 for o in figures)


def test_paper_notebook_without_a_study_guides_the_user(tmp_path, monkeypatch):
    study = tmp_path / "no_study"
    monkeypatch.setenv("DRAKE_RUS_STUDY_DIR", str(study))
    nb = _execute("reproduce_paper.ipynb")
    text = "".join(o["data"]["text/markdown"] for o in _outputs(nb, "text/markdown"))
    assert "No study results" in text and "drake-rus study" in text
    assert not _outputs(nb, "image/png")
    assert not study.exists()  # nothing created beside a missing study


@pytest.fixture(scope="module")
def small_study(tmp_path_factory):
    """A tiny kinematic er-sweep (one patient, two ERs, coarse voxels)."""
    from drake_rus.cli import main

    study = tmp_path_factory.mktemp("small") / "study"
    assert (
        main(
            [
                "study",
                "er-sweep",
                "--patients",
                "test:0",
                "--ers",
                "0.6,1",
                "--workers",
                "0",
                "--voxel",
                "0.004",
                "--out",
                str(study),
                "--no-progress",
            ]
        )
        == 0
    )
    return study


def test_paper_notebook_draws_a_small_study(small_study, tmp_path, monkeypatch):
    """The notebook on the tiny study, told where it is by a path relative to the
    repository's root (as after `drake-rus study ... --out reports/small` and `make
    notebooks`: the kernel runs in notebooks/)."""
    study = tmp_path / "study"
    shutil.copytree(small_study, study)
    monkeypatch.setenv("DRAKE_RUS_STUDY_DIR", os.path.relpath(study, NOTEBOOKS.parent))
    nb = _execute("reproduce_paper.ipynb")
    assert len(_outputs(nb, "image/png")) >= 1  # Fig. 7d
    text = "".join(o["data"]["text/markdown"] for o in _outputs(nb, "text/markdown"))
    assert "no runs of starts, efficiency" in text
    assert (study / "notebook" / "fig7d_er_sweep.png").stat().st_size > 0


def test_paper_notebook_draws_each_mode_on_its_own(small_study, tmp_path, monkeypatch):
    """A study folder holding kinematic runs and closed-loop scans of the same patient and
    ERs (both modes share OUT/runs, as `drake-rus study --mode closed-loop` into the same
    folder leaves it): each mode is its own figure (in its own folder) and table, never one
    mode's run of a patient standing in for the other's."""
    study = tmp_path / "study"
    shutil.copytree(small_study, study)
    kinematic = {}
    for path in sorted((study / "runs").glob("er-sweep__*.json")):
        run = json.loads(path.read_text())
        kinematic[run["er"]] = run["e_trans_mm"]
        # The same run as a closed-loop scan 40 mm off (only its errors matter here).
        run["run_id"] += "__cl"
        run["task"]["mode"] = run["mode"] = "closed-loop"
        run["status"] = "DONE"
        run["e_trans_mm"] = 40.0 + run["er"]
        (study / "runs" / f"{run['run_id']}.json").write_text(json.dumps(run))
    monkeypatch.setenv("DRAKE_RUS_STUDY_DIR", str(study))
    nb = _execute("reproduce_paper.ipynb")
    cell = next(c for c in nb.cells if "analyze_er_sweep(" in c.source)  # Fig. 7d's
    text = "".join(
        o["data"]["text/markdown"] for o in cell.outputs if "text/markdown" in o.get("data", {})
    )
    tables = text.split("| ER | E_trans (mm)")[1:]
    assert len(tables) == 2, text
    for er, e_trans in kinematic.items():
        assert f"| {er * 100:.0f}% | {e_trans:.2f} +- 0.00 |" in tables[0], tables[0]
        assert f"| {er * 100:.0f}% | {40.0 + er:.2f} +- 0.00 |" in tables[1], tables[1]
    assert (study / "notebook" / "fig7d_er_sweep.png").stat().st_size > 0
    assert (study / "notebook" / "closed-loop" / "fig7d_er_sweep.png").stat().st_size > 0
    assert sum("image/png" in o.get("data", {}) for o in cell.outputs) == 2
