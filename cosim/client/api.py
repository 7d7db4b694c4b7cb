"""The Python client: join an episode's lockstep, read every tick, act on the agents.

    from cosim.client import connect, actions

    with connect("follow") as client:                       # COSIM_ENDPOINT / COSIM_PREFIX or arguments
        for obs in client.ticks():                           # one Observation per tick, in order
            v = obs.labels.agent("vehicle_0")
            client.act([actions.set_speed("vehicle_0", 5.0)])  # applied in the step to the next tick

An observation is a :class:`cosim.io.reader.Tick` built from the bytes the episode file holds, so the
reader's typed accessors (``labels``, ``transforms``, ``points(agent)``, ``visibility(agent)``...) work on
it. A tick the client leaves without calling :meth:`Client.act` is answered with no actions.
"""

from __future__ import annotations

import json
import logging
import os
import queue
import time
from collections.abc import Iterator, Sequence
from typing import Any

import zenoh

from cosim.client import wire
from cosim.errors import ActionRejected, CosimError, InputError
from cosim.io.reader import RawMessage, Tick
from cosim.transport import check_endpoint, open_client

log = logging.getLogger(__name__)

ENDPOINT_ENV = "COSIM_ENDPOINT"
PREFIX_ENV = "COSIM_PREFIX"
_CONDUCTOR_GONE = object()
_ACT_TIMEOUT_S = 30.0  # [s] for the conductor's verdict on an act query


class Observation(Tick):
    """One tick as a client sees it: the subscribed messages plus the loop's bookkeeping.

    ``last`` is True on the episode's final tick (no action is awaited after it); ``failed`` lists this
    client's and other clients' actions that the engines could not apply in the step to this tick.
    """

    def __init__(self, index: int, t_ns: int, messages: dict[str, RawMessage], *, last: bool,
                 failed: list[dict[str, Any]]):
        super().__init__(index, t_ns, messages)
        self.last = last
        self.failed = failed


class Client:
    """One closed-loop client; see :func:`connect`."""

    def __init__(self, name: str, *, endpoint: str | None = None, prefix: str | None = None,
                 topics: Sequence[str] = wire.DEFAULT_TOPICS, connect_timeout_s: float = 120.0):
        endpoint = endpoint or os.environ.get(ENDPOINT_ENV)
        prefix = prefix or os.environ.get(PREFIX_ENV)
        if not endpoint or not prefix:
            raise InputError(f"a client needs the conductor's endpoint and prefix: pass endpoint= and prefix= or set "
                             f"{ENDPOINT_ENV} and {PREFIX_ENV} (cosim run prints them)")
        check_endpoint(endpoint)
        self.name = name
        self.prefix = prefix
        self._inbox: queue.Queue[Any] = queue.Queue()
        self._tick: int | None = None  # the tick being acted on
        self._acted = False
        self._last = False
        self._session = open_client(endpoint)
        try:
            self._keep = [
                self._session.declare_subscriber(wire.client_key(prefix, name, "obs"),
                                                 lambda s: self._inbox.put(s.payload.to_bytes())),
                self._session.liveliness().declare_subscriber(f"{prefix}/alive/conductor", self._on_conductor),
                self._session.liveliness().declare_token(wire.alive_key(prefix, name)),
            ]
            self.episode = self._hello(list(topics), connect_timeout_s)
        except BaseException:
            self._session.close()
            raise

    def _on_conductor(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.DELETE:
            self._inbox.put(_CONDUCTOR_GONE)

    def _query(self, verb: str, payload: dict[str, Any], timeout_s: float) -> tuple[bool, dict[str, Any]] | None:
        """The conductor's reply (ok, data), or None when no conductor answered."""
        replies = self._session.get(wire.client_key(self.prefix, self.name, verb), payload=json.dumps(payload),
                                    timeout=timeout_s, express=True)
        for reply in replies:
            if reply.ok is not None:
                return True, json.loads(reply.ok.payload.to_bytes())
            return False, json.loads(reply.err.payload.to_bytes())
        return None

    def _hello(self, topics: list[str], timeout_s: float) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            answer = self._query("hello", {"protocol": wire.CLIENT_PROTOCOL_VERSION, "topics": topics}, 2.0)
            if answer is None:  # no conductor (yet): it may still be building the world
                time.sleep(0.2)
                continue
            ok, data = answer
            if not ok:
                raise CosimError(f"client {self.name!r}: the conductor refused it: {data.get('error')}")
            log.info("client %s joined %s (%s ticks)", self.name, data.get("scenario"), data.get("n_ticks"))
            return data
        raise CosimError(f"client {self.name!r}: no conductor answered on prefix {self.prefix} within {timeout_s:g} s")

    # -- the loop -------------------------------------------------------------------------------

    def ticks(self) -> Iterator[Observation]:
        """Every tick of the episode in order; ends after the last one."""
        while True:
            obs = self._next()
            self._tick, self._last, self._acted = obs.index, obs.last, False
            yield obs
            if not self._acted and not obs.last:
                self.act([])
            if obs.last:
                return

    def _next(self) -> Observation:
        item = self._inbox.get()
        if item is _CONDUCTOR_GONE:
            at = f" after tick {self._tick}" if self._tick is not None else ""
            raise CosimError(f"client {self.name!r}: the conductor went away{at}")
        header, parts = wire.unpack_observation(item)
        t_ns = header["t_ns"]
        messages = {m["topic"]: RawMessage(m["topic"], m["schema"], m["encoding"], t_ns, t_ns, 0, data, schema)
                    for m, schema, data in parts}
        return Observation(header["tick"], t_ns, messages, last=header["last"], failed=header["failed"])

    def act(self, actions: Sequence[dict[str, Any]]) -> int:
        """Send this tick's actions (see :mod:`cosim.actions`); returns how many were accepted.

        Raises :class:`~cosim.errors.ActionRejected` when the conductor refused them (the message names each
        bad action); the tick then counts as answered with no actions and the episode goes on. On the last
        tick nothing is sent.
        """
        if self._tick is None:
            raise CosimError("act() before the first tick: iterate over ticks() first")
        if self._last:
            return 0  # the episode's last tick: nothing is awaited
        if self._acted:
            raise CosimError(f"client {self.name!r} already acted on tick {self._tick}")
        self._acted = True
        answer = self._query("act", {"tick": self._tick, "actions": list(actions)}, _ACT_TIMEOUT_S)
        if answer is None:
            raise CosimError(f"client {self.name!r}: no answer from the conductor to the actions of tick {self._tick}")
        ok, data = answer
        if not ok:
            raise ActionRejected(f"tick {self._tick}: {data.get('error')}")
        return int(data["accepted"])

    # -- lifecycle ------------------------------------------------------------------------------

    def close(self) -> None:
        for entity in reversed(self._keep):
            entity.undeclare()
        self._keep.clear()
        if not self._session.is_closed():
            self._session.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def connect(name: str, *, endpoint: str | None = None, prefix: str | None = None,
            topics: Sequence[str] = wire.DEFAULT_TOPICS, connect_timeout_s: float = 120.0) -> Client:
    """Join the episode at ``endpoint`` / ``prefix`` (default: ``$COSIM_ENDPOINT`` / ``$COSIM_PREFIX``) as
    client ``name`` (one of the scenario's ``clients`` or ``cosim run --clients``), reading ``topics``
    (names or shell patterns of docs/episode_format.md, e.g. ``/drone_*/visibility``)."""
    return Client(name, endpoint=endpoint, prefix=prefix, topics=topics, connect_timeout_s=connect_timeout_s)
