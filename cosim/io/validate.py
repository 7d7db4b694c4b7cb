"""``cosim validate``: check an episode file against docs/episode_format.md.

The file is read linearly record by record (no trust in its summary), so a truncated or corrupt
file yields a problem report, never an exception. Checks:

- structure: MCAP magic, header, every record readable, data end, summary and footer present,
  summary statistics equal to the messages actually found;
- metadata: the ``episode`` record with every required key and a readable format version;
- attachments: scenario, network, routes, world layout;
- topics: each topic's schema is the one the format names for it;
- completeness: every tick 0..n_ticks-1 has exactly one message on every topic;
- actions: ``/actions`` entries answer the previous tick and name agents of the episode;
- time: log times non-decreasing in file order, on the tick grid, inside the episode,
  ``publish_time == log_time`` and the message's own timestamp equal to its log time;
- labels: unique track ids of known classes, one stable class per track, every box, agent,
  LiDAR point, instance pixel and visibility entry refers to a track alive at that tick;
- transforms: ``/tf`` forms one tree rooted at ``map`` (one parent per frame, no cycle), every
  agent has ``<agent>/base_link`` and every message's frame id is in the tree;
- calibration: every image has a calibration on the same tick, same frame, same size, finite
  intrinsics, and a lens that is a pinhole or ``plumb_bob`` with 5 coefficients;
- sensors: LiDAR point records have the fields and types of section 3.4, depth images the encoding
  of section 3.5 (and, with pixels, only NaN or finite distances >= 0);
- boxes: LiDAR returns with an object's instance id lie inside its box and instance pixels inside its
  projected box (:mod:`cosim.io.validate_boxes`; not for ``cosim synthetic`` episodes, whose sensor data
  is not rendered);
- comm: ``/comm/links`` decodes (columns of one length, known link types and LOS states, finite
  numbers, PER and delivery in [0, 1]) and names only the metadata's agents.
"""


from __future__ import annotations

import json
import logging
import math
import struct
import zlib
from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mcap.exceptions import EndOfFile, RecordLengthLimitExceeded
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
)
from mcap.stream_reader import StreamReader, get_chunk_data_stream

from cosim.classes import OBJECT_CLASSES
from cosim.comm.message import decode_links
from cosim.errors import CosimError, FormatError, InputError
from cosim.geometry import has_distortion
from cosim.io.decode import PROTO_DECODERS, TransformTree, decode_transforms, parse_json, parse_proto
from cosim.io.format import (
    LABEL_TOPICS,
    MAP_FRAME,
    REQUIRED_ATTACHMENTS,
    REQUIRED_METADATA,
    STATIC_INSTANCE_MIN,
    expected_topics,
    topic_spec,
)
from cosim.io.points import layout_problems
from cosim.io.reader import JSON_METADATA, check_format_version, parse_metadata
from cosim.io.validate_boxes import (
    LIDAR_TOLERANCE_M,
    NOISE_SIGMAS,
    PIXEL_TOLERANCE,
    instance_ids,
    lidar_excess,
    object_boxes,
    pixel_excess,
)

log = logging.getLogger(__name__)

MAGIC_BYTES = 8  # the MCAP magic before the first record
#: Depth encodings by format version (None: any other 1.x).
DEPTH_ENCODINGS: dict[str | None, tuple[str, ...]] = {"1.0": ("16UC1",), "1.1": ("32FC1",),
                                                     None: ("cosim-depth", "32FC1")}

#: Problems kept per (check, topic); the rest are counted.
MAX_PER_KIND = 8


@dataclass(frozen=True)
class Problem:
    """One way the file departs from the format."""

    #: structure | metadata | attachments | topics | completeness | time | labels | transforms | calibration | comm
    #: | sensors | boxes
    check: str
    message: str
    tick: int | None = None
    topic: str | None = None

    def __str__(self) -> str:
        where = []
        if self.tick is not None:
            where.append(f"tick {self.tick}")
        if self.topic:
            where.append(self.topic)
        loc = f" {' '.join(where)}:" if where else ""
        return f"[{self.check}]{loc} {self.message}"


@dataclass(frozen=True)
class ChunkFacts:
    """What the summary's chunk index must say about one chunk (the chunk's data is not kept)."""

    message_start_time: int
    message_end_time: int
    compressed_size: int
    uncompressed_size: int
    compression: str
    record_length: int  # [bytes] the chunk record, opcode and length prefix included


@dataclass
class ValidationReport:
    path: Path
    problems: list[Problem] = field(default_factory=list)
    suppressed: dict[tuple[str, str], int] = field(default_factory=dict)
    messages: int = 0
    ticks: int = 0
    topics: dict[str, int] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.problems

    def checks_failed(self) -> set[str]:
        return {p.check for p in self.problems}

    def lines(self) -> list[str]:
        out = [str(p) for p in self.problems]
        out += [
            f"[{c}] {t or '(file)'}: {n} more problems of this kind not shown" for (c, t), n in self.suppressed.items()
        ]
        return out


def _ranges(ticks: Iterable[int]) -> str:
    ks = sorted(set(ticks))
    parts: list[str] = []
    i = 0
    while i < len(ks):
        j = i
        while j + 1 < len(ks) and ks[j + 1] == ks[j] + 1:
            j += 1
        parts.append(str(ks[i]) if i == j else f"{ks[i]}-{ks[j]}")
        i = j + 1
    if len(parts) > 12:
        parts = [*parts[:12], f"... ({len(ks)} ticks)"]
    return ", ".join(parts)


class _Validator:
    def __init__(self, path: Path, pixels: bool):
        self.report = ValidationReport(path)
        self.pixels = pixels
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.meta: dict[str, Any] | None = None
        self.tick_ns: int | None = None
        self.n_ticks: int | None = None
        self.agents: list[str] = []
        self.attachments: set[str] = set()
        self.topic_ticks: dict[str, list[int]] = defaultdict(list)
        self.track_class: dict[int, str] = {}
        self.last_time = -1
        self.done_times: set[int] = set()
        self.group_t: int | None = None
        self.group: list[tuple[Channel, Message]] = []
        self.counts: dict[int, int] = defaultdict(int)
        self.statistics: Statistics | None = None
        self.seen_header = self.seen_data_end = self.seen_footer = False
        self.scenario_yaml: bytes | None = None
        self.min_time = 2**64
        self.n_attachments = self.n_metadata = 0
        self.data_ids: set[tuple[str, int]] = set()
        self.summary_ids: set[tuple[str, int]] = set()
        self.chunks: dict[int, ChunkFacts] = {}  # file offset -> what the chunk index must say about it
        self.chunk_message_index_bytes: dict[int, int] = {}  # chunk offset -> bytes of its message indexes
        self.chunk_messages: dict[int, list[tuple[int, int]]] = {}  # last chunk: channel -> (log time, offset)
        self.chunk_indexes: list[ChunkIndex] = []
        self.chunk_channels: dict[int, set[int]] = {}  # chunk offset -> channels with messages in it
        self.message_indexes: dict[int, int] = {}  # file offset of a message index -> its channel
        self.records_at: dict[int, tuple[str, str, int]] = {}  # attachments, metadata: offset -> kind, name, length
        self.fit_calibrations: dict[str, Any] = {}
        self.fit: dict[str, Any] = {}  # this tick's boxes, /tf and IMU rates for the boxes check
        self.lidar_fit: list[tuple[int | None, str, int, float, int, int]] = []  # over 0.1 m: judged at the end

    # -- reporting --------------------------------------------------------------------------------

    def problem(self, check: str, message: str, tick: int | None = None, topic: str | None = None) -> None:
        key = (check, topic or "")
        kept = sum(1 for p in self.report.problems if (p.check, p.topic or "") == key)
        if kept >= MAX_PER_KIND:
            self.report.suppressed[key] = self.report.suppressed.get(key, 0) + 1
            return
        self.report.problems.append(Problem(check, message, tick, topic))

    # -- records ----------------------------------------------------------------------------------

    def run(self) -> ValidationReport:
        path = self.report.path
        size = path.stat().st_size
        offset_hint = MAGIC_BYTES
        last_chunk: int | None = None  # the chunk whose message indexes follow, while they do
        try:
            with open(path, "rb") as f, open(path, "rb") as raw:
                reader = StreamReader(f, emit_chunks=True, validate_crcs=True, record_size_limit=max(size, 1))
                for record in reader.records:
                    start, offset_hint = offset_hint, f.tell()
                    if isinstance(record, Chunk):
                        self.chunks[start] = ChunkFacts(
                            record.message_start_time,
                            record.message_end_time,
                            len(record.data),
                            record.uncompressed_size,
                            record.compression,
                            offset_hint - start,
                        )
                        last_chunk = start
                        self.chunk_message_index_bytes[start] = 0
                        self.chunk_messages = {}
                        for offset, inner in _chunk_records(record):
                            if isinstance(inner, Message):
                                self.chunk_messages.setdefault(inner.channel_id, []).append((inner.log_time, offset))
                            self.on_record(inner)
                        self.chunk_channels[start] = set(self.chunk_messages)
                    elif isinstance(record, MessageIndex):
                        self.message_indexes[start] = record.channel_id
                        if last_chunk is not None:
                            self.chunk_message_index_bytes[last_chunk] += offset_hint - start
                        self.check_message_index(record, start)
                    elif isinstance(record, Attachment):
                        last_chunk = None
                        self.check_attachment_crc(raw, start, offset_hint, record.name)
                        self.records_at[start] = ("attachment", record.name, offset_hint - start)
                        self.on_record(record)
                    elif isinstance(record, Metadata):
                        self.records_at[start] = ("metadata", record.name, offset_hint - start)
                        self.on_record(record)
                    elif isinstance(record, AttachmentIndex | MetadataIndex):
                        self.check_record_index(record)
                    else:
                        last_chunk = None
                        self.on_record(record)
        except Exception as exc:  # a corrupt file may break the MCAP parser in any way; report, never crash
            if isinstance(exc, EndOfFile | struct.error | RecordLengthLimitExceeded):
                what = f"unexpected end of file{f': {exc}' if str(exc) else ''}"
            else:
                what = f"{type(exc).__name__}: {exc}"
            last = (
                f"; last message read at t={self.last_time} ns (tick {self.last_time // self.tick_ns})"
                if self.last_time >= 0 and self.tick_ns
                else "; no message could be read"
            )
            self.problem("structure", f"file is truncated or corrupt after byte {offset_hint} of {size} ({what}){last}")
        self.flush_group()
        self.finish()
        return self.report

    def on_definition(self, kind: str, rid: int, name: str, record: Any, table: dict[int, Any]) -> bool:
        """A schema or channel: defined once in the data section, repeated identically in the summary.
        Returns True the first time an id is seen."""
        summary = self.seen_data_end
        (self.summary_ids if summary else self.data_ids).add((kind, rid))
        before = table.get(rid)
        if before is None:
            table[rid] = record
            if summary:
                self.problem("structure", f"{kind} {rid} ({name!r}) is in the summary but not in the data (corrupt)")
            return not summary
        if before != record:
            self.problem(
                "structure",
                f"{kind} {rid} ({before.name if kind == 'schema' else before.topic!r}) "
                f"differs between the data and summary sections (corrupt)",
            )
        return False

    def check_message_index(self, index: MessageIndex, offset: int) -> None:
        """A chunk's message index (used by seeking readers) must list exactly its messages."""
        actual = sorted(self.chunk_messages.get(index.channel_id, []))
        if sorted(index.records) != actual:
            ch = self.channels.get(index.channel_id)
            self.problem(
                "structure",
                f"message index at byte {offset} does not match its chunk's messages "
                f"({len(index.records)} entries, {len(actual)} messages)",
                topic=ch.topic if ch else f"channel {index.channel_id}",
            )

    def check_record_index(self, index: AttachmentIndex | MetadataIndex) -> None:
        """A summary's attachment or metadata index must point at that record in the data section
        (readers fetch attachments and metadata through it)."""
        kind = "attachment" if isinstance(index, AttachmentIndex) else "metadata"
        found = self.records_at.get(index.offset)
        if found != (kind, index.name, index.length):
            self.problem("structure", f"{kind} index for {index.name!r} points at byte {index.offset} "
                                      f"(length {index.length}), where no such record is (corrupt)")

    def check_attachment_crc(self, raw: Any, start: int, end: int, name: str) -> None:
        """MCAP attachments carry a CRC over their fields that readers do not check; check it here."""
        raw.seek(start)
        data = raw.read(end - start)
        stored = int.from_bytes(data[-4:], "little")
        if stored and zlib.crc32(data[9:-4]) != stored:
            self.problem("attachments", f"attachment {name!r} fails its CRC (corrupt)")

    def on_record(self, record: Any) -> None:
        if isinstance(record, Header):
            self.seen_header = True
        elif isinstance(record, Schema):
            self.on_definition("schema", record.id, record.name, record, self.schemas)
        elif isinstance(record, Channel):
            if self.on_definition("channel", record.id, record.topic, record, self.channels):
                self.check_channel(record)
        elif isinstance(record, ChunkIndex):
            self.chunk_indexes.append(record)
        elif isinstance(record, Message):
            self.on_message(record)
        elif isinstance(record, Metadata):
            self.n_metadata += 1
            if record.name == "episode":
                self.on_metadata(dict(record.metadata))
        elif isinstance(record, Attachment):
            self.n_attachments += 1
            self.attachments.add(record.name)
            if record.name == "scenario.yaml":
                self.scenario_yaml = record.data
        elif isinstance(record, DataEnd):
            self.seen_data_end = True
        elif isinstance(record, Statistics):
            self.statistics = record
        elif isinstance(record, Footer):
            self.seen_footer = True
            if record.summary_start == 0:
                self.problem("structure", "no summary section (the writer did not finish the file)")

    def on_metadata(self, raw: dict[str, str]) -> None:
        missing = [k for k in REQUIRED_METADATA if k not in raw]
        if missing:
            self.problem("metadata", f"episode record lacks {', '.join(missing)}")
        try:
            check_format_version(raw.get("format_version"), "episode")
        except FormatError as exc:
            self.problem("metadata", str(exc))
        self.meta = parse_metadata(raw)
        for key in JSON_METADATA:
            if key in raw and self.meta[key] is raw[key]:
                self.problem("metadata", f"{key} is not valid JSON: {raw[key][:60]!r}")
        table = self.meta.get("class_table")
        if isinstance(table, dict) and not (
            isinstance(table.get("object_classes"), list) and isinstance(table.get("semantic_classes"), list)
        ):
            self.problem("metadata", "class_table lacks object_classes / semantic_classes lists")
        try:
            self.tick_ns = int(self.meta["tick_ns"])
            self.n_ticks = int(self.meta["n_ticks"])
            if self.tick_ns <= 0 or self.n_ticks <= 0:
                raise ValueError(f"tick_ns {self.tick_ns}, n_ticks {self.n_ticks}")
        except (KeyError, ValueError, TypeError) as exc:
            self.problem("metadata", f"unusable tick_ns / n_ticks ({exc}); time checks skipped")
            self.tick_ns = self.n_ticks = None
        agents = self.meta.get("agents", [])
        self.agents = [str(a) for a in agents] if isinstance(agents, list) else []

    def check_channel(self, ch: Channel) -> None:
        schema = self.schemas.get(ch.schema_id)
        name = schema.name if schema else ""
        found = topic_spec(ch.topic)
        if found is None:
            self.problem("topics", f"topic is not part of the format (schema {name!r})", topic=ch.topic)
            return
        spec, parts = found
        if "agent" in parts and self.meta is not None and parts["agent"] not in self.agents:
            self.problem("topics", f"agent {parts['agent']!r} is not in the metadata's agents", topic=ch.topic)
        ok = name in spec.schemas or (name.startswith("cosim.") and any(s.startswith("cosim.") for s in spec.schemas))
        if not ok:
            self.problem("topics", f"schema {name!r}, expected {' or '.join(spec.schemas)}", topic=ch.topic)
        if name.startswith("foxglove.") and ch.message_encoding != "protobuf":
            self.problem("topics", f"encoding {ch.message_encoding!r} for {name}, expected protobuf", topic=ch.topic)

    def on_message(self, m: Message) -> None:
        ch = self.channels.get(m.channel_id)
        if ch is None:
            self.problem("structure", f"message on unknown channel id {m.channel_id} at log time {m.log_time} ns")
            return
        self.counts[m.channel_id] += 1
        self.report.messages += 1
        tick = self.tick_of(m.log_time, ch.topic)
        if m.log_time < self.last_time:
            self.problem(
                "time",
                f"log time {m.log_time} ns goes back from {self.last_time} ns (not monotonic)",
                tick,
                ch.topic,
            )
        self.last_time = max(self.last_time, m.log_time)
        self.min_time = min(self.min_time, m.log_time)
        if m.publish_time != m.log_time:
            self.problem("time", f"publish_time {m.publish_time} ns != log_time {m.log_time} ns", tick, ch.topic)
        if tick is not None:
            self.topic_ticks[ch.topic].append(tick)
        if self.group_t is not None and m.log_time != self.group_t:
            self.flush_group()
        if m.log_time in self.done_times and self.group_t != m.log_time:
            self.problem("time", f"messages of t={m.log_time} ns are not contiguous in the file", tick, ch.topic)
        self.group_t = m.log_time
        self.group.append((ch, m))

    def tick_of(self, t_ns: int, topic: str) -> int | None:
        if self.tick_ns is None:
            return None
        k, rem = divmod(t_ns, self.tick_ns)
        if rem:
            self.problem("time", f"log time {t_ns} ns is not on the {self.tick_ns} ns tick grid", None, topic)
            return None
        if self.n_ticks is not None and not 0 <= k < self.n_ticks:
            self.problem("time", f"log time {t_ns} ns is outside the episode (ticks 0..{self.n_ticks - 1})", k, topic)
            return None
        return k

    # -- one tick ---------------------------------------------------------------------------------

    def flush_group(self) -> None:
        if self.group_t is None:
            return
        t_ns, group = self.group_t, self.group
        self.group_t, self.group = None, []
        self.done_times.add(t_ns)
        tick = t_ns // self.tick_ns if self.tick_ns else None
        if self.tick_ns and t_ns % self.tick_ns:
            return  # already reported; contents cannot be placed on a tick
        try:
            self.check_tick(tick, t_ns, group)
        except Exception as exc:  # a check must never take the whole run down
            self.problem("structure", f"could not check this tick: {type(exc).__name__}: {exc}", tick)

    def check_tick(self, tick: int | None, t_ns: int, group: list[tuple[Channel, Message]]) -> None:
        """All per-tick checks. Labels and /tf first; then each sensor message is parsed, checked and
        dropped, so memory stays near one tick of raw data."""
        by_topic: dict[str, list[tuple[Channel, Message]]] = defaultdict(list)
        for ch, m in group:
            by_topic[ch.topic].append((ch, m))
        group.clear()
        for topic, msgs in by_topic.items():
            if len(msgs) > 1:
                self.problem("completeness", f"{len(msgs)} messages on one tick (expected 1)", tick, topic)
        small = {t: self.parse_checked(tick, t_ns, *by_topic.pop(t)[0]) for t in LABEL_TOPICS if t in by_topic}
        tree = self.check_tf(tick, small.get("/tf"))
        live = self.check_labels(tick, small)
        frames = tree.frames | {MAP_FRAME} if tree is not None else None
        if tree is not None:
            self.check_agent_poses(tick, tree, small.get("/labels/objects"))
        for topic, value in small.items():
            self.check_frame_ids(tick, topic, value, frames)
        objs = small.get("/labels/objects")
        fits = (tree is not None and isinstance(objs, dict)
                and (self.meta or {}).get("generator") != "cosim synthetic")
        self.fit = {"tree": tree, "boxes": object_boxes(objs), "objects": objs, "rates": {}} if fits else {}
        images: dict[str, tuple[str, tuple[int, int] | None]] = {}
        calibrations: dict[str, Any] = {}
        self.fit_calibrations = calibrations
        # IMUs and calibrations first: the boxes check of LiDAR sweeps and instance images needs them
        for topic in sorted(by_topic, key=lambda t: (not t.endswith(("/imu", "/calibration")), t)):
            ch, m = by_topic.pop(topic)[0]
            value = self.parse_checked(tick, t_ns, ch, m)
            del m
            if value is None:
                continue
            self.check_frame_ids(tick, topic, value, frames)
            self.check_sensor(tick, topic, value, live)
            if topic == "/actions":
                self.check_actions(tick, value)
            if topic.endswith("/imu") and self.fit and isinstance(value, dict):
                self.fit["rates"][topic.split("/")[1]] = value.get("angular_velocity_radps", (0.0, 0.0, 0.0))
            if topic.endswith("/image"):
                images[topic] = (value.frame_id, _image_size(value))
            elif topic.endswith("/calibration"):
                calibrations[topic] = value
            del value
        for topic, (frame_id, size) in images.items():
            self.check_calibration(
                tick, topic, frame_id, size, calibrations.get(topic[: -len("image")] + "calibration")
            )

    def parse_checked(self, tick: int | None, t_ns: int, ch: Channel, m: Message) -> Any:
        schema = self.schemas.get(ch.schema_id)
        value = self.parse(tick, ch, schema.name if schema else "", schema.data if schema else b"", m)
        if value is not None:
            self.check_stamp(tick, ch.topic, value, t_ns)
        return value

    def check_agent_poses(self, tick: int | None, tree: TransformTree, objs: Any) -> None:
        """Every metadata agent is in the labels, at the pose ``/tf`` gives its base_link."""
        if not isinstance(objs, dict) or not isinstance(objs.get("agents"), list):
            return
        poses = {a.get("agent_id"): a for a in objs["agents"] if isinstance(a, dict)}
        missing = [a for a in self.agents if a not in poses]
        if missing:
            self.problem("labels", f"agents {missing} have no pose in /labels/objects", tick, "/labels/objects")
        for agent_id, a in poses.items():
            t = tree.by_child.get(f"{agent_id}/base_link")
            if t is None or t.parent != MAP_FRAME:
                continue
            try:
                pos = np.asarray(a["position_m"], dtype=np.float64)
                rot = np.asarray(a["rotation"], dtype=np.float64)
            except (KeyError, TypeError, ValueError):
                self.problem("labels", f"agent {agent_id!r} has no usable position_m/rotation", tick, "/labels/objects")
                continue
            same_rot = np.allclose(rot, t.rotation, atol=1e-9) or np.allclose(rot, -t.rotation, atol=1e-9)
            if pos.shape != (3,) or not np.allclose(pos, t.translation_m, atol=1e-6) or not same_rot:
                self.problem(
                    "labels",
                    f"agent {agent_id!r} pose {pos.tolist()} differs from /tf map -> "
                    f"{agent_id}/base_link {t.translation_m.tolist()}",
                    tick,
                    "/labels/objects",
                )

    def parse(self, tick: int | None, ch: Channel, schema_name: str, schema_data: bytes, m: Message) -> Any:
        try:
            if ch.message_encoding == "protobuf":
                return parse_proto(schema_name, m.data, schema_data)
            if ch.message_encoding == "json":
                return parse_json(schema_name, m.data)
            self.problem("topics", f"unknown message encoding {ch.message_encoding!r}", tick, ch.topic)
        except (FormatError, CosimError) as exc:
            self.problem("structure", str(exc), tick, ch.topic)
        return None

    def check_stamp(self, tick: int | None, topic: str, value: Any, t_ns: int) -> None:
        stamps: list[int] = []
        if isinstance(value, dict):
            if "timestamp_ns" in value:
                stamps.append(value["timestamp_ns"])
            if "tick" in value and tick is not None and value["tick"] != tick:
                self.problem("time", f"payload says tick {value['tick']}", tick, topic)
        elif hasattr(value, "DESCRIPTOR"):
            names = {f.name for f in value.DESCRIPTOR.fields}
            if "timestamp" in names and value.HasField("timestamp"):
                stamps.append(value.timestamp.seconds * 1_000_000_000 + value.timestamp.nanos)
            for rep in ("transforms", "entities"):
                if rep in names:
                    stamps += [x.timestamp.seconds * 1_000_000_000 + x.timestamp.nanos for x in getattr(value, rep)]
        bad = sorted({s for s in stamps if s != t_ns})
        if bad:
            self.problem("time", f"message timestamp {bad[0]} ns != log time {t_ns} ns", tick, topic)

    def check_tf(self, tick: int | None, msg: Any) -> TransformTree | None:
        if msg is None:
            return None
        tree = decode_transforms(msg)
        parents: dict[str, list[str]] = defaultdict(list)
        for t in tree.transforms:
            parents[t.child].append(t.parent)
            if not (np.isfinite(t.translation_m).all() and np.isfinite(t.rotation).all()):
                self.problem("transforms", f"transform {t.parent} -> {t.child} is not finite: translation "
                                           f"{t.translation_m.tolist()}, rotation {t.rotation.tolist()}", tick, "/tf")
        for child, ps in parents.items():
            if len(ps) > 1:
                self.problem("transforms", f"frame {child!r} has {len(ps)} parents: {', '.join(ps)}", tick, "/tf")
            if child == MAP_FRAME:
                self.problem("transforms", f"the root {MAP_FRAME!r} has a parent {ps[0]!r}", tick, "/tf")
        for frame in sorted(tree.frames - {MAP_FRAME}):
            path, f = [frame], frame
            while f != MAP_FRAME:
                p = parents.get(f)
                if not p:
                    self.problem(
                        "transforms",
                        f"frame {frame!r} does not reach {MAP_FRAME!r}: {f!r} has no parent "
                        f"(chain {' -> '.join(path)})",
                        tick,
                        "/tf",
                    )
                    break
                f = p[0]
                if f in path:
                    self.problem("transforms", f"cycle through {f!r}: {' -> '.join([*path, f])}", tick, "/tf")
                    break
                path.append(f)
        for agent in self.agents:
            if f"{agent}/base_link" not in tree.frames:
                self.problem("transforms", f"agent {agent!r} has no frame {agent}/base_link", tick, "/tf")
        return tree

    def check_frame_ids(self, tick: int | None, topic: str, value: Any, frames: set[str] | None) -> None:
        if frames is None:
            return
        ids: set[str] = set()
        if hasattr(value, "DESCRIPTOR"):
            names = {f.name for f in value.DESCRIPTOR.fields}
            if "frame_id" in names and value.frame_id:
                ids.add(value.frame_id)
            if "entities" in names:
                ids |= {e.frame_id for e in value.entities}
        elif isinstance(value, dict) and isinstance(value.get("frame_id"), str):
            ids.add(value["frame_id"])
        for fid in sorted(ids - frames):
            self.problem("transforms", f"frame_id {fid!r} is not in this tick's /tf tree", tick, topic)

    def check_labels(self, tick: int | None, decoded: dict[str, Any]) -> set[int] | None:
        objs = decoded.get("/labels/objects")
        if not isinstance(objs, dict):
            return None
        try:
            ids = [int(o["track_id"]) for o in objs["objects"]]
            classes = [str(o["class"]) for o in objs["objects"]]
            agents = list(objs.get("agents", []))
        except (KeyError, TypeError, ValueError) as exc:
            self.problem("labels", f"object without a usable track_id/class ({exc})", tick, "/labels/objects")
            return None
        for where, value in _non_finite(objs, "")[:3]:
            self.problem("labels", f"{where[1:]} is not finite ({value})", tick, "/labels/objects")
        live = set(ids)
        if len(live) != len(ids):
            dupes = sorted({i for i in ids if ids.count(i) > 1})
            self.problem("labels", f"track ids repeated within the tick: {dupes}", tick, "/labels/objects")
        for i, c in zip(ids, classes, strict=True):
            if c not in OBJECT_CLASSES:
                self.problem(
                    "labels",
                    f"track {i} has unknown class {c!r}; known: {', '.join(OBJECT_CLASSES)}",
                    tick,
                    "/labels/objects",
                )
            before = self.track_class.setdefault(i, c)
            if before != c:
                self.problem("labels", f"track {i} changed class from {before!r} to {c!r}", tick, "/labels/objects")
        for a in agents:
            tid = a.get("track_id") if isinstance(a, dict) else None
            if tid is not None and tid not in live:
                self.problem(
                    "labels",
                    f"agent {a.get('agent_id')!r} references track {tid}, which is not in /labels/objects at this tick",
                    tick,
                    "/labels/objects",
                )
        boxes = decoded.get("/labels/boxes")
        if boxes is not None:
            box_ids = [e.id for e in boxes.entities]
            dangling = sorted(set(box_ids) - {str(i) for i in live}, key=lambda s: (len(s), s))
            if dangling:
                self.problem(
                    "labels",
                    f"box entities {', '.join(dangling)} reference tracks not in /labels/objects at this tick",
                    tick,
                    "/labels/boxes",
                )
            missing = sorted(live - {int(b) for b in box_ids if b.lstrip("-").isdigit()})
            if missing:
                self.problem("labels", f"tracks {missing} have no box", tick, "/labels/boxes")
            if not any(d.type == d.ALL for d in boxes.deletions):
                self.problem("labels", "no delete-all before the boxes", tick, "/labels/boxes")
        return live

    def check_actions(self, tick: int | None, value: Any) -> None:
        """``/actions`` (3.11): answers to the previous tick, for agents of this episode."""
        entries = value.get("actions") if isinstance(value, dict) else None
        if not isinstance(entries, list) or not isinstance(value.get("failed"), list):
            self.problem("structure", "no 'actions' and 'failed' lists", tick, "/actions")
            return
        for e in entries:
            action = e.get("action") if isinstance(e, dict) else None
            if not isinstance(action, dict) or not isinstance(e.get("client"), str):
                self.problem("structure", f"malformed entry {e!r}", tick, "/actions")
            elif tick is not None and e.get("observed_tick") != tick - 1:
                self.problem("time", f"observed_tick {e.get('observed_tick')} is not tick - 1", tick, "/actions")
            elif self.meta is not None and action.get("agent") not in self.agents:
                self.problem("labels", f"action for {action.get('agent')!r}, not an agent of this episode", tick,
                             "/actions")

    def check_sensor(self, tick: int | None, topic: str, value: Any, live: set[int] | None) -> None:
        """Track references of one sensor message (LiDAR instance ids, instance pixels, visibility)."""
        found = topic_spec(topic)
        if found is None or live is None:
            return
        pattern = found[0].pattern
        refs: set[int] = set()
        if pattern == "/<agent>/<cam>/depth":
            self.check_depth(tick, topic, value)
        if pattern == "/<agent>/lidar":
            refs = self.point_tracks(tick, topic, value)
        elif pattern == "/<agent>/<cam>/instance" and self.pixels:
            refs = self.pixel_tracks(tick, topic, value)
        elif pattern == "/<agent>/visibility" and isinstance(value, dict):
            refs = set(_track_ids_in(value))
        elif pattern == "/events" and isinstance(value, dict):
            refs = {int(t) for e in value.get("events", []) if isinstance(e, dict)
                    for key in ("vehicle_track_ids", "obstacle_track_ids", "pedestrian_track_ids")
                    for t in e.get(key, [])}
        elif pattern == "/comm/links":
            self.check_links(tick, topic, value)
        dangling = sorted(refs - live)
        if dangling:
            self.problem(
                "labels",
                f"references tracks {dangling[:10]}{' ...' if len(dangling) > 10 else ''} "
                f"not in /labels/objects at this tick",
                tick,
                topic,
            )

    def check_links(self, tick: int | None, topic: str, value: Any) -> None:
        """``/comm/links``: decodable columns of one length, known values, every end a metadata agent."""
        try:
            links = decode_links(value)
        except FormatError as exc:
            self.problem("comm", str(exc), tick, topic)
            return
        unknown = sorted((set(links.tx) | set(links.rx)) - set(self.agents))
        if unknown:
            self.problem("comm", f"links name agents {unknown} not in the metadata's agents", tick, topic)
        self_links = [a for a, b in zip(links.tx, links.rx, strict=True) if a == b]
        if self_links:
            self.problem("comm", f"links from an agent to itself: {sorted(set(self_links))}", tick, topic)

    def point_tracks(self, tick: int | None, topic: str, msg: Any) -> set[int]:
        try:
            pc = PROTO_DECODERS["foxglove.PointCloud"](msg)
        except FormatError as exc:
            self.problem("structure", str(exc), tick, topic)
            return set()
        for p in layout_problems(pc.stored.dtype):
            self.problem("sensors", f"point record: {p} (section 3.4)", tick, topic)
        if "instance_id" not in pc.fields:
            return set()
        if self.fit:
            self.fit_points(tick, topic, pc)
        ids = np.unique(pc.points["instance_id"])
        return {int(i) for i in ids if 0 < i < STATIC_INSTANCE_MIN}

    def fit_points(self, tick: int | None, topic: str, pc: Any) -> None:
        """The boxes check of one sweep (:func:`cosim.io.validate_boxes.lidar_excess`); returns more than
        0.1 m outside are kept and judged at the end against the rig's range noise."""
        tree, agent = self.fit["tree"], topic.split("/")[1]
        try:
            lidar_to_map = tree.to_root(pc.frame_id)
            base_to_map = tree.to_root(f"{agent}/base_link")
        except FormatError:
            return  # reported by the transforms check
        velocity = next((a.get("velocity_mps", (0.0, 0.0, 0.0)) for a in self.fit["objects"].get("agents", [])
                         if isinstance(a, dict) and a.get("agent_id") == agent), (0.0, 0.0, 0.0))
        rates = self.fit["rates"].get(agent, (0.0, 0.0, 0.0))
        for tid, (excess, n_out, n) in lidar_excess(pc, lidar_to_map, base_to_map, velocity, rates,
                                                    self.fit["boxes"]).items():
            if n_out:
                self.lidar_fit.append((tick, topic, tid, excess, n_out, n))

    def check_depth(self, tick: int | None, topic: str, msg: Any) -> None:
        """Depth is ``cosim-depth`` or ``32FC1`` metres (only ``32FC1`` in format 1.1, ``16UC1`` millimetres in
        1.0): with pixels, every value is NaN (no hit) or a finite distance >= 0."""
        compressed = msg.DESCRIPTOR.full_name == "foxglove.CompressedImage"
        encoding = msg.format if compressed else getattr(msg, "encoding", None)
        allowed = DEPTH_ENCODINGS.get(self.format_minor(), DEPTH_ENCODINGS[None])
        if encoding not in allowed:
            self.problem("sensors", f"depth encoding {encoding!r}, expected {' or '.join(allowed)} (section 3.5)",
                         tick, topic)
            return
        if not self.pixels or encoding not in ("32FC1", "cosim-depth"):
            return
        try:
            a = PROTO_DECODERS[msg.DESCRIPTOR.full_name](msg).array
        except FormatError as exc:
            self.problem("structure", str(exc), tick, topic)
            return
        bad = int(np.count_nonzero(a < 0)) + int(np.count_nonzero(a == np.inf))  # NaN is neither
        if bad:
            self.problem("sensors", f"{bad} depth pixels are infinite or negative (no hit is NaN)", tick, topic)

    def format_minor(self) -> str | None:
        version = str((self.meta or {}).get("format_version", ""))
        return version if version in DEPTH_ENCODINGS else None

    def pixel_tracks(self, tick: int | None, topic: str, msg: Any) -> set[int]:
        name = msg.DESCRIPTOR.full_name
        try:
            img = PROTO_DECODERS[name](msg)
        except (FormatError, KeyError) as exc:
            self.problem("structure", str(exc), tick, topic)
            return set()
        extents = instance_ids(img.array)
        calib = self.fit_calibrations.get(topic[: -len("instance")] + "calibration") if self.fit else None
        if calib is not None:
            self.fit_pixels(tick, topic, extents, calib)
        return {int(i) for i in extents[0]}

    def fit_pixels(self, tick: int | None, topic: str, extents: tuple, calib: Any) -> None:
        """The boxes check of one instance image's :func:`cosim.io.validate_boxes.instance_ids`
        (:func:`cosim.io.validate_boxes.pixel_excess`)."""
        try:
            optical_to_map = self.fit["tree"].to_root(calib.frame_id)
            calibration = PROTO_DECODERS["foxglove.CameraCalibration"](calib)
            excess = pixel_excess(extents, calibration, optical_to_map, self.fit["boxes"])
        except FormatError:
            return  # reported by the transforms and calibration checks
        for tid, px in sorted(excess.items()):
            if px > PIXEL_TOLERANCE:
                self.problem("boxes", f"instance pixels of track {tid} reach {px:.1f} px outside its projected box "
                                      f"(tolerance {PIXEL_TOLERANCE} px)", tick, topic)

    def check_calibration(
        self, tick: int | None, topic: str, frame_id: str, size: tuple[int, int] | None, calib: Any
    ) -> None:
        if calib is None:
            self.problem("calibration", f"image without {topic[: -len('image')]}calibration on this tick", tick, topic)
            return
        if calib.frame_id != frame_id:
            self.problem(
                "calibration", f"image frame {frame_id!r} != calibration frame {calib.frame_id!r}", tick, topic
            )
        if size is not None and size != (calib.width, calib.height):
            self.problem(
                "calibration",
                f"image is {size[0]}x{size[1]}, calibration says {calib.width}x{calib.height}",
                tick,
                topic,
            )
        K, D = np.asarray(calib.K, np.float64), np.asarray(calib.D, np.float64)
        if not (K.size == 9 and np.isfinite(K).all() and K[0] > 0 and K[4] > 0):
            self.problem("calibration", f"intrinsics K = {K.tolist()} are not a pinhole camera's "
                         "(9 finite values, fx > 0, fy > 0)", tick, topic)
        if not np.isfinite(D).all():
            self.problem("calibration", f"lens D = {D.tolist()} is not finite", tick, topic)
        elif has_distortion(D) and (calib.distortion_model != "plumb_bob" or D.size != 5):
            self.problem("calibration", f"lens model {calib.distortion_model!r} with D = {D.tolist()}: a distorted "
                         "lens is plumb_bob with 5 coefficients (k1, k2, p1, p2, k3)", tick, topic)

    def check_chunk_index(self) -> None:
        """The summary's chunk index must point at the chunks really in the file (seeking readers use it)."""
        if not self.seen_footer:
            return
        indexed = {ci.chunk_start_offset: ci for ci in self.chunk_indexes}
        for offset, chunk in self.chunks.items():
            ci = indexed.get(offset)
            if ci is None:
                self.problem("structure", f"chunk at byte {offset} is missing from the summary's chunk index")
                continue
            fields = {
                "message_start_time": (ci.message_start_time, chunk.message_start_time),
                "message_end_time": (ci.message_end_time, chunk.message_end_time),
                "compressed_size": (ci.compressed_size, chunk.compressed_size),
                "uncompressed_size": (ci.uncompressed_size, chunk.uncompressed_size),
                "compression": (ci.compression, chunk.compression),
                "chunk_length": (ci.chunk_length, chunk.record_length),
                "message_index_length": (ci.message_index_length, self.chunk_message_index_bytes.get(offset, 0)),
            }
            bad = [f"{k} {a} != {b}" for k, (a, b) in fields.items() if a != b]
            pointed = {cid: self.message_indexes.get(off) for cid, off in ci.message_index_offsets.items()}
            wrong = sorted(cid for cid, found in pointed.items() if found != cid)
            if wrong:
                bad.append(f"message index offsets of channels {wrong} point at no index of that channel")
            if set(pointed) != self.chunk_channels.get(offset, set()):
                bad.append("message index offsets do not cover exactly the chunk's channels")
            if bad:
                self.problem(
                    "structure", f"chunk index entry for byte {offset} disagrees with the chunk: {'; '.join(bad)}"
                )
        for offset in sorted(set(indexed) - set(self.chunks)):
            self.problem("structure", f"chunk index points at byte {offset}, where no chunk starts")

    def scenario(self) -> Any:
        """The resolved scenario attachment as a Scenario, or None when absent or unreadable."""
        if self.scenario_yaml is None:
            return None
        try:
            import yaml

            from cosim.scenario.model import Scenario

            return Scenario.model_validate(yaml.safe_load(self.scenario_yaml))
        except Exception as exc:  # an old or foreign scenario: the rig checks are skipped, not failed
            log.info("scenario.yaml attachment not usable for rig checks: %s", exc)
            return None

    # -- whole file -------------------------------------------------------------------------------

    def finish_boxes(self) -> None:
        """Judge the LiDAR returns kept by :meth:`fit_points` against each rig's range noise (the scenario
        attachment; the default 2 cm when it is unusable)."""
        if not self.lidar_fit:
            return
        scenario = self.scenario()
        for tick, topic, tid, excess, n_out, n in self.lidar_fit:
            noise = 0.02
            if scenario is not None:
                try:
                    lidar = scenario.rig_for(topic.split("/")[1]).lidar
                    noise = lidar.range_noise_m if lidar is not None else noise
                except Exception:  # an agent the scenario does not name: the default noise
                    pass
            tol = LIDAR_TOLERANCE_M + NOISE_SIGMAS * noise
            if excess > tol:
                self.problem("boxes", f"{n_out} of {n} returns of track {tid} lie more than 0.1 m outside its box, "
                                      f"up to {excess:.2f} m (tolerance {tol:.2f} m)", tick, topic)

    def finish(self) -> None:
        r = self.report
        self.finish_boxes()
        if not self.seen_header:
            self.problem("structure", "no MCAP header")
        if not self.seen_data_end or not self.seen_footer:
            self.problem("structure", "file ends before the data-end/footer records: truncated or not finished")
        if self.meta is None:
            self.problem("metadata", "no 'episode' metadata record")
        missing = [a for a in REQUIRED_ATTACHMENTS if a not in self.attachments]
        if missing and self.seen_footer:
            self.problem("attachments", f"missing {', '.join(missing)}")
        self.check_chunk_index()
        if self.seen_footer:
            for kind, rid in sorted(self.data_ids - self.summary_ids):
                self.problem("structure", f"{kind} {rid} is missing from the summary section")
        if self.statistics is not None and self.seen_footer:
            st = self.statistics
            facts = {
                "message_count": (st.message_count, self.report.messages),
                "schema_count": (st.schema_count, len(self.schemas)),
                "channel_count": (st.channel_count, len(self.channels)),
                "attachment_count": (st.attachment_count, self.n_attachments),
                "metadata_count": (st.metadata_count, self.n_metadata),
                "chunk_count": (st.chunk_count, len(self.chunks)),
                "message_start_time": (st.message_start_time, self.min_time if self.report.messages else 0),
                "message_end_time": (st.message_end_time, max(self.last_time, 0)),
            }
            bad = [f"{k} {a} (file: {b})" for k, (a, b) in facts.items() if a != b]
            if bad:
                self.problem("structure", f"summary statistics disagree with the file: {'; '.join(bad)}")
            missing_counts = sorted(set(self.counts) - set(st.channel_message_counts))
            if missing_counts:
                self.problem("structure", f"summary statistics lack message counts of channels {missing_counts}")
            for cid, n in self.statistics.channel_message_counts.items():
                if self.counts.get(cid, 0) != n:
                    ch = self.channels.get(cid)
                    self.problem(
                        "structure",
                        f"summary counts {n} messages, the file holds {self.counts.get(cid, 0)}",
                        topic=ch.topic if ch else f"channel {cid}",
                    )
        topics = {ch.topic for ch in self.channels.values()}
        if self.meta is not None:
            for t in sorted(set(LABEL_TOPICS) - topics):
                self.problem("completeness", "topic missing from the file", topic=t)
            scenario = self.scenario()
            if scenario is not None and self.seen_footer:
                for t in sorted(expected_topics(scenario, self.agents) - topics - set(LABEL_TOPICS)):
                    self.problem("completeness", "topic missing from the file (the scenario's rig has it)", topic=t)
        r.topics = {t: len(self.topic_ticks.get(t, [])) for t in sorted(topics)}
        if self.n_ticks is None:
            return
        all_ticks = set(range(self.n_ticks))
        seen_ticks: set[int] = set()
        truncated = not self.seen_footer
        for topic in sorted(topics):
            ticks = self.topic_ticks.get(topic, [])
            seen_ticks.update(ticks)
            missing_ticks = all_ticks - set(ticks)
            if missing_ticks and not truncated:  # a truncated file's missing ticks are reported once, above
                self.problem(
                    "completeness",
                    f"no message on ticks {_ranges(missing_ticks)} ({len(missing_ticks)} of {self.n_ticks})",
                    topic=topic,
                )
        r.ticks = len(seen_ticks)


def _non_finite(value: Any, path: str) -> list[tuple[str, float]]:
    """(dotted path, value) of every NaN or infinity in decoded JSON (JSON parsers accept NaN and Infinity)."""
    if isinstance(value, float):
        return [] if math.isfinite(value) else [(path, value)]
    if isinstance(value, dict):
        return [hit for k, v in value.items() for hit in _non_finite(v, f"{path}.{k}")]
    if isinstance(value, list):
        return [hit for i, v in enumerate(value) for hit in _non_finite(v, f"{path}.{i}")]
    return []


def _chunk_records(chunk: Chunk) -> list[tuple[int, Any]]:
    """The records of a chunk with their byte offsets in its uncompressed data (CRC checked)."""
    stream, length = get_chunk_data_stream(chunk, validate_crc=True)
    out: list[tuple[int, Any]] = []
    while stream.count < length:
        offset = stream.count
        opcode = stream.read1()
        size = stream.read8()
        if opcode == Opcode.MESSAGE:
            out.append((offset, Message.read(stream, size)))
        elif opcode == Opcode.CHANNEL:
            out.append((offset, Channel.read(stream)))
        elif opcode == Opcode.SCHEMA:
            out.append((offset, Schema.read(stream)))
        else:
            stream.read(size)
    return out


def _image_size(msg: Any) -> tuple[int, int] | None:
    if msg.DESCRIPTOR.full_name == "foxglove.RawImage":
        return msg.width, msg.height
    try:
        import io

        from PIL import Image

        with Image.open(io.BytesIO(msg.data)) as im:
            return im.size
    except Exception:  # undecodable images are reported by the decode checks
        return None


def _track_ids_in(value: Any) -> Iterable[int]:
    """Every integer under a ``track_id`` key anywhere in a JSON value."""
    if isinstance(value, dict):
        for k, v in value.items():
            if k == "track_id" and isinstance(v, int):
                yield v
            else:
                yield from _track_ids_in(v)
    elif isinstance(value, list):
        for v in value:
            yield from _track_ids_in(v)


def validate_episode(path: str | Path, *, pixels: bool = True) -> ValidationReport:
    """Check one episode file; the report lists every problem found (empty = valid).

    ``pixels=False`` skips decoding instance masks (the slowest check). Raises
    :class:`~cosim.errors.InputError` only when ``path`` is not a file.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"no episode file at {path}")
    return _Validator(path, pixels).run()


def report_json(report: ValidationReport) -> str:
    return json.dumps(
        {
            "path": str(report.path),
            "ok": report.ok,
            "messages": report.messages,
            "ticks": report.ticks,
            "problems": [p.__dict__ for p in report.problems],
        },
        indent=2,
    )
