"""The one imaging-chain builder of the simulated station (seed III-A).

    X_BP -> SliceSensor (label volume, optionally moving with the patient)
         -> [label_image_hook: e.g. reliability's label-frame faults]
         -> UltrasoundEmulator -> us_image

Everything that emulates the ultrasound machine in simulation goes through
:func:`AddImagingChain`; fault injection reaches it only through ``label_image_hook``, which
the caller (``drake_rus.reliability``) passes in from outside.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

from pydrake.math import RigidTransform
from pydrake.systems.framework import DiagramBuilder, OutputPort

from drake_rus.anatomy.labels import LabelVolume
from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.systems import SliceSensor, UltrasoundEmulator

__all__ = ["AddImagingChain", "ImagingChain", "LabelImageHook"]

# (builder, label_image port) -> the label_image port the emulator should read.
LabelImageHook = Callable[[DiagramBuilder, OutputPort], OutputPort]


@dataclasses.dataclass
class ImagingChain:
    """Ports of the imaging chain: ``us_image`` (UsFrame, grey uint8) and ``label_image``
    (UsFrame, tissue labels: what the emulator was given, after any hook)."""

    sensor: SliceSensor
    emulator: UltrasoundEmulator
    us_image: OutputPort
    label_image: OutputPort


def AddImagingChain(
    builder: DiagramBuilder,
    config: ImagingConfig,
    volume: LabelVolume,
    X_BV: RigidTransform,
    X_BP_port: OutputPort,
    *,
    seed: int = 0,
    motion=None,
    label_image_hook: LabelImageHook | None = None,
    offset_port: OutputPort | None = None,
    slice_frames: bool = True,
) -> ImagingChain:
    """Adds slice sensor -> [hook] -> emulator to ``builder``.

    Args:
        config: the scenario's ``imaging`` section.
        volume, X_BV: the patient's label volume and the pose of its grid in B.
        X_BP_port: the probe tip pose (RigidTransform) the sensor slices at.
        seed: the emulator's speckle seed.
        motion: optional patient motion (``offset_B(t)``, m in B) moving the volume.
        label_image_hook: optional filter on the label frames before the emulator.
        offset_port: optional 3-vector port (m in B) moving the volume instead of
            ``motion`` (a patient who reacts to the scan's prompts).
        slice_frames: False: the sensor never slices (no frames in the diagram; a renderer
            outside it slices at the sensor's poses, see ``SliceSensor``).
    """
    sensor = builder.AddNamedSystem(
        "slice_sensor", SliceSensor(config, volume, X_BV, motion, acquire=slice_frames)
    )
    builder.Connect(X_BP_port, sensor.GetInputPort("X_BP"))
    if offset_port is not None:
        builder.Connect(offset_port, sensor.GetInputPort("offset_B"))
    label_image = sensor.GetOutputPort("label_image")
    if label_image_hook is not None:
        label_image = label_image_hook(builder, label_image)
    emulator = builder.AddNamedSystem("ultrasound_emulator", UltrasoundEmulator(config, seed))
    builder.Connect(label_image, emulator.GetInputPort("label_image"))
    return ImagingChain(sensor, emulator, emulator.GetOutputPort("us_image"), label_image)
