"""File writers of the dataset exports: ASCII PCD, PNG, pickle and YAML, each byte-deterministic.

What the loaders need from each (docs/exports.md): PCD files that ``open3d.io.read_point_cloud``
reads with the intensity in the red colour channel (``opencood/utils/pcd_utils.py: pcd_to_np``);
PNG through Pillow; pickles of plain Python types at protocol 4 (the devkits document Python 3.7);
YAML that ``yaml.safe_load`` reads (plain floats, no numpy tags).
"""

from __future__ import annotations

import io
import json
import pickle
from pathlib import Path
from typing import Any

import numpy as np
import yaml

PICKLE_PROTOCOL = 4
_MAX_ABS_MM = 10**7 - 1  # [mm] the fixed-width PCD coordinates hold up to 9999.999 m
_PCD_HEADER = (
    "# .PCD v0.7 - Point Cloud Data file format\n"
    "VERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F U\nCOUNT 1 1 1 1\n"
    "WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA ascii\n"
)
#: Decimal text of ``r << 16`` for every 8-bit red value, left-aligned in 8 bytes (no leading zeros:
#: Open3D parses the unsigned field with strtoul base 0, which would read them as octal).
_RGB_TEXT = np.full((256, 8), ord(" "), np.uint8)
for _r in range(256):
    _s = str(_r << 16).encode()
    _RGB_TEXT[_r, : len(_s)] = np.frombuffer(_s, np.uint8)


def pcd_ascii(xyz: np.ndarray, intensity: np.ndarray) -> bytes:
    """An ASCII PCD of points (N, 3) [m] with ``intensity`` in [0, 1] as the red channel.

    Fields ``x y z rgb`` (``rgb`` an unsigned 0x00RRGGBB, green and blue 0); coordinates in
    millimetres as fixed-width text (``+0012.345``), so formatting is vectorised. Intensity is
    quantised to 1/255 (8-bit colour). Open3D reads it back as points and ``colors[:, 0]``.
    """
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    n = len(xyz)
    mm = np.rint(xyz * 1000.0).astype(np.int64)
    if n and np.abs(mm).max() > _MAX_ABS_MM:
        raise ValueError(f"PCD coordinates beyond {_MAX_ABS_MM / 1000} m: {np.abs(xyz).max():.1f} m")
    row = np.full((n, 39), ord(" "), np.uint8)
    for k in range(3):
        base = 10 * k
        row[:, base] = np.where(mm[:, k] < 0, ord("-"), ord("+"))
        d = np.abs(mm[:, k])
        for pos in (8, 7, 6, 4, 3, 2, 1):
            row[:, base + pos] = 48 + d % 10
            d //= 10
        row[:, base + 5] = ord(".")
    red = np.clip(np.rint(np.asarray(intensity, np.float64) * 255.0), 0, 255).astype(np.int64)
    row[:, 30:38] = _RGB_TEXT[red]
    row[:, 38] = ord("\n")
    return _PCD_HEADER.format(n=n).encode() + row.tobytes()


def png_bytes(array: np.ndarray) -> bytes:
    """PNG of a (H, W) bool (written as grey 0 / 255), (H, W) uint8 grey or (H, W, 3) uint8 RGB image, through
    the episode writer's encoder (``cosim.sensors.encoding.encode_png``: deterministic, releases the GIL)."""
    from cosim.sensors.encoding import encode_png

    a = np.asarray(array)
    if a.dtype == np.bool_:
        a = a.view(np.uint8) * np.uint8(255)
    if a.dtype != np.uint8 or a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] != 3):
        raise ValueError(f"no PNG for an array of {a.dtype} {a.shape}")
    return encode_png(np.ascontiguousarray(a))


def is_rgb8_png(data: bytes) -> bool:
    """True for a PNG whose header says 8-bit RGB (colour type 2): what the loaders expect as is."""
    return data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR" and data[24] == 8 and data[25] == 2


def npy_bytes(a: np.ndarray) -> bytes:
    """``np.save`` of an array (no pickled objects)."""
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


def pickle_bytes(obj: Any) -> bytes:
    return pickle.dumps(obj, protocol=PICKLE_PROTOCOL)


def yaml_text(obj: Any) -> str:
    return yaml.safe_dump(obj, sort_keys=False, default_flow_style=None, width=120)


def json_text(obj: Any) -> str:
    return json.dumps(obj, indent=2, sort_keys=True) + "\n"


def write_bytes(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)


def plain(value: Any) -> Any:
    """``value`` with numpy scalars and arrays turned into Python floats, ints and lists (recursively)."""
    if isinstance(value, dict):
        return {plain(k): plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return plain(value.tolist())
    if isinstance(value, np.bool_ | bool):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.floating | float):
        return float(value)
    return value
