"""The readers' numba kernels (cosim.pixel_kernels) equal their numpy references exactly."""

from __future__ import annotations

import numpy as np
import pytest

from cosim.depth import decode_codes_reference, decode_depth, encode_depth
from cosim.io.format import STATIC_INSTANCE_MIN
from cosim.io.validate_boxes import instance_ids
from cosim.pixel_kernels import instance_extents


def _depth(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A planar ramp with steps, far jumps (escapes), sky (NaN and inf) and zero-count pixels."""
    yy, xx = np.mgrid[0:h, 0:w]
    d = (5.0 + 0.01 * xx + 0.03 * yy).astype(np.float32)
    far = rng.random((h, w)) < 0.05
    d[far] = rng.uniform(0.5, 900.0, size=int(far.sum()))
    d[:, w // 3] += 40.0
    d[rng.random((h, w)) < 0.1] = np.nan
    d[rng.random((h, w)) < 0.02] = np.inf
    d[0, :3] = 1e-4  # rounds to the count 0: no hit, as the format says
    return d


@pytest.mark.parametrize("shape", [(1, 1), (3, 5), (37, 61), (120, 213)])
def test_depth_kernel_equals_the_numpy_reference(shape):
    rng = np.random.default_rng(sum(shape))
    d = _depth(rng, *shape)
    data = encode_depth(d)
    fast, ref = decode_depth(data), decode_codes_reference(data)
    assert fast.dtype == ref.dtype == np.float32 and fast.shape == shape
    assert np.array_equal(np.isnan(fast), np.isnan(ref))
    assert np.array_equal(fast[~np.isnan(fast)], ref[~np.isnan(ref)])
    q = np.rint(d / 2.0**-10) * 2.0**-10  # and both are the stored grid of the input
    hit = np.isfinite(d) & (q != 0)
    assert np.array_equal(np.isnan(fast), ~hit)
    assert np.allclose(fast[hit], q[hit], rtol=0, atol=0)


def _extents_reference(img: np.ndarray, lo: int, hi: int):
    flat = img.astype(np.int64).ravel()
    sel = np.nonzero((flat > lo) & (flat < hi))[0]
    ids, inv = np.unique(flat[sel], return_inverse=True)
    rows, cols = np.divmod(sel, img.shape[1])
    out = [ids]
    for values, fn, add in ((cols, np.minimum, 0), (cols, np.maximum, 1), (rows, np.minimum, 0), (rows, np.maximum, 1)):
        acc = np.full(len(ids), np.iinfo(np.int64).max if fn is np.minimum else -1, np.int64)
        fn.at(acc, inv, values)
        out.append(acc + add)
    return out


@pytest.mark.parametrize("n_ids", [0, 1, 7, 3000])
def test_instance_extents_equal_the_numpy_reference(n_ids):
    """Random blobs of ``n_ids`` objects (3000 fills the first hash table four times over: it must grow), static
    ids and the background left out."""
    rng = np.random.default_rng(n_ids)
    h, w = 180, 320
    img = np.zeros((h, w), np.uint32)
    img[rng.random((h, w)) < 0.2] = STATIC_INSTANCE_MIN + 5
    for tid in rng.choice(np.arange(1, 999_999), size=n_ids, replace=False):
        r, c = rng.integers(0, h), rng.integers(0, w)
        img[r:r + rng.integers(1, 20), c:c + rng.integers(1, 30)] = tid
    got = instance_extents(img, 0, STATIC_INSTANCE_MIN)
    ref = _extents_reference(img, 0, STATIC_INSTANCE_MIN)
    assert len(got[0]) == len(ref[0]) and len(got[0]) <= n_ids
    assert n_ids == 0 or len(got[0]) > 0
    for a, b in zip(got, ref, strict=True):
        assert np.array_equal(a, b)
    three = instance_ids(np.stack([img, img * 0, img * 0], axis=-1))  # (H, W, C): the first channel
    for a, b in zip(three, ref, strict=True):
        assert np.array_equal(a, b)
