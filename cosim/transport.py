"""Zenoh configuration for cosim's topology (docs/conventions.md section 6).

The conductor runs a Zenoh *router* listening on a loopback TCP endpoint; workers are *clients*
connected to it. Multicast scouting is off everywhere, so nothing leaves the machine unless the user
asks for a non-loopback endpoint, and two episodes on one host never meet (each also has its own
key prefix).
"""

from __future__ import annotations

import json
import socket
import uuid

import zenoh

from cosim.errors import InputError


def free_loopback_endpoint() -> str:
    """A TCP endpoint on 127.0.0.1 with a port that is free right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def check_endpoint(endpoint: str) -> str:
    """Validate a Zenoh endpoint given on the command line (``tcp/HOST:PORT``)."""
    proto, sep, rest = endpoint.partition("/")
    host, colon, port = rest.rpartition(":")
    if not sep or proto not in ("tcp", "udp", "quic", "tls") or not colon or not host or not port.isdigit():
        raise InputError(f"invalid endpoint {endpoint!r}: expected PROTO/HOST:PORT, for example tcp/127.0.0.1:7447")
    return endpoint


#: Zenoh session lease [ms]: a peer that sends nothing (not even keep-alives, four per lease) for this long is
#: disconnected, so a stopped or frozen worker loses its liveliness token within about this time (Zenoh's
#: default is 10 000 ms, which made a hung worker take longer to notice than the tick timeout).
LEASE_MS = 3000


def _config(mode: str, *, listen: list[str] | None = None, connect: list[str] | None = None) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("transport/link/tx/lease", str(LEASE_MS))
    conf.insert_json5("scouting/multicast/enabled", "false")
    # No shared-memory transport: its default 16 MB pool per session is mapped by both ends of each link
    # (about 80 MB of the episode's process tree), for messages that are small (the snapshots) or go through
    # TCP on loopback anyway.
    conf.insert_json5("transport/shared_memory/enabled", "false")
    if mode != "client":
        conf.insert_json5("scouting/gossip/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps(listen or []))
    conf.insert_json5("connect/endpoints", json.dumps(connect or []))
    if mode == "client":
        # Keep retrying the router for a while: a worker may be started before the conductor.
        conf.insert_json5("connect/timeout_ms", "-1")
    return conf


def open_router(listen: str) -> zenoh.Session:
    """The conductor's session: a router listening on ``listen``."""
    try:
        return zenoh.open(_config("router", listen=[listen]))
    except zenoh.ZError as exc:
        raise InputError(f"cannot listen on {listen}: {exc}") from None


def open_client(connect: str) -> zenoh.Session:
    """A worker's session: a client of the conductor's router at ``connect``."""
    return zenoh.open(_config("client", connect=[connect]))


def new_prefix() -> str:
    """A fresh per-episode key prefix."""
    return f"cosim/ep/{uuid.uuid4().hex[:12]}"


#: Prefix used when workers are started by hand (``cosim worker ... --connect``) and no --prefix is given.
EXTERNAL_PREFIX = "cosim/external"
