"""Sensor frames -> (topic, message) pairs for the episode writer (docs/episode_format.md sections 3.4-3.10).

Foxglove protobuf messages wherever a schema exists; the IMU and visibility topics, which have
none, come as ``(topic, (schema_name, json_schema, payload_dict))``. Every timestamp inside a
message is the simulation time ``t_ns``. PNG/JPEG encoding runs in a thread pool (zlib and
libjpeg release the GIL), so it overlaps with the rest of the tick's work.

:func:`frame_records` is what the episode writer takes: made lazily, camera after camera, the
images as :class:`~cosim.io.writer.Serialized` records written around their pixels in
place; :func:`frame_messages` gives the same as protobuf messages (for code that reads them).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from concurrent.futures import Future

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.Grid_pb2 import Grid
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

from cosim.depth import DEPTH_FORMAT
from cosim.errors import CosimError
from cosim.io.points import encode_points
from cosim.io.writer import Serialized
from cosim.sensors.encoding import PackedLabels, encode_depth, encode_jpeg, encode_png, submit, submit_encode
from cosim.sensors.kinds import SENSOR_KINDS
from cosim.sensors.suite import SensorFrameSet

__all__ = ["depth_image", "encode_jpeg", "encode_png", "frame_messages", "frame_records", "lidar_message",
           "quantize_depth", "raw_image_record"]

_F = PackedElementField.NumericType

#: numpy type -> foxglove numeric type of a packed field.
_NUMERIC = {"|u1": _F.UINT8, "|i1": _F.INT8, "<u2": _F.UINT16, "<i2": _F.INT16, "<u4": _F.UINT32,
            "<i4": _F.INT32, "<f4": _F.FLOAT32, "<f8": _F.FLOAT64}

IMU_SCHEMA = {
    "title": "cosim.Imu",
    "type": "object",
    "properties": {
        "timestamp_ns": {"type": "integer", "description": "simulation time [ns]"},
        "frame_id": {"type": "string"},
        "linear_acceleration_mps2": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3,
                                     "description": "specific force, body FLU [m/s^2]"},
        "angular_velocity_radps": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3,
                                   "description": "body rates, FLU [rad/s]"},
        "orientation": {"type": "array", "items": {"type": "number"}, "minItems": 4, "maxItems": 4,
                        "description": "map <- body quaternion (x, y, z, w)"},
    },
    "required": ["timestamp_ns", "frame_id", "linear_acceleration_mps2", "angular_velocity_radps"],
}

VISIBILITY_SCHEMA = {
    "title": "cosim.Visibility",
    "type": "object",
    "properties": {
        "timestamp_ns": {"type": "integer"},
        "agent_id": {"type": "string"},
        "objects": {
            "type": "array",
            "items": {
                "type": "object",
                "properties": {
                    "track_id": {"type": "integer"},
                    "lidar_points": {"type": "integer", "description": "LiDAR returns on the object"},
                    "pixels": {"type": "object", "additionalProperties": {"type": "integer"},
                               "description": "camera name -> instance pixels"},
                },
                "required": ["track_id", "lidar_points", "pixels"],
            },
        },
    },
    "required": ["timestamp_ns", "agent_id", "objects"],
}

# ----------------------------------------------------------------------------------- messages


def _stamp(msg, t_ns: int) -> None:
    msg.timestamp.FromNanoseconds(int(t_ns))


def lidar_message(agent_id: str, frame, t_ns: int, positions: str = "float32") -> PointCloud:
    """One sweep in the compact record of :mod:`cosim.io.points` (``positions``: ``quantized`` or ``float32``)."""
    extra = {}
    if getattr(frame, "t_offset_ns", None) is not None:
        extra["t_offset_ns"] = np.asarray(frame.t_offset_ns, "<i4")
    if getattr(frame, "return_kind", None) is not None:
        extra["return"] = np.asarray(frame.return_kind, "u1")
    rec = encode_points(frame.points, frame.intensity, frame.ring, frame.class_id, frame.instance_id, extra,
                        kind=positions)
    msg = PointCloud(frame_id=f"{agent_id}/lidar", point_stride=rec.dtype.itemsize, data=rec.tobytes())
    _stamp(msg, t_ns)
    msg.pose.orientation.w = 1.0
    for name in rec.dtype.names:
        typ, off = rec.dtype.fields[name][:2]
        msg.fields.add(name=name, offset=off, type=_NUMERIC[typ.str])
    return msg


#: [m] depth is stored rounded to multiples of this (docs/episode_format.md 3.5): error <= 0.49 mm at any
#: range, and zstd compresses the zeroed low mantissa bits (3.4x smaller than unrounded float32).
DEPTH_QUANTUM_M = 2.0**-10


def quantize_depth(depth_m: np.ndarray, out: np.ndarray) -> np.ndarray:
    """Planar depth (H, W) [m] (inf on a miss) -> ``out`` (H, W) float32: metres on the
    :data:`DEPTH_QUANTUM_M` grid (exact below 16 km; float32 steps are coarser beyond), NaN where
    nothing was hit. In place, without temporaries of the image's size but one mask."""
    np.multiply(depth_m, np.float32(1.0 / DEPTH_QUANTUM_M), out=out, dtype=np.float32)  # powers of two: exact
    np.rint(out, out=out)
    np.multiply(out, np.float32(DEPTH_QUANTUM_M), out=out)
    np.copyto(out, np.float32(np.nan), where=~np.isfinite(out))
    return out


def depth_image(depth_m: np.ndarray) -> np.ndarray:
    """The stored ``32FC1`` image of a planar depth (H, W) float32 [m] (see :func:`quantize_depth`)."""
    return quantize_depth(depth_m, np.empty(np.shape(depth_m), "<f4"))


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        byte, n = n & 0x7F, n >> 7
        out.append(byte | (0x80 if n else 0))
        if not n:
            return bytes(out)


#: byte alignment of an image payload inside its serialized message (whole float32/int32 pixels for numpy)
_PAYLOAD_ALIGN = 64


def raw_image_record(frame_id: str, t_ns: int, shape: tuple[int, int], dtype: str, encoding: str,
                     fill: Callable[[np.ndarray], object]) -> Serialized:
    """A ``foxglove.RawImage`` serialized around its pixels, which ``fill(view)`` writes in place into a
    (H, W) view of ``dtype`` inside the message buffer (no image-sized copies besides that one).

    Protobuf writes fields in number order: timestamp (1), width, height, encoding, step (2-5), data
    (6), frame_id (7), so the bytes are those of the two partial messages around the data field
    (the same as ``RawImage(...).SerializeToString(deterministic=True)``; tested)."""
    h, w = shape
    step = w * np.dtype(dtype).itemsize
    n = step * h
    head = RawImage(width=w, height=h, encoding=encoding, step=step)
    _stamp(head, t_ns)
    pre = head.SerializeToString(deterministic=True) + (b"\x32" + _varint(n) if n else b"")
    post = RawImage(frame_id=frame_id).SerializeToString(deterministic=True)
    total = len(pre) + n + len(post)
    raw = np.empty(total + _PAYLOAD_ALIGN, np.uint8)
    start = -(raw.ctypes.data + len(pre)) % _PAYLOAD_ALIGN
    buf = raw[start:start + total]
    buf[:len(pre)] = np.frombuffer(pre, np.uint8)
    fill(buf[len(pre):len(pre) + n].view(dtype).reshape(h, w))
    buf[len(pre) + n:] = np.frombuffer(post, np.uint8)
    return Serialized(RawImage, buf)


def compressed_image_record(frame_id: str, t_ns: int, image_format: str, data: bytes) -> Serialized:
    """A ``foxglove.CompressedImage`` serialized around its encoded bytes (fields timestamp (1), data (2),
    format (3), frame_id (4), in that order; one copy of ``data``)."""
    head = CompressedImage()
    _stamp(head, t_ns)
    tag = b"\x12" + _varint(len(data)) if data else b""
    tail = CompressedImage(format=image_format, frame_id=frame_id)
    return Serialized(CompressedImage, b"".join((head.SerializeToString(deterministic=True), tag, data,
                                                 tail.SerializeToString(deterministic=True))))


def calibration_message(frame_id: str, cam, t_ns: int) -> CameraCalibration:
    msg = CameraCalibration(frame_id=frame_id, width=cam.width, height=cam.height, distortion_model="plumb_bob")
    _stamp(msg, t_ns)
    msg.D.extend(float(v) for v in getattr(cam, "D", (0.0,) * 5))
    msg.K.extend(float(v) for v in cam.K.ravel())
    msg.R.extend([1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0])
    msg.P.extend(float(v) for v in cam.P.ravel())
    return msg


def bev_message(agent_id: str, bev, t_ns: int) -> Grid:
    """The BEV grid in ``map``: the pose puts the grid's corner cell (0, 0) where it lies in the world."""
    _ny, nx, n_layers = bev.grid.shape
    hx, hy = bev.half_extent_m
    c, s = math.cos(bev.yaw_rad), math.sin(bev.yaw_rad)
    ox, oy, oz = bev.origin_m
    msg = Grid(frame_id="map", column_count=nx, row_stride=nx * n_layers, cell_stride=n_layers,
               data=np.ascontiguousarray(bev.grid).tobytes())
    _stamp(msg, t_ns)
    msg.pose.position.x = ox + c * -hx - s * -hy
    msg.pose.position.y = oy + s * -hx + c * -hy
    msg.pose.position.z = oz
    msg.pose.orientation.z = math.sin(bev.yaw_rad / 2)
    msg.pose.orientation.w = math.cos(bev.yaw_rad / 2)
    msg.cell_size.x = bev.cell_m
    msg.cell_size.y = bev.cell_m
    for k, name in enumerate(bev.layers):
        msg.fields.add(name=name, offset=k, type=_F.UINT8)
    return msg


def imu_payload(agent_id: str, imu, t_ns: int) -> dict:
    return {
        "timestamp_ns": int(t_ns), "frame_id": f"{agent_id}/imu",
        "linear_acceleration_mps2": list(imu.linear_acceleration_mps2),
        "angular_velocity_radps": list(imu.angular_velocity_radps), "orientation": list(imu.orientation),
    }


def visibility_payload(agent_id: str, vis, t_ns: int) -> dict:
    return {
        "timestamp_ns": int(t_ns), "agent_id": agent_id,
        "objects": [{"track_id": o.track_id, "lidar_points": o.lidar_points, "pixels": dict(o.pixels)}
                    for o in vis.objects],
    }


def _label_records(fid: str, base: str, cam, t_ns: int, depth_format: str) -> list[tuple[str, Serialized]]:
    """Depth (``cosim-depth`` or 32FC1 m), semantic (mono8) and instance (32SC1) images of one camera (runs in
    the encoder pool)."""
    out = []
    if cam.depth is not None and depth_format == "compressed":
        out.append((f"{base}/depth", compressed_image_record(fid, t_ns, DEPTH_FORMAT, encode_depth(cam.depth))))
    elif cam.depth is not None:
        out.append((f"{base}/depth", raw_image_record(fid, t_ns, cam.depth.shape, "<f4", "32FC1",
                                                      lambda v: quantize_depth(cam.depth, v))))
    pre = cam.encoded
    semantic = cam.semantic if cam.semantic is not None else getattr(pre, "semantic", None)
    instance = cam.instance if cam.instance is not None else getattr(pre, "instance", None)
    if semantic is not None:
        out.append((f"{base}/semantic", raw_image_record(fid, t_ns, semantic.shape, "|u1", "mono8",
                                                         _filler(semantic))))
    if instance is not None:
        # stored as int32: the same bytes as uint32 for ids < 2^31
        out.append((f"{base}/instance", raw_image_record(fid, t_ns, instance.shape, "<u4", "32SC1",
                                                         _filler(instance))))
    return out


def _filler(img: np.ndarray | PackedLabels) -> Callable[[np.ndarray], object]:
    """Writes a label image, an array or one the suite packed (:class:`PackedLabels`), into a message view."""
    if isinstance(img, PackedLabels):
        return img.into
    return lambda v: np.copyto(v, img, casting="unsafe")


#: cameras whose depth/semantic/instance messages are built ahead (in the encoder pool) of the one being
#: written: enough to keep the pool busy, few enough that a frame's messages never pile up in memory.
LOOKAHEAD_CAMERAS = 3


def frame_records(frames: SensorFrameSet, t_ns: int, *, image_format: str = "png", jpeg_quality: int = 80,
                  lidar_positions: str = "float32", depth_format: str = "compressed",
                  consume: bool = False) -> Iterator[tuple[str, object]]:
    """Every sensor topic of one tick as ``(topic, record)``, agents in frame order, made as they are
    taken: a record is a protobuf message, a :class:`~cosim.io.writer.Serialized` one (the
    images) or a JSON ``(schema_name, json_schema, payload)`` triple, all of which
    :meth:`EpisodeWriter.write <cosim.io.writer.EpisodeWriter.write>` takes.

    Frames rendered by the suite already carry a started RGB encode (``CameraFrame.encoded``) in the
    scenario's format; other formats are started here. The label images of the next
    :data:`LOOKAHEAD_CAMERAS` cameras are built in the encoder pool (numpy and the copies release the
    GIL) while the current one is taken. ``consume``: drop each camera (and then each agent) from
    ``frames`` once its messages are made, so that a frame's arrays are freed while it is written
    rather than after (the frames are empty afterwards). ``lidar_positions``: how point positions are
    stored (``sensors.lidar_positions``, see :mod:`cosim.io.points`); ``depth_format``: ``compressed``
    (:mod:`cosim.depth`) or ``raw`` (32FC1), ``output.depth_format``.
    """
    order = [(af, name) for af in frames.agents.values() for name in af.cameras]
    started: dict[int, tuple[Future | None, Future]] = {}
    n_started = [0]

    def start(upto: int) -> None:
        for k in range(n_started[0], min(upto, len(order))):
            n_started[0] = k + 1
            af, name = order[k]
            cam = af.cameras[name]
            pre = cam.encoded
            rgb = depth = None
            if pre is not None and pre.rgb is not None and pre.image_format == image_format:
                rgb = pre.rgb
            elif cam.rgb is not None:
                rgb = submit_encode(cam.rgb, image_format, jpeg_quality)
            elif pre is not None and pre.rgb is not None:
                raise CosimError(f"{af.agent_id}/{name}: the suite encoded {pre.image_format}, not {image_format}, "
                                 "and released the pixels")
            if pre is not None and pre.depth is not None:
                if depth_format != "compressed":
                    raise CosimError(f"{af.agent_id}/{name}: the suite encoded the depth compact and released it")
                depth = pre.depth
            fid, base = f"{af.agent_id}/{name}/optical", f"/{af.agent_id}/{name}"
            started[k] = (rgb, depth, submit(_label_records, fid, base, cam, t_ns, depth_format))

    k = 0
    for agent_id, af in list(frames.agents.items()):
        a = agent_id
        start(k + LOOKAHEAD_CAMERAS)
        if af.lidar is not None:
            yield f"/{a}/lidar", lidar_message(a, af.lidar, t_ns, lidar_positions)
        for name in list(af.cameras):
            start(k + 1 + LOOKAHEAD_CAMERAS)
            cam = af.cameras[name]
            fid, base = f"{a}/{name}/optical", f"/{a}/{name}"
            rgb, depth, labels = started.pop(k)
            k += 1
            if rgb is not None:
                yield f"{base}/image", compressed_image_record(fid, t_ns, image_format, rgb.result())
            if depth is not None:  # encoded by the suite (in the same order as _label_records would)
                yield f"{base}/depth", compressed_image_record(fid, t_ns, DEPTH_FORMAT, depth.result())
            yield from labels.result()
            del rgb, depth, labels
            yield f"{base}/calibration", calibration_message(fid, cam, t_ns)
            if consume:
                del af.cameras[name]
            del cam
        for kind, frame in (af.sensors or {}).items():
            yield f"/{a}/{kind}", SENSOR_KINDS.get(kind).message(a, frame, t_ns)
        if af.imu is not None:
            yield f"/{a}/imu", ("cosim.Imu", IMU_SCHEMA, imu_payload(a, af.imu, t_ns))
        if af.bev is not None:
            yield f"/{a}/bev", bev_message(a, af.bev, t_ns)
        if af.visibility is not None:
            yield f"/{a}/visibility", ("cosim.Visibility", VISIBILITY_SCHEMA,
                                       visibility_payload(a, af.visibility, t_ns))
        if consume:
            del frames.agents[agent_id]


def frame_messages(frames: SensorFrameSet, t_ns: int, *, image_format: str = "png",
                   jpeg_quality: int = 80, lidar_positions: str = "float32",
                   depth_format: str = "compressed") -> list[tuple[str, object]]:
    """Every sensor topic of one tick as protobuf messages (or JSON triples), agents in frame order: the
    records of :func:`frame_records` with the serialized ones parsed back (for code that reads the
    messages in memory, such as closed-loop clients; the episode writer takes the records)."""
    return [(topic, rec.message() if isinstance(rec, Serialized) else rec)
            for topic, rec in frame_records(frames, t_ns, image_format=image_format, jpeg_quality=jpeg_quality,
                                            lidar_positions=lidar_positions, depth_format=depth_format)]
