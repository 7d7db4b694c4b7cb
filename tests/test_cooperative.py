"""The cooperative layout (issue 34): the group's placement invariants, the hover points, the one-line error
of a map that cannot hold a group, determinism with either layout, the collaboration report against a hand
count, and a real 20 s rural episode whose ego-ticks nearly all have two collaborators in range."""

from __future__ import annotations

import hashlib
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import sumolib

from cosim.batch.report import collaboration_section
from cosim.drones.routes import cover_points, focus_junctions, ranked_junctions
from cosim.errors import InputError
from cosim.eval.collaboration import (
    CollabCounts,
    collaboration_tables,
    collaborators_in_range,
    compute_collaboration,
    object_split,
)
from cosim.eval.dataset import load_dataset
from cosim.scenario import load_scenario_data
from cosim.world import build_world, geom
from cosim.world.group import NEAR_M
from cosim.world.netgen import sumo_binary
from cosim.world.routes import read_sumolib
from tests.helpers import run_cli

KINDS = ("urban", "suburban", "rural", "highway")


def _loaded(kind: str, layout: str = "cooperative", seed: int = 0, size: float = 400.0, **extra: object):
    data = {"name": f"c_{kind}", "seed": seed, "map": {"kind": kind, "size_m": size},
            "agents": {"layout": layout, **extra}}
    return load_scenario_data(data)


def _departures(world) -> dict[str, tuple[np.ndarray, tuple[str, ...]]]:
    """Connected vehicle id -> (departure x, y [m], route edges)."""
    net = read_sumolib(world.net_xml)
    out = {}
    for v in ET.fromstring(world.routes_xml).iter("vehicle"):
        if v.get("id").startswith("vehicle_"):
            edges = tuple(v.find("route").get("edges").split())
            lane = net.getEdge(edges[0]).getLanes()[int(v.get("departLane"))]
            xy = sumolib.geomhelper.positionAtShapeOffset(lane.getShape(), float(v.get("departPos")))
            out[v.get("id")] = (np.array(xy), edges)
    return out


@pytest.mark.integration
@pytest.mark.parametrize("kind", KINDS)
def test_group_departs_together_on_one_route_with_rsus_and_drones_on_it(kind: str, tmp_path: Path) -> None:
    world = build_world(_loaded(kind), tmp_path)
    dep = _departures(world)
    assert sorted(dep) == [f"vehicle_{i}" for i in range(4)]
    xy = np.array([d[0] for d in dep.values()])
    dist = np.linalg.norm(xy[:, None] - xy[None], axis=2) + np.eye(len(xy)) * 1e9
    nearest = dist.min(axis=1)
    assert ((nearest >= NEAR_M[0]) & (nearest <= NEAR_M[1])).all(), nearest
    # one shared route: every member's route is the tail of the longest one
    routes = sorted((d[1] for d in dep.values()), key=len, reverse=True)
    assert all(routes[0][len(routes[0]) - len(r):] == r for r in routes)
    # the RSUs stand at junctions the group's route passes
    assert world.group_junctions and all(r.junction_id in world.group_junctions for r in world.rsus)
    # drones: patrols centre on the group's first junction, hover points off the road surface, near the group
    assert focus_junctions(world)[0].junction_id == world.group_junctions[0]
    road = geom.Raster.empty(world.bounds_m, 0.5).with_polygons(
        [np.array(p.footprint) for p in world.layout.prisms if p.cls == "road"])
    first = np.array(focus_junctions(world)[0].position_m)
    for p in cover_points(world, 2):
        assert not road.lookup(p[None])[0], p
        assert np.linalg.norm(p - first) <= 400.0


@pytest.mark.integration
def test_spread_keeps_the_old_placement_and_both_layouts_are_deterministic(tmp_path: Path) -> None:
    spread = build_world(_loaded("urban", "spread", 5), tmp_path / "s")
    coop = build_world(_loaded("urban", "cooperative", 5), tmp_path / "c")
    coop2 = build_world(_loaded("urban", "cooperative", 5), tmp_path / "c2")
    spread2 = build_world(_loaded("urban", "spread", 5), tmp_path / "s2")
    assert coop.to_wire() == coop2.to_wire() and spread.to_wire() == spread2.to_wire()
    assert hashlib.sha256(coop.routes_xml).digest() == hashlib.sha256(coop2.routes_xml).digest()
    assert spread.group_junctions == () and "group_junctions" not in spread.to_wire()
    assert coop.routes_xml != spread.routes_xml
    assert spread.net_xml == coop.net_xml and spread.layout.prisms[:50] == coop.layout.prisms[:50]
    # without a group the drones rank junctions as before
    assert focus_junctions(spread) == ranked_junctions(spread)


def _tiny_net(tmp_path: Path) -> Path:
    """One straight two-way road of 70 m between two dead ends (netconvert, as a user's map file)."""
    (tmp_path / "t.nod.xml").write_text('<nodes><node id="a" x="0" y="0"/><node id="b" x="70" y="0"/></nodes>')
    (tmp_path / "t.edg.xml").write_text('<edges><edge id="ab" from="a" to="b" numLanes="1"/>'
                                        '<edge id="ba" from="b" to="a" numLanes="1"/></edges>')
    import subprocess

    subprocess.run([sumo_binary("netconvert"), "-n", "t.nod.xml", "-e", "t.edg.xml", "-o", "t.net.xml"],
                   cwd=tmp_path, check=True, capture_output=True)
    return tmp_path / "t.net.xml"


@pytest.mark.integration
def test_a_map_too_small_for_the_group_is_one_clear_error(tmp_path: Path) -> None:
    net = _tiny_net(tmp_path)
    data = {"name": "tiny", "map": {"kind": "net", "file": str(net)}, "agents": {"vehicles": {"count": 4}}}
    with pytest.raises(InputError, match=r"agents\.layout cooperative"):
        build_world(load_scenario_data(data), tmp_path / "w")
    spread = load_scenario_data({**data, "agents": {"vehicles": {"count": 4}, "layout": "spread"}})
    assert len(_departures(build_world(spread, tmp_path / "s"))) == 4  # spread still places them
    scenario = tmp_path / "tiny.yaml"
    scenario.write_text(f"name: tiny\nmap: {{kind: net, file: {net}}}\n")
    r = run_cli("run", str(scenario), "--no-sensors", "--duration", "1", "--out", str(tmp_path / "o"), "-q")
    assert r.returncode == 2, r.stderr
    assert r.stderr.count("\n") == 1 and "agents.layout cooperative" in r.stderr and "spread" in r.stderr, r.stderr


def test_collaboration_counts_match_a_hand_count() -> None:
    # ego at the origin; vehicle_1 at 100 m (in range), vehicle_2 at 130 m (out), rsu_0 at 119 m (in),
    # rsu_1 at 121 m (out), drone_0 150 m away and 60 m up (162 m: in), drone_1 at 190 m (out)
    pos = {"vehicle_0": np.zeros(3), "vehicle_1": np.array([100.0, 0, 0]), "vehicle_2": np.array([0, 130.0, 0]),
           "rsu_0": np.array([-119.0, 0, 0]), "rsu_1": np.array([0, -121.0, 0]),
           "drone_0": np.array([150.0, 0, 60.0]), "drone_1": np.array([190.0, 0, 0])}
    assert collaborators_in_range("vehicle_0", pos) == {"vehicle": 1, "rsu": 1, "drone": 1, "any": 3}
    # vehicle_2: vehicle_0 130 m, vehicle_1 164 m, rsu_1 251 m, drone_0 206 m away: nobody in range
    assert collaborators_in_range("vehicle_2", pos) == {"vehicle": 0, "rsu": 0, "drone": 0, "any": 0}
    # five objects in the area (the sixth is outside): A ego only, B ego + rsu, C vehicle_1 only,
    # D drone_0 only, E nobody
    mask = np.array([1, 1, 1, 1, 1, 0], bool)
    seen = {"vehicle_0": np.array([1, 1, 0, 0, 0, 1], bool), "vehicle_1": np.array([0, 0, 1, 0, 0, 0], bool),
            "rsu_0": np.array([0, 1, 0, 0, 0, 0], bool), "drone_0": np.array([0, 0, 0, 1, 0, 1], bool)}
    assert object_split(seen, "vehicle_0", mask) == {"nobody": 1, "ego": 2, "only collaborators": 2,
                                                     "only drones": 1}
    c = CollabCounts(ego_ticks=4, objects=5, in_range={"vehicle": [4, 1], "rsu": [2, 0], "drone": [3, 3],
                                                       "any": [4, 3]},
                     seen={"nobody": 1, "ego": 2, "only collaborators": 2, "only drones": 1})
    rng, obj = collaboration_tables({("overall", "all"): c}, {("overall", "all"): 20.0})
    assert rng.rows[0] == ["overall", "all", 4, 100.0, 25.0, 50.0, 0.0, 75.0, 75.0, 100.0, 75.0]
    assert obj.rows[0][:7] == ["overall", "all", 5, 20.0, 40.0, 40.0, 20.0] and obj.rows[0][7] == 20.0


@pytest.mark.integration
def test_a_rural_episode_keeps_two_collaborators_in_range(tmp_path: Path) -> None:
    """20 s of town_rural_night, labels only (real SUMO, drones, Zenoh and MCAP): >= 90 % of ego-ticks have
    at least 2 collaborators in range (the same layout spread: about half, issue 34)."""
    r = run_cli("run", "town_rural_night", "--no-sensors", "-q", "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    counts = compute_collaboration(load_dataset(tmp_path))[("overall", "all")]
    assert counts.ego_ticks == 4 * 100
    assert counts.share("any", 2) >= 90.0, counts
    # cosim report's section of the same numbers (labels only: the objects' table is n/a)
    section = collaboration_section(tmp_path)
    row = next(line for line in section.splitlines() if line.startswith("| overall | all | 400 |"))
    assert f"| {counts.share('any', 2):.1f} |" in row and "| n/a |" in section


def test_rsus_fill_up_from_the_junctions_nearest_the_route() -> None:
    from cosim.world.network import JunctionGeom
    from cosim.world.rsu import choose_on_route

    def j(i: str, x: float, y: float, kind: str = "priority") -> JunctionGeom:
        return JunctionGeom(i, (x, y), kind, np.zeros((0, 2)))

    # a 5 x 5 grid 100 m apart; the route passes b, c (signalised), d; four RSUs wanted
    js = [j(f"g{x}{y}", 100.0 * x, 100.0 * y) for x in range(5) for y in range(5)]
    route = ("g22", "g23", "g33")
    js = [j(g.junction_id, *g.position_m, "traffic_light" if g.junction_id == "g23" else "priority") for g in js]
    chosen = [c.junction_id for c in choose_on_route(js, {}, 4, (200.0, 200.0), route)]
    assert chosen[:3] == list(route)  # inner ones, in route order
    assert chosen[3] in {"g12", "g21", "g32", "g13", "g24", "g34", "g43"}  # 100 m from the route
    # one RSU: of the route's first two junctions, the signalised one
    assert [c.junction_id for c in choose_on_route(js, {}, 1, (200.0, 200.0), route)] == ["g23"]
