"""Emulated frames with ground-truth kidney masks: the segmenter's training and test data.

Recipe (the same for training and evaluation; only the patients differ):

1. a labelled volume (a virtual patient from ``drake_rus.anatomy.load_patient``, or a
   synthetic :func:`~drake_rus.imaging.phantoms.kidney_phantom`), in either posture; the
   probe looks down from above the patient (+z of the bed frame): through the upper
   (anterior) skin when supine, through the right flank in left lateral decubitus;
2. probe poses that look at the kidney through the skin, like the exploration's transverse
   views: a random kidney voxel, moved up to ``lateral_jitter`` across the beam (so some
   views only graze the kidney or miss it), an approach direction within ``tilt_deg`` of
   the volume's skin-facing direction (a ``far_fraction`` of views up to ``far_jitter``
   off, which often miss it; a ``free_fraction`` aimed ``free_offset`` away, kidney-free
   at most depths; a ``near_miss_fraction`` whose image plane passes ``near_miss_offset``
   beyond the kidney's last voxel along the plane's normal: kidney-free, with the kidney's
   surroundings, its perirenal fat shell among them, in view), the face placed on the skin
   along that line and pressed ``indent`` into it, a random rotation of the array about the
   beam;
3. per pose: label image (:func:`slice_volume`), emulated image (:func:`emulate`, speckle
   seeded by the frame index), mask = kidney labels.

Training extras (:func:`canvas_frames`, used by ``train_segmenter``): every frame at a random
depth preset, an emulator with randomised gain, TGC, dynamic range, frequency, interface
echo and speckle grain (:func:`randomised_emulator`), volumes with a thicker wall
(:func:`thicken_wall`: more subcutaneous fat, and more tissue between the wall and the
kidney, so kidneys also lie as deep as in real bodies), the kidney's context and inside
randomised (:func:`remove_perirenal_fat`: cortex against soft tissue; :func:`layered_kidney`
with :func:`draw_kidney_layers`: cortex, continuous medulla and sinus in layers of published
thickness, as imported kidneys are labelled; :func:`thin_cortex`), and image and mask stored
on the model's physical canvas (:class:`~drake_rus.imaging.onnx_backend.PhysicalCanvas`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from pydrake.math import RigidTransform, RotationMatrix
from scipy import ndimage

from drake_rus.anatomy.labels import Label, LabelVolume, is_kidney
from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.emulator import EmulatorModel, emulate
from drake_rus.imaging.onnx_backend import PhysicalCanvas
from drake_rus.imaging.probe import ProbeGeometry
from drake_rus.imaging.slicing import sample_labels, slice_volume


@dataclass
class ViewSampler:
    """Samples probe poses X_VP (in the volume's grid frame V) that look at the kidney."""

    volume: LabelVolume
    approach_V: np.ndarray  # unit vector from the kidney towards the skin, in V
    tilt_deg: float = 25.0
    lateral_jitter: float = 0.025  # m
    far_fraction: float = 0.15  # share of views offset up to far_jitter (may miss)
    far_jitter: float = 0.07  # m
    indent: float = 0.004  # m, face pressed into the skin
    max_depth: float = 0.16  # m, give up if no skin within this distance
    free_fraction: float = 0.0  # share of views aimed free_offset away (kidney-free)
    free_offset: tuple = (0.08, 0.16)  # m, range of that offset across the beam
    # Share of views whose image plane lies just beyond the kidney: the plane through the
    # aim point is moved along its normal until it clears every kidney voxel, then
    # near_miss_offset further (m). What the scan's pivot images past the kidney's edge: the
    # perirenal fat shell's section, an ellipse like a kidney's (docs/results/segmenter.md,
    # 2026-11-28, "false marks past the kidney's edge").
    near_miss_fraction: float = 0.0
    near_miss_offset: tuple = (0.001, 0.012)
    targets_V: np.ndarray | None = field(default=None, repr=False)  # (N, 3) aim points in V

    def __post_init__(self):
        self.approach_V = np.asarray(self.approach_V, float)
        self.approach_V /= np.linalg.norm(self.approach_V)
        if self.targets_V is not None:
            self._kidney_V = np.asarray(self.targets_V, float).reshape(-1, 3)
            if len(self._kidney_V) == 0:
                raise ValueError("ViewSampler: targets_V is empty")
            return
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
            # (The near-miss and free-view draws only when asked for, so the default keeps its
            # old sequence.)
            if self.near_miss_fraction > 0 and rng.random() < self.near_miss_fraction:
                X_VP = self._near_miss(target, u, rng)
                if X_VP is None:
                    continue
                return X_VP
            if self.free_fraction > 0 and rng.random() < self.free_fraction:
                target = target + rng.uniform(*self.free_offset) * w
                if sample_labels(self.volume, target[None])[0] == Label.OUTSIDE:
                    continue
            else:
                jitter = (
                    self.far_jitter if rng.random() < self.far_fraction else self.lateral_jitter
                )
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

    def _near_miss(self, target, u, rng: np.random.Generator) -> RigidTransform | None:
        """A pose looking along ``u`` whose image plane (normal y_P, a random rotation about
        the beam) lies ``near_miss_offset`` beyond the kidney's last voxel along y_P, or
        None when no skin is found."""
        z = -np.asarray(u, float)
        x = np.cross(rng.normal(size=3), z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        # Nearest-voxel slicing reaches up to sqrt(3) h / 2 from a voxel centre along any
        # normal: the plane clears the last centre by one voxel h more.
        clear = float(np.max((self._kidney_V - target) @ y)) + self.volume.voxel_size
        moved = target + (clear + rng.uniform(*self.near_miss_offset)) * y
        skin = self._skin_along(moved, u)
        if skin is None:
            return None
        origin = skin - (self.indent + 0.5 * self.volume.voxel_size) * u
        return RigidTransform(RotationMatrix(np.column_stack([x, y, z])), origin)


def make_frames(
    volume: LabelVolume,
    approach_V: np.ndarray,
    model: EmulatorModel,
    n: int,
    rng: np.random.Generator,
    seed: int = 0,
    first_index: int = 0,
    planes: int = 1,
    combine: str = "majority",
    sampler: ViewSampler | None = None,
):
    """``n`` (emulated image uint8, kidney mask bool, label image uint8, X_VP) tuples
    (``sampler``: default ``ViewSampler(volume, approach_V)``)."""
    sampler = sampler or ViewSampler(volume, approach_V)
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


# --- training extras ------------------------------------------------------------------------

# Labels of the body wall above the kidney (skin side): what stays "wall" when the wall is
# thickened; the first other label below the skin is the top of what lies inside it.
_WALL = (Label.OUTSIDE, Label.FAT, Label.MUSCLE, Label.BONE)


def thicken_wall(
    volume: LabelVolume, up_V, fat: float = 0.0, inner: float = 0.0, chunk: int = 8192
) -> LabelVolume:
    """The volume with a thicker wall under the upper skin (``up_V``, a grid axis within
    18 deg): ``fat`` (m) more subcutaneous fat on top of every column of voxels along up,
    and ``inner`` (m) more soft tissue between the wall (fat, muscle, bone) and what lies
    under it (viscera, liver or the kidney), so the kidney lies that much deeper below the
    upper skin. Everything below the insertion keeps its place in the patient frame; the
    grid grows towards the skin. Columns with no tissue under the wall (the far flanks) move
    up whole, so the wall stays continuous. A modelling choice for domain randomisation (the
    generator does not expose fat thickness), not anatomy."""
    h = volume.voxel_size
    tf, ti = int(round(fat / h)), int(round(inner / h))
    if tf < 0 or ti < 0:
        raise ValueError(f"thicken_wall: fat and inner must be >= 0, got {fat}, {inner}")
    if tf == ti == 0:
        return volume
    up = np.asarray(up_V, float)
    up = up / np.linalg.norm(up)
    axis = int(np.argmax(np.abs(up)))
    if abs(up[axis]) < np.cos(np.radians(18)):
        raise ValueError(f"thicken_wall: up_V {up} is not close to a grid axis")
    positive = up[axis] > 0
    L = np.moveaxis(volume.labels, axis, -1)
    if not positive:
        L = L[..., ::-1]
    shape = L.shape
    cols = L.reshape(-1, shape[-1])  # bottom first: index grows towards the skin
    Z, T = shape[-1], tf + ti
    out = np.empty((cols.shape[0], Z + T), volume.labels.dtype)
    o = np.arange(Z + T)[None, :]
    wall_lut = np.zeros(256, bool)
    wall_lut[list(_WALL)] = True
    for a in range(0, cols.shape[0], chunk):
        u = cols[a : a + chunk]
        tissue = u != Label.OUTSIDE
        has = tissue.any(axis=1)
        top = Z - 1 - np.argmax(tissue[:, ::-1], axis=1)  # topmost tissue voxel
        inside = ~wall_lut[u]
        has_in = inside.any(axis=1)
        hc = np.where(has_in, Z - np.argmax(inside[:, ::-1], axis=1), 0)[:, None]
        top = top[:, None]
        shift = np.where(o < hc, 0, np.where(o < hc + ti, -1, ti))
        src = np.clip(o - np.maximum(shift, 0), 0, Z - 1)
        col = np.take_along_axis(u, src, axis=1)
        fill_in = np.where(has_in, int(Label.SOFT_TISSUE), u[:, 0])[:, None]
        col = np.where(shift < 0, fill_in, col)
        above = o > top + ti
        fat_zone = above & (o <= top + ti + tf) & has[:, None]
        col = np.where(above, int(Label.OUTSIDE), col)
        col = np.where(fat_zone, int(Label.FAT), col)
        out[a : a + chunk] = col
    out = out.reshape(shape[:-1] + (Z + T,))
    if not positive:
        out = out[..., ::-1]
    labels = np.ascontiguousarray(np.moveaxis(out, -1, axis))
    X_PtV = volume.X_PtV
    if not positive:
        # Old voxel i is now i + T along the axis: move the grid origin back by T voxels.
        e = np.zeros(3)
        e[axis] = -T * h
        X_PtV = X_PtV @ RigidTransform(e)
    return LabelVolume(labels, h, X_PtV)


@dataclass(frozen=True)
class Randomisation:
    """Ranges of the per-frame domain randomisation (uniform unless said otherwise)."""

    gain_db: tuple = (-18.0, -6.0)  # scenario default -12
    # TGC slope: the default 0.7 dB/cm/MHz, changed by this many dB at the image's bottom (a
    # fixed range in dB whatever the depth and frequency, like the TGC sliders of a scanner).
    tgc_bottom_db: tuple = (-10.0, 10.0)
    dynamic_range_db: tuple = (42.0, 58.0)  # default 50
    frequency_mhz: tuple = (2.5, 5.0)  # default 3.5 (attenuation vs TGC)
    interface_gain: tuple = (3.0, 9.0)  # default 6
    scan_lines: tuple = (96, 128, 160)  # speckle grain across the beam (default 128)
    samples_per_line: tuple = (192, 256, 320)  # speckle grain along it (default 256)
    nominal_grain: float = 0.5  # share of frames at the default grain
    speckle_seeds: int = 64  # speckle banks drawn from
    # Echogenicity (backscatter amplitude) of each tissue times a factor in this range, so
    # the model cannot rely on one brightness order of kidney and surroundings (real bodies
    # differ: no bright perirenal fat rim in the VH female, for one).
    # The ranges keep the cortex about iso- to hypo-echoic to liver and soft tissue.
    echogenicity: tuple = (
        (int(Label.SOFT_TISSUE), 0.85, 1.3),
        (int(Label.FAT), 0.6, 1.2),
        (int(Label.MUSCLE), 0.7, 1.3),
        (int(Label.LIVER), 0.85, 1.3),
        (int(Label.KIDNEY_CORTEX), 0.75, 1.1),
        (int(Label.KIDNEY_MEDULLA), 0.6, 1.4),
        (int(Label.KIDNEY_SINUS), 0.8, 1.1),
    )
    # Share of frames made with the scenario's emulator as is (no randomisation at all).
    nominal: float = 0.35


def randomised_emulator(
    base: EmulatorModel, rng: np.random.Generator, r: Randomisation = Randomisation()
) -> EmulatorModel:
    """``base`` with randomised gain, TGC, dynamic range, frequency and interface echo (the
    TGC offset relative to ``base``'s); the geometry's precomputed tables (scan lines, scan
    conversion, speckle banks) are shared."""
    f = float(rng.uniform(*r.frequency_mhz))
    depth_cm = 100.0 * base.geometry.depth
    tgc = base.tgc_db_per_cm_mhz + float(rng.uniform(*r.tgc_bottom_db)) / (2 * f * depth_cm)
    m = replace(
        base,
        gain_db=float(rng.uniform(*r.gain_db)),
        tgc_db_per_cm_mhz=max(0.0, tgc),
        dynamic_range_db=float(rng.uniform(*r.dynamic_range_db)),
        frequency_mhz=f,
        interface_gain=float(rng.uniform(*r.interface_gain)),
    )
    for name in (
        "polar_to_image_index",
        "scan_conversion",
        "scan_matrix",
        "tables",
        "compact_codes",
        "_banks",
        "_polar_index_T",
        "_scan_csr_T",
        "_scan_quads",
        "_banks_T",
    ):
        object.__setattr__(m, name, getattr(base, name))
    if r.echogenicity:
        # The diffuse-echo table depends only on the sample's own tissue code (low 4 bits).
        loss, diffuse, spec = m.pair_luts
        e = np.sqrt(diffuse[:16]).astype(np.float64)  # echogenicity per code
        for label, lo, hi in r.echogenicity:
            e[int(label)] *= rng.uniform(lo, hi)
        diffuse = np.ascontiguousarray((e**2)[np.arange(256) & 15], dtype=np.float32)
        object.__setattr__(m, "pair_luts", (loss, diffuse, spec))
    return m


def _relabel_by_depth(volume: LabelVolume, relabel) -> LabelVolume:
    """A copy of ``volume`` whose kidneys ``relabel(sub, kidney, depth)`` relabelled in
    place: ``sub`` the labels over the kidneys' bounding box grown by one voxel, ``kidney``
    the kidney mask there and ``depth`` (m) the depth below the kidney's surface. The
    volume itself without kidney voxels."""
    kid = is_kidney(volume.labels)
    idx = np.argwhere(kid)
    if len(idx) == 0:
        return volume
    lo = np.maximum(idx.min(axis=0) - 1, 0)
    hi = np.minimum(idx.max(axis=0) + 2, volume.labels.shape)
    box = tuple(slice(a, b) for a, b in zip(lo, hi))
    k = kid[box]
    labels = volume.labels.copy()
    relabel(labels[box], k, ndimage.distance_transform_edt(k) * volume.voxel_size)
    return LabelVolume(labels, volume.voxel_size, volume.X_PtV)


def thin_cortex(volume: LabelVolume, cortex: float = 0.004) -> LabelVolume:
    """The volume with the kidney's cortex deeper than ``cortex`` (m) below the kidney's
    surface made medulla: a thin cortex over a continuous dark medulla, a kidney structure
    the generator does not make (it draws discrete pyramids in a thick cortex). Domain
    randomisation of the kidney's inside; the kidney's outline does not change."""

    def relabel(sub, k, depth):
        sub[(depth > cortex) & (sub == Label.KIDNEY_CORTEX)] = Label.KIDNEY_MEDULLA

    return _relabel_by_depth(volume, relabel)


def layered_kidney(
    volume: LabelVolume, cortex: float = 0.0066, parenchyma: float = 0.0154
) -> LabelVolume:
    """The volume with its kidneys relabelled in layers by depth below the kidney's surface:
    cortex up to ``cortex`` (m), a continuous medulla up to ``parenchyma`` (m), sinus deeper;
    the rule the importer applies to every imported kidney (``anatomy/importers.py``,
    Glodny 2009 means 6.6 / 15.4 mm; surface meshes resolve no pyramids), where the generator
    draws discrete pyramids in a thick cortex. Domain randomisation of the kidney's inside
    (draw the depths with :func:`draw_kidney_layers`); the outline does not change."""
    if not 0 < cortex < parenchyma:
        raise ValueError(
            f"layered_kidney: need 0 < cortex < parenchyma, got {cortex}, {parenchyma}"
        )

    def relabel(sub, k, depth):
        sub[k] = Label.KIDNEY_CORTEX
        sub[k & (depth >= cortex)] = Label.KIDNEY_MEDULLA
        sub[k & (depth >= parenchyma)] = Label.KIDNEY_SINUS

    return _relabel_by_depth(volume, relabel)


# Published kidney layer thicknesses (docs/facts/anatomy_and_ultrasound.md, Glodny 2009):
# cortex 6.6 +- 1.9 mm, parenchymal width (right) 15.4 +- 2.8 mm.
CORTEX_MM = (6.6, 1.9)
PARENCHYMA_MM = (15.4, 2.8)


def draw_kidney_layers(
    rng: np.random.Generator,
    clip_cortex=(0.003, 0.011),
    min_medulla: float = 0.004,
    max_parenchyma: float = 0.025,
) -> tuple[float, float]:
    """(cortex, parenchyma) depths (m) for :func:`layered_kidney`: normal draws around the
    published means and SDs (:data:`CORTEX_MM`, :data:`PARENCHYMA_MM`), the cortex clipped
    to ``clip_cortex``, the parenchyma at least ``min_medulla`` deeper than the cortex and at
    most ``max_parenchyma``."""
    c = float(np.clip(rng.normal(CORTEX_MM[0], CORTEX_MM[1]) * 1e-3, *clip_cortex))
    p = float(
        np.clip(
            rng.normal(PARENCHYMA_MM[0], PARENCHYMA_MM[1]) * 1e-3,
            c + min_medulla,
            max(max_parenchyma, c + min_medulla),
        )
    )
    return c, p


def remove_perirenal_fat(volume: LabelVolume, margin: float = 0.015) -> LabelVolume:
    """The volume with fat within ``margin`` (m) of the kidney relabelled soft tissue (no
    bright fat rim or fat-kidney interface echo around the kidney, as in a body imported
    without perirenal fat). Domain randomisation, not anatomy."""
    kid = is_kidney(volume.labels)
    idx = np.argwhere(kid)
    if len(idx) == 0:
        return volume
    r = int(np.ceil(margin / volume.voxel_size - 1e-9))
    lo = np.maximum(idx.min(axis=0) - r - 1, 0)
    hi = np.minimum(idx.max(axis=0) + r + 2, volume.labels.shape)
    box = tuple(slice(a, b) for a, b in zip(lo, hi))
    near = ndimage.distance_transform_edt(~kid[box]) * volume.voxel_size <= margin + 1e-9
    labels = volume.labels.copy()
    sub = labels[box]
    sub[near & (sub == Label.FAT)] = Label.SOFT_TISSUE
    return LabelVolume(labels, volume.voxel_size, volume.X_PtV)


class EmulatorBank:
    """Base emulator models per (depth, scan lines, samples per line), built once each."""

    def __init__(self, config: ImagingConfig | None = None):
        self.config = config or ImagingConfig()
        self._models: dict = {}

    def get(
        self, depth: float, lines: int | None = None, samples: int | None = None
    ) -> EmulatorModel:
        c = self.config
        key = (
            round(float(depth), 6),
            int(lines or c.scan_lines),
            int(samples or c.samples_per_line),
        )
        m = self._models.get(key)
        if m is None:
            cfg = replace(c, depth=key[0], scan_lines=key[1], samples_per_line=key[2])
            m = self._models[key] = EmulatorModel.from_config(cfg, ProbeGeometry.from_config(cfg))
        return m


@dataclass
class VolumeVariant:
    """A (possibly thickened) volume of one patient and posture, with its view sampler."""

    volume: LabelVolume
    approach_V: np.ndarray
    extra_depth: float = 0.0  # m the kidney was moved down (fat + inner)
    fat: float = 0.0
    inner: float = 0.0
    sampler_kw: dict = field(default_factory=dict)
    weight: float = 1.0  # how often its views are drawn, relative to the other variants

    def __post_init__(self):
        self.sampler = ViewSampler(self.volume, self.approach_V, **self.sampler_kw)


def canvas_frames(
    variants: list[VolumeVariant],
    presets: list[float],
    n: int,
    rng: np.random.Generator,
    bank: EmulatorBank,
    pixel_size: float,
    canvas_shape: tuple[int, int],
    canvas_top: float | None,
    randomisation: Randomisation | None = Randomisation(),
    max_extra=lambda depth: max(0.0, depth - 0.10) + 0.03,
    preset_weights=None,
) -> dict:
    """``n`` randomised training frames on the physical canvas: for each, a depth preset
    (over ``presets``, with ``preset_weights`` or uniform), a volume variant whose ``extra_depth``
    is at most ``max_extra(depth)`` (so thick walls come with the deep presets; drawn by the
    variants' ``weight``), a view, a randomised
    emulator (``randomisation`` None: the scenario's, at every frame; else a share
    ``randomisation.nominal`` of frames with the scenario's) and a random speckle seed.

    Returns arrays: ``image`` (n, H, W) float16 grey 0-255 on the canvas, ``kidney`` (n, H,
    W) float16 kidney area fraction per canvas pixel, ``depth`` (n,), ``variant`` (n,),
    ``kidney_px`` (n,) kidney pixels in the 256 x 256 image."""
    H, W = canvas_shape
    images = np.zeros((n, H, W), np.float16)
    masks = np.zeros((n, H, W), np.float16)
    depth_of = np.zeros(n, np.float32)
    variant_of = np.zeros(n, np.int16)
    kidney_px = np.zeros(n, np.int32)
    canvases: dict = {}
    r = randomisation
    pw = np.ones(len(presets)) if preset_weights is None else np.asarray(preset_weights, float)
    pw = pw / pw.sum()
    X_VV = RigidTransform()
    k = 0
    attempts = 0
    while k < n:
        attempts += 1
        if attempts > 20 * n + 100:
            raise RuntimeError(f"canvas_frames: only {k} of {n} views found")
        depth = float(presets[rng.choice(len(presets), p=pw)])
        allowed = [i for i, v in enumerate(variants) if v.extra_depth <= max_extra(depth)]
        if not allowed:
            vi = 0
        else:
            w = np.array([variants[i].weight for i in allowed], float)
            vi = allowed[rng.choice(len(allowed), p=w / w.sum())]
        v = variants[vi]
        X_VP = v.sampler.sample(rng)
        if X_VP is None:
            continue
        nominal = r is None or rng.random() < r.nominal
        if not nominal and rng.random() >= r.nominal_grain:
            base = bank.get(
                depth, int(rng.choice(r.scan_lines)), int(rng.choice(r.samples_per_line))
            )
        else:
            base = bank.get(depth)
        model = base if nominal else randomised_emulator(base, rng, r)
        g = base.geometry
        canvas = canvases.get(depth)
        if canvas is None:
            canvas = canvases[depth] = PhysicalCanvas(g, pixel_size, canvas_shape, canvas_top)
        labels = slice_volume(g, v.volume, X_VV, X_VP)
        seed = int(rng.integers(r.speckle_seeds if r is not None else 64))
        us = emulate(labels, model, seed, int(rng.integers(1 << 30)))
        kid = is_kidney(labels)
        images[k] = canvas.to_canvas(us)
        masks[k] = canvas.to_canvas(kid.astype(np.float32))
        depth_of[k], variant_of[k], kidney_px[k] = depth, vi, int(kid.sum())
        k += 1
    return {
        "image": images,
        "kidney": masks,
        "depth": depth_of,
        "variant": variant_of,
        "kidney_px": kidney_px,
    }
