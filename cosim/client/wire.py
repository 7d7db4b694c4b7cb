"""Keys and the observation framing between the conductor and closed-loop clients.

Keys, under the episode's prefix (docs/architecture.md, "Closed-loop clients")::

    <prefix>/alive/client/<name>     liveliness token of a client
    <prefix>/clients/<name>/hello    query to the conductor: subscribe (topics), get the episode's facts
    <prefix>/clients/<name>/act      query to the conductor: the actions for one tick; error reply if refused
    <prefix>/clients/<name>/obs      put by the conductor: one tick's messages

An observation is ``u32 little-endian header length``, a JSON header, then per message its schema
bytes (only the first time a topic is sent) and its data: the same bytes the episode file holds.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from typing import Any

from google.protobuf.message import Message as ProtoMessage

CLIENT_PROTOCOL_VERSION = 1
#: What a client reads when it names no topics.
DEFAULT_TOPICS = ("/labels/objects",)


def alive_key(prefix: str, name: str) -> str:
    return f"{prefix}/alive/client/{name}"


def client_key(prefix: str, name: str, verb: str) -> str:
    return f"{prefix}/clients/{name}/{verb}"


@dataclass(frozen=True)
class Encoded:
    """One message as the episode file holds it."""

    schema_name: str
    encoding: str  # protobuf | json
    data: bytes


def encode_message(message: Any) -> Encoded:
    """The bytes :class:`cosim.io.writer.EpisodeWriter` writes for a (topic, message) pair's message:
    a protobuf message, or a ``(schema_name, json_schema, payload)`` triple."""
    if isinstance(message, ProtoMessage):
        return Encoded(message.DESCRIPTOR.full_name, "protobuf", message.SerializeToString(deterministic=True))
    schema_name, _, payload = message
    return Encoded(schema_name, "json", json.dumps(payload, separators=(",", ":")).encode())


def schema_bytes(message: Any) -> bytes:
    """The schema record's data the writer stores for this message's channel."""
    if isinstance(message, ProtoMessage):
        from cosim.io.writer import proto_file_descriptor_set

        return proto_file_descriptor_set(type(message))
    return json.dumps(message[1], sort_keys=True).encode()


def pack_observation(header: dict[str, Any], parts: list[tuple[str, Encoded, bytes]]) -> bytes:
    """Frame one observation; ``parts`` are (topic, encoded message, schema bytes or b"")."""
    header = {**header, "messages": [
        {"topic": t, "schema": e.schema_name, "encoding": e.encoding, "schema_size": len(s), "size": len(e.data)}
        for t, e, s in parts
    ]}
    head = json.dumps(header, separators=(",", ":")).encode()
    chunks = [struct.pack("<I", len(head)), head]
    for _, e, s in parts:
        chunks += [s, e.data]
    return b"".join(chunks)


def unpack_observation(payload: bytes) -> tuple[dict[str, Any], list[tuple[dict[str, Any], bytes, bytes]]]:
    """The header and per message (entry, schema bytes, data) of a framed observation."""
    (n,) = struct.unpack_from("<I", payload, 0)
    header = json.loads(payload[4 : 4 + n])
    pos = 4 + n
    out = []
    for m in header["messages"]:
        schema = payload[pos : pos + m["schema_size"]]
        pos += m["schema_size"]
        out.append((m, schema, payload[pos : pos + m["size"]]))
        pos += m["size"]
    return header, out
