"""Real ``cosim run`` episodes: same seed -> byte-identical file; every shipped scenario validates."""

from __future__ import annotations

import hashlib

import pytest

from cosim.io import open_episode
from cosim.io.validate import validate_episode
from tests.helpers import SCENARIOS, run_cli

pytestmark = pytest.mark.integration

TINY = ["--no-sensors", "--set", "map.size_m=300"]


def _run(scenario: str, out, *extra: str):
    r = run_cli("run", scenario, "--out", str(out), "-q", *TINY, *extra)
    assert r.returncode == 0, r.stderr
    (path,) = list(out.iterdir())
    return path


def test_two_runs_of_one_seed_give_byte_identical_files(tmp_path):
    a = _run("scenarios/default.yaml", tmp_path / "a", "--duration", "2")
    b = _run("scenarios/default.yaml", tmp_path / "b", "--duration", "2")
    c = _run("scenarios/default.yaml", tmp_path / "c", "--duration", "2", "--seed", "1")
    digest = [hashlib.sha256(p.read_bytes()).hexdigest() for p in (a, b, c)]
    assert digest[0] == digest[1]
    assert digest[0] != digest[2]
    report = validate_episode(a)
    assert report.ok, report.lines()
    with open_episode(a) as ep:
        assert ep.n_ticks == 10 and ep.format_version == "1.1"
        assert {t.message_count for t in ep.topics.values()} == {10}


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


def test_two_runs_with_sensors_give_byte_identical_valid_files(tmp_path):
    paths = []
    for run in ("a", "b"):
        r = run_cli(
            "run", "scenarios/default.yaml", "--duration", "0.4", "--out", str(tmp_path / run), "-q", *SMALL_SENSORS
        )
        assert r.returncode == 0, r.stderr
        paths.append(tmp_path / run / "default_s0.mcap")
    assert paths[0].read_bytes() == paths[1].read_bytes()
    report = validate_episode(paths[0])
    assert report.ok, report.lines()
    with open_episode(paths[0]) as ep:
        assert "/drone_0/down/instance" in ep.topics and "/vehicle_0/lidar" in ep.topics
        assert len(ep.tick(1).points("vehicle_0")) > 1000


@pytest.mark.parametrize("scenario", sorted(p.name for p in SCENARIOS.glob("*.yaml")))
def test_every_shipped_scenario_gives_a_valid_episode(tmp_path, scenario):
    path = _run(f"scenarios/{scenario}", tmp_path, "--duration", "1")
    report = validate_episode(path)
    assert report.ok, report.lines()
    r = run_cli("validate", str(path))
    assert r.returncode == 0 and "ok (5 ticks" in r.stdout, r.stdout + r.stderr
