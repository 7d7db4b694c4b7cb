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
_DEPTH_MAGIC = b"CDP2"  # format 1.4; b"CDP1" (formats 1.2 and 1.3: four byte planes of the residuals) is still read
_DEPTH_MAGIC_V1 = b"CDP1"
_DEPTH_HEAD = struct.Struct("<4sII")  # magic, width, height
_DEPTH_ZSTD_LEVEL = 9  # 3.3 % fewer depth bytes than level 3 for about 3 ms more per 1280x720 image (docs 3.5)
#: Residual codes 0, 1 and 2 (r = 0, -1, 1) are the residual; code 3 says "look in the escapes".
_ESCAPE = 3


def encode_depth(depth_m: np.ndarray) -> bytes:
    """Lossless compact depth (``cosim-depth``) of a planar depth image (H, W) [m], inf or NaN = no hit.

    The depth is rounded to :data:`DEPTH_QUANTUM_M` (the grid of the stored 32FC1 depth) as int32
    counts, 0 where nothing was hit. Each count is predicted from its left, upper and upper-left
    neighbours (``left + up - upper_left``, exact on depth that changes linearly across the image) and
    the residuals zigzag-coded (small magnitudes, small numbers). Rendered depth leaves residuals of
    0, -1 and 1 (the rounding of smooth surfaces) at 98 % of the pixels: each pixel gets a 2-bit code,
    its zigzag value when below 3, else 3 and its value less 3 goes to the escapes (uint32, their four
    bytes gathered into four planes). Bytes: the header ``b"CDP2"``, width and height (uint32
    little-endian), then one zstd frame of the codes, four to a byte (pixel k in bits 2 (k mod 4) of
    byte k div 4, pixels row by row), followed by the escape planes.
    """
    d = np.asarray(depth_m, np.float32)
    if d.ndim != 2:
        raise CosimError(f"encode_depth takes (H, W) float depth, got {d.dtype} {d.shape}")
    return pack_depth(d.shape[1], d.shape[0], *depth_codes(depth_residuals(d)))


def depth_residuals(d: np.ndarray) -> np.ndarray:
    """The zigzag-coded residuals (H, W) uint32 of :func:`encode_depth` for ``d`` (H, W) float32."""
    c = np.rint(d * np.float32(1.0 / DEPTH_QUANTUM_M))
    c[~np.isfinite(c)] = 0
    c = c.astype(np.int64)
    r = c.copy()
    r[1:] -= c[:-1]
    r[:, 1:] -= c[:, :-1]
    r[1:, 1:] += c[:-1, :-1]
    return ((r << 1) ^ (r >> 63)).astype("<u4")


def depth_codes(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The packed 2-bit codes (ceil(N / 4),) uint8 and the escapes (M,) uint32 of the residuals ``z`` (the numpy
    reference of ``cosim.sensors.kernels.depth_codes``, which the episode writer uses)."""
    z = z.ravel()
    code = np.minimum(z, _ESCAPE).astype(np.uint8)
    code = np.concatenate([code, np.zeros(-len(code) % 4, np.uint8)]).reshape(-1, 4)
    packed = (code << np.array([0, 2, 4, 6], np.uint8)).sum(axis=1, dtype=np.uint8)
    return packed, (z[z >= _ESCAPE] - _ESCAPE).astype("<u4")


def pack_depth(width: int, height: int, codes: np.ndarray, escapes: np.ndarray) -> bytes:
    """``cosim-depth`` bytes of an image's packed codes and escapes (:func:`depth_codes`)."""
    planes = np.ascontiguousarray(np.asarray(escapes, "<u4").view(np.uint8).reshape(-1, 4).T)
    body = zstandard.ZstdCompressor(level=_DEPTH_ZSTD_LEVEL).compress(codes.tobytes() + planes.tobytes())
    return _DEPTH_HEAD.pack(_DEPTH_MAGIC, width, height) + body


def decode_depth(data: bytes) -> np.ndarray:
    """(H, W) float32 metres, NaN where nothing was hit, of :func:`encode_depth`'s bytes (FormatError if bad);
    also reads format 1.2 and 1.3's ``CDP1`` (the four byte planes of every residual)."""
    magic = bytes(data[:4])
    if len(data) < _DEPTH_HEAD.size or magic not in (_DEPTH_MAGIC, _DEPTH_MAGIC_V1):
        raise FormatError(f"not a {DEPTH_FORMAT} image ({len(data)} bytes, starts {magic!r})")
    _, w, h = _DEPTH_HEAD.unpack_from(data)
    n = w * h
    n_codes = (n + 3) // 4
    most = 4 * n if magic == _DEPTH_MAGIC_V1 else n_codes + 4 * n
    try:
        raw = zstandard.ZstdDecompressor().decompress(bytes(data[_DEPTH_HEAD.size:]), max_output_size=most)
    except zstandard.ZstdError as exc:
        raise FormatError(f"{DEPTH_FORMAT} {w}x{h}: {exc}") from None
    b = np.frombuffer(raw, np.uint8)
    if magic == _DEPTH_MAGIC_V1:
        if len(b) != 4 * n:
            raise FormatError(f"{DEPTH_FORMAT} {w}x{h}: {len(b)} bytes of residuals, expected {4 * n}")
        z = b.reshape(4, -1).T.copy().view("<u4").reshape(h, w).astype(np.int64)
        return depth_from_residuals((z >> 1) ^ -(z & 1))
    from cosim.pixel_kernels import count_escapes, depth_from_codes

    if len(b) < n_codes:
        raise FormatError(f"{DEPTH_FORMAT} {w}x{h}: {len(b)} bytes, fewer than the {n_codes} bytes of codes")
    m = count_escapes(b, n)
    if len(b) != n_codes + 4 * m:
        raise FormatError(f"{DEPTH_FORMAT} {w}x{h}: {len(b) - n_codes} bytes of escapes, expected {4 * m}")
    out = np.empty((h, w), np.float32)
    depth_from_codes(b, n_codes, m, DEPTH_QUANTUM_M, out)
    return out


def decode_codes_reference(data: bytes) -> np.ndarray:
    """:func:`decode_depth` of ``CDP2`` bytes in numpy (the reference the one-pass kernel
    :func:`cosim.pixel_kernels.depth_from_codes` must equal, bit for bit)."""
    _, w, h = _DEPTH_HEAD.unpack_from(data)
    n = w * h
    n_codes = (n + 3) // 4
    b = np.frombuffer(zstandard.ZstdDecompressor().decompress(bytes(data[_DEPTH_HEAD.size:]),
                                                              max_output_size=n_codes + 4 * n), np.uint8)
    code = ((b[:n_codes, None] >> np.array([0, 2, 4, 6], np.uint8)) & 3).reshape(-1)[:n]
    z = code.astype(np.int64)
    esc = code == _ESCAPE
    m = int(np.count_nonzero(esc))
    z[esc] = b[n_codes:].reshape(4, m).T.copy().view("<u4").reshape(-1).astype(np.int64) + _ESCAPE
    z = z.reshape(h, w)
    return depth_from_residuals((z >> 1) ^ -(z & 1))


def depth_from_residuals(r: np.ndarray) -> np.ndarray:
    """Depth (H, W) float32 [m], NaN for no hit, of the decoded residuals ``r`` (H, W) int64."""
    # undo the predictor: c[i, j] = r[i, j] + c[i - 1, j] + c[i, j - 1] - c[i - 1, j - 1] is a 2D prefix sum
    c = np.cumsum(np.cumsum(r, axis=0), axis=1)
    out = (c * DEPTH_QUANTUM_M).astype(np.float32)
    out[c == 0] = np.nan
    return out
