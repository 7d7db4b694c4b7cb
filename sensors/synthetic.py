"""A small synthetic world and snapshot with known geometry, for tests, pictures and benchmarks.

Layout (map frame, metres): terrain over [-L, L]^2 with its top at z = 0; a road cross (x and y
axes, 14 m wide, top at 0.02 m) with dashed centre lines; sidewalks; buildings in the four quadrants
(one L-shaped, i.e. concave); poles and street lights (pole + lamp arm reaching over the road
towards y = 6.2 m) along the roads.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from cosim.geometry import quat_from_rpy
from cosim.scenario.model import AgentsSpec, DroneSpec, RsuAgents, Scenario, VehicleAgents
from cosim.snapshot import Actor, AgentState, WorldSnapshot
from cosim.world.types import Prism, StaticLayout, World

ROAD_HALF_M = 7.0
ROAD_TOP_M = 0.02


def _rect(x0: float, y0: float, x1: float, y1: float) -> tuple[tuple[float, float], ...]:
    return ((x0, y0), (x1, y0), (x1, y1), (x0, y1))


def synthetic_scenario(*, vehicles: int = 1, rsus: int = 0, drones: Sequence[DroneSpec] = (), name: str = "t",
                       **overrides: Any) -> Scenario:
    """A scenario for the synthetic worlds: ``vehicles`` connected vehicles, ``rsus`` RSUs and the drone specs
    ``drones`` (none by default); any other :class:`Scenario` field (``sensors``, ``environment``, ``seed``,
    ``comm``, ...) as a keyword."""
    agents = AgentsSpec(vehicles=VehicleAgents(count=vehicles), rsus=RsuAgents(count=rsus), drones=list(drones))
    return Scenario(name=name, agents=agents, **overrides)


def synthetic_world(half_m: float = 150.0) -> World:
    """The layout described in the module docstring."""
    L, r = half_m, ROAD_HALF_M
    prisms: list[Prism] = [Prism("terrain", _rect(-L, -L, L, L), -0.5, 0.0)]
    prisms.append(Prism("road", _rect(-L, -r, L, r), 0.0, ROAD_TOP_M))
    prisms.append(Prism("road", _rect(-r, r, r, L), 0.0, ROAD_TOP_M))
    prisms.append(Prism("road", _rect(-r, -L, r, -r), 0.0, ROAD_TOP_M))
    for x in range(-int(L) + 5, int(L) - 5, 10):
        if abs(x) > r + 2:
            prisms.append(Prism("lane_marking", _rect(x, -0.08, x + 4, 0.08), ROAD_TOP_M, ROAD_TOP_M + 0.005))
            prisms.append(Prism("lane_marking", _rect(-0.08, x, 0.08, x + 4), ROAD_TOP_M, ROAD_TOP_M + 0.005))
    sw = 3.0
    for sx in (-1, 1):
        for sy in (-1, 1):
            x0, x1 = sorted((sx * r, sx * L))
            y0, y1 = sorted((sy * r, sy * (r + sw)))
            prisms.append(Prism("sidewalk", _rect(x0, y0, x1, y1), 0.0, 0.15))
            x0, x1 = sorted((sx * r, sx * (r + sw)))
            y0, y1 = sorted((sy * (r + sw), sy * L))
            prisms.append(Prism("sidewalk", _rect(x0, y0, x1, y1), 0.0, 0.15))
    inst = 1_000_000
    buildings = [
        _rect(20, 20, 45, 40),
        ((20.0, -20.0), (20.0, -60.0), (60.0, -60.0), (60.0, -50.0), (32.0, -50.0), (32.0, -20.0))[::-1],
        _rect(-50, 15, -20, 60),
        _rect(-70, -45, -25, -20),
        _rect(70, 20, 100, 50),
        _rect(-120, 30, -90, 80),
    ]
    heights = [18.0, 12.0, 30.0, 9.0, 22.0, 15.0]
    for fp, h in zip(buildings, heights, strict=True):
        prisms.append(Prism("building", tuple(fp) if _ccw(fp) else tuple(fp[::-1]), 0.0, h, inst))
        inst += 1
    for k, x in enumerate(range(-60, 61, 30)):
        if x == 0:
            continue
        prisms.append(Prism("street_light", _octagon(x, r + 1.0, 0.15), 0.0, 8.0, inst))
        prisms.append(Prism("street_light", _rect(x - 0.12, r - 0.8, x + 0.12, r + 1.0), 7.7, 8.0, inst + 1))
        inst += 2
        prisms.append(Prism("pole", _octagon(x + 15, -(r + 1.0), 0.12), 0.0, 4.0 + k % 2, inst))
        inst += 1
    prisms.append(Prism("vegetation", _octagon(-40, -80, 3.0), 0.0, 6.0, 0))
    return World(
        map_kind="synthetic", net_xml=b"", routes_xml=b"", bounds_m=(-L, -L, L, L), junctions=(), rsus=(),
        layout=StaticLayout(tuple(prisms), 0.0), geo_origin=(37.3352, -121.8811, 20.0),
    )


def _ccw(fp) -> bool:
    s = 0.0
    for (x0, y0), (x1, y1) in zip(fp, fp[1:] + fp[:1], strict=True):
        s += x0 * y1 - x1 * y0
    return s > 0


def _octagon(cx: float, cy: float, radius: float) -> tuple[tuple[float, float], ...]:
    return tuple((cx + radius * math.cos(k * math.pi / 4), cy + radius * math.sin(k * math.pi / 4)) for k in range(8))


SIZES = {
    "car": (4.5, 1.9, 1.5), "van": (5.2, 2.0, 2.2), "truck": (8.5, 2.5, 3.4), "bus": (12.0, 2.6, 3.2),
    "motorcycle": (2.1, 0.8, 1.5), "bicycle": (1.8, 0.6, 1.7), "drone": (1.0, 1.0, 0.35),
    "pedestrian": (0.5, 0.6, 1.75), "static_obstacle": (0.4, 0.4, 0.7),
}


def actor(track: int, cls: str, x: float, y: float, yaw_deg: float = 0.0, z_ground: float = ROAD_TOP_M,
          agent_id: str | None = None, z: float | None = None) -> Actor:
    size = SIZES[cls]
    cz = z if z is not None else z_ground + size[2] / 2
    return Actor(track, cls, (x, y, cz), size, quat_from_rpy(0.0, 0.0, math.radians(yaw_deg)), (0.0, 0.0, 0.0),
                 agent_id)


def synthetic_snapshot(n_vehicles: int = 5, n_rsus: int = 5, n_drones: int = 5, tick: int = 0) -> WorldSnapshot:
    """A busy junction: background traffic of every class plus connected vehicles, RSUs and drones."""
    actors: list[Actor] = []
    agents: list[AgentState] = []
    track = 1
    classes = ["car", "van", "truck", "bus", "motorcycle", "bicycle"]
    for k in range(12):
        cls = classes[k % len(classes)]
        x = -90 + 16 * k
        lane = -3.5 if k % 2 else 3.5
        actors.append(actor(track, cls, x, lane, 0.0 if lane < 0 else 180.0))
        track += 1
    for k in range(6):
        cls = classes[(k + 2) % len(classes)]
        actors.append(actor(track, cls, 3.5 if k % 2 else -3.5, -70 + 25 * k, 90.0 if k % 2 else -90.0))
        track += 1
    for i in range(n_vehicles):
        x, y, yaw = -30.0 + 14 * i, -3.5 if i % 2 == 0 else 3.5, 0.0 if i % 2 == 0 else 180.0
        a = actor(track, "car", x, y, yaw, agent_id=f"vehicle_{i}")
        actors.append(a)
        agents.append(AgentState(f"vehicle_{i}", "vehicle", (x, y, ROAD_TOP_M), a.rotation, track_id=track))
        track += 1
    rsu_sites = [(9.5, 9.5, 225.0), (-9.5, -9.5, 45.0), (9.5, -9.5, 135.0), (-9.5, 9.5, -45.0), (40.0, 9.5, 180.0)]
    for i in range(n_rsus):
        x, y, yaw = rsu_sites[i % len(rsu_sites)]
        agents.append(AgentState(f"rsu_{i}", "rsu", (x, y, 7.0), quat_from_rpy(0, 0, math.radians(yaw))))
    for i in range(n_drones):
        x, y, z = -40.0 + 20 * i, 10.0 * ((i % 3) - 1), 40.0 + 8 * i
        yaw = math.radians(30 * i)
        q = quat_from_rpy(0.02, -0.03, yaw)
        a = Actor(track, "drone", (x, y, z), SIZES["drone"], q, (0.0, 0.0, 0.0), f"drone_{i}")
        actors.append(a)
        agents.append(AgentState(f"drone_{i}", "drone", (x, y, z), q, track_id=track,
                                 gimbal_rotation=quat_from_rpy(0.0, 0.0, yaw),
                                 angular_rate_radps=(0.01, -0.02, 0.05), specific_force_mps2=(0.1, 0.0, 9.81)))
        track += 1
    return WorldSnapshot(tick, tick * 200_000_000, tuple(actors), tuple(agents))


def world_snapshot(world: World, n_vehicles: int, n_drones: int, n_background: int, seed: int = 0,
                   tick: int = 0, speed_mps: float = 0.0) -> WorldSnapshot:
    """Actors and agents placed on a built world (benchmarks, pictures): vehicles on road polygons
    along their long axis, RSUs at ``world.rsus``, drones 40-80 m above junctions. Road users and
    drones move forward at ``speed_mps`` (drones at half of it)."""
    import numpy as np
    from matplotlib.path import Path as MplPath

    rng = np.random.default_rng(seed)
    roads = [p for p in world.layout.prisms if p.cls == "road"]
    roads.sort(key=lambda p: -_area(p.footprint))
    classes = ["car", "car", "car", "van", "truck", "bus", "motorcycle", "bicycle"]
    actors: list[Actor] = []
    agents: list[AgentState] = []
    taken: list[tuple[float, float]] = []
    track = 1
    n_total = n_vehicles + n_background
    tries = 0
    while len(actors) < n_total and roads and tries < 50 * n_total:
        tries += 1
        road = roads[int(rng.integers(0, min(len(roads), 40)))]
        fp = np.asarray(road.footprint)
        c = fp.mean(0)
        u, _, _ = np.linalg.svd(np.cov((fp - c).T))
        axis = u[:, 0]
        along = (fp - c) @ axis
        lateral = rng.choice([-1.7, 1.7])
        pos = c + axis * rng.uniform(along.min() + 4, along.max() - 4) + np.array([-axis[1], axis[0]]) * lateral
        if not MplPath(fp).contains_point(pos) or any(math.hypot(pos[0] - x, pos[1] - y) < 9 for x, y in taken):
            continue
        taken.append((float(pos[0]), float(pos[1])))
        yaw = math.degrees(math.atan2(axis[1], axis[0])) + (0.0 if lateral < 0 else 180.0)
        connected = len(actors) < n_vehicles
        cls = "car" if connected else classes[int(rng.integers(0, len(classes)))]
        aid = f"vehicle_{len(actors)}" if connected else None
        a = actor(track, cls, float(pos[0]), float(pos[1]), yaw, z_ground=road.z1_m, agent_id=aid)
        v = (speed_mps * math.cos(math.radians(yaw)), speed_mps * math.sin(math.radians(yaw)), 0.0)
        a = Actor(a.track_id, a.cls, a.center_m, a.size_m, a.rotation, v, a.agent_id)
        actors.append(a)
        if connected:
            agents.append(AgentState(aid, "vehicle", (a.center_m[0], a.center_m[1], road.z1_m), a.rotation, v,
                                     track_id=track, specific_force_mps2=(0.2, 0.0, 9.81)))
        track += 1
    for r in world.rsus:
        agents.append(AgentState(r.agent_id, "rsu", r.position_m, quat_from_rpy(0.0, 0.0, r.yaw_rad)))
    spots = [j.position_m for j in world.junctions] or [tuple(np.asarray(roads[0].footprint).mean(0))]
    for i in range(n_drones):
        x, y = spots[(i * 3) % len(spots)]
        z = 40.0 + 10.0 * (i % 5)
        yaw = rng.uniform(-math.pi, math.pi)
        q = quat_from_rpy(0.0, 0.0, yaw)
        v = (0.5 * speed_mps * math.cos(yaw), 0.5 * speed_mps * math.sin(yaw), 0.0)
        actors.append(Actor(track, "drone", (x, y, z), SIZES["drone"], q, v, f"drone_{i}"))
        agents.append(AgentState(f"drone_{i}", "drone", (x, y, z), q, v, track_id=track, gimbal_rotation=q))
        track += 1
    return WorldSnapshot(tick, tick * 200_000_000, tuple(actors), tuple(agents))


def _area(fp) -> float:
    s = 0.0
    for (x0, y0), (x1, y1) in zip(fp, (*fp[1:], fp[0]), strict=True):
        s += x0 * y1 - x1 * y0
    return abs(s) / 2
