"""The pivot's view against the registration: one rule for the scan and its verdict.

The pivot images the kidney across its long axis, a view the registration did not use. A
registered template that explains the explored cloud but not the pivot's view (turned
about the part the exploration saw, or missing a bulge such as a tumour) leaves the pivot
frames' kidney boundary farther from it than the explored cloud. The scan evaluates the
rule at the pivot's end before it says DONE (``localization.tracking``'s monitor, beside
the control loop; the supervisor may take a second look), and the verdict
(``scan.verdict.check_pivot_residual``) evaluates it on the finished scan.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

# The opening words of the monitor's answer when the pivot's view contradicts the
# registration (the supervisor's second look quotes them).
PIVOT_VIEW_CONTRADICTS = "the pivot's view contradicts the registration"


def pivot_residual(surface_B, cloud_B, pivot_B, percentile: float = 90.0) -> tuple:
    """(seen, fitted) (m): the ``percentile`` of the distances from the pivot frames'
    boundary points ``pivot_B`` (M, 3) to the nearest point of the registered template
    ``surface_B`` (N, 3), and the same of the explored cloud ``cloud_B`` (K, 3). The pivot
    residual is ``seen - fitted``: the difference, so that the template's own mismatch
    with the kidney (the cloud's residual) is not counted twice. NaN for an empty set."""
    pivot = np.asarray(pivot_B, float).reshape(-1, 3)
    cloud = np.asarray(cloud_B, float).reshape(-1, 3)
    tree = cKDTree(np.asarray(surface_B, float).reshape(-1, 3))
    seen = float(np.percentile(tree.query(pivot)[0], percentile)) if len(pivot) else np.nan
    fitted = float(np.percentile(tree.query(cloud)[0], percentile)) if len(cloud) else np.nan
    return seen, fitted


def pivot_residual_bound(
    excess: float, max_rms: float, respiration_mode: str, hold_allowance: float
) -> float:
    """The largest pivot residual (m) the rule accepts: ``excess`` x the registration's RMS
    bound ``max_rms``, plus, when the patient breathes under a breath-hold protocol or
    gating (``respiration_mode`` other than "none"), ``hold_allowance`` (m,
    localization.tracking_hold_allowance): the pivot's frames come from other holds or
    end-expiration windows than the explored cloud, and repeat holds put the kidney only
    within about 4 mm of each other (Schwartz 1994, docs/facts)."""
    bound = float(excess) * float(max_rms)
    if respiration_mode != "none":
        bound += float(hold_allowance)
    return bound


def pivot_view_error(surface_B, cloud_B, pivot_B, bound: float, percentile: float) -> str:
    """Why the pivot's view contradicts the registration ("" when it does not, or when
    there is nothing to judge): the pivot residual (:func:`pivot_residual`) above
    ``bound`` (m)."""
    seen, fitted = pivot_residual(surface_B, cloud_B, pivot_B, percentile)
    if not (np.isfinite(seen) and np.isfinite(fitted)) or seen - fitted <= bound:
        return ""
    return (
        f"{PIVOT_VIEW_CONTRADICTS}: {percentile:g}th percentile of the distances to the "
        f"registered template: pivot boundary {seen * 1e3:.1f} mm, explored cloud "
        f"{fitted * 1e3:.1f} mm, {(seen - fitted) * 1e3:.1f} mm more (limit "
        f"{bound * 1e3:.3g} mm)"
    )
