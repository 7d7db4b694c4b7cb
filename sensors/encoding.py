"""Image encoders (PNG, JPEG, depth) and the thread pool they run in.

Every encoder here is deterministic (the same array gives the same bytes) and releases the GIL, so
encodes submitted to the pool run beside the ray casting. The suite starts each camera's encode as
soon as its pixels are final (``CameraFrame.encoded``); the message exporter only collects the results.

Measured on one core on 1280x720 cosim images (docs/episode_format.md section 7, README performance):

- PNG: rows through the PNG "Up" filter, then libdeflate level 1 (through ``imagecodecs``): about
  90 MP/s, 0.56 MB a frame; zlib level 1 gave 46 MP/s and 0.63 MB, Pillow (zlib 6) 6.6 MP/s and
  0.45 MB, fpng 220 MP/s but 0.74 MB.
- JPEG: libjpeg-turbo (``imagecodecs``), 4:2:0 chroma, about 440 MP/s; 77 kB a frame at quality 80,
  PSNR 40.4 dB on average against the lossless image; Huffman tables made for each image cost about 2 ms
  more a frame and store the same pixels in about 4 % fewer bytes (2.2 % on the default run).
- depth: :func:`encode_depth` (:func:`cosim.depth.encode_depth` compiled), counts of 1/1024 m, a gradient
  predictor, 2-bit codes of the small residuals with escapes, zstd: 27 % fewer bytes than format 1.3's byte
  planes (which were 2.7 times fewer than the raw float32 image under the episode's chunk compression),
  2.8 ms a frame.
"""

from __future__ import annotations

import os
import struct
import zlib
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import imagecodecs
import numpy as np

from cosim.errors import CosimError

IMAGE_FORMATS = ("jpeg", "png")


@dataclass(frozen=True)
class PackedLabels:
    """A label image (semantic uint8 or instance uint32, (H, W)) held zstd-compressed (level 1) until its
    message is made: rendered label images are large flat regions, so a 1280x720 instance image of 3.7 MB
    keeps some kB (2-6 kB on the synthetic world), for about 1 ms to pack and at most 2 ms to unpack
    (straight into the message buffer).
    Lossless: :meth:`into` gives back exactly the packed pixels, so the episode bytes do not change."""

    shape: tuple[int, int]
    dtype: str
    data: bytes

    @classmethod
    def of(cls, img: np.ndarray) -> PackedLabels:
        img = np.ascontiguousarray(img)
        return cls(img.shape, img.dtype.str, bytes(imagecodecs.zstd_encode(img, level=1)))

    def into(self, out: np.ndarray) -> None:
        """Write the pixels into ``out`` (H, W), cast to its dtype when that differs (as ``np.copyto`` unsafe)."""
        if out.dtype.str == self.dtype and out.flags.c_contiguous:
            imagecodecs.zstd_decode(self.data, out=out.reshape(-1).view(np.uint8))
        else:
            np.copyto(out, self.unpack(), casting="unsafe")

    def unpack(self) -> np.ndarray:
        return np.frombuffer(imagecodecs.zstd_decode(self.data), self.dtype).reshape(self.shape)


@dataclass(frozen=True)
class Encodes:
    """A camera's encodes started by the suite (``CameraFrame.encoded``): the RGB image in ``image_format``
    and, when the suite also let go of the depth array, the ``cosim-depth`` bytes of its depth; when it let
    go of the label images too, the packed ``semantic`` and ``instance`` images and ``instance_counts`` (the
    camera's pixels per track id, what :func:`~cosim.sensors.visibility.render_visibility` needs)."""

    image_format: str
    rgb: Future | None = None
    depth: Future | None = None
    semantic: PackedLabels | None = None
    instance: PackedLabels | None = None
    instance_counts: dict[int, int] | None = None

    def cancel(self) -> None:
        for f in (self.rgb, self.depth):
            if f is not None:
                f.cancel()

_POOL: ThreadPoolExecutor | None = None


def _pool() -> ThreadPoolExecutor:
    global _POOL
    if _POOL is None:
        _POOL = ThreadPoolExecutor(max_workers=max(2, min(8, os.cpu_count() or 2)), thread_name_prefix="cosim-enc")
    return _POOL


# ----------------------------------------------------------------------------------- encoders


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def encode_png(img: np.ndarray, level: int = 1) -> bytes:
    """Lossless PNG of ``img`` (H, W, 3) uint8 RGB or (H, W) uint8 grey.

    Rows use the PNG "Up" filter (difference to the row above), which suits rendered images, and
    libdeflate's zlib stream at ``level`` (1-12), which releases the GIL and gives the same bytes on
    every run (ISA-L's deflate, faster still, was seen to give different bytes for the same rows;
    episodes must be byte-identical for the same scenario and seed).
    """
    if img.dtype != np.uint8 or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (3, 4)):
        raise CosimError(f"encode_png takes uint8 (H, W), (H, W, 3) or (H, W, 4), got {img.dtype} {img.shape}")
    h, w = img.shape[:2]
    ch = 1 if img.ndim == 2 else img.shape[2]
    rows = img.reshape(h, w * ch)
    filt = np.empty((h, w * ch + 1), np.uint8)
    filt[:, 0] = 2
    filt[0, 0] = 0
    filt[0, 1:] = rows[0]
    np.subtract(rows[1:], rows[:-1], out=filt[1:, 1:])
    colour = {1: 0, 3: 2, 4: 6}[ch]
    head = struct.pack(">IIBBBBB", w, h, 8, colour, 0, 0, 0)
    idat = imagecodecs.deflate_encode(filt, level=level)
    return b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", head) + _png_chunk(b"IDAT", idat) + _png_chunk(b"IEND", b"")


def encode_jpeg(img: np.ndarray, quality: int = 80) -> bytes:
    """Baseline JPEG of ``img`` (H, W, 3) uint8 RGB through libjpeg-turbo, 4:2:0 chroma, at ``quality``, with
    Huffman tables made for the image (``optimize``: the same pixels decode, about 4 % fewer bytes)."""
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise CosimError(f"encode_jpeg takes uint8 (H, W, 3), got {img.dtype} {img.shape}")
    return bytes(imagecodecs.jpeg8_encode(np.ascontiguousarray(img), level=int(quality), subsampling="420",
                                          optimize=True))


def encode_depth(depth_m: np.ndarray) -> bytes:
    """:func:`cosim.depth.encode_depth` (the same bytes) through one compiled pass: about 6 times faster
    than its numpy formulation, which spends 17 ms on a 1280x720 image before zstd's 1 ms."""
    from cosim.depth import DEPTH_QUANTUM_M, pack_depth

    from . import kernels

    d = np.ascontiguousarray(depth_m, np.float32)
    if d.ndim != 2:
        raise CosimError(f"encode_depth takes (H, W) float depth, got {d.dtype} {d.shape}")
    codes = np.zeros((d.size + 3) // 4, np.uint8)
    escapes = np.empty(d.size, np.uint32)
    m = kernels.depth_codes(d, np.float32(1.0 / DEPTH_QUANTUM_M), codes, escapes)
    return pack_depth(d.shape[1], d.shape[0], codes, escapes[:m])


def encode_image(img: np.ndarray, image_format: str, jpeg_quality: int = 80) -> bytes:
    """``img`` (H, W, 3) uint8 RGB as ``image_format`` (:data:`IMAGE_FORMATS`)."""
    if image_format == "png":
        return encode_png(img)
    if image_format == "jpeg":
        return encode_jpeg(img, jpeg_quality)
    raise CosimError(f"unknown image format {image_format!r}; known: {', '.join(IMAGE_FORMATS)}")


def submit(fn, *args) -> Future:
    """Run ``fn(*args)`` in the encoder pool (for other GIL-releasing work such as label images)."""
    return _pool().submit(fn, *args)


def submit_encode(img: np.ndarray, image_format: str, jpeg_quality: int = 80) -> Future:
    """Start encoding ``img`` (H, W, 3) uint8 in the pool; the future gives the bytes."""
    if image_format not in IMAGE_FORMATS:
        raise CosimError(f"unknown image format {image_format!r}; known: {', '.join(IMAGE_FORMATS)}")
    return _pool().submit(encode_image, img, image_format, jpeg_quality)
