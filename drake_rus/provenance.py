"""What a run needs to be repeated: the resolved scenario, the overrides, the seeds, the
package versions and the project's commit (``summary.json``'s ``provenance``; every study
run's record).

Everything here is read locally (package metadata, the ``.git`` folder beside the package);
nothing touches the network. A checkout without git reports the commit as None.
"""

from __future__ import annotations

import datetime
import platform
import subprocess
import sys
from importlib import metadata

from drake_rus.paths import REPO_ROOT

# The packages whose versions can change a run's numbers (simulation, geometry, imaging,
# registration, compiled kernels).
RESULT_PACKAGES = (
    "drake",
    "numpy",
    "scipy",
    "open3d",
    "trimesh",
    "onnxruntime",
    "numba",
    "scikit-image",
    "SimpleITK",
    "pynrrd",
)


def package_versions(names=RESULT_PACKAGES) -> dict:
    """{package: version or None (not installed)} for ``names``, plus drake-rus itself."""
    versions = {"drake-rus": _version("drake-rus")}
    for name in names:
        versions[name] = _version(name)
    return versions


def _version(name: str) -> str | None:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def cpu_model(cpuinfo: str = "/proc/cpuinfo") -> str | None:
    """The processor's model name (Linux ``/proc/cpuinfo``; else ``platform.processor()``,
    None when neither names it). Compiled kernels (onnxruntime's int8 matrix products,
    BLAS) choose their code by the instruction set, so two machines may round differently."""
    try:
        with open(cpuinfo, encoding="utf-8", errors="replace") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key.strip() == "model name" and value.strip():
                    return value.strip()
    except OSError:
        pass
    return platform.processor() or None


def project_commit() -> dict:
    """{"commit": sha or None, "dirty": bool or None}: the checkout the code runs from."""
    if not (REPO_ROOT / ".git").exists():
        return {"commit": None, "dirty": None}
    try:
        sha = subprocess.run(
            ["git", "-C", str(REPO_ROOT), "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=5,
        )
        status = subprocess.run(
            ["git", "-C", str(REPO_ROOT), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=5,
        )
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "dirty": None}
    if sha.returncode != 0:
        return {"commit": None, "dirty": None}
    return {
        "commit": sha.stdout.strip() or None,
        "dirty": bool(status.stdout.strip()) if status.returncode == 0 else None,
    }


def Provenance(
    scenario=None,
    *,
    scenario_name: str | None = None,
    scenarios_file: str | None = None,
    overrides: str | None = None,
    seeds: dict | None = None,
    argv: list[str] | None = None,
) -> dict:
    """The record that lets a run be repeated.

    ``scenario``: the resolved ``Scenario`` (stored whole as YAML, so a rerun needs neither
    the scenarios file nor the overrides); ``scenario_name``, ``scenarios_file`` and
    ``overrides`` (the ``--set`` text) say how it was made; ``seeds`` every seed that drew a
    random number ({"random_seed": 0, "patient": "test:0", ...}); ``argv`` the command line.
    """
    record = {
        "created_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "argv": list(sys.argv if argv is None else argv),
        "scenario_name": scenario_name,
        "scenarios_file": None if scenarios_file is None else str(scenarios_file),
        "overrides": overrides,
        "seeds": dict(seeds or {}),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpu": cpu_model(),
        "packages": package_versions(),
        **project_commit(),
    }
    if scenario is not None:
        # Imported here: provenance is a core helper below the scenario layer.
        from pydrake.common.yaml import yaml_dump_typed

        record["scenario_yaml"] = yaml_dump_typed(scenario)
        record["seeds"].setdefault("random_seed", int(scenario.random_seed))
    return record
