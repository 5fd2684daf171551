"""Optional dependencies: which extra of ``pyproject.toml`` installs each, and one line saying
so when one is missing.

``pip install -e .`` (``make demo``) installs what the scan, the studies and the pictures
need; the real robot and the rehearsal need the ``hardware`` extra (OpenCV, franky), training
the segmenter the ``train`` extra, the notebooks the ``notebooks`` extra.
"""

import importlib

# Importable module -> (extra of pyproject.toml, what it is).
EXTRAS = {
    "cv2": ("hardware", "OpenCV"),
    "franky": ("hardware", "franky-control"),
    "torch": ("train", "PyTorch"),
    "onnx": ("train", "onnx"),
    "sympy": ("train", "sympy"),
    "jupyterlab": ("notebooks", "JupyterLab"),
}


class MissingExtra(ImportError, ValueError):
    """An optional dependency is not installed. A ValueError too, so the command line prints
    it as one line (exit status 2) like any other user error."""


def install_hint(extra: str) -> str:
    """The command that installs ``extra`` (run in the repository, with the project's pip:
    ``.venv/bin/pip`` after ``make demo``)."""
    return f"pip install -e '.[{extra}]'"


def missing_extra_message(module: str, needed_by: str) -> str:
    extra, what = EXTRAS[module]
    return (
        f"{needed_by} needs {what} (module {module}), part of the '{extra}' extra: "
        f"{install_hint(extra)}"
    )


def require(module: str, needed_by: str):
    """Imports and returns ``module`` (a key of ``EXTRAS``), or raises MissingExtra saying in
    one line which extra installs it."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise MissingExtra(missing_extra_message(module, needed_by), name=module) from None
