"""Fault-injection LeafSystems for the simulated station (thin shells around
:mod:`drake_rus.reliability.faults`).

- :class:`LabelImageFaults`: image dropouts, frozen frames, segmentation misses and false
  positives, NaN-stamped frames, on the label frames before the ultrasound emulator (so the
  emulated image and any segmenter see them);
- :class:`RobotSensorFaults`: force spikes and bias, joint-state delay, NaN in the joint
  state, force or probe pose.
"""

from __future__ import annotations

import math

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import EventStatus, LeafSystem

from drake_rus.imaging.frames import UsFrame
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.reliability import faults as F
from drake_rus.reliability.config import FaultConfig

IMAGE_FAULTS = (
    "image_dropout",
    "frozen_image",
    "segmentation_miss",
    "segmentation_false_positive",
    "nan_image",
)
ROBOT_FAULTS = (
    "force_spike",
    "force_bias",
    "joint_state_delay",
    "nan_joint_position",
    "nan_joint_velocity",
    "nan_force",
    "nan_pose",
)


class LabelImageFaults(LeafSystem):
    """Label frames in (``label_image``), corrupted label frames out (``label_image``).

    image_dropout: an affected frame is replaced by the last delivered one (same index and
    time: the stream looks stalled); frozen_image: the last delivered image content with the
    new frame's time, pose and index; segmentation_miss / segmentation_false_positive: the
    kidney removed / a kidney-like blob added; nan_image: the frame's probe pose is NaN.
    The last delivered frame is kept as state, updated half a frame after each frame.
    """

    def __init__(self, config, faults: FaultConfig, seed: int = 0):
        super().__init__()
        self._faults = [f for f in faults.sensor if f.kind in IMAGE_FAULTS]
        self._seed = seed
        geometry = ProbeGeometry.from_config(config)
        self._fan = geometry.fan_mask
        empty = UsFrame(np.zeros(geometry.image_shape, np.uint8))
        self._in = self.DeclareAbstractInputPort("label_image", AbstractValue.Make(empty))
        self._last = self.DeclareAbstractState(AbstractValue.Make(empty))
        period = 1.0 / config.frame_rate_hz
        self.DeclarePeriodicUnrestrictedUpdateEvent(period, 0.5 * period, self._remember)
        self.DeclareAbstractOutputPort(
            "label_image",
            lambda: AbstractValue.Make(empty),
            self._calc,
            prerequisites_of_calc={
                self.input_port_ticket(self._in.get_index()),
                self.abstract_state_ticket(self._last),
            },
        )
        self._memo_key, self._memo = None, None

    def _apply(self, frame: UsFrame, last: UsFrame) -> UsFrame:
        if not frame.valid:
            return frame
        for f in self._faults:
            if not (
                F.fault_active(frame.time, f) and F.frame_affected(frame.frame_index, f, self._seed)
            ):
                continue
            if f.kind == "image_dropout" and last.valid:
                return last
            if f.kind == "frozen_image" and last.valid:
                frame = UsFrame(last.image, frame.time, frame.X_BP, frame.frame_index)
            elif f.kind == "segmentation_miss":
                frame = UsFrame(
                    F.remove_kidney(frame.image), frame.time, frame.X_BP, frame.frame_index
                )
            elif f.kind == "segmentation_false_positive":
                frame = UsFrame(
                    F.add_false_kidney(frame.image, self._fan, frame.frame_index, self._seed),
                    frame.time,
                    frame.X_BP,
                    frame.frame_index,
                )
            elif f.kind == "nan_image":
                frame = UsFrame(
                    frame.image,
                    frame.time,
                    RigidTransform(frame.X_BP.rotation(), np.full(3, math.nan)),
                    frame.frame_index,
                )
        return frame

    def _output(self, context) -> UsFrame:
        frame = self._in.Eval(context)
        last = context.get_abstract_state(self._last).get_value()
        key = (id(frame.image), frame.frame_index, frame.time, id(last))
        if key != self._memo_key:
            self._memo_key, self._memo = key, self._apply(frame, last)
        return self._memo

    def _calc(self, context, output):
        output.set_value(self._output(context))

    def _remember(self, context, state):
        out = self._output(context)
        if out.valid:
            state.get_mutable_abstract_state(self._last).set_value(out)
        return EventStatus.Succeeded()


class RobotSensorFaults(LeafSystem):
    """Pass-through of joint_position (n), joint_velocity (n), X_BP (RigidTransform) and
    probe_force (6) with the configured robot-sensor faults. force faults add their
    magnitude to the pressing force (probe f_z is negative when pressing);
    joint_state_delay outputs the joint state ``delay`` s old (a ring buffer sampled at
    ``sample_period``; declared only when such a fault is configured)."""

    def __init__(self, faults: FaultConfig, n: int = 7, sample_period: float = 1e-3):
        super().__init__()
        self._faults = [f for f in faults.sensor if f.kind in ROBOT_FAULTS]
        self._n = n
        self._q = self.DeclareVectorInputPort("joint_position", n)
        self._v = self.DeclareVectorInputPort("joint_velocity", n)
        self._X = self.DeclareAbstractInputPort("X_BP", AbstractValue.Make(RigidTransform()))
        self._F = self.DeclareVectorInputPort("probe_force", 6)
        delays = [f for f in self._faults if f.kind == "joint_state_delay"]
        self._delay_fault = delays[0] if delays else None
        if self._delay_fault is not None:
            self._h = sample_period
            self._slots = max(1, int(round(self._delay_fault.delay / sample_period))) + 1
            # [q, v] history, oldest first, then a fill counter.
            self._buffer = self.DeclareDiscreteState(self._slots * 2 * n + 1)
            self.DeclarePeriodicDiscreteUpdateEvent(sample_period, 0.0, self._sample)
        self.DeclareVectorOutputPort("joint_position", n, self._calc_q)
        self.DeclareVectorOutputPort("joint_velocity", n, self._calc_v)
        self.DeclareAbstractOutputPort(
            "X_BP", lambda: AbstractValue.Make(RigidTransform()), self._calc_X
        )
        self.DeclareVectorOutputPort("probe_force", 6, self._calc_F)

    def _active(self, t, kind):
        return any(f.kind == kind and F.fault_active(t, f) for f in self._faults)

    def _sample(self, context, discrete_state):
        buf = np.array(context.get_discrete_state(0).get_value())
        width = 2 * self._n
        hist = buf[:-1].reshape(self._slots, width)
        hist = np.vstack([hist[1:], np.concatenate([self._q.Eval(context), self._v.Eval(context)])])
        filled = min(buf[-1] + 1, self._slots)
        discrete_state.set_value(0, np.concatenate([hist.ravel(), [filled]]))

    def _delayed(self, context):
        """(q, v) ``delay`` s ago, or None when not delaying now."""
        if self._delay_fault is None or not self._active(context.get_time(), "joint_state_delay"):
            return None
        buf = context.get_discrete_state(0).get_value()
        filled = int(buf[-1])
        if filled < 1:
            return None
        hist = np.asarray(buf[:-1]).reshape(self._slots, 2 * self._n)
        row = hist[self._slots - filled] if filled < self._slots else hist[0]
        return row[: self._n], row[self._n :]

    def _calc_q(self, context, output):
        delayed = self._delayed(context)
        q = np.array(self._q.Eval(context)) if delayed is None else np.array(delayed[0])
        if self._active(context.get_time(), "nan_joint_position"):
            q[0] = math.nan
        output.SetFromVector(q)

    def _calc_v(self, context, output):
        delayed = self._delayed(context)
        v = np.array(self._v.Eval(context)) if delayed is None else np.array(delayed[1])
        if self._active(context.get_time(), "nan_joint_velocity"):
            v[-1] = math.nan
        output.SetFromVector(v)

    def _calc_X(self, context, output):
        X = self._X.Eval(context)
        if self._active(context.get_time(), "nan_pose"):
            X = RigidTransform(X.rotation(), np.full(3, math.nan))
        output.set_value(X)

    def _calc_F(self, context, output):
        t = context.get_time()
        W = np.array(self._F.Eval(context))
        W[5] -= sum(F.force_offset(t, f) for f in self._faults)
        if self._active(t, "nan_force"):
            W[5] = math.nan
        output.SetFromVector(W)
