"""Issue 17: the notebooks show their figures when executed headless (the inline backend, as
in Jupyter) and guide the user when the data they need are missing."""

import os
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


def test_paper_notebook_draws_a_small_study(tmp_path, monkeypatch):
    """A tiny kinematic er-sweep (one patient, two ERs, coarse voxels), then the notebook,
    told where the study is by a path relative to the repository's root (as after
    `drake-rus study ... --out reports/small` and `make notebooks`: the kernel runs in
    notebooks/)."""
    from drake_rus.cli import main

    study = tmp_path / "study"
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
    monkeypatch.setenv("DRAKE_RUS_STUDY_DIR", os.path.relpath(study, NOTEBOOKS.parent))
    nb = _execute("reproduce_paper.ipynb")
    assert len(_outputs(nb, "image/png")) >= 1  # Fig. 7d
    text = "".join(o["data"]["text/markdown"] for o in _outputs(nb, "text/markdown"))
    assert "no runs of starts, efficiency" in text
    assert (study / "notebook" / "fig7d_er_sweep.png").stat().st_size > 0
