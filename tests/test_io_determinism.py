"""Real ``cosim run`` episodes: same seed -> byte-identical file; every shipped scenario validates."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest
from mcap.reader import make_reader

from cosim.io import open_episode
from cosim.io.manifest import latest_records
from cosim.io.validate import validate_episode
from tests.helpers import SCENARIOS, run_cli

pytestmark = pytest.mark.integration

def _labels(path) -> list[bytes]:
    with open(path, "rb") as f:
        return [m.data for _s, _c, m in make_reader(f).iter_messages(topics=["/labels/objects"])]


#: LiDARs, GNSS, IMU, BEV, visibility on every agent and one small nadir camera per drone.
SMALL_SENSORS = [
    "--set",
    "map.size_m=300",
    "--set",
    "sensors.vehicle.cameras=[]",
    "--set",
    "sensors.rsu.cameras=[]",
    "--set",
    "sensors.drone.cameras=[{name: down, width: 64, height: 36, gimbal: true, "
    "mount: {xyz_m: [0, 0, -0.15], rpy_deg: [0, 90, 0]}}]",
    "--set",
    "runtime.tick_timeout_s=120",
]


def test_two_runs_of_one_seed_give_byte_identical_valid_files_and_another_seed_other_traffic(tmp_path):
    """Every topic (LiDARs, GNSS, IMU, BEV, visibility, a small camera per drone, labels): the same seed gives
    the same bytes; seed 1 gives other traffic, not only other bytes."""
    paths = []
    for run, seed in (("a", "0"), ("b", "0"), ("c", "1")):
        r = run_cli("run", "scenarios/default.yaml", "--duration", "0.4", "--seed", seed, "--out", str(tmp_path / run),
                    "-q", *SMALL_SENSORS)
        assert r.returncode == 0, r.stderr
        (path,) = list((tmp_path / run).iterdir())
        paths.append(path)
    a, b, c = paths
    assert a.read_bytes() == b.read_bytes()
    assert hashlib.sha256(a.read_bytes()).digest() != hashlib.sha256(c.read_bytes()).digest()
    assert _labels(a) != _labels(c)
    report = validate_episode(a)
    assert report.ok, report.lines()
    with open_episode(a) as ep:
        assert ep.n_ticks == 2 and ep.format_version == "1.4"
        assert {ep.topics[t].message_count for t in ("/labels/objects", "/vehicle_0/lidar")} == {2}
        assert "/drone_0/down/instance" in ep.topics and "/vehicle_0/lidar" in ep.topics
        assert len(ep.tick(1).points("vehicle_0")) > 1000


SHIPPED = sorted(p.name for p in SCENARIOS.glob("*.yaml"))


@pytest.fixture(scope="module")
def shipped_episodes(tmp_path_factory) -> tuple[dict[str, Path], str]:
    """One tiny labels-only episode of every shipped scenario (2 ticks, 300 m map), all from one `cosim batch`
    with two workers, and one `cosim validate` of them all: two process starts for the lot instead of two
    per scenario. Returns scenario file name -> episode, and the validate output."""
    tmp = tmp_path_factory.mktemp("shipped")
    sweep = tmp / "shipped.yaml"
    sweep.write_text(f"name: shipped\nbase: [{', '.join(str(SCENARIOS / n) for n in SHIPPED)}]\n"
                     f"set: {{duration_s: 0.4, sensors.enabled: false, map.size_m: 300}}\ncount: {len(SHIPPED)}\n")
    out = tmp / "out"
    r = run_cli("batch", str(sweep), "--out", str(out), "--workers", "2", "-q", timeout=3000)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    files = {f"{rec['labels']['base']}.yaml": out / rec["file"] for rec in latest_records(out).values()}
    assert sorted(files) == SHIPPED
    v = run_cli("validate", *map(str, files.values()))
    return files, v.stdout + v.stderr


@pytest.mark.timeout(900)  # the first one builds the fixture: 19 episodes and their worlds (minutes when busy)
@pytest.mark.parametrize("scenario", SHIPPED)
def test_every_shipped_scenario_gives_a_valid_episode(shipped_episodes, scenario):
    files, validated = shipped_episodes
    path = files[scenario]
    report = validate_episode(path)
    assert report.ok, report.lines()
    assert f"{path}: ok (2 ticks" in validated, validated


def test_a_10_hz_full_rig_episode_validates_and_stamps_every_sensor_message_with_its_capture_time(tmp_path):
    """``tick_hz: 10`` with the default scenario's full rig (5 + 5 + 5 agents, every LiDAR and camera; images
    at 1/20 size to keep it short): the episode validates, so every LiDAR return lies in its object's box at its
    firing time and every instance pixel in its object's box at the tick (docs/episode_format.md section 2);
    every sensor message's own timestamp is its log time, the tick k at k x 100 ms, and a sweep's points fire
    within the 50 ms before it (t_offset_ns in [-50 ms, 0])."""
    out = tmp_path / "ep"
    r = run_cli("run", "scenarios/default.yaml", "--set", "tick_hz=10", "--duration", "0.3", "--out", str(out), "-q",
                "--set", "map.size_m=300", "--set", "sensors.image_scale=0.05")
    assert r.returncode == 0, r.stderr
    path = out / "default_s0.mcap"
    report = validate_episode(path)
    assert report.ok, report.lines()
    stamped = set()
    with open_episode(path) as ep:
        assert ep.tick_ns == 100_000_000 and ep.n_ticks == 3
        for m in ep.messages():
            assert m.log_time_ns % ep.tick_ns == 0 and m.publish_time_ns == m.log_time_ns, m.topic
            if m.topic.endswith(("/lidar", "/image", "/depth", "/semantic", "/instance", "/gnss")):
                msg = m.decode()
                assert msg.t_ns == m.log_time_ns, (m.topic, msg.t_ns, m.log_time_ns)
                stamped.add(m.topic.rsplit("/", 1)[1])
                if m.topic.endswith("/lidar"):
                    offsets = msg.points["t_offset_ns"]
                    assert offsets.max() <= 0 and offsets.min() >= -50_000_000 and offsets.min() < -40_000_000
    assert stamped == {"lidar", "image", "depth", "semantic", "instance", "gnss"}
