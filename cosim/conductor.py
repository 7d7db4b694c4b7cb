"""The conductor: starts the workers, and locks them together tick by tick over Zenoh.

Per tick it sends one query to every worker and waits for every reply before going on (lockstep).
Worker deaths arrive as liveliness DELETE events on the same inbox as the replies, so a SIGKILLed
worker stops the episode within milliseconds with a message that names it and the tick; a stopped or
frozen worker loses its Zenoh session after the lease (``transport.LEASE_MS``) and is reported the same
way; a worker that computes forever is reported when its reply is ``runtime.tick_timeout_s`` late.
:meth:`Conductor.poll` lets long work between sending a step and collecting it (sensor rendering) notice
these at once instead of after the frame.

Workers are spawned (never forked: a forked child's ``zenoh.open`` hangs) and always reaped: on
success, error or Ctrl-C the responsive ones are asked to close, then terminated, then killed; an
unresponsive one (timed out, stopped, disconnected) is killed without waiting.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import queue
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import psutil
import zenoh

from cosim import protocol, transport
from cosim.errors import SyncTimeout, WorkerError
from cosim.logs import NOTICE
from cosim.workers import ROLES, spawned_worker_main
from cosim.workers.process import remove_workdirs

log = logging.getLogger(__name__)

_CLOSE_GRACE_S = 2.0  # [s] for a worker to acknowledge "close" and exit before it is terminated
_FAILED_CLOSE_S = 0.25  # [s] for the "close" acknowledgement when the episode failed (then the worker is killed)
_FAILED_EXIT_GRACE_S = 0.0  # [s] after its "close" acknowledgement (engine released) when the episode failed
_CLOSE_TICK = -2  # tick id of the close queries (init uses -1)


@dataclass(frozen=True)
class _Reply:
    role: str
    tick: int
    ok: bool
    data: Any
    received_s: float  # time.perf_counter() when the reply arrived (telemetry)


@dataclass(frozen=True)
class _Pending:
    """Queries sent for one tick whose replies have not been collected yet."""

    verb: str
    tick: int
    roles: tuple[str, ...]
    deadline: float  # time.monotonic() by which every reply must be in
    timeout_s: float
    sent_s: float  # time.perf_counter() when the queries went out (telemetry)


@dataclass(frozen=True)
class _Liveliness:
    role: str
    alive: bool


class Conductor:
    """Owns the Zenoh router, the worker processes and the lockstep loop of one episode.

    ``worker_target(role, endpoint, prefix, log_level)`` is the spawned processes' entry point
    (module-level, so ``spawn`` can import it); tests pass one that serves fake engines.

    Use as a context manager::

        with Conductor(scenario_data, world_wire, startup_timeout_s=60, tick_timeout_s=10) as c:
            c.start()
            replies = c.step(tick, t_ns, escort_targets)
    """

    def __init__(
        self,
        scenario_data: dict[str, Any],
        world_wire: dict[str, Any],
        *,
        startup_timeout_s: float,
        tick_timeout_s: float,
        listen: str | None = None,
        external_workers: bool = False,
        prefix: str | None = None,
        worker_log_level: int = logging.WARNING,
        worker_target: Callable[[str, str, str, int], None] = spawned_worker_main,
    ):
        self._init = protocol.InitRequest(scenario=scenario_data, world=world_wire)
        self._startup_timeout_s = startup_timeout_s
        self._tick_timeout_s = tick_timeout_s
        self.external = external_workers
        self.endpoint = listen or transport.free_loopback_endpoint()
        self.prefix = prefix or (transport.EXTERNAL_PREFIX if external_workers else transport.new_prefix())
        self._worker_log_level = worker_log_level
        self._worker_target = worker_target
        self._inbox: queue.Queue[_Reply | _Liveliness] = queue.Queue()
        self._alive: set[str] = set()
        self._unresponsive: set[str] = set()  # killed at shutdown without being asked to close
        self._outstanding: _Pending | None = None  # the query sent last, until collected
        self._early: dict[str, Any] = {}  # replies to it taken from the inbox by poll()
        self._procs: dict[str, mp.process.BaseProcess] = {}
        self._session: zenoh.Session | None = None
        self._keep: list[Any] = []  # declared Zenoh entities, alive as long as the session

    # -- lifecycle ------------------------------------------------------------------------------

    def __enter__(self) -> Conductor:
        self._session = transport.open_router(self.endpoint)
        live = self._session.liveliness()
        self._keep.append(live.declare_token(f"{self.prefix}/alive/conductor"))
        self._keep.append(live.declare_subscriber(f"{self.prefix}/alive/*", self._on_liveliness, history=True))
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        self.shutdown(failed=exc_type is not None)

    @property
    def session(self) -> zenoh.Session:
        """The router session (closed-loop clients are served on it: cosim.client.hub)."""
        assert self._session is not None, "Conductor used outside its with-block"
        return self._session

    def start(self) -> None:
        """Start (or wait for) the workers and have each build its engine from the world."""
        if not self.external:
            ctx = mp.get_context("spawn")
            for role in ROLES:
                proc = ctx.Process(
                    target=self._worker_target,
                    args=(role, self.endpoint, self.prefix, self._worker_log_level),
                    name=f"cosim-{role}",
                    daemon=True,
                )
                proc.start()
                self._procs[role] = proc
        else:
            log.log(NOTICE, "waiting for external workers: cosim worker traffic|drones --connect %s --prefix %s",
                    self.endpoint, self.prefix)
        self._wait_alive()
        self._query_all("init", -1, {role: self._init for role in ROLES}, self._startup_timeout_s)

    def _wait_alive(self) -> None:
        deadline = time.monotonic() + self._startup_timeout_s
        while not all(r in self._alive for r in ROLES):
            self._check_processes(tick=None)
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                missing = [r for r in ROLES if r not in self._alive]
                raise SyncTimeout(missing[0], f"did not come up within {self._startup_timeout_s:g} s "
                                  f"(endpoint {self.endpoint}, prefix {self.prefix})")
            try:
                event = self._inbox.get(timeout=min(remaining, 0.1))
            except queue.Empty:
                continue
            if isinstance(event, _Liveliness) and not event.alive:
                raise WorkerError(event.role, "went away while starting")

    def shutdown(self, *, failed: bool = False) -> None:
        """Ask the responsive workers to close, kill the others, then make sure every child process is gone.

        ``failed``: the episode is lost anyway, so a worker gets ``_FAILED_CLOSE_S`` to acknowledge (it releases
        its engine first) and is then killed (the user waits for the error message, not for processes to unload).
        """
        for role in self._unresponsive:  # a stopped or hung worker would only make us wait: no grace
            proc = self._procs.get(role)
            if proc is not None and proc.is_alive():
                proc.kill()
        responsive = [r for r in ROLES if r in self._alive and r not in self._unresponsive]
        if self._session is not None and not self._session.is_closed() and responsive:
            # Wait for the acknowledgements, so that a worker ends on "close" (status 0) rather than on
            # seeing the conductor's liveliness token vanish (status 1).
            with contextlib.suppress(WorkerError, zenoh.ZError):
                self._query_all("close", _CLOSE_TICK, {r: {} for r in responsive},
                                _FAILED_CLOSE_S if failed else _CLOSE_GRACE_S)
        deadline = time.monotonic() + (_FAILED_EXIT_GRACE_S if failed else _CLOSE_GRACE_S)
        for proc in self._procs.values():
            proc.join(max(0.0, deadline - time.monotonic()))
        for proc in self._procs.values():
            if proc.is_alive() and not failed and not _stopped(proc.pid):  # SIGTERM waits while a process is stopped
                proc.terminate()
                proc.join(1.0)
            if proc.is_alive():
                proc.kill()
                proc.join(1.0)
        for role, proc in self._procs.items():
            if proc.exitcode is not None:  # gone: a worker killed before its finalisers leaves its scratch folder
                remove_workdirs(role, proc.pid)
        self._procs.clear()
        self._keep.clear()
        if self._session is not None:
            self._session.close()
            self._session = None

    # -- lockstep -------------------------------------------------------------------------------

    def step(self, tick: int, t_ns: int, escort_targets: dict[str, protocol.EscortTarget]) -> dict[str, Any]:
        """Advance every worker to ``t_ns``; returns {role: reply data} once all have answered."""
        return self.collect(self.send_step(tick, t_ns, escort_targets))

    def send_step(self, tick: int, t_ns: int, escort_targets: dict[str, protocol.EscortTarget],
                  roles: tuple[str, ...] = ROLES, actions: dict[str, list[dict[str, Any]]] | None = None) -> _Pending:
        """Send tick ``tick``'s step requests to ``roles`` without waiting (see :meth:`collect`).

        This lets the workers compute the next tick while the caller writes and renders this one.
        ``actions`` maps a role to the closed-loop clients' actions it applies before stepping.
        """
        actions = actions or {}
        requests = {
            "traffic": protocol.StepRequest(tick, t_ns, actions=actions.get("traffic", [])),
            "drones": protocol.StepRequest(tick, t_ns, escort_targets, actions.get("drones", [])),
        }
        return self._send("step", tick, {r: requests[r] for r in roles}, self._tick_timeout_s)

    def collect(self, pending: _Pending) -> dict[str, Any]:
        """Wait for every reply of ``pending``; raises WorkerError / SyncTimeout naming worker and tick."""
        return self._collect(pending)

    def poll(self) -> None:
        """Raise now if a worker has died, disconnected or missed the outstanding query's deadline; never waits.

        Cheap (a queue drain and a ``waitpid`` per worker): long work between :meth:`send_step` and
        :meth:`collect`, such as rendering the sensors, calls it every few tens of milliseconds, so a failed
        worker ends the episode at once rather than after the frame. Replies it meets are kept for ``collect``.
        """
        pending = self._outstanding
        if pending is None:
            return
        shown_tick = pending.tick if pending.tick >= 0 else None
        while True:
            try:
                event = self._inbox.get_nowait()
            except queue.Empty:
                break
            self._take(event, pending, self._early)
        if len(self._early) < len(pending.roles) and time.monotonic() >= pending.deadline:
            self._raise_timeout(pending, self._early)
        self._check_processes(shown_tick)

    def _query_all(self, verb: str, tick: int, requests: dict[str, Any], timeout_s: float) -> dict[str, Any]:
        return self._collect(self._send(verb, tick, requests, timeout_s))

    def _send(self, verb: str, tick: int, requests: dict[str, Any], timeout_s: float) -> _Pending:
        assert self._session is not None, "Conductor used outside its with-block"
        shown_tick = tick if tick >= 0 else None
        for role, request in requests.items():
            if role not in self._alive:
                raise WorkerError(role, self._death_reason(role), tick=shown_tick)
            self._session.get(
                f"{self.prefix}/{role}/{verb}",
                lambda reply, role=role: self._on_reply(role, tick, reply),
                payload=protocol.encode(request),
                timeout=timeout_s + 1.0,
            )
        pending = _Pending(verb, tick, tuple(requests), time.monotonic() + timeout_s, timeout_s, time.perf_counter())
        self._outstanding, self._early = pending, {}
        return pending

    def _collect(self, pending: _Pending) -> dict[str, Any]:
        shown_tick = pending.tick if pending.tick >= 0 else None
        results: dict[str, Any] = self._early if pending is self._outstanding else {}
        while len(results) < len(pending.roles):
            # Replies that arrived while the caller was busy (rendering the previous tick) are taken
            # first; the deadline only fails a worker whose reply is really missing.
            remaining = pending.deadline - time.monotonic()
            try:
                event = self._inbox.get(timeout=max(0.0, min(remaining, 0.25)))
            except queue.Empty:
                if time.monotonic() >= pending.deadline:
                    self._raise_timeout(pending, results)
                # closing: a worker that already died must not keep the others from being closed
                self._check_processes(shown_tick, pending.roles if pending.tick == _CLOSE_TICK else ROLES)
                continue
            self._take(event, pending, results)
        if pending is self._outstanding:
            self._outstanding, self._early = None, {}
        return results

    def _take(self, event: _Reply | _Liveliness, pending: _Pending, results: dict[str, Any]) -> None:
        """Account one inbox event against ``pending``: keep its reply, raise on a worker's death or error."""
        shown_tick = pending.tick if pending.tick >= 0 else None
        if isinstance(event, _Liveliness):
            if not event.alive and (event.role in pending.roles or pending.tick != _CLOSE_TICK):
                raise WorkerError(event.role, self._death_reason(event.role), tick=shown_tick)
            return
        if event.tick != pending.tick or event.role not in pending.roles:
            return  # a late reply from an earlier query
        if not event.ok:
            raise WorkerError(event.role, event.data.get("error", "failed"), tick=shown_tick)
        # round trip of this query: what Zenoh, encoding and scheduling add on top of the worker's compute
        event.data["round_trip_s"] = event.received_s - pending.sent_s
        results[event.role] = event.data

    def _raise_timeout(self, pending: _Pending, results: dict[str, Any]) -> None:
        late = [r for r in pending.roles if r not in results]
        self._unresponsive.update(late)
        raise SyncTimeout(late[0], f"no reply to {pending.verb} within {pending.timeout_s:g} s",
                          tick=pending.tick if pending.tick >= 0 else None)

    # -- callbacks (Zenoh threads) --------------------------------------------------------------

    def _on_reply(self, role: str, tick: int, reply: zenoh.Reply) -> None:
        if reply.ok is not None:
            self._inbox.put(_Reply(role, tick, True, protocol.decode(reply.ok.payload.to_bytes()), time.perf_counter()))
        else:
            try:
                data = protocol.decode(reply.err.payload.to_bytes())
            except ValueError:
                data = {"error": reply.err.payload.to_string()}
            self._inbox.put(_Reply(role, tick, False, data, time.perf_counter()))

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        role = str(sample.key_expr).rsplit("/", 1)[-1]
        if role not in ROLES:
            return
        alive = sample.kind == zenoh.SampleKind.PUT
        if alive:
            self._alive.add(role)
        else:
            self._alive.discard(role)
        self._inbox.put(_Liveliness(role, alive))

    # -- process health -------------------------------------------------------------------------

    def _check_processes(self, tick: int | None, roles: tuple[str, ...] = ROLES) -> None:
        for role, proc in self._procs.items():
            if role in roles and not proc.is_alive():
                raise WorkerError(role, self._death_reason(role), tick=tick)

    def _death_reason(self, role: str) -> str:
        proc = self._procs.get(role)
        if proc is None:
            return "disconnected (liveliness lost)"
        proc.join(0.2)
        code = proc.exitcode
        if code is None:  # alive but gone from Zenoh: frozen, stopped, or its connection broke
            self._unresponsive.add(role)
            if _stopped(proc.pid):
                return (f"process {proc.pid} is stopped (SIGSTOP or a debugger) and stopped answering "
                        f"(Zenoh lease {transport.LEASE_MS / 1000:g} s expired)")
            return f"process {proc.pid} disconnected (liveliness lost)"
        if code < 0:
            return f"process {proc.pid} died (killed by signal {-code})"
        return f"process {proc.pid} exited with status {code}"


def _stopped(pid: int) -> bool:
    """Whether a process is stopped (SIGSTOP, SIGTSTP, a tracer)."""
    try:
        return psutil.Process(pid).status() in (psutil.STATUS_STOPPED, psutil.STATUS_TRACING_STOP)
    except psutil.Error:
        return False
