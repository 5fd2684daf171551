"""A geometric stand-in for the image + segmenter: what part of a known kidney ellipsoid the
probe's image plane cuts (tests and tuning of the scan supervisor without the imaging chain).

The image plane is the x_P-z_P plane of the tip frame P (docs/design.md); its field of view is
approximated by the fan of a curvilinear probe: depths w in [0, depth] below the face and
lateral positions |u| <= (radius + w) sin(half_angle), u along +x_P. Image columns run
along +x_P, so the horizontal mask centroid is c_msk = (u_mean - u_min) / (u_max - u_min).
"""

from __future__ import annotations

import math

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import LeafSystem


def kidney_section(
    X_BP: RigidTransform,
    X_BK: RigidTransform,
    semi_axes,
    *,
    depth=0.15,
    radius=0.05,
    half_angle=math.radians(20.0),
    n=64,
):
    """Cut of the ellipsoid (centre and axes X_BK, semi-axes in m) by the image plane of
    the probe at X_BP. Returns (area (m^2), c_msk in [0, 1], or NaN when empty)."""
    u_max = (radius + depth) * math.sin(half_angle)
    u = np.linspace(-u_max, u_max, n)
    w = np.linspace(0.0, depth, n)
    U, W = np.meshgrid(u, w)
    in_fan = np.abs(U) <= (radius + W) * math.sin(half_angle)
    R = X_BP.rotation().matrix()
    pts = X_BP.translation()[:, None] + np.outer(R[:, 0], U.ravel()) + np.outer(R[:, 2], W.ravel())
    p_K = X_BK.inverse().multiply(pts)
    inside = np.sum((p_K / np.asarray(semi_axes, float)[:, None]) ** 2, axis=0) <= 1.0
    inside &= in_fan.ravel()
    cell = (u[1] - u[0]) * (w[1] - w[0])
    area = float(inside.sum()) * cell
    if not inside.any():
        return 0.0, math.nan
    u_mean = float(U.ravel()[inside].mean())
    return area, (u_mean + u_max) / (2 * u_max)


class GeometricKidneyView(LeafSystem):
    """Segmenter stand-in over :func:`kidney_section`, sampled at the frame rate.

    Input: X_BP (RigidTransform). Outputs: kidney_visible (1, 0/1: cut area >= min_area),
    mask_centroid (1, c_msk in [0, 1]; 0.5 when not visible), X_BK (RigidTransform: the
    true kidney pose, the ground-truth stand-in for localization).
    """

    def __init__(
        self,
        X_BK: RigidTransform,
        semi_axes,
        frame_rate_hz: float = 20.0,
        min_area: float = 1.0e-4,
        **fan,
    ):
        super().__init__()
        self._X_BK, self._axes, self._min_area, self._fan = X_BK, semi_axes, min_area, fan
        self._X = self.DeclareAbstractInputPort("X_BP", AbstractValue.Make(RigidTransform()))
        self._s = self.DeclareDiscreteState([0.0, 0.5])
        period = 1.0 / frame_rate_hz
        self.DeclareInitializationDiscreteUpdateEvent(self._sample)
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._sample)
        self.DeclareVectorOutputPort(
            "kidney_visible",
            1,
            lambda c, o: o.SetFromVector([c.get_discrete_state(self._s).get_value()[0]]),
        )
        self.DeclareVectorOutputPort(
            "mask_centroid",
            1,
            lambda c, o: o.SetFromVector([c.get_discrete_state(self._s).get_value()[1]]),
        )
        self.DeclareAbstractOutputPort(
            "X_BK",
            lambda: AbstractValue.Make(RigidTransform()),
            lambda c, o: o.set_value(self._X_BK),
        )

    def _sample(self, context, discrete_state):
        area, c = kidney_section(self._X.Eval(context), self._X_BK, self._axes, **self._fan)
        visible = area >= self._min_area
        discrete_state.set_value(self._s, [float(visible), c if visible else 0.5])
