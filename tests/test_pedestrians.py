"""Pedestrians (SUMO's pedestrian model), the jaywalk and cut_in events, on real SUMO; one episode with sensors."""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest
from cosim.sensors.synthetic import synthetic_scenario

from cosim.scenario import load_scenario_data

EVENTS = [
    {"kind": "jaywalk", "at_s": 1.0, "ahead_of": "vehicle_0", "ahead_m": 30},
    {"kind": "cut_in", "at_s": 1.0, "ahead_of": "vehicle_3", "gap_m": 6},
]
# vehicle_0 and vehicle_1 start on the same inner edge and wait ~13 s at its red light 6 m from the edge's end, where
# a cut-in has no room ahead (it would stay 'starting'); vehicle_3 drives on a free edge at 1 s


def _scenario(**extra):
    return load_scenario_data({
        "name": "peds", "seed": 5, "duration_s": 16, "map": {"kind": "urban", "size_m": 300},
        "traffic": {"density_veh_per_km": 20},
        "pedestrians": {"density_per_km": 20, "jaywalk_share": 0.3, "jaywalk_every_s": 8},
        "agents": {"vehicles": {"count": 4}, "rsus": {"count": 0}, "drones": []}, "events": EVENTS, **extra,
    })


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """16 s of a small town with pedestrians, a jaywalk and a cut-in: per tick the states, the event records,
    each pedestrian's place kind and SUMO lane, and the cut-in's and its connected vehicle's lanes."""
    import libsumo

    from cosim.traffic import TrafficSim
    from cosim.world import build_world

    tmp = tmp_path_factory.mktemp("peds")
    loaded = _scenario()
    sc = loaded.scenario
    world = build_world(loaded, tmp / "w")
    sim = TrafficSim(sc, world, tmp / "s")
    ticks = []
    try:
        jay = set(sim.pedestrians.jaywalkers)
        for k in range(sc.n_ticks):
            states = sim.step_to(k * sc.tick_ns)
            peds = sim.pedestrians
            places = {s.sumo_id: (peds.where(s.sumo_id), "" if s.sumo_id in peds.crossings else
                                  libsumo.person.getLaneID(s.sumo_id)) for s in states if s.cls == "pedestrian"}
            v = libsumo.vehicle
            lanes = {vid: (v.getRoadID(vid), v.getLaneIndex(vid), v.getLanePosition(vid), v.getLength(vid))
                     for vid in v.getIDList() if vid in ("vehicle_3", "ev1_0")}
            ticks.append((states, {r["id"]: r for r in sim.events()}, places, lanes))
        shapes = {ln: (libsumo.lane.getShape(ln), libsumo.lane.getWidth(ln)) for ln in libsumo.lane.getIDList()
                  if tuple(libsumo.lane.getAllowed(ln)) == ("pedestrian",)}
        junctions = {j: libsumo.junction.getShape(j) for j in libsumo.junction.getIDList()}
    finally:
        sim.close()
    return {"ticks": ticks, "jaywalkers": jay, "world": world, "shapes": shapes, "junctions": junctions}


def _dist_to_polyline(p, shape) -> float:
    best = math.inf
    for a, b in itertools.pairwise(shape):
        a, b = np.asarray(a), np.asarray(b)
        d = b - a
        f = float(np.clip(np.dot(p - a, d) / max(float(np.dot(d, d)), 1e-12), 0.0, 1.0))
        best = min(best, float(np.linalg.norm(p - (a + f * d))))
    return best


def _inside(p, poly, tol_m: float = 0.5) -> bool:
    """Inside the polygon or within ``tol_m`` of its outline."""
    from matplotlib.path import Path as MplPath

    closed = [*poly, poly[0]]
    return bool(MplPath(np.asarray(poly)).contains_point(p)) or _dist_to_polyline(p, closed) <= tol_m


@pytest.mark.integration
def test_pedestrians_stay_on_sidewalks_and_crossings(run):
    """Every pedestrian but a jaywalker is, on every tick, on a sidewalk, a crossing or a walking area, and its
    box centre lies on a pedestrian surface (:func:`_on_walkable`; on a walking area: or inside its junction),
    never inside a road lane's outline between junctions. Jaywalkers do
    step onto the road."""
    from cosim.world.layout import edge_road_polygon
    from cosim.world.network import read_network

    net = read_network(run["world"].net_xml)
    roads = [p for e in net.road_edges() if (p := edge_road_polygon(e)) is not None]
    seen = {"sidewalk": 0, "crossing": 0, "walkingarea": 0}
    jay_on_road = 0
    for states, _, places, _ in run["ticks"]:
        for s in states:
            if s.cls != "pedestrian":
                continue
            kind, lane = places[s.sumo_id]
            p = np.array(s.center_m[:2])
            if s.sumo_id in run["jaywalkers"] or s.sumo_id.startswith("ev"):
                jay_on_road += kind == "road"
                continue
            assert kind in seen, (s.sumo_id, kind, lane)
            seen[kind] += 1
            if kind == "walkingarea":
                # SUMO walks a straight path between a walking area's entries; at a bend of the road (a corner
                # junction of two edges) that path leaves the area's outline across the junction's surface
                junction = lane[1:].rsplit("_", 2)[0]
                assert (_on_walkable(p, lane, run["shapes"]) or _inside(p, run["junctions"][junction], 0.5)), \
                    (s.sumo_id, lane, p)
            else:
                assert _on_walkable(p, lane, run["shapes"]), (s.sumo_id, lane, p)
            assert not any(_inside_strict(p, poly) for poly in roads), (s.sumo_id, lane, p)
    assert seen["sidewalk"] > 1000 and seen["crossing"] > 0 and seen["walkingarea"] > 0, seen
    assert jay_on_road > 0


def _on_walkable(p, lane: str, shapes) -> bool:
    """On the surface of ``lane`` (SUMO's place for the person) or of a pedestrian lane next to it: within
    0.5 m of a sidewalk's or crossing's strip, inside a walking area's outline or within 1 m of it (SUMO's
    paths over a walking area are curves between its entries that may leave the outline a little)."""
    def on(ln: str) -> bool:
        shape, width = shapes[ln]
        if ":" in ln and "_w" in ln:
            return _inside(p, shape, 1.0)
        return _dist_to_polyline(p, shape) <= width / 2 + 0.5

    if on(lane):
        return True
    near = [ln for ln, (shape, _) in shapes.items() if min(math.dist(p, q) for q in shape) < 30.0]
    return any(on(ln) for ln in near)  # entering or leaving it: SUMO names the lane its front is on


def _inside_strict(p, poly) -> bool:
    from matplotlib.path import Path as MplPath

    return bool(MplPath(np.asarray(poly)).contains_point(p, radius=-0.05))  # 5 cm inside the outline


@pytest.mark.integration
def test_pedestrians_walk_with_gait_phase_and_class_size(run):
    from cosim.traffic.pedestrians import SIZE_M
    from sensors.synthetic import SIZES

    assert SIZES["pedestrian"] == SIZE_M
    first = {s.sumo_id: s for s in run["ticks"][0][0] if s.cls == "pedestrian"}
    last = {s.sumo_id: s for s in run["ticks"][-1][0] if s.cls == "pedestrian"}
    assert len(first) >= 20 and set(first) <= set(last)  # everyone stays for the whole episode, same id
    moved = [p for p in first if math.dist(first[p].center_m[:2], last[p].center_m[:2]) > 5.0]
    assert len(moved) > 0.5 * len(first)
    phases = {round(s.gait_phase, 3) for states, *_ in run["ticks"] for s in states if s.sumo_id == moved[0]}
    assert len(phases) > 10 and all(0.0 <= p < 1.0 for p in phases)


@pytest.mark.integration
def test_jaywalk_event_crosses_the_road_in_front_of_the_vehicle(run):
    """The event's pedestrian walks straight over the road lanes from one kerb to the other, at its speed."""
    from cosim.world.layout import edge_road_polygon
    from cosim.world.network import read_network

    net = read_network(run["world"].net_xml)
    rec = run["ticks"][-1][1]["event_0"]
    assert rec["state"] == "active" and rec["pedestrians"] == ["ev0_ped"], rec
    track = [(k, s) for k, (states, *_) in enumerate(run["ticks"]) for s in states if s.sumo_id == "ev0_ped"]
    assert track and track[0][1].speed_mps == pytest.approx(1.4)
    edge = net.edges[rec["edge"]]
    road = edge_road_polygon(edge)
    on_road = [k for k, s in track if _inside_strict(np.array(s.center_m[:2]), road)]
    assert len(on_road) >= 5
    # it started at the kerb of vehicle_0's route 30 m ahead of it (along the route, which may turn; the kerb
    # of a 3-lane avenue is up to about 12 m from a lane)
    states0 = {s.sumo_id: s for s in run["ticks"][track[0][0]][0]}
    assert math.dist(states0["vehicle_0"].center_m[:2], track[0][1].center_m[:2]) < 30.0 + 12.0 + 15.0
    # cars see it (a hidden standing vehicle in its place on each lane) and stop: vehicle_0, 30 m away when it
    # stepped off, never touches it (a car right there when it steps onto a lane may: it cannot stop)
    from cosim.traffic.metrics import bev_corners, convex_overlap_area

    hits = [(k, s.sumo_id) for k, (states, *_) in enumerate(run["ticks"]) for ped in states if ped.sumo_id == "ev0_ped"
            for s in states if s.cls not in ("pedestrian", "static_obstacle")
            and convex_overlap_area(bev_corners(s), bev_corners(ped)) > 0.0]
    assert hits_by(hits, "vehicle_0") == [], hits


def hits_by(hits, vid):
    return [h for h in hits if h[1] == vid]


@pytest.mark.integration
def test_cut_in_ends_in_the_connected_vehicles_lane_ahead_at_a_small_gap(run):
    rec = run["ticks"][-1][1]["event_1"]
    assert rec["state"] == "active" and rec["vehicles"] == ["ev1_0"], rec
    beside = merged = None
    for k, (_, _, _, lanes) in enumerate(run["ticks"]):
        if "ev1_0" not in lanes or "vehicle_3" not in lanes:
            continue
        (r0, l0, p0, _), (r1, l1, p1, len1) = lanes["vehicle_3"], lanes["ev1_0"]
        if r0 == r1 and l0 != l1 and beside is None:
            beside = k
        if beside is not None and r0 == r1 and l0 == l1:
            merged = (k, p1 - len1 - p0)  # the cutting car's rear to the connected vehicle's front
            break
    assert beside is not None and merged is not None, (beside, merged)
    assert 0.5 < merged[1] <= 6 + 4.0, merged


def test_crossings_only_with_pedestrians(tmp_path: Path):
    """netconvert guesses crossings only when the scenario has pedestrians (others keep their network bytes)."""
    from cosim.world import build_world

    with_peds = build_world(_scenario(), tmp_path / "a")
    loaded = load_scenario_data({"name": "nopeds", "seed": 5, "duration_s": 16, "map": {"kind": "urban", "size_m": 300},
                                 "agents": {"vehicles": {"count": 2}, "rsus": {"count": 0}, "drones": []}})
    without = build_world(loaded, tmp_path / "b")
    assert b'function="crossing"' in with_peds.net_xml and b'function="crossing"' not in without.net_xml


@pytest.mark.parametrize(
    ("event", "path", "words"),
    [
        ({"kind": "cut_in", "at_s": 1, "position_m": [10, 10]}, "events.0.ahead_of", "cut_in needs ahead_of"),
        ({"kind": "jaywalk", "at_s": 1, "ahead_of": "vehicle_0", "speed_mps": 9}, "events.0.speed_mps", "4"),
        ({"kind": "cut_in", "at_s": 1, "ahead_of": "vehicle_0", "gap_m": 0.2}, "events.0.gap_m", "1"),
    ],
)
def test_bad_jaywalk_and_cut_in_name_key_path_and_line(tmp_path: Path, event, path, words):
    import yaml

    from cosim.errors import ScenarioError
    from cosim.scenario import load_scenario

    f = tmp_path / "s.yaml"
    f.write_text(yaml.safe_dump({"name": "x", "agents": {"vehicles": {"count": 1}}, "events": [event]}))
    with pytest.raises(ScenarioError) as err:
        load_scenario(f)
    import re

    assert path in str(err.value) and re.search(r"s\.yaml:\d+:", str(err.value)) and words in str(err.value), \
        str(err.value)


@pytest.mark.integration
def test_jaywalk_episode_escorted_vehicle_sees_the_pedestrian(tmp_path: Path):
    """A real episode (sensors at image scale 0.1): the jaywalker in front of the escorted vehicle lies in that
    vehicle's evaluation area and in the escort drone's visibility annotations, and every LiDAR return with
    a pedestrian's instance id lies inside that pedestrian's box grown by 0.1 m."""
    from cosim.eval.dataset import AREA_HALF_M
    from cosim.io import open_episode
    from tests.helpers import lidar_box_excess, run_cli

    r = run_cli("run", "scenarios/event_jaywalk.yaml", "--duration", "3.4", "--out", str(tmp_path),
                "--set", "sensors.image_scale=0.1", "--set", "agents.rsus.count=0", "--set", "map.size_m=300",
                "--set", "agents.vehicles.count=1", "--set", "pedestrians.density_per_km=10",
                "--set", "agents.drones=[{strategy: escort, target: vehicle_0, altitude_m: 40, offset_m: [-8, 0]}]",
                "--set", "events=[{kind: jaywalk, at_s: 1, ahead_of: vehicle_0, ahead_m: 15}]")
    assert r.returncode == 0, r.stderr
    path = tmp_path / "event_jaywalk_s0.mcap"
    v = run_cli("validate", str(path))
    assert v.returncode == 0, v.stdout + v.stderr
    in_area = seen_by_drone = lidar_hits = 0
    with open_episode(path) as ep:
        escort = "drone_0"  # the one drone, escorting vehicle_0
        for tick in ep.ticks():
            objects = {o["track_id"]: o for o in json.loads(tick.raw("/labels/objects").data)["objects"]}
            events = json.loads(tick.raw("/events").data)["events"]
            jay = [t for e in events if e["kind"] == "jaywalk" for t in e.get("pedestrian_track_ids", [])]
            if not jay:
                continue
            (tid,) = jay
            o = objects[tid]
            assert o["class"] == "pedestrian"
            to_ego = np.linalg.inv(tick.transforms.to_root("vehicle_0/lidar"))
            c = to_ego[:3, :3] @ np.array(o["center_m"]) + to_ego[:3, 3]
            in_area += abs(c[0]) <= AREA_HALF_M[0] and abs(c[1]) <= AREA_HALF_M[1]
            vis = json.loads(tick.raw(f"/{escort}/visibility").data)
            seen_by_drone += any(x["track_id"] == tid for x in vis["objects"])
            for topic, p, excess in lidar_box_excess(tick, objects, lambda o: o["class"] == "pedestrian"):
                assert excess <= 0.1, (topic, p["track_id"], excess)
                lidar_hits += 1
    assert in_area > 0 and seen_by_drone > 0 and lidar_hits > 0, (in_area, seen_by_drone, lidar_hits)


def test_hazard_lamps_glow_amber_in_a_night_camera():
    """Real ray casting at night: a car 8 m ahead, seen from behind, with its hazard lamps lit and dark. The
    pixels that differ are its two rear lamp units: amber when lit, the red tail lights when dark."""
    from cosim.sensors import SensorSuite
    from cosim.sensors.synthetic import actor

    from cosim.scenario.model import (
        CameraSpec,
        Mount,
        RigSpec,
        SensorsSpec,
    )
    from cosim.snapshot import AgentState, WorldSnapshot
    from tests.helpers import wall_world as _wall_world

    rig = RigSpec(lidar=None, cameras=[CameraSpec(name="front", width=160, height=120, fov_deg=40.0,
                                                  mount=Mount(xyz_m=(0.0, 0.0, 1.0)))], gnss=None, imu=None)
    sc = synthetic_scenario(environment={"lighting": "night"},
                            sensors=SensorsSpec(vehicle=rig, bev=False))
    suite = SensorSuite(sc, _wall_world(), noise=False)
    ego = AgentState("vehicle_0", "vehicle", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    cams = {}
    for lit in (True, False):
        car = actor(2, "car", 8.0, 0.0, z_ground=0.0)
        car = type(car)(**{**{f: getattr(car, f) for f in car.__dataclass_fields__}, "hazard_lamps_on": lit})
        frame = suite.render(WorldSnapshot(0, 0, (car,), (ego,)), np.random.default_rng(0))
        cams[lit] = frame.agents["vehicle_0"].cameras["front"]
    diff = np.any(cams[True].rgb != cams[False].rgb, axis=2)
    assert diff.sum() >= 20 and np.all(cams[True].instance[diff] == 2)
    on, off = cams[True].rgb[diff].astype(int), cams[False].rgb[diff].astype(int)
    assert np.all((on[:, 0] > 200) & (on[:, 1] > 0.5 * on[:, 0]) & (on[:, 1] < 0.9 * on[:, 0]) & (on[:, 2] < 40))
    assert np.all((off[:, 0] > 150) & (off[:, 1] < 0.5 * off[:, 0]))  # the tail lights: red
    cols = np.flatnonzero(diff.any(axis=0))
    assert np.any(np.diff(cols) > 5)  # two separate lamp units, left and right


@pytest.mark.integration  # real SUMO, a second run of the fixture's town
def test_stepping_without_the_pedestrians_states_leaves_the_simulation_as_it_was(run, tmp_path):
    """``step_to(t, pedestrians=False)`` (what the drones' flights and the traffic statistics use: the pedestrians'
    posed boxes are most of a town's step) gives every other state of every tick unchanged."""
    from cosim.traffic import TrafficSim
    from cosim.world import build_world

    loaded = _scenario()
    sc = loaded.scenario
    sim = TrafficSim(sc, build_world(loaded, tmp_path / "w"), tmp_path / "s")
    try:
        without = [sim.step_to(k * sc.tick_ns, pedestrians=False) for k in range(sc.n_ticks)]
    finally:
        sim.close()
    for (states, *_), other in zip(run["ticks"], without, strict=True):
        assert other == [s for s in states if s.cls != "pedestrian"]
    assert any(s.cls == "pedestrian" for states, *_ in run["ticks"] for s in states)
