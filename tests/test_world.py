"""World building: geometry helpers, class counts, determinism, layout invariants, map files and OSM import."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from cosim.classes import SEMANTIC_CLASSES
from cosim.errors import InputError
from cosim.scenario import load_scenario_data
from cosim.world import World, build_world, geom
from cosim.world.layout import road_raster
from cosim.world.network import read_network
from cosim.world.routes import class_counts

GENERATED = ("urban", "suburban", "rural", "highway")


# ------------------------------------------------------------------------------------ pure helpers


def test_strip_is_ccw_band_of_given_width() -> None:
    line = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    band = geom.strip(line, 2.0)
    assert geom.signed_area(band) > 0
    # a right-angle band of width 2 along 20 m of centre line covers ~40 m^2
    assert abs(geom.signed_area(band)) == pytest.approx(40.0, abs=1.0)
    assert geom.points_in_polygon(np.array([[5.0, 0.9], [5.0, 1.1], [10.9, 5.0]]), band).tolist() == [True, False, True]


def test_offset_polyline_keeps_distance() -> None:
    line = np.array([[0.0, 0.0], [50.0, 0.0], [80.0, 30.0]])
    left = geom.offset_polyline(line, 1.5)
    assert left[0].tolist() == pytest.approx([0.0, 1.5])
    u, w = line[2] - line[1], left[2] - line[1]
    d = (u[0] * w[1] - u[1] * w[0]) / np.linalg.norm(u)
    assert d == pytest.approx(1.5)


def test_occupancy_free_and_raster_lookup() -> None:
    occ = geom.Occupancy((0.0, 0.0, 100.0, 100.0), 0.5)
    occ.add(geom.rect(50.0, 50.0, 10.0, 10.0, 0.0))
    assert not occ.free(geom.rect(56.0, 50.0, 4.0, 4.0, 0.0))
    assert occ.free(geom.rect(60.0, 50.0, 4.0, 4.0, 0.0))
    r = occ.raster()
    assert r.lookup(np.array([[50.0, 50.0], [70.0, 70.0], [-5.0, 0.0]])).tolist() == [True, False, False]


@pytest.mark.parametrize("n", [0, 1, 6, 7, 13, 40, 200])
def test_class_counts_follow_mix(n: int) -> None:
    """Every class gets the floor or ceiling of its share, and on average exactly its share: no class
    is rounded up in every episode (the old rule gave every class one vehicle, whatever its share)."""
    mix = {"car": 0.6, "van": 0.1, "truck": 0.08, "bus": 0.05, "motorcycle": 0.1, "bicycle": 0.07}
    rng = np.random.default_rng(n)
    draws = [class_counts(mix, n, rng) for _ in range(400)]
    for counts in draws:
        assert sum(counts.values()) == n
        assert all(math.floor(mix[c] * n) <= counts[c] <= math.ceil(mix[c] * n) for c in mix), counts
    for c in mix:
        assert np.mean([d[c] for d in draws]) == pytest.approx(mix[c] * n, abs=0.1)
    if 0 < n < 20:
        assert any(d["bus"] == 0 for d in draws)


# ------------------------------------------------------------------------------------ built worlds


def _loaded(kind: str, seed: int = 0, size: float = 250.0, **extra: object):
    return load_scenario_data({"name": f"w_{kind}", "seed": seed, "map": {"kind": kind, "size_m": size}, **extra})


@pytest.mark.integration
def test_build_is_deterministic(tmp_path: Path) -> None:
    a = build_world(_loaded("urban", 7), tmp_path / "a")
    b = build_world(_loaded("urban", 7), tmp_path / "b")
    c = build_world(_loaded("urban", 8), tmp_path / "c")
    assert a.net_xml == b.net_xml
    assert a.routes_xml == b.routes_xml
    assert a.layout == b.layout
    assert a.rsus == b.rsus
    assert a.to_wire() == b.to_wire()
    assert (c.net_xml, c.routes_xml) != (a.net_xml, a.routes_xml)
    assert b"generated on" not in a.net_xml  # no wall-clock header


@pytest.mark.integration
@pytest.mark.parametrize("kind", GENERATED)
def test_layout_invariants(kind: str, tmp_path: Path) -> None:
    loaded = _loaded(kind, 3)
    sc = loaded.scenario
    world = build_world(loaded, tmp_path)
    assert World.from_wire(world.to_wire()) == world
    assert world.geo_origin == (sc.geo_origin.lat_deg, sc.geo_origin.lon_deg, sc.geo_origin.alt_m)
    prisms = world.layout.prisms
    assert all(p.cls in SEMANTIC_CLASSES for p in prisms)
    assert all(geom.signed_area(np.array(p.footprint)) > 0 for p in prisms)
    assert all(p.z1_m > p.z0_m for p in prisms)
    ids = [p.instance_id for p in prisms if p.cls in ("building", "pole", "street_light", "rsu")]
    assert all(i >= 1_000_000 for i in ids) and len(ids) == len(set(ids))
    classes = {p.cls for p in prisms}
    assert {"road", "terrain", "vegetation", "lane_marking", "rsu"} <= classes
    assert "building" in classes or kind == "highway"  # a small highway map may have no room for any
    # buildings never stand on the road surface (sampled on a 0.25 m grid inside each footprint)
    road = road_raster(read_network(world.net_xml), world.bounds_m, 0.25)
    for p in prisms:
        if p.cls != "building":
            continue
        poly = np.array(p.footprint)
        lo, hi = poly.min(axis=0), poly.max(axis=0)
        gx, gy = np.meshgrid(np.arange(lo[0], hi[0], 0.25), np.arange(lo[1], hi[1], 0.25))
        pts = np.stack([gx.ravel(), gy.ravel()], axis=1)
        pts = pts[geom.points_in_polygon(pts, poly)]
        assert not road.lookup(pts).any(), f"building {p.instance_id} overlaps the road"
    # RSUs: count, height range, within MAX_OFFSET_M of their junction, inside the urban town (not on the
    # outer ring, where the map's roads end), a pole prism each
    from cosim.world.rsu import MAX_OFFSET_M, outer_ring

    junctions = {j.junction_id: j.position_m for j in world.junctions}
    ring = outer_ring([j for j in read_network(world.net_xml).real_junctions()])
    assert [r.agent_id for r in world.rsus] == [f"rsu_{i}" for i in range(sc.agents.rsus.count)]
    lo_h, hi_h = sc.agents.rsus.height_m
    for r in world.rsus:
        # positions are rounded to the millimetre
        assert math.dist(r.position_m[:2], junctions[r.junction_id]) <= MAX_OFFSET_M + 0.01
        assert lo_h <= r.height_m <= hi_h and r.position_m[2] == pytest.approx(r.height_m)
        if kind == "urban":  # (the small suburban test town has too few feasible inner junctions)
            assert r.junction_id not in ring
    assert sum(p.cls == "rsu" for p in prisms) == len(world.rsus)


@pytest.mark.integration
def test_downtown_is_taller_than_suburb(tmp_path: Path) -> None:
    def heights(kind: str) -> list[float]:
        w = build_world(_loaded(kind, 1, 400.0), tmp_path / kind)
        return [p.z1_m for p in w.layout.prisms if p.cls == "building"]

    urban, suburban = heights("urban"), heights("suburban")
    assert np.median(urban) > 2 * np.median(suburban)
    assert max(suburban) < 10.0


@pytest.mark.integration
def test_map_size_and_lanes_are_configurable(tmp_path: Path) -> None:
    small = build_world(_loaded("urban", 1, 200.0), tmp_path / "s")
    large = build_world(
        _loaded(
            "urban",
            1,
            600.0,
        ),
        tmp_path / "l",
    )
    assert small.bounds_m[2] - small.bounds_m[0] < 300 < large.bounds_m[2] - large.bounds_m[0]
    loaded = load_scenario_data({"name": "h", "map": {"kind": "highway", "size_m": 300, "lanes": 4}})
    net = read_network(build_world(loaded, tmp_path / "h").net_xml)
    assert max(len([ln for ln in e.lanes if ln.is_road]) for e in net.road_edges()) >= 4


def test_missing_map_file_is_input_error(tmp_path: Path) -> None:
    loaded = load_scenario_data({"name": "m", "map": {"kind": "net", "file": str(tmp_path / "nope.net.xml")}})
    with pytest.raises(InputError, match="not found"):
        build_world(loaded, tmp_path)


def test_bad_map_files_are_input_errors(tmp_path: Path) -> None:
    (tmp_path / "bad.net.xml").write_text("<html>not a network</html>")
    (tmp_path / "bad.osm").write_text("<?xml version='1.0'?><gpx></gpx>")
    for kind, name in (("net", "bad.net.xml"), ("osm", "bad.osm")):
        loaded = load_scenario_data({"name": "b", "map": {"kind": kind, "file": str(tmp_path / name)}})
        with pytest.raises(InputError, match=name):
            build_world(loaded, tmp_path / kind)


# ------------------------------------------------------------------------------------ OpenStreetMap


def write_small_osm(path: Path) -> None:
    """A 3 x 3 block of streets (about 120 m apart) and two buildings, near 48.1 N 11.5 E."""
    lat0, lon0 = 48.1, 11.5
    dlat = 120.0 / 111_320.0
    dlon = 120.0 / (111_320.0 * math.cos(math.radians(lat0)))
    lines = ["<?xml version='1.0' encoding='UTF-8'?>", "<osm version='0.6' generator='cosim-test'>"]
    nid = 1

    def node(lat: float, lon: float) -> int:
        nonlocal nid
        lines.append(f"  <node id='{nid}' visible='true' version='1' lat='{lat:.7f}' lon='{lon:.7f}'/>")
        nid += 1
        return nid - 1

    grid = [[node(lat0 + i * dlat, lon0 + j * dlon) for j in range(4)] for i in range(4)]
    ways = []
    for i in range(4):
        ways.append(([grid[i][j] for j in range(4)], {"highway": "secondary" if i == 1 else "residential"}))
        ways.append(([grid[j][i] for j in range(4)], {"highway": "residential"}))
    for bi, bj, tags in ((0, 0, {"building": "yes"}), (1, 2, {"building": "apartments", "building:levels": "4"})):
        la, lo = lat0 + (bi + 0.3) * dlat, lon0 + (bj + 0.3) * dlon
        ring = [
            node(la, lo),
            node(la, lo + 0.3 * dlon),
            node(la + 0.3 * dlat, lo + 0.3 * dlon),
            node(la + 0.3 * dlat, lo),
        ]
        ways.append((ring + ring[:1], tags))
    for w, (refs, tags) in enumerate(ways, start=1000):
        lines.append(f"  <way id='{w}' visible='true' version='1'>")
        lines += [f"    <nd ref='{r}'/>" for r in refs]
        lines += [f"    <tag k='{k}' v='{v}'/>" for k, v in tags.items()]
        lines.append("  </way>")
    lines.append("</osm>")
    path.write_text("\n".join(lines))


@pytest.mark.integration
def test_osm_import_roads_and_buildings(tmp_path: Path) -> None:
    osm = tmp_path / "small.osm"
    write_small_osm(osm)
    loaded = load_scenario_data(
        {
            "name": "o",
            "seed": 2,
            "map": {"kind": "osm", "file": str(osm)},
            "agents": {"vehicles": {"count": 2}, "rsus": {"count": 2}},
        }
    )
    world = build_world(loaded, tmp_path / "w")
    net = read_network(world.net_xml)
    assert 1.5 < net.road_length_km() < 4.0  # 8 streets of 360 m, less the junctions
    assert len(net.real_junctions()) >= 9
    buildings = [p for p in world.layout.prisms if p.cls == "building"]
    assert len(buildings) == 2  # the two outlines from the file, not generated ones
    for b in buildings:
        side = math.sqrt(abs(geom.signed_area(np.array(b.footprint))))
        assert side == pytest.approx(36.0, rel=0.1)
    assert 13.0 in [b.z1_m for b in buildings]  # building:levels = 4 -> 3 m a level + 1 m
    lat, lon, _ = world.geo_origin
    assert abs(lat - 48.1) < 0.01 and abs(lon - 11.5) < 0.01
    assert b'<vehicle id="vehicle_1"' in world.routes_xml


# -------------------------------------------------------------------------- SUMO tools die with their process


def test_netconvert_and_other_sumo_tools_die_with_the_conductor(tmp_path):
    """A process running a SUMO tool through the world builder is SIGKILLed: the tool goes too."""
    import subprocess
    import sys
    import time

    import psutil

    script = ("import sys\nfrom pathlib import Path\nimport cosim.world.netgen as n\n"
              "n.sumo_binary = lambda name: '/bin/sleep'\nprint('go', flush=True)\n"
              "n._run_tool('netconvert', ['60'], Path('.'))\n")
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, cwd=tmp_path)
    assert proc.stdout.readline().strip() == "go"
    deadline = time.monotonic() + 20
    children: list[psutil.Process] = []
    while not children and time.monotonic() < deadline:
        children = psutil.Process(proc.pid).children()
        time.sleep(0.02)
    assert children and children[0].name() == "sleep", children
    proc.kill()
    proc.wait(10)
    _, alive = psutil.wait_procs(children, timeout=5)
    assert not alive, alive
