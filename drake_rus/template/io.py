"""Reading the kidney template file (``models/kidney_template.npz``)."""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from drake_rus.paths import MODELS_DIR

DEFAULT_TEMPLATE_PATH = MODELS_DIR / "kidney_template.npz"
_REQUIRED = ("points", "normals", "modes", "variances", "metadata")


@dataclass
class Template:
    """Kidney template in its canonical frame K (m): x_k inferior -> superior, y_k medial ->
    lateral, z_k = x_k x y_k, origin at the centroid.

    ``points`` (M, 3) and ``normals`` (M, 3, outward unit) are the mean shape (eq. 15);
    ``modes`` (k, M, 3) unit-norm shape modes with ``variances`` (k,) in m^2 (95% of the
    cohort's variance): a shape is ``points + sum_i b_i modes[i]``, b_i ~ N(0, variances[i]).
    """
    points: np.ndarray
    normals: np.ndarray
    modes: np.ndarray
    variances: np.ndarray
    meta: dict = field(default_factory=dict)
    convergence: dict = field(default_factory=dict)

    def shape(self, coefficients) -> np.ndarray:
        """Template deformed by mode coefficients b (m), (M, 3)."""
        b = np.asarray(coefficients, dtype=float)
        if b.shape != (len(self.variances),):
            raise ValueError(f"coefficients: expected shape ({len(self.variances)},), got {b.shape}")
        return self.points + np.tensordot(b, self.modes, axes=1)

    def shape_sd(self, sds) -> np.ndarray:
        """Template deformed by ``sds`` standard deviations along each mode."""
        return self.shape(np.asarray(sds, dtype=float) * np.sqrt(self.variances))


def load_template(path=None) -> Template:
    """Loads a template file; ``path`` defaults to ``models/kidney_template.npz``."""
    path = Path(path) if path is not None else DEFAULT_TEMPLATE_PATH
    if not path.is_file():
        raise FileNotFoundError(
            f"kidney template not found: {path} (build it: drake-rus template build)")
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in _REQUIRED if k not in z.files]
            if missing:
                raise ValueError(f"kidney template {path}: missing arrays {missing}")
            data = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as e:
        if isinstance(e, ValueError) and str(path) in str(e):
            raise
        raise ValueError(f"kidney template {path}: not a readable .npz file ({e})") from None
    try:
        meta = json.loads(str(data["metadata"]))
    except json.JSONDecodeError as e:
        raise ValueError(f"kidney template {path}: 'metadata' is not valid JSON ({e})") from None
    pts, nrm = data["points"], data["normals"]
    if pts.ndim != 2 or pts.shape[1] != 3 or nrm.shape != pts.shape:
        raise ValueError(f"kidney template {path}: points/normals must be (M, 3) arrays")
    if not (np.all(np.isfinite(pts)) and np.all(np.isfinite(nrm))):
        raise ValueError(f"kidney template {path}: points/normals contain NaN or inf")
    conv = {}
    if "convergence_n" in data:
        conv = {"n": data["convergence_n"].tolist(), "change": data["convergence_change"].tolist(),
                "to_final": data["convergence_to_final"].tolist()}
    return Template(points=pts, normals=nrm, modes=data["modes"], variances=data["variances"],
                    meta=meta, convergence=conv)
