"""Read an episode: metadata, agents, topics, and an iterator over ticks with lazy decoding.

    with open_episode("out/default_s0.mcap") as ep:
        print(ep.scenario, ep.n_ticks, ep.agents)
        for tick in ep.ticks(topics=["/labels/objects", "/vehicle_0/lidar"]):
            boxes = tick.labels.centers_m          # (N, 3) [m] in map
            xyz = tick.points("vehicle_0").xyz     # (M, 3) [m] in vehicle_0/lidar

Messages are read through the MCAP chunk index of a seekable file (only chunks holding the asked
topics and times are read) and decoded on first access, so asking for one topic of one tick never
decodes the others.
"""

from __future__ import annotations

import fnmatch
import json
import logging
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

from mcap.reader import SeekingReader, make_reader

from cosim.comm.message import LinkSet
from cosim.errors import CosimError, EpisodeFileError, FormatError, InputError
from cosim.io.decode import (
    Boxes,
    Calibration,
    GnssFix,
    Grid,
    Image,
    Objects,
    PointCloud,
    TransformTree,
    decode,
)

log = logging.getLogger(__name__)

#: Format versions this reader understands (major version).
SUPPORTED_MAJOR = 1
#: Metadata values stored as JSON text.
JSON_METADATA = (
    "strategies",
    "agents",
    "sensors_enabled",
    "geo_origin",
    "map_bounds_m",
    "class_table",
    "events",
    "versions",
    "tick_hz",
    "tick_ns",
    "n_ticks",
    "duration_s",
    "seed",
)
LABEL_TOPICS = ("/tf", "/labels/objects", "/labels/boxes")


def check_format_version(version: str | None, source: str = "episode") -> str:
    """Raise :class:`FormatError` unless ``version`` is a format version this reader can read."""
    if version is None:
        raise FormatError(f"{source}: no 'format_version' in the 'episode' metadata record; not a cosim episode?")
    major, _, _ = str(version).partition(".")
    if not major.isdigit():
        raise FormatError(f"{source}: malformed format_version {version!r}; expected MAJOR.MINOR such as '1.0'")
    if int(major) != SUPPORTED_MAJOR:
        import cosim

        raise FormatError(
            f"{source}: episode format version {version} is not supported: cosim {cosim.__version__} reads "
            f"format {SUPPORTED_MAJOR}.x only (see docs/episode_format.md); "
            f"use a cosim release that reads {major}.x"
        )
    return str(version)


def parse_metadata(raw: dict[str, str]) -> dict[str, Any]:
    """The ``episode`` record with JSON-valued keys decoded (strings stay strings)."""
    out: dict[str, Any] = dict(raw)
    for key in JSON_METADATA:
        if key in raw:
            try:
                out[key] = json.loads(raw[key])
            except json.JSONDecodeError:
                out[key] = raw[key]
    return out


@dataclass(frozen=True)
class TopicInfo:
    """One channel: its schema, encoding and message statistics from the summary."""

    topic: str
    schema_name: str
    message_encoding: str
    message_count: int


@dataclass(frozen=True)
class RawMessage:
    """One undecoded message: bytes plus what is needed to decode them."""

    topic: str
    schema_name: str
    message_encoding: str
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    data: bytes
    schema_data: bytes = field(default=b"", repr=False)

    def decode(self) -> Any:
        """The decoded message (see :mod:`cosim.io.decode`); FormatError when the bytes do not decode."""
        try:
            return decode(self.schema_name, self.message_encoding, self.data, self.schema_data)
        except CosimError:
            raise
        except Exception as exc:  # corrupt bytes can fail anywhere in protobuf, numpy or PIL
            raise FormatError(
                f"{self.topic} at t={self.log_time_ns} ns: cannot decode {self.schema_name} "
                f"({type(exc).__name__}: {exc})"
            ) from None


class Tick:
    """The messages of one tick; each is decoded on first access and cached.

    ``tick[topic]`` gives the decoded message, ``tick.raw(topic)`` the bytes; typed accessors
    (``labels``, ``transforms``, ``points(agent)``, ``image(agent, cam)``...) name the topics of
    docs/episode_format.md.
    """

    def __init__(self, index: int, t_ns: int, messages: dict[str, RawMessage]):
        self.index = index
        self.t_ns = t_ns
        self._raw = messages
        self._decoded: dict[str, Any] = {}

    def __repr__(self) -> str:
        return f"Tick({self.index}, t_ns={self.t_ns}, topics={len(self._raw)})"

    @property
    def topics(self) -> list[str]:
        return sorted(self._raw)

    def __contains__(self, topic: str) -> bool:
        return topic in self._raw

    def raw(self, topic: str) -> RawMessage:
        try:
            return self._raw[topic]
        except KeyError:
            raise KeyError(
                f"tick {self.index} has no message on {topic!r}; read topics: {', '.join(self.topics)}"
            ) from None

    def __getitem__(self, topic: str) -> Any:
        if topic not in self._decoded:
            self._decoded[topic] = self.raw(topic).decode()
        return self._decoded[topic]

    def get(self, topic: str, default: Any = None) -> Any:
        return self[topic] if topic in self._raw else default

    @property
    def decoded_topics(self) -> list[str]:
        """Topics decoded so far (for checking laziness)."""
        return sorted(self._decoded)

    # -- typed accessors ------------------------------------------------------------------------

    @property
    def labels(self) -> Objects:
        return self["/labels/objects"]

    def snapshot(self) -> Any:
        """The :class:`~cosim.snapshot.WorldSnapshot` of this tick, rebuilt from ``/labels/objects``."""
        return self.labels.to_snapshot()

    @property
    def boxes(self) -> Boxes:
        return self["/labels/boxes"]

    @property
    def transforms(self) -> TransformTree:
        return self["/tf"]

    def points(self, agent: str) -> PointCloud:
        return self[f"/{agent}/lidar"]

    def image(self, agent: str, camera: str) -> Image:
        return self[f"/{agent}/{camera}/image"]

    def depth(self, agent: str, camera: str) -> Image:
        return self[f"/{agent}/{camera}/depth"]

    def semantic(self, agent: str, camera: str) -> Image:
        return self[f"/{agent}/{camera}/semantic"]

    def instance(self, agent: str, camera: str) -> Image:
        return self[f"/{agent}/{camera}/instance"]

    def calibration(self, agent: str, camera: str) -> Calibration:
        return self[f"/{agent}/{camera}/calibration"]

    def gnss(self, agent: str) -> GnssFix:
        return self[f"/{agent}/gnss"]

    def imu(self, agent: str) -> Any:
        return self[f"/{agent}/imu"]

    def bev(self, agent: str) -> Grid:
        return self[f"/{agent}/bev"]

    def visibility(self, agent: str) -> Any:
        return self[f"/{agent}/visibility"]

    def links(self) -> LinkSet:
        """``/comm/links`` as arrays (:class:`cosim.comm.message.LinkSet`), when ``comm.enabled``."""
        return self["/comm/links"]


class Episode:
    """An open episode file. Use :func:`open_episode`; close it (or use ``with``) when done."""

    def __init__(self, path: Path, stream: BinaryIO, reader: SeekingReader, summary: Any, raw_metadata: dict[str, str]):
        self.path = path
        self._stream = stream
        self._reader = reader
        self._summary = summary
        self.raw_metadata = raw_metadata
        self.metadata = parse_metadata(raw_metadata)
        self.format_version = check_format_version(raw_metadata.get("format_version"), str(path))
        self._attachment_index = {a.name: a for a in summary.attachment_indexes}
        self.topics: dict[str, TopicInfo] = {}
        counts = summary.statistics.channel_message_counts if summary.statistics else {}
        for cid, ch in sorted(summary.channels.items()):
            schema = summary.schemas.get(ch.schema_id)
            self.topics[ch.topic] = TopicInfo(
                ch.topic, schema.name if schema else "", ch.message_encoding, counts.get(cid, 0)
            )

    # -- metadata ---------------------------------------------------------------------------------

    @property
    def scenario(self) -> str:
        return self.metadata.get("scenario", "")

    @property
    def agents(self) -> list[str]:
        """Connected agent ids (``vehicle_0``, ``rsu_0``, ``drone_0``...)."""
        return list(self.metadata.get("agents", []))

    @property
    def tick_ns(self) -> int:
        return int(self.metadata["tick_ns"])

    @property
    def n_ticks(self) -> int:
        return int(self.metadata["n_ticks"])

    @property
    def duration_s(self) -> float:
        return self.n_ticks * self.tick_ns / 1e9

    @property
    def start_ns(self) -> int:
        st = self._summary.statistics
        return st.message_start_time if st and st.message_count else 0

    @property
    def end_ns(self) -> int:
        st = self._summary.statistics
        return st.message_end_time if st and st.message_count else 0

    @property
    def chunk_compression(self) -> str:
        """Compression of the file's chunks (``zstd``, ``lz4`` or ``""``), from the chunk index."""
        chunks = self._summary.chunk_indexes
        return chunks[0].compression if chunks else ""

    def message_sizes(self) -> Iterator[tuple[Any, dict[str, int]]]:
        """Per chunk of the file: its chunk index record and the bytes of its message records per topic, read
        from the message indexes alone (no chunk is read or decompressed). A record's size is the distance
        to the next record of the chunk, less the schema and channel records the writer puts before a
        channel's first message (their sizes follow from the summary)."""
        summary = self._summary
        topic_of = {cid: ch.topic for cid, ch in summary.channels.items()}

        def text(value: str | bytes) -> int:
            return 4 + len(value.encode() if isinstance(value, str) else value)

        channel_size = {cid: 9 + 2 + 2 + text(ch.topic) + text(ch.message_encoding)
                        + 4 + sum(text(k) + text(v) for k, v in ch.metadata.items())
                        for cid, ch in summary.channels.items()}
        schema_size = {sid: 9 + 2 + text(sc.name) + text(sc.encoding) + text(sc.data)
                       for sid, sc in summary.schemas.items()}
        seen_channels: set[int] = set()
        seen_schemas: set[int] = set()
        for chunk in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
            starts: list[tuple[int, int]] = []
            for cid, where in chunk.message_index_offsets.items():
                self._stream.seek(where)
                head = self._stream.read(15)  # opcode (1), record length (8), channel id (2), array length (4)
                if len(head) < 15:
                    raise FormatError(f"{self.path}: message index at byte {where} is cut off")
                body = self._stream.read(int.from_bytes(head[11:15], "little"))
                starts.extend((int.from_bytes(body[i + 8:i + 16], "little"), cid) for i in range(0, len(body) - 15, 16))
            starts.sort()
            sizes: dict[str, int] = {}
            for k, (offset, cid) in enumerate(starts):
                end = chunk.uncompressed_size
                if k + 1 < len(starts):
                    end, following = starts[k + 1]
                    if following not in seen_channels:  # its channel (and maybe schema) record comes first
                        seen_channels.add(following)
                        end -= channel_size.get(following, 0)
                        sid = summary.channels[following].schema_id if following in summary.channels else 0
                        if sid and sid not in seen_schemas:
                            seen_schemas.add(sid)
                            end -= schema_size.get(sid, 0)
                seen_channels.add(cid)
                seen_schemas.add(summary.channels[cid].schema_id if cid in summary.channels else 0)
                sizes[topic_of.get(cid, "?")] = sizes.get(topic_of.get(cid, "?"), 0) + max(0, end - offset)
            yield chunk, sizes

    @property
    def message_count(self) -> int:
        st = self._summary.statistics
        return st.message_count if st else 0

    @property
    def class_table(self) -> dict[str, Any]:
        return self.metadata.get("class_table", {})

    def cameras(self, agent: str) -> list[str]:
        """Camera names of ``agent`` that have an image topic in this file."""
        prefix = f"/{agent}/"
        return sorted(
            t[len(prefix) : -len("/image")]
            for t in self.topics
            if t.startswith(prefix) and t.endswith("/image") and t.count("/") == 3
        )

    def schemas(self) -> dict[str, tuple[str, str, bytes]]:
        """Per topic: (schema name, schema encoding, schema bytes) as stored in the file."""
        out: dict[str, tuple[str, str, bytes]] = {}
        for ch in self._summary.channels.values():
            s = self._summary.schemas.get(ch.schema_id)
            out[ch.topic] = (s.name, s.encoding, s.data) if s else ("", "", b"")
        return out

    # -- attachments ------------------------------------------------------------------------------

    @property
    def attachments(self) -> list[str]:
        return sorted(self._attachment_index)

    def attachment(self, name: str) -> bytes:
        """The bytes of one attachment (``scenario.yaml``, ``map.net.xml``, ``routes.rou.xml``...)."""
        if name not in self._attachment_index:
            raise KeyError(f"{self.path} has no attachment {name!r}; it has: {', '.join(self.attachments)}")
        try:
            for a in self._reader.iter_attachments():
                if a.name == name:
                    return a.data
        except Exception as exc:  # a damaged file
            raise FormatError(f"{self.path}: cannot read attachment {name!r} ({type(exc).__name__}: {exc})") from None
        raise FormatError(f"{self.path}: attachment {name!r} is indexed but cannot be read")

    # -- messages ---------------------------------------------------------------------------------

    def select(self, topics: Iterable[str] | str | None) -> list[str]:
        """Topics of this file matching names or shell patterns (``/vehicle_0/*``, ``*/lidar``).

        A name or pattern that matches nothing raises ``KeyError`` listing the topics.
        """
        if topics is None:
            return sorted(self.topics)
        if isinstance(topics, str):
            topics = [topics]
        out: set[str] = set()
        for pattern in topics:
            hits = [t for t in self.topics if fnmatch.fnmatchcase(t, pattern)]
            if not hits:
                raise KeyError(f"no topic matches {pattern!r} in {self.path}; topics: {', '.join(sorted(self.topics))}")
            out.update(hits)
        return sorted(out)

    def messages(
        self,
        topics: Iterable[str] | str | None = None,
        start_ns: int | None = None,
        end_ns: int | None = None,
    ) -> Iterator[RawMessage]:
        """Undecoded messages in log-time order, limited to ``topics`` and ``[start_ns, end_ns)``."""
        selected = self.select(topics)
        try:
            for schema, channel, message in self._reader.iter_messages(
                topics=selected, starting_at=start_ns, ending_before=end_ns, log_time_order=True
            ):
                yield RawMessage(
                    channel.topic,
                    schema.name if schema else "",
                    channel.message_encoding,
                    message.log_time,
                    message.publish_time,
                    message.sequence,
                    message.data,
                    schema.data if schema else b"",
                )
        except Exception as exc:  # the MCAP library and zstd raise many types on a corrupt file
            raise FormatError(
                f"{self.path}: cannot read messages ({type(exc).__name__}: {exc}); run `cosim validate` on it"
            ) from None

    def ticks(
        self, topics: Iterable[str] | str | None = None, start: int = 0, stop: int | None = None
    ) -> Iterator[Tick]:
        """Ticks ``start <= k < stop`` in order, each holding the messages of ``topics`` (default all)."""
        stop = self.n_ticks if stop is None else stop
        if start >= stop:
            return
        current: dict[str, RawMessage] = {}
        current_t: int | None = None
        for m in self.messages(topics, start * self.tick_ns, stop * self.tick_ns):
            if current_t is not None and m.log_time_ns != current_t:
                yield Tick(current_t // self.tick_ns, current_t, current)
                current = {}
            current_t = m.log_time_ns
            current[m.topic] = m
        if current_t is not None:
            yield Tick(current_t // self.tick_ns, current_t, current)

    def tick(self, index: int, topics: Iterable[str] | str | None = None) -> Tick:
        """One tick by index (reads only the chunks around its time)."""
        if not 0 <= index < self.n_ticks:
            raise IndexError(f"tick {index} out of range: {self.path} has ticks 0..{self.n_ticks - 1}")
        for t in self.ticks(topics, index, index + 1):
            return t
        return Tick(index, index * self.tick_ns, {})

    def __len__(self) -> int:
        return self.n_ticks

    # -- lifecycle --------------------------------------------------------------------------------

    def close(self) -> None:
        self._stream.close()

    def __enter__(self) -> Episode:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return (
            f"Episode({str(self.path)!r}, scenario={self.scenario!r}, ticks={self.n_ticks}, "
            f"agents={len(self.agents)}, topics={len(self.topics)})"
        )


def open_episode(path: str | Path) -> Episode:
    """Open an episode for reading.

    Raises :class:`~cosim.errors.InputError` when the file is missing and
    :class:`~cosim.errors.EpisodeFileError` (a FormatError and an InputError: exit status 2) when it is not a
    complete cosim episode (truncated, no
    summary, no ``episode`` metadata) or has a format major version this reader does not know.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"no episode file at {path}")
    stream = open(path, "rb")  # noqa: SIM115 (owned by the Episode)
    try:
        reader = make_reader(stream)
        if not isinstance(reader, SeekingReader):
            raise FormatError(f"{path}: not seekable")
        try:
            summary = reader.get_summary()
        except Exception as exc:  # a damaged footer or summary fails in many ways
            raise FormatError(
                f"{path}: truncated or corrupt MCAP (no readable footer/summary: {exc}); run `cosim validate` on it"
            ) from None
        if summary is None:
            raise FormatError(f"{path}: MCAP without a summary section; the writer did not finish it")
        raw: dict[str, str] | None = None
        for record in reader.iter_metadata():
            if record.name == "episode":
                raw = dict(record.metadata)
        if raw is None:
            raise FormatError(f"{path}: no 'episode' metadata record; not a cosim episode")
        return Episode(path, stream, reader, summary, raw)
    except FormatError as exc:
        stream.close()
        if isinstance(exc, InputError):
            raise
        raise EpisodeFileError(str(exc)) from None
    except CosimError:
        stream.close()
        raise
    except Exception as exc:
        stream.close()
        raise EpisodeFileError(f"{path}: not a readable MCAP file ({type(exc).__name__}: {exc})") from None
    except BaseException:
        stream.close()
        raise
