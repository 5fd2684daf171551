"""One colour per tissue label, for every picture that shows tissues.

The label slices of a patient (``drake-rus patient show``), the label image of
``drake-rus imaging-pictures``, the start planner's image plane (``start_plan.png``) and the
segmenter's kidney mask over emulated frames (``pivot_frames.png``, the imaging pictures) all
take their colours and their legend from here, so a tissue looks the same in every picture.
"""

from __future__ import annotations

import numpy as np

from drake_rus.anatomy.labels import Label

# Display colour of each label (hex RGB) and its name in a legend.
TISSUE_COLORS: dict[Label, str] = {
    Label.OUTSIDE: "#ffffff",
    Label.SOFT_TISSUE: "#e6cbb8",
    Label.FAT: "#f2dc8c",
    Label.MUSCLE: "#b8705f",
    Label.KIDNEY_CORTEX: "#c0203a",
    Label.KIDNEY_MEDULLA: "#7d1024",
    Label.KIDNEY_SINUS: "#f08c9c",
    Label.LIVER: "#7a4b2a",
    Label.BONE: "#c8c8c8",
    Label.GAS: "#262626",
    Label.VESSEL: "#2f4fa8",
    Label.TUMOUR: "#f08a24",
    Label.KIDNEY_TUMOUR: "#f5b041",
}
TISSUE_NAMES: dict[Label, str] = {
    Label.OUTSIDE: "air (outside the body)",
    Label.SOFT_TISSUE: "soft tissue",
    Label.FAT: "fat",
    Label.MUSCLE: "muscle",
    Label.KIDNEY_CORTEX: "kidney cortex",
    Label.KIDNEY_MEDULLA: "kidney medulla",
    Label.KIDNEY_SINUS: "renal sinus",
    Label.LIVER: "liver",
    Label.BONE: "bone",
    Label.GAS: "bowel gas",
    Label.VESSEL: "large vessel",
    Label.TUMOUR: "renal tumour (not the kidney)",
    Label.KIDNEY_TUMOUR: "renal tumour (part of the kidney)",
}
# The segmenter's kidney mask over a B-mode image: the kidney's colour, translucent.
KIDNEY_COLOR = TISSUE_COLORS[Label.KIDNEY_CORTEX]
MASK_ALPHA = 0.45
# The true kidney's outline over a B-mode image (a colour no tissue uses).
TRUTH_OUTLINE_COLOR = "#00e5ff"
# Pixels with no label to show (outside the image fan): light grey.
NO_IMAGE_COLOR = "#f0f0f0"


def rgb(color: str) -> tuple[float, float, float]:
    """(r, g, b) in 0-1 of a ``#rrggbb`` colour."""
    c = color.lstrip("#")
    return tuple(int(c[k : k + 2], 16) / 255.0 for k in (0, 2, 4))


def label_lut() -> np.ndarray:
    """(256, 3) RGB 0-1 of every uint8 label value; values without a label are magenta, so
    an unknown label shows instead of passing for a tissue."""
    lut = np.tile(np.array([1.0, 0.0, 1.0]), (256, 1))
    for label, color in TISSUE_COLORS.items():
        lut[int(label)] = rgb(color)
    return lut


def label_image(labels: np.ndarray, where: np.ndarray | None = None) -> np.ndarray:
    """RGB 0-1 picture (rows, cols, 3) of a 2-D label array; pixels outside the boolean
    ``where`` (e.g. the image fan) in ``NO_IMAGE_COLOR``."""
    labels = np.asarray(labels)
    out = label_lut()[np.clip(labels, 0, 255).astype(np.uint8)]
    if where is not None:
        out[~np.asarray(where, bool)] = rgb(NO_IMAGE_COLOR)
    return out


def mask_overlay(grey: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """RGB 0-1 picture of a uint8 grey image with the kidney ``mask`` filled in the kidney's
    colour (``MASK_ALPHA``)."""
    out = np.repeat(np.asarray(grey, float)[..., None], 3, axis=2) / 255.0
    m = np.asarray(mask, bool)
    out[m] = (1.0 - MASK_ALPHA) * out[m] + MASK_ALPHA * np.array(rgb(KIDNEY_COLOR))
    return out


def labels_present(*arrays) -> list[Label]:
    """The labels occurring in the given label arrays, in label order."""
    values = set()
    for a in arrays:
        values.update(int(v) for v in np.unique(np.asarray(a)))
    return [label for label in Label if int(label) in values]


def tissue_handles(labels=None) -> list:
    """Legend handles (matplotlib patches, with an edge so white shows) of ``labels`` (all
    labels if None)."""
    from matplotlib.patches import Patch

    return [
        Patch(
            facecolor=TISSUE_COLORS[label],
            edgecolor="0.4",
            linewidth=0.5,
            label=TISSUE_NAMES[label],
        )
        for label in (labels or list(Label))
    ]


def mask_handles(truth: bool = False) -> list:
    """Legend handles of the segmenter's kidney mask and, if ``truth``, the true outline."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    handles = [
        Patch(
            facecolor=KIDNEY_COLOR,
            alpha=MASK_ALPHA,
            edgecolor="0.4",
            linewidth=0.5,
            label="kidney: the segmenter's mask",
        )
    ]
    if truth:
        handles.append(
            Line2D([], [], color=TRUTH_OUTLINE_COLOR, lw=1.2, label="kidney: true outline")
        )
    return handles
