"""scripts/pip_install.sh: the Makefile's pip step says how much disk it needs and, when pip
fails, how much was free where pip writes, instead of leaving a bare "[Errno 28]"."""

import os
import shutil
import stat
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "pip_install.sh"


def _fake_venv(tmp_path: Path, pip_exit: int) -> Path:
    """A venv whose python records its arguments and exits with ``pip_exit``."""
    venv = tmp_path / "venv"
    (venv / "bin").mkdir(parents=True)
    python = venv / "bin" / "python"
    python.write_text(f'#!/usr/bin/env bash\necho "$@" > "{tmp_path}/args"\nexit {pip_exit}\n')
    python.chmod(python.stat().st_mode | stat.S_IXUSR)
    return venv


def _run(venv: Path, need_mb: int, tmp_path: Path):
    env = dict(os.environ, TMPDIR=str(tmp_path))
    return subprocess.run(
        ["bash", str(SCRIPT), str(venv), str(need_mb), "the test extra", "-e", ".[test]"],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
    )


def test_success_passes_the_arguments_to_pip_and_says_nothing(tmp_path):
    venv = _fake_venv(tmp_path, 0)
    done = _run(venv, 1, tmp_path)
    assert done.returncode == 0, done.stderr
    assert done.stderr == ""
    assert (tmp_path / "args").read_text().split() == [
        "-m",
        "pip",
        "install",
        "--quiet",
        "-e",
        ".[test]",
    ]


def test_failure_keeps_pips_exit_and_names_the_free_space(tmp_path):
    venv = _fake_venv(tmp_path, 3)
    done = _run(venv, 1, tmp_path)
    assert done.returncode == 3
    assert "pip could not install the test extra (exit 3)" in done.stderr
    assert f"in {venv}" in done.stderr and f"in {tmp_path}" in done.stderr
    assert "MB free now" in done.stderr and "? MB" not in done.stderr


def test_too_little_space_is_said_before_pip_runs(tmp_path):
    venv = _fake_venv(tmp_path, 0)
    free_mb = shutil.disk_usage(venv).free // 2**20
    done = _run(venv, free_mb + 10**7, tmp_path)
    assert done.returncode == 0
    assert f"needs about {free_mb + 10**7} MB in {venv}" in done.stderr
    assert (tmp_path / "args").exists()


def test_the_makefile_installs_through_it():
    makefile = (ROOT / "Makefile").read_text()
    pip_lines = [line for line in makefile.splitlines() if "pip install" in line]
    assert pip_lines, "the Makefile no longer installs with pip"
    # Only pip's own upgrade bypasses the script (it needs no space to speak of).
    assert [line for line in pip_lines if "--upgrade pip" not in line] == []
    assert makefile.count("scripts/pip_install.sh") >= 3
