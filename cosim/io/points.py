"""LiDAR point records as stored in ``/<agent>/lidar`` (docs/episode_format.md section 3.4).

The writer stores points compactly; readers get one float view whatever was stored:

- ``x``, ``y``, ``z``: float32 metres rounded to 1/128 m (``sensors.lidar_positions: float32``, the
  default since format 1.2: what a reader that knows only the ``foxglove.PointCloud`` schema, such as
  the Foxglove app, draws at true scale); or, with ``quantized``, int16 counts of
  :data:`POSITION_QUANTUM_M` (1/256 m, about 3.9 mm) when every coordinate of the sweep fits
  (|v| < 128 m), int32 counts otherwise;
- ``intensity``: uint8 counts of 1/255 (0..1);
- ``ring`` uint8, ``class_id`` uint8, ``instance_id`` uint32, ``t_offset_ns`` int32 (firing time
  relative to the sweep's end, <= 0), ``return`` uint8 (0 single, 1 strongest, 2 last of a dual pair).

:func:`float_view` turns any stored record array into ``x``, ``y``, ``z`` float32 metres and
``intensity`` float32 in [0, 1], other fields unchanged, so consumers never see the storage types.
"""

from __future__ import annotations

import numpy as np

#: [m] one count of an integer ``x``, ``y`` or ``z`` field.
POSITION_QUANTUM_M = 1.0 / 256.0
#: [m] float32 positions are rounded to multiples of this: its error (2.3 mm RMS, 3.9 mm at most) adds
#: 1.3 % to the variance of the default 2 cm range noise, and the zeroed low mantissa bits compress (a
#: full-rig tick's LiDAR: 6.99 MB against 7.68 at 1/256 m under zstd).
FLOAT_QUANTUM_M = 1.0 / 128.0
#: Largest |coordinate| [m] an int16 position holds.
INT16_REACH_M = 32767 * POSITION_QUANTUM_M
#: Integer intensity counts 1/INTENSITY_COUNTS.
INTENSITY_COUNTS = 255
#: What ``sensors.lidar_positions`` may name (the first is the default).
POSITION_KINDS = ("float32", "quantized")

#: Fields after the position and before any optional field: (name, numpy type).
BASE_FIELDS: tuple[tuple[str, str], ...] = (("intensity", "u1"), ("ring", "u1"), ("class_id", "u1"),
                                            ("instance_id", "<u4"))


def position_type(xyz_m: np.ndarray, kind: str = "float32") -> str:
    """numpy type of the stored ``x``, ``y``, ``z`` of the points ``xyz_m`` (N, 3) [m]."""
    if kind == "float32":
        return "<f4"
    if kind != "quantized":
        raise ValueError(f"unknown LiDAR position kind {kind!r}; known: {', '.join(POSITION_KINDS)}")
    reach = float(np.abs(xyz_m).max()) if xyz_m.size else 0.0
    return "<i2" if reach < INT16_REACH_M - POSITION_QUANTUM_M else "<i4"


def record_dtype(pos_type: str, extra: tuple[tuple[str, str], ...] = ()) -> np.dtype:
    """Packed (unaligned) record: x, y, z of ``pos_type``, :data:`BASE_FIELDS`, then ``extra``."""
    fields = [("x", pos_type), ("y", pos_type), ("z", pos_type), *BASE_FIELDS, *extra]
    return np.dtype(fields)  # a list of (name, type) is packed: offsets follow without padding


def encode_points(xyz_m: np.ndarray, intensity: np.ndarray, ring: np.ndarray, class_id: np.ndarray,
                  instance_id: np.ndarray, extra: dict[str, np.ndarray] | None = None,
                  kind: str = "float32") -> np.ndarray:
    """Stored records (N,) of one sweep. ``xyz_m`` (N, 3) [m]; ``intensity`` (N,) in [0, 1];
    ``extra``: further fields by name, stored with their arrays' own dtypes, in the given order."""
    extra = extra or {}
    pos_t = position_type(xyz_m, kind)
    dt = record_dtype(pos_t, tuple((k, v.dtype.str) for k, v in extra.items()))
    rec = np.empty(len(xyz_m), dt)
    if pos_t == "<f4":  # rounded to FLOAT_QUANTUM_M: the zeroed low mantissa bits compress
        q = np.rint(np.asarray(xyz_m, np.float64) / FLOAT_QUANTUM_M) * FLOAT_QUANTUM_M
        for i, k in enumerate("xyz"):
            rec[k] = q[:, i]
    else:
        q = np.rint(np.asarray(xyz_m, np.float64) / POSITION_QUANTUM_M)
        for i, k in enumerate("xyz"):
            rec[k] = q[:, i]
    rec["intensity"] = np.rint(np.clip(intensity, 0.0, 1.0) * INTENSITY_COUNTS)
    rec["ring"] = ring
    rec["class_id"] = class_id
    rec["instance_id"] = instance_id
    for k, v in extra.items():
        rec[k] = v
    return rec


def float_view(stored: np.ndarray) -> np.ndarray:
    """Records with ``x``, ``y``, ``z`` as float32 metres and ``intensity`` float32 in [0, 1] (see the
    module docstring); other fields keep their stored types. Float fields are passed through."""
    names = stored.dtype.names or ()
    out_fields = []
    for n in names:
        t = stored.dtype.fields[n][0]
        if n in ("x", "y", "z", "intensity") and t.kind in "iu":
            out_fields.append((n, "<f4"))
        else:
            out_fields.append((n, t.str))
    if all(stored.dtype.fields[n][0].str == t for n, t in out_fields):
        return stored
    out = np.empty(len(stored), out_fields)
    for n, _ in out_fields:
        src = stored[n]
        if n in ("x", "y", "z") and src.dtype.kind in "iu":
            out[n] = src.astype(np.float32) * np.float32(POSITION_QUANTUM_M)
        elif n == "intensity" and src.dtype.kind in "iu":
            out[n] = src.astype(np.float32) / np.float32(np.iinfo(src.dtype).max)
        else:
            out[n] = src
    return out


#: Fields a stored sweep may have and the numpy types each may be stored as (format 1.0 files wrote
#: float32 positions and intensity and a uint16 ring). ``x`` .. ``instance_id`` are required.
FIELD_TYPES: dict[str, tuple[str, ...]] = {
    "x": ("<i2", "<i4", "<f4"), "y": ("<i2", "<i4", "<f4"), "z": ("<i2", "<i4", "<f4"),
    "intensity": ("|u1", "<f4"), "ring": ("|u1", "<u2"), "class_id": ("|u1",), "instance_id": ("<u4",),
    "t_offset_ns": ("<i4",), "return": ("|u1",),
}
REQUIRED_FIELDS = ("x", "y", "z", "intensity", "ring", "class_id", "instance_id")


def layout_problems(dtype: np.dtype) -> list[str]:
    """What is wrong with a stored record type against :data:`FIELD_TYPES` (empty when nothing)."""
    names = dtype.names or ()
    out = [f"missing field {n!r}" for n in REQUIRED_FIELDS if n not in names]
    for n in names:
        t = dtype.fields[n][0].str
        if n not in FIELD_TYPES:
            out.append(f"unknown field {n!r}")
        elif t not in FIELD_TYPES[n]:
            out.append(f"field {n!r} is {t}, expected one of {', '.join(FIELD_TYPES[n])}")
    if len({dtype.fields[n][0].str for n in ("x", "y", "z") if n in names}) > 1:
        out.append("x, y, z have different types")
    return out
