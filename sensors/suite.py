"""The sensor suite: every agent's rig rendered from one snapshot, as plain arrays.

``SensorSuite(scenario, world)`` builds the static scene once (mesh, Open3D BVH, light map, BEV
raster); ``render(snapshot, rng)`` places the tick's actors in a small second scene and renders all
agents. ``render`` is pure with respect to its inputs: the same snapshot and generator state give
bit-identical arrays: the generator is split (``spawn``) into one child per agent and sensor, so
the draws do not depend on the order in which the worker threads run.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cosim.geometry import rotation_matrix
from cosim.scenario.model import RigSpec, Scenario
from cosim.snapshot import Actor, AgentState, WorldSnapshot
from cosim.world.traffic_lights import signal_heads
from cosim.world.traffic_signs import traffic_signs
from cosim.world.types import World

from . import kernels
from .assets.signals import SignalLamps, signal_parts
from .bev import BevFrame, render_bev, static_raster
from .camera import (
    CameraFrame,
    LightMap,
    Occluders,
    StaticImage,
    box_corners,
    cast_image,
    ground_shadow,
    shade,
    shading_tables,
    shadow_boxes,
)
from .encoding import Encodes, PackedLabels, encode_depth, submit, submit_encode
from .environment import Atmosphere, atmosphere
from .imu import ImuFrame, imu_biases, render_imu
from .kinds import SensorContext, render_kinds
from .lidar import LidarFrame, actors_in_reach, reach_ball, render_lidar
from .meshes import concat, is_lamp, static_mesh
from .procs import RenderProcesses
from .rig import camera_pose, intrinsics, projection, sensor_pose
from .scene import StaticHits, StaticScene, TickScene
from .signals import SIGN_CENTRE_M, sign_mesh, signal_mesh
from .surface import surface_inputs
from .visibility import VisibilityFrame, instance_counts, render_visibility

log = logging.getLogger(__name__)

VEHICLE_CLASSES = ("car", "van", "truck", "bus", "motorcycle")
CHECK_PERIOD_S = 0.05  # [s] how often render() calls its check while it waits for the sensors


@dataclass(frozen=True)
class AgentFrames:
    """One agent's outputs at one tick; a sensor its rig lacks is None (cameras: empty)."""

    agent_id: str
    kind: str
    lidar: LidarFrame | None
    cameras: dict[str, CameraFrame]
    sensors: dict[str, Any] | None  # the frames of the sensor kinds (cosim.sensors.kinds) by kind name
    imu: ImuFrame | None
    bev: BevFrame | None
    visibility: VisibilityFrame | None

    @property
    def gnss(self) -> Any:
        """The GNSS fix (:class:`cosim.sensors.gnss.GnssFrame`) or None."""
        return (self.sensors or {}).get("gnss")


@dataclass(frozen=True)
class SensorFrameSet:
    """All agents' frames at ``t_ns``. ``timing_s`` is bookkeeping only (not data)."""

    tick: int
    t_ns: int
    agents: dict[str, AgentFrames]
    timing_s: dict[str, float] = field(default_factory=dict, compare=False)

    def cancel_encodes(self) -> None:
        """Drop the image encodes not started yet (the frames are abandoned, e.g. the episode failed).
        The writer thread may still be consuming the set (taking cameras out), so this walks copies."""
        for agent in list(self.agents.values()):
            for cam in list(agent.cameras.values()):
                if cam.encoded is not None:
                    cam.encoded.cancel()


def _shaded(albedo: np.ndarray, normals: np.ndarray, atm: Atmosphere, sun: bool = True) -> np.ndarray:
    """Linear colour (T, 3) float32 of triangles lit by the sun (Lambert; ``sun=False``: in its
    shadow) and the sky."""
    lam = np.clip((normals * atm.sun_dir).sum(axis=1), 0.0, None)[:, None] if sun else 0.0
    sky = (0.75 + 0.25 * normals[:, 2:3])  # surfaces facing up see more sky
    return (albedo * (atm.ambient_rgb * sky + atm.sun_rgb * lam)).astype(np.float32)


def _thin_segments(world: World) -> np.ndarray:
    """Centre lines (S, 2, 3) of the static things narrower than 1.5 m (poles, lamp arms, RSU
    poles, lane markings, trunks): adaptive casting refines along them instead of interpolating."""
    out = []
    for p in world.layout.prisms:
        fp = np.asarray(p.footprint, np.float64)
        ext = fp.max(0) - fp.min(0)
        if min(ext) >= 1.5:
            continue
        c = fp.mean(0)
        height = p.z1_m - p.z0_m
        if height >= max(ext):
            out.append([[c[0], c[1], p.z0_m], [c[0], c[1], p.z1_m]])
            continue
        u, _, _ = np.linalg.svd(np.cov((fp - c).T))
        along = (fp - c) @ u[:, 0]
        z = p.z1_m if height < 0.1 else 0.5 * (p.z0_m + p.z1_m)
        a, b = c + u[:, 0] * along.min(), c + u[:, 0] * along.max()
        out.append([[a[0], a[1], z], [b[0], b[1], z]])
    return np.asarray(out, np.float64).reshape(-1, 2, 3)


def _street_light_map(world: World, bounds: np.ndarray, res_m: float) -> LightMap:
    """Ground irradiance of the street lights: E = h^3 / (r^2 + h^2)^1.5 (1 under a lamp of height h)."""
    x0, y0, x1, y1 = bounds
    nx, ny = math.ceil((x1 - x0) / res_m), math.ceil((y1 - y0) / res_m)
    values = np.zeros((ny, nx), np.float32)
    xs = x0 + (np.arange(nx) + 0.5) * res_m
    ys = y0 + (np.arange(ny) + 0.5) * res_m
    reach = 30.0
    for p in world.layout.prisms:
        if not is_lamp(p):
            continue
        fp = np.asarray(p.footprint)
        lx, ly = fp.mean(0)
        h = max(p.z1_m, 2.0)
        j0, j1 = np.searchsorted(xs, [lx - reach, lx + reach])
        i0, i1 = np.searchsorted(ys, [ly - reach, ly + reach])
        r2 = (xs[None, j0:j1] - lx) ** 2 + (ys[i0:i1, None] - ly) ** 2
        values[i0:i1, j0:j1] += (h**3 / (r2 + h * h) ** 1.5).astype(np.float32)
    return LightMap(values, float(x0), float(y0), res_m)


def _add_headlights(light: LightMap, actors: tuple[Actor, ...]) -> LightMap:
    """A copy of ``light`` with a forward cone (40 m, about +-20 deg) for each road vehicle."""
    values = light.values.copy()
    ny, nx = values.shape
    res = light.res_m
    reach = 40.0
    for a in actors:
        if a.cls not in VEHICLE_CLASSES:
            continue
        r = rotation_matrix(a.rotation)
        fx, fy = r[0, 0], r[1, 0]
        norm = math.hypot(fx, fy) or 1.0
        fx, fy = fx / norm, fy / norm
        sx = a.center_m[0] + fx * a.size_m[0] / 2
        sy = a.center_m[1] + fy * a.size_m[0] / 2
        j0 = max(0, int((min(sx, sx + fx * reach) - 12 - light.x0) / res))
        j1 = min(nx, int((max(sx, sx + fx * reach) + 12 - light.x0) / res) + 1)
        i0 = max(0, int((min(sy, sy + fy * reach) - 12 - light.y0) / res))
        i1 = min(ny, int((max(sy, sy + fy * reach) + 12 - light.y0) / res) + 1)
        if j0 >= j1 or i0 >= i1:
            continue
        px = light.x0 + (np.arange(j0, j1) + 0.5) * res - sx
        py = light.y0 + (np.arange(i0, i1) + 0.5) * res - sy
        along = fx * px[None, :] + fy * py[:, None]
        across = -fy * px[None, :] + fx * py[:, None]
        d = np.sqrt(along**2 + across**2)
        ang = np.arctan2(np.abs(across), np.maximum(along, 1e-6))
        # smooth throughout: the cone's edge fades with the angle, its reach over its last 10 m
        fade = np.clip((reach - d) / 10.0, 0.0, 1.0)
        e = 1.2 * np.exp(-((ang / 0.35) ** 2)) * (6.0 / np.maximum(d, 6.0)) ** 2 * fade * fade * (3 - 2 * fade)
        values[i0:i1, j0:j1] += np.where(along > 0, e, 0.0).astype(np.float32)
    return LightMap(values, light.x0, light.y0, res)


class SensorSuite:
    """All rigs of a scenario over one world (see the module docstring).

    ``block_px``: adaptive camera casting block (1 = one ray per pixel). ``noise``: False turns
    every random sensor effect off (exact ranges, depths, fixes), for tests. ``encode_images``:
    start encoding each RGB image (``scenario.output.image_format``) in a thread pool as soon as it
    is shaded, so encoding overlaps with the rest of the tick. ``release_pixels`` (with
    ``encode_images``): also start the compact depth encode (``output.depth_format: compressed``) and
    leave a camera's ``rgb`` and ``depth`` None, their encodes holding them only until done, and its
    ``semantic`` and ``instance`` None, packed losslessly in the encodes (:class:`PackedLabels`), so that
    a rendered tick keeps a few percent of its camera arrays' bytes while it waits for the writer
    (the episode runner; whoever reads the pixels leaves it off). ``workers``: threads rendering
    cameras and agents side by side (Open3D holds the GIL while casting, but the numpy work around
    it releases it, so a few threads keep two cores busy); results do not depend on it.
    ``processes``: render processes (:mod:`cosim.sensors.procs`; 0 renders in this process). Each
    holds its own copy of the static scene, built once, and renders a fixed share of the agents
    from the snapshot; the images come back through shared memory. The output bytes do not depend
    on the number of processes.
    ``cull_actors``: a tick no camera renders places only the actors its LiDARs can reach (the same returns,
    :func:`cosim.sensors.lidar.actors_in_reach`; off for comparisons).
    """

    def __init__(self, scenario: Scenario, world: World, *, block_px: int = 8, noise: bool = True,
                 encode_images: bool = True, workers: int = 3, processes: int = 0, release_pixels: bool = False,
                 cull_actors: bool = True):
        self.scenario = scenario
        self.cull_actors = cull_actors
        self.encode_images = encode_images
        self.release_pixels = release_pixels and encode_images
        self._pool = ThreadPoolExecutor(max_workers=max(1, workers), thread_name_prefix="cosim-render")
        self.world = world
        self.block_px = block_px
        self.noise = noise
        self.atm = atmosphere(scenario.environment, scenario.seed)
        t0 = time.perf_counter()
        layout_mesh = static_mesh(world.layout)
        heads = signal_heads(world.net_xml)  # traffic lights at SUMO's signalised junctions
        signals = signal_parts(heads) if heads else None
        self._signals = SignalLamps(layout_mesh.n_triangles, signals, heads) if signals is not None else None
        signs = traffic_signs(world.net_xml)  # stop, give way, speed limits
        extra = [m for m in (signal_mesh(signals) if signals is not None else None, sign_mesh(signs)) if m is not None]
        self.static = StaticScene(concat([layout_mesh, *extra]) if extra else layout_mesh,
                                  scenario.sensors.ray_backend)
        m = self.static.mesh
        self._static_rgb = _shaded(m.albedo, self.static.normals, self.atm)
        self._static_rgb_shadow = _shaded(m.albedo, self.static.normals, self.atm, sun=False)
        shadows = self.atm.casts_shadows and scenario.sensors.sun_shadows
        self._sun = self.atm.sun_dir.astype(np.float64) if shadows else None
        self._thin = _thin_segments(world)
        if signals is not None:
            self._thin = np.concatenate([self._thin, signals.segments])
        if signs:
            posts = [[[*s.xy, 0.0], [*s.xy, SIGN_CENTRE_M + 0.3]] for s in signs]
            self._thin = np.concatenate([self._thin, np.asarray(posts, np.float64)])
        if self._sun is not None:  # thin things' shadows on the ground are refined like the things
            self._thin = np.concatenate([self._thin, ground_shadow(self._thin, self._sun, world.layout.ground_z_m)])
        verts = m.vertices.astype(np.float64)
        self._static_points = np.unique(verts, axis=0) if len(verts) else np.zeros((0, 3))
        self._light: LightMap | None = None
        if self.atm.artificial > 0:
            # over the layout only (the far ground around it is unlit: lookups beyond clamp to the edge)
            foot = np.array([q for p in world.layout.prisms for q in p.footprint], np.float64).reshape(-1, 2)
            if len(foot):
                lo, hi = foot.min(0) - 50, foot.max(0) + 50
            else:
                lo, hi = np.array([-100.0, -100.0]), np.array([100.0, 100.0])
            res = max(0.5, float(max(hi - lo)) / 4000)
            self._light = _street_light_map(world, np.array([*lo, *hi]), res)
        s = scenario.sensors
        self._bev_raster = static_raster(world.layout, s.bev_cell_m) if s.bev else None
        self._biases: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self._fixed: dict[tuple[str, str], StaticImage] = {}
        self._fixed_lidar: dict[str, StaticHits] = {}
        self._fixed_lock = threading.Lock()
        for i, agent_id in enumerate(scenario.agent_ids()):
            rig = scenario.rig_for(agent_id)
            if rig.imu is not None:
                self._biases[agent_id] = imu_biases(rig.imu, np.random.default_rng([scenario.seed, 0x1B, i]))
        log.info("static scene: %d triangles, built in %.2f s", m.n_triangles, time.perf_counter() - t0)
        self._procs = None
        if processes > 0:
            self._procs = RenderProcesses(scenario, world, processes,
                                          {"block_px": block_px, "noise": noise, "workers": 1})

    def rig(self, agent: AgentState) -> RigSpec:
        return self.scenario.rig_for(agent.agent_id)

    def close(self, wait: bool = True) -> None:
        """Stop the render threads (idle threads also end with the interpreter). ``wait=False``: do not wait for
        sensors still rendering an abandoned frame (queued ones are cancelled either way)."""
        self._pool.shutdown(wait=wait, cancel_futures=True)
        if self._procs is not None:
            self._procs.close()
            self._procs = None

    def __enter__(self) -> SensorSuite:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _render_agent_base(self, agent: AgentState, rig: RigSpec, own: int | None, scene: TickScene,
                           rng: np.random.Generator, actors: tuple[Actor, ...], t_ns: int):
        """LiDAR, the sensor kinds (GNSS), IMU and BEV of one agent (draws from ``rng`` in that order)."""
        t0 = time.perf_counter()
        lidar = None
        if rig.lidar is not None:
            pose = sensor_pose(agent, rig.lidar.mount)
            fixed = None
            if agent.kind == "rsu":  # RSUs stand still: the static world is cast once for their LiDAR
                with self._fixed_lock:
                    fixed = self._fixed_lidar.setdefault(agent.agent_id, StaticHits())
            lidar = render_lidar(agent.agent_id, rig.lidar, pose, scene, self.atm, rng, own, self.noise, fixed,
                                 agent, t_ns)
        t1 = time.perf_counter()
        kinds = render_kinds(rig, lambda spec: SensorContext(agent, spec, self.world, rng, self.noise, t_ns))
        imu = None
        if rig.imu is not None:
            biases = self._biases.get(agent.agent_id, (np.zeros(3), np.zeros(3)))
            imu = render_imu(agent, rig.imu, biases, rng, self.noise)
        s = self.scenario.sensors
        bev = render_bev(agent, self._bev_raster, actors, s.bev_cell_m, s.bev_range_m) if s.bev else None
        return (lidar, kinds, imu, bev), {"lidar": t1 - t0, "labels": time.perf_counter() - t1}

    def _render_camera(self, agent: AgentState, cam, own: int | None, scene: TickScene, occ: Occluders,
                       tables, light, lut, rng: np.random.Generator):
        """One camera's frame (rain streaks draw from ``rng``) and its timings."""
        t0 = time.perf_counter()
        K = intrinsics(cam)
        pose = camera_pose(agent, cam)
        fixed = None
        if agent.kind == "rsu":  # RSUs stand still: their cameras keep their static image
            with self._fixed_lock:
                fixed = self._fixed.setdefault((agent.agent_id, cam.name), StaticImage())
        gid, depth, lit = cast_image(cam, K, pose, scene, occ, own, self.block_px, fixed)
        t1 = time.perf_counter()
        rgb = encoded = None
        out_spec = self.scenario.output
        if "rgb" in cam.outputs:
            rgb = shade(gid, depth, lit, cam, K, pose, tables, self.atm, light, rng, 1, self.noise)
            if self.encode_images:
                encoded = Encodes(out_spec.image_format,
                                  submit_encode(rgb, out_spec.image_format, out_spec.jpeg_quality))
        keep_depth = "depth" in cam.outputs
        if self.release_pixels:
            depth_f = None
            if keep_depth and out_spec.depth_format == "compressed":
                depth_f, keep_depth = submit(encode_depth, depth), False
            encoded = Encodes(out_spec.image_format, encoded.rgb if encoded else None, depth_f)
            rgb = None if encoded.rgb is not None else rgb
        t2 = time.perf_counter()
        if "semantic" in cam.outputs:
            semantic, instance = kernels.gather2(gid, lut["semantic"], lut["instance"])
        else:
            semantic, instance = None, kernels.gather(gid, lut["instance"])
        if self.release_pixels:  # the label images wait for the writer packed, their counts taken now
            encoded = dataclasses.replace(
                encoded, semantic=None if semantic is None else PackedLabels.of(semantic),
                instance=PackedLabels.of(instance) if "instance" in cam.outputs else None,
                instance_counts=instance_counts(instance))
            semantic = instance = None
        frame = CameraFrame(
            agent.agent_id, cam.name, cam.width, cam.height, K, projection(cam), pose, rgb,
            depth if keep_depth else None, semantic, instance, encoded,
            tuple(float(v) for v in cam.distortion or (0.0,) * 5),
        )
        return frame, {"camera_cast": t1 - t0, "shading": t2 - t1, "labels": time.perf_counter() - t2}

    def _prepare(self, snapshot: WorldSnapshot, cameras: bool = True,
                 lidar_agents: list[AgentState] | None = None) -> _Tick:
        """What every agent's sensors share at one tick: the tick scene, shading tables, light, actor boxes
        (``cameras=False``: no camera renders this tick, so no shading tables and no light map, and with
        ``lidar_agents``, the agents whose LiDARs render it, the scene holds only the actors those LiDARs can
        reach, :func:`cosim.sensors.lidar.actors_in_reach`)."""
        placed = snapshot.actors
        if not cameras and lidar_agents is not None:
            placed = actors_in_reach(placed, [reach_ball(a, self.rig(a).lidar) for a in lidar_agents
                                              if self.rig(a).lidar is not None])
        scene = TickScene.build(self.static, placed)
        lut = scene.labels
        tables = light = None
        if cameras:
            n_act = lut["normal"][scene.n_static:scene.miss]
            rgb = scene.table(self._static_rgb, _shaded(scene.actors.albedo, n_act, self.atm), (0.0, 0.0, 0.0))
            rgb_shadow = scene.table(self._static_rgb_shadow,
                                     _shaded(scene.actors.albedo, n_act, self.atm, sun=False), (0.0, 0.0, 0.0))
            if self._signals is not None:  # the lit lamps of the traffic lights, self-luminous
                rows, lit = self._signals.lit(snapshot.traffic_lights, self.atm.exposure)
                rgb[rows] = lit
                rgb_shadow[rows] = lit
            tables = shading_tables(rgb, lut["albedo"], lut["emissive"], scene.miss, self.atm, rgb_shadow,
                                    surface_inputs(scene, self.scenario.sensors.surface_detail))
            light = _add_headlights(self._light, snapshot.actors) if self._light is not None else None
        actors = snapshot.actors
        if actors:
            a_corners = box_corners(np.array([a.center_m for a in actors]), np.array([a.size_m for a in actors]),
                                    np.array([rotation_matrix(a.rotation) for a in actors]))
            a_tracks = np.array([a.track_id for a in actors])
        else:
            a_corners, a_tracks = np.zeros((0, 8, 3)), np.zeros(0, np.int64)
        own_track = {a.agent_id: a.track_id for a in actors if a.agent_id is not None}
        # every actor's shadow (the own one too: a camera sees its vehicle's shadow)
        sboxes = shadow_boxes(a_corners, self._sun) if self._sun is not None else None
        return _Tick(scene, lut, tables, light, a_corners, a_tracks, own_track, sboxes)

    def render(self, snapshot: WorldSnapshot, rng: np.random.Generator,
               check: Callable[[], None] | None = None) -> SensorFrameSet:
        """Every agent's sensors at ``snapshot.t_ns`` (see the module docstring).

        ``check`` is called every ``CHECK_PERIOD_S`` while the frame renders; whatever it raises abandons the
        frame (sensors not started yet are cancelled) and propagates, so a caller can stop a long frame at
        once, e.g. when a simulation worker has died.
        """
        t_start = time.perf_counter()
        agents = snapshot.agents
        # one child generator per agent, then per sensor: the draws do not depend on thread timing
        agent_rngs = rng.spawn(len(agents)) if agents else []
        if self._procs is not None:
            out, timing = self._procs.render(snapshot, list(zip(agents, agent_rngs, strict=True)), check)
            if self.encode_images:
                fmt = self.scenario.output
                out = {aid: _with_encodes(af, fmt.image_format, fmt.jpeg_quality) for aid, af in out.items()}
        else:
            out, timing = self.render_agents(snapshot, list(zip(agents, agent_rngs, strict=True)), check)
        timing["total"] = time.perf_counter() - t_start
        return SensorFrameSet(snapshot.tick, snapshot.t_ns, out, timing)

    def render_agents(self, snapshot: WorldSnapshot, items: list[tuple[AgentState, np.random.Generator]],
                      check: Callable[[], None] | None = None) -> tuple[dict[str, AgentFrames], dict[str, float]]:
        """The frames of the agents in ``items`` (each with its own generator) and the timings."""
        t_start = time.perf_counter()
        timing = {"scene": 0.0, "lidar": 0.0, "camera_cast": 0.0, "shading": 0.0, "labels": 0.0}
        tick = self._prepare(snapshot, cameras=any(self.rig(agent).cameras for agent, _ in items),
                             lidar_agents=[agent for agent, _ in items] if self.cull_actors else None)
        scene, actors = tick.scene, snapshot.actors
        timing["scene"] += time.perf_counter() - t_start
        jobs: list[tuple[AgentState, object, list]] = []
        for agent, arng in items:
            rig = self.rig(agent)
            own = agent.track_id if agent.track_id is not None else tick.own_track.get(agent.agent_id)
            boxes = tick.a_corners[tick.a_tracks != own]
            occ = Occluders(self._thin, self._static_points, boxes, self._sun,
                            None if self._sun is None else tick.shadow_boxes)
            srngs = arng.spawn(1 + len(rig.cameras))
            base = self._pool.submit(self._render_agent_base, agent, rig, own, scene, srngs[0], actors, snapshot.t_ns)
            cams = [self._pool.submit(self._render_camera, agent, cam, own, scene, occ, tick.tables, tick.light,
                                      tick.lut, r)
                    for cam, r in zip(rig.cameras, srngs[1:], strict=True)]
            jobs.append((agent, base, cams))
        out: dict[str, AgentFrames] = {}
        try:
            for _, base_f, cam_fs in jobs:
                _wait(base_f, check)
                for f in cam_fs:
                    _wait(f, check)
        except BaseException:
            for _, base_f, cam_fs in jobs:
                for f in (base_f, *cam_fs):
                    if not f.cancel() and f.done() and f.exception() is None and f is not base_f:
                        encoded = f.result()[0].encoded
                        if encoded is not None:
                            encoded.cancel()
            raise
        for agent, base_f, cam_fs in jobs:
            rig = self.rig(agent)
            (lidar, kinds, imu, bev), t_base = base_f.result()
            cams: dict[str, CameraFrame] = {}
            for f in cam_fs:
                frame, t_cam = f.result()
                cams[frame.name] = frame
                for k, v in t_cam.items():
                    timing[k] += v
            for k, v in t_base.items():
                timing[k] += v
            t0 = time.perf_counter()
            vis = render_visibility(agent.agent_id, lidar.instance_id if lidar is not None else None,
                                    {n: _instance_or_counts(c) for n, c in cams.items()})
            cams = {n: c if "instance" in rig_cam_outputs(rig, n) else _drop_instance(c) for n, c in cams.items()}
            timing["labels"] += time.perf_counter() - t0
            out[agent.agent_id] = AgentFrames(agent.agent_id, agent.kind, lidar, cams, kinds, imu, bev, vis)
        timing["cast_rays"] = scene.timer.seconds
        timing["rays"] = float(scene.timer.rays)
        return out, timing


def render_processes(scenario: Scenario) -> int:
    """``scenario.sensors.render_processes``, or when null one per core (at most 2) for rigs of at least
    2 Mpx of cameras per frame (smaller ones render fastest in one process)."""
    s = scenario.sensors
    if s.render_processes is not None:
        return s.render_processes
    px = sum(c.width * c.height for a in scenario.agent_ids() for c in scenario.rig_for(a).cameras)
    return min(2, os.cpu_count() or 1) if px >= 2_000_000 and (os.cpu_count() or 1) > 1 else 0


def _wait(future: Future, check: Callable[[], None] | None) -> None:
    """Wait until ``future`` is done, calling ``check()`` every ``CHECK_PERIOD_S`` meanwhile."""
    if check is None:
        wait([future])
        return
    while not wait([future], timeout=CHECK_PERIOD_S).done:
        check()


def rig_cam_outputs(rig: RigSpec, name: str) -> tuple[str, ...]:
    for c in rig.cameras:
        if c.name == name:
            return c.outputs
    return ()


def _instance_or_counts(c: CameraFrame) -> np.ndarray | dict[int, int]:
    """The camera's instance array, or its pixel counts per track when the suite let go of the array."""
    if c.instance is None and c.encoded is not None and c.encoded.instance_counts is not None:
        return c.encoded.instance_counts
    return c.instance


def _drop_instance(c: CameraFrame) -> CameraFrame:
    return dataclasses.replace(c, instance=None)


def _with_encodes(af: AgentFrames, image_format: str, jpeg_quality: int) -> AgentFrames:
    """``af`` with an encode started for each RGB image (frames from render processes come without)."""
    cams = {n: c if c.rgb is None else dataclasses.replace(
        c, encoded=Encodes(image_format, submit_encode(c.rgb, image_format, jpeg_quality)))
        for n, c in af.cameras.items()}
    return dataclasses.replace(af, cameras=cams)


@dataclass(frozen=True)
class _Tick:
    scene: TickScene
    lut: dict[str, np.ndarray]
    tables: object | None  # None: no camera this tick
    light: LightMap | None
    a_corners: np.ndarray
    a_tracks: np.ndarray
    own_track: dict[str, int]
    shadow_boxes: np.ndarray | None
