"""The conductor's side of closed-loop clients: who is connected, what they read, what they answered.

Per tick the runner calls :meth:`ClientHub.publish` (the tick's messages, filtered by each client's
topics, put to ``<prefix>/clients/<name>/obs``) and then :meth:`ClientHub.collect`, which waits for
every client's ``act`` query of that tick. Queries are answered on Zenoh's threads as they arrive:
validated against the observed tick (:func:`cosim.actions.check_actions`), a refused message
gets an error reply naming each bad action and counts as the client's (empty) answer, so the episode
goes on. A client's liveliness token going away ends the episode with :class:`ClientError`, a missing
answer with :class:`ClientTimeout`, both naming the client and the tick.
"""

from __future__ import annotations

import fnmatch
import json
import logging
import queue
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import zenoh

from cosim.actions import ActionContext, as_dicts, check_actions
from cosim.client import wire
from cosim.errors import ActionRejected, ClientError, ClientTimeout
from cosim.logs import NOTICE
from cosim.scenario.model import ClientSpec

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class _Hello:
    name: str


@dataclass(frozen=True)
class _Act:
    name: str
    tick: int
    actions: list[dict[str, Any]]


@dataclass(frozen=True)
class _Gone:
    name: str


@dataclass(frozen=True)
class ClientAction:
    """One accepted action, as the workers get it and ``/actions`` records it."""

    client: str
    observed_tick: int
    action: dict[str, Any]


class ClientHub:
    """Closed-loop clients of one episode on the conductor's Zenoh session."""

    def __init__(self, session: zenoh.Session, prefix: str, specs: Sequence[ClientSpec], *,
                 default_timeout_s: float, episode: dict[str, Any]):
        self._session = session
        self._prefix = prefix
        self._specs = {c.name: c for c in specs}
        self._timeout_s = {c.name: c.timeout_s or default_timeout_s for c in specs}
        self._episode = episode  # facts every client gets in its hello reply
        self._inbox: queue.Queue[_Hello | _Act | _Gone] = queue.Queue()
        self._lock = threading.Lock()
        self._topics: dict[str, tuple[str, ...]] = {}  # client -> topic patterns, once it said hello
        self._sent_schemas: dict[str, set[str]] = {name: set() for name in self._specs}
        self._awaiting: int | None = None  # the tick whose actions are being collected
        self._answered: set[str] = set()
        self._context: ActionContext | None = None
        self._published_s = 0.0  # time.monotonic() when the awaited tick went out
        self._gone: set[str] = set()  # clients whose liveliness token went away (main thread only)
        self._keep = [
            session.declare_queryable(wire.client_key(prefix, "*", "*"), self._on_query),
            session.liveliness().declare_subscriber(wire.alive_key(prefix, "*"), self._on_liveliness, history=True),
        ]

    @property
    def names(self) -> list[str]:
        return list(self._specs)

    def wants_sensor_topics(self) -> bool:
        """Whether any client reads topics beyond the labels (the runner then builds sensor messages at once)."""
        from cosim.io.format import LABEL_TOPICS

        return any(not all(p in LABEL_TOPICS or p == "/actions" for p in pats) for pats in self._topics.values())

    # -- start-up -------------------------------------------------------------------------------

    def wait_connected(self, timeout_s: float, endpoint: str) -> None:
        """Block until every client said hello; ClientTimeout naming the first missing one."""
        log.log(NOTICE, "waiting for clients %s: connect with cosim.client.connect(NAME, endpoint=%r, prefix=%r) "
                "or COSIM_ENDPOINT=%s COSIM_PREFIX=%s", ", ".join(self._specs), endpoint, self._prefix,
                endpoint, self._prefix)
        deadline = time.monotonic() + timeout_s
        while True:
            with self._lock:
                missing = [n for n in self._specs if n not in self._topics]
            if not missing:
                return
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise ClientTimeout(missing[0], f"did not connect within {timeout_s:g} s "
                                                f"(endpoint {endpoint}, prefix {self._prefix})")
            try:
                event = self._inbox.get(timeout=min(remaining, 0.25))
            except queue.Empty:
                continue
            if isinstance(event, _Gone):
                raise ClientError(event.name, "went away before the episode started")

    # -- per tick -------------------------------------------------------------------------------

    def publish(self, tick: int, t_ns: int, messages: Sequence[tuple[str, Any]], context: ActionContext, *,
                last: bool, failed: Sequence[dict[str, Any]] = ()) -> None:
        """Send tick ``tick``'s messages to every client and start collecting its actions (unless ``last``)."""
        with self._lock:
            self._context = context
            self._awaiting = None if last else tick
            self._answered = set()
            self._published_s = time.monotonic()
        encoded: dict[str, tuple[wire.Encoded, Any]] = {}
        for name, patterns in self._topics.items():
            parts = []
            for topic, message in messages:
                if not any(fnmatch.fnmatchcase(topic, p) for p in patterns):
                    continue
                if topic not in encoded:
                    encoded[topic] = (wire.encode_message(message), message)
                enc, msg = encoded[topic]
                schema = b""
                if topic not in self._sent_schemas[name]:
                    schema = wire.schema_bytes(msg)
                    self._sent_schemas[name].add(topic)
                parts.append((topic, enc, schema))
            header = {"tick": tick, "t_ns": t_ns, "last": last, "failed": list(failed)}
            self._session.put(wire.client_key(self._prefix, name, "obs"), wire.pack_observation(header, parts),
                              congestion_control=zenoh.CongestionControl.BLOCK, express=True)

    def collect(self, tick: int) -> list[ClientAction]:
        """Wait for every client's answer to ``tick``; the accepted actions in client order."""
        got: dict[str, list[dict[str, Any]]] = {}
        deadlines = {n: self._published_s + t for n, t in self._timeout_s.items()}
        while len(got) < len(self._specs):
            waiting = [n for n in self._specs if n not in got]
            gone = [n for n in waiting if n in self._gone]  # a client that died after answering the last tick too
            if gone:
                raise ClientError(gone[0], "disconnected (liveliness lost)", tick=tick)
            first = min(waiting, key=lambda n: deadlines[n])
            remaining = deadlines[first] - time.monotonic()
            if remaining <= 0:
                raise ClientTimeout(first, f"no action within {self._timeout_s[first]:g} s", tick=tick)
            try:
                event = self._inbox.get(timeout=remaining)
            except queue.Empty:
                continue
            if isinstance(event, _Gone):
                self._gone.add(event.name)
            if isinstance(event, _Act) and event.tick == tick:
                got[event.name] = event.actions
        return [ClientAction(n, tick, a) for n in self._specs for a in got[n]]

    # -- Zenoh callbacks ------------------------------------------------------------------------

    def _on_query(self, query: zenoh.Query) -> None:
        _, name, verb = str(query.key_expr).rsplit("/", 2)
        try:
            data = json.loads(query.payload.to_bytes()) if query.payload else {}
            if name not in self._specs:
                raise ActionRejected(f"no client named {name!r} in this episode (expected: {', '.join(self._specs)})")
            if verb == "hello":
                reply = self._hello(name, data)
            elif verb == "act":
                reply = self._act(name, data)
            else:
                raise ActionRejected(f"unknown request {verb!r}")
            query.reply(query.key_expr, json.dumps(reply).encode())
        except ActionRejected as exc:
            query.reply_err(json.dumps({"error": str(exc)}).encode())
        except (ValueError, TypeError, KeyError) as exc:
            query.reply_err(json.dumps({"error": f"malformed {verb} request: {exc}"}).encode())

    def _hello(self, name: str, data: dict[str, Any]) -> dict[str, Any]:
        if data.get("protocol") != wire.CLIENT_PROTOCOL_VERSION:
            raise ActionRejected(f"client protocol {data.get('protocol')} not supported (the conductor speaks "
                                 f"{wire.CLIENT_PROTOCOL_VERSION})")
        topics = data.get("topics")
        if not isinstance(topics, list) or not all(isinstance(t, str) for t in topics):
            raise ActionRejected("topics must be a list of topic names or patterns")
        with self._lock:
            if name in self._topics:
                raise ActionRejected(f"client {name!r} is already connected")
            self._topics[name] = tuple(topics)
        self._inbox.put(_Hello(name))
        log.info("client %s connected, reading %s", name, ", ".join(topics) or "nothing")
        return {**self._episode, "timeout_s": self._timeout_s[name]}

    def _act(self, name: str, data: dict[str, Any]) -> dict[str, Any]:
        tick = data["tick"]
        with self._lock:
            if self._awaiting is None or tick != self._awaiting:
                waiting = "no tick" if self._awaiting is None else f"tick {self._awaiting}"
                raise ActionRejected(f"actions for tick {tick}, but the conductor waits for {waiting}")
            if name in self._answered:
                raise ActionRejected(f"client {name!r} already answered tick {tick}")
            self._answered.add(name)
            context = self._context
        assert context is not None
        try:
            actions = as_dicts(check_actions(data.get("actions"), context))
        except ActionRejected as exc:
            log.warning("client %s at tick %d: actions refused: %s", name, tick, exc)
            self._inbox.put(_Act(name, tick, []))
            raise
        self._inbox.put(_Act(name, tick, actions))
        return {"accepted": len(actions)}

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        if sample.kind == zenoh.SampleKind.DELETE and name in self._specs:
            self._inbox.put(_Gone(name))
