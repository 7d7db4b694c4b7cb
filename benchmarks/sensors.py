"""Sensor rendering benchmark: the paper's full rig on the default town, with reference ratios.

    PYTHONPATH=. .venv/bin/python benchmarks/sensors.py [--frames 3] [--no-pybullet] [--weather W --lighting L]
        [--ray-backend open3d,embree]
    PYTHONPATH=. .venv/bin/python benchmarks/sensors.py --pictures docs/img
    PYTHONPATH=. .venv/bin/python benchmarks/sensors.py --smoke  (every step on a small input: the suite's check)

Prints the CPU-seconds per frame of the whole process tree (this process and its render processes),
by stage, and the wall time per frame over bare casting. Rig: 5 vehicles (LiDAR + 6 cameras), 5 RSUs
(LiDAR + 4 cameras), 5 drones (LiDAR + 1 gimbal camera),
every camera 1280x720, on the world that ``build_world`` makes for scenarios/default.yaml, with
background traffic moving at ``--speed`` (LiDAR motion distortion casts each firing at its own time;
``--lidar-snapshot`` turns that off, ``--dual-returns`` on); ``--frames`` different snapshots (each
measured against the references). ``--ray-backend a,b`` measures everything once per ray backend
(``sensors.ray_backend``), one after the other in this process, and prints the CPU ratio.

The frame time is measured the way ``cosim run`` works: the sensors of frame k+1 render while the
episode's writer thread encodes and writes frame k (``BackgroundWriter``); it is the wall time of
an episode of ``--episode-frames`` frames (cycling through the snapshots), up to the last one
written, divided by their number. A sequential pass
(render, then wait for the encodes, then write) gives the per-frame breakdown: casting, shading,
labels/other (the render threads' busy times scaled to the render wall time), encoding wait and
writing. Each is the mean of two runs, before and after the references, which are measured in the
same run on the same snapshots:

- *bare casting*: one Open3D ``cast_rays`` call per sensor over all its rays (one ray per pixel
  and per LiDAR beam) against a single scene holding the static world and the tick's actors,
  nothing else; printed as frame time / bare;
- the PyBullet rendering of the same rig (``rayTestBatch`` LiDARs, TinyRenderer cameras at the
  same resolution and poses); printed as PyBullet / frame time.

``--pictures DIR`` writes sensors_<weather>_<lighting>.png (12, 480x270, RSU view) and a grid instead.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
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
from cosim.sensors.raycast import build, ray_backend
from cosim.sensors.rig import camera_pose, intrinsics, rotate, sensor_pose
from cosim.sensors.scene import cast, place_actors, static_bare_mesh
from cosim.sensors.suite import render_processes
from cosim.sensors.synthetic import world_snapshot

from cosim.assemble import traffic_lights
from cosim.scenario.loader import load_scenario, load_scenario_data
from cosim.world.build import build_world
from cosim.world.traffic_lights import first_phases

log = logging.getLogger("bench")
ROOT = Path(__file__).resolve().parents[1]
#: [s] wall time per full-rig frame in an episode that issue 14 asks for on a 2-core machine
FRAME_TARGET_S = 1.0
#: [CPU-s] per full-rig frame for the whole process tree that issue 26 asks for
FRAME_TARGET_CPU_S = 4.0
#: What ``--smoke`` sets (with one frame and five road users): every step on a small input, numbers meaningless.
SMOKE_SETS = ("map.size_m=300", "sensors.image_scale=0.05")


def paper_rig_scenario(path: Path, compression: str | None = None, lidar: dict | None = None,
                       sun_shadows: bool = True, ray_backend: str | None = None, overrides: tuple[str, ...] = (),
                       **env):
    """The scenario at ``path`` (with ``--set``-style ``overrides``) with the paper's rig: 5 vehicles, 5 RSUs,
    5 hovering drones."""
    data = json.loads(json.dumps(load_scenario(path, list(overrides)).resolved))
    data["sensors"]["sun_shadows"] = sun_shadows
    if ray_backend:
        data["sensors"]["ray_backend"] = ray_backend
    if compression:
        data["output"]["compression"] = compression
    for kind in ("vehicle", "rsu", "drone"):
        if lidar and data["sensors"][kind].get("lidar"):
            data["sensors"][kind]["lidar"].update(lidar)
    data["agents"]["vehicles"]["count"] = 5
    data["agents"]["rsus"]["count"] = 5
    data["agents"]["drones"] = [{"strategy": "hover", "altitude_m": 40 + 10 * i} for i in range(5)]
    data["environment"].update(env)
    return load_scenario_data(data)


def bare_cast_seconds(suite: SensorSuite, snap) -> tuple[float, int]:
    """Seconds in Open3D's ``cast_rays`` for one ray per pixel/beam of every sensor against one combined scene."""
    mesh = static_bare_mesh(suite.static, snap.actors)
    scene = build(ray_backend("open3d"), mesh.vertices, mesh.triangles, "high")
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


def tree_cpu_s() -> float:
    """CPU seconds (user + system) used so far by this process and every live child (render processes)."""
    import psutil

    me = psutil.Process()
    total = sum(me.cpu_times()[:2])
    for child in me.children(recursive=True):
        with contextlib.suppress(psutil.Error):
            total += sum(child.cpu_times()[:2])
    return total


_ENCODE_CPU_S = [0.0]


def count_encode_cpu() -> None:
    """Wrap the RGB encoders of :mod:`cosim.sensors.encoding` so that :func:`encode_cpu_s` adds up their
    thread CPU time (the encoder pool's threads run them in this process)."""
    from cosim.sensors import encoding

    def counted(fn):
        def wrapper(*a, **k):
            t0 = time.thread_time()
            try:
                return fn(*a, **k)
            finally:
                _ENCODE_CPU_S[0] += time.thread_time() - t0
        return wrapper

    for name in ("encode_png", "encode_jpeg"):
        setattr(encoding, name, counted(getattr(encoding, name)))
    from cosim.sensors import suite

    from cosim.io import sensor_messages

    for module in (sensor_messages, suite):  # the compact depth images count as encoding too
        if hasattr(module, "encode_depth"):
            module.encode_depth = counted(module.encode_depth)


def encode_cpu_s() -> float:
    return _ENCODE_CPU_S[0]


def _data_kind(topic: str) -> str:
    """The data kind of a sensor topic: RGB, depth, semantic, instance, LiDAR, labels (everything else)."""
    last = topic.rsplit("/", 1)[-1]
    return {"image": "RGB", "depth": "depth", "semantic": "semantic", "instance": "instance",
            "lidar": "LiDAR"}.get(last, "labels")


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


def run(args, backend: str) -> float:
    """Measure with ray backend ``backend``; returns the pipelined CPU-s per frame."""
    from cosim.io.sensor_messages import frame_records
    from cosim.io.writer import BackgroundWriter, EpisodeWriter

    env = {k: v for k, v in (("weather", args.weather), ("lighting", args.lighting)) if v}
    lidar = {"motion_distortion": not args.lidar_snapshot, "dual_returns": args.dual_returns}
    loaded = paper_rig_scenario(ROOT / "scenarios" / "default.yaml", compression=args.compression, lidar=lidar,
                                sun_shadows=not args.no_shadows, ray_backend=backend,
                                overrides=SMOKE_SETS if args.smoke else (), **env)
    sc = loaded.scenario
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        world = build_world(loaded, Path(tmp))
        t_world = time.perf_counter() - t0
        t0 = time.perf_counter()
        processes = render_processes(sc) if args.processes is None else args.processes
        # as the episode runner does: RGB and compact depth encoded as each camera is rendered
        suite = SensorSuite(sc, world, block_px=args.block_px, processes=processes, release_pixels=True)
        t_static = time.perf_counter() - t0
        print(f"world: {len(world.layout.prisms)} prisms, static mesh {suite.static.n_triangles} triangles; "
              f"world {t_world:.2f} s, static scene {t_static:.2f} s (once per episode)")
        n_cams = sum(len(sc.rig_for(a).cameras) for a in sc.agent_ids())
        print(f"ray backend {backend}; rig: {len(sc.agent_ids())} agents, {n_cams} cameras at 1280x720, 15 LiDARs; "
              f"{sc.environment.weather} {sc.environment.lighting}; "
              f"image format {sc.output.image_format}, MCAP chunk compression {sc.output.compression}; "
              f"block_px {args.block_px}; {processes} render processes; {args.frames} snapshots, pipelined episodes "
              f"of {args.episode_frames} frames")
        snaps = [world_snapshot(world, 5, 5, args.background, seed=k, tick=k, speed_mps=args.speed)
                 for k in range(args.frames)]

        def messages(frames, consume=False):
            return frame_records(frames, frames.t_ns, image_format=sc.output.image_format,
                                 jpeg_quality=sc.output.jpeg_quality, lidar_positions=sc.sensors.lidar_positions,
                                 depth_format=sc.output.depth_format, consume=consume)

        kinds: dict[str, list[int]] = {}  # data kind -> [serialized bytes, zstd bytes] over the first pass
        n_agent_frames = [0]

        def tally(frames, msgs) -> None:
            import zstandard

            if n_agent_frames[0] >= len(snaps) * len(frames.agents):
                return
            n_agent_frames[0] += len(frames.agents)
            z = zstandard.ZstdCompressor()
            for topic, msg in msgs:
                kind = _data_kind(topic)
                if hasattr(msg, "SerializeToString"):
                    raw = msg.SerializeToString()
                else:
                    raw = bytes(msg.data) if hasattr(msg, "data") else json.dumps(msg[2]).encode()
                k = kinds.setdefault(kind, [0, 0])
                k[0] += len(raw)
                k[1] += len(z.compress(raw))

        def sequential(name: str) -> list[dict]:
            """Each frame rendered, encoded and written before the next starts (the breakdown)."""
            rows = []
            rng = np.random.default_rng(sc.seed)
            with EpisodeWriter(Path(tmp) / f"{name}.mcap", compression=sc.output.compression) as w:
                for snap in snaps:
                    c0, e0 = tree_cpu_s(), encode_cpu_s()
                    t0 = time.perf_counter()
                    frames = suite.render(snap, rng)
                    for af in frames.agents.values():  # the suite's encodes count as encoding, not writing
                        for cam in af.cameras.values():
                            if cam.encoded is not None:
                                for f in (cam.encoded.rgb, cam.encoded.depth):
                                    if f is not None:
                                        f.result()
                    t1 = time.perf_counter()
                    c1, e1 = tree_cpu_s(), encode_cpu_s()
                    msgs = list(messages(frames))
                    t2 = time.perf_counter()
                    ca = tree_cpu_s()
                    tally(frames, msgs)  # a measurement, not part of the frame's cost
                    c2 = tree_cpu_s()
                    for topic, msg in msgs:
                        w.write(topic, msg, snap.t_ns)
                    t3 = time.perf_counter()
                    c3 = tree_cpu_s()
                    tm = frames.timing_s
                    # the render threads' times overlap: split the render wall time in proportion to them
                    busy = tm["scene"] + tm["lidar"] + tm["camera_cast"] + tm["shading"] + tm["labels"]
                    scale = (t1 - t0) / busy if busy > 0 else 1.0
                    # and the render CPU (the tree's, less the RGB encodes) in the same proportions
                    enc = e1 - e0
                    cpu_scale = max(0.0, c1 - c0 - enc) / busy if busy > 0 else 0.0
                    rows.append({"total": t3 - t0, "render": t1 - t0, "casting": tm["cast_rays"] * scale,
                                 "shading": tm["shading"] * scale,
                                 "other_render": (busy - tm["cast_rays"] - tm["shading"]) * scale,
                                 "labels": tm["labels"] * scale, "encoding": t2 - t1, "writing": t3 - t2,
                                 "rays": tm["rays"], "cast_thread_s": tm["cast_rays"],
                                 "cpu_total": c3 - c0 - (c2 - ca),
                                 "cpu_casting": tm["cast_rays"] * cpu_scale, "cpu_shading": tm["shading"] * cpu_scale,
                                 "cpu_labels": tm["labels"] * cpu_scale,
                                 "cpu_rest": (busy - tm["cast_rays"] - tm["shading"] - tm["labels"]) * cpu_scale,
                                 "cpu_encoding": enc, "cpu_writing": c3 - c1 - (c2 - ca)})
                rows[-1]["bytes"] = w.finish().stat().st_size
            return rows

        # the pipelined episode cycles through the snapshots (ticks 0, 1, ...: the same scenes again)
        episode = [world_snapshot(world, 5, 5, args.background, seed=k % len(snaps), tick=k, speed_mps=args.speed)
                   for k in range(args.episode_frames)]

        def pipelined(name: str) -> tuple[float, float]:
            """Seconds and CPU-seconds of the process tree per frame the way ``cosim run`` works: frame k
            is encoded and written by the episode's writer thread while frame k+1 renders; includes
            writing the last frame."""
            rng = np.random.default_rng(sc.seed)
            c0 = tree_cpu_s()
            with EpisodeWriter(Path(tmp) / f"{name}.mcap", compression=sc.output.compression) as w, \
                    BackgroundWriter(w) as bg:
                t0 = time.perf_counter()
                for snap in episode:
                    frames = suite.render(snap, rng)
                    bg.submit(snap.t_ns, lambda frames=frames: messages(frames, consume=True))
                bg.flush()
                wall = time.perf_counter() - t0
                cpu = tree_cpu_s() - c0
                w.finish()
            return wall / len(episode), cpu / len(episode)

        # the first tick of an episode also casts the static world for the RSUs' kept hits
        t0 = time.perf_counter()
        suite.render(snaps[0], np.random.default_rng(sc.seed))
        print(f"first render of the episode (RSU static hits; not in the frame times): "
              f"{time.perf_counter() - t0:.2f} s")
        # interleaved (ours, references, ours again) so that load changes hit both sides alike
        seq_a, pipe_a = sequential("seq_a"), pipelined("pipe_a")
        refs = []
        for snap in snaps:
            bare, bare_rays = bare_cast_seconds(suite, snap)
            pyb = pybullet_seconds(suite, snap) if not args.no_pybullet else None
            refs.append((bare, bare_rays, pyb))
        pipe_b, seq_b = pipelined("pipe_b"), sequential("seq_b")
        suite.close()

        for k, (first, second, (bare, bare_rays, pyb)) in enumerate(zip(seq_a, seq_b, refs, strict=True)):
            row = {key: 0.5 * (first[key] + second[key]) for key in first if key != "bytes"}
            print(f"frame {k}: {row['total']:.2f} s (runs {first['total']:.2f}, {second['total']:.2f}) = "
                  f"render {row['render']:.2f} (casting {row['casting']:.2f}, shading {row['shading']:.2f}, "
                  f"labels/other {row['other_render']:.2f}: labels {row['labels']:.2f}, the rest numpy around "
                  f"casting: camera sampling/fills, LiDAR models) + encoding wait {row['encoding']:.2f} + writing "
                  f"{row['writing']:.2f}; {row['rays'] / 1e6:.1f} M rays cast")
            print(f"         CPU-s of the process tree: {row['cpu_total']:.2f} = casting {row['cpu_casting']:.2f} + "
                  f"shading {row['cpu_shading']:.2f} + label gathers {row['cpu_labels']:.2f} + rest (scene, LiDAR "
                  f"models, numpy around casting) {row['cpu_rest']:.2f} + encoding {row['cpu_encoding']:.2f} + "
                  f"writing {row['cpu_writing']:.2f} (render CPU split in proportion to the render threads' times)")
            print(f"         bare cast_rays, one ray per pixel/beam, one scene: {bare:.2f} s for "
                  f"{bare_rays / 1e6:.1f} M rays; own cast_rays calls: {row['rays'] / 1e6:.1f} M rays, "
                  f"{row['cast_thread_s']:.2f} s")
            if pyb is not None:
                print(f"         PyBullet same rig: {pyb[0]:.2f} s (rayTestBatch {pyb[1]:.2f}, "
                      f"TinyRenderer {pyb[2]:.2f})")
        seq = float(np.mean([0.5 * (a["total"] + b["total"]) for a, b in zip(seq_a, seq_b, strict=True)]))
        seq_cpu = {k: float(np.mean([0.5 * (a[k] + b[k]) for a, b in zip(seq_a, seq_b, strict=True)]))
                   for k in seq_a[0] if k.startswith("cpu_")}
        pipe = 0.5 * (pipe_a[0] + pipe_b[0])
        pipe_cpu = 0.5 * (pipe_a[1] + pipe_b[1])
        pipe_a, pipe_b = pipe_a[0], pipe_b[0]
        bare = float(np.mean([r[0] for r in refs]))
        print(f"episode file: {seq_a[-1]['bytes'] / 1e6 / len(snaps):.0f} MB per frame")
        n = max(1, n_agent_frames[0])
        print("bytes per agent-frame by data kind (message bytes; zstd of each message, as in MCAP chunks): "
              + ", ".join(f"{k} {v[0] / n / 1e6:.2f} MB ({v[1] / n / 1e6:.2f} MB)" for k, v in sorted(kinds.items())))
        print(f"per frame: sequential {seq:.2f} s (mean over {len(snaps)} snapshots: render, then encode, then "
              f"write); pipelined {pipe:.2f} s (runs {pipe_a:.2f}, {pipe_b:.2f}; episodes of {len(episode)} frames, "
              f"writing overlaps the next render, as in cosim run); bare casting {bare:.2f} s")
        line = (f"RESULT frame time {pipe:.2f} s (target <= {FRAME_TARGET_S:.1f} s on 2 cores): frame/bare = "
                f"{pipe / bare:.2f} (target <= 1.3)")
        extra = f"sequential: {seq / bare:.2f}"
        if not args.no_pybullet:
            pb = float(np.mean([r[2][0] for r in refs]))
            line += f"; pybullet/frame = {pb / pipe:.1f} (target >= 10)"
            extra += f", {pb / seq:.1f}"
        print(f"{line} ({extra})")
        print(f"RESULT CPU per frame {pipe_cpu:.2f} CPU-s for the whole process tree, pipelined (target <= "
              f"{FRAME_TARGET_CPU_S:.0f}); sequential {seq_cpu['cpu_total']:.2f} = casting {seq_cpu['cpu_casting']:.2f}"
              f" + shading {seq_cpu['cpu_shading']:.2f} + label gathers {seq_cpu['cpu_labels']:.2f} + rest "
              f"{seq_cpu['cpu_rest']:.2f} + encoding {seq_cpu['cpu_encoding']:.2f} + writing "
              f"{seq_cpu['cpu_writing']:.2f}; frame/bare casting {pipe / bare:.2f} (wall) [{backend}]")
    return pipe_cpu


def pictures(out_dir: Path) -> None:
    """sensors_<weather>_<lighting>.png (480x270, RSU camera) for the 12 combinations, plus a grid."""
    from PIL import Image

    from cosim.scenario.model import CameraSpec

    out_dir.mkdir(parents=True, exist_ok=True)
    base = paper_rig_scenario(ROOT / "scenarios" / "default.yaml")
    with tempfile.TemporaryDirectory() as tmp:
        world = build_world(base, Path(tmp))
        snap = world_snapshot(world, 5, 5, 60, seed=3)
        # the traffic lights in their programs' first phase (no SUMO here)
        snap = dataclasses.replace(snap, traffic_lights=traffic_lights(world, first_phases(world.net_xml)))
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
    ap.add_argument("--frames", type=int, default=3, help="snapshots (each with its references)")
    ap.add_argument("--episode-frames", type=int, default=9, help="frames of each pipelined episode (cycling "
                    "through the snapshots)")
    ap.add_argument("--background", type=int, default=40, help="background road users")
    ap.add_argument("--block-px", type=int, default=8, help="adaptive casting block (1 = a ray per pixel)")
    ap.add_argument("--no-pybullet", action="store_true")
    ap.add_argument("--processes", type=int, help="render processes (default: sensors.render_processes, 0 unless set)")
    ap.add_argument("--compression", choices=("zstd", "lz4", "none"), help="MCAP chunk compression "
                    "(default: the scenario's)")
    ap.add_argument("--weather", choices=("clear", "cloudy", "foggy", "rainy"), help="default: the scenario's")
    ap.add_argument("--lighting", choices=("day", "dusk", "night"), help="default: the scenario's")
    ap.add_argument("--pictures", type=Path, help="write the weather x lighting pictures here and exit")
    ap.add_argument("--speed", type=float, default=12.0, help="road users' speed [m/s] (drones half): what "
                    "LiDAR motion distortion works on")
    ap.add_argument("--lidar-snapshot", action="store_true", help="LiDARs without motion distortion")
    ap.add_argument("--dual-returns", action="store_true", help="LiDARs with dual returns")
    ap.add_argument("--no-shadows", action="store_true", help="cameras without sun shadows (sensors.sun_shadows)")
    ap.add_argument("--ray-backend", default="embree", help="sensors.ray_backend; several, comma-separated, are "
                    "measured one after the other")
    ap.add_argument("--smoke", action="store_true", help="a 300 m map, cameras at 1/20 size, one frame: checks "
                    "the script runs (tests/test_benchmarks.py); its numbers mean nothing")
    args = ap.parse_args()
    if args.smoke:
        args.frames, args.episode_frames, args.background = 1, 1, 5
    logging.basicConfig(level=logging.WARNING)
    count_encode_cpu()
    if args.pictures:
        pictures(args.pictures)
        return
    backends = args.ray_backend.split(",")
    cpu = {b: run(args, b) for b in backends}
    if len(cpu) > 1:
        first = backends[0]
        print("RESULT CPU per frame by ray backend: " + ", ".join(
            f"{b} {c:.2f} CPU-s ({cpu[first] / c:.2f}x of {first})" for b, c in cpu.items()))


if __name__ == "__main__":
    main()

