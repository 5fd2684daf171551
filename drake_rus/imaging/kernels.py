"""Compiled (numba) kernels of the per-frame imaging chain.

Each kernel does the same float32 operations in the same order on every value as the numpy
code it replaces, so the images are the same bit for bit (``tests/test_imaging_kernels.py``).
No fastmath (it would reorder and contract the sums), no threads. ``cache=True``: the machine
code is kept in ``__pycache__`` and later processes load it (about 10x faster than compiling).
The imaging systems compile or load them at construction (``emulator.warm_up``,
``slicing.warm_up``: the real calls on blank inputs, so with the chain's own argument types,
read-only arrays included), never inside a simulation step.

``log10`` stays in numpy: numpy's float32 ``log10`` is its own SIMD implementation (it
differs from libm's in the last bit on about half of all inputs), so the emulator runs
:func:`echo_and_loss`, ``np.log10`` in place, then :func:`grey_scan_convert`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

_INT32_LIMIT = np.float32(2147483648.0)


@njit(cache=True, nogil=True)
def echo_and_loss(
    label_flat,
    polar_index,
    codes_lut,
    gel_code,
    probe_code,
    n_gel,
    loss_lut,
    diffuse_lut,
    spec_lut,
    speckle,
    sp_s,
    sp_l,
    use_speckle,
    echo_floor,
    echo,
    cum_loss,
):
    """Per sample, in (sample, line) order (S, L): the echo intensity ``max(diffuse *
    speckle + specular, floor)`` and the running two-way loss (dB) along its line, float32.

    ``label_flat``: the label image (uint8, flat); ``polar_index`` (S, L): the image pixel
    of every sample; ``codes_lut`` (256,): compact code 0-15 by label; samples before any
    tissue within ``n_gel`` samples of the face read as gel (``gel_code``); the face before
    sample 0 has ``probe_code``. Pair tables (256,) are indexed by ``code(prev) << 4 | code``.
    ``speckle`` (2S, 2L): the speckle bank, the frame's window at (``sp_s``, ``sp_l``).
    The loss adds row s to row s - 1 (float32): the additions of ``np.cumsum`` along each
    line, all lines at once (no chain of dependent additions through one line).
    """
    n_samples, n_lines = polar_index.shape
    prev = np.empty(n_lines, np.int64)
    air = np.empty(n_lines, np.bool_)
    for ln in range(n_lines):
        prev[ln] = probe_code
        air[ln] = True
    for s in range(n_samples):
        gel_zone = s < n_gel
        for ln in range(n_lines):
            label = label_flat[polar_index[s, ln]]
            code = np.int64(codes_lut[label])
            if gel_zone:
                a = air[ln] and label == 0
                air[ln] = a
                if a:
                    code = np.int64(gel_code)
            pair = (prev[ln] << 4) | code
            prev[ln] = code
            loss = loss_lut[pair]
            if s == 0:
                cum_loss[s, ln] = loss
            else:
                cum_loss[s, ln] = cum_loss[s - 1, ln] + loss
            e = diffuse_lut[pair]
            if use_speckle:
                e = e * speckle[sp_s + s, sp_l + ln]
            e = e + spec_lut[pair]
            if e < echo_floor:  # np.maximum: NaN stays NaN
                e = echo_floor
            echo[s, ln] = e


@njit(cache=True, nogil=True)
def db_level(log_echo, cum_loss, tgc, db):
    """Echo level (dB) ``log10(echo) * 10 - loss + tgc[s]`` per sample (S, L) (float32)."""
    n_samples, n_lines = log_echo.shape
    ten = np.float32(10.0)
    for s in range(n_samples):
        t = tgc[s]
        for ln in range(n_lines):
            db[s, ln] = (log_echo[s, ln] * ten - cum_loss[s, ln]) + t


@njit(cache=True, nogil=True, inline="always")
def _to_uint8(v):
    """numpy's float32 -> uint8 cast on x86: truncation to int32, its low byte (out of int32
    range or NaN: INT32_MIN, low byte 0)."""
    if v > np.float32(-2147483648.0) and v < _INT32_LIMIT:
        return np.uint8(np.int32(v) & 0xFF)
    return np.uint8(0)


@njit(cache=True, nogil=True)
def csr_to_uint8(indptr, indices, data, x, out):
    """``uint8(A @ x + 0.5)`` of a CSR matrix ``A`` (float32) and a float32 vector, each
    row summed as scipy's ``csr_matvec`` does: from 0, in stored order, in float32."""
    for r in range(out.size):
        acc = np.float32(0.0)
        for k in range(indptr[r], indptr[r + 1]):
            acc = acc + data[k] * x[indices[k]]
        out[r] = _to_uint8(acc + np.float32(0.5))


@njit(cache=True, nogil=True)
def quads_to_uint8(rows, first, offsets, data, x, out):
    """:func:`csr_to_uint8` of a matrix whose non-empty rows ``rows`` hold 4 entries each,
    row q at indices ``first[q] + offsets`` with weights ``data[q]`` (n, 4), in stored
    order; ``out`` is left alone in the empty rows (0 there). A fixed-length sum: no branch
    per row on its length."""
    o1, o2, o3 = offsets[1], offsets[2], offsets[3]
    for q in range(rows.size):
        i = first[q]
        acc = np.float32(0.0)
        acc = acc + data[q, 0] * x[i]
        acc = acc + data[q, 1] * x[i + o1]
        acc = acc + data[q, 2] * x[i + o2]
        acc = acc + data[q, 3] * x[i + o3]
        out[rows[q]] = _to_uint8(acc + np.float32(0.5))


@njit(cache=True, nogil=True)
def grey_levels(log_echo, cum_loss, tgc, dynamic_range, scale, grey):
    """Grey level per sample (S, L): ``clip((log10(echo) * 10 - loss + tgc[s] +
    dynamic_range) * scale, 0, 255)`` into ``grey`` (S * L,), float32."""
    n_samples, n_lines = log_echo.shape
    ten = np.float32(10.0)
    lo = np.float32(0.0)
    hi = np.float32(255.0)
    for s in range(n_samples):
        t = tgc[s]
        row = s * n_lines
        for ln in range(n_lines):
            g = (((log_echo[s, ln] * ten - cum_loss[s, ln]) + t) + dynamic_range) * scale
            if g < lo:  # the clip ufunc: NaN stays NaN
                g = lo
            elif g > hi:
                g = hi
            grey[row + ln] = g


@njit(cache=True, nogil=True)
def grey_scan_convert(
    log_echo, cum_loss, tgc, dynamic_range, scale, rows, first, offsets, data, grey, out
):
    """:func:`grey_levels` then their scan conversion :func:`quads_to_uint8` into ``out``
    (rows * cols,), zeros outside the fan."""
    grey_levels(log_echo, cum_loss, tgc, dynamic_range, scale, grey)
    quads_to_uint8(rows, first, offsets, data, grey, out)


@njit(cache=True, nogil=True)
def slice_plane(px, z_rows, per_row, A, c, shape, flat, dest, out, index):
    """Nearest labels of one plane: fan pixel p (row-major) at voxel coordinate
    ``f[a] = px[p] A[a, 0] + (z_row A[a, 2] + c[a])`` (float32, ``c`` with the + 1.5 of
    ``slicing._lookup_padded``) truncated and clipped to the padded grid ``shape``;
    ``out[dest[p]]`` = that voxel of the padded volume ``flat``; ``index`` (fan pixels,)
    is scratch for the flat voxel indices (int32 when the volume allows: fewer bytes).

    The coordinates are clipped to [0, m - 1] before the truncation, a loop that vectorises
    (then the gather): the same index as numpy's truncate-then-clip for every f below 2^31
    (NaN gives 0 in both). Beyond, numpy's int32 cast overflows to index 0, this gives
    m - 1: both on the border of ``outside``, so the same label.
    """
    m0, m1, m2 = shape[0], shape[1], shape[2]
    s0 = np.int64(m1) * m2
    h0, h1, h2 = np.float32(m0 - 1), np.float32(m1 - 1), np.float32(m2 - 1)
    zero = np.float32(0.0)
    a0, a1, a2 = A[0, 0], A[1, 0], A[2, 0]
    p = 0
    for r in range(per_row.size):
        n = per_row[r]
        z = z_rows[r]
        t0 = z * A[0, 2] + c[0]
        t1 = z * A[1, 2] + c[1]
        t2 = z * A[2, 2] + c[2]
        for q in range(p, p + n):
            x = px[q]
            f0 = x * a0 + t0
            f1 = x * a1 + t1
            f2 = x * a2 + t2
            f0 = f0 if f0 > zero else zero  # NaN -> 0
            f1 = f1 if f1 > zero else zero
            f2 = f2 if f2 > zero else zero
            f0 = f0 if f0 < h0 else h0
            f1 = f1 if f1 < h1 else h1
            f2 = f2 if f2 < h2 else h2
            index[q] = np.int64(np.int32(f0)) * s0 + np.int64(np.int32(f1)) * m2 + np.int32(f2)
        p += n
    for q in range(p):
        out[dest[q]] = flat[index[q]]
