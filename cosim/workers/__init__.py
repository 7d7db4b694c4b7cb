"""Simulation workers: one OS process per engine, speaking the lockstep protocol over Zenoh.

This module is what a spawned worker imports first, so it stays light (no Zenoh, no engines): the worker
arms its death-with-the-conductor (:mod:`cosim.workers.process`) before the imports that take seconds on a
loaded machine.
"""

from __future__ import annotations

import logging

from cosim.workers.process import die_with_conductor

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
    """multiprocessing target: tie the process to the conductor, then run the worker and exit with its status."""
    die_with_conductor(role)
    raise SystemExit(worker_main(role, connect, prefix, log_level, spawned=True))
