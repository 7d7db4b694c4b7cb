"""Dynamic drone positioning: the drones fly to the connected vehicles' objects that no agent sees.

Runs a scenario twice with ``cosim run`` (sensors on, so every agent's ``/visibility`` exists), with the
same hovering drones both times: once left alone, once commanded by this policy as a closed-loop client.
It then prints, for both episodes, the share of the connected vehicles' objects (actors within
``RADIUS_M`` of a connected vehicle) that at least one agent sees (LiDAR returns or camera pixels), per
tick and on average, measured from the episode files by the same code. ``cosim coverage EP.mcap``
(docs/evaluation.md) scores either episode per ego vehicle and evaluation area, by agent type.

    python examples/drone_coverage_policy.py [--scenario town_urban_day_clear] [--duration 60] \
        [--image-scale 0.1] [--out out/coverage]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np

from cosim import cli_args
from cosim.client import actions, connect
from cosim.io import open_episode
from cosim.transport import free_loopback_endpoint

RADIUS_M = 50.0  # [m] an actor this close to a connected vehicle is one of "its" objects
ALTITUDE_M = 40.0  # [m] above ground (raised by the drone's clearance planning where needed)
SPEED_MPS = 12.0
REPLAN_TICKS = 5  # a new waypoint per drone once a second at 5 Hz
SPREAD_M = 40.0  # [m] two drones never get goals closer than this
VISIBILITY = "/*/visibility"


def objects_of_interest(labels) -> dict[int, np.ndarray]:
    """Track id -> (x, y) of every actor near a connected vehicle (drones and the vehicles themselves left out)."""
    ego = [labels.centers_m[i, :2] for i, a in enumerate(labels.agent_ids) if a and a.startswith("vehicle_")]
    out = {}
    for i, tid in enumerate(labels.track_ids):
        if labels.agent_ids[i] is not None or labels.classes[i] == "drone":
            continue
        xy = labels.centers_m[i, :2]
        if any(np.hypot(*(xy - e)) <= RADIUS_M for e in ego):
            out[int(tid)] = xy
    return out


def seen_tracks(tick, agents: list[str]) -> set[int]:
    """Tracks that at least one agent sees at this tick."""
    seen = set()
    for agent in agents:
        vis = tick.get(f"/{agent}/visibility")
        for o in (vis or {}).get("objects", []):
            if o["lidar_points"] > 0 or any(n > 0 for n in o["pixels"].values()):
                seen.add(o["track_id"])
    return seen


def plan(labels, unseen: dict[int, np.ndarray], drones: list[str]) -> list[dict]:
    """Greedy: each drone in turn takes the nearest unseen object away from the goals already taken."""
    where = {a["agent_id"]: np.array(a["position_m"][:2]) for a in labels.agents}
    goals: list[np.ndarray] = []
    out = []
    for d in drones:
        free = [xy for xy in unseen.values() if all(np.hypot(*(xy - g)) > SPREAD_M for g in goals)]
        if not free:
            continue
        goal = min(free, key=lambda xy: float(np.hypot(*(xy - where[d]))))
        goals.append(goal)
        out.append(actions.goto(d, float(goal[0]), float(goal[1]), altitude_m=ALTITUDE_M, speed_mps=SPEED_MPS))
    return out


def run_policy(name: str, endpoint: str, prefix: str) -> None:
    with connect(name, endpoint=endpoint, prefix=prefix, topics=["/labels/objects", VISIBILITY]) as client:
        agents = client.episode["agents"]
        drones = [a for a in agents if a.startswith("drone_")]
        for obs in client.ticks():
            if obs.index % REPLAN_TICKS or obs.last:
                continue  # the tick is answered with no actions
            labels = obs.labels
            seen = seen_tracks(obs, agents)
            unseen = {t: xy for t, xy in objects_of_interest(labels).items() if t not in seen}
            client.act(plan(labels, unseen, drones))


def coverage(path: Path) -> tuple[list[float], list[float]]:
    """Per tick: share of the connected vehicles' objects seen by at least one agent, and by a drone."""
    by_any, by_drones = [], []
    with open_episode(path) as ep:
        drones = [a for a in ep.agents if a.startswith("drone_")]
        for tick in ep.ticks(["/labels/objects", VISIBILITY]):
            interest = set(objects_of_interest(tick.labels))
            if interest:
                by_any.append(len(interest & seen_tracks(tick, ep.agents)) / len(interest))
                by_drones.append(len(interest & seen_tracks(tick, drones)) / len(interest))
    return by_any, by_drones


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default="town_urban_day_clear")
    p.add_argument("--duration", type=cli_args.positive_float, default=60.0, help="simulated seconds")
    p.add_argument("--image-scale", type=cli_args.positive_float, default=0.1,
                   help="sensors.image_scale (visibility needs cameras)")
    p.add_argument("--out", default="out/coverage", type=cli_args.output_folder)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="more scenario overrides")
    args = p.parse_args()
    from cosim.scenario import load_scenario

    n_drones = len(load_scenario(args.scenario).scenario.agents.drones)
    hover = "agents.drones=[" + ", ".join(["{strategy: hover, altitude_m: 60}"] * n_drones) + "]"
    common = [sys.executable, "-m", "cosim.cli", "run", args.scenario, "--duration", str(args.duration), "-q",
              "--set", f"sensors.image_scale={args.image_scale}", "--set", hover, "--set", "output.name=episode"]
    for kv in args.set:
        common += ["--set", kv]
    out = Path(args.out)
    subprocess.run([*common, "--out", str(out / "hover")], check=True, stdout=subprocess.DEVNULL)
    endpoint, prefix = free_loopback_endpoint(), "cosim/coverage-policy"
    run = subprocess.Popen([*common, "--out", str(out / "policy"), "--clients", "policy", "--listen", endpoint,
                            "--prefix", prefix], stdout=subprocess.DEVNULL)
    try:
        run_policy("policy", endpoint, prefix)
    finally:
        status = run.wait()
    if status != 0:
        print(f"cosim run failed with status {status}", file=sys.stderr)
        return 1
    (base, base_d), (policy, policy_d) = coverage(out / "hover" / "episode.mcap"), coverage(out / "policy" /
                                                                                          "episode.mcap")
    print(f"scenario {args.scenario}, {args.duration:g} s, {n_drones} drones, image scale {args.image_scale:g}")
    print("objects of the connected vehicles (mean over ticks)  seen by at least one agent | seen by a drone:")
    print(f"  hovering drones   {np.mean(base):.1%} | {np.mean(base_d):.1%}  ({len(base)} ticks)")
    print(f"  coverage policy   {np.mean(policy):.1%} | {np.mean(policy_d):.1%}  ({len(policy)} ticks)")
    print(f"  difference        {np.mean(policy) - np.mean(base):+.1%} | {np.mean(policy_d) - np.mean(base_d):+.1%}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
