"""numba kernels of the exports' per-pixel passes. Each equals a numpy reference exactly (tests/test_export_frames.py
compares them); imported lazily, so that importing an exporter does not import numba; cached on disk."""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def depth_rgb24_up_rows(depth_m: np.ndarray, codes_per_m: np.float32, levels: np.float32, out: np.ndarray) -> None:
    """Fill ``out`` (H, 1 + 3 W) uint8 with the PNG rows of the RGB24 depth image of ``depth_m`` (H, W) float32 [m]:
    :func:`cosim.exporters.carla_frames.encode_depth_rgb24` (code = rint(clip(depth x ``codes_per_m``, 0, ``levels``)),
    NaN the far plane ``levels``; R = low byte) with each row under the PNG "Up" filter (type 2; the first row
    unfiltered, type 0), as ``cosim.sensors.encoding.encode_png`` filters, in one pass."""
    h, w = depth_m.shape
    prev = np.zeros(3 * w, np.uint8)
    zero = np.float32(0.0)
    for i in range(h):
        out[i, 0] = 2 if i > 0 else 0
        for j in range(w):
            v = depth_m[i, j]
            if np.isnan(v):
                x = levels
            else:
                x = v * codes_per_m
                x = zero if x < zero else (levels if x > levels else x)
            c = np.uint32(np.rint(x))
            for k in range(3):
                byte = np.uint8((c >> np.uint32(8 * k)) & np.uint32(255))
                out[i, 1 + 3 * j + k] = np.uint8(byte - prev[3 * j + k])
                prev[3 * j + k] = byte
