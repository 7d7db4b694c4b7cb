"""World assets v2 (issue 28): procedural vehicles and people, their boxes, the LiDAR ray drop."""

from __future__ import annotations

import math

import numpy as np
import open3d as o3d
import pytest
from cosim.sensors import catalogue
from cosim.sensors.assets import people, vehicles
from cosim.sensors.meshes import _PART_BODY, _PART_PLATE, actor_template, template_for

from cosim.geometry import quat_from_rpy
from cosim.scenario.model import LidarSpec, Mount
from cosim.snapshot import Actor


@pytest.fixture(scope="module")
def rows():
    return catalogue.catalogue()


def test_the_catalogue_has_40_vehicle_models_of_every_style_and_12_people(rows):
    veh = [r for r in rows if r["class"] != "pedestrian"]
    ped = [r for r in rows if r["class"] == "pedestrian"]
    assert len({(r["class"], r["length_m"], r["width_m"], r["height_m"]) for r in veh}) == len(veh) >= 40
    assert {r["class"] for r in veh} == {"car", "van", "truck", "bus", "motorcycle", "bicycle"}
    assert {r["style"] for r in veh} == set(vehicles.CLASS_OF_STYLE)
    assert len({(r["height_m"], r["width_m"], r["build"]) for r in ped}) == len(ped) >= 12
    assert any(r["style"] == "child" for r in ped) and any(r["style"] == "adult" for r in ped)
    assert all(200 <= r["triangles"] <= 5000 for r in rows)


def test_class_dimensions_are_the_published_ones(rows):
    def dims(cls):
        return np.array([[r["length_m"], r["width_m"], r["height_m"]] for r in rows if r["class"] == cls])

    car, mc, bike = dims("car"), dims("motorcycle"), dims("bicycle")
    assert car[:, 0].min() == pytest.approx(2.21, abs=0.1) and car[:, 0].max() <= 5.6  # Microlino .. Patrol
    assert np.all((car[:, 2] > 1.2) & (car[:, 2] < 2.06))
    assert np.all((mc[:, 0] >= 1.85) & (mc[:, 0] <= 2.4)) and np.all((mc[:, 1] > 0.6) & (mc[:, 1] < 0.9))
    assert np.all((bike[:, 0] >= 1.5) & (bike[:, 0] <= 2.45))
    people_h = [r["height_m"] for r in rows if r["class"] == "pedestrian"]
    assert min(people_h) >= 0.95 and max(people_h) <= 1.97


def test_mesh_volume_over_box_volume_is_real_world_per_class(rows):
    ranges = {"car": (0.55, 0.85), "bus": (0.8, 0.95), "pedestrian": (0.15, 0.45)}
    for r in rows:
        if r["class"] in ranges:
            lo, hi = ranges[r["class"]]
            assert lo <= r["volume_ratio"] <= hi, r


def test_vtypes_take_their_size_from_the_models():
    from cosim.world.vtypes import variants

    for cls, of_class in variants().items():
        for v in of_class:
            assert vehicles.BY_NAME[v.model].cls == cls
            assert (v.length_m, v.width_m, v.height_m) == vehicles.mesh_dims(v.model)


def test_the_tight_box_table_is_every_models_mesh_box():
    """vehicles.TIGHT_BOX_M stands in for measuring the meshes: one entry per model, each its mesh's box."""
    assert list(vehicles.TIGHT_BOX_M) == [m.name for m in vehicles.MODELS]
    wrong = [f'    "{m.name}": {vehicles.mesh_dims(m.name)!r},' for m in vehicles.MODELS
             if vehicles.TIGHT_BOX_M[m.name] != vehicles.mesh_dims(m.name)]
    assert not wrong, "TIGHT_BOX_M differs from the meshes; the lines to put there:\n" + "\n".join(wrong)


def test_every_variant_type_id_names_its_class():
    from cosim.world.vtypes import class_of_type, variants

    for vs in variants().values():
        for v in vs:
            assert class_of_type(v.type_id) == v.cls
    assert class_of_type("DEFAULT_VEHTYPE") == "DEFAULT"


def _placed_extent(actor: Actor) -> tuple[np.ndarray, np.ndarray]:
    from cosim.sensors.scene import place_actors

    mesh, _ = place_actors([actor])
    return mesh.vertices.min(0), mesh.vertices.max(0)


@pytest.mark.parametrize("name", [m.name for m in vehicles.MODELS])
def test_every_model_fills_its_label_box_within_a_centimetre(name):
    size = vehicles.dims(name)
    cls = vehicles.BY_NAME[name].cls
    a = Actor(7, cls, (10.0, -4.0, size[2] / 2), size, quat_from_rpy(0, 0, 0), (0.0, 0.0, 0.0), source_id="x")
    assert actor_template(a).name == name  # the vType's size picks the model
    lo, hi = _placed_extent(a)
    box_lo = np.array([10.0, -4.0, 0.0]) - np.array([size[0] / 2, size[1] / 2, 0.0])
    box_hi = box_lo + np.array(size)
    assert np.all(np.abs(lo - box_lo) <= 0.01) and np.all(np.abs(hi - box_hi) <= 0.01)
    raw = vehicles.build(name)[0]
    assert np.all(np.abs((raw.max(0) - raw.min(0)) - size) <= 0.005)  # the model's own size, unscaled


@pytest.mark.parametrize("name", [m.name for m in vehicles.MODELS if m.cls in ("car", "van", "truck", "bus")])
def test_a_lidar_finds_no_hole_in_a_hull(name):
    """Rays from inside the hull in every direction all meet its surface from inside (outward normals)."""
    v, t, _, _, comp = vehicles.build(name)
    t = t[comp == 0]  # the lofted hull (the first part)
    hv = v[np.unique(t)]
    x_mid = np.median(hv[:, 0])
    section = hv[np.abs(hv[:, 0] - x_mid) <= np.sort(np.abs(hv[:, 0] - x_mid))[7] + 1e-9]
    inside = section.mean(0)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(t.astype(np.uint32)))
    rng = np.random.default_rng(0)
    d = rng.standard_normal((4000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rays = np.concatenate([np.broadcast_to(inside, d.shape), d], 1).astype(np.float32)
    ans = scene.cast_rays(o3d.core.Tensor(rays))
    assert np.all(np.isfinite(ans["t_hit"].numpy())), "a ray escaped the hull"
    n = ans["primitive_normals"].numpy()
    assert np.all((n * d).sum(1) > 0), "a hull face is wound inward"


def test_a_walking_persons_limbs_move_between_ticks_and_the_box_follows():
    key = "walker_1"
    boxes, meshes = [], []
    for phase in (0.0, 0.125, 0.25):
        size, centre = people.posed_box(key, phase, 1.4)
        _, v, _, _, _, lo, hi = people.posed(key, phase, 1.4)
        assert np.allclose(hi - lo, size) and np.allclose((lo + hi) / 2, centre)
        a = Actor(3, "pedestrian", (0.0, 0.0, size[2] / 2), size, quat_from_rpy(0, 0, 0), (1.4, 0.0, 0.0),
                  source_id=key, gait_phase=phase)
        plo, phi = _placed_extent(a)
        assert np.allclose(phi - plo, size, atol=1e-3)  # the placed body fills exactly its label box
        boxes.append(np.array(size))
        meshes.append(v)
    moved = [np.abs(meshes[k + 1] - meshes[k]).max() for k in range(2)]
    assert min(moved) > 0.05  # limbs swing between ticks 1/8 of a cycle apart
    assert np.abs(boxes[0][0] - boxes[2][0]) > 0.1  # the box's length follows the stride
    # standing still: the same body at any phase, legs together
    s0 = people.posed(key, 0.0, 0.0)[1]
    assert np.array_equal(s0, people.posed(key, 0.6, 0.0)[1])
    assert people.posed_box(key, 0.3, 0.0)[0][0] < boxes[2][0]


def test_the_fast_pedestrian_box_is_the_posed_meshs_box_bit_for_bit():
    """posed_box builds no mesh (body_points: the same vertices, no triangles); over people of every age
    and build, all phase steps of a cycle and speeds from standing to running, it equals the posed
    mesh's tight box exactly."""
    keys = [f"ped_{k}" for k in range(12)] + ["walker_1"]
    assert {people.Person.from_key(k).child for k in keys} == {True, False}
    n = 0
    for key in keys:
        for q_phase in range(0, people.PHASE_STEPS, 5):
            for q_speed in (0, 7, 20, 28, 45, 60):
                phase, speed = q_phase / people.PHASE_STEPS, q_speed / 20
                _, v, _, _, _, lo, hi = people.posed(key, phase, speed)
                assert np.array_equal(v.min(0), lo) and np.array_equal(v.max(0), hi)
                size, centre = people.posed_box(key, phase, speed)
                assert size == tuple(float(x) for x in hi - lo)
                assert centre == tuple(float(x) for x in (lo + hi) / 2)
                n += 1
    assert n == len(keys) * 52 * 6


def test_people_differ_in_height_build_and_clothes():
    ps = [people.Person.from_key(k) for k in catalogue.people_keys()]
    assert len({(p.height_m, p.build) for p in ps}) == len(ps) >= 12
    assert len({p.colours[2].tobytes() for p in ps}) >= 4
    assert max(p.build for p in ps) - min(p.build for p in ps) > 0.2
    kids = [p for p in ps if p.child]
    assert kids and all(1.0 <= p.height_m <= 1.3 for p in kids)
    assert all(1.5 <= p.height_m <= 1.95 for p in ps if not p.child)


def test_riders_sit_on_their_two_wheelers():
    for m in vehicles.MODELS:
        if m.cls in ("motorcycle", "bicycle"):
            _, _, part, _, _ = vehicles.build(m.name)
            assert np.any(part == people.PART_SKIN) and np.any(part == people.PART_SHOES), m.name
            assert template_for(m.cls).palette is not None


# ------------------------------------------------------------------------------ LiDAR


def _wall_scene(distance_m: float, actors=()):
    """A building wall across +x at ``distance_m`` (and ``actors``), nothing else."""
    from cosim.sensors.meshes import static_mesh
    from cosim.sensors.scene import StaticScene, TickScene

    from cosim.world.types import Prism, StaticLayout

    wall = Prism("building", ((distance_m, -40.0), (distance_m + 1, -40.0), (distance_m + 1, 40.0),
                              (distance_m, 40.0)), 0.0, 30.0, 1_000_001)
    return TickScene.build(StaticScene(static_mesh(StaticLayout((wall,)))), list(actors))


def _atm():
    from cosim.sensors.environment import atmosphere

    from cosim.scenario.model import EnvironmentSpec

    return atmosphere(EnvironmentSpec(weather="clear", lighting="day"))


def _sweep(spec: LidarSpec, scene, seed: int = 1):
    from cosim.sensors.lidar import render_lidar
    from cosim.sensors.rig import Pose

    pose = Pose(np.eye(3), np.array([0.0, 0.0, 2.0]))
    return render_lidar("v", spec, pose, scene, _atm(), np.random.default_rng(seed))


def test_ray_drop_share_on_a_flat_wall_is_the_configured_one():
    base = dict(channels=32, upper_fov_deg=10.0, lower_fov_deg=-5.0, horizontal_resolution_deg=0.2, range_m=200.0,
                motion_distortion=False, mount=Mount(xyz_m=(0.0, 0.0, 0.0)), range_noise_m=0.0)
    scene = _wall_scene(20.0)
    off = LidarSpec(**base, dropoff_general_rate=0.0, dropoff_intensity_limit=0.0, detection_range_10pct_m=5000)
    n_all = _sweep(off, scene).n_points
    assert n_all > 1000
    for rate in (0.1, 0.45):
        spec = LidarSpec(**base, dropoff_general_rate=rate, dropoff_intensity_limit=0.0, detection_range_10pct_m=5000)
        share = 1 - _sweep(spec, scene).n_points / n_all
        assert abs(share - rate) <= 0.01, (rate, share)
    # CARLA's intensity rule: a wall darker than the limit loses dropoff_zero_intensity x (1 - I / limit)
    spec = LidarSpec(**base, dropoff_general_rate=0.0, dropoff_intensity_limit=1.0, dropoff_zero_intensity=0.5,
                     detection_range_10pct_m=5000)
    frame = _sweep(spec, scene)
    i_mean = float(_sweep(off, scene).intensity.mean())
    expect = 0.5 * (1 - i_mean)
    assert abs((1 - frame.n_points / n_all) - expect) <= 0.01


def test_defaults_drop_far_and_grazing_returns_more_than_near_ones():
    from cosim.sensors.lidar import drop_probability

    spec = LidarSpec()
    r = np.array([10.0, 50.0, 100.0, 10.0])
    energy = np.array([0.3, 0.3, 0.3, 0.3 * 0.05])  # the last one at grazing incidence
    p = drop_probability(spec, np.full(4, 0.3), r, energy, np.zeros(4), np.zeros(4, bool), np.zeros(4))
    assert p[0] == pytest.approx(spec.dropoff_general_rate, abs=0.01)
    assert p[0] < p[1] < p[2] and p[3] > p[0]
    glass = drop_probability(spec, np.full(1, 0.05), r[:1], energy[:1], np.zeros(1), np.ones(1, bool), np.zeros(1))
    assert glass[0] > 0.8
    retro = drop_probability(spec, np.full(1, 0.0), r[2:3], energy[:1] * 0, np.ones(1), np.ones(1, bool), np.ones(1))
    assert retro[0] == 0.0


def test_licence_plates_outshine_paint_in_lidar_intensity():
    from cosim.sensors.lidar import _surface_intensity

    size = vehicles.dims("saloon_1")
    car = Actor(5, "car", (8.0, 0.0, size[2] / 2), size, quat_from_rpy(0, 0, math.pi), (0.0, 0.0, 0.0), source_id="c")
    scene = _wall_scene(60.0, [car])
    ys, zs = np.meshgrid(np.linspace(-1.2, 1.2, 160), np.linspace(0.1, 1.4, 120))
    d = np.stack([np.full(ys.size, 6.0), ys.ravel(), zs.ravel() - 1.0], 1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rays = np.concatenate([np.broadcast_to([0.0, 0.0, 1.0], d.shape), d], 1).astype(np.float32)
    t, gid = scene.cast(rays)
    hit = gid >= scene.n_static
    atm = _atm()
    inten, _, _ = _surface_intensity(scene, atm, gid[hit], d[hit], t[hit].astype(np.float64))
    part = actor_template(car).part[gid[hit] - scene.n_static]
    plate, paint = inten[part == _PART_PLATE], inten[part == _PART_BODY]
    assert len(plate) > 5 and len(paint) > 50
    assert plate.min() > paint.max()


def _tree_prisms(x: float, y: float, radius: float = 2.5, height: float = 9.0):
    from cosim.world.types import Prism

    trunk = Prism("vegetation", ((x - 0.2, y - 0.2), (x + 0.2, y - 0.2), (x + 0.2, y + 0.2), (x - 0.2, y + 0.2)),
                  0.0, 2.5, 0)
    ang = np.arange(8) * math.pi / 4 + 0.3
    crown = Prism("vegetation", tuple((x + radius * math.cos(a), y + radius * math.sin(a)) for a in ang), 2.5,
                  height, 0)
    return [trunk, crown]


def test_every_species_crown_passes_10_to_50_percent_of_lidar_rays():
    from cosim.sensors.assets.vegetation import SPECIES, species_of
    from cosim.sensors.lidar import _through_crowns
    from cosim.sensors.meshes import static_mesh
    from cosim.sensors.scene import StaticScene, TickScene

    from cosim.world.types import Prism, StaticLayout

    for species in SPECIES:
        y = next(float(y) for y in np.arange(0.0, 50.0, 0.5) if species_of(15.0, float(y)) == species)
        wall = Prism("building", ((30.0, y - 20), (31.0, y - 20), (31.0, y + 20), (30.0, y + 20)), 0.0, 30.0,
                     1_000_001)
        scene = TickScene.build(StaticScene(static_mesh(StaticLayout((*_tree_prisms(15.0, y), wall)))), [])
        assert scene.static.mesh.n_triangles > 100  # a trunk, branches and a crown, not two prisms
        zs, ys = np.meshgrid(np.linspace(2.0, 10.0, 80), np.linspace(y - 3.0, y + 3.0, 80))
        d = np.stack([np.full(ys.size, 15.0), ys.ravel() - y, zs.ravel() - 5.5], 1)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        rays = np.concatenate([np.broadcast_to([0.0, y, 5.5], d.shape), d], 1).astype(np.float32)
        t, gid = scene.cast(rays)
        crown = np.take(scene.labels["leaf_density"], gid) > 0
        assert crown.sum() > 500
        t2, g2 = _through_crowns(scene, rays, t, gid, np.random.default_rng(3).random(len(rays)), None,
                                 np.zeros(len(rays)))
        behind = np.take(scene.labels["instance"], g2[crown]) == 1_000_001
        assert 0.10 <= behind.mean() <= 0.50, (species, behind.mean())
        assert np.all(t2[crown] >= t[crown])  # never in front of the crown's surface


def test_cosim_assets_writes_the_catalogue_and_refuses_a_file_as_folder(tmp_path, capsys):
    import json

    from cosim.cli import main

    assert main(["assets", "--out", str(tmp_path / "cat"), "--no-pictures"]) == 0
    data = json.loads((tmp_path / "cat" / "catalogue.json").read_text())
    names = [m["name"] for m in data["models"]]
    assert len(names) == len(set(names)) == len(vehicles.MODELS) + catalogue.N_PEOPLE
    assert {"name", "class", "style", "length_m", "width_m", "height_m", "triangles", "volume_ratio"} <= set(
        data["models"][0])
    assert "51 vehicle models, 16 people" in capsys.readouterr().out
    (tmp_path / "file").write_text("x")
    assert main(["assets", "--out", str(tmp_path / "file")]) == 2
    assert "not a folder" in capsys.readouterr().err


def test_gallery_pictures_show_the_models(tmp_path):
    from PIL import Image

    catalogue.gallery(["saloon_0", "person_1"], tmp_path / "g.png", px=60, cols=2)
    img = np.asarray(Image.open(tmp_path / "g.png").convert("RGB")).astype(int)
    assert img.shape == (74, 240, 3)
    for cell in (img[14:, :120], img[14:, 120:]):  # each model's two views differ from the background
        assert (np.abs(cell - [237, 240, 245]).sum(axis=2) > 60).mean() > 0.05
    catalogue.lidar_gallery(["saloon_0"], tmp_path / "l.png", px=80)
    assert len(catalogue.lidar_scan("saloon_0", 10.0)) > 10 * len(catalogue.lidar_scan("saloon_0", 40.0)) > 0
    # the street furniture: a signal head with its green lamp lit, the signs' red faces
    catalogue.gallery(list(catalogue.FURNITURE), tmp_path / "f.png", px=120, cols=4)
    img = np.asarray(Image.open(tmp_path / "f.png").convert("RGB")).astype(int)
    cells = [img[14:, k * 240:(k + 1) * 240] for k in range(4)]
    assert ((cells[0][..., 1] > 200) & (cells[0][..., 0] < 120)).sum() > 3  # lit green
    for cell in cells[1:]:
        assert ((cell[..., 0] > 150) & (cell[..., 1] < 60)).sum() > 20  # red sheeting


def test_cosim_assets_refuses_an_unwritable_folder_at_once(capsys):
    from cosim.cli import main

    assert main(["assets", "--out", "/proc/cosim_assets"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "/proc/cosim_assets" in err


# ----------------------------------------------------------------------------------- traffic signs

#: a hand-made network: a main road west -> east (50 km/h) crossed at x = 0 by a minor road from the south
#: that yields (state m) and continues north at 30 km/h
_SIGN_NET = b"""<net>
  <edge id="w"><lane id="w_0" index="0" speed="13.89" width="3.2" shape="-100,-1.6 -10,-1.6"/></edge>
  <edge id="e"><lane id="e_0" index="0" speed="13.89" width="3.2" shape="10,-1.6 100,-1.6"/></edge>
  <edge id="s"><lane id="s_0" index="0" speed="13.89" width="3.2" shape="1.6,-100 1.6,-10"/></edge>
  <edge id="n"><lane id="n_0" index="0" speed="8.33" width="3.2" shape="1.6,10 1.6,100"/></edge>
  <connection from="w" to="e" fromLane="0" toLane="0" state="M"/>
  <connection from="s" to="n" fromLane="0" toLane="0" state="m"/>
  <connection from="s" to="e" fromLane="0" toLane="0" state="m"/>
</net>"""


def test_signs_stand_where_the_network_asks_for_them():
    """A give-way sign at the right kerb of the yielding approach's stop line, facing its traffic, none on
    the major road; a 30 km/h sign where the road's speed drops."""
    from cosim.world.traffic_signs import traffic_signs

    signs = {s.sign_id: s for s in traffic_signs(_SIGN_NET)}
    assert set(signs) == {"give_way/s", "speed_limit/n"}  # e keeps the speed of the roads into it
    gw = signs["give_way/s"]
    assert gw.xy == pytest.approx((1.6 + 1.6 + 1.0, -10.0))  # right of the lane's edge, at the stop line
    assert gw.yaw_rad == pytest.approx(-math.pi / 2)  # traffic comes from the south heading north: face south
    assert signs["speed_limit/n"].value_kmh == 30
    x, y = signs["speed_limit/n"].xy
    assert x > 1.6 + 1.6 and 10 < y < 20  # just past the junction, on the right
    stop = _SIGN_NET.replace(b'state="m"', b'state="s"')
    assert {s.kind for s in traffic_signs(stop)} == {"stop", "speed_limit"}


def test_retro_reflective_signs_outshine_paint_in_lidar_intensity():
    from cosim.sensors.lidar import _surface_intensity
    from cosim.sensors.meshes import concat, static_mesh
    from cosim.sensors.scene import StaticScene, TickScene
    from cosim.sensors.signals import sign_mesh

    from cosim.classes import SEMANTIC_ID
    from cosim.world.traffic_signs import TrafficSign
    from cosim.world.types import Prism, StaticLayout

    signs = [TrafficSign(f"{k}/x", k, 50, (12.0, 2.5 * i - 2.5), math.pi) for i, k in
             enumerate(("stop", "give_way", "speed_limit"))]
    wall = Prism("building", ((60.0, -40.0), (61.0, -40.0), (61.0, 40.0), (60.0, 40.0)), 0.0, 30.0, 1_000_001)
    size = vehicles.dims("saloon_1")
    car = Actor(5, "car", (9.0, 6.0, size[2] / 2), size, quat_from_rpy(0, 0, math.pi / 2), (0.0, 0.0, 0.0),
                source_id="c")
    scene = TickScene.build(StaticScene(concat([static_mesh(StaticLayout((wall,))), sign_mesh(signs)])), [car])
    ys, zs = np.meshgrid(np.linspace(-5, 8, 260), np.linspace(0.3, 2.8, 100))
    d = np.stack([np.where(ys > 4.5, 9.0, 12.0) * np.ones_like(ys), ys, zs - 1.0], -1).reshape(-1, 3)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rays = np.concatenate([np.broadcast_to([0.0, 0.0, 1.0], d.shape), d], 1).astype(np.float32)
    t, gid = scene.cast(rays)
    hit = gid < scene.miss
    inten, _, _ = _surface_intensity(scene, _atm(), gid[hit], d[hit], t[hit].astype(np.float64))
    sem = scene.labels["semantic"][gid[hit]]
    face = inten[(sem == SEMANTIC_ID["traffic_sign"]) & (scene.labels["retro"][gid[hit]] > 0)]
    part = actor_template(car).part[np.clip(gid[hit] - scene.n_static, 0, None)]
    paint = inten[(gid[hit] >= scene.n_static) & (part == _PART_BODY)]
    assert len(face) > 50 and len(paint) > 50
    assert face.min() > paint.max()
    assert {int(i) for i in scene.labels["instance"][gid[hit]][sem == SEMANTIC_ID["traffic_sign"]]} == \
        {4_000_000, 4_000_001, 4_000_002}  # every sign seen
