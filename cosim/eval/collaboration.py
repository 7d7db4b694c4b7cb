"""The collaboration report of ``cosim coverage`` and ``cosim report``: who is in range of the ego, and who
adds what (docs/evaluation.md, "Collaboration").

Per ego-tick (every vehicle agent at every tick), the collaborators in range are the other agents within the
paper's communication ranges of the ego (:data:`RANGE_M`: 120 m for vehicles and RSUs, 180 m for drones; 3D
distance between the agents' ``base_link`` frames). Shares of ego-ticks with at least 1 and at least 2 in
range are counted per agent kind and over all kinds. Where the episode has visibility topics (sensors on),
the objects of the scored classes in the ego's evaluation area are split into: seen by nobody, seen by the
ego, seen only by collaborators (some agent but not the ego), and seen only by drones (by a drone and by no
vehicle or RSU).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from cosim.eval.dataset import (
    CONDITIONS,
    DEFAULT_RULE,
    VEHICLE_CLASSES,
    EpisodeRef,
    VisibilityRule,
    agent_kind,
    iter_truth,
)
from cosim.eval.tables import Table
from cosim.io import open_episode

#: The paper's communication ranges per agent kind [m].
RANGE_M: dict[str, float] = {"vehicle": 120.0, "rsu": 120.0, "drone": 180.0}
KINDS: tuple[str, ...] = ("vehicle", "rsu", "drone", "any")
KIND_LABELS = {"vehicle": "vehicles", "rsu": "RSUs", "drone": "drones", "any": "any"}
OBJECT_SHARES: tuple[str, ...] = ("nobody", "ego", "only collaborators", "only drones")


@dataclass
class CollabCounts:
    ego_ticks: int = 0
    #: kind (and "any") -> [ego-ticks with >= 1, with >= 2 collaborators of that kind in range]
    in_range: dict[str, list[int]] = field(default_factory=lambda: {k: [0, 0] for k in KINDS})
    objects: int = 0  # objects in the ego's area over the ego-ticks with visibility
    seen: dict[str, int] = field(default_factory=lambda: dict.fromkeys(OBJECT_SHARES, 0))

    def share(self, kind: str, at_least: int) -> float:
        return 100.0 * self.in_range[kind][at_least - 1] / self.ego_ticks if self.ego_ticks else float("nan")

    def object_share(self, what: str) -> float:
        return 100.0 * self.seen[what] / self.objects if self.objects else float("nan")


def collaborators_in_range(ego: str, positions: dict[str, np.ndarray]) -> dict[str, int]:
    """Agents other than ``ego`` within :data:`RANGE_M` of it, counted per kind and in all (``any``);
    ``positions``: agent id -> (3,) map position [m]."""
    out = dict.fromkeys(KINDS, 0)
    p = positions[ego]
    for a, q in positions.items():
        kind = agent_kind(a)
        if a != ego and kind in RANGE_M and float(np.linalg.norm(q - p)) <= RANGE_M[kind]:
            out[kind] += 1
            out["any"] += 1
    return out


def object_split(seen_by_agent: dict[str, np.ndarray], ego: str, mask: np.ndarray) -> dict[str, int]:
    """Objects of ``mask`` (M,) seen by nobody, by ``ego``, only by other agents, only by drones
    (``seen_by_agent``: agent id -> (M,) bool)."""
    none = np.zeros(len(mask), bool)
    anyone, ground = none.copy(), none.copy()
    for a, v in seen_by_agent.items():
        anyone |= v
        if agent_kind(a) != "drone":
            ground |= v
    by_ego = seen_by_agent.get(ego, none)
    return {"nobody": int(np.count_nonzero(mask & ~anyone)), "ego": int(np.count_nonzero(mask & by_ego)),
            "only collaborators": int(np.count_nonzero(mask & anyone & ~by_ego)),
            "only drones": int(np.count_nonzero(mask & anyone & ~ground))}


def agent_positions(ref: EpisodeRef) -> dict[int, dict[str, np.ndarray]]:
    """Tick index -> agent id -> (3,) map position [m] of its ``base_link`` (labels-only episodes too)."""
    out: dict[int, dict[str, np.ndarray]] = {}
    with open_episode(ref.path) as ep:
        agents = ep.agents
        for tick in ep.ticks(topics=["/tf"]):
            frames = tick.transforms.frames
            out[tick.index] = {a: tick.transforms.to_root(f"{a}/base_link")[:3, 3].copy()
                               for a in agents if f"{a}/base_link" in frames}
    return out


def compute_collaboration(refs: Sequence[EpisodeRef], rule: VisibilityRule = DEFAULT_RULE,
                          classes: Sequence[str] = VEHICLE_CLASSES,
                          progress: Callable[[int, int], None] | None = None,
                          ) -> dict[tuple[str, str], CollabCounts]:
    """(breakdown, value) -> counts over every episode, tick and vehicle ego; ("overall", "all") first,
    then per condition (:data:`CONDITIONS`) and per episode (breakdown ``episode``)."""
    counts: dict[tuple[str, str], CollabCounts] = {("overall", "all"): CollabCounts()}
    wanted = set(classes)
    for n, ref in enumerate(refs):
        keys = [("overall", "all"), *((c, ref.conditions.get(c, "?")) for c in CONDITIONS), ("episode", ref.id)]
        for k in keys:
            counts.setdefault(k, CollabCounts())
        positions = agent_positions(ref)
        egos = [a for a in ref.agents if agent_kind(a) == "vehicle"]
        for tick in sorted(positions):
            for ego in egos:
                if ego not in positions[tick]:
                    continue
                near = collaborators_in_range(ego, positions[tick])
                for k in keys:
                    c = counts[k]
                    c.ego_ticks += 1
                    for kind in KINDS:
                        c.in_range[kind][0] += near[kind] >= 1
                        c.in_range[kind][1] += near[kind] >= 2
        for truth in iter_truth(ref, egos=egos, rule=rule):
            if truth.seen_by_agent is None:
                break
            mask = truth.in_area & np.array([c in wanted for c in truth.classes], bool)
            split = object_split(truth.seen_by_agent, truth.ego, mask)
            for k in keys:
                counts[k].objects += int(np.count_nonzero(mask))
                for what, v in split.items():
                    counts[k].seen[what] += v
        if progress:
            progress(n + 1, len(refs))
    return counts


def collaboration_tables(counts: dict[tuple[str, str], CollabCounts], drones_add: dict[tuple[str, str], float]
                         | None = None, rsus_add: dict[tuple[str, str], float] | None = None) -> list[Table]:
    """Two tables over the same rows (overall, per condition, per episode): collaborators in range, and
    who sees the objects (with ``drones add`` / ``RSUs add`` from the coverage counts where given)."""
    rng_cols = ["breakdown", "condition", "ego-ticks"] + [f"{KIND_LABELS[k]} >={n} (%)" for k in KINDS for n in (1, 2)]
    obj_cols = ["breakdown", "condition", "objects", *(f"{w} (%)" for w in OBJECT_SHARES), "drones add",
                "RSUs add"]
    order = ("overall", *CONDITIONS, "episode")
    keys = sorted(counts, key=lambda k: (order.index(k[0]) if k[0] in order else len(order), k[1]))
    rng_rows, obj_rows = [], []
    for k in keys:
        c = counts[k]
        rng_rows.append([k[0], k[1], c.ego_ticks, *(c.share(kind, n) for kind in KINDS for n in (1, 2))])
        obj_rows.append([k[0], k[1], c.objects, *(c.object_share(w) for w in OBJECT_SHARES),
                         (drones_add or {}).get(k, float("nan")), (rsus_add or {}).get(k, float("nan"))])
    ranges = ", ".join(f"{KIND_LABELS[k]} {v:.0f} m" for k, v in RANGE_M.items())
    return [
        Table("collaboration_range", "Collaborators in range of the ego", rng_cols, rng_rows,
              note=f"Share of ego-ticks (every vehicle agent at every tick) with at least 1 / 2 other agents of "
                   f"the kind within range ({ranges})."),
        Table("collaboration_objects", "Who sees the objects in the ego's evaluation area", obj_cols, obj_rows,
              note="Share of objects (in %) seen by no agent, by the ego, only by collaborators (not the ego), "
                   "only by drones (no vehicle or RSU); `drones add` and `RSUs add` as in the coverage table "
                   "(n/a: no visibility topics, or not computed for the row)."),
    ]
