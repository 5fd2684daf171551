"""Thin Drake LeafSystems over the imaging functions.

- :class:`SliceSensor`: probe pose -> label image, sampled at the frame rate;
- :class:`UltrasoundEmulator`: label image -> B-mode-like image;
- :class:`Segmenter`: image -> kidney mask, visible flag, c_msk, boundary pixels;
- :class:`PointCloudAccumulator`: boundary pixels (+ their X_BP) -> P_local in the base frame.

Images travel as :class:`~drake_rus.imaging.frames.UsFrame` (image + acquisition time + X_BP +
frame index). Only the SliceSensor samples on a clock (a periodic unrestricted update at
``frame_rate_hz``); the emulator and segmenter are direct feedthrough, and compute once per
new frame: each keeps a frame's result in a Context cache entry, keyed on the frame.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import EventStatus, LeafSystem, ValueProducer

from drake_rus.anatomy.labels import LabelVolume
from drake_rus.imaging.backprojection import accumulate_consistent
from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.emulator import EmulatorModel, emulate
from drake_rus.imaging.emulator import warm_up as warm_emulator
from drake_rus.imaging.frames import BoundaryPixels, KidneySurface, PointCloud, UsFrame
from drake_rus.imaging.onnx_backend import OnnxSegmenter
from drake_rus.imaging.probe import ProbeGeometry, check_pose
from drake_rus.imaging.segment import (
    KidneyTrack,
    acoustic_shadow,
    echo_supported_boundary,
    predicted_section,
    read_mask,
    segment_classical,
    segment_oracle,
    track_prior,
    track_settings,
    track_update,
)
from drake_rus.imaging.slicing import slice_volume
from drake_rus.imaging.slicing import warm_up as warm_slicer


def _frame_key(frame: UsFrame):
    return (id(frame.image), frame.frame_index, frame.time)


class SliceSensor(LeafSystem):
    """Oblique slicing of a patient's label volume at the probe pose (seed III-A).

    Input ``X_BP`` (abstract RigidTransform): pose of the probe tip frame P in the robot base B.
    Output ``label_image`` (abstract UsFrame): uint8 tissue labels (rows, cols) on the probe's
    fan (0 outside it), stamped with the acquisition time (s) and the X_BP used. A frame is
    acquired at initialization and then every 1 / ``frame_rate_hz`` s.

    ``motion`` (optional, e.g. :class:`drake_rus.anatomy.motion.PatientMotion`): anything with
    ``offset_B(t)`` (m, in B); the volume then sits at translate(offset_B(t)) * X_BV, so a
    breathing or shifting patient moves under the probe. Input ``offset_B`` (3-vector, m in
    B; optional): when connected, the volume's offset instead of ``motion``'s.

    ``acquire=False``: the sensor never slices (``label_image`` stays the empty frame); a
    renderer outside the simulation slices at the poses ``volume_pose`` and ``X_BP`` give
    (the rehearsal's video process: the robot's physics never waits for a picture).
    """

    def __init__(
        self,
        config: ImagingConfig,
        volume: LabelVolume,
        X_BV: RigidTransform,
        motion=None,
        *,
        acquire: bool = True,
    ):
        super().__init__()
        if not isinstance(volume, LabelVolume):
            raise ValueError(
                f"SliceSensor: volume must be a LabelVolume, got {type(volume).__name__}"
            )
        self._geometry = ProbeGeometry.from_config(config)
        self._volume = volume
        self._X_BV = check_pose(X_BV, "SliceSensor X_BV (pose of the volume grid in B)")
        self._motion = motion
        self._planes = int(config.elevation_planes)
        self._combine = config.elevation_combine
        # The padded volume and the compiled kernel, now, not in the first frame.
        if acquire:
            warm_slicer(self._geometry, volume, self._planes, self._combine)
        self._X_BP_port = self.DeclareAbstractInputPort(
            "X_BP", AbstractValue.Make(RigidTransform())
        )
        self._offset_port = self.DeclareVectorInputPort("offset_B", 3)
        empty = UsFrame(np.zeros(self._geometry.image_shape, np.uint8))
        self._state_index = self.DeclareAbstractState(AbstractValue.Make(empty))
        period = 1.0 / config.frame_rate_hz
        if acquire:
            self.DeclareInitializationUnrestrictedUpdateEvent(self._acquire)
            self.DeclarePeriodicUnrestrictedUpdateEvent(period, period, self._acquire)
        self.DeclareAbstractOutputPort(
            "label_image",
            lambda: AbstractValue.Make(empty),
            self._calc_label_image,
            prerequisites_of_calc={self.abstract_state_ticket(self._state_index)},
        )

    @property
    def geometry(self) -> ProbeGeometry:
        return self._geometry

    def X_BV(self, t: float) -> RigidTransform:
        """Pose of the label grid in B at time t (s)."""
        if self._motion is None:
            return self._X_BV
        return RigidTransform(self._motion.offset_B(t)) @ self._X_BV

    @property
    def volume(self) -> LabelVolume:
        return self._volume

    def volume_pose(self, context) -> RigidTransform:
        """Pose of the label grid in B now (``offset_B`` if connected, else ``motion``)."""
        return self._X_BV_now(context)

    def _X_BV_now(self, context) -> RigidTransform:
        if self._offset_port.HasValue(context):
            return RigidTransform(np.asarray(self._offset_port.Eval(context), float)) @ self._X_BV
        return self.X_BV(context.get_time())

    def _acquire(self, context, state):
        if not self._X_BP_port.HasValue(context):
            raise RuntimeError("SliceSensor: input port 'X_BP' is not connected")
        X_BP = self._X_BP_port.Eval(context)
        check_pose(X_BP, f"SliceSensor input 'X_BP' at t = {context.get_time():.4f} s")
        previous = context.get_abstract_state(self._state_index).get_value()
        image = slice_volume(
            self._geometry,
            self._volume,
            self._X_BV_now(context),
            X_BP,
            self._planes,
            self._combine,
        )
        frame = UsFrame(
            image=image,
            time=context.get_time(),
            X_BP=RigidTransform(X_BP),
            frame_index=previous.frame_index + 1,
        )
        state.get_mutable_abstract_state(self._state_index).set_value(frame)
        return EventStatus.Succeeded()

    def _calc_label_image(self, context, output):
        output.set_value(context.get_abstract_state(self._state_index).get_value())


class UltrasoundEmulator(LeafSystem):
    """Label image -> B-mode-like image (speckle, attenuation, interfaces, shadows).

    Input ``label_image`` (abstract UsFrame, uint8 labels). Output ``us_image`` (abstract
    UsFrame, uint8 grey 0-255, 0 outside the fan) with the input frame's time, X_BP and index.
    Deterministic: frame k's speckle depends only on (``seed``, k).
    """

    def __init__(self, config: ImagingConfig, seed: int = 0):
        super().__init__()
        self._model = EmulatorModel.from_config(config)
        self._seed = int(seed)
        empty = UsFrame(np.zeros(self._model.geometry.image_shape, np.uint8))
        self._empty = empty
        self._in = self.DeclareAbstractInputPort("label_image", AbstractValue.Make(empty))
        # The frame's emulated image, kept (in the Context) while the input is the same frame.
        self._frame_cache = self.DeclareCacheEntry(
            description="emulated frame (frame key, UsFrame)",
            value_producer=ValueProducer(
                allocate=lambda: AbstractValue.Make((None, empty)), calc=self._emulate
            ),
            prerequisites_of_calc={self.input_port_ticket(self._in.get_index())},
        )
        self.DeclareAbstractOutputPort(
            "us_image",
            lambda: AbstractValue.Make(empty),
            lambda c, o: o.set_value(self._frame_cache.Eval(c)[1]),
            prerequisites_of_calc={self._frame_cache.ticket()},
        )
        # Build the scan-line tables and compile (or load) the kernels now, not inside the
        # first simulation step.
        warm_emulator(self._model, self._seed)

    @property
    def model(self) -> EmulatorModel:
        """The emulator's model (its ``us_image`` of a label frame k is
        ``emulate(labels, model, seed, k)``: another thread can make the same picture)."""
        return self._model

    @property
    def seed(self) -> int:
        return self._seed

    def _emulate(self, context, value):
        frame = self._in.Eval(context)
        if not frame.valid:
            value.set_value((None, self._empty))
            return
        key = _frame_key(frame)
        if value.get_value()[0] == key:  # the same frame re-evaluated upstream: keep it
            return
        image = emulate(frame.image, self._model, self._seed, frame.frame_index)
        value.set_value(
            (
                key,
                UsFrame(
                    image=image, time=frame.time, X_BP=frame.X_BP, frame_index=frame.frame_index
                ),
            )
        )


def make_segmenter_backend(config: ImagingConfig, geometry: ProbeGeometry):
    """A callable ``(us_image, label_image, prev_mask, prev_age=inf, section=None) -> mask``
    for ``config.segmenter``: ``prev_mask`` is the classical backend's temporal prior, or the
    kidney last seen ``prev_age`` s ago that the onnx backend follows (None: none);
    ``section`` the registered template's predicted section of this frame (bool; None: no
    prediction), which the onnx backend follows too and the classical one takes as its prior
    when it has no previous mask. Raises ValueError naming the field when the backend
    cannot be built (e.g. a bad model)."""
    backend = config.segmenter
    if backend == "oracle":
        return lambda us, labels, prev, age=math.inf, section=None: segment_oracle(labels)
    if backend == "classical":
        min_area = config.min_kidney_area
        # An all-False previous mask (the last frame found no kidney) is no previous mask:
        # the template's section, when there is one, is the prior then.
        return lambda us, labels, prev, age=math.inf, section=None: segment_classical(
            us,
            geometry,
            prev if section is None or (prev is not None and prev.any()) else section,
            min_area,
        )
    if backend == "onnx":
        model = OnnxSegmenter.from_config(config, geometry)
        return lambda us, labels, prev, age=math.inf, section=None: model(us, prev, age, section)
    raise ValueError(
        f"imaging.segmenter: unknown backend {backend!r}; expected 'oracle', 'classical' or 'onnx'"
    )


def segment_frame(
    backend,
    geometry: ProbeGeometry,
    min_area: float,
    frame: UsFrame,
    prior,
    *,
    follows: bool,
    uses_prior: bool,
    track_confirm: float,
    source: str,
    surface_points: np.ndarray | None = None,
    slab: float = 0.0,
    shadow_floor: float = 0.0,
    shadow_max_fraction: float = 1.0,
):
    """(mask UsFrame, MaskReadout, BoundaryPixels) of one frame: the Segmenter's work,
    wherever it runs (in the control loop's thread or a worker process).

    ``backend(us, labels, prev, age, section)``: :func:`make_segmenter_backend`; ``frame``:
    the source frame (grey for the classical and onnx backends, labels for the oracle, said
    by ``source``: the port's name); ``prior``: the Segmenter's prior state (a KidneyTrack
    when it ``follows`` the kidney, else the previous mask frame when it ``uses_prior``);
    ``surface_points`` (N, 3; m, B): the registered template's surface (None: no
    localization yet), whose section in the frame's image plane (:func:`predicted_section`,
    points within ``slab`` m of it) is the backend's ``section`` prior. The section is cut
    here, with the segmentation (in the worker when one hosts it), not in the control loop.
    With a grey source and ``shadow_floor`` > 0 the BoundaryPixels hold only the boundary
    the echoes support (:func:`echo_supported_boundary` in the frame's
    :func:`acoustic_shadow`, ``shadow_max_fraction``); the mask and read-outs are the
    segmenter's.
    """
    if not frame.valid:
        empty = np.zeros(geometry.image_shape, bool)
        return (
            UsFrame(empty),
            read_mask(empty, geometry, min_area),
            BoundaryPixels(np.zeros((0, 2)), frame.time, frame.X_BP, -1),
        )
    if frame.image.shape != geometry.image_shape:
        raise ValueError(
            f"Segmenter: input '{source}' has shape "
            f"{frame.image.shape}, expected {geometry.image_shape} (imaging.image_"
            f"height_px x image_width_px)"
        )
    us = frame.image if source == "us_image" else None
    labels = frame.image if source == "label_image" else None
    if follows:
        prev, age = track_prior(prior, frame.time, track_confirm)
    elif uses_prior and prior.valid:
        prev, age = prior.image, frame.time - prior.time
    else:
        prev, age = None, math.inf
    section = None
    if surface_points is not None and (follows or uses_prior):
        section = predicted_section(surface_points, frame.X_BP, geometry, slab)
    mask = np.asarray(backend(us, labels, prev, age, section), bool) & geometry.fan_mask
    readout = read_mask(mask, geometry, min_area)
    boundary = readout.boundary
    if us is not None and shadow_floor > 0.0 and len(boundary):
        shadow = acoustic_shadow(us, geometry, shadow_floor)
        boundary = echo_supported_boundary(mask, boundary, shadow, geometry, shadow_max_fraction)
    return (
        UsFrame(mask, frame.time, frame.X_BP, frame.frame_index),
        readout,
        BoundaryPixels(boundary, frame.time, frame.X_BP, frame.frame_index),
    )


def warm_segmenter_backend(config: ImagingConfig, geometry: ProbeGeometry):
    """:func:`make_segmenter_backend`, run once on a blank frame (a worker builds and warms
    its own backend before the scan starts)."""
    backend = make_segmenter_backend(config, geometry)
    blank = np.zeros(geometry.image_shape, np.uint8)
    backend(blank, blank, None, math.inf, None)
    return backend


class Segmenter(LeafSystem):
    """Kidney segmentation of the current frame and the read-outs the controller uses.

    Inputs: ``us_image`` (abstract UsFrame, uint8 grey) for the ``classical`` and ``onnx``
    backends; ``label_image`` (abstract UsFrame, uint8 labels) for the ``oracle`` backend;
    ``kidney_surface`` (abstract KidneySurface, optional: the registered template's surface
    in B after localization), from which each frame's predicted section
    (:func:`~drake_rus.imaging.segment.predicted_section`, at the frame's X_BP, slab half the
    elevational beam width) is the tracker's prior: the kidney is found again where the
    template puts it, after a pivot leg's end or any loss. The surface goes with the frame
    to wherever the segmentation runs; the section is cut there.
    Outputs (all for the latest frame segmented):
      ``kidney_mask`` (abstract UsFrame, bool mask, with the frame's time, X_BP, index);
      ``kidney_visible`` (1-vector, 1.0 when the mask area >= ``min_kidney_area``, else 0.0);
      ``mask_centroid`` (1-vector, c_msk in [0, 1] across the image width, eq. 17; 0.5
      when not visible);
      ``boundary_pixels`` (abstract BoundaryPixels, (N, 2) pixels (u, v) + time, X_BP, index):
      the mask's boundary that the image's echoes support (``imaging.shadow_floor``: none
      from a mask drawn in acoustic shadow, none within 2 mm of a shadow).
    The classical backend keeps the previous frame's mask as a temporal prior; the onnx
    backend follows the kidney once seen (``imaging.track_gap``, ``track_reach``,
    ``track_confirm``; :class:`~drake_rus.imaging.segment.KidneyTrack`).

    Two ways to host the work (:func:`segment_frame`):

    - ``executor`` None: direct feedthrough, the frame segmented when an output is first
      evaluated (kept in a Context cache entry), the prior updated at the frame rate;
    - an ``executor`` (``drake_rus.executor``; the scan diagram's): every ``poll_period`` s
      (just after the sensor's and the controller's ticks, by 5% of the period) a new
      frame is handed to the executor's ``frames`` lane when it is free (frames arriving
      meanwhile are skipped: ``frames_skipped``), and a result is taken when it is ready:
      the outputs then switch to it and the prior follows it. The control loop never waits
      for a segmentation; the outputs keep the source frame's time stamp, so the safety
      layer's stale-image watchdog counts the segmentation's latency too.
    """

    def __init__(self, config: ImagingConfig, *, executor=None, poll_period: float = 0.01):
        super().__init__()
        self._geometry = ProbeGeometry.from_config(config)
        self._backend_name = config.segmenter
        self._backend = make_segmenter_backend(config, self._geometry)
        self._min_area = config.min_kidney_area
        shape = self._geometry.image_shape
        empty = UsFrame(np.zeros(shape, np.uint8))
        self._empty_mask = UsFrame(np.zeros(shape, bool))
        self._us = self.DeclareAbstractInputPort("us_image", AbstractValue.Make(empty))
        self._labels = self.DeclareAbstractInputPort("label_image", AbstractValue.Make(empty))
        self._surface = self.DeclareAbstractInputPort(
            "kidney_surface", AbstractValue.Make(KidneySurface())
        )
        self._slab = 0.5 * config.elevation_width
        self._shadow_floor = config.shadow_floor
        self._shadow_max_fraction = config.shadow_max_fraction
        self._source = self._labels if self._backend_name == "oracle" else self._us
        self._uses_prior = self._backend_name in ("classical", "onnx")
        # The classical prior is the previous frame's mask; the onnx backend follows a
        # KidneyTrack (the last visible kidney, kept while the kidney is not seen).
        self._follows = self._backend_name == "onnx"
        self._track_config = track_settings(config)
        self._track_confirm = config.track_confirm
        self._prior_index = self.DeclareAbstractState(
            AbstractValue.Make(KidneyTrack() if self._follows else self._empty_mask)
        )
        self._executor = executor
        if executor is None:
            result = self._declare_direct(config)
        else:
            result = self._declare_hosted(config, executor, float(poll_period))
        self.DeclareAbstractOutputPort(
            "kidney_mask",
            lambda: AbstractValue.Make(self._empty_mask),
            lambda c, o: o.set_value(self._result(c)[0]),
            prerequisites_of_calc=result,
        )
        self.DeclareVectorOutputPort(
            "kidney_visible",
            1,
            lambda c, o: o.SetAtIndex(0, float(self._result(c)[1].visible)),
            prerequisites_of_calc=result,
        )
        self.DeclareVectorOutputPort(
            "mask_centroid",
            1,
            lambda c, o: o.SetAtIndex(0, self._result(c)[1].centroid),
            prerequisites_of_calc=result,
        )
        self.DeclareAbstractOutputPort(
            "boundary_pixels",
            lambda: AbstractValue.Make(BoundaryPixels(np.zeros((0, 2)))),
            lambda c, o: o.set_value(self._result(c)[2]),
            prerequisites_of_calc=result,
        )

    @property
    def geometry(self) -> ProbeGeometry:
        return self._geometry

    def _work(self, frame: UsFrame, prior, surface: KidneySurface | None):
        """The arguments of :func:`segment_frame` after the backend and geometry."""
        return (
            self._min_area,
            frame,
            prior,
        ), dict(
            follows=self._follows,
            uses_prior=self._uses_prior,
            track_confirm=self._track_confirm,
            source=self._source.get_name(),
            surface_points=None if surface is None else surface.points_B,
            slab=self._slab,
            shadow_floor=self._shadow_floor,
            shadow_max_fraction=self._shadow_max_fraction,
        )

    def _surface_now(self, context) -> KidneySurface | None:
        """The registered template's surface, or None (unconnected, or no estimate yet)."""
        if not self._uses_prior or not self._surface.HasValue(context):
            return None
        surface = self._surface.Eval(context)
        return surface if surface.valid else None

    def _check_connected(self, context):
        if not self._source.HasValue(context):
            raise RuntimeError(
                f"Segmenter ({self._backend_name}): input port "
                f"'{self._source.get_name()}' is not connected"
            )

    def _next_prior(self, prior, result):
        """The prior after a segmented frame (``result``), or ``prior`` if unchanged."""
        mask_frame, readout, _ = result
        if not mask_frame.valid:
            return prior
        if self._follows:
            return track_update(
                prior,
                mask_frame.image,
                readout.visible,
                mask_frame.time,
                self._geometry,
                **self._track_config,
            )
        return mask_frame

    # --- direct feedthrough ---------------------------------------------------------------
    def _declare_direct(self, config):
        tickets = {
            self.input_port_ticket(self._source.get_index()),
            self.input_port_ticket(self._surface.get_index()),
        }
        if self._uses_prior:
            tickets.add(self.abstract_state_ticket(self._prior_index))
            period = 1.0 / config.frame_rate_hz
            self.DeclarePeriodicUnrestrictedUpdateEvent(period, 0.5 * period, self._keep_prior)
        # The frame's segmentation (mask, read-outs, boundary), kept in the Context while the
        # frame is the same (see _segment); every output reads it.
        self._result_cache = self.DeclareCacheEntry(
            description="segmentation of the current frame (key, result)",
            value_producer=ValueProducer(
                allocate=lambda: AbstractValue.Make((None, None)), calc=self._segment
            ),
            prerequisites_of_calc=tickets,
        )
        return {self._result_cache.ticket()}

    def _result(self, context):
        """(mask UsFrame, MaskReadout, BoundaryPixels) of the current frame."""
        if self._executor is not None:
            return context.get_abstract_state(self._hosted_index).get_value().result
        self._check_connected(context)
        return self._result_cache.Eval(context)[1]

    def _segment(self, context, value):
        memo_key, _ = value.get_value()
        self._check_connected(context)
        frame = self._source.Eval(context)
        prior = (
            context.get_abstract_state(self._prior_index).get_value()
            if self._uses_prior
            else self._empty_mask
        )
        frame_key = _frame_key(frame)
        surface = self._surface_now(context)
        # A prior taken from this very frame (the update event after it ran) must not change
        # the frame's segmentation: the controller and the point cloud see one result, and
        # the frame is segmented once.
        prior_from_frame = (
            prior.time >= frame.time
            if self._follows
            else prior.valid and prior.frame_index >= frame.frame_index
        )
        if (
            memo_key is not None
            and memo_key[0] == frame_key
            and frame.frame_index >= 0
            and prior_from_frame
        ):
            return
        key = (
            frame_key,
            id(prior),
            None if surface is None else (surface.time, len(surface.points_B)),
        )
        if key == memo_key:
            return
        args, kwargs = self._work(frame, prior, surface)
        value.set_value((key, segment_frame(self._backend, self._geometry, *args, **kwargs)))

    def _keep_prior(self, context, state):
        if not self._source.HasValue(context):
            return EventStatus.DidNothing()
        result = self._result(context)
        if not result[0].valid:
            return EventStatus.DidNothing()
        prior = context.get_abstract_state(self._prior_index).get_value()
        new = self._next_prior(prior, result)
        if new is not prior:
            state.get_mutable_abstract_state(self._prior_index).set_value(new)
        return EventStatus.Succeeded()

    # --- hosted by an executor ------------------------------------------------------------
    def _declare_hosted(self, config, executor, poll_period: float):
        if not poll_period > 0.0:
            raise ValueError(f"Segmenter: poll_period must be > 0 s, got {poll_period}")
        if executor.mode == "inline":
            self._hosted_backend = self._backend
        else:
            # The worker builds (and warms) its own backend; this one was built to check the
            # configuration here, at construction.
            self._hosted_backend = executor.share(
                "frames", warm_segmenter_backend, config, self._geometry
            )
            self._backend = None
        empty = segment_frame(
            None,
            self._geometry,
            self._min_area,
            UsFrame(np.zeros(self._geometry.image_shape, np.uint8)),
            None,
            follows=False,
            uses_prior=False,
            track_confirm=0.0,
            source=self._source.get_name(),
        )
        self._hosted_index = self.DeclareAbstractState(
            AbstractValue.Make(HostedSegmentation(result=empty))
        )
        #: Frames that arrived while a segmentation was running and were never segmented.
        self.frames_skipped = 0
        self.DeclarePeriodicUnrestrictedUpdateEvent(poll_period, 0.05 * poll_period, self._poll)
        return {self.abstract_state_ticket(self._hosted_index)}

    def _poll(self, context, state):
        self._check_connected(context)
        h = context.get_abstract_state(self._hosted_index).get_value()
        prior = context.get_abstract_state(self._prior_index).get_value()
        t = context.get_time()
        new_prior = prior
        changed = False
        if h.pending is not None:
            done = self._executor.poll(h.pending, t)
            if done is not None:
                h = dataclasses.replace(h, result=done.value, pending=None)
                new_prior = self._next_prior(prior, done.value) if self._uses_prior else prior
                changed = True
        frame = self._source.Eval(context)
        key = (frame.frame_index, frame.time)
        if frame.valid and key != h.submitted:
            if h.pending is not None:
                if h.waiting != key:
                    self.frames_skipped += h.waiting is not None
                    h = dataclasses.replace(h, waiting=key)
                    changed = True
            else:
                # A frame that waited and was overtaken by this newer one was never segmented.
                self.frames_skipped += h.waiting is not None and h.waiting != key
                args, kwargs = self._work(
                    frame, new_prior if self._uses_prior else None, self._surface_now(context)
                )
                ticket = self._executor.submit(
                    "frames",
                    _segment_job,
                    self._hosted_backend,
                    self._geometry,
                    args,
                    kwargs,
                    t=t,
                    kind="segmentation",
                )
                h = dataclasses.replace(h, pending=ticket, submitted=key, waiting=None)
                changed = True
                done = self._executor.poll(ticket, t)  # ready at once (inline, no latency)
                if done is not None:
                    h = dataclasses.replace(h, result=done.value, pending=None)
                    if self._uses_prior:
                        new_prior = self._next_prior(new_prior, done.value)
        if not changed:
            return EventStatus.DidNothing()
        state.get_mutable_abstract_state(self._hosted_index).set_value(h)
        if new_prior is not prior:
            state.get_mutable_abstract_state(self._prior_index).set_value(new_prior)
        return EventStatus.Succeeded()


def _segment_job(backend, geometry, args, kwargs):
    """:func:`segment_frame` as an executor job (a module-level function: it pickles)."""
    return segment_frame(backend, geometry, *args, **kwargs)


@dataclasses.dataclass(frozen=True)
class HostedSegmentation:
    """A hosted Segmenter's state: the latest result taken (mask UsFrame, MaskReadout,
    BoundaryPixels), the segmentation running (its Ticket, or None), the key (frame index,
    time) of the last frame handed over and of a newer one waiting (or None)."""

    result: tuple
    pending: object = None
    submitted: tuple | None = None
    waiting: tuple | None = None

    def __deepcopy__(self, memo):  # immutable: clones may share it
        return self


class PointCloudAccumulator(LeafSystem):
    """Collects P_local: back-projected kidney boundary points in the base frame (seed II-E).

    Inputs: ``boundary_pixels`` (abstract BoundaryPixels from the Segmenter); ``enable``
    (1-vector, optional: accumulate while > 0.5; always when unconnected); ``reset``
    (1-vector, optional: > 0.5 clears the cloud).
    Outputs: ``point_cloud`` (abstract PointCloud: points (N, 3) in B (m), frame count, the
    X_BP and time (s) of every kept frame); ``frame_count`` (1-vector).
    Checks for a new frame at ``frame_rate_hz``, half a period after the sensor's clock.
    A frame whose section jumps from the last frames' (``imaging.cloud_section_jump``;
    :func:`~drake_rus.imaging.backprojection.accumulate_consistent`) counts, but its points
    are left out.
    """

    def __init__(self, config: ImagingConfig, max_points_per_frame: int = 0):
        super().__init__()
        self._geometry = ProbeGeometry.from_config(config)
        self._max_points = int(max_points_per_frame)
        self._jump = config.cloud_section_jump
        # ((time s, section extent (6,)), ...) of the last frames with a section.
        self._recent_index = self.DeclareAbstractState(AbstractValue.Make(()))
        self._boundary = self.DeclareAbstractInputPort(
            "boundary_pixels", AbstractValue.Make(BoundaryPixels(np.zeros((0, 2))))
        )
        self._enable = self.DeclareVectorInputPort("enable", 1)
        self._reset = self.DeclareVectorInputPort("reset", 1)
        self._cloud_index = self.DeclareAbstractState(AbstractValue.Make(PointCloud()))
        # Index of the last frame taken (so a frame is never counted twice).
        self._last_index = self.DeclareAbstractState(AbstractValue.Make(-1))
        period = 1.0 / config.frame_rate_hz
        self.DeclarePeriodicUnrestrictedUpdateEvent(period, 0.5 * period, self._update)
        self.DeclareAbstractOutputPort(
            "point_cloud",
            lambda: AbstractValue.Make(PointCloud()),
            lambda c, o: o.set_value(c.get_abstract_state(self._cloud_index).get_value()),
            prerequisites_of_calc={self.abstract_state_ticket(self._cloud_index)},
        )
        self.DeclareVectorOutputPort(
            "frame_count",
            1,
            lambda c, o: o.SetAtIndex(
                0, c.get_abstract_state(self._cloud_index).get_value().frame_count
            ),
            prerequisites_of_calc={self.abstract_state_ticket(self._cloud_index)},
        )

    def _flag(self, port, context, default: bool) -> bool:
        if not port.HasValue(context):
            return default
        return bool(port.Eval(context)[0] > 0.5)

    def _update(self, context, state):
        if self._flag(self._reset, context, False):
            state.get_mutable_abstract_state(self._cloud_index).set_value(PointCloud())
            state.get_mutable_abstract_state(self._recent_index).set_value(())
            return EventStatus.Succeeded()
        if not self._flag(self._enable, context, True) or not self._boundary.HasValue(context):
            return EventStatus.DidNothing()
        boundary = self._boundary.Eval(context)
        last = context.get_abstract_state(self._last_index).get_value()
        if boundary.frame_index < 0 or boundary.frame_index <= last:
            return EventStatus.DidNothing()
        cloud = context.get_abstract_state(self._cloud_index).get_value()
        recent = context.get_abstract_state(self._recent_index).get_value()
        cloud, recent = accumulate_consistent(
            cloud, recent, boundary, self._geometry, self._max_points, self._jump
        )
        state.get_mutable_abstract_state(self._cloud_index).set_value(cloud)
        state.get_mutable_abstract_state(self._recent_index).set_value(recent)
        state.get_mutable_abstract_state(self._last_index).set_value(boundary.frame_index)
        return EventStatus.Succeeded()
