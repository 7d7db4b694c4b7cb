"""numba kernels of the readers' per-pixel passes (layer 0, beside :mod:`cosim.depth`): decoding ``cosim-depth``
and the extents of instance ids in an image. Each has a numpy reference it must equal exactly (the tests compare
them: tests/test_pixel_kernels.py). Imported lazily, so that importing a reader does
not import numba; the kernels are cached on disk (``cache=True``)."""

from __future__ import annotations

import numba
import numpy as np

_ESCAPE = 3


@numba.njit(cache=True, nogil=True)
def count_escapes(codes: np.ndarray, n: int) -> int:
    """How many of the first ``n`` 2-bit codes packed four to a byte in ``codes`` are the escape code 3."""
    m = 0
    for k in range(n):
        if (codes[k >> 2] >> (2 * (k & 3))) & 3 == _ESCAPE:
            m += 1
    return m


@numba.njit(cache=True, nogil=True)
def depth_from_codes(b: np.ndarray, n_codes: int, n_escapes: int, quantum: float, out: np.ndarray) -> None:
    """Fill ``out`` (H, W) float32 [m] from a ``CDP2`` body ``b`` (uint8: ``n_codes`` bytes of 2-bit codes, then
    four byte planes of ``n_escapes`` escapes): the inverse of :func:`cosim.sensors.kernels.depth_codes` in one
    pass (zigzag decode, then count = residual + left + up - upper left), NaN where the count is 0."""
    h, w = out.shape
    up = np.zeros(w, np.int64)
    k = 0
    e = 0
    base = n_codes
    for i in range(h):
        left = np.int64(0)
        upleft = np.int64(0)
        for j in range(w):
            z = np.int64((b[k >> 2] >> (2 * (k & 3))) & 3)
            if z == _ESCAPE:
                z = (np.int64(b[base + e]) | (np.int64(b[base + n_escapes + e]) << 8)
                     | (np.int64(b[base + 2 * n_escapes + e]) << 16)
                     | (np.int64(b[base + 3 * n_escapes + e]) << 24)) + _ESCAPE
                e += 1
            r = (z >> 1) ^ -(z & 1)
            c = r + up[j] + left - upleft
            upleft = up[j]
            up[j] = c
            left = c
            out[i, j] = np.float32(np.float64(c) * quantum) if c != 0 else np.float32(np.nan)
            k += 1


@numba.njit(cache=True, nogil=True)
def _extents(img: np.ndarray, lo: int, hi: int, table_bits: int):
    """Sorted ids in ``(lo, hi)`` of the (H, W) image and their pixel extents (open-addressing hash table of
    ``2 ** table_bits`` slots; the flag is False when it fills up, the caller retries with a bigger one)."""
    h, w = img.shape
    size = 1 << table_bits
    mask = size - 1
    keys = np.full(size, -1, np.int64)
    c0 = np.empty(size, np.int64)
    c1 = np.empty(size, np.int64)
    r0 = np.empty(size, np.int64)
    r1 = np.empty(size, np.int64)
    used = 0
    prev = np.int64(-1)
    slot = 0
    for i in range(h):
        for j in range(w):
            v = np.int64(img[i, j])
            if v <= lo or v >= hi:
                continue
            if v != prev:  # runs of one id are the rule: look the slot up once per run
                slot = (v * 2654435761) & mask
                while keys[slot] != v and keys[slot] != -1:
                    slot = (slot + 1) & mask
                if keys[slot] == -1:
                    if 2 * (used + 1) > size:
                        return False, keys, c0, c1, r0, r1
                    keys[slot] = v
                    c0[slot] = j
                    c1[slot] = j
                    r0[slot] = i
                    r1[slot] = i
                    used += 1
                prev = v
            if j < c0[slot]:
                c0[slot] = j
            if j > c1[slot]:
                c1[slot] = j
            r1[slot] = i  # rows only grow
    idx = np.nonzero(keys != -1)[0]
    order = np.argsort(keys[idx])
    idx = idx[order]
    return True, keys[idx], c0[idx], c1[idx] + 1, r0[idx], r1[idx] + 1


def instance_extents(img: np.ndarray, lo: int, hi: int) -> tuple[np.ndarray, ...]:
    """The ids ``lo < id < hi`` of an instance image (H, W), sorted, and their pixel extents: first column,
    last column + 1, first row, last row + 1 (each (K,) int64)."""
    img = np.ascontiguousarray(img)
    bits = 10
    while True:
        ok, *found = _extents(img, lo, hi, bits)
        if ok:
            return tuple(found)
        bits += 2
