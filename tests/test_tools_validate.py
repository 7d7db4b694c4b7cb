"""``cosim validate`` and ``cosim info``: a valid file passes; each defect class is found and named."""

from __future__ import annotations

import copy
import json
import math
import random

import pytest
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

from cosim.cli import main
from cosim.io.synthetic import TICK_NS, write_synthetic_episode
from cosim.io.validate import validate_episode
from tests.helpers import cli_in_process as cli
from tests.helpers import write_file


def _only(report, check):
    assert not report.ok
    found = [p for p in report.problems if p.check == check]
    assert found, f"expected a {check!r} problem, got: {report.lines()}"
    return found


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    return write_synthetic_episode(tmp_path_factory.mktemp("val") / "good.mcap", ticks=8)


def test_a_complete_episode_is_valid(good, capsys):
    report = validate_episode(good)
    assert report.ok, report.lines()
    assert report.ticks == 8 and report.messages == 8 * len(report.topics)
    assert main(["validate", str(good)]) == 0
    assert "ok (8 ticks" in capsys.readouterr().out


def test_info_lists_scenario_agents_topics_and_rates(good, capsys):
    assert main(["info", str(good), "--full"]) == 0
    out = capsys.readouterr().out
    assert "synthetic (seed 0)" in out and "urban, clear, day; drones: hover" in out
    assert "1.6 s, 8 ticks at 5 Hz" in out and "vehicle_0 rsu_0 drone_0" in out
    line = next(ln for ln in out.splitlines() if ln.strip().startswith("/vehicle_0/lidar"))
    assert line.split()[1:] == ["foxglove.PointCloud", "8", "msgs", "5.00", "Hz"]


def test_missing_file_is_bad_input_exit_2(tmp_path, capsys):
    assert main(["validate", str(tmp_path / "absent.mcap")]) == 2
    assert main(["info", str(tmp_path / "absent.mcap")]) == 2
    assert "no episode file" in capsys.readouterr().err


@pytest.mark.parametrize("keep_fraction", [0.97, 0.6, 0.3, 0.02])
def test_truncated_file_is_reported_not_crashed(good, tmp_path, keep_fraction, capsys):
    cut = tmp_path / "cut.mcap"
    data = good.read_bytes()
    cut.write_bytes(data[: int(len(data) * keep_fraction)])
    found = _only(validate_episode(cut), "structure")
    assert any("truncated" in p.message for p in found)
    assert main(["validate", str(cut)]) == 1
    assert "truncated" in capsys.readouterr().out
    assert main(["info", str(cut)]) == 2  # bad input (the file is not a readable episode): a message, no traceback
    assert "truncated or corrupt" in capsys.readouterr().err


def test_corrupt_bytes_are_reported_not_crashed(good, tmp_path):
    rng = random.Random(3)
    data = bytearray(good.read_bytes())
    for _ in range(40):
        data[rng.randrange(100, len(data) - 100)] ^= 0xFF
    bad = tmp_path / "flipped.mcap"
    bad.write_bytes(bytes(data))
    report = validate_episode(bad)
    assert not report.ok and "structure" in report.checks_failed()


def test_a_missing_message_on_one_tick_is_named(tmp_path):
    path = write_synthetic_episode(
        tmp_path / "drop.mcap", ticks=8, edit=lambda k, t, m: None if (k, t) == (3, "/labels/boxes") else m
    )
    found = _only(validate_episode(path), "completeness")
    assert [(p.topic, p.message) for p in found] == [("/labels/boxes", "no message on ticks 3 (1 of 8)")]


def test_a_missing_tick_is_named_for_every_topic(tmp_path):
    path = write_synthetic_episode(tmp_path / "gap.mcap", ticks=8, edit=lambda k, t, m: None if k in (5, 6) else m)
    found = _only(validate_episode(path), "completeness")
    assert {p.topic for p in found} >= {"/tf", "/labels/objects", "/vehicle_0/lidar"}
    assert all("ticks 5-6 (2 of 8)" in p.message for p in found)


def test_a_dangling_box_label_is_named(tmp_path):
    def edit(k, topic, msg):
        if (k, topic) == (2, "/labels/boxes"):
            msg = copy.deepcopy(msg)
            msg.entities[0].id = "99"
        return msg

    found = _only(validate_episode(write_synthetic_episode(tmp_path / "dangle.mcap", ticks=4, edit=edit)), "labels")
    assert any(p.tick == 2 and p.topic == "/labels/boxes" and "99" in p.message for p in found)


def test_a_dangling_track_in_lidar_and_visibility_is_named(tmp_path):
    def edit(k, topic, msg):
        if k == 1 and topic == "/rsu_0/visibility":
            name, schema, payload = msg
            return name, schema, {**payload, "objects": [{"track_id": 42, "lidar_points": 1, "pixels": {}}]}
        if k == 1 and topic == "/drone_0/lidar":
            msg = copy.deepcopy(msg)
            data = bytearray(msg.data)
            data[msg.point_stride - 4 : msg.point_stride] = (77).to_bytes(4, "little")  # instance_id of point 0
            msg.data = bytes(data)
        return msg

    found = _only(validate_episode(write_synthetic_episode(tmp_path / "d2.mcap", ticks=3, edit=edit)), "labels")
    assert {(p.tick, p.topic) for p in found} == {(1, "/rsu_0/visibility"), (1, "/drone_0/lidar")}
    assert any("[42]" in p.message for p in found) and any("[77]" in p.message for p in found)


def test_a_broken_transform_tree_is_named(tmp_path):
    def edit(k, topic, msg):
        if (k, topic) == (4, "/tf"):
            msg = FrameTransforms.FromString(msg.SerializeToString())
            for t in msg.transforms:
                if t.child_frame_id == "vehicle_0/lidar":
                    t.parent_frame_id = "vehicle_0/base_lnk"
        return msg

    found = _only(validate_episode(write_synthetic_episode(tmp_path / "tf.mcap", ticks=6, edit=edit)), "transforms")
    assert any(
        p.tick == 4 and "'vehicle_0/lidar' does not reach 'map'" in p.message and "vehicle_0/base_lnk" in p.message
        for p in found
    )
    assert all(p.tick == 4 for p in found)


def test_a_transform_cycle_and_a_second_parent_are_named(tmp_path):
    def edit(k, topic, msg):
        if (k, topic) == (1, "/tf"):
            msg = FrameTransforms.FromString(msg.SerializeToString())
            extra = msg.transforms.add()
            extra.CopyFrom(msg.transforms[0])  # map -> vehicle_0/base_link, now with a second parent
            extra.parent_frame_id = "vehicle_0/lidar"
        return msg

    found = _only(validate_episode(write_synthetic_episode(tmp_path / "cyc.mcap", ticks=3, edit=edit)), "transforms")
    assert any("'vehicle_0/base_link' has 2 parents" in p.message for p in found)


def test_timestamps_off_the_grid_and_backwards_are_named(tmp_path):
    def edit(k, topic, msg):
        if (k, topic) == (2, "/labels/objects"):
            return [(2 * TICK_NS + 1, topic, msg)]
        if (k, topic) == (3, "/tf"):
            return [(1 * TICK_NS, topic, msg)]
        return msg

    found = _only(validate_episode(write_synthetic_episode(tmp_path / "time.mcap", ticks=5, edit=edit)), "time")
    text = "\n".join(str(p) for p in found)
    assert "400000001 ns is not on the 200000000 ns tick grid" in text
    assert "goes back" in text


def test_a_header_stamp_that_disagrees_with_log_time_is_named(tmp_path):
    def edit(k, topic, msg):
        if (k, topic) == (2, "/labels/boxes"):
            msg = SceneUpdate.FromString(msg.SerializeToString())
            msg.entities[0].timestamp.nanos += 5
        return msg

    found = _only(validate_episode(write_synthetic_episode(tmp_path / "stamp.mcap", ticks=3, edit=edit)), "time")
    assert found[0].tick == 2 and "400000005 ns != log time 400000000 ns" in found[0].message


def test_an_image_without_calibration_is_named(tmp_path):
    path = write_synthetic_episode(
        tmp_path / "cal.mcap", ticks=3, edit=lambda k, t, m: None if t == "/drone_0/down/calibration" else m
    )
    found = _only(validate_episode(path), "calibration")
    assert {p.tick for p in found} == {0, 1, 2} and all(p.topic == "/drone_0/down/image" for p in found)


def _lens(model, D):
    def edit(k, topic, msg):
        if topic == "/drone_0/down/calibration" and k == 1:
            msg = copy.deepcopy(msg)
            msg.distortion_model = model
            del msg.D[:]
            msg.D.extend(D)
        return msg

    return edit


@pytest.mark.parametrize(
    ("model", "D", "words"),
    [
        ("plumb_bob", [-0.1, 0.01, 0, 0, float("nan")], "is not finite"),
        ("equidistant", [-0.1, 0.01, 0, 0], "a distorted lens is plumb_bob with 5 coefficients"),
        ("plumb_bob", [-0.1, 0.01, 0], "a distorted lens is plumb_bob with 5 coefficients"),
    ],
)
def test_a_lens_cosim_cannot_project_is_named(tmp_path, model, D, words):
    path = write_synthetic_episode(tmp_path / "lens.mcap", ticks=3, edit=_lens(model, D))
    found = _only(validate_episode(path), "calibration")
    assert [(p.tick, p.topic) for p in found] == [(1, "/drone_0/down/image")] and words in found[0].message


def test_a_distorted_plumb_bob_lens_is_valid(tmp_path):
    path = write_synthetic_episode(tmp_path / "lens.mcap", ticks=3, edit=_lens("plumb_bob", [-0.1, 0.01, 0, 0, 0]))
    assert validate_episode(path).ok


def test_an_unknown_format_version_is_named(tmp_path, capsys):
    path = write_synthetic_episode(tmp_path / "v9.mcap", ticks=2, sensors=False, metadata={"format_version": "9.1"})
    found = _only(validate_episode(path), "metadata")
    assert "9.1 is not supported" in found[0].message
    assert main(["info", str(path)]) == 2  # a file this cosim cannot read is bad input
    assert "9.1" in capsys.readouterr().err


def test_a_sensor_topic_the_rig_promises_but_the_file_lacks_is_named(tmp_path):
    path = write_synthetic_episode(
        tmp_path / "rig.mcap", ticks=3, edit=lambda k, t, m: None if t == "/vehicle_0/rear/semantic" else m
    )
    found = _only(validate_episode(path), "completeness")
    assert [(p.topic, p.message) for p in found] == [
        ("/vehicle_0/rear/semantic", "topic missing from the file (the scenario's rig has it)")
    ]


def test_labels_and_tf_disagreeing_on_an_agent_pose_is_named(tmp_path):
    def edit(k, topic, msg):
        if (k, topic) == (1, "/labels/objects"):
            name, schema, payload = copy.deepcopy(msg)
            payload["agents"][0]["position_m"][0] += 0.5
            return name, schema, payload
        return msg

    found = _only(validate_episode(write_synthetic_episode(tmp_path / "pose.mcap", ticks=3, edit=edit)), "labels")
    assert len(found) == 1 and found[0].tick == 1 and "agent 'vehicle_0' pose" in found[0].message


def test_info_and_validate_json_output(good, capsys):
    import json

    assert main(["info", str(good), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["n_ticks"] == 8 and info["agents"] == ["vehicle_0", "rsu_0", "drone_0"]
    assert {t["topic"]: t["messages"] for t in info["topics"]}["/tf"] == 8
    assert main(["validate", str(good), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["ok"] is True and report["problems"] == []


@pytest.mark.parametrize("compression", ["zstd", "none"])
def test_random_damage_is_always_found_and_never_crashes(tmp_path, compression):
    """Bit flips, zeroed runs, cut-outs and truncations anywhere in the file (records, chunks,
    indexes, attachments, summary) are each reported; validate never raises."""
    src = write_synthetic_episode(tmp_path / "src.mcap", ticks=4, compression=compression).read_bytes()
    rng = random.Random(11)
    bad = tmp_path / "bad.mcap"
    for _ in range(60):
        data = bytearray(src)
        kind = rng.choice(["flip", "zero", "cut", "truncate"])
        if kind == "flip":
            for _ in range(rng.randint(1, 8)):
                data[rng.randrange(len(data))] ^= rng.randrange(1, 256)
        elif kind == "zero":
            a = rng.randrange(len(data) - 64)
            data[a : a + 64] = bytes(64)
        elif kind == "cut":
            a = rng.randrange(len(data) - 1)
            del data[a : a + rng.randint(1, 500)]
        else:
            del data[rng.randrange(len(data)) :]
        if bytes(data) == src:
            continue
        bad.write_bytes(bytes(data))
        report = validate_episode(bad)
        assert not report.ok, f"{kind} damage not found"


# --------------------------------------------------- cosim info: summary first, bytes estimated from one tick


@pytest.fixture
def counted_reads(monkeypatch) -> list[int]:
    """Messages read through Episode.messages (one entry per message)."""
    from cosim.io.reader import Episode

    read: list[int] = []
    real = Episode.messages

    def counting(self, *a, **k):
        for m in real(self, *a, **k):
            read.append(1)
            yield m

    monkeypatch.setattr(Episode, "messages", counting)
    return read


def test_info_prints_summary_and_family_bytes_first_and_topics_per_agent_without_reading_the_file(
        synthetic_episode, capsys, counted_reads):
    from cosim.io import open_episode

    with open_episode(synthetic_episode) as ep:
        per_tick = len(ep.topics)
        total = ep.message_count
        small = 2 * ep.n_ticks  # /labels/objects and /tf of every tick: the labels and the drones' altitudes
    status, out, _ = cli(capsys, "info", str(synthetic_episode))
    assert status == 0
    lines = out.splitlines()
    family_at = next(i for i, ln in enumerate(lines) if ln.startswith("bytes by topic family"))
    topics_at = next(i for i, ln in enumerate(lines) if ln.startswith("topics "))
    assert family_at < topics_at and lines[topics_at] == f"topics       {per_tick} (per agent; --full lists each)"
    per_agent = lines[topics_at + 1:]
    assert [ln.split()[0] for ln in per_agent] == ["episode", "vehicle_0", "rsu_0", "drone_0"]
    assert "1 camera (down) x image depth semantic instance calibration" in per_agent[3]
    assert len(counted_reads) <= per_tick + small < total  # one tick read, for the compression ratios

    counted_reads.clear()
    status, out, _ = cli(capsys, "info", str(synthetic_episode), "--full")
    assert status == 0 and len(counted_reads) == total + small
    assert "/drone_0/down/image" in out and "(payloads; stored = compressed alone" in out


def test_info_estimates_family_bytes_close_to_the_full_count(synthetic_episode):
    from cosim.io.info import episode_info

    quick = {f.family: f for f in episode_info(synthetic_episode).families}
    exact = {f.family: f for f in episode_info(synthetic_episode, full=True).families}
    assert quick.keys() == exact.keys()
    for fam, f in exact.items():
        assert quick[fam].messages == f.messages
        assert abs(quick[fam].raw_bytes - f.raw_bytes) <= 0.05 * f.raw_bytes + 2048, (fam, quick[fam], f)
        assert abs(quick[fam].stored_bytes - f.stored_bytes) <= 0.5 * f.stored_bytes + 2048, (fam, quick[fam], f)


def test_info_json_writes_the_seed_as_a_number(synthetic_episode, capsys):
    status, out, _ = cli(capsys, "info", str(synthetic_episode), "--json", "--no-bytes")
    info = json.loads(out)
    assert status == 0 and info["seed"] == 0 and isinstance(info["seed"], int)


# ----------------------------------------------------------- non-finite values; a file that is not an episode


def test_validate_rejects_non_finite_transforms_and_labels(tmp_path):
    from cosim.io.synthetic import write_synthetic_episode
    from cosim.io.validate import validate_episode

    def poison(tick, topic, msg):
        if tick == 3 and topic == "/tf":
            msg.transforms[0].translation.x = math.nan
        if tick == 4 and topic == "/labels/objects":
            payload = msg[2]
            payload["objects"][0]["center_m"][2] = math.inf
        return msg

    good = validate_episode(write_synthetic_episode(tmp_path / "good.mcap", ticks=6, sensors=False))
    assert good.ok, good.lines()
    report = validate_episode(write_synthetic_episode(tmp_path / "bad.mcap", ticks=6, sensors=False, edit=poison))
    lines = report.lines()
    assert any("tick 3" in line and "/tf" in line and "is not finite" in line for line in lines), lines
    assert any("tick 4" in line and "objects.0.center_m.2 is not finite (inf)" in line for line in lines), lines


def test_info_on_a_file_that_is_not_an_episode_exits_2(tmp_path, capsys):
    for content in (b"hello\n", bytes(range(256))):
        f = write_file(tmp_path, "x.mcap", content)
        status, _, err = cli(capsys, "info", str(f))
        assert status == 2 and "Traceback" not in err and f"{f}: not a readable MCAP file" in err, err


def _raised_drone(tick, topic, msg, by_m: float = 45.0):
    """A synthetic episode's edit: drone_0 (asked altitude_m 60) flies ``by_m`` higher."""
    if topic == "/tf":
        for t in msg.transforms:
            if t.child_frame_id == "drone_0/base_link":
                t.translation.z += by_m
    return msg


def test_info_counts_labels_per_class_and_says_when_a_drone_flies_far_from_its_altitude(tmp_path, capsys):
    """`cosim info`: the objects of /labels/objects per class (distinct tracks, mean per tick), and a drone flying
    farther than ALTITUDE_NOTE_M from its scenario's altitude_m named with both heights (nothing when it does
    not)."""
    from cosim.io import open_episode

    path = write_synthetic_episode(tmp_path / "high.mcap", ticks=4, sensors=False, edit=_raised_drone)
    tracks, per_tick = {}, {}
    with open_episode(path) as ep:
        for tick in ep.ticks(topics=["/labels/objects"]):
            for cls, tid in zip(tick.labels.classes, tick.labels.track_ids, strict=True):
                tracks.setdefault(cls, set()).add(int(tid))
                per_tick[cls] = per_tick.get(cls, 0) + 1 / len(ep)
    status, out, _ = cli(capsys, "info", str(path), "--no-bytes")
    assert status == 0
    lines = out.splitlines()
    at = next(i for i, ln in enumerate(lines) if ln.startswith("labels "))
    n_tracks = sum(map(len, tracks.values()))
    assert lines[at] == f"labels       {n_tracks} tracks in {len(tracks)} classes (/labels/objects)"
    rows = {ln.split()[0]: (int(ln.split()[1]), float(ln.split()[2])) for ln in lines[at + 2:at + 2 + len(tracks)]}
    assert rows == {c: (len(t), round(per_tick[c], 1)) for c, t in tracks.items()} and len(rows) >= 2
    assert "altitude     drone_0 (hover) flies at 105 m, 45 m above its altitude_m 60" in lines
    assert any("agents.drone_separation_m" in ln for ln in lines)
    info = json.loads(cli(capsys, "info", str(path), "--json", "--no-bytes")[1])
    assert info["drones"] == [{"agent": "drone_0", "strategy": "hover", "asked_m": 60.0, "flown_m": 105.0,
                               "far": True}]
    assert info["objects"]["car"]["tracks"] == len(tracks["car"])

    level = write_synthetic_episode(tmp_path / "level.mcap", ticks=4, sensors=False)
    status, out, _ = cli(capsys, "info", str(level), "--no-bytes")
    assert status == 0 and "altitude" not in out and "labels " in out


def test_the_run_summary_says_when_a_drone_flies_far_from_its_altitude(tmp_path, capsys, monkeypatch):
    """`cosim run`'s summary ends with the same altitude lines as `cosim info`, read from the episode it wrote
    (here the engines are replaced by a written synthetic episode whose drone flies 45 m too high)."""
    import cosim.runner
    from cosim.runner import EpisodeResult

    path = write_synthetic_episode(tmp_path / "high.mcap", ticks=3, sensors=False, edit=_raised_drone)

    def fake_run(loaded, out_dir, **_kwargs):
        return EpisodeResult(path=path, ticks=3, sim_time_s=0.6, actors=3, messages=1, size_bytes=path.stat().st_size,
                             wall_time_s=1.0)

    monkeypatch.setattr(cosim.runner, "run_episode", fake_run)
    status, out, err = cli(capsys, "run", "default", "--no-sensors", "--out", str(tmp_path / "o"), "-q")
    assert status == 0, err
    lines = out.splitlines()
    at = lines.index("altitude drone_0 (hover) flies at 105 m, 45 m above its altitude_m 60")
    assert lines[at - 1].startswith("wall ") and "agents.drone_separation_m" in lines[at + 1]
