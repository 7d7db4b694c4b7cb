"""The ray-backend seam (issue 36): every backend hits what the reference hits, labels stay exact to what
each one rendered, and the scenario key is checked like every other."""

from __future__ import annotations

import subprocess
import sys
from typing import get_args

import numpy as np
import pytest
from cosim.sensors import SensorSuite
from cosim.sensors.camera import Occluders, StaticImage, cast_image
from cosim.sensors.raycast import RAY_BACKENDS, backend_names, build, ray_backend
from cosim.sensors.rig import camera_pose, intrinsics
from cosim.sensors.synthetic import synthetic_scenario, synthetic_snapshot, synthetic_world

from cosim.errors import InputError
from cosim.scenario.model import CameraSpec, LidarSpec, RigSpec, SensorsSpec, default_rsu_rig, default_vehicle_rig
from tests.helpers import REPO, run_cli

BACKENDS = ("open3d", "embree")


def _scenario(backend: str):
    vcams = [CameraSpec(name=c.name, width=320, height=180, mount=c.mount) for c in default_vehicle_rig().cameras[:3]]
    rcams = [CameraSpec(name=c.name, width=320, height=180, mount=c.mount) for c in default_rsu_rig().cameras[:2]]
    lidar = LidarSpec(horizontal_resolution_deg=1.0)
    sensors = SensorsSpec(vehicle=RigSpec(lidar=lidar, cameras=vcams), rsu=RigSpec(lidar=lidar, cameras=rcams),
                          ray_backend=backend)
    return synthetic_scenario(vehicles=3, rsus=2, sensors=sensors)


@pytest.fixture(scope="module")
def rendered():
    """Per backend: the suite, the tick, the frames and every camera's global triangle index image."""
    world = synthetic_world()
    snap = synthetic_snapshot(3, 2, 0)
    out = {}
    for name in BACKENDS:
        suite = SensorSuite(_scenario(name), world, encode_images=False, workers=1)
        frames = suite.render(snap, np.random.default_rng(0))
        tick = suite._prepare(snap)
        gids = {}
        for agent in snap.agents:
            own = agent.track_id if agent.track_id is not None else tick.own_track.get(agent.agent_id)
            occ = Occluders(suite._thin, suite._static_points, tick.a_corners[tick.a_tracks != own], suite._sun,
                            None if suite._sun is None else tick.shadow_boxes)
            for cam in suite.rig(agent).cameras:
                fixed = StaticImage() if agent.kind == "rsu" else None  # as the suite casts them
                gids[(agent.agent_id, cam.name)] = cast_image(cam, intrinsics(cam), camera_pose(agent, cam),
                                                              tick.scene, occ, own, suite.block_px, fixed)[0]
        out[name] = (suite, tick, frames, gids)
    yield out
    for suite, *_ in out.values():
        suite.close()


def test_the_scenario_key_lists_every_registered_backend():
    assert set(get_args(SensorsSpec.model_fields["ray_backend"].annotation)) == set(backend_names())
    assert SensorsSpec().ray_backend == "embree"
    for name in BACKENDS:
        assert ray_backend(name).name == name and name in RAY_BACKENDS


def test_an_unknown_backend_is_an_input_error_listing_the_known_ones():
    with pytest.raises(InputError, match="unknown ray backend 'optix'; known: embree, open3d"):
        ray_backend("optix")


def test_the_known_backends_are_listed_before_any_of_them_is_imported():
    """In a fresh process neither backend module is imported yet (they load their engines when chosen): the
    message still lists both (it listed the registered ones only, so what it said hung on earlier imports)."""
    code = ("import sys; from cosim.sensors.raycast import ray_backend\n"
            "assert 'cosim.sensors.ray_open3d' not in sys.modules\n"
            "try:\n    ray_backend('optix')\nexcept Exception as e:\n    print(e)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "unknown ray backend 'optix'; known: embree, open3d"


@pytest.mark.integration  # a `cosim run` process, refused before any engine starts
def test_cli_refuses_an_unknown_backend_with_exit_2_and_the_key_path(tmp_path):
    f = tmp_path / "bad.yaml"
    f.write_text("name: t\nsensors:\n  ray_backend: optix\n")
    r = run_cli("run", str(f), "--out", str(tmp_path / "out"), timeout=60)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    assert "bad.yaml:3: sensors.ray_backend: Input should be 'embree' or 'open3d'" in r.stderr


def test_triangle_ids_agree_between_backends_on_a_tick(rendered):
    ref, other = rendered["open3d"][3], rendered["embree"][3]
    same = sum(int(np.sum(ref[k] == other[k])) for k in ref)
    total = sum(g.size for g in ref.values())
    assert same / total >= 0.995, f"{same / total:.4%} of {total} pixels hit the same triangle"


@pytest.mark.parametrize("backend", BACKENDS)
def test_labels_are_exact_to_what_each_backend_rendered(rendered, backend):
    _, tick, frames, gids = rendered[backend]
    lut = tick.lut
    for (agent_id, cam_name), gid in gids.items():
        f = frames.agents[agent_id].cameras[cam_name]
        assert np.array_equal(f.semantic, lut["semantic"][gid]), (agent_id, cam_name)
        assert np.array_equal(f.instance, lut["instance"][gid]), (agent_id, cam_name)
        assert np.array_equal(np.isfinite(f.depth), gid != tick.scene.miss), (agent_id, cam_name)


def test_lidar_sweeps_agree_between_backends(rendered):
    a, b = rendered["open3d"][2], rendered["embree"][2]
    for agent_id, fa in a.agents.items():
        la, lb = fa.lidar, b.agents[agent_id].lidar
        if la is None:
            continue
        assert abs(la.n_points - lb.n_points) <= 0.005 * la.n_points, agent_id
        if la.n_points == lb.n_points:
            assert np.mean(la.instance_id == lb.instance_id) >= 0.995, agent_id


def _box(c, h):
    v = np.array([[x, y, z] for z in (-h, h) for y in (-h, h) for x in (-h, h)], np.float32) + np.float32(c)
    t = np.array([[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4], [2, 6, 3], [3, 6, 7],
                  [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]], np.uint32)
    return v, t


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_ray_meets_a_box_at_the_analytic_distance_and_occluded_agrees(backend):
    v, t = _box((10.0, 0.0, 0.0), 1.0)
    scene = build(ray_backend(backend), v, t, "high")
    rng = np.random.default_rng(1)
    n = 4000
    rays = np.zeros((n, 6), np.float32)
    rays[:, 3:] = rng.normal(size=(n, 3))
    rays[:, 3:] /= np.linalg.norm(rays[:, 3:], axis=1, keepdims=True)
    rays[:2, 3:] = [[1, 0, 0], [-1, 0, 0]]
    t_hit, prim = scene.closest(rays)
    assert t_hit[0] == pytest.approx(9.0, abs=1e-5) and prim[0] >= 0
    assert np.isinf(t_hit[1]) and prim[1] == -1
    assert np.array_equal(np.isfinite(t_hit), prim >= 0)
    assert np.array_equal(scene.occluded(rays), prim >= 0)
    assert build(ray_backend(backend), v[:0], t[:0], "low") is None


@pytest.mark.parametrize("backend", BACKENDS)
def test_actors_moved_to_a_time_are_hit_where_they_are_then(backend):
    from cosim.sensors.meshes import static_mesh
    from cosim.sensors.scene import StaticScene, TickScene
    from cosim.sensors.synthetic import synthetic_world as world

    from cosim.snapshot import Actor

    car = Actor(track_id=7, cls="car", center_m=(20.0, 0.0, 0.75), size_m=(4.5, 1.8, 1.5),
                rotation=(0.0, 0.0, 0.0, 1.0), velocity_mps=(10.0, 0.0, 0.0))
    scene = TickScene.build(StaticScene(static_mesh(world().layout), backend), [car])
    ray = np.array([[20.0, -10.0, 0.75, 0.0, 1.0, 0.0], [15.0, -10.0, 0.75, 0.0, 1.0, 0.0]], np.float32)
    t_now, g_now = scene.cast(ray, with_static=False)
    t_before, g_before = scene.cast(ray, with_static=False, dt_s=-0.5)  # the car was 5 m back
    assert 10.0 - 0.9 - 1e-3 <= t_now[0] <= 10.0  # the body, inside its box (side 0.9 m from the centre line)
    assert np.isinf(t_now[1])
    assert np.isinf(t_before[0]) and np.isfinite(t_before[1])
    assert scene.labels["instance"][g_now[0]] == 7 and scene.labels["instance"][g_before[1]] == 7


def test_actors_at_a_time_as_instances_hit_what_the_moved_mesh_hits():
    """The embree backend casts the actors at a LiDAR firing's time as translated instances of one scene per
    actor (TickScene._moved) instead of a new BVH of the moved mesh: the same triangles, the same distances
    to float32 rounding, and the same when a sensor's own shape is left out."""
    import dataclasses

    from cosim.sensors.scene import StaticScene, TickScene

    world = synthetic_world()
    snap = synthetic_snapshot(3, 2, 1)
    moving = tuple(dataclasses.replace(a, velocity_mps=(12.0 - 2 * k % 7, 3.0 - k % 5, 0.0))
                   for k, a in enumerate(snap.actors))
    suite = SensorSuite(_scenario("embree"), world, encode_images=False, workers=1)
    static = StaticScene(suite.static.mesh, "embree")
    suite.close()
    inst = TickScene.build(static, moving)
    flat = dataclasses.replace(TickScene.build(static, moving), actor_counts=None)  # the moved-mesh path
    rng = np.random.default_rng(11)
    centres = np.array([a.center_m for a in moving])
    aim = centres[rng.integers(0, len(centres), 20_000)] + rng.normal(0.0, 1.5, (20_000, 3))
    origin = aim + rng.normal(0.0, 25.0, (20_000, 3)) * [1, 1, 0.2] + [0, 0, 3.0]
    d = aim - origin
    rays = np.concatenate([origin, d / np.linalg.norm(d, axis=1, keepdims=True)], axis=1).astype(np.float32)
    own = moving[0].track_id
    for dt in (-0.04, -0.01):
        assert inst._actor_scene(dt).handle.__class__.__name__ == "EmbreeInstances"
        for exclude in (None, own):
            t_i, p_i = inst._cast_actors(rays, exclude, dt)
            t_f, p_f = flat._cast_actors(rays, exclude, dt)
            hit = p_f >= 0
            assert hit.mean() > 0.3  # the rays were aimed at the actors
            assert np.mean(p_i == p_f) >= 0.999
            same = hit & (p_i == p_f)
            assert np.allclose(t_i[same], t_f[same], rtol=0, atol=2e-4)
            if exclude is not None:
                assert not np.any(np.isin(p_i[p_i >= 0], np.nonzero(inst.actor_track == own)[0]))
