"""In-process fake engines for fast conductor tests: real processes, real Zenoh, no SUMO or JSBSim; and fake
episode functions for batch tests.

The behaviour is chosen by the scenario's name so that it travels with the init request:
``fake-hang-drones-3`` makes the drone worker hang at tick 3, ``fake-fail-traffic-2`` makes the
traffic worker raise at tick 2, ``fake-exit-drones-4`` makes it exit abruptly.
"""

from __future__ import annotations

import json
import logging
import multiprocessing as mp
import os
import time
from pathlib import Path
from typing import Any

from cosim import protocol
from cosim.errors import CosimError
from cosim.workers.base import serve
from cosim.workers.process import die_with_conductor


class FakeEngine:
    def __init__(self, role: str):
        self.role = role
        self.mode: tuple[str, str, int] | None = None

    def init(self, request: protocol.InitRequest) -> dict[str, Any]:
        parts = request.scenario["name"].split("-")
        if len(parts) == 4 and parts[0] == "fake":
            self.mode = (parts[1], parts[2], int(parts[3]))
        return {"ready": True}

    def step(self, request: protocol.StepRequest) -> dict[str, Any]:
        if self.mode and self.mode[1] == self.role and request.tick == self.mode[2]:
            action = self.mode[0]
            if action == "hang":
                time.sleep(3600)
            if action == "fail":
                raise CosimError(f"injected failure at tick {request.tick}")
            if action == "exit":
                os._exit(3)
        t = request.t_ns / 1e9
        if self.role == "traffic":
            v = protocol.VehicleState("vehicle_0", "car", (10.0 * t, 0.0, 0.75), (4.5, 1.9, 1.5), 0.0, 0.0,
                                      10.0, (10.0, 0.0, 0.0), 0.0, 0.0, "vehicle_0")
            return {"tick": request.tick, "t_ns": request.t_ns, "vehicles": [v]}
        d = protocol.DroneState("drone_0", (0.0, 0.0, 50.0), (0.0, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0),
                                (0.0, 0.0, 9.81), (0.0, 0.0, 0.0, 1.0), 0.0, "hover", "hold")
        return {"tick": request.tick, "t_ns": request.t_ns, "drones": [d],
                "escorts_seen": sorted(request.escort_targets)}

    def close(self) -> None:
        pass


def fake_worker_main(role: str, connect: str, prefix: str, log_level: int) -> None:
    die_with_conductor(role)
    logging.basicConfig(level=log_level)
    raise SystemExit(serve(role, connect, prefix, FakeEngine(role), spawned=True))


# ------------------------------------------------------------------------- fake episode functions
# Module-level so spawn children import them by name. Behaviour comes from the scenario's
# ``description`` (a real schema field), set per level in the test sweeps: no hooks in production code.


def _write_atomically(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.partial")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def fake_episode(job, progress):
    """Deterministic bytes from the scenario; behaviour from ``description``."""
    s = job.scenario
    how = s.get("description", "")
    ticks = round(s["duration_s"] * s["tick_hz"])
    marker = Path(job.out_dir) / f".crashed-{job.episode_id}"
    if how == "crash_once" and not marker.exists():
        marker.write_text("x")
        os._exit(3)  # a hard crash: no exception, no result
    if how == "always_fail":
        raise CosimError(f"forced failure of {job.episode_id}")
    for k in range(ticks):
        if how == "slow":
            time.sleep(0.15)
        progress(k + 1, ticks)
    payload = json.dumps({"seed": s["seed"], "env": s["environment"], "map": s["map"],
                          "vehicles": s["agents"]["vehicles"]["count"]}, sort_keys=True).encode()
    _write_atomically(job.path, payload * 50)
    return {"ticks": ticks}


def niceness_episode(job, progress):
    """:func:`fake_episode`, leaving the niceness it ran at in ``OUT/.nice-<episode>`` (the last attempt's)."""
    (Path(job.out_dir) / f".nice-{job.episode_id}").write_text(str(os.nice(0)))
    return fake_episode(job, progress)


def _child_ok() -> None:
    pass


def spawning_episode(job, progress):
    """An episode that starts its own process, as the real conductor does (needs a non-daemonic parent)."""
    p = mp.get_context("spawn").Process(target=_child_ok)
    p.start()
    p.join(30)
    if p.exitcode != 0:
        raise CosimError(f"grandchild exited with {p.exitcode}")
    return fake_episode(job, progress)
