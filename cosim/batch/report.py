"""``cosim report DIR``: the dataset statistics the AirV2X-Perception paper shows, for a batch folder.

Hours per split; shares of weather, lighting, environment (by driving time) and drone strategy (by
drone time); bytes on disk, frames and visible objects (mean per frame) per split and condition; objects per
class (unique track ids per episode, summed); agents per scene; throughput
per node (where each episode ran, from the manifest); the collaboration tables (``cosim coverage``'s, with its
``drones add`` / ``RSUs add``). Written as Markdown plus PNG plots (matplotlib, Agg backend).

The episode list comes from the manifest (last record per episode, status ``done``); each episode's
conditions come from its own ``episode`` metadata record and its objects from ``/labels/objects``.
"""

from __future__ import annotations

import json
import logging
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cosim.errors import FormatError, InputError
from cosim.io.manifest import latest_records

log = logging.getLogger(__name__)

OBJECTS_TOPIC = "/labels/objects"
CONDITIONS = ("weather", "lighting", "environment")
SPLIT_ORDER = ("train", "val", "validation", "test")


@dataclass(frozen=True)
class EpisodeStats:
    episode: str
    split: str
    duration_s: float
    weather: str
    lighting: str
    environment: str
    strategies: tuple[str, ...]
    agents: dict[str, int]  # kind (vehicle, rsu, drone) -> count
    objects: dict[str, int]  # class -> unique track ids
    size_bytes: int = 0  # the episode file on disk
    frames: int = 0  # ticks (``/labels/objects`` messages)
    visible: int = 0  # object-frames: per tick, objects seen by at least one agent (``/<agent>/visibility``)


@dataclass
class Report:
    md_path: Path
    images: list[Path] = field(default_factory=list)
    collaboration: str = ""  # the collaboration tables (Markdown), also the end of ``md_path``
    episodes: int = 0
    hours: float = 0.0
    stats: dict[str, Any] = field(default_factory=dict)


def episode_stats(path: Path, episode: str = "", split: str = "all", duration_s: float | None = None) -> EpisodeStats:
    """Read one episode's metadata and count unique track ids per class in ``/labels/objects``."""
    from mcap.reader import make_reader

    tracks: dict[str, set[int]] = defaultdict(set)
    seen: dict[int, set[int]] = defaultdict(set)  # log time -> track ids some agent sees
    frames = 0
    try:
        with open(path, "rb") as f:
            reader = make_reader(f)
            meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
            ep = meta.get("episode")
            if ep is None:
                raise FormatError(f"{path}: no 'episode' metadata record")
            names = json.loads(ep.get("agents", "[]"))
            for _schema, channel, message in reader.iter_messages(
                    topics=[OBJECTS_TOPIC, *(f"/{a}/visibility" for a in names)]):
                doc = json.loads(message.data)
                if channel.topic != OBJECTS_TOPIC:
                    seen[message.log_time].update(int(o["track_id"]) for o in doc.get("objects", []))
                    continue
                frames += 1
                for obj in doc.get("objects", []):
                    tracks[obj["class"]].add(int(obj["track_id"]))
        size = path.stat().st_size
    except (OSError, ValueError, KeyError) as exc:
        raise FormatError(f"{path}: cannot read episode statistics: {exc}") from exc
    agents = Counter(a.rsplit("_", 1)[0] for a in names)
    return EpisodeStats(
        episode=episode or path.stem, split=split,
        duration_s=float(duration_s if duration_s is not None else ep.get("duration_s", 0.0)),
        weather=ep.get("weather", "?"), lighting=ep.get("lighting", "?"), environment=ep.get("environment", "?"),
        strategies=tuple(json.loads(ep.get("strategies", "[]"))),
        agents={k: agents.get(k, 0) for k in ("vehicle", "rsu", "drone")},
        objects={k: len(v) for k, v in sorted(tracks.items())},
        size_bytes=size, frames=frames, visible=sum(len(v) for v in seen.values()),
    )


def collect(out_dir: Path) -> tuple[list[EpisodeStats], dict[str, int]]:
    """Stats of every finished episode in the manifest, and the manifest's status counts."""
    records = latest_records(out_dir)
    if not records:
        raise InputError(f"no manifest records in {out_dir} (expected manifest*.jsonl from `cosim batch`)")
    status = Counter(r.get("status", "?") for r in records.values())
    out = []
    for rec in records.values():
        if rec.get("status") != "done":
            continue
        path = Path(out_dir) / rec["file"]
        if not path.is_file():
            raise FormatError(f"{path}: listed as done in the manifest but missing")
        out.append(episode_stats(path, rec["episode"], rec.get("split", "all"), rec.get("duration_s")))
    return out, dict(status)


def node_label(record: dict[str, Any]) -> str:
    """The node an episode ran on: host, then the Ray node id and container id (shortened) when present."""
    parts = [str(record.get("host") or "?")]
    if record.get("node"):
        parts.append(f"ray:{str(record['node'])[:12]}")
    if record.get("container"):
        parts.append(f"container:{str(record['container'])[:12]}")
    return " ".join(parts)


def throughput(records: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Per node: ``episodes``, ``sim_s`` (driving time), ``busy_s`` (sum of episode wall times),
    ``span_s`` (first start to last finish) and ``sim_per_wall`` (sim_s / span_s: what the node added
    to the batch's speed, with all its workers)."""
    groups: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for rec in records:
        if rec.get("status") == "done":
            groups[node_label(rec)].append(rec)
    out = {}
    for label, recs in sorted(groups.items()):
        busy = sum(float(r.get("wall_time_s") or 0.0) for r in recs)
        ends = [float(r.get("time_unix") or 0.0) for r in recs]
        starts = [e - float(r.get("wall_time_s") or 0.0) for e, r in zip(ends, recs, strict=True)]
        span = max(ends) - min(starts)
        sim = sum(float(r.get("duration_s") or 0.0) for r in recs)
        out[label] = {"episodes": len(recs), "sim_s": sim, "busy_s": busy, "span_s": span,
                      "sim_per_wall": sim / span if span > 0 else 0.0}
    return out


def summarize(episodes: list[EpisodeStats]) -> dict[str, Any]:
    """The numbers of the report (also what the tests compare with the manifest)."""
    hours: Counter[str] = Counter()
    count: Counter[str] = Counter()
    shares: dict[str, Counter[str]] = {c: Counter() for c in (*CONDITIONS, "strategy")}
    objects: Counter[str] = Counter()
    agents_per_scene: Counter[int] = Counter()
    per_kind: dict[str, list[int]] = defaultdict(list)
    for e in episodes:
        h = e.duration_s / 3600.0
        hours[e.split] += h
        count[e.split] += 1
        for c in CONDITIONS:
            shares[c][getattr(e, c)] += h
        for s in e.strategies:
            shares["strategy"][s] += h  # drone-hours
        objects.update(e.objects)
        agents_per_scene[sum(e.agents.values())] += 1
        for k, n in e.agents.items():
            per_kind[k].append(n)
    order = sorted(hours, key=lambda s: (SPLIT_ORDER.index(s) if s in SPLIT_ORDER else len(SPLIT_ORDER), s))
    return {
        "episodes": len(episodes),
        "hours": sum(hours.values()),
        "hours_per_split": {s: hours[s] for s in order},
        "episodes_per_split": {s: count[s] for s in order},
        "shares": {c: _fractions(v) for c, v in shares.items()},
        "hours_by": {c: dict(v) for c, v in shares.items()},
        "objects_per_class": dict(sorted(objects.items(), key=lambda kv: -kv[1])),
        "agents_per_scene": dict(sorted(agents_per_scene.items())),
        "agents_per_kind": {k: (min(v), sum(v) / len(v), max(v)) for k, v in per_kind.items()},
        "size_per_split_condition": size_per_split_condition(episodes, order),
    }


def size_per_split_condition(episodes: list[EpisodeStats], split_order: list[str]) -> dict[str, dict[str, Any]]:
    """``"<split> <weather>/<lighting>/<environment>"`` -> episodes, bytes on disk, frames, visible
    object-frames (``visible``: summed over the ticks, the objects at least one agent sees) and their mean per
    frame (``visible_per_frame``), splits in ``split_order``."""
    out: dict[tuple[int, str, str], dict[str, Any]] = {}
    for e in episodes:
        cond = "/".join(getattr(e, c) for c in CONDITIONS)
        row = out.setdefault((split_order.index(e.split), e.split, cond),
                             {"split": e.split, "condition": cond, "episodes": 0, "bytes": 0, "frames": 0,
                              "visible": 0})
        row["episodes"] += 1
        row["bytes"] += e.size_bytes
        row["frames"] += e.frames
        row["visible"] += e.visible
    for row in out.values():
        row["visible_per_frame"] = row["visible"] / row["frames"] if row["frames"] else 0.0
    return {f"{split} {cond}": row for (_i, split, cond), row in sorted(out.items())}


def _fractions(c: Counter[str]) -> dict[str, float]:
    total = sum(c.values())
    return {k: v / total for k, v in sorted(c.items(), key=lambda kv: -kv[1])} if total else {}


# ------------------------------------------------------------------------------------- plots


def _plots(stats: dict[str, Any], img_dir: Path, prefix: str) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    img_dir.mkdir(parents=True, exist_ok=True)
    paths = []

    def save(fig: Any, name: str) -> None:
        path = img_dir / f"{prefix}{name}.png"
        fig.tight_layout()
        fig.savefig(path, dpi=90)
        plt.close(fig)
        paths.append(path)

    fig, ax = plt.subplots(figsize=(5, 3))
    splits = list(stats["hours_per_split"])
    vals = [stats["hours_per_split"][s] for s in splits]
    bars = ax.bar(splits, vals, color="#4c72b0")
    for b, s in zip(bars, splits, strict=True):
        ax.annotate(f"{stats['episodes_per_split'][s]} ep.", (b.get_x() + b.get_width() / 2, b.get_height()),
                    ha="center", va="bottom", fontsize=8)
    ax.set_ylabel("driving time [h]")
    ax.set_title(f"Hours per split ({stats['hours']:.3f} h, {stats['episodes']} episodes)")
    save(fig, "hours_per_split")

    fig, axes = plt.subplots(1, 4, figsize=(13, 3.2))
    titles = {"weather": "Weather", "lighting": "Lighting", "environment": "Environment",
              "strategy": "Drone strategy (drone time)"}
    for ax, (key, title) in zip(axes, titles.items(), strict=True):
        share = stats["shares"][key]
        if share:
            ax.pie(list(share.values()), labels=list(share), autopct="%1.0f%%", startangle=90,
                   textprops={"fontsize": 8})
        ax.set_title(title, fontsize=10)
    save(fig, "conditions")

    fig, ax = plt.subplots(figsize=(6, 3))
    objs = stats["objects_per_class"]
    ax.bar(list(objs), list(objs.values()), color="#55a868")
    ax.set_ylabel("unique objects (tracks)")
    ax.set_title("Objects per class")
    save(fig, "objects_per_class")

    fig, ax = plt.subplots(figsize=(5, 3))
    aps = stats["agents_per_scene"]
    ax.bar([str(k) for k in aps], list(aps.values()), color="#c44e52")
    ax.set_xlabel("connected agents per scene (vehicles + RSUs + drones)")
    ax.set_ylabel("episodes")
    ax.set_title("Agents per scene")
    save(fig, "agents_per_scene")
    return paths


# ---------------------------------------------------------------------------------- markdown


def _pct_table(title: str, share: dict[str, float], hours: dict[str, float], unit: str) -> list[str]:
    lines = [f"| {title} | {unit} | share |", "|---|---:|---:|"]
    lines += [f"| {k} | {hours[k]:.4f} | {v * 100:.1f} % |" for k, v in share.items()]
    return [*lines, ""]


def _markdown(stats: dict[str, Any], status: dict[str, int], images: list[Path], md_path: Path, name: str) -> str:
    import os

    out = [f"# Dataset report: {name}", ""]
    failed = status.get("failed", 0)
    unfinished = sum(v for k, v in status.items() if k not in ("done", "failed"))
    out += [f"{stats['episodes']} episodes, {stats['hours']:.4f} hours of driving "
            f"(manifest: {status.get('done', 0)} done, {failed} failed, {unfinished} unfinished).", ""]
    out += ["| split | episodes | hours |", "|---|---:|---:|"]
    for s, h in stats["hours_per_split"].items():
        out.append(f"| {s} | {stats['episodes_per_split'][s]} | {h:.4f} |")
    out.append("")
    out += ["| split | condition (weather/lighting/environment) | episodes | bytes on disk | frames | "
            "visible objects (per frame, seen by an agent) |", "|---|---|---:|---:|---:|---:|"]
    out += [f"| {r['split']} | {r['condition']} | {r['episodes']} | {r['bytes']:,} | {r['frames']} | "
            f"{r['visible_per_frame']:.1f} |" for r in stats["size_per_split_condition"].values()]
    out.append("")
    for key, title, unit in (("weather", "weather", "hours"), ("lighting", "lighting", "hours"),
                             ("environment", "environment", "hours"), ("strategy", "drone strategy", "drone-hours")):
        out += _pct_table(title, stats["shares"][key], stats["hours_by"][key], unit)
    out += ["| class | objects (unique tracks) |", "|---|---:|"]
    out += [f"| {k} | {v} |" for k, v in stats["objects_per_class"].items()]
    out += ["", "| agents per scene | episodes |", "|---:|---:|"]
    out += [f"| {k} | {v} |" for k, v in stats["agents_per_scene"].items()]
    out += ["", "| agent kind | min | mean | max |", "|---|---:|---:|---:|"]
    out += [f"| {k} | {lo} | {mean:.2f} | {hi} |" for k, (lo, mean, hi) in stats["agents_per_kind"].items()]
    out += ["", "| node | episodes | sim s | episode wall s | span s | sim s per wall s |",
            "|---|---:|---:|---:|---:|---:|"]
    out += [f"| {k} | {v['episodes']} | {v['sim_s']:.1f} | {v['busy_s']:.1f} | {v['span_s']:.1f} | "
            f"{v['sim_per_wall']:.3f} |" for k, v in stats["nodes"].items()]
    out.append("")
    for p in images:
        rel = os.path.relpath(p, md_path.parent)
        out.append(f"![{p.stem}]({rel})")
    out.append("")
    return "\n".join(out)


def collaboration_section(out_dir: Path) -> str:
    """The collaboration tables of the batch (cosim/eval/collaboration.py), overall and per condition, with
    ``drones add`` / ``RSUs add`` computed as ``cosim coverage`` does over the episodes with visibility topics
    (n/a where no episode of the row has them)."""
    from cosim.eval.collaboration import collaboration_tables, compute_collaboration
    from cosim.eval.coverage import compute_coverage, coverage_adds
    from cosim.eval.dataset import load_dataset
    from cosim.io import open_episode

    refs = load_dataset(out_dir)
    counts = compute_collaboration(refs)
    counts = {k: v for k, v in counts.items() if k[0] != "episode"}
    seen = []
    for ref in refs:
        with open_episode(ref.path) as ep:
            if all(f"/{a}/visibility" in ep.topics for a in ep.agents):
                seen.append(ref)
    adds = coverage_adds(compute_coverage(seen)) if seen else (None, None)
    return "\n## Collaboration\n\n" + "\n".join(t.markdown() for t in collaboration_tables(counts, *adds))


def build_report(out_dir: Path, *, md_path: Path | None = None, img_dir: Path | None = None,
                 img_prefix: str = "report_") -> Report:
    """Write ``report.md`` (default in ``out_dir``) and the plots; returns what was written."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise InputError(f"not a folder: {out_dir}")
    episodes, status = collect(out_dir)
    if not episodes:
        raise InputError(f"{out_dir}: the manifest lists no finished episode")
    stats = {**summarize(episodes), "nodes": throughput(list(latest_records(out_dir).values()))}
    md = Path(md_path) if md_path else out_dir / "report.md"
    images = _plots(stats, Path(img_dir) if img_dir else md.parent, img_prefix)
    md.parent.mkdir(parents=True, exist_ok=True)
    collaboration = collaboration_section(out_dir)
    md.write_text(_markdown(stats, status, images, md, out_dir.name) + collaboration)
    return Report(md_path=md, images=images, collaboration=collaboration, episodes=stats["episodes"],
                  hours=stats["hours"], stats=stats)
