"""``cosim info``: what an episode holds, from its metadata and summary (no message is decoded)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cosim.io.reader import open_episode


@dataclass(frozen=True)
class TopicLine:
    topic: str
    schema_name: str
    messages: int
    rate_hz: float


@dataclass(frozen=True)
class EpisodeInfo:
    path: Path
    size_bytes: int
    format_version: str
    generator: str
    scenario: str
    description: str
    seed: str
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

    def as_dict(self) -> dict[str, Any]:
        d = dict(self.__dict__)
        d["path"] = str(self.path)
        d["topics"] = [t.__dict__ for t in self.topics]
        return d


def episode_info(path: str | Path) -> EpisodeInfo:
    """Summary of one episode; raises InputError / FormatError like :func:`open_episode`."""
    path = Path(path)
    with open_episode(path) as ep:
        m = ep.metadata
        duration = ep.duration_s
        topics = [
            TopicLine(t.topic, t.schema_name, t.message_count, t.message_count / duration if duration else 0.0)
            for t in ep.topics.values()
        ]
        return EpisodeInfo(
            path=path,
            size_bytes=path.stat().st_size,
            format_version=ep.format_version,
            generator=str(m.get("generator", "")),
            scenario=ep.scenario,
            description=str(m.get("description", "")),
            seed=str(m.get("seed", "")),
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
        )


def human_size(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{int(n)} B" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} GiB"


def format_info(info: EpisodeInfo) -> str:
    kinds: dict[str, int] = {}
    for a in info.agents:
        kind = a.rsplit("_", 1)[0]
        kinds[kind] = kinds.get(kind, 0) + 1
    names = {"vehicle": ("vehicle", "vehicles"), "rsu": ("RSU", "RSUs"), "drone": ("drone", "drones")}
    agents = ", ".join(f"{n} {names.get(k, (k, k + 's'))[n != 1]}" for k, n in kinds.items()) or "none"
    lines = [
        f"episode      {info.path}",
        f"size         {human_size(info.size_bytes)} ({info.messages} messages)",
        f"format       {info.format_version} ({info.generator})",
        f"scenario     {info.scenario} (seed {info.seed})" + (f": {info.description}" if info.description else ""),
        f"conditions   {info.environment}, {info.weather}, {info.lighting}; drones: "
        f"{', '.join(info.strategies) or 'none'}",
        f"duration     {info.duration_s:g} s, {info.n_ticks} ticks at {info.tick_hz:g} Hz",
        f"agents       {agents}: {' '.join(info.agents)}",
        f"geo origin   {', '.join(f'{v:g}' for v in info.geo_origin)}",
        f"attachments  {', '.join(info.attachments) or 'none'}",
        f"topics       {len(info.topics)}",
    ]
    width = max((len(t.topic) for t in info.topics), default=10)
    schema_w = max((len(t.schema_name) for t in info.topics), default=10)
    for t in info.topics:
        lines.append(f"  {t.topic:<{width}}  {t.schema_name:<{schema_w}}  {t.messages:>6} msgs  {t.rate_hz:6.2f} Hz")
    return "\n".join(lines)
