"""Ray backends side by side on one real tick of the paper's full rig (issue 36).

    PYTHONPATH=. .venv/bin/python benchmarks/ray_backends.py [--repeats 3] [--backends open3d,embree]
    PYTHONPATH=. .venv/bin/python benchmarks/ray_backends.py --export tick.npz

Builds the world of scenarios/default.yaml with the rig of benchmarks/sensors.py (5 vehicles, 5 RSUs,
5 drones, 55 cameras at 1280x720, 15 LiDARs), places ``world_snapshot`` (seed 0, 40 road users at
12 m/s), and measures, per backend, the CPU-seconds of this process (every thread: Open3D casts on its
own threads) for

- *coherent image*: one ray per pixel of vehicle_0's front camera against one scene of the static world
  and the actors, in row order, and the sun-shadow rays of its hits (``occluded``);
- *adaptive tick*: every camera of the tick cast as the renderer casts it (``cast_image``, quadtree
  refinement, sun shadows, actors), no image kept between ticks;
- *LiDAR tick*: every LiDAR of the tick (``render_lidar``: motion distortion, crowns, ray drop).

Each measurement alternates the backends ``--repeats`` times (the median is printed) so that load
changes hit both alike; then the ratios, and the triangle-id agreement of the adaptive images and the
LiDAR sweeps (the same global index per pixel/return).

``--export PATH`` writes the tick for ``benchmarks/device_probe.py`` instead (a compressed .npz of about
1.2 MB): the static + actor triangles, vehicle_0's front camera and its triangle ids per pixel from the
embree backend (one ray per pixel, -1 for a miss).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from cosim.sensors import SensorSuite, kernels
from cosim.sensors.camera import NEAR_CLIP_M, Occluders, _rays, cast_image
from cosim.sensors.lidar import render_lidar
from cosim.sensors.raycast import build, ray_backend
from cosim.sensors.rig import camera_pose, intrinsics, sensor_pose
from cosim.sensors.scene import static_bare_mesh
from cosim.sensors.synthetic import world_snapshot

from benchmarks.sensors import paper_rig_scenario
from cosim.world.build import build_world

ROOT = Path(__file__).resolve().parents[1]


def camera_rays(cam, K, pose) -> np.ndarray:
    """One ray per pixel (H W, 6), row-major, starting at the near clip."""
    xs = (np.arange(cam.width) + 0.5 - K[0, 2]) / K[0, 0]
    ys = (np.arange(cam.height) + 0.5 - K[1, 2]) / K[1, 1]
    gx, gy = np.meshgrid(xs, ys)
    return _rays(pose, gx.ravel(), gy.ravel(), NEAR_CLIP_M)


def cpu(fn) -> tuple[float, object]:
    c0 = time.process_time()
    out = fn()
    return time.process_time() - c0, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--backends", default="open3d,embree")
    ap.add_argument("--export", type=Path, help="write the tick for benchmarks/device_probe.py and exit")
    args = ap.parse_args()
    names = args.backends.split(",")
    loaded = paper_rig_scenario(ROOT / "scenarios" / "default.yaml")
    with tempfile.TemporaryDirectory() as tmp:
        world = build_world(loaded, Path(tmp))
    snap = world_snapshot(world, 5, 5, 40, seed=0, tick=0, speed_mps=12.0)
    base = json.loads(json.dumps(loaded.resolved))
    suites = {}
    for name in names:
        data = json.loads(json.dumps(base))
        data["sensors"]["ray_backend"] = name
        from cosim.scenario.loader import load_scenario_data

        suites[name] = SensorSuite(load_scenario_data(data).scenario, world, encode_images=False, workers=1)
    first = suites[names[0]]
    sc = first.scenario
    agents = {a.agent_id: a for a in snap.agents}
    car = agents["vehicle_0"]
    cam = sc.rig_for("vehicle_0").cameras[0]
    K, pose = intrinsics(cam), camera_pose(car, cam)
    mesh = static_bare_mesh(first.static, snap.actors)
    rays = camera_rays(cam, K, pose)

    if args.export:
        scene = build(ray_backend("embree"), mesh.vertices, mesh.triangles, "high")
        t, prim = scene.closest(rays)
        args.export.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(args.export, vertices=mesh.vertices.astype(np.float32),
                            triangles=mesh.triangles.astype(np.uint32), rays=np.zeros(0),
                            cam_K=K, cam_rotation=pose.rotation, cam_position=pose.position_m,
                            cam_size=np.array([cam.width, cam.height]), near_m=np.float64(NEAR_CLIP_M),
                            cpu_prim=prim.reshape(cam.height, cam.width).astype(np.int32),
                            cpu_t=t.reshape(cam.height, cam.width).astype(np.float16))
        print(f"wrote {args.export}: {mesh.n_triangles} triangles, camera {cam.width}x{cam.height}, "
              f"{args.export.stat().st_size / 1e6:.1f} MB")
        return

    sun = first.atm.sun_dir.astype(np.float32)
    scenes = {n: build(ray_backend(n), mesh.vertices, mesh.triangles, "high") for n in names}
    res: dict[str, dict[str, list[float]]] = {n: {} for n in names}
    hits: dict[str, dict] = {n: {} for n in names}

    def add(n: str, key: str, value: float) -> None:
        res[n].setdefault(key, []).append(value)

    ticks = {n: suites[n]._prepare(snap) for n in names}
    lab_n = np.concatenate([mesh.normals(), [[0, 0, 1]]]).astype(np.float32)
    for _ in range(args.repeats):
        for n in names:
            scene = scenes[n]
            c, (t, g) = cpu(lambda scene=scene: scene.closest(rays))
            add(n, "image, row order", c)
            gid = np.where(g >= 0, g, mesh.n_triangles).astype(np.int32)
            sh, _ = kernels.shadow_rays(rays, t, gid, lab_n, sun, np.float32(0.02))
            c, occ = cpu(lambda scene=scene, sh=sh: scene.occluded(sh))
            add(n, "shadow rays (occluded)", c)
            hits[n]["shadow"] = occ
            hits[n]["image"] = g
            tick = ticks[n]
            suite = suites[n]

            def adaptive(tick=tick, suite=suite):
                out = {}
                for agent in snap.agents:
                    own = agent.track_id if agent.track_id is not None else tick.own_track.get(agent.agent_id)
                    occ = Occluders(suite._thin, suite._static_points, tick.a_corners[tick.a_tracks != own],
                                    suite._sun, None if suite._sun is None else tick.shadow_boxes)
                    for cm in suite.rig(agent).cameras:
                        out[(agent.agent_id, cm.name)] = cast_image(cm, intrinsics(cm), camera_pose(agent, cm),
                                                                    tick.scene, occ, own, suite.block_px)[0]
                return out

            r0 = tick.scene.timer.rays
            c, imgs = cpu(adaptive)
            add(n, "adaptive tick (55 cameras)", c)
            hits[n]["adaptive_rays"] = tick.scene.timer.rays - r0
            hits[n]["adaptive"] = imgs

            def lidars(tick=tick, suite=suite):
                out = {}
                for agent in snap.agents:
                    rig = suite.rig(agent)
                    if rig.lidar is None:
                        continue
                    own = agent.track_id if agent.track_id is not None else tick.own_track.get(agent.agent_id)
                    f = render_lidar(agent.agent_id, rig.lidar, sensor_pose(agent, rig.lidar.mount), tick.scene,
                                     suite.atm, np.random.default_rng(0), own, True, None, agent, snap.t_ns)
                    out[agent.agent_id] = f
                return out

            c, lid = cpu(lidars)
            add(n, "LiDAR tick (15 sweeps)", c)
            hits[n]["lidar"] = lid
    print(f"tick: {mesh.n_triangles} triangles (static {first.static.n_triangles}); camera {cam.width}x{cam.height}; "
          f"{len(sh)} shadow rays; median CPU-s of {args.repeats} alternating runs")
    ref = names[0]
    for key in res[ref]:
        cells = [f"{n} {np.median(res[n][key]):.3f}" for n in names]
        ratios = [f"{np.median(res[ref][key]) / np.median(res[n][key]):.2f}x" for n in names[1:]]
        print(f"  {key:28s} " + ", ".join(cells) + f"  ({ref}/other: {', '.join(ratios)})")
    for n in names[1:]:
        a, b = hits[ref], hits[n]
        img = float(np.mean(a["image"] == b["image"]))
        shadow = float(np.mean(a["shadow"] == b["shadow"]))
        same = total = 0
        for k, ga in a["adaptive"].items():
            same += int(np.sum(ga == b["adaptive"][k]))
            total += ga.size
        lid_same = lid_total = n_equal = n_diff = 0
        for k, fa in a["lidar"].items():
            fb = b["lidar"][k]
            n_diff += abs(fa.n_points - fb.n_points)
            if fa.n_points == fb.n_points:
                n_equal += 1
                lid_same += int(np.sum((fa.instance_id == fb.instance_id) & (fa.class_id == fb.class_id)))
                lid_total += fa.n_points
        print(f"  triangle ids {ref} vs {n}: coherent image {100 * img:.3f} % of pixels (shadow rays "
              f"{100 * shadow:.3f} %); adaptive tick "
              f"{100 * same / total:.3f} % of {total / 1e6:.1f} M pixels ({a['adaptive_rays'] / 1e6:.1f} M / "
              f"{b['adaptive_rays'] / 1e6:.1f} M rays); LiDAR class+instance {100 * lid_same / max(lid_total, 1):.2f} "
              f"% of {lid_total} returns of the {n_equal} of {len(a['lidar'])} sweeps of equal length; the others "
              f"{n_diff} returns apart in all)")
    for s in suites.values():
        s.close()


if __name__ == "__main__":
    main()
