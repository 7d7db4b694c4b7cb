"""The episode writer: one MCAP file per episode, complete or absent.

The file is written to a hidden temporary name beside the destination and renamed only by
:meth:`EpisodeWriter.finish`; any failure (or leaving the ``with`` block on an exception) deletes
the temporary file, so a crash never leaves a file that looks complete.

Times: every record's ``log_time`` and ``publish_time`` is simulation time in integer ns since the
episode start, never the wall clock, so the same scenario and seed give the same bytes.

Chunks: ``mcap``'s writer compresses each chunk with ``zstandard.compress`` (level 3) and checks it with
``zlib.crc32``, both looked up in its module. This module hands it :class:`_ChunkCodec` in their place:
zstd at :data:`CHUNK_ZSTD_LEVEL` (1) and libdeflate's CRC-32 (``imagecodecs.deflate_crc32``: the same
polynomial and values as zlib's, 3.9x its speed here). On cosim's data level 1 is both faster and smaller
than 3: rewriting the messages of an 8 s LiDAR-only episode took 1.49 instead of 2.46 CPU-s and 151.5
instead of 154.3 MB, a full-rig second 1.4-1.8 instead of 2.1-2.4 CPU-s and 88.6 instead of 89.0 MB (the
point clouds compress better at 1, the label images and BEV grids alike). Files are standard MCAP either
way; any reader checks the CRCs with its own CRC-32.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import re
import threading
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import imagecodecs
import mcap.writer
import zstandard
from google.protobuf import descriptor_pb2
from google.protobuf.message import Message as ProtoMessage
from mcap.writer import CompressionType, Writer

import cosim
from cosim.errors import CosimError

log = logging.getLogger(__name__)

COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
CHUNK_SIZE = 4 * 1024 * 1024  # [bytes]
#: zstd level of the episode's chunks (module docstring)
CHUNK_ZSTD_LEVEL = 1


class _ChunkCodec:
    """What ``mcap.writer`` calls as ``zstandard.compress`` and ``zlib.crc32`` (module docstring). One zstd
    context per thread (a context is not safe to share); single-threaded zstd gives the same bytes for the
    same input and level on every run."""

    _local = threading.local()

    @classmethod
    def compress(cls, data: bytes) -> bytes:
        ctx = getattr(cls._local, "zstd", None)
        if ctx is None:
            ctx = cls._local.zstd = zstandard.ZstdCompressor(level=CHUNK_ZSTD_LEVEL)
        return ctx.compress(data)

    crc32 = staticmethod(imagecodecs.deflate_crc32)


def chunk_compress(data: bytes) -> bytes:
    """``data`` zstd-compressed as the writer compresses an episode's chunks."""
    return _ChunkCodec.compress(data)


mcap.writer.zstandard = _ChunkCodec  # type: ignore[attr-defined]
mcap.writer.zlib = _ChunkCodec  # type: ignore[attr-defined]


def temporary_path(final: Path, pid: int | None = None) -> Path:
    """Where an episode is written before it is complete: ``.<name>.<pid>.partial`` beside ``final``, hidden,
    named after the writing process (default: this one) and locked by it while it writes (``flock``), so that
    a later run into the folder tells a file left by a killed run (:func:`remove_stale_partials`) from one
    being written."""
    return final.with_name(f".{final.name}.{os.getpid() if pid is None else pid}.partial")


#: Names of unfinished episodes: ``.<name>.mcap.<pid>.partial``, and ``.<name>.mcap.partial`` as older cosim named them.
_PARTIAL_NAME = re.compile(r"\..+\.mcap(\.\d+)?\.partial")


def remove_stale_partials(folder: Path) -> list[Path]:
    """Delete the unfinished episodes in ``folder`` that no live writer holds (their run was killed) and log
    each at WARNING with its size; returns them. Files another running episode is writing are kept."""
    removed: list[Path] = []
    try:
        candidates = sorted(p for p in Path(folder).glob(".*.partial") if _PARTIAL_NAME.fullmatch(p.name))
    except OSError:
        return removed
    for path in candidates:
        try:
            fd = os.open(path, os.O_RDONLY)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:  # a running episode holds it
            os.close(fd)
            continue
        try:
            size = os.fstat(fd).st_size
            path.unlink()
        except OSError:
            continue
        finally:
            os.close(fd)
        log.warning("removed %s (%.1f MiB), an unfinished episode left by a run that was killed", path,
                    size / 2**20)
        removed.append(path)
    return removed


def proto_file_descriptor_set(message_type: type[ProtoMessage]) -> bytes:
    """Serialized FileDescriptorSet of a message type and everything it imports (dependencies first)."""
    fds = descriptor_pb2.FileDescriptorSet()
    seen: set[str] = set()

    def add(fd: Any) -> None:
        if fd.name in seen:
            return
        seen.add(fd.name)
        for dep in fd.dependencies:
            add(dep)
        proto = descriptor_pb2.FileDescriptorProto()
        fd.CopyToProto(proto)
        fds.file.append(proto)

    add(message_type.DESCRIPTOR.file)
    return fds.SerializeToString(deterministic=True)


@dataclass(frozen=True)
class Serialized:
    """A protobuf message already serialized: ``data`` holds exactly the bytes that
    ``message_type(...).SerializeToString(deterministic=True)`` gives, in any contiguous buffer (bytes,
    or a uint8 array that an image was written into in place, sparing the copies of building and
    serialising a message around a large payload). ``message_type`` names the channel's schema."""

    message_type: type[ProtoMessage]
    data: Any

    def message(self) -> ProtoMessage:
        """The message itself (parsed back; for readers of messages in memory, not for writing)."""
        return self.message_type.FromString(bytes(self.data))


class EpisodeWriter:
    """Writes protobuf (Foxglove) and JSON (project schema) messages into one MCAP episode."""

    def __init__(self, final_path: Path, *, compression: str = "zstd"):
        self.final_path = Path(final_path)
        self.tmp_path = temporary_path(self.final_path)
        self.final_path.parent.mkdir(parents=True, exist_ok=True)
        self._stream: BinaryIO = open(self.tmp_path, "wb")  # noqa: SIM115 (closed in finish/abort)
        fcntl.flock(self._stream.fileno(), fcntl.LOCK_EX)  # held until closed: marks the file as being written
        self._writer = Writer(self._stream, chunk_size=CHUNK_SIZE, compression=COMPRESSION[compression])
        self._writer.start(profile="", library=f"cosim {cosim.__version__}")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._sequence: dict[int, int] = {}
        self._done = False
        self.message_count = 0

    # -- channels -------------------------------------------------------------------------------

    def _channel(self, topic: str, schema_name: str, schema_encoding: str, schema_data: bytes,
                 message_encoding: str) -> int:
        channel_id = self._channels.get(topic)
        if channel_id is not None:
            return channel_id
        schema_id = self._schemas.get(schema_name)
        if schema_id is None:
            schema_id = self._writer.register_schema(schema_name, schema_encoding, schema_data)
            self._schemas[schema_name] = schema_id
        channel_id = self._writer.register_channel(topic, message_encoding, schema_id)
        self._channels[topic] = channel_id
        self._sequence[channel_id] = 0
        return channel_id

    def _add(self, channel_id: int, data: bytes, t_ns: int) -> None:
        seq = self._sequence[channel_id]
        self._sequence[channel_id] = seq + 1
        self._writer.add_message(channel_id, log_time=t_ns, data=data, publish_time=t_ns, sequence=seq)
        self.message_count += 1

    # -- messages -------------------------------------------------------------------------------

    def write_proto(self, topic: str, message: ProtoMessage, t_ns: int) -> None:
        """Write a protobuf message (e.g. a ``foxglove.FrameTransforms``) at simulation time ``t_ns``."""
        self._add(self._proto_channel(topic, type(message)), message.SerializeToString(deterministic=True), t_ns)

    def write_serialized(self, topic: str, record: Serialized, t_ns: int) -> None:
        """Write a message serialized beforehand (see :class:`Serialized`) at simulation time ``t_ns``."""
        self._add(self._proto_channel(topic, record.message_type), record.data, t_ns)

    def _proto_channel(self, topic: str, message_type: type[ProtoMessage]) -> int:
        """The channel id of ``topic``, registered with ``message_type``'s schema on first use."""
        channel_id = self._channels.get(topic)
        if channel_id is None:
            channel_id = self._channel(topic, message_type.DESCRIPTOR.full_name, "protobuf",
                                       proto_file_descriptor_set(message_type), "protobuf")
        return channel_id

    def write_json(self, topic: str, schema_name: str, schema: dict[str, Any], payload: Any, t_ns: int) -> None:
        """Write a JSON message described by a JSON Schema (project schemas such as ``cosim.ObjectArray``)."""
        channel_id = self._channels.get(topic)
        if channel_id is None:
            channel_id = self._channel(topic, schema_name, "jsonschema",
                                       json.dumps(schema, sort_keys=True).encode(), "json")
        self._add(channel_id, json.dumps(payload, separators=(",", ":")).encode(), t_ns)

    def write(self, topic: str, message: Any, t_ns: int) -> None:
        """Write a protobuf message, a :class:`Serialized` one or a ``(schema_name, json_schema, payload)`` triple."""
        if isinstance(message, ProtoMessage):
            self.write_proto(topic, message, t_ns)
        elif isinstance(message, Serialized):
            self.write_serialized(topic, message, t_ns)
        else:
            schema_name, schema, payload = message
            self.write_json(topic, schema_name, schema, payload, t_ns)

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self._writer.add_metadata(name, data)

    def add_attachment(self, name: str, media_type: str, data: bytes, t_ns: int = 0) -> None:
        self._writer.add_attachment(create_time=t_ns, log_time=t_ns, name=name, media_type=media_type, data=data)

    # -- lifecycle ------------------------------------------------------------------------------

    def finish(self) -> Path:
        """Write the summary, flush to disk and move the file to its final name."""
        self._writer.finish()
        self._stream.flush()
        os.fsync(self._stream.fileno())
        self._stream.close()
        os.replace(self.tmp_path, self.final_path)
        self._done = True
        log.debug("wrote %s (%d messages)", self.final_path, self.message_count)
        return self.final_path

    def abort(self) -> None:
        """Drop the unfinished episode: close and delete the temporary file."""
        if self._done:
            return
        self._done = True
        try:
            self._stream.close()
        finally:
            self.tmp_path.unlink(missing_ok=True)

    def __enter__(self) -> EpisodeWriter:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if not self._done:
            self.abort()


class BackgroundWriter:
    """Writes an episode's ticks from a thread of its own, so that serialising, compressing and
    writing tick k overlap with simulating and rendering tick k+1.

    ``submit(t_ns, build)`` hands over one tick: ``build()`` runs in the writer thread and yields
    the tick's ``(topic, message)`` pairs (it may wait on image encodes). Ticks are written one at
    a time in submission order, so the file has the same bytes as when written inline. ``submit``
    first waits for the previous tick to be written: at most one tick is in the writer, which
    bounds memory to two ticks' sensor data and pushes back when writing is the slower side. An
    error in the writer thread is raised by the next ``submit`` or ``flush`` (as a
    :class:`~cosim.errors.CosimError` naming the file for an ``OSError``) and the episode is then
    aborted like any other failure. Use it as a context manager inside the :class:`EpisodeWriter`'s.
    """

    def __init__(self, writer: EpisodeWriter):
        self.writer = writer
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="cosim-writer")
        self._pending: Future | None = None
        self._abandoned = False

    def _write(self, t_ns: int, build: Callable[[], Iterable[tuple[str, Any]]]) -> None:
        for topic, message in build():
            if self._abandoned:
                return
            self.writer.write(topic, message, t_ns)

    def flush(self) -> None:
        """Wait until every submitted tick is written; raise the writer thread's error, if any."""
        pending, self._pending = self._pending, None
        if pending is None:
            return
        try:
            pending.result()
        except OSError as exc:
            raise CosimError(f"writing {self.writer.final_path} failed: {exc}") from exc

    def submit(self, t_ns: int, build: Callable[[], Iterable[tuple[str, Any]]]) -> None:
        """Write the messages ``build()`` yields at ``t_ns``, after the ticks submitted before."""
        self.flush()
        self._pending = self._pool.submit(self._write, t_ns, build)

    def close(self) -> None:
        """Stop the thread (after the tick it is writing); the file is the :class:`EpisodeWriter`'s to
        finish or abort."""
        self._pool.shutdown(wait=True, cancel_futures=True)
        self._pending = None

    def __enter__(self) -> BackgroundWriter:
        return self

    def abandon(self) -> None:
        """Stop without waiting: the tick being written is dropped at its next message (the episode failed and
        its :class:`EpisodeWriter` is about to delete the file)."""
        self._abandoned = True
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._pending = None

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abandon()
