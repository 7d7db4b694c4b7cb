"""Sensor rendering benchmark: the paper's full rig on the default town, with reference ratios.

    PYTHONPATH=. .venv/bin/python benchmarks/sensors.py [--frames 2] [--no-pybullet] [--pictures docs/img]

Rig: 5 vehicles (LiDAR + 6 cameras), 5 RSUs (LiDAR + 4 cameras), 5 drones (LiDAR + 1 gimbal camera),
every camera 1280x720, on the world that ``build_world`` makes for scenarios/default.yaml, with
background traffic. Per frame it prints the wall time and its breakdown (casting, shading,
labels/other: the render threads' busy times scaled to the render wall time; encoding wait;
writing with the episode writer), each the mean of two runs taken before and after the
references, and, measured in the same run on the same scene:

- the ratio of the frame time to *bare casting*: one Open3D ``cast_rays`` call per sensor over all
  its rays (one ray per pixel and per LiDAR beam) against a single scene holding the static world
  and the tick's actors, nothing else;
- the ratio of the PyBullet rendering of the same rig (``rayTestBatch`` LiDARs, TinyRenderer
  cameras at the same resolution and poses) to the frame time.

``--pictures DIR`` also writes sensors_<weather>_<lighting>.png (12, 480x270, RSU view) and a grid.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import tempfile
import time
from pathlib import Path

import numpy as np
from cosim.sensors import SensorSuite
from cosim.sensors.camera import _rays
from cosim.sensors.lidar import beam_pattern
from cosim.sensors.rig import camera_pose, intrinsics, rotate, sensor_pose
from cosim.sensors.scene import cast, place_actors, static_bare_mesh
from cosim.sensors.synthetic import world_snapshot

from cosim.scenario.loader import load_scenario, load_scenario_data
from cosim.world.build import build_world

log = logging.getLogger("bench")
ROOT = Path(__file__).resolve().parents[1]


def paper_rig_scenario(path: Path, compression: str | None = None, **env):
    data = json.loads(json.dumps(load_scenario(path).resolved))
    if compression:
        data["output"]["compression"] = compression
    data["agents"]["vehicles"]["count"] = 5
    data["agents"]["rsus"]["count"] = 5
    data["agents"]["drones"] = [{"strategy": "hover", "altitude_m": 40 + 10 * i} for i in range(5)]
    data["environment"].update(env)
    return load_scenario_data(data)


def write_messages(msgs, t_ns: int, out: Path, compression: str) -> int:
    """Write (topic, message) pairs with the episode writer (exporters/mcap_writer.py); file bytes."""
    from cosim.exporters.mcap_writer import EpisodeWriter

    w = EpisodeWriter(out, compression=compression)
    for topic, msg in msgs:
        w.write(topic, msg, t_ns)
    return w.finish().stat().st_size


def bare_cast_seconds(suite: SensorSuite, snap) -> tuple[float, int]:
    """Seconds in ``cast_rays`` for one ray per pixel/beam of every sensor against one combined scene."""
    import open3d as o3d

    mesh = static_bare_mesh(suite.static, snap.actors)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices), o3d.core.Tensor(mesh.triangles))
    total, n_rays = 0.0, 0
    for agent in snap.agents:
        rig = suite.rig(agent)
        batches = []
        if rig.lidar is not None:
            pose = sensor_pose(agent, rig.lidar.mount)
            d, _ = beam_pattern(rig.lidar)
            r = np.empty((len(d), 6), np.float32)
            r[:, :3] = pose.position_m
            r[:, 3:] = rotate(d, pose.rotation)
            batches.append(r)
        for cam in rig.cameras:
            K = intrinsics(cam)
            xs = (np.arange(cam.width) + 0.5 - K[0, 2]) / K[0, 0]
            ys = (np.arange(cam.height) + 0.5 - K[1, 2]) / K[1, 1]
            gx, gy = np.meshgrid(xs, ys)
            batches.append(_rays(camera_pose(agent, cam), gx.ravel(), gy.ravel()))
        for rays in batches:
            t0 = time.perf_counter()
            cast(scene, rays)
            total += time.perf_counter() - t0
            n_rays += len(rays)
    return total, n_rays


def pybullet_seconds(suite: SensorSuite, snap) -> tuple[float, float, float]:
    """(total, lidar, camera) seconds for the same rig in PyBullet (DIRECT, TinyRenderer)."""
    import pybullet as pb

    cid = pb.connect(pb.DIRECT)
    try:
        m = suite.static.mesh
        for cls in np.unique(m.semantic):
            sel = np.nonzero(m.semantic == cls)[0]
            tri = m.triangles[sel]
            used, inv = np.unique(tri.ravel(), return_inverse=True)
            verts = m.vertices[used].astype(float).tolist()
            idx = inv.astype(int).tolist()
            col = pb.createCollisionShape(pb.GEOM_MESH, vertices=verts, indices=idx,
                                          flags=pb.GEOM_FORCE_CONCAVE_TRIMESH, physicsClientId=cid)
            rgba = [*m.albedo[sel[0]].tolist(), 1.0]
            vis = pb.createVisualShape(pb.GEOM_MESH, vertices=verts, indices=idx, rgbaColor=rgba, physicsClientId=cid)
            pb.createMultiBody(0, col, vis, physicsClientId=cid)
        for a in snap.actors:
            mesh, _ = place_actors([a])
            v = (mesh.vertices.astype(float) - np.asarray(a.center_m)).tolist()
            idx = mesh.triangles.ravel().astype(int).tolist()
            col = pb.createCollisionShape(pb.GEOM_MESH, vertices=v, indices=idx, flags=pb.GEOM_FORCE_CONCAVE_TRIMESH,
                                          physicsClientId=cid)
            vis = pb.createVisualShape(pb.GEOM_MESH, vertices=v, indices=idx, rgbaColor=[0.5, 0.5, 0.6, 1],
                                       physicsClientId=cid)
            pb.createMultiBody(0, col, vis, basePosition=list(a.center_m), physicsClientId=cid)
        t_lidar = t_cam = 0.0
        batch = pb.MAX_RAY_INTERSECTION_BATCH_SIZE if hasattr(pb, "MAX_RAY_INTERSECTION_BATCH_SIZE") else 16384
        for agent in snap.agents:
            rig = suite.rig(agent)
            if rig.lidar is not None:
                pose = sensor_pose(agent, rig.lidar.mount)
                d, _ = beam_pattern(rig.lidar)
                frm = np.broadcast_to(pose.position_m, d.shape)
                to = pose.position_m + rotate(d, pose.rotation) * rig.lidar.range_m
                t0 = time.perf_counter()
                for k in range(0, len(d), batch):
                    pb.rayTestBatch(frm[k:k + batch].tolist(), to[k:k + batch].tolist(), numThreads=0,
                                    physicsClientId=cid)
                t_lidar += time.perf_counter() - t0
            for cam in rig.cameras:
                pose = camera_pose(agent, cam)
                eye = pose.position_m
                fwd, down = pose.rotation[:, 2], pose.rotation[:, 1]
                vfov = 2 * math.degrees(math.atan(math.tan(math.radians(cam.fov_deg) / 2) * cam.height / cam.width))
                t0 = time.perf_counter()
                view = pb.computeViewMatrix(eye.tolist(), (eye + fwd).tolist(), (-down).tolist())
                proj = pb.computeProjectionMatrixFOV(vfov, cam.width / cam.height, 0.5, 300.0)
                pb.getCameraImage(cam.width, cam.height, view, proj, renderer=pb.ER_TINY_RENDERER,
                                  physicsClientId=cid)
                t_cam += time.perf_counter() - t0
        return t_lidar + t_cam, t_lidar, t_cam
    finally:
        pb.disconnect(cid)


def run(args) -> None:
    from cosim.exporters.sensor_messages import frame_messages

    loaded = paper_rig_scenario(ROOT / "scenarios" / "default.yaml", compression=args.compression)
    sc = loaded.scenario
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        world = build_world(loaded, Path(tmp))
        t_world = time.perf_counter() - t0
        t0 = time.perf_counter()
        suite = SensorSuite(sc, world, block_px=args.block_px)
        t_static = time.perf_counter() - t0
        print(f"world: {len(world.layout.prisms)} prisms, static mesh {suite.static.n_triangles} triangles; "
              f"world {t_world:.2f} s, static scene {t_static:.2f} s (once per episode)")
        n_cams = sum(len(sc.rig_for(a).cameras) for a in sc.agent_ids())
        print(f"rig: {len(sc.agent_ids())} agents, {n_cams} cameras at 1280x720, 15 LiDARs; "
              f"image format {sc.output.image_format}, MCAP chunk compression {sc.output.compression}; "
              f"block_px {args.block_px}")
        rng = np.random.default_rng(sc.seed)
        rows = []

        def one_frame(snap, k: int) -> dict:
            t0 = time.perf_counter()
            frames = suite.render(snap, rng)
            t1 = time.perf_counter()
            msgs = frame_messages(frames, snap.t_ns, image_format=sc.output.image_format)
            t2 = time.perf_counter()
            nbytes = write_messages(msgs, snap.t_ns, Path(tmp) / f"frame{k}.mcap", sc.output.compression)
            t3 = time.perf_counter()
            tm = frames.timing_s
            # the render threads' times overlap: split the render wall time in proportion to them
            busy = tm["scene"] + tm["lidar"] + tm["camera_cast"] + tm["shading"] + tm["labels"]
            scale = (t1 - t0) / busy if busy > 0 else 1.0
            return {"total": t3 - t0, "render": t1 - t0, "casting": tm["cast_rays"] * scale,
                    "shading": tm["shading"] * scale, "other_render": (busy - tm["cast_rays"] - tm["shading"]) * scale,
                    "labels": tm["labels"] * scale,
                    "encoding": t2 - t1, "writing": t3 - t2, "rays": tm["rays"], "bytes": nbytes,
                    "cast_thread_s": tm["cast_rays"]}

        for k in range(args.frames):
            snap = world_snapshot(world, 5, 5, args.background, seed=k, tick=k)
            # interleaved (ours, references, ours again) so that load changes hit both sides alike
            first = one_frame(snap, k)
            bare, bare_rays = bare_cast_seconds(suite, snap)
            pyb = pybullet_seconds(suite, snap) if not args.no_pybullet else None
            second = one_frame(snap, k)
            row = {key: 0.5 * (first[key] + second[key]) for key in first}
            row["bare"], row["bare_rays"] = bare, bare_rays
            if pyb is not None:
                row["pybullet"], row["pb_lidar"], row["pb_cam"] = pyb
            rows.append(row)
            print(f"frame {k}: total {row['total']:.2f} s (runs {first['total']:.2f}, {second['total']:.2f}) = "
                  f"render {row['render']:.2f} (casting {row['casting']:.2f}, shading {row['shading']:.2f}, "
                  f"labels/other {row['other_render']:.2f}: labels {row['labels']:.2f}, the rest numpy around "
                  f"casting: camera sampling/fills, LiDAR models) + encoding wait {row['encoding']:.2f} + writing "
                  f"{row['writing']:.2f}; {row['rays'] / 1e6:.1f} M rays cast, {row['bytes'] / 1e6:.0f} MB file")
            print(f"         bare cast_rays, one ray per pixel/beam, one scene: {bare:.2f} s for "
                  f"{bare_rays / 1e6:.1f} M rays -> total / bare = {row['total'] / bare:.2f}; total / own "
                  f"cast_rays calls ({row['rays'] / 1e6:.1f} M rays, {row['cast_thread_s']:.2f} s) = "
                  f"{row['total'] / row['cast_thread_s']:.2f}")
            if "pybullet" in row:
                print(f"         PyBullet same rig: {row['pybullet']:.2f} s (rayTestBatch {row['pb_lidar']:.2f}, "
                      f"TinyRenderer {row['pb_cam']:.2f}) -> PyBullet / total = {row['pybullet'] / row['total']:.1f}x")
        med = {k: float(np.median([r[k] for r in rows])) for k in rows[0]}
        print("median over frames: " + ", ".join(f"{k} {v:.3f}" for k, v in med.items()
                                                 if k not in ("rays", "bytes", "bare_rays", "cast_thread_s")))
        print(f"RESULT total/bare = {med['total'] / med['bare']:.2f} (target <= 1.3)"
              + (f"; pybullet/total = {med['pybullet'] / med['total']:.1f} (target >= 10)" if "pybullet" in med
                 else ""))


def pictures(out_dir: Path) -> None:
    """sensors_<weather>_<lighting>.png (480x270, RSU camera) for the 12 combinations, plus a grid."""
    from PIL import Image

    from cosim.scenario.model import CameraSpec

    out_dir.mkdir(parents=True, exist_ok=True)
    base = paper_rig_scenario(ROOT / "scenarios" / "default.yaml")
    with tempfile.TemporaryDirectory() as tmp:
        world = build_world(base, Path(tmp))
        snap = world_snapshot(world, 5, 5, 60, seed=3)
        tiles = []
        for weather in ("clear", "cloudy", "foggy", "rainy"):
            for lighting in ("day", "dusk", "night"):
                data = dict(base.resolved)
                data = json.loads(json.dumps(data))
                data["environment"].update({"weather": weather, "lighting": lighting})
                for kind in ("vehicle", "rsu", "drone"):
                    rig = data["sensors"][kind]
                    rig["lidar"] = None
                    rig["cameras"] = [dict(c, width=480, height=272) for c in rig["cameras"]]
                sc = load_scenario_data(data).scenario
                assert isinstance(sc.sensors.rsu.cameras[0], CameraSpec)
                suite = SensorSuite(sc, world)
                f = suite.render(snap, np.random.default_rng(0))
                img = f.agents["rsu_0"].cameras["front"].rgb[1:271]
                Image.fromarray(img).save(out_dir / f"sensors_{weather}_{lighting}.png", optimize=True)
                tiles.append(img)
                print(f"{weather} {lighting}: mean {img.mean():.1f}")
        grid = np.concatenate([np.concatenate(tiles[i * 3:(i + 1) * 3], axis=1) for i in range(4)], axis=0)
        Image.fromarray(grid).resize((grid.shape[1] // 2, grid.shape[0] // 2), Image.BILINEAR).save(
            out_dir / "sensors_grid.png", optimize=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=2)
    ap.add_argument("--background", type=int, default=40, help="background road users")
    ap.add_argument("--block-px", type=int, default=8, help="adaptive casting block (1 = a ray per pixel)")
    ap.add_argument("--no-pybullet", action="store_true")
    ap.add_argument("--compression", choices=("zstd", "lz4", "none"), help="MCAP chunk compression "
                    "(default: the scenario's)")
    ap.add_argument("--pictures", type=Path, help="write the weather x lighting pictures here and exit")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    if args.pictures:
        pictures(args.pictures)
        return
    run(args)


if __name__ == "__main__":
    main()

