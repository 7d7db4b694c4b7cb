"""The V2X link model: 3GPP path loss by hand, line of sight through a ray-cast scene, determinism,
drones' line of sight on a built town, and /comm/links in real episodes (run, validate, read, cosim comm)."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest
from cosim.sensors.synthetic import SIZES, actor, synthetic_snapshot, synthetic_world, world_snapshot

from cosim.comm import channel as ch
from cosim.comm import phy
from cosim.comm.links import LinkModel, compute_links, link_type
from cosim.comm.los import LinkScene
from cosim.comm.message import LinkSet, decode_links, links_payload
from cosim.errors import FormatError
from cosim.geometry import quat_from_rpy
from cosim.scenario.model import CommSpec
from cosim.snapshot import Actor, AgentState, WorldSnapshot
from tests.helpers import run_cli

FC = 5.9  # [GHz]
DISTANCES_M = (25.0, 120.0, 480.0)
log10 = math.log10


# ------------------------------------------------------------------------------ path loss by hand


@pytest.mark.parametrize("d", DISTANCES_M)
def test_tr37885_v2v_path_loss_equals_table_6_2_1_1(d):
    assert ch.v2v_highway_los_db(d, FC) == pytest.approx(32.4 + 20 * log10(d) + 20 * log10(FC), abs=0.1)
    assert ch.v2v_urban_los_db(d, FC) == pytest.approx(38.77 + 16.7 * log10(d) + 18.2 * log10(FC), abs=0.1)
    assert ch.v2v_urban_nlos_db(d, FC) == pytest.approx(36.85 + 30 * log10(d) + 18.9 * log10(FC), abs=0.1)
    # NLOSv: the LOS loss plus the blockage mean; antennas at 1.6 m, blockers of 1.5 m, 2.5 m and 3.4 m
    extra = max(0.0, 15 * log10(d) - 41)
    for blocker, mean, std in ((1.5, 0.0, 0.0), (2.5, 9 + extra, 4.5), (3.4, 9 + extra, 4.5)):
        m, s = ch.nlosv_blockage_db(d, 1.6, 1.6, blocker)
        assert (float(m), float(s)) == pytest.approx((mean, std), abs=0.1)
    m, s = ch.nlosv_blockage_db(d, 1.6, 8.0, 3.4)  # one antenna above the blocker, one below
    assert (float(m), float(s)) == pytest.approx((5 + extra, 4.0), abs=0.1)


@pytest.mark.parametrize("d", DISTANCES_M)
def test_tr38901_umi_street_canyon_equals_table_7_4_1_1(d):
    h_bs, h_ut = 8.0, 1.6
    d_bp = 4 * (h_bs - 1) * (h_ut - 1) * FC * 1e9 / 3.0e8  # about 330 m: the three distances straddle it
    d3 = math.sqrt(d**2 + (h_bs - h_ut) ** 2)
    if d <= d_bp:
        los = 32.4 + 21 * log10(d3) + 20 * log10(FC)
    else:
        los = 32.4 + 40 * log10(d3) + 20 * log10(FC) - 9.5 * log10(d_bp**2 + (h_bs - h_ut) ** 2)
    nlos = max(los, 35.3 * log10(d3) + 22.4 + 21.3 * log10(FC) - 0.3 * (h_ut - 1.5))
    assert float(ch.umi_sc_los_db(d3, d, h_bs, h_ut, FC)) == pytest.approx(los, abs=0.1)
    assert float(ch.umi_sc_nlos_db(d3, d, h_bs, h_ut, FC)) == pytest.approx(nlos, abs=0.1)


@pytest.mark.parametrize("d", DISTANCES_M)
@pytest.mark.parametrize("h", [40.0, 120.0])
def test_tr36777_aerial_path_loss_equals_table_b_2(d, h):
    fs = 20 * log10(d) + 20 * log10(FC) + 32.44
    umi_los = max(fs, 30.9 + (22.25 - 0.5 * log10(h)) * log10(d) + 20 * log10(FC))
    umi_nlos = max(umi_los, 32.4 + (43.2 - 7.6 * log10(h)) * log10(d) + 20 * log10(FC))
    uma_los = 28.0 + 22 * log10(d) + 20 * log10(FC)
    uma_nlos = -17.5 + (46 - 7 * log10(h)) * log10(d) + 20 * log10(40 * math.pi * FC / 3)
    rma_los = max(23.9 - 1.8 * log10(h), 20) * log10(d) + 20 * log10(40 * math.pi * FC / 3)
    rma_nlos = max(rma_los, -12 + (35 - 5.3 * log10(h)) * log10(d) + 20 * log10(40 * math.pi * FC / 3))
    got = [ch.umi_av_los_db(d, h, FC), ch.umi_av_nlos_db(d, h, FC), ch.uma_av_los_db(d, h, FC),
           ch.uma_av_nlos_db(d, h, FC), ch.rma_av_los_db(d, h, FC), ch.rma_av_nlos_db(d, h, FC),
           ch.free_space_db(d, FC)]
    want = [umi_los, umi_nlos, uma_los, uma_nlos, rma_los, rma_nlos, fs]
    assert [float(g) for g in got] == pytest.approx(want, abs=0.1)
    assert float(ch.av_shadow_std_db("umi_av", True, h)) == pytest.approx(max(5 * math.exp(-0.01 * h), 2), abs=1e-9)
    assert float(ch.av_shadow_std_db("uma_av", True, h)) == pytest.approx(4.64 * math.exp(-0.0066 * h), abs=1e-9)


def test_link_budget_noise_per_and_delay_follow_their_formulas():
    assert phy.noise_dbm(20e6, 9.0) == pytest.approx(-174 + 10 * log10(20e6) + 9, abs=1e-9)  # -92 dBm
    snr50 = 10 * log10(2 ** (1 / 0.6) - 1)  # QPSK 1/2 on the attenuated Shannon bound, alpha 0.6
    assert phy.snr50_db("qpsk_1_2", 0.6) == pytest.approx(snr50, abs=1e-9)
    per = phy.per(np.array([snr50 - 1.0, snr50, snr50 + 1.0]), "qpsk_1_2", 0.6, 2.0)
    assert per == pytest.approx([0.9, 0.5, 0.1], abs=1e-9)  # 90 % -> 10 % across the 2 dB waterfall
    rate = phy.mcs_rate_bps("16qam_3_4", 20e6, 0.42)
    assert rate == pytest.approx(20e6 * 0.58 * 4 * 0.75)
    assert phy.delay_ms(1600, rate, 2.0, 10.0) == pytest.approx(1600 * 8 / rate * 1e3 + 12.0)
    with pytest.raises(KeyError, match="known: qpsk_1_3"):
        phy.mcs("qam9")


# ------------------------------------------------------------------------ line of sight (synthetic)


@pytest.fixture(scope="module")
def synthetic_scene() -> LinkScene:
    return LinkScene.from_layout(synthetic_world().layout)


def _vehicle(i: int, track: int, x: float, y: float) -> tuple[Actor, AgentState]:
    a = actor(track, "car", x, y, agent_id=f"vehicle_{i}")
    return a, AgentState(f"vehicle_{i}", "vehicle", (x, y, 0.02), a.rotation, track_id=track)


def _drone(i: int, track: int, x: float, y: float, z: float) -> tuple[Actor, AgentState]:
    q = quat_from_rpy(0.0, 0.0, 0.0)
    return (Actor(track, "drone", (x, y, z), SIZES["drone"], q, (0.0, 0.0, 0.0), f"drone_{i}"),
            AgentState(f"drone_{i}", "drone", (x, y, z), q, track_id=track))


def _snapshot(pairs, extra_actors=(), tick: int = 0) -> WorldSnapshot:
    return WorldSnapshot(tick, tick * 200_000_000, tuple([a for a, _ in pairs] + list(extra_actors)),
                         tuple(s for _, s in pairs))


def _links(scene, snap, spec=None, map_kind="urban") -> LinkSet:
    spec = spec or CommSpec(shadow_fading=False)
    links, _ = compute_links(snap, scene, spec, map_kind, 200_000_000, None, np.random.default_rng(0))
    return links


def test_a_building_between_two_agents_makes_the_link_nlos_and_a_clear_line_los(synthetic_scene):
    # the building at x 20..45, y 20..40 (18 m high) stands between (10, 30) and (55, 30)
    blocked = _links(synthetic_scene, _snapshot([_vehicle(0, 1, 10.0, 30.0), _vehicle(1, 2, 55.0, 30.0)]))
    # along the road (y = -3.5), past street lights and poles, nothing in between
    clear = _links(synthetic_scene, _snapshot([_vehicle(0, 1, -40.0, -3.5), _vehicle(1, 2, 40.0, -3.5)]))
    assert blocked.los == ("nlos", "nlos") and clear.los == ("los", "los")
    d = clear.distance_m[0]
    assert d == pytest.approx(80.0)
    assert clear.path_loss_db[0] == pytest.approx(38.77 + 16.7 * log10(d) + 18.2 * log10(FC), abs=0.01)
    db = blocked.distance_m[0]
    assert blocked.path_loss_db[0] == pytest.approx(36.85 + 30 * log10(db) + 18.9 * log10(FC), abs=0.01)
    assert clear.model == ("tr37885_urban",) * 2 and clear.link_type == ("vehicle-vehicle",) * 2


def test_a_truck_in_between_makes_nlosv_with_the_blockage_loss_and_a_drone_sees_over_the_building(
        synthetic_scene):
    v0, v1 = _vehicle(0, 1, -40.0, -3.5), _vehicle(1, 2, 40.0, -3.5)
    truck = actor(3, "truck", 0.0, -3.5)  # 3.4 m high, above both 1.62 m antennas
    links = _links(synthetic_scene, _snapshot([v0, v1], [truck]))
    assert links.los == ("nlosv", "nlosv")
    d = links.distance_m[0]
    want = 38.77 + 16.7 * log10(d) + 18.2 * log10(FC) + 9 + max(0.0, 15 * log10(d) - 41)
    assert links.path_loss_db[0] == pytest.approx(want, abs=0.01)
    # the two ends' own boxes never block; a drone 60 m above the building's far side sees the vehicle
    links = _links(synthetic_scene, _snapshot([_vehicle(0, 1, 10.0, 30.0), _drone(0, 2, 40.0, 30.0, 60.0)]))
    assert links.los == ("los", "los") and links.link_type == ("vehicle-drone",) * 2
    assert links.model == ("tr36777_umi_av",) * 2
    low = _links(synthetic_scene, _snapshot([_vehicle(0, 1, 10.0, 30.0), _drone(0, 2, 40.0, 30.0, 15.0)]))
    assert low.los == ("nlos", "nlos") and low.model == ("tr38901_umi_sc",) * 2  # below 22.5 m: terrestrial


def test_link_types_and_ordered_pairs():
    assert link_type("drone", "vehicle") == "vehicle-drone" and link_type("rsu", "rsu") == "rsu-rsu"
    snap = synthetic_snapshot(3, 2, 2)
    scene = LinkScene.from_layout(synthetic_world().layout)
    links = _links(scene, snap)
    n = len(snap.agents)
    assert len(links) == n * (n - 1)
    assert {(a, b) for a, b in zip(links.tx, links.rx, strict=True)} == {
        (a.agent_id, b.agent_id) for a in snap.agents for b in snap.agents if a is not b}
    i, j = links.index("vehicle_0", "drone_1"), links.index("drone_1", "vehicle_0")
    assert links.snr_db[i] == links.snr_db[j] and links.link_type[i] == "vehicle-drone"
    assert len(_links(scene, synthetic_snapshot(1, 0, 0))) == 0  # one agent: no link, no error


# ------------------------------------------------------------------------------------ determinism


def _moving(tick: int) -> WorldSnapshot:
    """The synthetic junction with every connected vehicle and drone moved 3 m east per tick."""
    snap = synthetic_snapshot(4, 3, 3, tick=tick)

    def shift(p):
        return (p[0] + 3.0 * tick, p[1], p[2])

    actors = tuple(dataclasses.replace(a, center_m=shift(a.center_m)) if a.agent_id else a for a in snap.actors)
    agents = tuple(a if a.kind == "rsu" else dataclasses.replace(a, position_m=shift(a.position_m))
                   for a in snap.agents)
    return WorldSnapshot(snap.tick, snap.t_ns, actors, agents)


def _episode_links(scene, seed: int) -> list[LinkSet]:
    model = LinkModel(CommSpec(), scene, "urban", seed, 200_000_000)
    return [model.step(_moving(k)) for k in range(6)]


def test_same_seed_same_links_other_seed_changes_only_the_fading(synthetic_scene):
    a, b, c = (_episode_links(synthetic_scene, s) for s in (7, 7, 8))
    for la, lb, lc in zip(a, b, c, strict=True):
        for f in dataclasses.fields(LinkSet):
            va, vb, vc = getattr(la, f.name), getattr(lb, f.name), getattr(lc, f.name)
            assert np.array_equal(va, vb), f.name
            if f.name in ("shadow_fading_db", "rx_power_dbm", "snr_db", "capacity_bps"):
                assert not np.array_equal(va, vc), f.name
            elif f.name not in ("per", "rate_bps", "delivery"):
                assert np.array_equal(va, vc), f.name  # geometry, LOS, path loss, delay: no randomness
    # fading is correlated: a pair's value changes less from one tick to the next than between seeds
    steps = np.concatenate([np.abs(n.shadow_fading_db - p.shadow_fading_db) for p, n in itertools.pairwise(a)])
    seeds = np.abs(a[0].shadow_fading_db - c[0].shadow_fading_db)
    assert np.median(steps) < np.median(seeds)
    rsu = [i for i, (x, y) in enumerate(zip(a[0].tx, a[0].rx, strict=True)) if x.startswith("rsu") and
           y.startswith("rsu")]
    assert np.array_equal(a[0].shadow_fading_db[rsu], a[-1].shadow_fading_db[rsu])  # RSUs do not move


def test_links_payload_round_trip_and_bad_payloads(synthetic_scene):
    links = _links(synthetic_scene, synthetic_snapshot(2, 1, 1), CommSpec())
    back = decode_links(links_payload(links, "qpsk_1_2", 1600, 20e6))
    assert back.tx == links.tx and back.los == links.los
    assert np.allclose(back.snr_db, links.snr_db, atol=1e-3) and np.allclose(back.per, links.per, atol=1e-6)
    payload = links_payload(links, "qpsk_1_2", 1600, 20e6)
    payload["links"]["snr_db"] = payload["links"]["snr_db"][:-1]
    with pytest.raises(FormatError, match="columns differ in length"):
        decode_links(payload)
    payload = links_payload(links, "qpsk_1_2", 1600, 20e6)
    payload["links"]["los"][0] = "maybe"
    with pytest.raises(FormatError, match="unknown link_type"):
        decode_links(payload)


# ----------------------------------------------------------------- drones on a built urban town


@pytest.fixture(scope="module")
def urban_town(tmp_path_factory):
    from cosim.scenario.loader import load_scenario_data
    from cosim.world.build import build_world

    loaded = load_scenario_data({"name": "comm_town", "seed": 5, "map": {"kind": "urban", "size_m": 300},
                                 "agents": {"vehicles": {"count": 5}, "rsus": {"count": 5}}})
    world = build_world(loaded, tmp_path_factory.mktemp("world"))
    return world, LinkScene.from_layout(world.layout)


def test_a_drone_higher_above_the_same_ground_agents_has_line_of_sight_more_often(urban_town):
    world, scene = urban_town
    ground = world_snapshot(world, 5, 0, 10, seed=2)
    spots = [j.position_m for j in world.junctions] + [a.position_m[:2] for a in ground.agents]
    shares = {}
    for h in (30.0, 60.0, 150.0):
        los = []
        for k, (x, y) in enumerate(spots):
            d_actor, d_state = _drone(0, 10_000, x + 6.0, y + 6.0, h)
            snap = WorldSnapshot(k, 0, (*ground.actors, d_actor), (*ground.agents, d_state))
            links = _links(scene, snap)
            los += [s == "los" for s, t in zip(links.los, links.tx, strict=True) if t == "drone_0"]
        shares[h] = float(np.mean(los))
    assert shares[30.0] < shares[60.0] < shares[150.0], shares
    assert shares[30.0] > 0.0 and shares[150.0] > shares[30.0] + 0.1, shares


# ------------------------------------------------------------------------------- validation


def _links_edit(change):
    """A synthetic-episode edit applying ``change(payload)`` to /comm/links of tick 2."""
    def edit(tick, topic, msg):
        if topic == "/comm/links" and tick == 2:
            name, schema, payload = msg
            payload = change(json_copy(payload))
            return None if payload is None else (name, schema, payload)
        return msg
    return edit


def json_copy(value):
    import json

    return json.loads(json.dumps(value))


def _renamed(payload):
    payload["links"]["rx"][0] = "vehicle_9"
    return payload


def _short(payload):
    payload["links"]["per"] = payload["links"]["per"][:-1]
    return payload


@pytest.mark.parametrize(("change", "check", "words"), [
    (_renamed, "comm", "vehicle_9"),
    (_short, "comm", "columns differ in length"),
    (lambda p: None, "completeness", "no message on ticks 2"),
])
def test_validate_names_broken_links(tmp_path, change, check, words):
    from cosim.io import open_episode
    from cosim.io.synthetic import write_synthetic_episode
    from cosim.io.validate import validate_episode

    good = write_synthetic_episode(tmp_path / "good.mcap", ticks=4, sensors=False)
    assert validate_episode(good).ok
    with open_episode(good) as ep:
        assert len(ep.tick(1).links()) == 6  # vehicle_0, rsu_0, drone_0: every ordered pair
    bad = write_synthetic_episode(tmp_path / "bad.mcap", ticks=4, sensors=False, edit=_links_edit(change))
    report = validate_episode(bad)
    assert any(p.check == check and words in p.message and p.topic == "/comm/links" for p in report.problems), \
        report.lines()


# ------------------------------------------------------------------------------- real episodes


@pytest.fixture(scope="module")
def episodes(tmp_path_factory):
    out = {}
    for name, extra in (("on", []), ("off", ["--set", "comm.enabled=false"])):
        d = tmp_path_factory.mktemp(f"comm_{name}")
        r = run_cli("run", "scenarios/town_urban_day_clear.yaml", "--no-sensors", "--duration", "1", "-q",
                    "--set", "map.size_m=300", "--out", str(d), *extra)
        assert r.returncode == 0, r.stderr
        (out[name],) = list(d.iterdir())
    return out


@pytest.mark.integration
def test_episode_carries_valid_links_read_back_as_arrays(episodes):
    from cosim.io import open_episode
    from cosim.io.validate import validate_episode

    report = validate_episode(episodes["on"])
    assert report.ok, report.lines()
    with open_episode(episodes["on"]) as ep:
        assert ep.topics["/comm/links"].message_count == ep.n_ticks == 5
        links = ep.tick(2).links()
        n = len(ep.agents)
        assert len(links) == n * (n - 1) and set(links.tx) == set(ep.agents)
        assert links.snr_db.dtype == np.float64 and np.all(np.isfinite(links.path_loss_db))
        assert set(links.los) <= {"los", "nlosv", "nlos"} and "nlos" in links.los  # an urban town blocks links


@pytest.mark.integration
def test_comm_disabled_writes_no_links_and_changes_no_other_message(episodes):
    from cosim.io import open_episode

    with open_episode(episodes["on"]) as on, open_episode(episodes["off"]) as off:
        assert "/comm/links" not in off.topics
        assert set(on.topics) - set(off.topics) == {"/comm/links"}
        assert on.metadata == off.metadata  # only the scenario.yaml attachment names comm.enabled
        for topic in off.topics:
            assert [m.data for m in on.messages(topic)] == [m.data for m in off.messages(topic)], topic


@pytest.mark.integration
def test_cosim_comm_prints_the_summary_and_writes_the_plots(episodes, tmp_path):
    r = run_cli("comm", str(episodes["on"]), "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    assert "vehicle-vehicle" in r.stdout and "(any drone end)" in r.stdout and "5 ticks" in r.stdout
    assert (tmp_path / "comm_quality.png").stat().st_size > 10_000
    assert (tmp_path / "comm_map_t2.png").stat().st_size > 10_000
    r = run_cli("comm", str(episodes["off"]))
    assert r.returncode == 2 and "has no /comm/links topic" in r.stderr


@pytest.mark.integration  # a `cosim run` process (refused before any engine starts)
def test_bad_comm_key_is_one_clear_message_with_exit_2(tmp_path):
    r = run_cli("run", "scenarios/default.yaml", "--no-sensors", "--out", str(tmp_path), "--set", "comm.mcs=qam9")
    assert r.returncode == 2 and "comm.mcs" in r.stderr and "Traceback" not in r.stderr
    assert not list(tmp_path.iterdir())


@pytest.mark.integration
def test_a_higher_drone_has_line_of_sight_more_often_over_a_real_episode(tmp_path):
    """The same town, traffic and ground agents (same seed), hovering drones all at 30 m or all at 150 m.

    One hover drone per junction of the 300 m town (the k-th hover drone takes the k-th ranked junction, 16 in
    all), and only the drone-ground links count. One drone is too small a sample since the connected vehicles
    and RSUs sit at the inner junctions between the downtown's tall buildings (up to ~65 m): from the single
    default site (the junction nearest the centre, ~100 m from most of them) the same 5 of 8 links are LOS at
    both heights. Over every junction, 150 m sees into the street canyons more often (about 0.49 vs 0.32)."""
    from cosim.io import open_episode

    drones = "[" + ", ".join(["{strategy: hover, altitude_m: H}"] * 16) + "]"
    shares = {}
    for h in (30, 150):
        out = tmp_path / f"h{h}"
        r = run_cli("run", "scenarios/town_urban_day_clear.yaml", "--no-sensors", "--duration", "1", "-q",
                    "--set", "map.size_m=300", "--set", f"agents.drones={drones.replace('H', str(h))}",
                    "--out", str(out))
        assert r.returncode == 0, r.stderr
        (path,) = list(out.iterdir())
        with open_episode(path) as ep:
            los = []
            for k in range(ep.n_ticks):
                links = ep.tick(k).links()
                los += [s == "los" for s, tx, rx in zip(links.los, links.tx, links.rx, strict=True)
                        if tx.startswith("drone_") != rx.startswith("drone_")]
        assert len(los) > 50
        shares[h] = float(np.mean(los))
    assert shares[150] > shares[30] + 0.1, shares
