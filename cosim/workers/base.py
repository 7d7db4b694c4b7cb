"""The worker side of the lockstep protocol, shared by the traffic and drone workers.

A worker is a Zenoh client that declares a liveliness token ``<prefix>/alive/<role>`` and one
queryable ``<prefix>/<role>/*``. Queries are handled one at a time on the main thread (libsumo and
the dynamics engines are not thread-safe): ``init`` builds the engine, ``step`` advances it,
``close`` ends the worker. The worker also exits when the conductor's liveliness token goes away,
so a dead conductor never leaves workers behind.
"""

from __future__ import annotations

import logging
import os
import queue
import signal
import time
import traceback
from typing import Any, Protocol

import zenoh

from cosim import protocol
from cosim.errors import CosimError
from cosim.transport import open_client
from cosim.workers.process import set_process

log = logging.getLogger(__name__)

_CONDUCTOR_GONE = object()


class Engine(Protocol):
    """What a worker drives: built by ``init``, advanced by ``step``."""

    def init(self, request: protocol.InitRequest) -> dict[str, Any]: ...

    def step(self, request: protocol.StepRequest) -> dict[str, Any]: ...

    def close(self) -> None: ...


def serve(role: str, connect: str, prefix: str, engine: Engine, *, spawned: bool = False) -> int:
    """Serve one episode for ``role`` and return the process exit status."""
    set_process(role, die_with_parent=spawned)
    if spawned:
        # Ctrl-C reaches the whole process group; the conductor shuts us down in order instead.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    inbox: queue.Queue[Any] = queue.Queue()
    session = open_client(connect)
    try:
        def on_conductor(sample: zenoh.Sample) -> None:
            if sample.kind == zenoh.SampleKind.DELETE:
                inbox.put(_CONDUCTOR_GONE)

        conductor_watch = session.liveliness().declare_subscriber(f"{prefix}/alive/conductor", on_conductor)
        queryable = session.declare_queryable(f"{prefix}/{role}/*", inbox.put)
        token = session.liveliness().declare_token(f"{prefix}/alive/{role}")
        log.info("%s worker ready on %s (prefix %s, pid %d)", role, connect, prefix, os.getpid())
        status = _loop(role, inbox, engine)
        token.undeclare()
        queryable.undeclare()
        conductor_watch.undeclare()
        return status
    finally:
        engine.close()
        session.close()


def _loop(role: str, inbox: queue.Queue[Any], engine: Engine) -> int:
    """Serve queries until ``close`` (status 0) or until the conductor goes away: status 0 if this worker
    had already answered the episode's last tick, 1 if the episode was cut short."""
    last_tick, final_tick = -1, None
    while True:
        query = inbox.get()
        if query is _CONDUCTOR_GONE:
            if final_tick is not None and last_tick == final_tick:
                log.info("%s worker: episode complete, conductor gone; exiting", role)
                return 0
            log.warning("%s worker: conductor went away at tick %d; exiting", role, last_tick)
            return 1
        verb = str(query.key_expr).rsplit("/", 1)[-1]
        try:
            data = protocol.unbytes(protocol.decode(query.payload.to_bytes())) if query.payload else {}
            if verb == "init":
                request = protocol.InitRequest(**data)
                reply = engine.init(request)
                final_tick = _final_tick(request.scenario)
            elif verb == "step":
                started = time.perf_counter_ns()  # telemetry only: never feeds the simulation
                step = protocol.step_request_from_dict(data)
                reply = engine.step(step)
                reply["compute_ns"] = time.perf_counter_ns() - started
                last_tick = step.tick
            elif verb == "close":  # release the engine first: once acknowledged, this process may be killed
                engine.close()
                query.reply(query.key_expr, protocol.encode({"closed": True}))
                return 0
            else:
                raise CosimError(f"unknown request {verb!r}")
            query.reply(query.key_expr, protocol.encode(reply))
        except CosimError as exc:
            query.reply_err(protocol.encode({"error": str(exc), "type": type(exc).__name__}))
        except Exception as exc:  # an engine bug: report it to the conductor with its traceback
            log.exception("%s worker failed on %s", role, verb)
            detail = "".join(traceback.format_exception_only(exc)).strip()
            query.reply_err(protocol.encode({"error": f"internal error: {detail}", "type": type(exc).__name__}))
        finally:
            del query


def _final_tick(scenario: dict[str, Any]) -> int | None:
    """Index of the episode's last tick, from the resolved scenario in the init request."""
    try:
        return round(float(scenario["duration_s"]) * float(scenario["tick_hz"])) - 1
    except (KeyError, TypeError, ValueError):
        return None
