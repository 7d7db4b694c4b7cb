"""What a shipped scenario's data is worth: empty camera frames and stopped traffic, per scenario.

    PYTHONPATH=. .venv/bin/python benchmarks/data_quality.py [--scenarios NAME ...] [--image-scale 0.25]
        [--traffic-s 120] [--no-cameras] [--set KEY=VALUE]

Per shipped scenario (``cosim.scenario.loader.shipped_scenarios``), two measurements:

- Empty camera frames: the episode is run as shipped (its duration, seed, agents, events) with every camera
  reduced to its ``instance`` output at ``--image-scale`` of its size, no LiDAR, no BEV, no sun shadows and no
  surface detail; these change neither what stands where nor which pixels show which object, only how finely.
  For every RSU and connected-vehicle camera at every tick, the frame is empty when the agent's
  ``/<agent>/visibility`` message counts no pixel of any labelled object (track) in that camera. At low
  resolution a far object smaller than one pixel is missed, so the shares are upper bounds of the full
  resolution's shares.
- Traffic: SUMO alone (``cosim.traffic.sumo_sim.TrafficSim``, no sensors) over ``--traffic-s`` seconds at the
  scenario's tick rate. ``stopped max``: the largest share, over the ticks, of the vehicles on the map (road
  users of SUMO's vehicle model; pedestrians, parked cars and event obstacles not counted) moving slower than
  0.1 m/s; ``at 18 s``: that share at t = 18 s. ``standstill``: the longest time any connected vehicle
  stood still (below 0.1 m/s) without a break, and which one.

Prints one table row per scenario (Markdown) and, with ``--json FILE``, writes the numbers.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
from pathlib import Path
from typing import Any

log = logging.getLogger("data_quality")
STOPPED_MPS = 0.1  # [m/s] below this a road user counts as stopped


def low_res_cameras(loaded: Any, image_scale: float) -> Any:
    """``loaded`` with instance-only RSU and vehicle cameras at ``image_scale`` (the drones' are not counted: none),
    no LiDAR, BEV, sun shadows or surface detail."""
    from cosim.scenario.loader import load_scenario_data

    data = json.loads(json.dumps(loaded.resolved))
    sensors = data["sensors"]
    for kind in ("vehicle", "rsu", "drone"):
        sensors[kind]["lidar"] = None
        for cam in sensors[kind]["cameras"]:
            cam["outputs"] = ["instance"]
    sensors["drone"]["cameras"] = []
    sensors.update(image_scale=image_scale, bev=False, sun_shadows=False, surface_detail=False)
    data["comm"]["enabled"] = False
    out = load_scenario_data(data)
    return type(out)(out.scenario, loaded.source, out.resolved, loaded.base_dir)


def empty_frame_shares(loaded: Any, image_scale: float) -> dict[str, float]:
    """Share of RSU and connected-vehicle camera frames with no labelled object (see the module docstring)."""
    from cosim.io.reader import open_episode
    from cosim.runner import run_episode

    low = low_res_cameras(loaded, image_scale)
    frames = {"rsu": 0, "vehicle": 0}
    per_camera: dict[str, int] = {}
    empty = {"rsu": 0, "vehicle": 0}
    with tempfile.TemporaryDirectory(prefix="cosim-quality-") as tmp:
        result = run_episode(low, Path(tmp))
        with open_episode(result.path) as ep:
            agents = [a for a in ep.agents if a.startswith(("rsu_", "vehicle_"))]
            rigs = {"rsu": low.scenario.sensors.rsu, "vehicle": low.scenario.sensors.vehicle}
            cams = {a: [c.name for c in rigs[a.split("_")[0]].cameras] for a in agents}
            topics = [f"/{a}/visibility" for a in agents]
            for tick in ep.ticks(topics):
                for a in agents:
                    kind = a.split("_")[0]
                    vis = tick.get(f"/{a}/visibility") or {}
                    seen = {c for o in vis.get("objects", []) for c, n in (o.get("pixels") or {}).items() if n > 0}
                    frames[kind] += len(cams[a])
                    empty[kind] += sum(c not in seen for c in cams[a])
                    for c in cams[a]:
                        per_camera[f"{a}/{c}"] = per_camera.get(f"{a}/{c}", 0) + (c not in seen)
    log.info("empty frames per camera: %s", {k: v for k, v in sorted(per_camera.items()) if v})
    return {f"{k}_empty": empty[k] / frames[k] if frames[k] else float("nan") for k in frames}


def traffic_shares(loaded: Any, duration_s: float) -> dict[str, Any]:
    """Stopped share (largest over the ticks, and at 18 s) and the longest connected-vehicle standstill."""
    import libsumo

    from cosim.traffic.sumo_sim import TrafficSim
    from cosim.world import build_world

    sc = loaded.scenario
    n_ticks = round(duration_s * sc.tick_hz)
    worst = at_18 = 0.0
    still_since: dict[str, float] = {}
    longest, who = 0.0, ""
    with tempfile.TemporaryDirectory(prefix="cosim-quality-") as tmp:
        world = build_world(loaded, Path(tmp) / "world")
        with TrafficSim(sc, world, Path(tmp) / "sumo") as sim:
            for k in range(n_ticks + 1):
                t = k / sc.tick_hz
                states = sim.step_to(k * sc.tick_ns)
                on_map = set(libsumo.vehicle.getIDList())
                road = [s for s in states if s.cls != "pedestrian" and s.sumo_id in on_map]
                share = sum(s.speed_mps < STOPPED_MPS for s in road) / max(1, len(road))
                worst = max(worst, share)
                if abs(t - 18.0) < 1e-9:
                    at_18 = share
                for s in road:
                    if s.agent_id is None and not s.sumo_id.startswith("vehicle_"):
                        continue
                    if s.speed_mps < STOPPED_MPS:
                        since = still_since.setdefault(s.sumo_id, t)
                        if t - since > longest:
                            longest, who = t - since, s.sumo_id
                    else:
                        still_since.pop(s.sumo_id, None)
    return {"stopped_max": worst, "stopped_at_18s": at_18, "standstill_s": longest, "standstill_who": who}


def main(argv: list[str] | None = None) -> int:
    from cosim.scenario.loader import load_scenario, shipped_scenarios

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenarios", nargs="*", help="shipped scenario names (default: all)")
    p.add_argument("--image-scale", type=float, default=0.25)
    p.add_argument("--traffic-s", type=float, default=120.0)
    p.add_argument("--no-cameras", action="store_true", help="traffic numbers only")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override (as cosim run --set)")
    p.add_argument("--json", type=Path, help="also write the numbers here")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
    log.setLevel(logging.INFO)
    shipped = dict(shipped_scenarios())
    names = args.scenarios or sorted(shipped)
    rows: dict[str, dict[str, Any]] = {}
    print("| scenario | RSU frames empty | vehicle frames empty | stopped max | stopped at 18 s | "
          "longest standstill |")
    print("|---|---:|---:|---:|---:|---|")
    for name in names:
        loaded = load_scenario(shipped[name], args.set)
        row: dict[str, Any] = {}
        if not args.no_cameras:
            row.update(empty_frame_shares(loaded, args.image_scale))
        row.update(traffic_shares(loaded, args.traffic_s))
        rows[name] = row
        cam = (f"{row['rsu_empty']:.1%} | {row['vehicle_empty']:.1%}" if "rsu_empty" in row else "- | -")
        print(f"| {name} | {cam} | {row['stopped_max']:.0%} | {row['stopped_at_18s']:.0%} | "
              f"{row['standstill_s']:.1f} s ({row['standstill_who']}) |", flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1, sort_keys=True))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
