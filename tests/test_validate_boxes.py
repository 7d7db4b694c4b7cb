"""``cosim validate``'s boxes check (issue 28): LiDAR returns and instance pixels lie in their objects' boxes
in a real episode, and a box moved away from its object's returns and pixels is named."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from cosim.io.validate import validate_episode
from tests.helpers import run_cli

pytestmark = pytest.mark.integration

SCENARIO = {
    "name": "fit", "seed": 4, "duration_s": 1.0, "map": {"kind": "urban", "size_m": 300},
    "traffic": {"density_veh_per_km": 40}, "pedestrians": {"density_per_km": 40},
    "agents": {"vehicles": {"count": 1}, "rsus": {"count": 1}, "drones": []},
    "sensors": {"vehicle": {"lidar": {"channels": 32}, "cameras": [{"name": "front", "width": 160, "height": 120}],
                            "imu": {}},
                "rsu": {"lidar": {"channels": 32}, "cameras": [{"name": "cam", "width": 160, "height": 120}]}},
}


@pytest.fixture(scope="module")
def episode(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("fit")
    (tmp / "fit.yaml").write_text(yaml.safe_dump(SCENARIO))
    r = run_cli("run", str(tmp / "fit.yaml"), "--out", str(tmp / "out"))
    assert r.returncode == 0, r.stderr
    return next((tmp / "out").glob("*.mcap"))


def _rewrite(src: Path, dst: Path, edit, raw=None) -> None:
    """A copy of episode ``src`` with each ``/labels/objects`` payload passed through ``edit(tick, payload)`` and
    every other message's bytes through ``raw(topic, data)`` when given."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(src, "rb") as f, open(dst, "wb") as out:
        reader = make_reader(f)
        w = Writer(out)
        w.start(profile="", library="test")
        for md in reader.iter_metadata():  # first, as the writer puts it: it gives the tick grid
            w.add_metadata(md.name, md.metadata)
        schemas, channels = {}, {}
        for schema, ch, m in reader.iter_messages(log_time_order=False):
            if schema.id not in schemas:
                schemas[schema.id] = w.register_schema(schema.name, schema.encoding, schema.data)
            if ch.id not in channels:
                channels[ch.id] = w.register_channel(ch.topic, ch.message_encoding, schemas[schema.id], ch.metadata)
            data = m.data
            if ch.topic == "/labels/objects":
                payload = json.loads(data)
                data = json.dumps(edit(payload["tick"], payload)).encode()
            elif raw is not None:
                data = raw(ch.topic, data)
            w.add_message(channels[ch.id], m.log_time, data, m.publish_time, m.sequence)
        for a in reader.iter_attachments():
            w.add_attachment(a.create_time, a.log_time, a.name, a.media_type, a.data)
        w.finish()


def test_a_real_episodes_returns_and_pixels_lie_in_their_boxes(episode):
    report = validate_episode(episode)
    assert report.ok, report.lines()


def test_a_moved_box_is_named_for_its_lidar_returns_and_pixels(episode, tmp_path):
    # the copy itself is valid: the check looks at what the edit changes only
    same = tmp_path / "same.mcap"
    _rewrite(episode, same, lambda tick, p: p)
    assert validate_episode(same).ok, validate_episode(same).lines()
    moved: dict[int, set[int]] = {}

    def shift(tick: int, payload: dict) -> dict:
        if tick == 2:
            for o in payload["objects"]:
                if o.get("agent_id") is None:
                    o["center_m"][0] += 1.0  # every other actor's box 1 m off its body
                    moved.setdefault(tick, set()).add(o["track_id"])
        return payload

    bad = tmp_path / "moved.mcap"
    _rewrite(episode, bad, shift)
    report = validate_episode(bad)
    found = [p for p in report.problems if p.check == "boxes"]
    assert found and {p.check for p in report.problems} == {"boxes"}, report.lines()
    assert {p.tick for p in found} == {2}
    assert any(p.topic.endswith("/lidar") and "returns of track" in p.message for p in found)
    assert any(p.topic.endswith("/instance") and "px outside its projected box" in p.message for p in found)
    r = run_cli("validate", str(bad))
    assert r.returncode != 0 and "[boxes]" in r.stdout + r.stderr


def test_negative_depth_is_named(episode, tmp_path):
    """The depth check decodes every pixel (the one-pass kernel of cosim.pixel_kernels): three negative pixels
    in one image are counted."""
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

    from cosim.depth import decode_depth, encode_depth

    done = []

    def negate(topic: str, data: bytes) -> bytes:
        if done or not topic.endswith("/depth"):
            return data
        msg = CompressedImage.FromString(data)
        d = decode_depth(msg.data)
        d[5, 7:10] = -2.0
        msg.data = encode_depth(d)
        done.append(topic)
        return msg.SerializeToString()

    bad = tmp_path / "negative.mcap"
    _rewrite(episode, bad, lambda tick, p: p, negate)
    problems = [p for p in validate_episode(bad).problems if p.check == "sensors"]
    assert [(p.topic, p.message) for p in problems] == [(done[0], "3 depth pixels are infinite or negative "
                                                                   "(no hit is NaN)")]
