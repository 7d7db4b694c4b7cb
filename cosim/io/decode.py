"""Decode episode messages (docs/episode_format.md) into numpy arrays and small frozen dataclasses.

Every decoder is a pure function ``bytes -> value`` chosen by the channel's schema name; the
registry :data:`DECODERS` lists them. Protobuf schemas without a dedicated decoder come back as
protobuf messages (built from the schema stored in the file); JSON messages come back as dicts,
except ``cosim.ObjectArray`` which becomes :class:`Objects` and ``cosim.LinkArray``
(``/comm/links``) which becomes :class:`~cosim.comm.message.LinkSet`.

Frames and units are those of the format: positions in metres, rotations (x, y, z, w)
quaternions parent <- child, time in integer ns since the episode start.
"""

from __future__ import annotations

import io
import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import cache
from typing import Any

import numpy as np
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from google.protobuf.message import DecodeError
from google.protobuf.message import Message as ProtoMessage

from cosim.comm.message import decode_links
from cosim.depth import DEPTH_FORMAT, decode_depth
from cosim.errors import FormatError
from cosim.geometry import has_distortion, project_to_image
from cosim.io.points import float_view

# ----------------------------------------------------------------------------------- types


@dataclass(frozen=True)
class PointCloud:
    """``foxglove.PointCloud``: ``points`` is a structured array (N,) with the message's fields, ``x``,
    ``y``, ``z`` as float32 metres in ``frame_id`` and ``intensity`` as float32 in [0, 1] whatever the
    stored types (:func:`cosim.io.points.float_view`); ``ring``, ``class_id``, ``instance_id``... as
    stored. ``stored`` is the record array exactly as in the message.
    """

    t_ns: int
    frame_id: str
    points: np.ndarray
    pose_translation_m: np.ndarray  # (3,) float64, pose of the points in frame_id (normally zero)
    pose_rotation: np.ndarray  # (4,) float64 (x, y, z, w)
    stored: np.ndarray | None = field(default=None, repr=False, compare=False)

    @property
    def xyz(self) -> np.ndarray:
        """Point positions (N, 3) float64 [m] in ``frame_id``."""
        return np.stack([self.points["x"], self.points["y"], self.points["z"]], axis=1).astype(np.float64)

    @property
    def fields(self) -> tuple[str, ...]:
        return tuple(self.points.dtype.names or ())

    def __len__(self) -> int:
        return len(self.points)


@dataclass(frozen=True)
class Image:
    """A raw or compressed image decoded to ``array``: (H, W) for one channel, (H, W, C) otherwise.

    ``encoding`` is the RawImage encoding (``rgb8``, ``mono16``, ``16UC1``, ``32FC1``...) or the
    CompressedImage format (``png``, ``jpeg``, ``cosim-depth``); depth images are float32 metres
    (``cosim-depth`` since format 1.2 or ``32FC1``, NaN = no hit), uint16 millimetres (``16UC1``) in
    1.0 files: use ``depth_m``.
    """

    t_ns: int
    frame_id: str
    encoding: str
    array: np.ndarray

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(self.array.shape)

    @property
    def depth_m(self) -> np.ndarray:
        """This depth image as (H, W) float32 metres, NaN where nothing was hit, whatever its encoding.

        Every reader of depth should use this rather than the raw ``array``, so that the stored encoding
        (docs/episode_format.md) can change without touching consumers.
        """
        a = self.array[..., 0] if self.array.ndim == 3 else self.array
        if a.dtype.kind in "iu":
            m = a.astype(np.float32) / 1000.0
            m[(a == 0) | (a == np.iinfo(a.dtype).max)] = np.nan
            return m
        m = a if a.dtype == np.float32 else a.astype(np.float32)
        return np.where((m > 0) & (m < np.inf), m, np.float32(np.nan))  # one new array, not a copy and a masked write


@dataclass(frozen=True)
class Calibration:
    """``foxglove.CameraCalibration``: pinhole ``K`` (3, 3), ``P`` (3, 4), ``R`` (3, 3), ``D`` (n,)."""

    t_ns: int
    frame_id: str
    width: int
    height: int
    distortion_model: str
    K: np.ndarray
    P: np.ndarray
    R: np.ndarray
    D: np.ndarray

    @property
    def distorted(self) -> bool:
        """True when the lens bends rays (a non-zero ``D``): straight lines are curves in the image."""
        return has_distortion(self.D)

    def project(self, points_optical: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (N, 2) [u, v] of points (N, 3) in this camera's optical frame through ``K``
        and ``D``, and whether each lies in front of the camera (N,) (``cosim.geometry.project_to_image``;
        docs/episode_format.md 3.6)."""
        if self.distorted and self.distortion_model != "plumb_bob":
            raise FormatError(f"CameraCalibration in {self.frame_id!r}: distortion model {self.distortion_model!r} "
                              f"with D = {self.D.tolist()}; cosim projects plumb_bob only")
        return project_to_image(points_optical, self.K, self.D if self.distorted else None)


@dataclass(frozen=True)
class Transform:
    """One rigid transform ``parent <- child``: translation [m] (3,), rotation (x, y, z, w) (4,)."""

    parent: str
    child: str
    translation_m: np.ndarray
    rotation: np.ndarray
    t_ns: int = 0

    def matrix(self) -> np.ndarray:
        """4x4 homogeneous matrix parent <- child (float64)."""
        m = np.eye(4)
        m[:3, :3] = quat_to_matrix(self.rotation)
        m[:3, 3] = self.translation_m
        return m


@dataclass(frozen=True)
class TransformTree:
    """All transforms of one ``/tf`` message, indexed by child frame."""

    transforms: tuple[Transform, ...]
    by_child: dict[str, Transform] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "by_child", {t.child: t for t in self.transforms})

    @property
    def frames(self) -> set[str]:
        return {t.child for t in self.transforms} | {t.parent for t in self.transforms}

    def parent(self, frame: str) -> str | None:
        t = self.by_child.get(frame)
        return t.parent if t is not None else None

    def to_root(self, frame: str, root: str = "map") -> np.ndarray:
        """4x4 matrix root <- frame along the parents; FormatError if ``frame`` does not reach ``root``."""
        m = np.eye(4)
        seen: set[str] = set()
        f = frame
        while f != root:
            t = self.by_child.get(f)
            if t is None or f in seen:
                raise FormatError(f"frame {frame!r} does not reach {root!r} in /tf (stuck at {f!r})")
            seen.add(f)
            m = t.matrix() @ m
            f = t.parent
        return m

    def __len__(self) -> int:
        return len(self.transforms)


@dataclass(frozen=True)
class Objects:
    """``/labels/objects`` (schema ``cosim.ObjectArray``) as arrays over the N labelled actors.

    ``centers_m`` (N, 3), ``sizes_m`` (N, 3) = length, width, height, ``rotations`` (N, 4) map <- body,
    ``velocities_mps`` (N, 3), all float64 in ``map``; ``track_ids`` (N,) int64. ``agents`` is the raw
    list of connected agents' poses (dicts with ``agent_id``, ``kind``, ``position_m``, ``rotation``...).
    """

    t_ns: int
    tick: int
    track_ids: np.ndarray
    classes: tuple[str, ...]
    centers_m: np.ndarray
    sizes_m: np.ndarray
    rotations: np.ndarray
    velocities_mps: np.ndarray
    agent_ids: tuple[str | None, ...]
    agents: tuple[dict[str, Any], ...]
    traffic_lights: tuple[dict[str, Any], ...] = ()  # the raw signal heads (format 1.3)

    @property
    def yaws_rad(self) -> np.ndarray:
        """Yaw (N,) [rad] about +z from +x of each box."""
        q = self.rotations
        return np.arctan2(2 * (q[:, 3] * q[:, 2] + q[:, 0] * q[:, 1]), 1 - 2 * (q[:, 1] ** 2 + q[:, 2] ** 2))

    def __len__(self) -> int:
        return len(self.track_ids)

    def to_snapshot(self) -> Any:
        """The tick's :class:`~cosim.snapshot.WorldSnapshot` rebuilt from the labels.

        Actors and agent poses are exact; what labels do not carry (agents' angular rates, specific
        force, gimbal attitude) keeps the AgentState defaults.
        """
        from cosim.snapshot import Actor, AgentState, TrafficLight, WorldSnapshot

        def t3(v: Any) -> tuple[float, float, float]:
            return (float(v[0]), float(v[1]), float(v[2]))

        actors = tuple(
            Actor(int(tid), cls, t3(c), t3(s), tuple(float(x) for x in q), t3(v), aid)  # type: ignore[arg-type]
            for tid, cls, c, s, q, v, aid in zip(
                self.track_ids,
                self.classes,
                self.centers_m,
                self.sizes_m,
                self.rotations,
                self.velocities_mps,
                self.agent_ids,
                strict=True,
            )
        )
        agents = tuple(
            AgentState(
                a["agent_id"],
                a["kind"],
                t3(a["position_m"]),
                tuple(float(x) for x in a["rotation"]),
                t3(a.get("velocity_mps", (0.0, 0.0, 0.0))),
                track_id=a.get("track_id"),
                extra=dict(a.get("extra") or {}),
            )  # type: ignore[arg-type]
            for a in self.agents
        )
        lights = tuple(TrafficLight(t["light_id"], t3(t["center_m"]), float(t["yaw_rad"]), t["state"], t["signal"])
                       for t in self.traffic_lights)
        return WorldSnapshot(self.tick, self.t_ns, actors, agents, lights)


@dataclass(frozen=True)
class Boxes:
    """``foxglove.SceneUpdate`` cubes: ``ids`` (N,) str, ``centers_m`` (N, 3), ``sizes_m`` (N, 3),
    ``rotations`` (N, 4), ``frame_ids`` (N,), ``delete_all`` True when the update clears the scene first."""

    t_ns: int
    ids: tuple[str, ...]
    frame_ids: tuple[str, ...]
    centers_m: np.ndarray
    sizes_m: np.ndarray
    rotations: np.ndarray
    delete_all: bool


@dataclass(frozen=True)
class GnssFix:
    """``foxglove.LocationFix``: WGS84 degrees and metres; ``covariance_m2`` (3, 3) ENU."""

    t_ns: int
    frame_id: str
    latitude_deg: float
    longitude_deg: float
    altitude_m: float
    covariance_m2: np.ndarray


@dataclass(frozen=True)
class Grid:
    """``foxglove.Grid``: ``cells`` is a structured array (rows, columns) with the message's fields
    (a one-field grid is also available as ``array``). ``cell_size_m`` (2,), origin pose in ``frame_id``."""

    t_ns: int
    frame_id: str
    cells: np.ndarray
    cell_size_m: np.ndarray
    origin_m: np.ndarray
    origin_rotation: np.ndarray

    @property
    def array(self) -> np.ndarray:
        """The grid's first field (rows, columns)."""
        names = self.cells.dtype.names or ()
        return self.cells[names[0]] if names else self.cells


# --------------------------------------------------------------------------------- helpers


def quat_to_matrix(q: Sequence[float]) -> np.ndarray:
    """Rotation matrix (3, 3) of a unit quaternion (x, y, z, w)."""
    x, y, z, w = (float(c) for c in q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _ns(ts: Any) -> int:
    return int(ts.seconds) * 1_000_000_000 + int(ts.nanos)


def _vec(v: Any) -> np.ndarray:
    return np.array([v.x, v.y, v.z], dtype=np.float64)


def _quat(q: Any) -> np.ndarray:
    return np.array([q.x, q.y, q.z, q.w], dtype=np.float64)


#: foxglove.PackedElementField.NumericType -> numpy little-endian type.
NUMERIC_TYPES: dict[int, str] = {
    1: "<u1",
    2: "<i1",
    3: "<u2",
    4: "<i2",
    5: "<u4",
    6: "<i4",
    7: "<f4",
    8: "<f8",
}


def packed_dtype(fields: Any, stride: int, what: str) -> np.dtype:
    """numpy structured dtype of foxglove packed fields (name, offset, type), ``stride`` bytes each."""
    names, formats, offsets = [], [], []
    for f in fields:
        if f.type not in NUMERIC_TYPES:
            raise FormatError(f"{what}: field {f.name!r} has unknown numeric type {f.type}")
        names.append(f.name)
        formats.append(NUMERIC_TYPES[f.type])
        offsets.append(f.offset)
    try:
        return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": stride})
    except (ValueError, TypeError) as exc:
        raise FormatError(f"{what}: inconsistent fields/stride ({exc})") from None


# -------------------------------------------------------------------------------- protobuf


@cache
def foxglove_class(schema_name: str) -> type[ProtoMessage] | None:
    """The generated protobuf class of a ``foxglove.*`` schema name, or None."""
    if not schema_name.startswith("foxglove."):
        return None
    short = schema_name.split(".", 1)[1]
    try:
        module = __import__(f"foxglove_schemas_protobuf.{short}_pb2", fromlist=[short])
    except ImportError:
        return None
    return getattr(module, short, None)


_POOL = descriptor_pool.DescriptorPool()


def proto_class(schema_name: str, schema_data: bytes) -> type[ProtoMessage]:
    """Message class for a protobuf schema: the Foxglove one when known, else built from the file's
    FileDescriptorSet."""
    cls = foxglove_class(schema_name)
    if cls is not None:
        return cls
    return _class_from_descriptor_set(schema_name, schema_data)


@cache
def _class_from_descriptor_set(schema_name: str, schema_data: bytes) -> type[ProtoMessage]:
    fds = descriptor_pb2.FileDescriptorSet.FromString(schema_data)
    for fd in fds.file:
        try:
            _POOL.FindFileByName(fd.name)
        except KeyError:
            _POOL.Add(fd)
    try:
        return message_factory.GetMessageClass(_POOL.FindMessageTypeByName(schema_name))
    except KeyError:
        raise FormatError(f"schema {schema_name!r} is not defined by its FileDescriptorSet") from None


def parse_proto(schema_name: str, data: bytes, schema_data: bytes = b"") -> ProtoMessage:
    cls = proto_class(schema_name, schema_data)
    try:
        return cls.FromString(data)
    except DecodeError as exc:
        raise FormatError(f"cannot decode a {schema_name} message ({len(data)} bytes): {exc}") from None


# -------------------------------------------------------------------------------- decoders


def decode_point_cloud(msg: Any) -> PointCloud:
    what = f"PointCloud in {msg.frame_id!r}"
    dtype = packed_dtype(msg.fields, msg.point_stride, what)
    if msg.point_stride == 0 or len(msg.data) % msg.point_stride:
        raise FormatError(f"{what}: {len(msg.data)} data bytes is not a multiple of point_stride {msg.point_stride}")
    stored = np.frombuffer(msg.data, dtype=dtype)
    return PointCloud(
        _ns(msg.timestamp),
        msg.frame_id,
        float_view(stored),
        _vec(msg.pose.position),
        _quat(msg.pose.orientation) if msg.HasField("pose") else np.array([0.0, 0, 0, 1]),
        stored,
    )


#: RawImage encoding -> (numpy dtype, channels).
RAW_ENCODINGS: dict[str, tuple[str, int]] = {
    "rgb8": ("u1", 3),
    "bgr8": ("u1", 3),
    "rgba8": ("u1", 4),
    "bgra8": ("u1", 4),
    "mono8": ("u1", 1),
    "8UC1": ("u1", 1),
    "8UC3": ("u1", 3),
    "mono16": ("<u2", 1),
    "16UC1": ("<u2", 1),
    "16SC1": ("<i2", 1),
    "32SC1": ("<i4", 1),
    "32FC1": ("<f4", 1),
}


def decode_raw_image(msg: Any) -> Image:
    what = f"RawImage {msg.encoding!r} in {msg.frame_id!r}"
    if msg.encoding not in RAW_ENCODINGS:
        raise FormatError(f"{what}: unknown encoding; known: {', '.join(RAW_ENCODINGS)}")
    dt, ch = RAW_ENCODINGS[msg.encoding]
    itemsize = np.dtype(dt).itemsize
    row = msg.width * ch * itemsize
    if msg.step < row or len(msg.data) < msg.step * msg.height:
        raise FormatError(f"{what}: {msg.width}x{msg.height} step {msg.step} does not fit {len(msg.data)} bytes")
    rows = np.frombuffer(msg.data, dtype=np.uint8, count=msg.step * msg.height).reshape(msg.height, msg.step)
    arr = rows[:, :row].copy().view(dt).reshape((msg.height, msg.width, ch) if ch > 1 else (msg.height, msg.width))
    return Image(_ns(msg.timestamp), msg.frame_id, msg.encoding, arr)


def decode_compressed_image(msg: Any) -> Image:
    from PIL import Image as PilImage

    if msg.format == DEPTH_FORMAT:
        try:
            return Image(_ns(msg.timestamp), msg.frame_id, msg.format, decode_depth(msg.data))
        except FormatError as exc:
            raise FormatError(f"CompressedImage {msg.format!r} in {msg.frame_id!r}: {exc}") from None

    try:
        with PilImage.open(io.BytesIO(msg.data)) as im:
            im.load()
            if im.mode in ("I;16", "I;16B", "I;16L"):
                arr = np.asarray(im, dtype=np.uint16)
            elif im.mode == "I":
                arr = np.asarray(im).astype(np.int64)
                arr = arr.astype(np.uint16) if arr.min(initial=0) >= 0 and arr.max(initial=0) < 65536 else arr
            elif im.mode in ("P", "CMYK", "YCbCr"):
                arr = np.asarray(im.convert("RGB"))
            else:
                arr = np.asarray(im)
    except (OSError, ValueError, SyntaxError) as exc:
        raise FormatError(f"CompressedImage {msg.format!r} in {msg.frame_id!r}: cannot decode ({exc})") from None
    return Image(_ns(msg.timestamp), msg.frame_id, msg.format, arr)


def decode_calibration(msg: Any) -> Calibration:
    k = np.asarray(msg.K, dtype=np.float64)
    p = np.asarray(msg.P, dtype=np.float64)
    r = np.asarray(msg.R, dtype=np.float64)
    if k.size != 9 or p.size != 12:
        raise FormatError(f"CameraCalibration in {msg.frame_id!r}: K has {k.size} values (9), P {p.size} (12)")
    return Calibration(
        _ns(msg.timestamp),
        msg.frame_id,
        msg.width,
        msg.height,
        msg.distortion_model,
        k.reshape(3, 3),
        p.reshape(3, 4),
        r.reshape(3, 3) if r.size == 9 else np.eye(3),
        np.asarray(msg.D, dtype=np.float64),
    )


def decode_transforms(msg: Any) -> TransformTree:
    return TransformTree(
        tuple(
            Transform(t.parent_frame_id, t.child_frame_id, _vec(t.translation), _quat(t.rotation), _ns(t.timestamp))
            for t in msg.transforms
        )
    )


def decode_scene_update(msg: Any) -> Boxes:
    ids, frames, centers, sizes, rots = [], [], [], [], []
    for e in msg.entities:
        for c in e.cubes:
            ids.append(e.id)
            frames.append(e.frame_id)
            centers.append(_vec(c.pose.position))
            sizes.append(_vec(c.size))
            rots.append(_quat(c.pose.orientation))
    delete_all = any(d.type == d.ALL for d in msg.deletions)
    t_ns = _ns(msg.entities[0].timestamp) if msg.entities else (_ns(msg.deletions[0].timestamp) if msg.deletions else 0)
    return Boxes(
        t_ns,
        tuple(ids),
        tuple(frames),
        np.array(centers).reshape(-1, 3),
        np.array(sizes).reshape(-1, 3),
        np.array(rots).reshape(-1, 4),
        delete_all,
    )


def decode_location_fix(msg: Any) -> GnssFix:
    cov = np.asarray(msg.position_covariance, dtype=np.float64)
    return GnssFix(
        _ns(msg.timestamp),
        msg.frame_id,
        msg.latitude,
        msg.longitude,
        msg.altitude,
        cov.reshape(3, 3) if cov.size == 9 else np.zeros((3, 3)),
    )


def decode_grid(msg: Any) -> Grid:
    what = f"Grid in {msg.frame_id!r}"
    if msg.column_count == 0 or msg.row_stride == 0:
        raise FormatError(f"{what}: column_count {msg.column_count}, row_stride {msg.row_stride}")
    if msg.row_stride < msg.column_count * msg.cell_stride or len(msg.data) % msg.row_stride:
        raise FormatError(
            f"{what}: {len(msg.data)} bytes do not fit rows of {msg.row_stride} bytes "
            f"({msg.column_count} cells of {msg.cell_stride})"
        )
    dtype = packed_dtype(msg.fields, msg.cell_stride, what)
    rows = len(msg.data) // msg.row_stride
    raw = np.frombuffer(msg.data, dtype=np.uint8).reshape(rows, msg.row_stride)
    used = raw[:, : msg.column_count * msg.cell_stride].copy()
    cells = used.view(dtype).reshape(rows, msg.column_count)
    return Grid(
        _ns(msg.timestamp),
        msg.frame_id,
        cells,
        np.array([msg.cell_size.x, msg.cell_size.y]),
        _vec(msg.pose.position),
        _quat(msg.pose.orientation) if msg.HasField("pose") else np.array([0.0, 0, 0, 1]),
    )


def decode_objects(payload: dict[str, Any]) -> Objects:
    objs = payload.get("objects", [])
    n = len(objs)

    def arr(key: str, width: int) -> np.ndarray:
        return np.array([o[key] for o in objs], dtype=np.float64).reshape(n, width)

    try:
        return Objects(
            t_ns=int(payload["timestamp_ns"]),
            tick=int(payload["tick"]),
            track_ids=np.array([o["track_id"] for o in objs], dtype=np.int64),
            classes=tuple(o["class"] for o in objs),
            centers_m=arr("center_m", 3),
            sizes_m=arr("size_m", 3),
            rotations=arr("rotation", 4),
            velocities_mps=arr("velocity_mps", 3),
            agent_ids=tuple(o.get("agent_id") for o in objs),
            agents=tuple(payload.get("agents", [])),
            traffic_lights=tuple(payload.get("traffic_lights", [])),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise FormatError(
            f"cosim.ObjectArray at t={payload.get('timestamp_ns')} ns: bad or missing field {exc}"
        ) from None


#: Protobuf schema name -> decoder of the parsed message.
PROTO_DECODERS: dict[str, Callable[[Any], Any]] = {
    "foxglove.PointCloud": decode_point_cloud,
    "foxglove.RawImage": decode_raw_image,
    "foxglove.CompressedImage": decode_compressed_image,
    "foxglove.CameraCalibration": decode_calibration,
    "foxglove.FrameTransforms": decode_transforms,
    "foxglove.SceneUpdate": decode_scene_update,
    "foxglove.LocationFix": decode_location_fix,
    "foxglove.Grid": decode_grid,
}

#: JSON schema name -> decoder of the parsed payload.
JSON_DECODERS: dict[str, Callable[[Any], Any]] = {
    "cosim.ObjectArray": decode_objects,
    "cosim.LinkArray": decode_links,
}

DECODERS = {**PROTO_DECODERS, **JSON_DECODERS}


def parse_json(schema_name: str, data: bytes) -> Any:
    try:
        return json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FormatError(f"cannot decode a {schema_name or 'JSON'} message ({len(data)} bytes): {exc}") from None


def decode(schema_name: str, message_encoding: str, data: bytes, schema_data: bytes = b"") -> Any:
    """Decode one message's bytes by its schema and encoding (see the module docstring)."""
    if message_encoding == "protobuf":
        msg = parse_proto(schema_name, data, schema_data)
        dec = PROTO_DECODERS.get(schema_name)
        return dec(msg) if dec is not None else msg
    if message_encoding == "json":
        payload = parse_json(schema_name, data)
        dec = JSON_DECODERS.get(schema_name)
        return dec(payload) if dec is not None else payload
    raise FormatError(f"unknown message encoding {message_encoding!r} (schema {schema_name!r}); known: protobuf, json")
