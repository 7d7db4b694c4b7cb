"""Run one episode: scenario in, one labelled MCAP file out.

``run_episode`` is the typed entry point behind ``cosim run`` and the batch executors. It builds the
world, starts the conductor and its workers, and per tick assembles the snapshot, renders the
sensors and writes labels and sensor data. The episode file appears only when it is complete.
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib.metadata
import itertools
import json
import logging
import platform
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

import cosim
from cosim.assemble import TrackRegistry, build_snapshot, escort_targets_of
from cosim.classes import class_table
from cosim.conductor import Conductor
from cosim.io.format import FORMAT_VERSION
from cosim.preflight import check_output_dir
from cosim.protocol import drone_from_dict, vehicle_from_dict
from cosim.scenario import LoadedScenario
from cosim.scenario.model import EscortDrone
from cosim.snapshot import WorldSnapshot
from cosim.world.types import World

log = logging.getLogger(__name__)

#: Independent random streams derived from the scenario seed.
SENSOR_STREAM = 0x5E5

_VERSIONED = ("libsumo", "eclipse-sumo", "jsbsim", "pybullet", "open3d-cpu", "eclipse-zenoh", "mcap",
              "numpy", "pydantic", "protobuf", "foxglove-schemas-protobuf")


@dataclass
class EpisodeResult:
    """What ``run_episode`` reports back (also what ``cosim run`` prints)."""

    path: Path
    ticks: int
    sim_time_s: float
    actors: int
    messages: int
    size_bytes: int
    wall_time_s: float
    tick_times_s: list[float] = field(default_factory=list)  # wall time the tick loop waited for the workers
    sync_costs_s: list[float] = field(default_factory=list)  # per tick, max over workers of round trip - compute
    compute_s: dict[str, list[float]] = field(default_factory=dict)  # per worker role: its own step time
    loop_wall_s: float = 0.0  # the tick loop alone (no world build, worker start-up or finishing)
    client_waits_s: list[float] = field(default_factory=list)  # per tick: observations out to the last action in
    client_cpu_s: list[float] = field(default_factory=list)  # per tick: the runner thread's CPU time for the clients

    @property
    def real_time_factor(self) -> float:
        return self.sim_time_s / self.wall_time_s if self.wall_time_s > 0 else float("inf")


def dependency_versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for name in _VERSIONED:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            continue
    return out


def episode_path(loaded: LoadedScenario, out_dir: Path) -> Path:
    s = loaded.scenario
    stem = s.output.name or f"{s.name}_s{s.seed}"
    return Path(out_dir) / f"{stem}.mcap"


def episode_metadata(loaded: LoadedScenario, world: World) -> dict[str, str]:
    """The ``episode`` metadata record (all values are strings; structured ones are JSON)."""
    s = loaded.scenario
    strategies = [d.strategy for d in s.agents.drones]
    return {
        "format_version": FORMAT_VERSION,
        "generator": f"cosim {cosim.__version__}",
        "scenario": s.name,
        "description": s.description,
        "seed": str(s.seed),
        "weather": s.environment.weather,
        "lighting": s.environment.lighting,
        "environment": world.map_kind,
        "strategies": json.dumps(strategies),
        "tick_hz": repr(s.tick_hz),
        "tick_ns": str(s.tick_ns),
        "n_ticks": str(s.n_ticks),
        "duration_s": repr(s.duration_s),
        "agents": json.dumps(s.agent_ids()),
        "sensors_enabled": json.dumps(s.sensors.enabled),
        "geo_origin": json.dumps(list(world.geo_origin)),
        "map_bounds_m": json.dumps(list(world.bounds_m)),
        "class_table": json.dumps(class_table()),
        "events": json.dumps([e.model_dump(mode="json") for e in s.events]),
        "versions": json.dumps(dependency_versions()),
    }


#: glibc malloc arenas of an episode's process (:func:`limit_malloc_arenas`)
MALLOC_ARENAS = 2
_M_ARENA_MAX = -8  # mallopt parameter (glibc malloc.h)


def limit_malloc_arenas(n: int = MALLOC_ARENAS) -> bool:
    """Cap glibc's malloc arenas of this process at ``n`` (``mallopt(M_ARENA_MAX, n)``); whether it took effect
    (False where the C library has no ``mallopt``). By default glibc gives threads up to 8 arenas per core,
    and each keeps the large image arrays the render threads free for reuse: the default episode's runner
    grew steadily to 1.23 GB over 3 s (the tree to 1.62 GB). With 2 arenas it peaks at 1.03 GB (the tree
    1.42 GB, under issue 26's 1.5 GB) for the same CPU time (``benchmarks/memory.py``; docs/architecture.md,
    "Processes and the lockstep protocol")."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return mallopt(_M_ARENA_MAX, int(n)) == 1


def run_episode(
    loaded: LoadedScenario,
    out_dir: Path,
    *,
    progress: Callable[[int, int], None] | None = None,
    listen: str | None = None,
    external_workers: bool = False,
    prefix: str | None = None,
    worker_log_level: int = logging.WARNING,
) -> EpisodeResult:
    """Generate one episode; returns where it went and how long it took.

    ``progress(done_ticks, total_ticks)`` is called after every tick. Raises a
    :class:`~cosim.errors.CosimError` on failure; no file is left at the output path then.
    """
    from cosim.io.events import EVENTS_SCHEMA, events_payload
    from cosim.io.labels import label_messages
    from cosim.io.writer import BackgroundWriter, EpisodeWriter, remove_stale_partials
    from cosim.preflight import check_scenario_inputs
    from cosim.world import build_world

    s = loaded.scenario
    started = time.perf_counter()
    limit_malloc_arenas()  # before the render and writer threads start
    final = episode_path(loaded, out_dir)
    check_scenario_inputs(loaded)  # before the output folder is made: a bad input leaves nothing behind
    check_output_dir(final.parent)
    remove_stale_partials(final.parent)
    with tempfile.TemporaryDirectory(prefix="cosim-world-") as workdir:
        world = build_world(loaded, Path(workdir))
    suite = _sensor_suite(loaded, world)
    links = _link_model(loaded, world)
    tracks = TrackRegistry()
    escorts = {f"drone_{i}": d.target for i, d in enumerate(s.agents.drones) if isinstance(d, EscortDrone)}
    tick_times: list[float] = []
    sync_costs: list[float] = []
    compute: dict[str, list[float]] = {}

    with contextlib.ExitStack() as cleanup, EpisodeWriter(final, compression=s.output.compression) as writer, \
            BackgroundWriter(writer) as background, Conductor(
        loaded.resolved,
        world.to_wire(),
        startup_timeout_s=s.runtime.startup_timeout_s,
        tick_timeout_s=s.runtime.tick_timeout_s,
        listen=listen,
        external_workers=external_workers,
        prefix=prefix,
        worker_log_level=worker_log_level,
    ) as conductor:
        rendered: list[Any] = []  # the frames handed to the writer last; on failure their encodes are dropped
        if suite is not None:  # on failure: drop the pending encodes, do not wait for abandoned sensors
            cleanup.push(lambda failed, *_: suite.close(wait=failed is None))
            cleanup.callback(lambda: rendered and rendered[-1].cancel_encodes())
        writer.add_metadata("episode", episode_metadata(loaded, world))
        loop = _closed_loop(conductor, loaded, world, escorts)
        conductor.start()
        if loop is not None:
            loop.wait_connected()
        log.info("workers ready; stepping %d ticks", s.n_ticks)
        loop_started = time.perf_counter()
        pending = None
        for tick in range(s.n_ticks):
            t_ns = tick * s.tick_ns
            t0 = time.perf_counter()
            replies = _first_tick(conductor, escorts) if pending is None else conductor.collect(pending)
            vehicles = [vehicle_from_dict(v) for v in replies["traffic"]["vehicles"]]
            if loop is None and tick + 1 < s.n_ticks:  # workers compute tick k+1 while tick k is written
                pending = conductor.send_step(tick + 1, t_ns + s.tick_ns, escort_targets_of(vehicles, escorts))
            drones = [drone_from_dict(d) for d in replies["drones"]["drones"]]
            snapshot = build_snapshot(tick, t_ns, vehicles, drones, world, tracks,
                                      replies["traffic"].get("signals"))
            step_s = time.perf_counter() - t0
            tick_times.append(step_s)
            sync_costs.append(max(r["round_trip_s"] - r.get("compute_ns", 0) / 1e9 for r in replies.values()))
            for role, reply in replies.items():
                compute.setdefault(role, []).append(reply.get("compute_ns", 0) / 1e9)
            rig_tf = suite.transforms(snapshot) if suite is not None else []
            labels = label_messages(snapshot, rig_tf)
            if s.events:
                payload = events_payload(tick, t_ns, replies["traffic"].get("events", []),
                                         lambda sid: tracks.get("sumo", sid))
                labels.append(("/events", ("cosim.Events", EVENTS_SCHEMA, payload)))
            if loop is not None:
                labels.append(loop.record(tick, t_ns, replies))
            if links is not None:
                labels.append(links.message(snapshot))
            if suite is None:
                messages = labels
                write = lambda labels=labels: labels  # noqa: E731
            elif loop is not None and loop.wants_sensor_topics():  # the clients get them before tick k+1
                frames = suite.render(snapshot, np.random.default_rng([s.seed, tick, SENSOR_STREAM]), conductor.poll)
                messages = [*labels, *suite.messages(frames)]
                write = lambda messages=messages: messages  # noqa: E731
            else:
                # rendered here; encoded, serialised and written while the next tick renders, one camera
                # after the other, each camera's arrays freed once its messages are made (the frame set is
                # consumed), so a frame's arrays and its messages are not all held at once
                # conductor.poll: a worker that dies or hangs meanwhile stops the frame, not just the next tick
                frames = suite.render(snapshot, np.random.default_rng([s.seed, tick, SENSOR_STREAM]), conductor.poll)
                write = lambda labels=labels, frames=frames: itertools.chain(labels, suite.records(frames))  # noqa: E731
                rendered[:] = [frames]
                messages = labels
            if loop is not None:  # closed loop: tick k+1 is stepped with the clients' actions on tick k
                # the writer thread takes the tick only after the clients answered (and the workers were sent
                # tick k+1), so that it does not compete with the round trip for the GIL
                loop.publish(tick, t_ns, vehicles, messages, last=tick + 1 == s.n_ticks)
                if tick + 1 < s.n_ticks:
                    actions = loop.collect(tick)
                    pending = conductor.send_step(tick + 1, t_ns + s.tick_ns, escort_targets_of(vehicles, escorts),
                                                  actions=actions)
            background.submit(t_ns, write)
            if progress is not None:
                progress(tick + 1, s.n_ticks)
        background.flush()
        loop_wall_s = time.perf_counter() - loop_started
        _attach(writer, loaded, world)
        messages = writer.message_count
        path = writer.finish()
    return EpisodeResult(
        path=path,
        ticks=s.n_ticks,
        sim_time_s=s.n_ticks * s.tick_ns / 1e9,
        actors=len(tracks),
        messages=messages,
        size_bytes=path.stat().st_size,
        wall_time_s=time.perf_counter() - started,
        tick_times_s=tick_times,
        sync_costs_s=sync_costs,
        compute_s=compute,
        loop_wall_s=loop_wall_s,
        client_waits_s=loop.waits_s if loop is not None else [],
        client_cpu_s=loop.cpu_s if loop is not None else [],
    )


def _closed_loop(conductor: Conductor, loaded: LoadedScenario, world: World, escorts: dict[str, str]) -> Any:
    """The closed-loop side of the episode (cosim.client.loop), or None without clients."""
    if not loaded.scenario.clients:
        return None
    from cosim.client.loop import ClosedLoop

    return ClosedLoop(conductor, loaded, world, escorts)


def _first_tick(conductor: Conductor, escorts: dict[str, str]) -> dict[str, Any]:
    """Tick 0: traffic first, so escorting drones start at their vehicle's offset point.

    From tick 1 on both workers step in parallel, the drones getting their targets' state one tick late.
    """
    traffic = conductor.collect(conductor.send_step(0, 0, {}, roles=("traffic",)))
    vehicles = [vehicle_from_dict(v) for v in traffic["traffic"]["vehicles"]]
    targets = escort_targets_of(vehicles, escorts)
    drones = conductor.collect(conductor.send_step(0, 0, targets, roles=("drones",)))
    return {**traffic, **drones}


def _attach(writer: Any, loaded: LoadedScenario, world: World) -> None:
    scenario_yaml = yaml.safe_dump(loaded.resolved, sort_keys=False).encode()
    writer.add_attachment("scenario.yaml", "application/yaml", scenario_yaml)
    writer.add_attachment("map.net.xml", "application/xml", world.net_xml)
    writer.add_attachment("routes.rou.xml", "application/xml", world.routes_xml)
    writer.add_attachment("world.json", "application/json", json.dumps(_world_summary(world)).encode())


def _world_summary(world: World) -> dict[str, Any]:
    """The static layout and RSU sites as plain JSON (what a reader needs to rebuild the scene)."""
    wire = world.to_wire()
    return {k: v for k, v in wire.items() if k not in ("net_xml", "routes_xml")}


class _SensorAdapter:
    """Couples the sensor suite to the runner: rig transforms for /tf, rendering, sensor messages."""

    def __init__(self, loaded: LoadedScenario, world: World):
        from cosim.io.sensor_messages import frame_messages, frame_records
        from cosim.sensors import SensorSuite
        from cosim.sensors.rig import sensor_transforms
        from cosim.sensors.suite import render_processes

        self._scenario = loaded.scenario
        self._suite = SensorSuite(loaded.scenario, world, processes=render_processes(loaded.scenario),
                                  release_pixels=True)
        self._frame_messages = frame_messages
        self._frame_records = frame_records
        self._sensor_transforms = sensor_transforms

    def transforms(self, snapshot: WorldSnapshot) -> list[Any]:
        out: list[Any] = []
        for agent in snapshot.agents:
            out.extend(self._sensor_transforms(self._scenario, agent))
        return out

    def render(self, snapshot: WorldSnapshot, rng: np.random.Generator, check: Callable[[], None]) -> Any:
        return self._suite.render(snapshot, rng, check)

    def messages(self, frames: Any) -> list[tuple[str, Any]]:
        """The sensor messages of rendered frames (waits for their image encodes)."""
        out = self._scenario.output
        return self._frame_messages(frames, frames.t_ns, image_format=out.image_format,
                                    jpeg_quality=out.jpeg_quality,
                                    lidar_positions=self._scenario.sensors.lidar_positions,
                                    depth_format=out.depth_format)

    def records(self, frames: Any) -> Iterator[tuple[str, Any]]:
        """The sensor records of rendered frames for the writer, made as they are taken; consumes ``frames``."""
        out = self._scenario.output
        return self._frame_records(frames, frames.t_ns, image_format=out.image_format,
                                   jpeg_quality=out.jpeg_quality,
                                   lidar_positions=self._scenario.sensors.lidar_positions,
                                   depth_format=out.depth_format, consume=True)

    @property
    def static(self) -> Any:
        """The suite's static scene (Open3D, built once), shared with the link model."""
        return self._suite.static

    def close(self, wait: bool = True) -> None:
        self._suite.close(wait)


def _sensor_suite(loaded: LoadedScenario, world: World) -> _SensorAdapter | None:
    if not loaded.scenario.sensors.enabled:
        return None
    return _SensorAdapter(loaded, world)


def _link_model(loaded: LoadedScenario, world: World) -> Any:
    """The ``/comm/links`` model (None when ``comm.enabled`` is false); it ray-casts through the walls
    of the layout's blocking prisms, whether sensors run or not (the renderer's porous tree crowns
    are a camera and LiDAR matter; a radio link sees a crown as its prism)."""
    s = loaded.scenario
    if not s.comm.enabled:
        return None
    from cosim.comm.links import LinkModel
    from cosim.comm.los import LinkScene

    scene = LinkScene.from_layout(world.layout, s.sensors.ray_backend)
    return LinkModel(s.comm, scene, world.map_kind, s.seed, s.tick_ns)
