"""Emulated frames with ground-truth kidney masks: the segmenter's training and test data.

Recipe (the same for training and evaluation; only the patients differ):

1. a labelled volume (a virtual patient from ``drake_rus.anatomy.load_patient``, or a
   synthetic :func:`~drake_rus.imaging.phantoms.kidney_phantom`);
2. probe poses that look at the kidney through the skin, like the exploration's transverse
   views: a random kidney voxel, moved up to ``lateral_jitter`` across the beam (so some
   views only graze the kidney or miss it), an approach direction within ``tilt_deg`` of
   the volume's skin-facing direction (a ``far_fraction`` of views up to ``far_jitter``
   off, which often miss it), the face placed on the skin along that line and
   pressed ``indent`` into it, a random rotation of the array about the beam;
3. per pose: label image (:func:`slice_volume`), emulated image (:func:`emulate`, speckle
   seeded by the frame index), mask = kidney labels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydrake.math import RigidTransform, RotationMatrix

from drake_rus.anatomy.labels import Label, LabelVolume, is_kidney
from drake_rus.imaging.emulator import EmulatorModel, emulate
from drake_rus.imaging.slicing import sample_labels, slice_volume


@dataclass
class ViewSampler:
    """Samples probe poses X_VP (in the volume's grid frame V) that look at the kidney."""
    volume: LabelVolume
    approach_V: np.ndarray            # unit vector from the kidney towards the skin, in V
    tilt_deg: float = 25.0
    lateral_jitter: float = 0.025     # m
    far_fraction: float = 0.15        # share of views offset up to far_jitter (may miss)
    far_jitter: float = 0.07          # m
    indent: float = 0.004             # m, face pressed into the skin
    max_depth: float = 0.16           # m, give up if no skin within this distance

    def __post_init__(self):
        self.approach_V = np.asarray(self.approach_V, float)
        self.approach_V /= np.linalg.norm(self.approach_V)
        k = np.argwhere(is_kidney(self.volume.labels))
        if len(k) == 0:
            raise ValueError("ViewSampler: the volume has no kidney voxels")
        self._kidney_V = k * self.volume.voxel_size

    def _skin_along(self, p_V: np.ndarray, u: np.ndarray) -> np.ndarray | None:
        """First air point going from p_V along u (None if none within max_depth)."""
        h = self.volume.voxel_size
        s = np.arange(0.0, self.max_depth, 0.5 * h)
        labels = sample_labels(self.volume, p_V + s[:, None] * u)
        air = np.flatnonzero(labels == Label.OUTSIDE)
        if len(air) == 0:
            return None
        return p_V + s[air[0]] * u

    def sample(self, rng: np.random.Generator, tries: int = 20) -> RigidTransform | None:
        """A probe pose X_VP, or None when no skin was found in ``tries`` attempts."""
        for _ in range(tries):
            target = self._kidney_V[rng.integers(len(self._kidney_V))]
            # Approach direction: within tilt_deg of approach_V (uniform on the cap).
            cos_max = np.cos(np.radians(self.tilt_deg))
            cz = rng.uniform(cos_max, 1.0)
            phi = rng.uniform(0, 2 * np.pi)
            sz = np.sqrt(1 - cz * cz)
            a = self.approach_V
            e1 = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(a, e1)
            u = cz * a + sz * (np.cos(phi) * e1 + np.sin(phi) * e2)
            # Lateral jitter across the beam.
            w = rng.normal(size=3)
            w -= w.dot(u) * u
            w /= np.linalg.norm(w)
            jitter = self.far_jitter if rng.random() < self.far_fraction else self.lateral_jitter
            target = target + rng.uniform(0, jitter) * w
            skin = self._skin_along(target, u)
            if skin is None:
                continue
            origin = skin - (self.indent + 0.5 * self.volume.voxel_size) * u
            z = -u
            x = np.cross(rng.normal(size=3), z)
            x /= np.linalg.norm(x)
            y = np.cross(z, x)
            return RigidTransform(RotationMatrix(np.column_stack([x, y, z])), origin)
        return None


def make_frames(volume: LabelVolume, approach_V: np.ndarray, model: EmulatorModel, n: int,
                rng: np.random.Generator, seed: int = 0, first_index: int = 0,
                planes: int = 1, combine: str = "majority"):
    """``n`` (emulated image uint8, kidney mask bool, label image uint8, X_VP) tuples."""
    sampler = ViewSampler(volume, approach_V)
    out = []
    X_VV = RigidTransform()
    i = 0
    while len(out) < n and i < 5 * n:
        i += 1
        X_VP = sampler.sample(rng)
        if X_VP is None:
            continue
        labels = slice_volume(model.geometry, volume, X_VV, X_VP, planes, combine)
        idx = first_index + len(out)
        us = emulate(labels, model, seed, idx)
        out.append((us, is_kidney(labels), labels, X_VP))
    return out
