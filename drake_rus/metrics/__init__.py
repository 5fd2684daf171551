"""drake-rus metrics: the seed's E_trans, E_rot,x, eps (eq. 24), V (eq. 25), and the sweep-cost
definitions (pole to pole, whole pivot, matched coverage, tilt cap) of ``metrics.sweep``."""

from drake_rus.metrics.core import (
    CoverageAccumulator,
    e_rot_x,
    e_trans,
    e_trans_of_offset,
    imaging_window_path_length,
    volume_ratio,
    window_steps,
)
from drake_rus.metrics.sweep import (
    MATCHED_V,
    POLE_TO_POLE,
    WHOLE_PIVOT,
    cumulative_eps,
    pivot_legs,
    pole_to_pole_indices,
    signed_pivot_angles,
    sweep_efficiency,
    tilt_cap_legs,
    to_reach,
)

__all__ = [
    "CoverageAccumulator",
    "MATCHED_V",
    "POLE_TO_POLE",
    "WHOLE_PIVOT",
    "cumulative_eps",
    "e_rot_x",
    "e_trans",
    "e_trans_of_offset",
    "imaging_window_path_length",
    "pivot_legs",
    "pole_to_pole_indices",
    "signed_pivot_angles",
    "sweep_efficiency",
    "tilt_cap_legs",
    "to_reach",
    "volume_ratio",
    "window_steps",
]
