"""B-mode-like ultrasound emulation from a label image, along the fan's scan lines.

Per scan line (a ray from the array into the body), every sample gets:

- diffuse backscatter: the tissue's echogenicity squared times fully developed speckle
  (exponentially distributed intensity, i.e. Rayleigh amplitude);
- a specular echo where the acoustic impedance changes: amplitude reflection coefficient
  ``r = |Z2 - Z1| / (Z2 + Z1)`` times ``interface_gain``;
- two-way transmission losses through every interface before it, ``prod (1 - r^2)^2``:
  soft tissue to gas reflects about 99.9% (complete shadow), to bone about 43%, and bone's
  5-15 dB/cm/MHz attenuation darkens the rest (strong shadow behind ribs);
- two-way attenuation ``2 f sum(alpha ds)`` (dB), minus the time-gain compensation;
- log compression to ``dynamic_range_db`` and scan conversion to the Cartesian image.

Depths assume the nominal 1540 m/s (speed-of-sound errors are not emulated). Tissue numbers:
``docs/facts/anatomy_and_ultrasound.md`` "Tissue acoustics" unless a comment says otherwise.
Deterministic: the speckle of frame ``k`` depends only on (seed, k).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy import ndimage

from drake_rus.anatomy.labels import Label
from drake_rus.imaging import kernels
from drake_rus.imaging._ufuncs import clip
from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.probe import ProbeGeometry

# Look-up index of coupling gel: air between the face and the skin within ``gel_gap`` of the
# face (the face's corners above a flat skin) is taken as gel, as on a gel-coupled probe.
GEL = 255
# Look-up index standing for the probe face (gel-coupled: impedance of gel) before sample 0.
PROBE_LABEL = GEL
# Smallest echo intensity before log compression (-120 dB): the echo of anechoic samples.
ECHO_FLOOR = np.float32(1e-12)


@dataclass(frozen=True)
class Tissue:
    impedance: float  # MRayl
    attenuation: float  # dB/cm/MHz
    echogenicity: float  # relative backscatter amplitude (1 = brightest parenchyma)


# Tissue table by label (facts: "Tissue acoustics"; echogenicity from the facts' ordering:
# sinus fat brightest, cortex iso- to hypo-echoic to liver, pyramids darker, vessels
# anechoic).
TISSUES: dict[int, Tissue] = {
    Label.OUTSIDE: Tissue(0.0004, 7.5, 0.0),  # air, like bowel gas
    Label.SOFT_TISSUE: Tissue(1.63, 0.7, 0.50),  # generic soft tissue (liver-like)
    Label.FAT: Tissue(1.38, 0.63, 0.70),  # fat: 1.38 MRayl, 0.63 dB/cm/MHz
    Label.MUSCLE: Tissue(1.70, 1.2, 0.35),  # muscle: 1.70 MRayl, 1.0-1.4
    Label.KIDNEY_CORTEX: Tissue(1.62, 1.0, 0.40),  # kidney: 1.62 MRayl, 1.0
    Label.KIDNEY_MEDULLA: Tissue(1.62, 1.0, 0.18),  # pyramids: darker than cortex
    Label.KIDNEY_SINUS: Tissue(1.38, 0.63, 1.00),  # sinus fat: fat's acoustics, brightest
    Label.LIVER: Tissue(1.65, 0.6, 0.50),  # liver: 1.65 MRayl, 0.5-0.7
    Label.BONE: Tissue(7.8, 10.0, 0.30),  # rib: 7.8 MRayl, 5-15 dB/cm/MHz
    Label.GAS: Tissue(0.0004, 7.5, 0.0),  # bowel gas: 0.0004 MRayl, 7.5
    # Blood (not in the facts table): about 1.61 MRayl and 0.18 dB/cm/MHz (textbook values).
    Label.VESSEL: Tissue(1.61, 0.18, 0.02),
    # Renal tumour (renal cell carcinoma; facts: "Renal tumours"): a solid tissue with the
    # kidney's impedance and attenuation (no published values found), echogenicity between
    # isoechoic and mildly hyperechoic to the cortex, the commonest classes of tumours over
    # 3 cm (49% and 33%, Sidhar 2016). Necrosis, cysts and calcification are not modelled.
    Label.TUMOUR: Tissue(1.62, 1.0, 0.48),
    Label.KIDNEY_TUMOUR: Tissue(1.62, 1.0, 0.48),
}
# Labels missing from the table behave as generic soft tissue.
_DEFAULT_TISSUE = TISSUES[Label.SOFT_TISSUE]


def tissue_tables() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Look-up tables (256,) by label value: impedance, attenuation, echogenicity."""
    Z = np.full(256, _DEFAULT_TISSUE.impedance, np.float32)
    a = np.full(256, _DEFAULT_TISSUE.attenuation, np.float32)
    e = np.full(256, _DEFAULT_TISSUE.echogenicity, np.float32)
    for label, t in TISSUES.items():
        Z[int(label)], a[int(label)], e[int(label)] = t.impedance, t.attenuation, t.echogenicity
    # Ultrasound gel: water-like (about 1.5 MRayl, negligible attenuation), anechoic.
    Z[GEL], a[GEL], e[GEL] = 1.52, 0.05, 0.0
    return Z, a, e


@dataclass(frozen=True)
class EmulatorModel:
    """Precomputed scan-line geometry and tissue tables for :func:`emulate`."""

    geometry: ProbeGeometry
    scan_lines: int = 128
    samples_per_line: int = 256
    frequency_mhz: float = 3.5
    tgc_db_per_cm_mhz: float = 0.7
    dynamic_range_db: float = 50.0
    gain_db: float = -12.0
    speckle: bool = True
    interface_gain: float = 6.0
    gel_gap: float = 0.005

    @classmethod
    def from_config(
        cls, config: ImagingConfig, geometry: ProbeGeometry | None = None
    ) -> "EmulatorModel":
        return cls(
            geometry=geometry or ProbeGeometry.from_config(config),
            scan_lines=int(config.scan_lines),
            samples_per_line=int(config.samples_per_line),
            frequency_mhz=config.center_frequency_mhz,
            tgc_db_per_cm_mhz=config.tgc_db_per_cm_mhz,
            dynamic_range_db=config.dynamic_range_db,
            gain_db=config.gain_db,
            speckle=config.speckle,
            interface_gain=config.interface_gain,
            gel_gap=config.gel_gap,
        )

    @property
    def line_angles(self) -> np.ndarray:
        """Angle (rad) of each scan line, centres of equal angular bins across the fan."""
        g, L = self.geometry, self.scan_lines
        return -g.half_angle + (np.arange(L) + 0.5) * (2 * g.half_angle / L)

    @property
    def sample_spacing(self) -> float:
        """Distance (m) between samples along a line."""
        return self.geometry.depth / self.samples_per_line

    @property
    def sample_depths(self) -> np.ndarray:
        return (np.arange(self.samples_per_line) + 0.5) * self.sample_spacing

    @cached_property
    def polar_to_image_index(self) -> np.ndarray:
        """(L, S) flat index of the fan pixel nearest to every scan-line sample."""
        g = self.geometry
        th, d = np.meshgrid(self.line_angles, self.sample_depths, indexing="ij")
        uv = g.P_to_pixel(g.polar_to_P(th, d))
        u = np.clip(np.rint(uv[:, 0]).astype(np.intp), 0, g.width_px - 1)
        v = np.clip(np.rint(uv[:, 1]).astype(np.intp), 0, g.height_px - 1)
        # Samples whose nearest pixel centre falls just outside the fan take the nearest fan
        # pixel instead (else the fan's edge would read as air and cast a false shadow).
        rows, cols = ndimage.distance_transform_edt(
            ~g.fan_mask, return_distances=False, return_indices=True
        )
        flat = rows[v, u] * g.width_px + cols[v, u]
        return flat.reshape(self.scan_lines, self.samples_per_line).astype(np.int32)

    @cached_property
    def scan_conversion(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Bilinear weights from the polar grid to the fan pixels: (i00, i01, i10, i11) flat
        polar indices and (wl, ws) weights, for pixels in ``geometry.fan_flat_index`` order."""
        g, L, S = self.geometry, self.scan_lines, self.samples_per_line
        theta, d = g.P_to_polar(g.fan_p_P)
        lf = np.clip((theta + g.half_angle) / (2 * g.half_angle / L) - 0.5, 0, L - 1)
        sf = np.clip(d / self.sample_spacing - 0.5, 0, S - 1)
        l0 = np.minimum(np.floor(lf).astype(np.intp), L - 2)
        s0 = np.minimum(np.floor(sf).astype(np.intp), S - 2)
        wl = (lf - l0).astype(np.float32)
        ws = (sf - s0).astype(np.float32)
        i00 = l0 * S + s0
        return i00, wl, ws, np.intp(S)

    @cached_property
    def gel_samples(self) -> int:
        return int(min(self.samples_per_line, np.ceil(self.gel_gap / self.sample_spacing)))

    @cached_property
    def scan_matrix(self):
        """Sparse (rows * cols, L * S) bilinear interpolation matrix of the scan conversion;
        rows of pixels outside the fan are empty (they come out 0)."""
        import scipy.sparse as sps

        g = self.geometry
        i00, wl, ws, S = self.scan_conversion
        rows = np.repeat(g.fan_flat_index, 4)
        cols = np.stack([i00, i00 + 1, i00 + S, i00 + S + 1], axis=1).ravel()
        w = np.stack([(1 - wl) * (1 - ws), (1 - wl) * ws, wl * (1 - ws), wl * ws], axis=1)
        return sps.csr_matrix(
            (w.ravel().astype(np.float32), (rows, cols)),
            shape=(g.height_px * g.width_px, self.scan_lines * self.samples_per_line),
        )

    @cached_property
    def _polar_index_T(self) -> np.ndarray:
        """(S, L) ``polar_to_image_index`` transposed: the kernels work in (sample, line)
        order, the running loss of all lines advancing together."""
        return np.ascontiguousarray(self.polar_to_image_index.T, dtype=np.int32)

    @cached_property
    def _scan_csr_T(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``scan_matrix`` for polar images in (sample, line) order, as CSR arrays (indptr,
        indices, data): the same weights in the same order within each row (so the same
        sums), column l * S + s moved to s * L + l."""
        m = self.scan_matrix
        L, S = self.scan_lines, self.samples_per_line
        line, sample = np.divmod(m.indices.astype(np.int64), S)
        return m.indptr, (sample * L + line).astype(m.indices.dtype), m.data

    @cached_property
    def _scan_quads(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """``_scan_csr_T`` as (non-empty rows, first index of each, the 4 index offsets
        within a row, (n, 4) weights) when every non-empty row has 4 entries at the same
        offsets (a fan pixel's bilinear weights, as :attr:`scan_matrix` builds them), else
        None. A third of the CSR arrays' bytes to stream per frame."""
        indptr, indices, data = self._scan_csr_T
        counts = np.diff(indptr)
        rows = np.flatnonzero(counts)
        if rows.size == 0 or not np.all(counts[rows] == 4) or rows[-1] >= 2**31:
            return None
        quads = indices.reshape(-1, 4).astype(np.int64)
        offsets = quads[0] - quads[0, 0]
        if not np.array_equal(quads - quads[:, :1], np.broadcast_to(offsets, quads.shape)):
            return None
        return (
            rows.astype(np.int32),
            quads[:, 0].astype(np.int32),
            offsets,
            np.ascontiguousarray(data.reshape(-1, 4), dtype=np.float32),
        )

    @cached_property
    def tables(self):
        return tissue_tables()

    @cached_property
    def tgc_db(self) -> np.ndarray:
        """(S,) time-gain compensation (dB, two-way) plus the overall gain at every depth."""
        d_cm = self.sample_depths * 100.0
        return (2.0 * self.frequency_mhz * self.tgc_db_per_cm_mhz * d_cm + self.gain_db).astype(
            np.float32
        )

    @cached_property
    def compact_codes(self) -> np.ndarray:
        """(256,) uint8 code 0-15 per label value: labels 0-14 keep their value, gel is 15,
        any other label maps to soft tissue (as in :func:`tissue_tables`)."""
        codes = np.full(256, int(Label.SOFT_TISSUE), np.uint8)
        codes[:15] = np.arange(15)
        codes[GEL] = 15
        return codes

    @cached_property
    def pair_luts(self):
        """Pair tables (256,) indexed by ``code(prev) << 4 | code(label)``."""
        full = pair_tables(self)
        label_of_code = np.arange(16)
        label_of_code[15] = GEL
        idx = (label_of_code[:, None] << 8 | label_of_code[None, :]).ravel()
        return tuple(np.ascontiguousarray(t[idx]) for t in full)

    @cached_property
    def _kernel_tables(self) -> tuple:
        """The per-line tables of :func:`kernels.echo_and_loss` and the TGC: (codes by label,
        gel code, probe-face code, gel samples, loss, diffuse and specular pair tables,
        ``tgc_db``)."""
        codes = self.compact_codes
        loss, diffuse, spec = self.pair_luts
        return (
            codes,
            int(codes[GEL]),
            int(codes[PROBE_LABEL]),
            self.gel_samples,
            loss,
            diffuse,
            spec,
            self.tgc_db,
        )

    def speckle_bank(self, seed: int) -> np.ndarray:
        """(2L, 2S) speckle intensities (mean 1) for ``seed``; frames take shifted windows."""
        bank = self._banks.get(seed)
        if bank is None:
            rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0x5EC1E])
            bank = rng.standard_exponential(
                (2 * self.scan_lines, 2 * self.samples_per_line), dtype=np.float32
            )
            if len(self._banks) > 8:
                self._banks.clear()
            self._banks[seed] = bank
        return bank

    @cached_property
    def _banks(self) -> dict:
        return {}

    def _speckle_bank_T(self, seed: int) -> np.ndarray:
        """``speckle_bank(seed)`` transposed (2S, 2L), C-contiguous."""
        bank = self._banks_T.get(seed)
        if bank is None:
            if len(self._banks_T) > 8:
                self._banks_T.clear()
            bank = self._banks_T[seed] = np.ascontiguousarray(self.speckle_bank(seed).T)
        return bank

    @cached_property
    def _banks_T(self) -> dict:
        return {}

    @cached_property
    def _offsets(self) -> dict:
        """Speckle window offsets drawn ahead: seed -> (first frame, [(line, sample)])."""
        return {}


def pair_tables(model: "EmulatorModel") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Look-up tables (65536,) indexed by ``prev_label << 8 | label`` of a sample and the one
    before it on its scan line:

    - ``loss_db``: two-way loss (dB) entering this sample: interface transmission
      ``-10 log10((1 - r^2)^2)`` plus attenuation ``2 f alpha ds``;
    - ``diffuse``: backscatter intensity ``echogenicity^2`` of the sample's tissue;
    - ``specular``: the interface echo ``(interface_gain r)^2`` divided by the interface's
      own transmission (the echo comes back before crossing it).
    """
    Z, a, e = tissue_tables()
    Zp, Zc = Z[:, None].astype(np.float64), Z[None, :].astype(np.float64)
    r = np.abs(Zc - Zp) / (Zc + Zp)
    t2 = (1.0 - r * r) ** 2
    ds_cm = model.sample_spacing * 100.0
    loss = -10.0 * np.log10(t2) + 2.0 * model.frequency_mhz * ds_cm * a[None, :]
    diffuse = np.broadcast_to(e[None, :].astype(np.float64) ** 2, (256, 256))
    spec = (model.interface_gain * r) ** 2 / t2

    def as32(x):
        return np.ascontiguousarray(x, dtype=np.float32).reshape(-1)

    return as32(loss), as32(diffuse), as32(spec)


def line_db(
    labels_ls: np.ndarray, model: "EmulatorModel", speckle: np.ndarray | None
) -> np.ndarray:
    """Echo level (dB re the brightest parenchyma, float32) of label samples (L, S).

    ``10 log10(diffuse * speckle + specular) - cumulative loss + TGC + gain``: the
    cumulative two-way loss adds interface transmission and attenuation in dB along the line.
    Labels are label values 0-255 (any integer type); the speckle (broadcast to (L, S)) is
    taken as float32, the emulator's own type.
    """
    labels_ls = np.asarray(labels_ls)
    shape = labels_ls.shape
    if labels_ls.ndim != 2 or shape[1] != model.samples_per_line:
        raise ValueError(
            f"labels_ls: expected (lines, {model.samples_per_line}) label "
            f"samples, got shape {shape}"
        )
    if labels_ls.size and (labels_ls.min() < 0 or labels_ls.max() > 255):
        raise ValueError(
            f"labels_ls: expected label values 0-255, got {labels_ls.min()}..{labels_ls.max()}"
        )
    # The compiled pass works in (sample, line) order.
    index = np.arange(labels_ls.size, dtype=np.int32).reshape(shape[::-1])
    flat = np.ascontiguousarray(labels_ls.T, dtype=np.uint8).reshape(-1)
    if speckle is not None:
        speckle = np.ascontiguousarray(np.broadcast_to(speckle, shape).T, dtype=np.float32)
    echo, cum = _echo_and_loss(flat, index, model, speckle, 0, 0)
    np.log10(echo, out=echo)
    db = np.empty(echo.shape, np.float32)
    kernels.db_level(echo, cum, model._kernel_tables[-1], db)
    return np.ascontiguousarray(db.T)


def _echo_and_loss(
    label_flat: np.ndarray,
    index: np.ndarray,
    model: "EmulatorModel",
    bank: np.ndarray | None,
    i: int,
    j: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Echo intensities and running losses (S, L) float32 of the labels ``label_flat[index]``
    (:func:`kernels.echo_and_loss`), with the speckle window of ``bank`` (2S, 2L) at
    (sample i, line j)."""
    codes, gel, probe, n_gel, loss, diffuse, spec, _ = model._kernel_tables
    echo = np.empty(index.shape, np.float32)
    cum = np.empty(index.shape, np.float32)
    use = bank is not None
    kernels.echo_and_loss(
        label_flat,
        index,
        codes,
        gel,
        probe,
        n_gel,
        loss,
        diffuse,
        spec,
        bank if use else _NO_SPECKLE,
        i,
        j,
        use,
        ECHO_FLOOR,
        echo,
        cum,
    )
    return echo, cum


_NO_SPECKLE = np.ones((1, 1), np.float32)


def line_intensity(
    labels_ls: np.ndarray, model: "EmulatorModel", speckle: np.ndarray | None
) -> np.ndarray:
    """Echo intensity (L, S) (linear, before log compression) of label samples (L, S)."""
    return np.power(np.float32(10.0), line_db(labels_ls, model, speckle) / np.float32(10.0))


def db_to_grey(db: np.ndarray, dynamic_range_db: float) -> np.ndarray:
    """Echo level (dB) -> grey level in [0, 255] (float32): 0 dB white, -range black."""
    return _db_to_grey_inplace(db + np.float32(dynamic_range_db), dynamic_range_db)


def _db_to_grey_inplace(grey: np.ndarray, dynamic_range_db: float) -> np.ndarray:
    """The rest of :func:`db_to_grey` on ``db + dynamic_range_db``, in place."""
    grey *= np.float32(255.0 / dynamic_range_db)
    return clip(grey, np.float32(0.0), np.float32(255.0), out=grey)


def log_compress(intensity: np.ndarray, dynamic_range_db: float) -> np.ndarray:
    """Intensity -> grey level in [0, 255] (float32): 0 dB white, -dynamic_range black."""
    db = 10.0 * np.log10(np.maximum(intensity, 1e-12)).astype(np.float32)
    return db_to_grey(db, dynamic_range_db)


def speckle_field(model: EmulatorModel, seed: int, frame_index: int) -> np.ndarray:
    """(L, S) fully developed speckle intensity (exponential, mean 1) for a frame.

    A window of a per-seed bank of 2L x 2S draws, at an offset drawn from (seed, frame), so
    frames differ without drawing 32k random numbers per frame.
    """
    bank = model.speckle_bank(int(seed))
    i, j = _speckle_offset(model, seed, frame_index)
    return bank[i : i + model.scan_lines, j : j + model.samples_per_line]


def _speckle_offset(model: EmulatorModel, seed: int, frame_index: int) -> tuple[int, int]:
    """(line, sample) offset of a frame's speckle window in its seed's bank: two draws of a
    generator seeded with (seed, frame).

    Frames asked for in sequence (a scan) get their offsets drawn ahead, up to 64 frames at
    a time, the same draws one frame after the other: seeding a generator is a long path of
    Python and Cython code, about 10 us when it runs repeatedly but ten times that once per
    frame between simulation steps (the code is out of the caches by then)."""
    seed, frame_index = int(seed), int(frame_index)
    first, offsets = model._offsets.get(seed, (0, ()))
    k = frame_index - first
    if 0 <= k < len(offsets):
        return offsets[k]
    n = min(max(2 * len(offsets), 1), 64) if k == len(offsets) else 1
    L, S = model.scan_lines, model.samples_per_line
    offsets = []
    for f in range(frame_index, frame_index + n):
        rng = np.random.default_rng([seed & 0xFFFFFFFF, f & 0xFFFFFFFF])
        offsets.append((rng.integers(0, L + 1), rng.integers(0, S + 1)))
    if seed not in model._offsets and len(model._offsets) > 8:
        model._offsets.clear()
    model._offsets[seed] = (frame_index, offsets)
    return offsets[0]


def emulate(
    label_image: np.ndarray, model: EmulatorModel, seed: int = 0, frame_index: int = 0
) -> np.ndarray:
    """Emulated B-mode image (rows, cols) uint8 of a label image (rows, cols).

    Deterministic in (label_image, seed, frame_index). Pixels outside the fan are 0. Labels
    are label values 0-255 of any integer type (others raise ValueError).
    """
    g = model.geometry
    label_image = np.asarray(label_image)
    if label_image.shape != g.image_shape:
        raise ValueError(
            f"emulate: label image has shape {label_image.shape}, the probe "
            f"geometry expects {g.image_shape}"
        )
    flat = label_image.reshape(-1)
    if flat.dtype != np.uint8:
        # As line_db: the labels are read as uint8, so 263 would be imaged as the liver.
        if not (np.issubdtype(flat.dtype, np.integer) or flat.dtype == np.bool_):
            raise ValueError(
                f"emulate: label image: expected integer label values 0-255, got dtype {flat.dtype}"
            )
        if flat.size and (flat.min() < 0 or flat.max() > 255):
            raise ValueError(
                f"emulate: label image: expected label values 0-255, got {flat.min()}..{flat.max()}"
            )
        flat = flat.astype(np.uint8)  # as the samples' uint8 cast after the gather
    bank, i, j = None, 0, 0
    if model.speckle:
        bank = model._speckle_bank_T(int(seed))
        i, j = _speckle_offset(model, seed, frame_index)
    return _emulate(flat, model, bank, int(j), int(i))


def _emulate(
    label_flat: np.ndarray, model: EmulatorModel, bank: np.ndarray | None, i: int, j: int
) -> np.ndarray:
    """:func:`emulate` of a flat uint8 label image with the speckle window of ``bank`` (2S,
    2L) at (sample i, line j): the compiled per-line pass, numpy's log10, the compiled grey
    levels and scan conversion, all in (sample, line) order."""
    echo, cum = _echo_and_loss(label_flat, model._polar_index_T, model, bank, i, j)
    np.log10(echo, out=echo)
    dr, tgc = model.dynamic_range_db, model._kernel_tables[-1]
    image = np.zeros(model.geometry.image_shape, np.uint8)
    grey = np.empty(echo.size, np.float32)
    quads = model._scan_quads
    if quads is not None:
        kernels.grey_scan_convert(
            echo, cum, tgc, np.float32(dr), np.float32(255.0 / dr), *quads, grey, image.reshape(-1)
        )
    else:
        kernels.grey_levels(echo, cum, tgc, np.float32(dr), np.float32(255.0 / dr), grey)
        kernels.csr_to_uint8(*model._scan_csr_T, grey, image.reshape(-1))
    return image


def warm_up(model: EmulatorModel, seed: int | None = None) -> None:
    """Compile or load the emulator's kernels for ``model``'s argument types (writable and
    read-only label images) and build its tables (and ``seed``'s speckle bank): call at
    construction, not inside a simulation step."""
    L, S = model.scan_lines, model.samples_per_line
    if model.speckle and seed is not None:
        bank = model._speckle_bank_T(int(seed))
    else:
        bank = np.ones((2 * S, 2 * L), np.float32)
    labels = np.zeros(model.geometry.image_shape, np.uint8).reshape(-1)
    frozen = labels.view()
    frozen.flags.writeable = False  # frames carry read-only images (frames.UsFrame)
    for flat in (labels, frozen):
        _emulate(flat, model, bank, 0, 0)
        _emulate(flat, model, None, 0, 0)
    scan_convert(np.zeros((L, S), np.float32), model)


def scan_convert(polar: np.ndarray, model: EmulatorModel) -> np.ndarray:
    """Polar grey image (L, S) -> Cartesian uint8 image (rows, cols), bilinear in the fan."""
    L, S = model.scan_lines, model.samples_per_line
    x = np.asarray(polar, dtype=np.float32)
    if x.size != L * S:
        raise ValueError(
            f"scan_convert: polar image has {x.size} samples, the model expects {L} x {S}"
        )
    x = np.ascontiguousarray(x.reshape(L, S).T).reshape(-1)  # (sample, line) order
    image = np.zeros(model.geometry.image_shape, np.uint8)
    quads = model._scan_quads
    if quads is not None:
        kernels.quads_to_uint8(*quads, x, image.reshape(-1))
    else:
        kernels.csr_to_uint8(*model._scan_csr_T, x, image.reshape(-1))
    return image
