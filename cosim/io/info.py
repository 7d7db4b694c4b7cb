"""``cosim info``: what an episode holds, from its metadata, summary and indexes (``full`` counts every
family's bytes exactly and lists every topic), with the labels per class (``/labels/objects``) and the
drones' flown altitudes against their scenario's ``altitude_m`` (``/tf``), the two small topics it reads."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from cosim.io.format import topic_spec
from cosim.io.reader import Episode, open_episode

#: Topic pattern (docs/episode_format.md section 3) -> family shown by ``cosim info``.
FAMILIES: dict[str, str] = {
    "/tf": "tf", "/labels/objects": "labels", "/labels/boxes": "labels", "/<agent>/lidar": "lidar",
    "/<agent>/<cam>/image": "camera rgb", "/<agent>/<cam>/depth": "camera depth",
    "/<agent>/<cam>/semantic": "camera semantic", "/<agent>/<cam>/instance": "camera instance",
    "/<agent>/<cam>/calibration": "camera calibration", "/<agent>/gnss": "gnss", "/<agent>/imu": "imu",
    "/<agent>/bev": "bev", "/<agent>/visibility": "visibility",
}
BLOCK_BYTES = 4 * 1024 * 1024  # [bytes] the writer's chunk size: families are compressed in blocks of it
#: [m] a drone whose median flight z is farther than this from its scenario ``altitude_m`` is pointed out
ALTITUDE_NOTE_M = 10.0


@dataclass(frozen=True)
class ClassCount:
    """Labelled objects of one class in ``/labels/objects``: distinct track ids, and objects per tick (mean)."""

    tracks: int
    per_tick: float


@dataclass(frozen=True)
class DroneAltitude:
    """A drone's asked altitude (its scenario's ``altitude_m`` above the ground) against the z it flew (its
    ``base_link`` in the map frame, median over the ticks) [m]."""

    agent: str
    strategy: str
    asked_m: float
    flown_m: float

    @property
    def far(self) -> bool:
        return abs(self.flown_m - self.asked_m) > ALTITUDE_NOTE_M

    def note(self) -> str:
        """``drone_4 (escort) flies at 106 m, 61 m above its altitude_m 45``."""
        off = self.flown_m - self.asked_m
        return (f"{self.agent} ({self.strategy}) flies at {self.flown_m:.0f} m, {abs(off):.0f} m "
                f"{'above' if off > 0 else 'below'} its altitude_m {self.asked_m:g}")


@dataclass(frozen=True)
class TopicLine:
    topic: str
    schema_name: str
    messages: int
    rate_hz: float


@dataclass(frozen=True)
class FamilyBytes:
    """Bytes of one topic family: ``raw_bytes`` is the message payloads; ``stored_bytes`` its share of the
    file. Exact count (``cosim info --full``, :func:`family_bytes`): the payloads compressed as the file's
    chunks are (its compression, 4 MiB blocks) but without the other families. From the index (default,
    :func:`family_bytes_from_index`): each chunk's compressed size split by the families' shares of its
    uncompressed records. ``per_agent_frame`` = stored bytes / (agents x ticks)."""

    family: str
    messages: int
    raw_bytes: int
    stored_bytes: int
    per_agent_frame: float


@dataclass(frozen=True)
class EpisodeInfo:
    path: Path
    size_bytes: int
    format_version: str
    generator: str
    scenario: str
    description: str
    seed: int | None
    weather: str
    lighting: str
    environment: str
    strategies: list[str]
    tick_hz: float
    n_ticks: int
    duration_s: float
    agents: list[str]
    messages: int
    topics: list[TopicLine]
    attachments: list[str]
    geo_origin: list[float]
    families: list[FamilyBytes]
    families_exact: bool = False  # families counted from every message (else estimated from the index)
    objects: dict[str, ClassCount] = field(default_factory=dict)  # class -> counts, most tracks first
    drones: list[DroneAltitude] = field(default_factory=list)
    separation_m: float = 0.0  # the scenario's agents.drone_separation_m

    def as_dict(self) -> dict[str, Any]:
        d = dict(self.__dict__)
        d["path"] = str(self.path)
        d["topics"] = [t.__dict__ for t in self.topics]
        d["families"] = [f.__dict__ for f in self.families]
        d["objects"] = {k: asdict(v) for k, v in self.objects.items()}
        d["drones"] = [{**asdict(a), "far": a.far} for a in self.drones]
        return d


def topic_family(topic: str) -> str:
    found = topic_spec(topic)
    return FAMILIES.get(found[0].pattern, "other") if found else "other"


def _compressor(name: str):
    if name == "zstd":
        from cosim.io.writer import chunk_compress

        return chunk_compress
    if name == "lz4":
        import lz4.frame

        return lz4.frame.compress
    return bytes


def _compressed(ep: Episode, messages: Iterable[Any]) -> tuple[dict[str, int], dict[str, int], dict[str, int]]:
    """(payload bytes, messages, stored bytes) per family of ``messages``, each family compressed alone in
    blocks as the writer's chunks are."""
    compress = _compressor(ep.chunk_compression)
    raw: dict[str, int] = {}
    count: dict[str, int] = {}
    stored: dict[str, int] = {}
    pending: dict[str, list[bytes]] = {}
    pending_n: dict[str, int] = {}
    family_of: dict[str, str] = {t: topic_family(t) for t in ep.topics}

    def flush(fam: str) -> None:
        if pending.get(fam):
            stored[fam] = stored.get(fam, 0) + len(compress(b"".join(pending[fam])))
        pending[fam], pending_n[fam] = [], 0

    for m in messages:
        fam = family_of[m.topic]
        n = len(m.data)
        raw[fam] = raw.get(fam, 0) + n
        count[fam] = count.get(fam, 0) + 1
        pending.setdefault(fam, []).append(m.data)
        pending_n[fam] = pending_n.get(fam, 0) + n
        if pending_n[fam] >= BLOCK_BYTES:
            flush(fam)
    for fam in list(pending):
        flush(fam)
    return raw, count, stored


def family_bytes(ep: Episode) -> list[FamilyBytes]:
    """Bytes per topic family (see :class:`FamilyBytes`), largest first; reads every message once."""
    raw, count, stored = _compressed(ep, ep.messages())
    frames = max(1, len(ep.agents)) * max(1, ep.n_ticks)
    out = [FamilyBytes(f, count[f], raw[f], stored.get(f, 0), stored.get(f, 0) / frames) for f in raw]
    return sorted(out, key=lambda f: (-f.stored_bytes, f.family))


#: [bytes] of a message record besides its payload: opcode, length, channel, sequence, log and publish time.
MESSAGE_RECORD_OVERHEAD = 1 + 8 + 2 + 4 + 8 + 8


def family_bytes_from_index(ep: Episode) -> list[FamilyBytes]:
    """Bytes per topic family, largest first, without reading the file: payloads from the chunk and message
    indexes, stored bytes from each family's compression ratio in the middle tick (the one tick read)."""
    family_of: dict[str, str] = {t: topic_family(t) for t in ep.topics}
    records: dict[str, int] = {}
    chunk_raw = chunk_stored = 0
    for chunk, sizes in ep.message_sizes():
        chunk_raw += chunk.uncompressed_size
        chunk_stored += chunk.compressed_size
        for topic, n in sizes.items():
            fam = family_of.get(topic, "other")
            records[fam] = records.get(fam, 0) + n
    count: dict[str, int] = {}
    for topic, t in ep.topics.items():
        count[family_of[topic]] = count.get(family_of[topic], 0) + t.message_count
    t0 = ep.start_ns + (ep.n_ticks // 2) * ep.tick_ns
    sample_raw, _, sample_stored = _compressed(ep, ep.messages(start_ns=t0, end_ns=t0 + ep.tick_ns))
    overall = chunk_stored / chunk_raw if chunk_raw else 1.0
    frames = max(1, len(ep.agents)) * max(1, ep.n_ticks)
    out = []
    for f, n in records.items():
        payload = max(0, n - MESSAGE_RECORD_OVERHEAD * count.get(f, 0))
        ratio = sample_stored.get(f, 0) / sample_raw[f] if sample_raw.get(f) else overall
        out.append(FamilyBytes(f, count.get(f, 0), payload, round(payload * ratio), payload * ratio / frames))
    return sorted(out, key=lambda f: (-f.stored_bytes, f.family))


def labels_and_altitudes(ep: Episode) -> tuple[dict[str, ClassCount], list[DroneAltitude], float]:
    """Objects per class (``/labels/objects``), each drone's altitude (``/tf`` against the ``scenario.yaml``
    attachment) and the scenario's ``agents.drone_separation_m``; reads those two topics once."""
    import numpy as np
    import yaml

    agents = (yaml.safe_load(ep.attachment("scenario.yaml")) if "scenario.yaml" in ep.attachments else {}) or {}
    agents = agents.get("agents") or {}
    specs = {f"drone_{i}": d for i, d in enumerate(agents.get("drones") or [])}
    drones = [a for a in ep.agents if a in specs and "altitude_m" in specs[a]]
    tracks: dict[str, set[int]] = {}
    objects: dict[str, int] = {}
    z: dict[str, list[float]] = {a: [] for a in drones}
    ticks = 0
    topics = [t for t in ("/labels/objects", "/tf") if t in ep.topics]
    for tick in ep.ticks(topics=topics) if topics else ():
        if "/labels/objects" in tick:
            ticks += 1
            labels = tick.labels
            for cls, track in zip(labels.classes, labels.track_ids, strict=True):
                tracks.setdefault(cls, set()).add(int(track))
                objects[cls] = objects.get(cls, 0) + 1
        if drones and "/tf" in tick:
            tree = tick.transforms
            for a in drones:
                if f"{a}/base_link" in tree.frames:
                    z[a].append(float(tree.to_root(f"{a}/base_link")[2, 3]))
    counts = {c: ClassCount(len(t), objects[c] / ticks) for c, t in sorted(tracks.items(), key=lambda kv: -len(kv[1]))}
    flown = [DroneAltitude(a, str(specs[a].get("strategy", "?")), float(specs[a]["altitude_m"]),
                           float(np.median(z[a]))) for a in drones if z[a]]
    return counts, flown, float(agents.get("drone_separation_m") or 0.0)


def altitude_notes(drones: list[DroneAltitude], separation_m: float) -> list[str]:
    """One line per drone flying more than :data:`ALTITUDE_NOTE_M` from its ``altitude_m``, and why it may."""
    far = [d.note() for d in drones if d.far]
    if not far:
        return []
    return [*far, f"(layers keep drones whose ways can meet agents.drone_separation_m = {separation_m:g} m apart;",
            " drones also climb to clear the buildings below them by clearance_m)"]


def _seed(value: object) -> int | None:
    try:
        return int(str(value))
    except ValueError:
        return None


def episode_info(path: str | Path, *, bytes_per_family: bool = True, full: bool = False) -> EpisodeInfo:
    """Summary of one episode; raises InputError / FormatError like :func:`open_episode`.
    ``bytes_per_family``: estimate :class:`FamilyBytes` from the index (off: summary only); ``full``: count
    them exactly, reading every message (seconds per 100 MiB)."""
    path = Path(path)
    with open_episode(path) as ep:
        m = ep.metadata
        duration = ep.duration_s
        topics = [
            TopicLine(t.topic, t.schema_name, t.message_count, t.message_count / duration if duration else 0.0)
            for t in ep.topics.values()
        ]
        objects, drones, separation_m = labels_and_altitudes(ep)
        return EpisodeInfo(
            path=path,
            size_bytes=path.stat().st_size,
            format_version=ep.format_version,
            generator=str(m.get("generator", "")),
            scenario=ep.scenario,
            description=str(m.get("description", "")),
            seed=_seed(m.get("seed", "")),
            weather=str(m.get("weather", "")),
            lighting=str(m.get("lighting", "")),
            environment=str(m.get("environment", "")),
            strategies=list(m.get("strategies") or []),
            tick_hz=float(m.get("tick_hz", 0.0)),
            n_ticks=ep.n_ticks,
            duration_s=duration,
            agents=ep.agents,
            messages=ep.message_count,
            topics=topics,
            attachments=ep.attachments,
            geo_origin=list(m.get("geo_origin") or []),
            families=(family_bytes(ep) if full else family_bytes_from_index(ep)) if bytes_per_family else [],
            families_exact=bytes_per_family and full,
            objects=objects,
            drones=drones,
            separation_m=separation_m,
        )


def human_size(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{int(n)} B" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} GiB"


def format_info(info: EpisodeInfo, *, all_topics: bool = False) -> str:
    """The text of ``cosim info``: summary, bytes per family, then the topics collapsed per agent (every topic
    on its own line with ``all_topics``)."""
    kinds: dict[str, int] = {}
    for a in info.agents:
        kind = a.rsplit("_", 1)[0]
        kinds[kind] = kinds.get(kind, 0) + 1
    names = {"vehicle": ("vehicle", "vehicles"), "rsu": ("RSU", "RSUs"), "drone": ("drone", "drones")}
    agents = ", ".join(f"{n} {names.get(k, (k, k + 's'))[n != 1]}" for k, n in kinds.items()) or "none"
    seed = "?" if info.seed is None else info.seed
    lines = [
        f"episode      {info.path}",
        f"size         {human_size(info.size_bytes)} ({info.messages} messages)",
        f"format       {info.format_version} ({info.generator})",
        f"scenario     {info.scenario} (seed {seed})" + (f": {info.description}" if info.description else ""),
        f"conditions   {info.environment}, {info.weather}, {info.lighting}; drones: "
        f"{', '.join(info.strategies) or 'none'}",
        f"duration     {info.duration_s:g} s, {info.n_ticks} ticks at {info.tick_hz:g} Hz",
        f"agents       {agents}: {' '.join(info.agents)}",
        f"geo origin   {', '.join(f'{v:g}' for v in info.geo_origin)}",
        f"attachments  {', '.join(info.attachments) or 'none'}",
    ]
    if info.objects:
        lines.append(f"labels       {sum(n.tracks for n in info.objects.values())} tracks in "
                     f"{len(info.objects)} classes (/labels/objects)")
        lines.append(f"  {'class':<18}  {'tracks':>8}  {'per tick':>8}")
        lines.extend(f"  {c:<18}  {n.tracks:>8}  {n.per_tick:>8.1f}" for c, n in info.objects.items())
    for n, note in enumerate(altitude_notes(info.drones, info.separation_m)):
        lines.append(f"{'altitude' if n == 0 else '':<13}{note}")
    if info.families:
        total = sum(f.stored_bytes for f in info.families) or 1
        how = ("payloads; stored = compressed alone as the file's chunks are" if info.families_exact else
               "payloads from the file's index, stored as the middle tick compresses; --full counts exactly")
        lines.append(f"bytes by topic family ({how})")
        lines.append(f"  {'family':<18}  {'messages':>8}  {'payload':>10}  {'stored':>10}  {'share':>6}  "
                     f"{'per agent-frame':>15}")
        for f in info.families:
            lines.append(f"  {f.family:<18}  {f.messages:>8}  {human_size(f.raw_bytes):>10}  "
                         f"{human_size(f.stored_bytes):>10}  {100 * f.stored_bytes / total:5.1f}%  "
                         f"{human_size(f.per_agent_frame):>15}")
    if all_topics:
        lines.append(f"topics       {len(info.topics)}")
        width = max((len(t.topic) for t in info.topics), default=10)
        schema_w = max((len(t.schema_name) for t in info.topics), default=10)
        for t in info.topics:
            lines.append(f"  {t.topic:<{width}}  {t.schema_name:<{schema_w}}  {t.messages:>6} msgs  "
                         f"{t.rate_hz:6.2f} Hz")
    else:
        lines.append(f"topics       {len(info.topics)} (per agent; --full lists each)")
        lines.extend(f"  {line}" for line in collapse_topics(info.topics, info.agents))
    return "\n".join(lines)


def _rates(topics: list[TopicLine]) -> str:
    lo, hi = min(t.rate_hz for t in topics), max(t.rate_hz for t in topics)
    return f"{lo:g} Hz" if abs(hi - lo) < 1e-9 else f"{lo:g}-{hi:g} Hz"


def collapse_topics(topics: list[TopicLine], agents: list[str]) -> list[str]:
    """One line per agent (and one for the episode-wide topics): its data kinds, cameras and what each camera
    writes, topic and message counts and rates."""
    groups: dict[str, list[TopicLine]] = {}
    for t in topics:
        head = t.topic.split("/")[1] if t.topic.count("/") >= 2 else ""
        groups.setdefault(head if head in agents else "", []).append(t)
    width = max((len(a) for a in agents), default=7)
    width = max(width, len("episode"))
    out = []
    for owner in ["", *agents]:
        group = groups.get(owner)
        if not group:
            continue
        if owner:
            parts = [t.topic[len(owner) + 2:] for t in group]
            kinds = [p for p in parts if "/" not in p]
            cams: dict[str, list[str]] = {}
            for p in parts:
                if "/" in p:
                    cam, _, what = p.partition("/")
                    cams.setdefault(cam, []).append(what)
            outputs = sorted({tuple(v) for v in cams.values()})
            what = " ".join(kinds)
            if cams:
                each = " ".join(outputs[0]) if len(outputs) == 1 else "various"
                what += f"; {len(cams)} camera{'s' if len(cams) > 1 else ''} ({' '.join(cams)}) x {each}"
        else:
            what = " ".join(t.topic for t in group)
        msgs = sum(t.messages for t in group)
        out.append(f"{owner or 'episode':<{width}}  {len(group):>3} topics {msgs:>7} msgs  {_rates(group):>8}  {what}")
    return out
