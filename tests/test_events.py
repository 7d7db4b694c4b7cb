"""The scenario timeline on real SUMO: breakdown, accident, lane closure, road block; schema errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cosim.errors import ScenarioError
from cosim.scenario import load_scenario, load_scenario_data
from cosim.traffic.metrics import bev_corners, convex_overlap_area

BLOCK_AT_S = 2.0
EVENTS = [
    {"kind": "breakdown", "at_s": 1.0, "ahead_of": "vehicle_0", "ahead_m": 40},
    {"kind": "accident", "at_s": 0.0, "ahead_of": "vehicle_1", "ahead_m": 30},
    # connected vehicles drive the inner town (issue 27): the closure is put ahead of one that comes up behind it
    # within the 12 s, the block where vehicles are routed over it
    {"kind": "lane_closure", "at_s": 0.0, "ahead_of": "vehicle_3", "ahead_m": 30, "length_m": 30},
    {"kind": "road_block", "at_s": BLOCK_AT_S, "ahead_of": "vehicle_2", "ahead_m": 80},
]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """12 s of a small town with the four events and people on the sidewalks: per tick the states, event
    records, every vehicle's SUMO lane, lane position and remaining route, and every person's SUMO edge."""
    # spread: each event has a connected vehicle of its own (in the cooperative queue they stand in one lane)
    return _events_run(tmp_path_factory.mktemp("events"), "spread")


def _events_run(tmp: Path, layout: str) -> list:
    import libsumo

    from cosim.traffic import TrafficSim
    from cosim.world import build_world

    loaded = load_scenario_data({
        "name": "events", "seed": 5, "duration_s": 12, "map": {"kind": "urban", "size_m": 300},
        "environment": {"lighting": "night"}, "traffic": {"density_veh_per_km": 30},
        "pedestrians": {"density_per_km": 20},
        "agents": {"layout": layout, "vehicles": {"count": 4}, "rsus": {"count": 0}, "drones": []},
        "events": EVENTS,
    })
    sc = loaded.scenario
    sim = TrafficSim(sc, build_world(loaded, tmp / "w"), tmp / "s")
    ticks = []
    try:
        for k in range(sc.n_ticks):
            states = sim.step_to(k * sc.tick_ns)
            v = libsumo.vehicle
            lanes = {vid: (v.getRoadID(vid), v.getLaneIndex(vid), v.getLanePosition(vid),
                           tuple(v.getRoute(vid)[v.getRouteIndex(vid) + 1:])) for vid in v.getIDList()}
            walkers = {pid: libsumo.person.getRoadID(pid) for pid in libsumo.person.getIDList()}
            ticks.append((k * sc.tick_ns, states, {r["id"]: r for r in sim.events()}, lanes, walkers))
    finally:
        sim.close()
    return ticks


def _active(ticks, event_id):
    return [(t, s, ev[event_id], ln, w) for t, s, ev, ln, w in ticks if ev[event_id]["state"] == "active"]


@pytest.mark.integration
def test_every_event_starts(run):
    last = run[-1][2]
    assert [r["state"] for r in last.values()] == ["active"] * 4, last
    assert last["event_0"]["hazard_lights"] is True  # night
    assert run[0][2]["event_0"]["state"] == "pending" and run[0][2]["event_3"]["state"] == "pending"
    assert all(r["active_from_ns"] >= r["at_ns"] for r in last.values())


@pytest.mark.integration
def test_broken_down_vehicle_stays_put(run):
    active = _active(run, "event_0")
    assert len(active) >= 40
    poses = np.array([[*s.center_m, s.yaw_rad, s.speed_mps] for _, states, _, _, _ in active for s in states
                      if s.sumo_id == "ev0_0"])
    assert len(poses) == len(active)
    assert np.ptp(poses[:, :4], axis=0).max() < 1e-6 and np.all(poses[:, 4] == 0.0)


@pytest.mark.integration
def test_events_in_the_cooperative_queue_wait_for_room_and_never_crash_sumo(tmp_path: Path):
    """In the cooperative queue the accident ahead of vehicle_1 lands where the vehicle ahead of it drives, so
    SUMO keeps its cars waiting to enter until there is room; the road block reaches that edge meanwhile.
    Closing lanes under a vehicle SUMO has yet to insert is a fatal SUMO error: the block is not placed and
    says why, and the run goes on."""
    ticks = _events_run(tmp_path, "cooperative")
    assert len(ticks) == 60
    last = ticks[-1][2]
    assert last["event_0"]["state"] == "active"  # vehicle_0 leads the queue: open road ahead of it
    assert last["event_1"]["state"] == "active" and last["event_1"]["active_from_ns"] > BLOCK_AT_S * 1e9  # waited
    assert last["event_3"]["state"] == "failed", last["event_3"]
    assert "ev1_0" in last["event_3"]["note"] and "wait" in last["event_3"]["note"]


@pytest.mark.integration
def test_accident_vehicles_touch_at_an_angle(run):
    for _, states, rec, _, _ in _active(run, "event_1"):
        by = {s.sumo_id: s for s in states}
        a, b = by["ev1_0"], by["ev1_1"]
        overlap = convex_overlap_area(bev_corners(a), bev_corners(b))
        assert 0.0 < overlap <= 0.05, overlap  # touching, barely overlapping
        assert abs(np.degrees(b.yaw_rad - a.yaw_rad) - 25.0) < 1e-6
        assert a.speed_mps == 0.0 == b.speed_mps and rec["vehicles"] == ["ev1_0", "ev1_1"]


@pytest.mark.integration
def test_nothing_drives_through_a_closed_lane(run):
    active = _active(run, "event_2")
    assert active
    rec = active[0][2]
    edge, lane, start = rec["edge"], rec["lane"], rec["lane_pos_m"]
    end = start + EVENTS[2]["length_m"]
    zone = np.array(rec["zone_m"])
    approached = set()  # came up behind the closure in its lane
    for _, states, _, lanes, _ in active:
        for vid, (road, idx, pos, _) in lanes.items():
            if vid.startswith("ev2_") or road != edge or idx != lane:
                continue
            # front positions: behind the span, or past its end (already there when the closure went up)
            assert pos < start + 0.5 or pos > end, f"{vid} in the closed span at {pos:.1f} m ({start:.1f}-{end:.1f})"
            if pos < start + 0.5:
                approached.add(vid)
            assert pos < start + 0.5 or vid not in approached, f"{vid} drove through the closed span"
        obstacles = [s for s in states if s.cls == "static_obstacle" and s.sumo_id.startswith("ev2_")]
        assert len(obstacles) == len(rec["obstacles"]) >= 3
        for s in states:
            if s.cls != "static_obstacle" and not s.sumo_id.startswith("ev"):
                # boxes of traffic beside the closure may graze its edge while merging; none enters it
                assert convex_overlap_area(bev_corners(s), zone) < 0.5, s.sumo_id
                for o in obstacles:
                    assert convex_overlap_area(bev_corners(s), bev_corners(o)) == 0.0, (s.sumo_id, o.sumo_id)
    assert approached, "no vehicle came up behind the closure: the test proves nothing"


@pytest.mark.integration
def test_road_block_reroutes_and_nothing_enters(run):
    active = _active(run, "event_3")
    edge = active[0][2]["edge"]
    block_ns = round(BLOCK_AT_S * 1e9)
    before = next(ln for t, _, _, ln, _ in run if t == block_ns - 200_000_000)
    on_edge = {vid for vid, (road, *_) in before.items() if road == edge}
    # in the junction toward the edge when the block came: they cannot turn elsewhere any more (they wait there)
    let_in = {vid for vid, (road, _, _, rest) in before.items() if road.startswith(":") and rest[:1] == (edge,)}
    would_use = {vid for vid, (road, _, _, rest) in before.items() if edge in rest and road != edge} - let_in
    assert would_use, "no vehicle was routed over the blocked edge: the test proves nothing"
    for _, _, _, lanes, _ in active:
        entered = {vid for vid, (road, *_) in lanes.items() if road == edge} - on_edge - let_in
        assert not entered, f"entered the blocked edge {edge}: {sorted(entered)}"
    rerouted = {vid for vid in would_use if vid in active[-1][3] and edge not in active[-1][3][vid][3]}
    assert rerouted == {vid for vid in would_use if vid in active[-1][3]}


@pytest.mark.integration
def test_road_block_keeps_its_sidewalk_open(run):
    """People walk on along a blocked street (before, the block closed the sidewalk too and SUMO stopped the
    run with "Person ... could not find sidewalk on edge ..." once someone walked onto it)."""
    active = _active(run, "event_3")
    rec = active[0][2]
    walking = {pid for _, _, _, _, walkers in active for pid, road in walkers.items() if road == rec["edge"]}
    assert walking, "nobody walked along the blocked edge: the test proves nothing"


@pytest.mark.parametrize(
    ("text", "path", "line", "words"),
    [
        ("name: t\nevents:\n  - kind: meteor\n    position_m: [1, 2]\n", "events.0", 3, ["unknown kind 'meteor'"]),
        ("name: t\nevents:\n  - kind: breakdown\n    at_s: 1.1\n    position_m: [1, 2]\n", "events.0.at_s", 4,
         ["whole number of ticks"]),
        ("name: t\nevents:\n  - kind: breakdown\n    ahead_of: car_1\n", "events.0.ahead_of", 4,
         ["connected vehicle id"]),
        ("name: t\nevents:\n  - kind: accident\n", "events.0.position_m", 3, ["exactly one of position_m"]),
        ("name: t\nevents:\n  - kind: road_block\n    ahead_of: vehicle_9\n", "events.0.ahead_of", 4,
         ["does not exist"]),
        ("name: t\nevents:\n  - kind: lane_closure\n    position_m: [0, 0]\n    length_m: 2\n",
         "events.0.length_m", 5, ["greater than or equal to 10"]),
    ],
)
def test_bad_events_name_key_path_and_line(tmp_path: Path, text, path, line, words):
    f = tmp_path / "bad.yaml"
    f.write_text(text)
    with pytest.raises(ScenarioError) as err:
        load_scenario(f)
    assert (err.value.path, err.value.line) == (path, line), str(err.value)
    for w in words:
        assert w in str(err.value)


@pytest.mark.integration
def test_episode_carries_events_and_validates(tmp_path: Path):
    """A real run (SUMO, drones, Zenoh, MCAP, labels only): /events every tick with track ids of the same tick's
    labels, the obstacles labelled static_obstacle, the events in the metadata, and `cosim validate` clean."""
    import json

    from cosim.io import open_episode
    from tests.helpers import run_cli

    r = run_cli("run", "scenarios/event_lane_closure.yaml", "--duration", "2", "--out", str(tmp_path), "--no-sensors",
                "--set", "agents.rsus.count=0", "--set", "map.size_m=300", "--set", "parked.density_veh_per_km=40")
    assert r.returncode == 0, r.stderr
    path = tmp_path / "event_lane_closure_s0.mcap"
    v = run_cli("validate", str(path))
    assert v.returncode == 0, v.stdout + v.stderr
    with open_episode(path) as ep:
        assert ep.format_version == "1.4"
        assert ep.metadata["events"][0]["kind"] == "construction_zone"
        assert "pedestrian" in ep.metadata["class_table"]["object_classes"]
    from mcap.reader import make_reader

    labels, events = {}, {}
    with open(path, "rb") as f:
        for _, ch, m in make_reader(f).iter_messages(topics=["/labels/objects", "/events"]):
            (labels if ch.topic == "/labels/objects" else events)[m.log_time] = json.loads(m.data)
    assert sorted(events) == sorted(labels) and len(events) == 10
    for t, msg in events.items():
        (e,) = msg["events"]
        assert e["state"] == "active" and e["kind"] == "construction_zone"
        classes = {o["track_id"]: o["class"] for o in labels[t]["objects"]}
        assert len(e["obstacle_track_ids"]) >= 3
        assert {classes[i] for i in e["obstacle_track_ids"]} == {"static_obstacle"}
    # parked vehicles: the same boxes every tick, flagged, never overlapped by a moving box
    parked = [{o["track_id"]: o for o in msg["objects"] if o.get("parked")} for msg in labels.values()]
    assert len(parked[0]) >= 5 and all(p == parked[0] for p in parked)
    assert {o["class"] for o in parked[0].values()} <= {"car", "van", "truck", "bus", "motorcycle", "bicycle"}
    for msg in labels.values():
        moving = [o for o in msg["objects"] if not o.get("parked") and o["class"] != "drone"]
        for p in parked[0].values():
            for o in moving:
                assert convex_overlap_area(_corners(p), _corners(o)) == 0.0, (p["track_id"], o["track_id"])


def _corners(o) -> np.ndarray:
    from cosim.world.geom import rect

    qx, qy, qz, qw = o["rotation"]
    yaw = np.arctan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))
    return rect(o["center_m"][0], o["center_m"][1], o["size_m"][0], o["size_m"][1], float(yaw))


def test_incidents_sweep_has_an_events_axis():
    from cosim.batch.plan import plan_file

    plan = plan_file(Path(__file__).resolve().parents[1] / "sweeps" / "incidents.yaml")
    kinds = {tuple(e["kind"] for e in ep.scenario["events"]) for ep in plan.episodes}
    assert kinds == {(), ("breakdown",), ("accident",), ("construction_zone",), ("road_block",), ("jaywalk",),
                     ("cut_in",)}
    assert plan.combinations == 21 and len(plan.episodes) == 42
    assert all(ep.scenario["parked"]["density_veh_per_km"] == 20 for ep in plan.episodes)


@pytest.mark.integration
def test_lidar_points_of_obstacles_and_parked_vehicles_lie_in_their_boxes(tmp_path: Path):
    """Sensors agree with the labels for the new boxes: every LiDAR return carrying the track id of a
    static obstacle or a parked vehicle lies inside that box grown by 0.1 m."""
    import json

    from cosim.io import open_episode
    from tests.helpers import lidar_box_excess, run_cli

    r = run_cli("run", "scenarios/event_lane_closure.yaml", "--duration", "0.4", "--out", str(tmp_path),
                "--set", "sensors.image_scale=0.1", "--set", "agents.rsus.count=0", "--set", "map.size_m=300",
                "--set", "parked.density_veh_per_km=40")
    assert r.returncode == 0, r.stderr
    hit = {"static_obstacle": 0, "parked": 0}
    with open_episode(tmp_path / "event_lane_closure_s0.mcap") as ep:
        for tick in ep.ticks():
            objects = {o["track_id"]: o for o in json.loads(tick.raw("/labels/objects").data)["objects"]}
            for topic, o, excess in lidar_box_excess(tick, objects, lambda o: o["class"] == "static_obstacle"
                                                     or o.get("parked")):
                assert excess <= 0.1, (topic, o["class"], o["track_id"], excess)
                hit["parked" if o.get("parked") else "static_obstacle"] += 1
    assert hit["static_obstacle"] > 0 and hit["parked"] > 0, hit


@pytest.mark.integration
def test_broken_down_car_blinks_its_hazard_lamps(run):
    """At night the broken-down car's hazard lamps blink at 1.5 Hz (lit half of each period) from activation;
    the renderer paints its lamp units amber and glowing while lit."""
    from cosim.traffic.events import HAZARD_PERIOD_NS
    from sensors.meshes import HAZARD_AMBER, actor_material, template_for

    active = _active(run, "event_0")
    t0 = active[0][2]["active_from_ns"]
    lit = [(t, s.hazard_lamps_on) for t, states, _, _, _ in active for s in states if s.sumo_id == "ev0_0"]
    assert {on for _, on in lit} == {True, False}
    assert all(on == ((t - t0) % HAZARD_PERIOD_NS < HAZARD_PERIOD_NS // 2) for t, on in lit)
    assert not any(s.hazard_lamps_on for _, states, _, _, _ in run for s in states if s.sumo_id != "ev0_0")
    part = template_for("car").part
    alb_on, _, emis_on = actor_material("car", 7, part, hazard_lamps_on=True)
    alb_off, _, _ = actor_material("car", 7, part)
    lamps = np.isin(part, [3, 4])  # front and rear lamp units
    assert np.allclose(alb_on[lamps], HAZARD_AMBER) and np.all(emis_on[lamps] > 0.0)
    assert not np.allclose(alb_off[lamps], HAZARD_AMBER) and np.array_equal(alb_on[~lamps], alb_off[~lamps])
