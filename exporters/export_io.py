"""File writers of the dataset exports: binary PCD, PNG, NPZ, pickle, YAML and JSON, each byte-deterministic.

What the loaders need from each (docs/exports.md): PCD files that ``open3d.io.read_point_cloud``
reads with the intensity in the red colour channel (``opencood/utils/pcd_utils.py: pcd_to_np``);
PNG through Pillow; pickles of plain Python types at protocol 4 (the devkits document Python 3.7);
YAML that ``yaml.safe_load`` reads (plain floats, no numpy tags).
"""

from __future__ import annotations

import io
import json
import pickle
import struct
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import yaml

PICKLE_PROTOCOL = 4
#: libdeflate level of the PNGs the export encodes from camera images: its fastest on them, as the episode writer's.
PNG_LEVEL = 1
#: ... and of CARLA RGB24 depth and the BEV maps: level 2 is as fast there (twice as fast on the maps' long runs of
#: one value) and about 5 % smaller (docs/exports.md).
SPARSE_PNG_LEVEL = 2
_PCD_HEADER = (
    "# .PCD v0.7 - Point Cloud Data file format\n"
    "VERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F U\nCOUNT 1 1 1 1\n"
    "WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n"
)
#: One point of :func:`pcd_binary`: x, y, z float32 [m] and rgb 0x00RRGGBB, little-endian, packed (16 bytes).
PCD_POINT = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])


def pcd_binary(xyz: np.ndarray, intensity: np.ndarray) -> bytes:
    """A binary PCD of points (N, 3) [m] with ``intensity`` in [0, 1] as the red channel.

    Fields ``x y z rgb``: coordinates float32 (the episode's own precision), ``rgb`` an unsigned
    0x00RRGGBB with green and blue 0, so Open3D's reader gives the intensity as ``colors[:, 0]``,
    quantised to 1/255 (8-bit colour). 16 bytes a point against the 39 of the fixed-width ASCII
    form this replaced, and written with one copy (docs/exports.md says why binary).
    """
    xyz = np.asarray(xyz).reshape(-1, 3)
    if not np.isfinite(xyz).all():
        raise ValueError("PCD coordinates must be finite")
    out = np.empty(len(xyz), PCD_POINT)
    out["x"], out["y"], out["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    red = np.clip(np.rint(np.asarray(intensity, np.float64) * 255.0), 0, 255).astype(np.uint32)
    out["rgb"] = red << np.uint32(16)
    return _PCD_HEADER.format(n=len(xyz)).encode() + out.tobytes()


def png_bytes(array: np.ndarray, level: int = PNG_LEVEL) -> bytes:
    """PNG of a (H, W) bool (written as grey 0 / 255), (H, W) uint8 grey or (H, W, 3) uint8 RGB image, through
    the episode writer's encoder (``cosim.sensors.encoding.encode_png``: deterministic, releases the GIL)."""
    from cosim.sensors.encoding import encode_png

    a = np.asarray(array)
    if a.dtype == np.bool_:
        a = a.view(np.uint8) * np.uint8(255)
    if a.dtype != np.uint8 or a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] != 3):
        raise ValueError(f"no PNG for an array of {a.dtype} {a.shape}")
    return encode_png(np.ascontiguousarray(a), level)


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def depth_png(depth_m: np.ndarray) -> bytes:
    """The PNG of CARLA's RGB24 depth image of planar depth (H, W) [m] (NaN: no hit, the far plane): the same
    bytes as ``png_bytes(carla_frames.encode_depth_rgb24(depth_m), SPARSE_PNG_LEVEL)``, with the code, the byte
    split and the PNG row filter in one compiled pass instead of six numpy ones (about 1 ms of a 1280 x 720
    image's 8; the deflate, the rest, is the same)."""
    import imagecodecs
    from cosim.exporters import carla_frames as cf
    from cosim.exporters.kernels import depth_rgb24_up_rows

    d = np.ascontiguousarray(depth_m, np.float32)
    h, w = d.shape
    rows = np.empty((h, 3 * w + 1), np.uint8)
    depth_rgb24_up_rows(d, np.float32(cf.DEPTH_LEVELS / cf.DEPTH_FAR_M), np.float32(cf.DEPTH_LEVELS), rows)
    head = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    idat = imagecodecs.deflate_encode(rows, level=SPARSE_PNG_LEVEL)
    return b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", head) + _png_chunk(b"IDAT", idat) + _png_chunk(b"IEND", b"")


def is_rgb8_png(data: bytes) -> bool:
    """True for a PNG whose header says 8-bit RGB (colour type 2): what the loaders expect as is."""
    return data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR" and data[24] == 8 and data[25] == 2


def jpeg_components(data: bytes) -> int:
    """The number of colour components a JPEG's frame header declares (3: YCbCr, decoded as RGB; 1: grey), 0
    for bytes that are no JPEG or whose frame header is not found."""
    if data[:2] != b"\xff\xd8":
        return 0
    pos = 2
    while pos + 4 <= len(data) and data[pos] == 0xFF:
        marker = data[pos + 1]
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # a start of frame
            return data[pos + 9] if pos + 9 < len(data) else 0
        pos += 2 + int.from_bytes(data[pos + 2 : pos + 4], "big")
    return 0


def npy_bytes(a: np.ndarray) -> bytes:
    """``np.save`` of an array (no pickled objects)."""
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


def npz_bytes(arrays: dict[str, np.ndarray], level: int = 1) -> bytes:
    """What ``np.load`` reads as an ``.npz``: one deflated ``<name>.npy`` member per array, in the given order.

    Written here rather than by ``np.savez_compressed``, which stamps each member with the time of day (the
    same arrays must give the same bytes); deflate ``level`` 1: per-point labels shrink about 14-fold at a few
    milliseconds a cloud (higher levels save a further third at twice the time).
    """
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name, a in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.create_system = 3  # the same header bytes on every platform
            info.external_attr = 0o644 << 16
            zf.writestr(info, npy_bytes(np.ascontiguousarray(a)), compresslevel=level)
    return buf.getvalue()


def pickle_bytes(obj: Any) -> bytes:
    return pickle.dumps(obj, protocol=PICKLE_PROTOCOL)


def yaml_text(obj: Any) -> str:
    return yaml.safe_dump(obj, sort_keys=False, default_flow_style=None, width=120)


def json_text(obj: Any) -> str:
    return json.dumps(obj, indent=2, sort_keys=True) + "\n"


def write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path``, making its folder only when it is missing (not one mkdir per file)."""
    try:
        path.write_bytes(data)
    except FileNotFoundError:
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
