"""drake-rus metrics: the seed's E_trans, E_rot,x, eps (eq. 24), V (eq. 25)."""

from drake_rus.metrics.core import (
    CoverageAccumulator, e_rot_x, e_trans, imaging_window_path_length, volume_ratio,
    window_steps)

__all__ = ["CoverageAccumulator", "e_rot_x", "e_trans", "imaging_window_path_length",
           "volume_ratio", "window_steps"]
