"""``cosim replay``: re-publish an episode over Zenoh with its original timing, scaled.

Each message goes to ``<prefix>/<topic without its leading slash>`` (``cosim/replay/vehicle_0/lidar``)
with the raw message bytes as payload. The Zenoh encoding names the message encoding and the schema
(``application/protobuf;foxglove.PointCloud``, ``application/json;cosim.ObjectArray``); the
attachment is a small JSON object with ``topic``, ``log_time_ns``, ``sequence``, ``schema`` and
``encoding``. The schemas themselves (FileDescriptorSet / JSON Schema bytes) are answered by a
queryable at ``<prefix>_schema/<topic without slash>`` (outside ``<prefix>/**``, so a subscriber to
the whole prefix receives messages only).

Payloads travel as the file stores them: where the episode's chunks are compressed (zstd, the default,
or lz4), every message that is not already compressed data (JPEG/PNG ``foxglove.CompressedImage``) and
shrinks is sent compressed the same way, and its attachment names the codec (``"compression": "zstd"``;
absent: the payload is the message as it is). Raw semantic, instance and BEV arrays, which the file
holds zstd-compressed, so cost about as many bytes on the wire as on disk instead of 20 to 30 times as
many. ``compress=False`` (``cosim replay --raw``) sends every payload as it is decoded.

Zenoh follows cosim's conventions (cosim/transport.py): peer mode, multicast scouting off,
endpoints given explicitly; by default the replayer listens on ``tcp/127.0.0.1:7447``. A subscriber
therefore finds it only by connecting to that endpoint (``connect/endpoints``); a default Zenoh
configuration, which relies on multicast scouting, hears nothing. ``on_ready`` receives the endpoints
and the Foxglove URL before the first message, so the command line can print them.

Waiting: with a Foxglove server, the replay sends nothing until the first viewer has connected and
subscribed to a topic (``wait_viewer``, on by default: a short episode would be over before a person has
pasted the URL into Foxglove; the server only sends a viewer the channels it subscribed to), then waits
``VIEWER_SETTLE_S`` for the rest of its subscriptions; it waits as long as it takes (``stop`` ends it).
Without one, it waits up to ``wait_subscribers_s`` for a Zenoh subscriber.
Messages are sent reliably with blocking congestion control, in log-time order.

Stopping: ``stop`` is checked between messages and at least every ``STOP_POLL_S`` while waiting, and
the Foxglove server and the Zenoh session are closed with a time limit each (``CLOSE_TIMEOUT_S``), so
an interrupted replay ends promptly even when a WebSocket client has just gone away. A viewer that
goes away without a clean WebSocket close is one warning line (:class:`ViewerGoneFilter`), not one
foxglove-sdk error per message it could not be sent.
"""

from __future__ import annotations

import json
import logging
import re
import socket
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cosim.errors import CosimError, InputError
from cosim.io.reader import Episode, open_episode

log = logging.getLogger(__name__)

DEFAULT_LISTEN = "tcp/127.0.0.1:7447"
DEFAULT_PREFIX = "cosim/replay"
DEFAULT_FOXGLOVE_HOST = "127.0.0.1"
LINGER_S = 0.5  # [s] kept open after the last message so queued data leaves the process
STOP_POLL_S = 0.1  # [s] longest wait between two looks at the stop event
CLOSE_TIMEOUT_S = 3.0  # [s] longest wait for the Foxglove server or the Zenoh session to close
VIEWER_SETTLE_S = 0.5  # [s] after a viewer's first subscription, for the others it sends at the same time
_WILDCARD_HOSTS = ("0.0.0.0", "::", "[::]")


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
    foxglove_host: str = DEFAULT_FOXGLOVE_HOST
    wait_viewer: bool = True  # with a Foxglove server: send nothing before a viewer subscribes (module docstring)
    compress: bool = True  # Zenoh payloads compressed as the file's chunks are (module docstring)


@dataclass(frozen=True)
class ReplayEndpoints:
    """Where to find a running replay (given to ``on_ready`` before the first message)."""

    zenoh_listen: list[str]  # the replayer listens here: subscribers put these in connect/endpoints
    zenoh_connect: list[str]  # the replayer connected to these (a router or a listening subscriber)
    prefix: str
    foxglove_url: str | None  # ws://HOST:PORT for Foxglove's "Foxglove WebSocket" connection
    waits_for_viewer: bool = False  # nothing is sent before a Foxglove viewer subscribes

    def subscriber_endpoints(self) -> list[str]:
        """Endpoints a subscriber on this host connects to (wildcard hosts replaced by this host's name)."""
        return [reachable_endpoint(e) for e in self.zenoh_listen]


def _reachable_host(host: str) -> str:
    return socket.gethostname() if host in _WILDCARD_HOSTS else host


def reachable_endpoint(endpoint: str) -> str:
    """``tcp/0.0.0.0:7447`` -> ``tcp/<this host's name>:7447``; other endpoints unchanged."""
    proto, _, rest = endpoint.partition("/")
    host, _, port = rest.rpartition(":")
    return f"{proto}/{_reachable_host(host)}:{port}" if host in _WILDCARD_HOSTS else endpoint


def foxglove_url(host: str, port: int) -> str:
    """The URL Foxglove connects to: ``ws://127.0.0.1:8765`` (a wildcard host becomes this host's name)."""
    shown = _reachable_host(host)
    return f"ws://[{shown}]:{port}" if ":" in shown else f"ws://{shown}:{port}"


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


#: Payloads smaller than this are sent as they are (compression would not pay for its attachment entry).
MIN_COMPRESS_BYTES = 256
#: Schemas whose data is already compressed (JPEG, PNG, cosim-depth): sent as they are.
PRECOMPRESSED_SCHEMAS = frozenset({"foxglove.CompressedImage"})


class PayloadCodec:
    """Compresses replay payloads with the episode file's chunk compression (``zstd``, ``lz4``; ``""``: none)."""

    def __init__(self, compression: str):
        self.name = compression if compression in ("zstd", "lz4") else ""
        self._compress: Callable[[bytes], bytes] | None = None
        if self.name == "zstd":
            import zstandard

            self._compress = zstandard.ZstdCompressor(level=1).compress  # smaller and faster than 3 here
        elif self.name == "lz4":
            import lz4.frame

            self._compress = lz4.frame.compress

    def encode(self, data: bytes, schema_name: str) -> tuple[bytes, str]:
        """(payload, codec name or ``""``): ``data`` compressed where that makes it smaller."""
        if self._compress is None or len(data) < MIN_COMPRESS_BYTES or schema_name in PRECOMPRESSED_SCHEMAS:
            return data, ""
        packed = self._compress(data)
        return (packed, self.name) if len(packed) < 0.9 * len(data) else (data, "")


def decode_payload(payload: bytes, attachment: dict[str, Any]) -> bytes:
    """A replayed message's bytes as the episode stores them, from a Zenoh sample's payload and its decoded
    JSON attachment (for subscribers: undoes the ``compression`` the replay applied)."""
    codec = attachment.get("compression", "")
    if codec == "zstd":
        import zstandard

        return zstandard.ZstdDecompressor().decompress(payload)
    if codec == "lz4":
        import lz4.frame

        return lz4.frame.decompress(payload)
    if codec:
        raise ValueError(f"unknown replay payload compression {codec!r}")
    return bytes(payload)


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

    def __init__(self, host: str, port: int, ep: Episode, topics: list[str]):
        try:
            import foxglove
            from foxglove import Channel, Context, Schema
        except ImportError:
            raise InputError("--foxglove needs the foxglove-sdk package: pip install foxglove-sdk") from None
        context = self._context = Context()  # this replay's channels only; held for the server's lifetime
        self.subscribed = threading.Event()  # set at a viewer's first subscription
        try:
            self._server = foxglove.start_server(port=port, host=host, context=context, name="cosim replay",
                                                 server_listener=_subscription_listener(self.subscribed))
        except Exception as exc:  # the SDK raises its own error types
            raise InputError(f"cannot serve Foxglove on {host}:{port}: {exc}") from None
        self.url = foxglove_url(host, self._server.port)
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
        log.info("Foxglove WebSocket server on %s", self.url)

    def send(self, topic: str, data: bytes, log_time_ns: int) -> None:
        self._channels[topic].log(data, log_time=log_time_ns)

    def wait_for_viewer(self, stop: threading.Event) -> bool:
        """Until a viewer subscribes to a channel (then ``VIEWER_SETTLE_S`` more) or ``stop``; True: a viewer."""
        log.info("waiting for a Foxglove viewer on %s", self.url)
        while not self.subscribed.is_set():
            if stop.wait(STOP_POLL_S):
                return False
        log.info("a Foxglove viewer subscribed: replaying")
        return not _wait(stop, VIEWER_SETTLE_S)

    def close(self) -> None:
        def stop_server() -> None:
            for channel in self._channels.values():
                channel.close()
            self._server.stop()

        _close_within(stop_server, "the Foxglove server")


def _subscription_listener(subscribed: threading.Event) -> Any:
    """A foxglove-sdk server listener that sets ``subscribed`` when a client subscribes to a channel (the SDK's
    ``ServerListener`` answers every other callback with nothing)."""
    from foxglove.websocket import ServerListener

    class SubscriptionListener(ServerListener):
        def on_subscribe(self, client: Any, channel: Any) -> None:
            subscribed.set()

    return SubscriptionListener()


_CLIENT = re.compile(r"client (\S+?):? ")
_GONE = ("broken pipe", "connection reset", "without closing handshake", "os error 32", "os error 104",
         "connection closed", "not connected")


class ViewerGoneFilter(logging.Filter):
    """Turns the foxglove-sdk's errors about a viewer that went away without a clean WebSocket close (one per
    message it then fails to send: "Broken pipe", "Connection reset") into one warning per viewer, and
    drops repeats of any other foxglove-sdk message within ``REPEAT_S`` (with a count when it comes back)."""

    REPEAT_S = 10.0

    def __init__(self) -> None:
        super().__init__()
        self._gone: set[str] = set()
        self._last: dict[str, tuple[float, int]] = {}  # message -> (when shown, dropped since)

    def filter(self, record: logging.LogRecord) -> bool:
        if not record.name.startswith("foxglove") or record.levelno < logging.WARNING:
            return True
        decided = getattr(record, "_cosim_shown", None)  # one decision per record, whatever the handlers
        if decided is None:
            decided = record._cosim_shown = self._decide(record)
        return decided

    def _decide(self, record: logging.LogRecord) -> bool:
        text = record.getMessage()
        if any(g in text.lower() for g in _GONE):
            m = _CLIENT.search(text)
            who = m.group(1) if m else "?"
            if who in self._gone:
                return False
            self._gone.add(who)
            record.msg, record.args = f"Foxglove viewer {who} went away without closing the connection", None
            record.levelno, record.levelname = logging.WARNING, "WARNING"
            return True
        now = time.monotonic()
        shown, dropped = self._last.get(text, (-1e9, 0))
        if now - shown < self.REPEAT_S:
            self._last[text] = (shown, dropped + 1)
            return False
        self._last[text] = (now, 0)
        if dropped:
            record.msg, record.args = f"{text} (and {dropped} more like it)", None
        return True


@contextmanager
def _viewer_gone_filtered() -> Iterator[None]:
    """:class:`ViewerGoneFilter` on the root logger's handlers (where the foxglove-sdk's records end up:
    a filter on a parent logger does not see its children's records) while the replay runs."""
    flt = ViewerGoneFilter()
    handlers = list(logging.getLogger().handlers)
    for h in handlers:
        h.addFilter(flt)
    try:
        yield
    finally:
        for h in handlers:
            h.removeFilter(flt)


def _close_within(close: Callable[[], None], what: str, timeout_s: float = CLOSE_TIMEOUT_S) -> None:
    """Run ``close`` in a helper thread and wait at most ``timeout_s``: shutting down never hangs the caller."""
    errors: list[BaseException] = []

    def run() -> None:
        try:
            close()
        except Exception as exc:  # reported below; closing must not mask the replay's own outcome
            errors.append(exc)

    closer = threading.Thread(target=run, name=f"close {what}", daemon=True)
    closer.start()
    closer.join(timeout_s)
    if closer.is_alive():
        log.warning("%s did not close within %.0f s; leaving it behind", what, timeout_s)
    elif errors:
        log.warning("closing %s failed: %s", what, errors[0])


def replay_episode(
    path: str | Path,
    opts: ReplayOptions,
    stop: threading.Event | None = None,
    on_ready: Callable[[ReplayEndpoints], None] | None = None,
) -> ReplayStats:
    """Publish the episode's messages (see the module docstring); returns what was sent.

    ``stop`` ends the replay early (Ctrl-C does too); ``on_ready`` gets the endpoints once the Zenoh
    session and the Foxglove server are up. Raises InputError for bad topics or endpoints.
    """
    import zenoh

    stop = stop or threading.Event()
    with open_episode(path) as ep, _viewer_gone_filtered():
        try:
            topics = ep.select(opts.topics)
        except KeyError as exc:
            raise InputError(str(exc.args[0])) from None
        listen = opts.listen or ([] if opts.connect else [DEFAULT_LISTEN])
        session = open_session(opts.connect, listen)
        try:
            fox = (
                _Foxglove(opts.foxglove_host, opts.foxglove_port, ep, topics)
                if opts.foxglove_port is not None
                else None
            )
        except BaseException:
            _close_within(session.close, "the Zenoh session")
            raise
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
            viewer = fox is not None and opts.wait_viewer
            if on_ready is not None:
                on_ready(ReplayEndpoints(listen, list(opts.connect), opts.prefix, fox.url if fox else None, viewer))
            if viewer:
                fox.wait_for_viewer(stop)
            else:
                _wait_for_subscriber(list(publishers.values()), opts.wait_subscribers_s, stop)
            codec = PayloadCodec(ep.chunk_compression if opts.compress else "")
            sent, loops, started = 0, 0, time.perf_counter()
            while not stop.is_set():
                sent += _one_pass(ep, topics, publishers, opts.rate, stop, fox, codec)
                loops += 1
                if not opts.loop:
                    break
            _wait(stop, LINGER_S)
            wall = time.perf_counter() - started
            queryable.undeclare()
            for p in publishers.values():
                p.undeclare()
        finally:
            if fox is not None:
                fox.close()
            _close_within(session.close, "the Zenoh session")
    return ReplayStats(sent, loops, wall)


def _wait(stop: threading.Event, seconds: float) -> bool:
    """Wait ``seconds`` or until ``stop`` is set (True then), looking at ``stop`` every STOP_POLL_S."""
    deadline = time.perf_counter() + seconds
    while not stop.is_set():
        left = deadline - time.perf_counter()
        if left <= 0:
            return False
        stop.wait(min(left, STOP_POLL_S))
    return True


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
        _wait(stop, 0.02)
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
    codec: PayloadCodec | None = None,
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
        if delay > 0 and _wait(stop, delay):
            break
        payload, compression = codec.encode(m.data, m.schema_name) if codec is not None else (m.data, "")
        meta = {
            "topic": m.topic,
            "log_time_ns": m.log_time_ns,
            "sequence": m.sequence,
            "schema": m.schema_name,
            "encoding": m.message_encoding,
        }
        if compression:
            meta["compression"] = compression
        attachment = json.dumps(meta, separators=(",", ":")).encode()
        try:
            publishers[m.topic].put(payload, attachment=attachment)
        except Exception as exc:  # zenoh raises its own error types
            raise CosimError(f"replay: publishing {m.topic} at t={m.log_time_ns} ns failed: {exc}") from None
        if fox is not None:
            fox.send(m.topic, m.data, m.log_time_ns)
        sent += 1
    return sent
