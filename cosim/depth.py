"""The compact lossless depth image of episodes (CompressedImage format ``cosim-depth``,
docs/episode_format.md section 3.5): written by the sensors' encoders (:mod:`cosim.sensors.encoding`), read by
:mod:`cosim.io.decode`. Below both (layer 0, docs/architecture.md): the sensors must not import :mod:`cosim.io`."""

from __future__ import annotations

import struct

import numpy as np
import zstandard

from cosim.errors import CosimError, FormatError

#: CompressedImage ``format`` of :func:`encode_depth`.
DEPTH_FORMAT = "cosim-depth"
#: [m] depth quantum: the grid the episode stores depth on (the 32FC1 depth's too).
DEPTH_QUANTUM_M = 2.0**-10
_DEPTH_MAGIC = b"CDP1"
_DEPTH_HEAD = struct.Struct("<4sII")  # magic, width, height
_DEPTH_ZSTD_LEVEL = 1


def encode_depth(depth_m: np.ndarray) -> bytes:
    """Lossless compact depth (``cosim-depth``) of a planar depth image (H, W) [m], inf or NaN = no hit.

    The depth is rounded to :data:`DEPTH_QUANTUM_M` (the grid of the stored 32FC1 depth) as int32
    counts, 0 where nothing was hit. Each count is predicted from its left, upper and upper-left
    neighbours (``left + up - upper_left``, exact on depth that changes linearly across the image),
    the residuals zigzag-coded (small magnitudes, small numbers), their four bytes gathered into
    four planes (high bytes are mostly zero), and the planes compressed with zstd. Bytes: the header
    ``b"CDP1"``, width and height (uint32 little-endian), then the zstd frame.
    """
    d = np.asarray(depth_m, np.float32)
    if d.ndim != 2:
        raise CosimError(f"encode_depth takes (H, W) float depth, got {d.dtype} {d.shape}")
    return pack_depth(depth_planes(d))


def depth_planes(d: np.ndarray) -> np.ndarray:
    """The byte planes (4, H, W) uint8 of :func:`encode_depth` for ``d`` (H, W) float32 (the numpy reference of
    ``cosim.sensors.kernels.depth_planes``, which the episode writer uses)."""
    c = np.rint(d * np.float32(1.0 / DEPTH_QUANTUM_M))
    c[~np.isfinite(c)] = 0
    c = c.astype(np.int64)
    r = c.copy()
    r[1:] -= c[:-1]
    r[:, 1:] -= c[:, :-1]
    r[1:, 1:] += c[:-1, :-1]
    z = ((r << 1) ^ (r >> 63)).astype("<u4")
    return np.ascontiguousarray(np.moveaxis(z.view(np.uint8).reshape(*d.shape, 4), 2, 0))


def pack_depth(planes: np.ndarray) -> bytes:
    """``cosim-depth`` bytes of the byte planes (4, H, W) uint8 of :func:`depth_planes`."""
    _, h, w = planes.shape
    return _DEPTH_HEAD.pack(_DEPTH_MAGIC, w, h) + zstandard.ZstdCompressor(level=_DEPTH_ZSTD_LEVEL).compress(planes)


def decode_depth(data: bytes) -> np.ndarray:
    """(H, W) float32 metres, NaN where nothing was hit, of :func:`encode_depth`'s bytes (FormatError if bad)."""
    if len(data) < _DEPTH_HEAD.size or bytes(data[:4]) != _DEPTH_MAGIC:
        raise FormatError(f"not a {DEPTH_FORMAT} image ({len(data)} bytes, starts {bytes(data[:4])!r})")
    _, w, h = _DEPTH_HEAD.unpack_from(data)
    try:
        planes = zstandard.ZstdDecompressor().decompress(bytes(data[_DEPTH_HEAD.size:]), max_output_size=4 * w * h)
    except zstandard.ZstdError as exc:
        raise FormatError(f"{DEPTH_FORMAT} {w}x{h}: {exc}") from None
    if len(planes) != 4 * w * h:
        raise FormatError(f"{DEPTH_FORMAT} {w}x{h}: {len(planes)} bytes of residuals, expected {4 * w * h}")
    z = np.frombuffer(planes, np.uint8).reshape(4, -1).T.copy().view("<u4").reshape(h, w).astype(np.int64)
    r = (z >> 1) ^ -(z & 1)
    # undo the predictor: c[i, j] = r[i, j] + c[i - 1, j] + c[i, j - 1] - c[i - 1, j - 1] is a 2D prefix sum
    c = np.cumsum(np.cumsum(r, axis=0), axis=1)
    out = (c * DEPTH_QUANTUM_M).astype(np.float32)
    out[c == 0] = np.nan
    return out
