"""Where strategies fly when the scenario does not say: hover points and patrol loops from the world.

Pure functions of the world (and an index), so every run picks the same places.
"""

from __future__ import annotations

import heapq
import math
import tempfile
from pathlib import Path

import numpy as np
import sumolib

from cosim.world.types import Junction, World

#: SUMO junction types a drone should not be sent to (not a real crossing).
_MINOR_KINDS = frozenset({"dead_end", "internal"})


def world_centre(world: World) -> np.ndarray:
    """(2,) centre of the world bounds [m]."""
    xmin, ymin, xmax, ymax = world.bounds_m
    return np.array([0.5 * (xmin + xmax), 0.5 * (ymin + ymax)])


def ranked_junctions(world: World) -> list[Junction]:
    """Real crossings first (not dead ends), then by distance to the world centre, then by id."""
    c = world_centre(world)

    def key(j: Junction) -> tuple[int, float, str]:
        d = math.hypot(j.position_m[0] - c[0], j.position_m[1] - c[1])
        return (1 if j.kind in _MINOR_KINDS else 0, round(d, 6), j.junction_id)

    return sorted(world.junctions, key=key)


def hover_point(world: World, k: int) -> np.ndarray:
    """(2,) map x, y [m] of the ``k``-th hover drone: the k-th ranked junction (wrapping), else the centre."""
    js = ranked_junctions(world)
    if not js:
        return world_centre(world)
    return np.array(js[k % len(js)].position_m, dtype=np.float64)


RoadGraph = dict[str, list[tuple[str, float]]]


def road_graph(net_xml: bytes) -> RoadGraph:
    """Junction adjacency of the network's drivable (passenger) edges, both directions, with lengths [m].

    Empty when the world carries no network. Read with sumolib from a temporary file.
    """
    if not net_xml.strip():
        return {}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "map.net.xml"
        path.write_bytes(net_xml)
        net = sumolib.net.readNet(str(path))
    links: dict[str, dict[str, float]] = {}
    for e in net.getEdges():
        if e.getFunction() == "internal" or not e.allows("passenger"):
            continue
        a, b = e.getFromNode().getID(), e.getToNode().getID()
        if a == b:
            continue
        for u, v in ((a, b), (b, a)):
            links.setdefault(u, {})
            links[u][v] = min(links[u].get(v, math.inf), e.getLength())
    return {a: sorted(adj.items()) for a, adj in sorted(links.items())}


def shortest_path(graph: RoadGraph, start: str, goal: str) -> list[str] | None:
    """Junction ids from ``start`` to ``goal`` along the roads (Dijkstra, ties broken by id), or None."""
    best = {start: 0.0}
    prev: dict[str, str] = {}
    heap = [(0.0, start)]
    while heap:
        d, node = heapq.heappop(heap)
        if node == goal:
            path = [goal]
            while path[-1] != start:
                path.append(prev[path[-1]])
            return path[::-1]
        if d > best.get(node, math.inf):
            continue
        for nxt, length in graph.get(node, ()):
            nd = d + length
            if nd < best.get(nxt, math.inf):
                best[nxt] = nd
                prev[nxt] = node
                heapq.heappush(heap, (nd, nxt))
    return None


def _drop_spikes(ids: list[str]) -> list[str]:
    """Remove repeats and out-and-back spikes (a, b, a -> a) from a closed junction sequence."""
    out: list[str] = []
    for j in ids:
        if len(out) >= 2 and out[-2] == j:
            out.pop()
        elif not out or out[-1] != j:
            out.append(j)
    while len(out) >= 3 and (out[0] == out[-1] or out[1] == out[-1]):
        out.pop() if out[0] == out[-1] else out.pop(0)
    return out


def _along_roads(ring: list[Junction], graph: RoadGraph, avoid: str) -> list[str]:
    """The ring's junctions joined by the shortest road paths between consecutive ones, not
    through ``avoid`` (the centre the ring goes around)."""
    detour = {a: [(b, d) for b, d in adj if b != avoid] for a, adj in graph.items() if a != avoid}
    ids: list[str] = []
    for a, b in zip(ring, ring[1:] + ring[:1], strict=True):
        leg = shortest_path(detour, a.junction_id, b.junction_id) or [a.junction_id, b.junction_id]
        ids.extend(leg[:-1])
    return _drop_spikes(ids)


def _inside(p: np.ndarray, poly: np.ndarray) -> bool:
    """Even-odd test of point ``p`` (2,) against polygon ``poly`` (N, 2)."""
    inside = False
    for (x0, y0), (x1, y1) in zip(poly, np.roll(poly, -1, axis=0), strict=True):
        if (y0 > p[1]) != (y1 > p[1]) and p[0] < x0 + (p[1] - y0) * (x1 - x0) / (y1 - y0):
            inside = not inside
    return inside


def _signed_area(xy: np.ndarray) -> float:
    x, y = xy[:, 0], xy[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def block_around(p: np.ndarray, pos: dict[str, tuple[float, float]], graph: RoadGraph) -> list[str] | None:
    """Junction ids around the city block (bounded face of the road graph, roads as straight
    segments) that contains the point ``p`` (2,), counter-clockwise; None when ``p`` lies outside
    the network."""
    best: tuple[float, str, str] | None = None
    for a, adj in graph.items():
        pa = np.asarray(pos[a])
        for b, _ in adj:
            if a >= b:
                continue
            pb = np.asarray(pos[b])
            ab = pb - pa
            u = float(np.clip(np.dot(p - pa, ab) / max(float(np.dot(ab, ab)), 1e-9), 0.0, 1.0))
            d = float(np.hypot(*(pa + u * ab - p)))
            if best is None or d < best[0]:
                best = (d, a, b)
    if best is None:
        return None
    _, a, b = best
    pa, pb = np.asarray(pos[a]), np.asarray(pos[b])
    if (pb - pa)[0] * (p - pa)[1] - (pb - pa)[1] * (p - pa)[0] < 0:
        a, b = b, a  # walk with the point on the left
    start, (u, v) = (a, b), (a, b)
    loop: list[str] = []
    for _ in range(4 * sum(len(adj) for adj in graph.values()) + 4):
        loop.append(u)
        pv = np.asarray(pos[v])
        back = math.atan2(pos[u][1] - pv[1], pos[u][0] - pv[0])
        # Keep the block on the left: take the first road clockwise from the way back.
        turns = []
        for w, _ in graph[v]:
            ang = math.atan2(pos[w][1] - pv[1], pos[w][0] - pv[0])
            rot = (back - ang) % (2.0 * math.pi)
            turns.append((rot if rot > 1e-9 else 2.0 * math.pi, w))
        u, v = v, min(turns)[1]
        if (u, v) == start:
            break
    else:
        return None
    xy = np.array([pos[j] for j in loop])
    if _signed_area(xy) <= 0.0 or not _inside(p, xy):  # the outer face: p is outside the network
        return None
    return _drop_spikes(loop)


def patrol_loop(
    world: World,
    k: int,
    loop_length_m: float,
    graph: RoadGraph | None = None,
    taken: set[frozenset[tuple[float, float]]] | None = None,
) -> np.ndarray:
    """(N, 2) closed patrol loop (last point not repeated) of about ``loop_length_m`` for patrol drone ``k``.

    Centred on the k-th ranked junction. With a road ``graph`` (:func:`road_graph`): around a city
    block at one of its corners (the k-th side first) whose perimeter is within 0.4 to 2.5 times
    the requested length and that is not in ``taken`` (vertex sets of loops other drones fly; the
    chosen one is added); otherwise around the junction itself, through one junction per
    45-degree sector at about the radius of a circle of that perimeter, joined along the roads.
    Without roads the ring's legs are straight; with fewer than 4 sectors filled, a square.
    """
    js = ranked_junctions(world)
    centre = np.array(js[k % len(js)].position_m) if js else world_centre(world)
    pos = {j.junction_id: j.position_m for j in world.junctions}
    roads = {a: [(b, d) for b, d in adj if b in pos] for a, adj in (graph or {}).items() if a in pos}
    if roads and js:
        for side in range(k, k + 4):  # the drone's side first, then the others
            ang = math.pi / 4.0 + math.pi / 2.0 * (side % 4)
            seed = centre + loop_length_m / 8.0 * math.sqrt(2.0) * np.array([math.cos(ang), math.sin(ang)])
            block = block_around(seed, pos, roads)
            if block is None or len(block) < 3:
                continue
            xy = np.array([pos[j] for j in block], dtype=np.float64)
            perimeter = float(np.sum(np.linalg.norm(np.roll(xy, -1, axis=0) - xy, axis=1)))
            key = frozenset(map(tuple, xy.tolist()))
            if 0.4 * loop_length_m <= perimeter <= 2.5 * loop_length_m and key not in (taken or ()):
                if taken is not None:
                    taken.add(key)
                return xy
    radius = loop_length_m / (2.0 * math.pi)
    picks: dict[int, tuple[float, Junction]] = {}
    for j in js:
        d = np.asarray(j.position_m, dtype=np.float64) - centre
        r = math.hypot(d[0], d[1])
        if not 0.5 * radius <= r <= 1.6 * radius or j.kind in _MINOR_KINDS:
            continue
        sector = int((math.atan2(d[1], d[0]) + math.pi) / (2 * math.pi) * 8) % 8
        score = abs(r - radius)
        if sector not in picks or score < picks[sector][0]:
            picks[sector] = (score, j)
    if len(picks) >= 4:
        ring = [picks[s][1] for s in sorted(picks)]
        if roads:
            ids = _along_roads(ring, roads, js[k % len(js)].junction_id)
            if len(ids) >= 3:
                return np.array([pos[j] for j in ids], dtype=np.float64)
        return np.array([j.position_m for j in ring], dtype=np.float64)
    half = loop_length_m / 8.0
    return centre + np.array([[-half, -half], [half, -half], [half, half], [-half, half]])
