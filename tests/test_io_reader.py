"""The reader API: writer -> reader round trip for every topic, lazy decoding, topic filters, versions."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import yaml
from google.protobuf.message import Message as ProtoMessage

import cosim.io.reader as reader_module
from cosim.errors import FormatError, InputError
from cosim.io import Calibration, GnssFix, Grid, Image, Objects, PointCloud, TransformTree, open_episode
from cosim.io.format import topic_spec
from cosim.io.synthetic import TICK_NS, write_synthetic_episode
from tests.helpers import cli_in_process as cli


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A synthetic full-rig episode and every (tick, topic) -> message the writer was given."""
    written: dict[tuple[int, str], object] = {}

    def keep(tick, topic, msg):
        written[(tick, topic)] = msg
        return msg

    path = write_synthetic_episode(tmp_path_factory.mktemp("io") / "ep.mcap", ticks=6, edit=keep)
    return path, written


def _bytes(msg) -> bytes:
    if isinstance(msg, ProtoMessage):
        return msg.SerializeToString(deterministic=True)
    return json.dumps(msg[2], separators=(",", ":")).encode()


def test_every_written_message_reads_back_byte_for_byte_on_its_tick(recorded):
    path, written = recorded
    seen = {}
    with open_episode(path) as ep:
        assert ep.n_ticks == 6 and ep.tick_ns == TICK_NS and ep.duration_s == pytest.approx(1.2)
        assert ep.agents == ["vehicle_0", "rsu_0", "drone_0"]
        assert set(ep.topics) == {t for _, t in written}
        assert all(info.message_count == 6 for info in ep.topics.values())
        for tick in ep.ticks():
            assert tick.t_ns == tick.index * TICK_NS
            for topic in tick.topics:
                raw = tick.raw(topic)
                assert raw.log_time_ns == raw.publish_time_ns == tick.t_ns
                seen[(tick.index, topic)] = raw.data
    assert seen.keys() == written.keys()
    assert all(seen[k] == _bytes(written[k]) for k in written)
    # every topic the writer produced is one the format document names
    assert all(topic_spec(topic) is not None for _, topic in written)


def test_decoded_arrays_equal_what_was_written(recorded):
    path, written = recorded
    with open_episode(path) as ep:
        tick = ep.tick(4)
        src = written[(4, "/vehicle_0/lidar")]
        pc = tick.points("vehicle_0")
        assert isinstance(pc, PointCloud) and pc.frame_id == "vehicle_0/lidar" and pc.t_ns == 4 * TICK_NS
        assert set(pc.fields) == {"x", "y", "z", "intensity", "ring", "class_id", "instance_id"}
        assert len(pc) == 64
        # points lie on a 10 m ring around the sensor, 1.9 m below it
        assert np.hypot(pc.xyz[:, 0], pc.xyz[:, 1]) == pytest.approx(np.full(64, 10.0), abs=0.006)
        assert pc.xyz[:, 2] == pytest.approx(np.full(64, -1.9), abs=2.0**-8)
        assert pc.points["x"].dtype == np.float32 and pc.stored["x"].dtype == np.float32
        assert pc.points["ring"].max() == 15 and len(src.data) == 64 * src.point_stride

        img = tick.image("vehicle_0", "front")
        assert isinstance(img, Image) and img.array.shape == (24, 32, 3) and img.array.dtype == np.uint8
        assert (img.array[:, :, 0] == np.arange(32, dtype=np.uint8)).all() and (img.array[:, :, 1] == 40).all()
        depth = tick.depth("vehicle_0", "front")
        assert depth.encoding == "32FC1" and depth.array.dtype == np.float32
        assert (depth.depth_m == np.float32(12.345)).all()
        sem = tick.semantic("rsu_0", "front")
        assert sem.array.shape == (24, 32) and sem.array[:12].max() == 0 and (sem.array[12:] == 1).all()
        inst = tick.instance("drone_0", "down")
        labels = tick.labels
        assert set(np.unique(inst.array)) == {0, int(labels.track_ids.min())}

        cal = tick.calibration("vehicle_0", "rear")
        assert isinstance(cal, Calibration) and cal.frame_id == "vehicle_0/rear/optical"
        f = 16 / math.tan(math.radians(55))
        assert pytest.approx(np.array([[f, 0, 16], [0, f, 12], [0, 0, 1]])) == cal.K
        assert cal.P.shape == (3, 4)

        gnss = tick.gnss("drone_0")
        assert isinstance(gnss, GnssFix) and gnss.altitude_m == pytest.approx(70.0)
        assert np.diag(gnss.covariance_m2) == pytest.approx([0.25] * 3)
        bev = tick.bev("rsu_0")
        assert isinstance(bev, Grid) and bev.array.shape == (8, 16) and bev.array[3:5].min() == 1
        assert bev.cells.dtype.names == ("road", "car") and bev.cells["car"].max() == 0
        assert bev.cell_size_m == pytest.approx([1.0, 1.0]) and bev.origin_m == pytest.approx([37, 41, 8])
        assert tick.imu("vehicle_0")["linear_acceleration_mps2"] == pytest.approx([0, 0, 9.80665])
        vis = tick.visibility("rsu_0")
        assert vis["objects"][0]["track_id"] in labels.track_ids

        assert isinstance(labels, Objects) and labels.tick == 4 and len(labels) == 3
        assert labels.classes == ("drone", "truck", "car")
        car = labels.classes.index("car")
        assert labels.centers_m[car] == pytest.approx([10 + 10 * 0.8, 0.0, 0.75])
        assert labels.sizes_m[car] == pytest.approx([4.5, 1.9, 1.5]) and labels.yaws_rad[car] == pytest.approx(0)
        boxes = tick.boxes
        assert sorted(boxes.ids) == sorted(str(i) for i in labels.track_ids) and boxes.delete_all

        tf = tick.transforms
        assert isinstance(tf, TransformTree)
        # optical z (forward) of the front camera is the vehicle's +x; the rear camera looks back
        front = tf.to_root("vehicle_0/front/optical")
        rear = tf.to_root("vehicle_0/rear/optical")
        assert front[:3, 2] == pytest.approx([1, 0, 0], abs=1e-9)
        assert rear[:3, 2] == pytest.approx([-1, 0, 0], abs=1e-9)
        assert front[:3, 3] == pytest.approx([18.0, 0.0, 1.6])


def test_one_tick_with_a_topic_filter_decodes_only_what_is_asked(recorded, monkeypatch):
    path, _ = recorded
    decoded: list[str] = []
    real = reader_module.decode

    def spy(schema_name, encoding, data, schema_data=b""):
        decoded.append(schema_name)
        return real(schema_name, encoding, data, schema_data)

    monkeypatch.setattr(reader_module, "decode", spy)
    with open_episode(path) as ep:
        tick = ep.tick(2, topics=["/labels/objects", "/drone_0/*"])
        assert tick.index == 2
        assert "/vehicle_0/lidar" not in tick and "/drone_0/lidar" in tick and "/labels/objects" in tick
        assert all(t.startswith("/drone_0/") or t == "/labels/objects" for t in tick.topics)
        assert decoded == []  # nothing decoded until asked
        tick.points("drone_0")
        tick.points("drone_0")  # cached
        assert decoded == ["foxglove.PointCloud"] and tick.decoded_topics == ["/drone_0/lidar"]
        with pytest.raises(KeyError, match="/vehicle_0/lidar"):
            tick.points("vehicle_0")
        with pytest.raises(KeyError, match="no topic matches"):
            ep.select("/nope/*")
        ranged = list(ep.ticks(topics="/tf", start=1, stop=4))
        assert [t.index for t in ranged] == [1, 2, 3] and all(t.topics == ["/tf"] for t in ranged)


def test_reading_one_tick_reads_only_the_chunks_around_it(tmp_path):
    # Large images make many 4 MiB chunks; one tick's topics come from a small part of the file.
    path = write_synthetic_episode(tmp_path / "big.mcap", ticks=40, width=640, height=480, compression="none")
    size = path.stat().st_size
    with open_episode(path) as ep:
        stream = ep._stream
        counted = {"n": 0}
        real_read = stream.read

        class Counting:
            def __getattr__(self, name):
                return getattr(stream, name)

            def read(self, n=-1):
                data = real_read(n)
                counted["n"] += len(data)
                return data

        ep._reader._stream = Counting()
        tick = ep.tick(20, topics=["/vehicle_0/front/depth"])
        assert tick.depth("vehicle_0", "front").array.shape == (480, 640)
    assert size > 5 * 4 * 2**20
    assert counted["n"] < size / 3


def test_unknown_major_format_version_is_refused_with_a_clear_message(tmp_path):
    path = write_synthetic_episode(tmp_path / "v2.mcap", ticks=2, sensors=False, metadata={"format_version": "2.0"})
    with pytest.raises(FormatError, match=r"format version 2\.0 is not supported.*1\.x"):
        open_episode(path)
    minor = write_synthetic_episode(tmp_path / "v1_7.mcap", ticks=2, sensors=False, metadata={"format_version": "1.7"})
    with open_episode(minor) as ep:
        assert ep.format_version == "1.7"


def test_missing_and_truncated_files_raise_cosim_errors(tmp_path):
    with pytest.raises(InputError, match="no episode file"):
        open_episode(tmp_path / "absent.mcap")
    path = write_synthetic_episode(tmp_path / "ep.mcap", ticks=3)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(FormatError, match="truncated or corrupt"):
        open_episode(cut)
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    with pytest.raises(FormatError):
        open_episode(junk)


def test_metadata_and_attachments(recorded):
    path, _ = recorded
    with open_episode(path) as ep:
        assert ep.metadata["class_table"]["object_classes"][:6] == [
            "car",
            "van",
            "truck",
            "bus",
            "motorcycle",
            "bicycle",
        ]
        assert ep.metadata["geo_origin"] == [37.0, -122.0, 10.0] and ep.metadata["sensors_enabled"] is True
        assert ep.attachments == ["map.net.xml", "routes.rou.xml", "scenario.yaml", "world.json"]
        assert yaml.safe_load(ep.attachment("scenario.yaml"))["sensors"]["drone"]["cameras"][0]["name"] == "down"
        assert ep.cameras("vehicle_0") == ["front", "rear"] and ep.cameras("drone_0") == ["down"]
        with pytest.raises(KeyError, match=r"scenario\.yaml"):
            ep.attachment("nope.txt")


def test_the_runnable_example_reads_an_episode(recorded):
    import subprocess
    import sys

    from tests.helpers import REPO

    path, _ = recorded
    r = subprocess.run(
        [sys.executable, str(REPO / "examples" / "read_episode.py"), str(path), "--ticks", "2"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
    )
    assert r.returncode == 0, r.stderr
    assert "tick   1 t=  0.2 s: 3 boxes (1 car, 1 drone, 1 truck)" in r.stdout
    assert "drone_0    64 points, mean height 60.0 m; down 32x24, median depth 12.3 m" in r.stdout


def test_the_snapshot_is_rebuilt_exactly_from_the_labels(tmp_path):
    from cosim.assemble import TrackRegistry
    from cosim.io.synthetic import synthetic_snapshot, synthetic_world

    path = write_synthetic_episode(tmp_path / "snap.mcap", ticks=4, sensors=False)
    tracks, world = TrackRegistry(), synthetic_world()
    originals = [synthetic_snapshot(k, tracks, world) for k in range(4)]
    with open_episode(path) as ep:
        rebuilt = [t.snapshot() for t in ep.ticks(topics="/labels/objects")]
    for want, got in zip(originals, rebuilt, strict=True):
        assert (got.tick, got.t_ns) == (want.tick, want.t_ns)
        # everything but the engine's own id, which labels do not carry
        assert got.actors == tuple(dataclasses.replace(a, source_id="") for a in want.actors)
        assert [(a.agent_id, a.kind, a.position_m, a.rotation, a.track_id) for a in got.agents] == [
            (a.agent_id, a.kind, a.position_m, a.rotation, a.track_id) for a in want.agents
        ]


# -------------------------------------------------------------------------- a truncated file in every command


@pytest.mark.parametrize("command", [["info"], ["render", "--out", "R"], ["export", "--format", "airv2x", "--out", "E"],
                                     ["export", "--format", "opv2v", "--out", "E"], ["comm"]])
def test_a_truncated_file_gives_the_same_status_and_message_in_every_command(synthetic_episode, tmp_path, capsys,
                                                                             command):
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(synthetic_episode.read_bytes()[: synthetic_episode.stat().st_size * 2 // 3])
    args = [str(tmp_path / a) if a in ("R", "E") else a for a in command[1:]]
    status, _, err = cli(capsys, command[0], str(cut), *args)
    assert status == 2
    assert err.startswith(f"cosim: error: {cut}: truncated or corrupt MCAP") and len(err.strip().splitlines()) == 1
