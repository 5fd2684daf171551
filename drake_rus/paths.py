"""Where the repository's files live, and the package map for ``package://drake_rus_models``."""

from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent
MODELS_DIR = REPO_ROOT / "models"
DIAGRAMS_DIR = REPO_ROOT / "diagrams"


def AddDrakeRusPackages(package_map) -> None:
    """Registers ``drake_rus_models`` (models/package.xml) on a Drake PackageMap."""
    if not package_map.Contains("drake_rus_models"):
        package_map.AddPackageXml(str(MODELS_DIR / "package.xml"))
