"""``cosim replay``: re-publish an episode over Zenoh with its original timing, scaled.

Each message goes to ``<prefix>/<topic without its leading slash>`` (``cosim/replay/vehicle_0/lidar``)
with the raw message bytes as payload. The Zenoh encoding names the message encoding and the schema
(``application/protobuf;foxglove.PointCloud``, ``application/json;cosim.ObjectArray``); the
attachment is a small JSON object with ``topic``, ``log_time_ns``, ``sequence``, ``schema`` and
``encoding``. The schemas themselves (FileDescriptorSet / JSON Schema bytes) are answered by a
queryable at ``<prefix>_schema/<topic without slash>`` (outside ``<prefix>/**``, so a subscriber to
the whole prefix receives messages only).

Zenoh follows cosim's conventions (cosim/transport.py): peer mode, multicast scouting off,
endpoints given explicitly; by default the replayer listens on ``tcp/127.0.0.1:7447``.
Messages are sent reliably with blocking congestion control, in log-time order.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cosim.errors import CosimError, InputError
from cosim.io.reader import Episode, open_episode

log = logging.getLogger(__name__)

DEFAULT_LISTEN = "tcp/127.0.0.1:7447"
DEFAULT_PREFIX = "cosim/replay"
LINGER_S = 0.5  # [s] kept open after the last message so queued data leaves the process


@dataclass(frozen=True)
class ReplayOptions:
    rate: float = 1.0  # speed factor: 10 = ten times faster than recorded
    loop: bool = False
    topics: list[str] | None = None  # names or shell patterns; None = all
    connect: list[str] = field(default_factory=list)
    listen: list[str] = field(default_factory=list)
    prefix: str = DEFAULT_PREFIX
    wait_subscribers_s: float = 5.0  # wait up to this long for a matching subscriber (0 = do not wait)
    foxglove_port: int | None = None


@dataclass(frozen=True)
class ReplayStats:
    messages: int
    loops: int
    wall_s: float


def topic_key(prefix: str, topic: str) -> str:
    """Zenoh key of an episode topic: ``cosim/replay`` + ``/vehicle_0/lidar`` -> ``cosim/replay/vehicle_0/lidar``."""
    return f"{prefix.rstrip('/')}/{topic.lstrip('/')}"


def schema_key(prefix: str, topic: str) -> str:
    """Key of the queryable that answers a topic's schema bytes."""
    return f"{prefix.rstrip('/')}_schema/{topic.lstrip('/')}"


def zenoh_encoding(message_encoding: str, schema_name: str) -> str:
    base = {"protobuf": "application/protobuf", "json": "application/json"}.get(
        message_encoding, "application/octet-stream"
    )
    return f"{base};{schema_name}" if schema_name else base


def open_session(connect: list[str], listen: list[str]) -> Any:
    """A Zenoh peer session with multicast scouting off, linked only to the given endpoints."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("peer"))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    conf.insert_json5("connect/endpoints", json.dumps(connect))
    try:
        return zenoh.open(conf)
    except zenoh.ZError as exc:
        raise InputError(f"cannot open Zenoh (connect {connect}, listen {listen}): {exc}") from None


class _Foxglove:
    """Optional live view: the foxglove-sdk WebSocket server, one channel per topic."""

    def __init__(self, port: int, ep: Episode, topics: list[str]):
        try:
            import foxglove
            from foxglove import Channel, Context, Schema
        except ImportError:
            raise InputError("--foxglove needs the foxglove-sdk package: pip install foxglove-sdk") from None
        context = self._context = Context()  # this replay's channels only; held for the server's lifetime
        try:
            self._server = foxglove.start_server(port=port, host="127.0.0.1", context=context, name="cosim replay")
        except Exception as exc:  # the SDK raises its own error types
            raise InputError(f"cannot serve Foxglove on 127.0.0.1:{port}: {exc}") from None
        self._channels: dict[str, Any] = {}
        schemas = ep.schemas()
        for t in topics:
            info = ep.topics[t]
            name, encoding, data = schemas[t]
            self._channels[t] = Channel(
                t,
                message_encoding=info.message_encoding,
                schema=Schema(name=name, encoding=encoding, data=data),
                context=context,
            )
        log.info("Foxglove WebSocket server on ws://127.0.0.1:%d", port)

    def send(self, topic: str, data: bytes, log_time_ns: int) -> None:
        self._channels[topic].log(data, log_time=log_time_ns)

    def close(self) -> None:
        for channel in self._channels.values():
            channel.close()
        self._server.stop()


def replay_episode(path: str | Path, opts: ReplayOptions, stop: threading.Event | None = None) -> ReplayStats:
    """Publish the episode's messages (see the module docstring); returns what was sent.

    ``stop`` ends the replay early (Ctrl-C does too). Raises InputError for bad topics or endpoints.
    """
    import zenoh

    stop = stop or threading.Event()
    with open_episode(path) as ep:
        try:
            topics = ep.select(opts.topics)
        except KeyError as exc:
            raise InputError(str(exc.args[0])) from None
        listen = opts.listen or ([] if opts.connect else [DEFAULT_LISTEN])
        session = open_session(opts.connect, listen)
        fox = _Foxglove(opts.foxglove_port, ep, topics) if opts.foxglove_port is not None else None
        try:
            publishers = {
                t: session.declare_publisher(
                    topic_key(opts.prefix, t),
                    encoding=zenoh.Encoding(zenoh_encoding(ep.topics[t].message_encoding, ep.topics[t].schema_name)),
                    congestion_control=zenoh.CongestionControl.BLOCK,
                    reliability=zenoh.Reliability.RELIABLE,
                )
                for t in topics
            }
            schemas = ep.schemas()
            queryable = session.declare_queryable(
                f"{opts.prefix.rstrip('/')}_schema/**", lambda q: _answer_schema(q, opts.prefix, schemas)
            )
            _wait_for_subscriber(list(publishers.values()), opts.wait_subscribers_s, stop)
            sent, loops, started = 0, 0, time.perf_counter()
            while not stop.is_set():
                sent += _one_pass(ep, topics, publishers, opts.rate, stop, fox)
                loops += 1
                if not opts.loop:
                    break
            stop.wait(LINGER_S)
            wall = time.perf_counter() - started
            queryable.undeclare()
            for p in publishers.values():
                p.undeclare()
        finally:
            if fox is not None:
                fox.close()
            session.close()
    return ReplayStats(sent, loops, wall)


def _answer_schema(query: Any, prefix: str, schemas: dict[str, tuple[str, str, bytes]]) -> None:
    base = f"{prefix.rstrip('/')}_schema/"
    topic = "/" + str(query.key_expr)[len(base) :]
    if topic in schemas:
        name, encoding, data = schemas[topic]
        query.reply(query.key_expr, data, encoding=f"{encoding};{name}")


def _wait_for_subscriber(publishers: list[Any], timeout_s: float, stop: threading.Event) -> None:
    if timeout_s <= 0 or not publishers:
        return
    deadline = time.perf_counter() + timeout_s
    while time.perf_counter() < deadline and not stop.is_set():
        if any(p.matching_status.matching for p in publishers):
            return
        stop.wait(0.02)
    log.warning("no subscriber after %.1f s; replaying anyway", timeout_s)


def send_offset_s(log_time_ns: int, first_log_time_ns: int, rate: float) -> float:
    """When a message is due [s after the pass starts]: its recorded offset scaled by ``1 / rate``."""
    return (log_time_ns - first_log_time_ns) / 1e9 / rate


def _one_pass(
    ep: Episode,
    topics: list[str],
    publishers: dict[str, Any],
    rate: float,
    stop: threading.Event,
    fox: _Foxglove | None,
) -> int:
    first: int | None = None
    started = time.perf_counter()
    sent = 0
    for m in ep.messages(topics):
        if stop.is_set():
            break
        if first is None:
            first = m.log_time_ns
        due = started + send_offset_s(m.log_time_ns, first, rate)
        delay = due - time.perf_counter()
        if delay > 0 and stop.wait(delay):
            break
        attachment = json.dumps(
            {
                "topic": m.topic,
                "log_time_ns": m.log_time_ns,
                "sequence": m.sequence,
                "schema": m.schema_name,
                "encoding": m.message_encoding,
            },
            separators=(",", ":"),
        ).encode()
        try:
            publishers[m.topic].put(m.data, attachment=attachment)
        except Exception as exc:  # zenoh raises its own error types
            raise CosimError(f"replay: publishing {m.topic} at t={m.log_time_ns} ns failed: {exc}") from None
        if fox is not None:
            fox.send(m.topic, m.data, m.log_time_ns)
        sent += 1
    return sent
