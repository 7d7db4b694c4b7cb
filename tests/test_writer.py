"""The episode writer and label messages: sim-time stamps, complete-or-absent files, determinism."""

from __future__ import annotations

import hashlib
import json
import math
import threading

import pytest
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from mcap.reader import make_reader

from cosim.assemble import TrackRegistry, build_snapshot
from cosim.errors import CosimError
from cosim.geometry import quat_from_rpy, rotation_matrix, rpy_from_quat, sumo_front_to_center
from cosim.io.labels import label_messages
from cosim.io.writer import BackgroundWriter, EpisodeWriter, temporary_path
from cosim.protocol import DroneState, VehicleState
from cosim.world.types import Junction, RsuSite, StaticLayout, World

TICK_NS = 200_000_000


def world() -> World:
    return World("urban", b"<net/>", b"<routes/>", (0, 0, 100, 100), (Junction("j0", (50.0, 50.0), "traffic_light"),),
                 (RsuSite("rsu_0", "j0", (45.0, 45.0, 8.0), 0.785, 8.0),), StaticLayout(()), (37.0, -122.0, 10.0))


def snapshot(tick: int, tracks: TrackRegistry):
    t = tick * 0.2
    cars = [
        VehicleState("bg.1", "truck", (5 + t, 3.0, 1.7), (8.0, 2.5, 3.4), 0.0, 0.0, 1.0, (1.0, 0, 0), 0.0, 0.0),
        VehicleState("vehicle_0", "car", (10 + 10 * t, 0.0, 0.75), (4.5, 1.9, 1.5), 0.0, 0.0, 10.0, (10.0, 0, 0),
                     0.0, 0.0, "vehicle_0"),
    ]
    drones = [DroneState("drone_0", (0.0, 0.0, 60.0), (0, 0, 0, 1), (0, 0, 0), (0, 0, 0), (0, 0, 9.8), (0, 0, 0, 1),
                         12.5 * tick, "hover", "hold")]
    return build_snapshot(tick, tick * TICK_NS, cars, drones, world(), tracks)


def write_episode(path, ticks=10, background=False):
    tracks = TrackRegistry()
    with EpisodeWriter(path) as w, BackgroundWriter(w) as bg:
        w.add_metadata("episode", {"scenario": "unit"})
        for k in range(ticks):
            snap = snapshot(k, tracks)
            if background:
                bg.submit(snap.t_ns, lambda snap=snap: label_messages(snap))
            else:
                for topic, msg in label_messages(snap):
                    w.write(topic, msg, snap.t_ns)
        bg.flush()
        w.add_attachment("scenario.yaml", "application/yaml", b"name: unit\n")
        w.finish()


def test_written_episode_reads_back_with_sim_time_and_one_message_per_tick(tmp_path):
    path = tmp_path / "ep.mcap"
    write_episode(path)
    with open(path, "rb") as f:
        reader = make_reader(f)
        per_topic: dict[str, list[int]] = {}
        objects = []
        for schema, channel, message in reader.iter_messages():
            per_topic.setdefault(channel.topic, []).append(message.log_time)
            assert message.publish_time == message.log_time
            if channel.topic == "/labels/objects":
                assert schema.name == "cosim.ObjectArray" and channel.message_encoding == "json"
                objects.append(json.loads(message.data))
            if channel.topic == "/tf":
                assert schema.name == "foxglove.FrameTransforms"
                decoded = FrameTransforms.FromString(message.data)
                frames = {t.child_frame_id for t in decoded.transforms}
                assert frames == {"vehicle_0/base_link", "rsu_0/base_link", "drone_0/base_link"}
                assert decoded.transforms[0].timestamp.ToNanoseconds() == message.log_time
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        attachments = {a.name: a.data for a in reader.iter_attachments()}
    expected = [k * TICK_NS for k in range(10)]
    assert per_topic == {"/tf": expected, "/labels/objects": expected, "/labels/boxes": expected}
    assert meta["episode"]["scenario"] == "unit"
    assert attachments["scenario.yaml"] == b"name: unit\n"
    first = objects[0]
    assert [o["agent_id"] for o in first["objects"]] == ["drone_0", None, "vehicle_0"]
    assert [a["agent_id"] for a in first["agents"]] == ["vehicle_0", "rsu_0", "drone_0"]
    # track ids are stable across ticks and unique
    ids = [[o["track_id"] for o in ob["objects"]] for ob in objects]
    assert all(i == ids[0] for i in ids) and len(set(ids[0])) == 3
    # the connected vehicle's base_link sits on the ground under its box centre
    veh = next(a for a in first["agents"] if a["agent_id"] == "vehicle_0")
    assert veh["position_m"] == pytest.approx([10.0, 0.0, 0.0])


def test_same_input_gives_identical_bytes(tmp_path):
    a, b = tmp_path / "a.mcap", tmp_path / "b.mcap"
    write_episode(a)
    write_episode(b)
    assert hashlib.sha256(a.read_bytes()).digest() == hashlib.sha256(b.read_bytes()).digest()


def test_a_crash_leaves_no_file_that_looks_complete(tmp_path):
    path = tmp_path / "ep.mcap"
    with pytest.raises(RuntimeError), EpisodeWriter(path) as w:
        snap = snapshot(0, TrackRegistry())
        for topic, msg in label_messages(snap):
            w.write(topic, msg, 0)
        assert temporary_path(path).exists() and not path.exists()
        raise RuntimeError("simulated crash")
    assert not path.exists()
    assert not temporary_path(path).exists()
    assert list(tmp_path.iterdir()) == []


def test_background_writer_gives_the_bytes_of_inline_writing(tmp_path):
    a, b = tmp_path / "inline.mcap", tmp_path / "background.mcap"
    write_episode(a)
    write_episode(b, background=True)
    assert a.read_bytes() == b.read_bytes()


def test_background_writer_keeps_one_tick_in_flight(tmp_path):
    release = threading.Event()
    written: list[int] = []

    def build(k):
        if k == 0:
            assert release.wait(30)
        written.append(k)
        return [("/tf", FrameTransforms())]

    with EpisodeWriter(tmp_path / "ep.mcap") as w, BackgroundWriter(w) as bg:
        bg.submit(0, lambda: build(0))  # returns at once: tick 0 waits in the writer thread
        second = threading.Thread(target=bg.submit, args=(1, lambda: build(1)))
        second.start()
        second.join(0.5)
        assert second.is_alive() and written == []  # tick 1 waits until tick 0 is written
        release.set()
        second.join(30)
        bg.flush()
        assert written == [0, 1] and w.message_count == 2


def test_background_writer_errors_surface_and_leave_no_file(tmp_path):
    path = tmp_path / "ep.mcap"

    def failing():
        raise OSError(28, "No space left on device")

    with (
        pytest.raises(CosimError, match=r"writing .*ep\.mcap failed: .*No space left"),
        EpisodeWriter(path) as w,
        BackgroundWriter(w) as bg,
    ):
        bg.submit(0, lambda: label_messages(snapshot(0, TrackRegistry())))
        bg.submit(1, failing)
        bg.submit(2, lambda: [])  # raises the error of tick 1
    assert list(tmp_path.iterdir()) == []


def test_sumo_front_bumper_to_box_centre_and_enu_yaw():
    # heading east (SUMO angle 90): centre is half a length west of the front bumper
    cx, cy, yaw = sumo_front_to_center(100.0, 20.0, 90.0, 4.0)
    assert (cx, cy) == pytest.approx((98.0, 20.0)) and yaw == pytest.approx(0.0)
    # heading north (SUMO 0): yaw +90 deg; heading south-west (225): yaw -135 deg
    cx, cy, yaw = sumo_front_to_center(0.0, 0.0, 0.0, 4.0)
    assert (cx, cy) == pytest.approx((0.0, -2.0)) and yaw == pytest.approx(math.pi / 2)
    cx, cy, yaw = sumo_front_to_center(0.0, 0.0, 225.0, 2 * math.sqrt(2))
    assert (cx, cy) == pytest.approx((1.0, 1.0)) and yaw == pytest.approx(-3 * math.pi / 4)


@pytest.mark.parametrize("rpy", [(0.1, -0.2, 0.3), (0.0, 0.0, -3.0), (-0.5, 0.4, 2.0)])
def test_quaternion_round_trip_and_matrix(rpy):
    q = quat_from_rpy(*rpy)
    assert sum(c * c for c in q) == pytest.approx(1.0)
    assert rpy_from_quat(q) == pytest.approx(rpy)
    r = rotation_matrix(quat_from_rpy(0, 0, rpy[2]))
    assert r @ [1, 0, 0] == pytest.approx([math.cos(rpy[2]), math.sin(rpy[2]), 0])


# ------------------------------------------------------------------------- serialized sensor records


def _camera_frames(n_cams: int = 3, h: int = 9, w: int = 13):
    """A frame set of one vehicle with ``n_cams`` cameras of random images (depth with misses, far and
    negative-zero values; instance ids up to 2^31 - 1)."""
    import numpy as np
    from cosim.sensors.camera import CameraFrame
    from cosim.sensors.rig import Pose
    from cosim.sensors.suite import AgentFrames, SensorFrameSet

    rng = np.random.default_rng(7)
    cams = {}
    for k in range(n_cams):
        depth = rng.uniform(0.0, 300.0, (h, w)).astype(np.float32)
        depth[0, :3] = np.inf
        depth[1, 0] = 20000.0
        depth[1, 1] = -0.0
        inst = rng.integers(0, 2**31, (h, w)).astype(np.uint32)
        K = np.array([[10.0, 0, w / 2], [0, 10.0, h / 2], [0, 0, 1]])
        cams[f"cam{k}"] = CameraFrame("vehicle_0", f"cam{k}", w, h, K, np.hstack([K, np.zeros((3, 1))]),
                                      Pose(np.eye(3), np.zeros(3)), rng.integers(0, 256, (h, w, 3), np.uint8),
                                      depth, rng.integers(0, 30, (h, w), np.uint8), inst)
    af = AgentFrames("vehicle_0", "vehicle", None, cams, None, None, None, None)
    return SensorFrameSet(0, 400_000_000, {"vehicle_0": af})


def test_serialized_image_records_are_the_bytes_of_the_messages():
    """Images serialized around their pixels in place give exactly SerializeToString(deterministic=True)
    of the same message built the plain way, and parse back to the arrays."""
    import numpy as np
    from cosim.sensors.encoding import encode_png
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

    from cosim.depth import encode_depth
    from cosim.io.sensor_messages import _stamp, depth_image, frame_records
    from cosim.io.writer import Serialized

    frames = _camera_frames()
    recs = dict(frame_records(frames, frames.t_ns, depth_format="raw"))
    compact = dict(frame_records(_camera_frames(), frames.t_ns))
    for name, cam in frames.agents["vehicle_0"].cameras.items():
        fid, base = f"vehicle_0/{name}/optical", f"/vehicle_0/{name}"
        expect = {
            "depth": (depth_image(cam.depth), "32FC1"),
            "semantic": (cam.semantic, "mono8"),
            "instance": (cam.instance.astype("<i4"), "32SC1"),
        }
        for kind, (img, encoding) in expect.items():
            rec = recs[f"{base}/{kind}"]
            assert isinstance(rec, Serialized) and rec.message_type is RawImage
            msg = RawImage(frame_id=fid, width=cam.width, height=cam.height, encoding=encoding,
                           step=img.strides[0], data=img.tobytes())
            _stamp(msg, frames.t_ns)
            assert bytes(rec.data) == msg.SerializeToString(deterministic=True), kind
        png = CompressedImage(frame_id=fid, format="png", data=encode_png(cam.rgb))
        _stamp(png, frames.t_ns)
        assert bytes(recs[f"{base}/image"].data) == png.SerializeToString(deterministic=True)
        depth = CompressedImage(frame_id=fid, format="cosim-depth", data=encode_depth(cam.depth))
        _stamp(depth, frames.t_ns)
        assert bytes(compact[f"{base}/depth"].data) == depth.SerializeToString(deterministic=True)
        depth = recs[f"{base}/depth"].message()
        got = np.frombuffer(depth.data, "<f4").reshape(cam.height, cam.width)
        fin = np.isfinite(cam.depth)
        assert np.array_equal(np.isnan(got), ~fin)
        assert np.max(np.abs(got[fin] - cam.depth[fin])) <= 2.0**-11


def test_consumed_frames_are_emptied_and_give_the_same_records():
    """``consume`` frees each camera once its messages are made; the records are the same, in order."""
    from cosim.io.sensor_messages import frame_records

    def as_bytes(recs):
        return [(t, bytes(r.data) if hasattr(r, "data") and not hasattr(r, "SerializeToString")
                 else r.SerializeToString(deterministic=True)) for t, r in recs]

    plain = as_bytes(frame_records(_camera_frames(6), 0))
    frames = _camera_frames(6)
    cams = frames.agents["vehicle_0"].cameras
    seen = []
    consumed = []
    for topic, rec in frame_records(frames, 0, consume=True):
        consumed.append((topic, rec))
        if topic.endswith("/calibration"):
            seen.append(len(cams))
    assert as_bytes(consumed) == plain
    assert seen == [6, 5, 4, 3, 2, 1]  # the camera whose calibration is yielded is dropped right after it
    assert frames.agents == {}


def test_serialized_records_write_the_bytes_of_messages(tmp_path):
    """The writer gives the same file for a serialized record as for the message it holds."""
    from cosim.io.sensor_messages import frame_records

    frames = _camera_frames()
    recs = list(frame_records(frames, frames.t_ns))
    paths = []
    for name, parse in (("records", False), ("messages", True)):
        with EpisodeWriter(tmp_path / f"{name}.mcap") as w:
            for topic, rec in recs:
                w.write(topic, rec.message() if parse and hasattr(rec, "message") else rec, frames.t_ns)
            paths.append(w.finish())
    assert paths[0].read_bytes() == paths[1].read_bytes()


def test_chunks_are_zstd_level_1_with_zlib_crcs(tmp_path):
    """The writer hands mcap its chunk codec (cosim/io/writer.py): every chunk is exactly level-1 zstd of its
    records (fails if mcap stops compressing through its module's ``zstandard``), and its CRC is zlib's CRC-32
    of the records, so any MCAP reader checks it."""
    import zlib

    import zstandard
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    path = tmp_path / "chunks.mcap"
    with EpisodeWriter(path) as w:
        for k in range(40):  # several chunks: 40 messages of 300 kB of compressible, varied bytes
            payload = bytes((i * (k + 3) // 7) % 251 for i in range(300_000))
            w.write("/blob", ("cosim.Blob", {"type": "object"}, {"k": k, "data": payload.hex()[:600_000]}), k * TICK_NS)
        w.finish()
    with open(path, "rb") as f:
        chunks = [r for r in StreamReader(f, emit_chunks=True, validate_crcs=True).records if isinstance(r, Chunk)]
    assert len(chunks) >= 3
    for c in chunks:
        records = zstandard.ZstdDecompressor().decompress(c.data, max_output_size=c.uncompressed_size)
        assert len(records) == c.uncompressed_size
        assert c.data == zstandard.ZstdCompressor(level=1).compress(records)
        assert c.data != zstandard.ZstdCompressor(level=3).compress(records)
        assert c.uncompressed_crc == zlib.crc32(records)
