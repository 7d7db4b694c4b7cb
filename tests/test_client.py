"""Closed loop (cosim.client): real `cosim run` processes, real clients in processes of their own, real Zenoh,
SUMO and JSBSim. The clients are tests/loop_clients.py; the conductor listens on a fixed endpoint and prefix."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import psutil
import pytest

from cosim.actions import ActionContext, check_actions
from cosim.errors import ActionRejected
from cosim.io import open_episode
from cosim.io.validate import validate_episode
from cosim.transport import free_loopback_endpoint
from tests.helpers import REPO, children_of, run_cli
from tests.loop_clients import GOAL_ALTITUDE_M, GOAL_XY_M, SLOW_MPS

pytestmark = pytest.mark.integration  # real `cosim run` processes with SUMO and JSBSim

SCENARIO = f"""\
extends: {REPO / "scenarios/base/paper.yaml"}
name: loop_main
duration_s: 12
map: {{size_m: 300}}
traffic: {{density_veh_per_km: 6}}
agents:
  layout: spread  # one connected vehicle on a route of its own (no group to keep together)
  vehicles: {{count: 1}}
  rsus: {{count: 0}}
  drones:
    - {{strategy: hover, altitude_m: 30, point: [0, 0], plan_altitude: false}}
    - {{strategy: hover, altitude_m: 50, point: [-20, 40], plan_altitude: false}}
    - {{strategy: hover, altitude_m: 20, point: [0, 20], plan_altitude: false}}
sensors: {{enabled: false}}
clients: [{{name: c0}}]
"""


class Loop:
    """One `cosim run` with one client process, both started here."""

    def __init__(self, tmp: Path, mode: str, *run_args: str, client: str = "c0", scenario: str = SCENARIO,
                 client_argv: list[str] | None = None):
        tmp.mkdir(parents=True, exist_ok=True)
        (tmp / "scenario.yaml").write_text(scenario)
        self.out = tmp / "out"
        endpoint, prefix = free_loopback_endpoint(), f"test/loop/{tmp.name}"
        env = {**os.environ, "COSIM_ENDPOINT": endpoint, "COSIM_PREFIX": prefix}
        self.run = subprocess.Popen(
            [sys.executable, "-m", "cosim.cli", "run", str(tmp / "scenario.yaml"), "--out", str(self.out), "-q",
             "--listen", endpoint, "--prefix", prefix, *run_args],
            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        argv = client_argv or ["-m", "tests.loop_clients", mode, client]
        self.client = subprocess.Popen([sys.executable, *argv], cwd=REPO, env=env,
                                       stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.lines: list[dict] = []
        self.client_argv = client_argv
        self.output = ""

    def read_until(self, tick: int) -> None:
        """Follow the client's output until it printed ``tick``."""
        while not self.lines or self.lines[-1]["tick"] < tick:
            line = self.client.stdout.readline()
            assert line, f"client ended before tick {tick}: {self.client.stderr.read()[-2000:]}"
            self.lines.append(json.loads(line))

    def finish(self, timeout_s: float = 300, *, read_client: bool = True) -> tuple[int, str]:
        _, err = self.run.communicate(timeout=timeout_s)
        if read_client and self.client.returncode != -signal.SIGKILL:
            try:
                out, _ = self.client.communicate(timeout=30)
            except subprocess.TimeoutExpired:  # say why the run ended, not only that the client is still waiting
                self.client.kill()
                _, client_err = self.client.communicate()
                raise AssertionError(f"the client did not end within 30 s of the run (exit {self.run.returncode})"
                                     f"\nrun: {err[-2000:]}\nclient: {client_err[-2000:]}") from None
            self.output = out
            if not self.client_argv:
                self.lines += [json.loads(x) for x in out.splitlines() if x.strip()]
        return self.run.returncode, err

    def kill(self) -> None:
        for p in (self.run, self.client):
            if p.poll() is None:
                p.kill()
                p.wait()


def speed_of(objects, agent_id: str) -> float:
    i = objects.agent_ids.index(agent_id)
    return float(np.hypot(*objects.velocities_mps[i, :2]))


def agent(objects, agent_id: str) -> dict:
    return next(a for a in objects.agents if a["agent_id"] == agent_id)


@pytest.fixture(scope="module")
def main_runs(tmp_path_factory):
    """The same scenario and the same deterministic client, twice."""
    runs = []
    for i in range(2):
        loop = Loop(tmp_path_factory.mktemp(f"main{i}"), "main")
        try:
            rc, err = loop.finish()
        finally:
            loop.kill()
        assert rc == 0, err
        runs.append((loop, err, loop.out / "loop_main_s0.mcap"))
    return runs


def test_client_sends_drone_0_to_a_waypoint_and_it_arrives_within_1_m(main_runs):
    loop, _, path = main_runs[0]
    with open_episode(path) as ep:
        ground_z = json.loads(ep.attachment("world.json"))["ground_z_m"]
        last = ep.tick(ep.n_ticks - 1).labels
    goal = np.array([*GOAL_XY_M, ground_z + GOAL_ALTITUDE_M])
    d0 = agent(last, "drone_0")
    assert np.linalg.norm(np.array(d0["position_m"]) - goal) <= 1.0
    assert (d0["extra"]["strategy"], d0["extra"]["strategy_state"]) == ("goto", "arrived")
    # what the client saw is what the file holds (same bytes, decoded by cosim.io)
    assert loop.lines[-1]["last"] and loop.lines[-1]["drone_0"][:3] == d0["position_m"]


def test_client_slows_vehicle_0_to_5_mps_and_labels_follow_within_3_s(main_runs):
    _, _, path = main_runs[0]
    with open_episode(path) as ep:
        speeds = [speed_of(t.labels, "vehicle_0") for t in ep.ticks("/labels/objects")]
    assert speeds[0] > SLOW_MPS + 0.5  # it was faster before the action (otherwise this test proves nothing)
    after = speeds[1 + 15 :]  # applied in the step to tick 1; 3 s = 15 ticks later
    assert max(after) <= SLOW_MPS + 0.05
    assert np.median(after) >= SLOW_MPS - 0.5  # it drives at the commanded speed, not stopped


def test_action_for_a_missing_agent_comes_back_as_an_error_and_the_run_goes_on(main_runs):
    loop, err, _ = main_runs[0]
    rejected = [x for x in loop.lines if "rejected" in x]
    assert [x["tick"] for x in rejected] == [2]
    assert "drone_9" in rejected[0]["rejected"] and "no drone" in rejected[0]["rejected"]
    assert "drone_9" in err  # the conductor logs it too
    assert loop.lines[-1]["tick"] == 59  # the episode went on to its end


def test_actions_are_recorded_and_strategy_switch_escort_and_land_apply(main_runs):
    _, _, path = main_runs[0]
    assert validate_episode(path).ok
    with open_episode(path) as ep:
        recorded = {t.index: t["/actions"] for t in ep.ticks("/actions")}
        last = ep.tick(ep.n_ticks - 1).labels
    assert len(recorded) == 60 and all(r["failed"] == [] for r in recorded.values())
    kinds = {k: [(a["client"], a["observed_tick"], a["action"]["type"]) for a in r["actions"]]
             for k, r in recorded.items() if r["actions"]}
    assert kinds == {1: [("c0", 0, "goto"), ("c0", 0, "set_speed")], 2: [("c0", 1, "strategy"), ("c0", 1, "land")],
                     5: [("c0", 4, "change_lane")]}
    escort, landed = agent(last, "drone_1"), agent(last, "drone_2")
    assert escort["extra"]["strategy"] == "escort" and escort["extra"]["strategy_state"] != "lost"
    assert landed["extra"]["strategy_state"] == "landed" and landed["position_m"][2] < 2.0


def test_a_deterministic_client_gives_identical_episode_files(main_runs):
    (_, _, a), (_, _, b) = main_runs
    assert a.read_bytes() == b.read_bytes()


def test_sigkilled_client_ends_the_run_naming_it_and_the_tick(tmp_path):
    # a tick timeout far beyond the wait below: only the client's lost liveliness can end the run this soon
    loop = Loop(tmp_path, "observe", "--clients", "c0", "--duration", "60", "--set", "runtime.tick_timeout_s=120")
    try:
        loop.read_until(5)
        workers = children_of(loop.run.pid)
        assert workers  # the run's workers, to check afterwards
        loop.client.send_signal(signal.SIGKILL)
        t0 = time.monotonic()
        rc, err = loop.finish(timeout_s=60)
        print(f"run ended {time.monotonic() - t0:.2f} s after the client's SIGKILL")
    finally:
        loop.kill()
    assert rc == 1
    assert "client 'c0' at tick" in err and "disconnected (liveliness lost)" in err
    assert not list(loop.out.glob("*.mcap")) and not list(loop.out.glob(".*partial"))
    assert not [p for p in workers if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]


def test_silent_client_times_out_naming_it_and_the_tick(tmp_path):
    loop = Loop(tmp_path, "silent", "--set", "clients=[{name: quiet, timeout_s: 1.5}]", client="quiet")
    try:
        rc, err = loop.finish(timeout_s=120, read_client=False)  # the client sleeps on; killed below
    finally:
        loop.kill()
    assert rc == 1
    assert "client 'quiet' at tick 2: no action within 1.5 s" in err
    assert not list(loop.out.glob("*.mcap")) and not list(loop.out.glob(".*partial"))


def test_example_client_follow_runs(tmp_path):
    loop = Loop(tmp_path, "", "--clients", "follow", "--duration", "2",
                client_argv=[str(REPO / "examples/client_follow.py")])
    try:
        rc, err = loop.finish(timeout_s=180)
    finally:
        loop.kill()
    assert rc == 0, err
    assert loop.client.returncode == 0
    lines = loop.output.splitlines()
    assert len(lines) == 10 and lines[0].startswith("tick 0: drone_0 is ") and lines[-1].startswith("tick 9: ")
    with open_episode(loop.out / "loop_main_s0.mcap") as ep:
        assert [a["action"]["type"] for a in ep.tick(1)["/actions"]["actions"]] == ["goto"]


def test_example_drone_coverage_policy_compares_with_hovering_drones(tmp_path):
    small = ["--set", "map.size_m=300", "--set", "agents.vehicles.count=2", "--set", "agents.rsus.count=0",
             "--set", "traffic.density_veh_per_km=20", "--set", "sensors.vehicle.lidar.channels=16",
             "--set", "sensors.drone.lidar.channels=16"]
    r = subprocess.run([sys.executable, str(REPO / "examples/drone_coverage_policy.py"), "--duration", "0.6",
                        "--image-scale", "0.1", "--out", str(tmp_path), *small],
                       cwd=REPO, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    shares = {line.split()[0]: float(line.split()[2].rstrip("%")) for line in r.stdout.splitlines()
              if line.strip().startswith(("hovering", "coverage"))}
    assert set(shares) == {"hovering", "coverage"} and all(0.0 <= v <= 100.0 for v in shares.values())
    with open_episode(tmp_path / "policy/episode.mcap") as policy, open_episode(tmp_path / "hover/episode.mcap") as h:
        assert "/actions" in policy.topics and "/actions" not in h.topics
        assert policy.n_ticks == h.n_ticks == 3 and any(t.endswith("/visibility") for t in policy.topics)


def test_repeated_client_names_are_bad_input(tmp_path):
    (tmp_path / "s.yaml").write_text(SCENARIO)
    r = run_cli("run", str(tmp_path / "s.yaml"), "--clients", "a,b,a", "--out", str(tmp_path))
    assert r.returncode == 2
    assert "clients" in r.stderr and "client names must be unique; repeated: a" in r.stderr
    assert "Traceback" not in r.stderr


# -- validation on arrival, no processes ------------------------------------------------------------------

CTX = ActionContext(vehicles=frozenset({"vehicle_0"}), drones={"drone_0": 15.0},
                    bounds_m=(-100.0, -100.0, 100.0, 100.0), max_lanes=2, edges=frozenset({"e1", "e2"}))


@pytest.mark.parametrize(("action", "names"), [
    ({"type": "goto", "agent": "drone_3", "position_m": [0, 0], "altitude_m": 30, "speed_mps": 5}, "no drone drone_3"),
    ({"type": "goto", "agent": "drone_0", "position_m": [500, 0], "altitude_m": 30, "speed_mps": 5}, "outside the map"),
    ({"type": "goto", "agent": "drone_0", "position_m": [0, 0], "altitude_m": 30, "speed_mps": 20}, "max_speed_mps 15"),
    ({"type": "goto", "agent": "drone_0", "position_m": [0, 0], "altitude_m": 1, "speed_mps": 5}, "altitude_m"),
    ({"type": "set_speed", "agent": "vehicle_0", "speed_mps": -1}, "speed_mps"),
    ({"type": "set_speed", "agent": "vehicle_4", "speed_mps": 3}, "no connected vehicle vehicle_4"),
    ({"type": "set_speed", "agent": "drone_0", "speed_mps": 3}, "not drones"),
    ({"type": "land", "agent": "rsu_0"}, "for drones, not rsus"),
    ({"type": "change_lane", "agent": "vehicle_0", "lane_index": 2}, "lane_index 2"),
    ({"type": "change_target", "agent": "vehicle_0", "edge": "nowhere"}, "'nowhere' is not in the network"),
    ({"type": "escort", "agent": "drone_0", "target": "vehicle_7"}, "escort target vehicle_7"),
    ({"type": "set_speed", "agent": "vehicle_0", "speed_mps": 3, "colour": "red"}, "colour"),
    ({"type": "fly", "agent": "drone_0"}, "fly"),
])
def test_bad_actions_are_refused_naming_agent_and_problem(action, names):
    with pytest.raises(ActionRejected, match="actions\\[1\\]") as err:
        check_actions([{"type": "land", "agent": "drone_0"}, action], CTX)
    assert names in str(err.value)


def test_good_actions_pass_with_defaults_filled_in():
    ok = check_actions([{"type": "land", "agent": "drone_0"}, {"type": "set_speed", "agent": "vehicle_0",
                                                                 "speed_mps": None}], CTX)
    assert [a.type for a in ok] == ["land", "set_speed"] and ok[0].speed_mps == 1.0
