"""Pictures of the traffic lights and signs in the cameras (docs/img/assets_street_furniture.png).

    PYTHONPATH=. .venv/bin/python benchmarks/street_furniture.py docs/img/assets_street_furniture.png

Top row: a vehicle camera 25 m before a signal head of a small urban town, its lights in their programs'
first phase (no SUMO), by day, at dusk and at night. Bottom row: a give-way sign and a speed-limit sign
of a suburban town from 12 m, by day, at dusk and at night.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
from cosim.sensors.suite import SensorSuite

from cosim.assemble import traffic_lights
from cosim.geometry import quat_from_rpy
from cosim.scenario import load_scenario_data
from cosim.snapshot import AgentState, WorldSnapshot
from cosim.world import build_world
from cosim.world.traffic_lights import first_phases, signal_heads
from cosim.world.traffic_signs import traffic_signs

LIGHTINGS = ("day", "dusk", "night")


def _scenario(kind: str, lighting: str):
    return load_scenario_data({
        "name": "furniture", "seed": 3, "duration_s": 1, "map": {"kind": kind, "size_m": 400},
        "environment": {"lighting": lighting},
        "agents": {"vehicles": {"count": 1}, "rsus": {"count": 0}, "drones": []},
        "sensors": {"vehicle": {"lidar": None, "gnss": None, "imu": None,
                                "cameras": [{"name": "front", "width": 400, "height": 250, "fov_deg": 50,
                                             "mount": {"xyz_m": [0.0, 0.0, 1.5]}}]}},
    })


def _view(world, lighting: str, kind: str, xy, yaw: float, distance: float, side: float, pitch: float):
    """The front camera of a vehicle ``distance`` m before (x, y) (up the facing ``yaw``), ``side`` m left of
    the way it drives (towards the thing)."""
    f, left = np.array([np.cos(yaw), np.sin(yaw)]), np.array([np.sin(yaw), -np.cos(yaw)])
    pos = np.asarray(xy) + distance * f + side * left
    agent = AgentState("vehicle_0", "vehicle", (float(pos[0]), float(pos[1]), 0.0),
                       quat_from_rpy(0.0, pitch, yaw + np.pi))
    snap = WorldSnapshot(0, 0, (), (agent,), traffic_lights(world, first_phases(world.net_xml)))
    with SensorSuite(_scenario(kind, lighting).scenario, world) as suite:
        return suite.render(snap, np.random.default_rng(0)).agents["vehicle_0"].cameras["front"].rgb


def main(out: Path) -> None:
    from PIL import Image

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        urban = build_world(_scenario("urban", "day"), Path(tmp) / "u")
        head = signal_heads(urban.net_xml)[3]
        rows.append([_view(urban, lt, "urban", head.center_m[:2], head.yaw_rad, 25.0, 1.5, -0.12)
                     for lt in LIGHTINGS])
        suburban = build_world(_scenario("suburban", "day"), Path(tmp) / "s")
        signs = traffic_signs(suburban.net_xml)
        gw = next(s for s in signs if s.kind == "give_way")
        sl = next(s for s in signs if s.kind == "speed_limit")
        rows.append([np.concatenate([_view(suburban, lt, "suburban", s.xy, s.yaw_rad, 14.0, 2.65, -0.05)[:, 150:400]
                                     for s in (gw, sl)], axis=1)[:, 50:450] for lt in LIGHTINGS])
    grid = np.concatenate([np.concatenate(r, axis=1) for r in rows], axis=0)
    Image.fromarray(grid).save(out, optimize=True)
    print(f"wrote {out}")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path, help="the PNG to write")
    main(ap.parse_args().out)
