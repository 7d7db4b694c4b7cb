"""``cosim comm EPISODE``: what the links of an episode were like, per link type, and two plots.

- the summary: per link type (and for the links with / without a drone end), the link-ticks
  counted (ordered links x ticks), the line-of-sight share (and NLOSv, NLOS), the median distance
  and SNR, and the delivery ratio of the configured message within one tick (mean of ``delivery``);
- ``comm_quality.png``: SNR over time of every unordered pair (one panel per link type, one line
  per pair, the grey band below the MCS's 50 % PER SNR);
- ``comm_map_t<tick>.png``: top view of one tick: the static layout, the agents and every link,
  coloured by SNR (dashed: NLOS, dotted: NLOSv).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cosim.comm.message import LINK_TYPES, TOPIC, LinkSet
from cosim.errors import InputError

log = logging.getLogger(__name__)


DRONE_END = "(any drone end)"
GROUND_ONLY = "(ground only)"


@dataclass(frozen=True)
class TypeSummary:
    """The links of one type over an episode (``link_ticks`` ordered links x ticks)."""

    link_type: str
    pairs: int
    link_ticks: int
    los_share: float
    nlosv_share: float
    nlos_share: float
    median_distance_m: float
    median_snr_db: float
    delivery_ratio: float


def read_links(ep: Any) -> list[LinkSet]:
    """Every tick's ``/comm/links`` of an open :class:`cosim.io.Episode`; InputError when it has none."""
    if TOPIC not in ep.topics:
        raise InputError(f"{ep.path} has no {TOPIC} topic (was it written with comm.enabled: false?)")
    return [t.links() for t in ep.ticks(TOPIC)]


def summarize(ticks: list[LinkSet]) -> list[TypeSummary]:
    """One :class:`TypeSummary` per link type present, in :data:`LINK_TYPES` order, then the links
    with a drone end (:data:`DRONE_END`) and those without (:data:`GROUND_ONLY`) together."""
    types = np.array([t for ls in ticks for t in ls.link_type])
    los = np.array([s for ls in ticks for s in ls.los])
    pairs = [frozenset((a, b)) for ls in ticks for a, b in zip(ls.tx, ls.rx, strict=True)]

    def col(name: str) -> np.ndarray:
        return np.concatenate([getattr(ls, name) for ls in ticks]) if ticks else np.zeros(0)

    snr, dist, delivery = col("snr_db"), col("distance_m"), col("delivery")

    def row(name: str, m: np.ndarray) -> TypeSummary:
        return TypeSummary(
            link_type=name,
            pairs=len({p for p, keep in zip(pairs, m, strict=True) if keep}),
            link_ticks=int(m.sum()),
            los_share=float(np.mean(los[m] == "los")),
            nlosv_share=float(np.mean(los[m] == "nlosv")),
            nlos_share=float(np.mean(los[m] == "nlos")),
            median_distance_m=float(np.median(dist[m])),
            median_snr_db=float(np.median(snr[m])),
            delivery_ratio=float(np.mean(delivery[m])),
        )

    out = [row(lt, types == lt) for lt in LINK_TYPES if np.any(types == lt)]
    drone_end = np.char.find(types.astype(str), "drone") >= 0 if len(types) else np.zeros(0, bool)
    for name, m in ((DRONE_END, drone_end), (GROUND_ONLY, ~drone_end)):
        if m.any():
            out.append(row(name, m))
    return out


def format_summary(rows: list[TypeSummary], n_ticks: int) -> str:
    head = (f"{'link type':<16} {'pairs':>5} {'link-ticks':>10} {'LOS':>6} {'NLOSv':>6} {'NLOS':>6} "
            f"{'med dist':>9} {'med SNR':>8} {'delivery':>8}")
    lines = [f"{n_ticks} ticks", head]
    for r in rows:
        lines.append(f"{r.link_type:<16} {r.pairs:>5} {r.link_ticks:>10} {r.los_share:>6.1%} {r.nlosv_share:>6.1%} "
                     f"{r.nlos_share:>6.1%} {r.median_distance_m:>7.1f} m {r.median_snr_db:>5.1f} dB "
                     f"{r.delivery_ratio:>8.1%}")
    return "\n".join(lines)


def summary_json(rows: list[TypeSummary]) -> list[dict[str, Any]]:
    return [asdict(r) for r in rows]


def plot_quality(ticks: list[LinkSet], tick_s: float, path: Path, snr50_db: float | None = None,
                 dpi: int = 80) -> Path:
    """SNR over time of every unordered pair, one panel per link type (see the module docstring)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cosim.io.render import _save

    series: dict[str, dict[tuple[str, str], list[tuple[float, float]]]] = {}
    for ls in ticks:
        t = ls.t_ns / 1e9
        for i, (a, b) in enumerate(zip(ls.tx, ls.rx, strict=True)):
            if a < b:
                series.setdefault(ls.link_type[i], {}).setdefault((a, b), []).append((t, float(ls.snr_db[i])))
    types = [lt for lt in LINK_TYPES if lt in series]
    fig, axes = plt.subplots(len(types), 1, figsize=(9, 2.2 * max(1, len(types))), sharex=True, squeeze=False)
    for ax, lt in zip(axes[:, 0], types, strict=True):
        for (a, b), pts in sorted(series[lt].items()):
            xs, ys = zip(*pts, strict=True)
            ax.plot(xs, ys, lw=1.0, label=f"{a}-{b}")
        if snr50_db is not None:
            ax.axhspan(-60, snr50_db, color="0.85", zorder=0)
        ax.set_ylim(-20, 70)
        ax.set_ylabel("SNR [dB]")
        ax.set_title(lt, fontsize=9, loc="left")
        if len(series[lt]) <= 8:
            ax.legend(fontsize=6, ncol=4, loc="upper right")
    axes[-1, 0].set_xlabel(f"time [s] (tick {tick_s:g} s)")
    fig.tight_layout()
    out = _save(fig, path, dpi)
    plt.close(fig)
    return out


def plot_map(ep: Any, ls: LinkSet, path: Path, dpi: int = 80) -> Path:
    """Top view of one tick: layout, agents, links coloured by SNR (see the module docstring)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection
    from matplotlib.patches import Polygon

    from cosim.io.render import AGENT_STYLE, _save, layout_polygons, place_agent_labels

    labels = ep.tick(ls.tick, "/labels/objects").labels
    pos = {a["agent_id"]: np.asarray(a["position_m"], np.float64) for a in labels.agents}
    kinds = {a["agent_id"]: a["kind"] for a in labels.agents}
    fig, ax = plt.subplots(figsize=(8, 7))
    for cls, fp in layout_polygons(ep):
        colour = {"building": "0.55", "road": "0.85"}.get(cls)
        if colour is not None:
            ax.add_patch(Polygon(fp, closed=True, facecolor=colour, edgecolor="none", zorder=0))
    segs, snr, style = [], [], []
    for i, (a, b) in enumerate(zip(ls.tx, ls.rx, strict=True)):
        if a < b and a in pos and b in pos:
            segs.append([pos[a][:2], pos[b][:2]])
            snr.append(float(ls.snr_db[i]))
            style.append({"los": "solid", "nlosv": "dotted", "nlos": "dashed"}[ls.los[i]])
    if segs:
        lc = LineCollection(segs, cmap="viridis", linestyles=style, linewidths=1.4, zorder=2)
        lc.set_array(np.asarray(snr))
        lc.set_clim(-10, 50)
        ax.add_collection(lc)
        fig.colorbar(lc, ax=ax, label="SNR [dB] (solid LOS, dotted NLOSv, dashed NLOS)", shrink=0.8)
    for agent, p in pos.items():
        marker, colour = AGENT_STYLE.get(kinds[agent], ("o", "k"))
        ax.scatter([p[0]], [p[1]], marker=marker, c=colour, s=50, edgecolors="k", zorder=3)
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.set_xlabel("x [m] (east)")
    ax.set_ylabel("y [m] (north)")
    ax.set_title(f"{ep.scenario}: links at tick {ls.tick} (t = {ls.t_ns / 1e9:g} s)", fontsize=9)
    fig.tight_layout()
    place_agent_labels(ax, [(f"{agent} ({p[2]:.0f} m)", p[0], p[1]) for agent, p in pos.items()], fontsize=6,
                       zorder=4)
    out = _save(fig, path, dpi)
    plt.close(fig)
    return out


def comm_report(path: Path, out_dir: Path | None, map_tick: int | None = None,
                dpi: int = 80) -> tuple[list[TypeSummary], int, list[Path]]:
    """Summary rows, tick count and the plots written to ``out_dir`` (none when it is None)."""
    from cosim.comm.phy import snr50_db
    from cosim.io.reader import open_episode

    with open_episode(path) as ep:
        ticks = read_links(ep)
        rows = summarize(ticks)
        written: list[Path] = []
        if out_dir is not None and ticks:
            k = len(ticks) // 2 if map_tick is None else map_tick
            if not 0 <= k < len(ticks):  # before the folder is made
                raise InputError(f"--tick {k} out of range: the episode has ticks 0..{len(ticks) - 1}")
            out_dir.mkdir(parents=True, exist_ok=True)
            threshold = None
            try:
                import yaml

                comm = (yaml.safe_load(ep.attachment("scenario.yaml")) or {}).get("comm") or {}
                threshold = snr50_db(comm.get("mcs", "qpsk_1_2"), float(comm.get("shannon_efficiency", 0.6)))
            except (KeyError, ValueError, TypeError) as exc:
                log.warning("no SNR threshold drawn: %s", exc)
            written.append(plot_quality(ticks, ep.tick_ns / 1e9, out_dir / "comm_quality.png", threshold, dpi))
            written.append(plot_map(ep, ticks[k], out_dir / f"comm_map_t{ticks[k].tick}.png", dpi))
        return rows, len(ticks), written
