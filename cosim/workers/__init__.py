"""Simulation workers: one OS process per engine, speaking the lockstep protocol over Zenoh."""

from __future__ import annotations

import logging

ROLES = ("traffic", "drones")


def make_engine(role: str):
    """The engine object for a worker role."""
    if role == "traffic":
        from cosim.workers.traffic import TrafficEngine

        return TrafficEngine()
    if role == "drones":
        from cosim.workers.drones import DroneEngine

        return DroneEngine()
    raise ValueError(f"unknown worker role {role!r}; known: {', '.join(ROLES)}")


def worker_main(role: str, connect: str, prefix: str, log_level: int = logging.WARNING, spawned: bool = True) -> int:
    """Process entry point of a worker (spawned by the conductor or run by ``cosim worker``)."""
    from cosim.workers.base import serve

    logging.basicConfig(level=log_level, format=f"%(asctime)s {role}[%(process)d] %(levelname)s %(message)s")
    return serve(role, connect, prefix, make_engine(role), spawned=spawned)


def spawned_worker_main(role: str, connect: str, prefix: str, log_level: int) -> None:
    """multiprocessing target: run the worker and exit with its status."""
    raise SystemExit(worker_main(role, connect, prefix, log_level, spawned=True))
