"""Fault injection between a station and the controller (controller safety tests, notebook
demonstrations), from outside: ``BuildClosedLoopWithFault`` or ``FaultInjectorHook``.

``FaultInjector`` re-exports a station's sensor ports under the same names (so
``AddController`` can be given it in place of the station) and corrupts one of them from
``t_fault`` on. It also stands in for a segmenter (``kidney_visible``, ``mask_centroid``)
and an image stream (``us_image``) when the station has none.
"""

from __future__ import annotations

import math

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import LeafSystem

from drake_rus.closed_loop import BuildClosedLoop

FAULTS = ("none", "force_spike", "frozen_image", "nan_pose", "segmentation_loss", "frozen_state")


class _Frame:
    """A minimal image frame: only its acquisition time (s) matters to the watchdog."""

    def __init__(self, time: float):
        self.time = time


class FaultInjector(LeafSystem):
    """Pass-through of the station's sensor outputs with one injected fault.

    Inputs (from the station): joint_position (7), joint_velocity (7), X_BP
    (RigidTransform), probe_force (6); optional kidney_visible (1), mask_centroid (1).
    Outputs: the same names, plus kidney_visible (1; 1 unless connected),
    mask_centroid (1; 0.5 unless connected) and us_image (a frame stamped every
    1 / frame_rate_hz s).
    Faults from ``t_fault`` (s): force_spike (probe f_z = -spike_force N, i.e. F_z =
    spike_force), frozen_image (image stamps stop), nan_pose (X_BP translation NaN),
    segmentation_loss (kidney_visible = 0), frozen_state (joint positions held at their last
    value before t_fault).
    """

    def __init__(
        self,
        fault: str = "none",
        t_fault: float = math.inf,
        spike_force: float = 30.0,
        frame_rate_hz: float = 20.0,
        n: int = 7,
    ):
        super().__init__()
        if fault not in FAULTS:
            raise ValueError(f"fault: expected one of {FAULTS}, got {fault!r}")
        self.fault, self.t_fault, self.spike = fault, t_fault, spike_force
        self._period = 1.0 / frame_rate_hz
        self._q = self.DeclareVectorInputPort("joint_position", n)
        self._v = self.DeclareVectorInputPort("joint_velocity", n)
        self._X = self.DeclareAbstractInputPort("X_BP", AbstractValue.Make(RigidTransform()))
        self._F = self.DeclareVectorInputPort("probe_force", 6)
        self._vis = self.DeclareVectorInputPort("kidney_visible", 1)
        self._c = self.DeclareVectorInputPort("mask_centroid", 1)
        if fault == "frozen_state":
            # The last joint positions before t_fault, sampled at 1 kHz (declared only for
            # this fault: a Python update per plant step is costly).
            self._q_last = self.DeclareDiscreteState(n)
            self.DeclarePeriodicDiscreteUpdateEvent(1e-3, 0.0, self._sample_q)
        self.DeclareVectorOutputPort("joint_position", n, self._calc_q)
        self.DeclareVectorOutputPort(
            "joint_velocity", n, lambda c, o: o.SetFromVector(self._v.Eval(c))
        )
        self.DeclareAbstractOutputPort(
            "X_BP", lambda: AbstractValue.Make(RigidTransform()), self._calc_X
        )
        self.DeclareVectorOutputPort("probe_force", 6, self._calc_F)
        self.DeclareVectorOutputPort("kidney_visible", 1, self._calc_vis)
        self.DeclareVectorOutputPort(
            "mask_centroid",
            1,
            lambda c, o: o.SetFromVector(
                [float(self._c.Eval(c)[0]) if self._c.HasValue(c) else 0.5]
            ),
        )
        self.DeclareAbstractOutputPort(
            "us_image", lambda: AbstractValue.Make(_Frame(0.0)), self._calc_image
        )

    def _active(self, context, kind: str) -> bool:
        return self.fault == kind and context.get_time() >= self.t_fault

    def _sample_q(self, context, discrete_state):
        if context.get_time() < self.t_fault:
            discrete_state.set_value(self._q_last, self._q.Eval(context))

    def _calc_q(self, context, output):
        if self._active(context, "frozen_state"):
            output.SetFromVector(context.get_discrete_state(self._q_last).get_value())
        else:
            output.SetFromVector(self._q.Eval(context))

    def _calc_X(self, context, output):
        X = self._X.Eval(context)
        if self._active(context, "nan_pose"):
            X = RigidTransform(X.rotation(), np.full(3, math.nan))
        output.set_value(X)

    def _calc_F(self, context, output):
        F = np.array(self._F.Eval(context))
        if self._active(context, "force_spike"):
            F[5] = -self.spike
        output.SetFromVector(F)

    def _calc_vis(self, context, output):
        vis = float(self._vis.Eval(context)[0]) if self._vis.HasValue(context) else 1.0
        if self._active(context, "segmentation_loss"):
            vis = 0.0
        output.SetFromVector([vis])

    def _calc_image(self, context, output):
        t = context.get_time()
        stamp = math.floor(t / self._period + 1e-9) * self._period
        if self._active(context, "frozen_image"):
            stamp = min(stamp, math.floor(self.t_fault / self._period + 1e-9) * self._period)
        output.set_value(_Frame(stamp))


def ConnectFaultInjector(builder, station, injector: FaultInjector, segmenter=None) -> None:
    """Connects the station's sensor outputs (and optionally a segmenter) to ``injector``."""
    for name in ("joint_position", "joint_velocity", "X_BP", "probe_force"):
        builder.Connect(station.GetOutputPort(name), injector.GetInputPort(name))
    if segmenter is not None:
        builder.Connect(
            segmenter.GetOutputPort("kidney_visible"), injector.GetInputPort("kidney_visible")
        )
        builder.Connect(
            segmenter.GetOutputPort("mask_centroid"), injector.GetInputPort("mask_centroid")
        )


def FaultInjectorHook(fault: str, t_fault: float, frame_rate_hz: float = 20.0):
    """A ``sensor_hook`` for :func:`drake_rus.closed_loop.BuildClosedLoop` that puts a
    :class:`FaultInjector` (``fault`` from ``t_fault`` s on) between the station and the
    controller."""

    def hook(builder, station, segmenter):
        injector = builder.AddNamedSystem(
            "fault_injector", FaultInjector(fault, t_fault, frame_rate_hz=frame_rate_hz)
        )
        ConnectFaultInjector(builder, station, injector, segmenter)
        return injector, injector, injector

    return hook


def BuildClosedLoopWithFault(scenario, fault: str, t_fault: float, **kwargs):
    """``BuildClosedLoop`` with a :class:`FaultInjector` (``fault`` from ``t_fault`` s)."""
    return BuildClosedLoop(
        scenario,
        sensor_hook=FaultInjectorHook(fault, t_fault, scenario.imaging.frame_rate_hz),
        **kwargs,
    )
