"""The label table of patient volumes and the labelled-volume container.

A :class:`LabelVolume` is a regular grid of integer tissue labels (1 mm voxels by default).
Voxel (i, j, k) has its centre at ``X_PtV * (voxel_size * [i, j, k])``: the grid frame V is
placed in the patient frame Pt by ``X_PtV`` (see ``PatientConfig`` for the patient frame).
"""

from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np
from pydrake.math import RigidTransform


class Label(IntEnum):
    """Tissue labels of a patient volume (uint8)."""

    OUTSIDE = 0  # air outside the body
    SOFT_TISSUE = 1  # generic soft tissue / viscera
    FAT = 2  # subcutaneous and perirenal fat
    MUSCLE = 3  # abdominal wall and back muscles
    KIDNEY_CORTEX = 4
    KIDNEY_MEDULLA = 5  # medullary pyramids
    KIDNEY_SINUS = 6  # renal sinus fat and collecting system
    LIVER = 7
    BONE = 8  # ribs 10-12, spine
    GAS = 9  # bowel gas
    VESSEL = 10  # large vessels (anechoic)
    # A renal tumour (real CT kidneys, anatomy/ct_patient.py). One tissue, two memberships:
    # whether it belongs to "the kidney" (the segmentation target and the true pose) is the
    # patient's kidney definition ("parenchyma": TUMOUR; "with_tumour": KIDNEY_TUMOUR).
    TUMOUR = 11  # renal tumour, not part of the kidney
    KIDNEY_TUMOUR = 12  # renal tumour counted as part of the kidney


# Every label that belongs to the kidney (the segmentation target).
KIDNEY_LABELS = (Label.KIDNEY_CORTEX, Label.KIDNEY_MEDULLA, Label.KIDNEY_SINUS, Label.KIDNEY_TUMOUR)
# Both tumour labels.
TUMOUR_LABELS = (Label.TUMOUR, Label.KIDNEY_TUMOUR)


def is_kidney(labels: np.ndarray) -> np.ndarray:
    """Boolean mask of kidney voxels/pixels in a label array."""
    return np.isin(labels, np.asarray(KIDNEY_LABELS, dtype=labels.dtype))


@dataclass
class LabelVolume:
    """A labelled volume: ``labels[i, j, k]`` (uint8) on a grid of ``voxel_size`` (m)."""

    labels: np.ndarray
    voxel_size: float = 0.001
    X_PtV: RigidTransform = field(default_factory=RigidTransform)

    def __post_init__(self):
        self.labels = np.asarray(self.labels)
        if self.labels.ndim != 3:
            raise ValueError(
                f"LabelVolume.labels: expected a 3-D array, got shape {self.labels.shape}"
            )
        if not np.issubdtype(self.labels.dtype, np.integer):
            raise ValueError(
                f"LabelVolume.labels: expected integer labels, got dtype {self.labels.dtype}"
            )
        if self.labels.size == 0:
            raise ValueError(f"LabelVolume.labels: the volume is empty (shape {self.labels.shape})")
        if self.labels.dtype != np.uint8:
            # Slicing reads the labels as uint8: 263 would pass for the liver, -1 for gel.
            lo, hi = int(self.labels.min()), int(self.labels.max())
            if lo < 0 or hi > 255:
                raise ValueError(
                    f"LabelVolume.labels: expected label values 0-255 (uint8), got {lo}..{hi}"
                )
        if not (np.isfinite(self.voxel_size) and self.voxel_size > 0):
            raise ValueError(
                f"LabelVolume.voxel_size: expected a positive size in m, got {self.voxel_size}"
            )

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.labels.shape)

    def voxel_centers_in_patient(self, ijk: np.ndarray) -> np.ndarray:
        """Positions (N, 3) in the patient frame of voxel indices ``ijk`` (N, 3)."""
        p_V = np.asarray(ijk, dtype=float) * self.voxel_size
        return (self.X_PtV.rotation().matrix() @ p_V.T).T + self.X_PtV.translation()
