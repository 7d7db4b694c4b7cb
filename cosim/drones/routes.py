"""Where strategies fly when the scenario does not say: hover points and patrol loops from the world.

Pure functions of the world (and an index), so every run picks the same places. Generated patrols
fly over lane centre lines (:func:`lane_paths`): around a block, around a junction, or, where the
roads form no loop of the right size (a highway), out along the road and back on the other
carriageway.
"""

from __future__ import annotations

import heapq
import itertools
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
#: (from junction, to junction) -> (N, 2) map x, y [m] of a lane centre line from one to the other
LanePaths = dict[tuple[str, str], np.ndarray]


def _drivable_edges(net_xml: bytes) -> list:
    """The network's non-internal edges that passenger cars may use, by id; none without a network."""
    if not net_xml.strip():
        return []
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "map.net.xml"
        path.write_bytes(net_xml)
        net = sumolib.net.readNet(str(path))
    edges = [e for e in net.getEdges() if e.getFunction() != "internal" and e.allows("passenger")]
    return sorted(edges, key=lambda e: e.getID())


def lane_paths(net_xml: bytes) -> LanePaths:
    """For every drivable edge between two junctions, the centre line of its middle lane (the shortest
    edge where two join the same junctions). Empty when the world carries no network."""
    out: dict[tuple[str, str], tuple[float, np.ndarray]] = {}
    for e in _drivable_edges(net_xml):
        a, b = e.getFromNode().getID(), e.getToNode().getID()
        lanes = e.getLanes()
        shape = np.array(lanes[(len(lanes) - 1) // 2].getShape(), dtype=np.float64)[:, :2]
        if a != b and ((a, b) not in out or e.getLength() < out[(a, b)][0]):
            out[(a, b)] = (e.getLength(), shape)
    return {k: v[1] for k, v in out.items()}


def road_graph(net_xml: bytes) -> RoadGraph:
    """Junction adjacency of the network's drivable (passenger) edges, both directions, with lengths [m].

    Empty when the world carries no network. Read with sumolib from a temporary file.
    """
    links: dict[str, dict[str, float]] = {}
    for e in _drivable_edges(net_xml):
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


def _simplify(xy: np.ndarray, tol_m: float) -> np.ndarray:
    """Douglas-Peucker: the points of the open polyline ``xy`` (N, 2) needed to stay within ``tol_m``."""
    if len(xy) <= 2:
        return xy
    a, b = xy[0], xy[-1]
    ab = b - a
    n = float(np.hypot(ab[0], ab[1]))
    rel = xy[1:-1] - a
    d = np.abs(ab[0] * rel[:, 1] - ab[1] * rel[:, 0]) / n if n > 1e-9 else np.hypot(rel[:, 0], rel[:, 1])
    i = int(np.argmax(d))
    if d[i] <= tol_m:
        return np.array([a, b])
    return np.vstack([_simplify(xy[: i + 2], tol_m)[:-1], _simplify(xy[i + 1 :], tol_m)])


def lane_polyline(ids: list[str], lanes: LanePaths, pos: dict[str, tuple[float, float]], closed: bool) -> np.ndarray:
    """(N, 2) the way through junctions ``ids`` over lane centre lines (the lane from a to b, else the
    lane from b to a backwards, else the straight line), repeated points dropped, simplified to 0.5 m;
    ``closed``: back to the first junction too (the closing point not repeated)."""
    legs = list(zip(ids, ids[1:] + ids[:1], strict=True)) if closed else list(itertools.pairwise(ids))
    parts = []
    for a, b in legs:
        if (a, b) in lanes:
            parts.append(lanes[(a, b)])
        elif (b, a) in lanes:
            parts.append(lanes[(b, a)][::-1])
        else:
            parts.append(np.array([pos[a], pos[b]], dtype=np.float64))
    xy = np.concatenate(parts) if parts else np.zeros((0, 2))
    keep = [0] + [i for i in range(1, len(xy)) if np.hypot(*(xy[i] - xy[i - 1])) > 0.5]
    xy = xy[keep]
    if closed:
        if len(xy) > 1 and np.hypot(*(xy[-1] - xy[0])) <= 0.5:
            xy = xy[:-1]
        return _simplify(np.vstack([xy, xy[:1]]), 0.5)[:-1]
    return _simplify(xy, 0.5)


def _cut(xy: np.ndarray, length_m: float) -> np.ndarray:
    """The first ``length_m`` of the open polyline ``xy`` (N, 2)."""
    seg = np.hypot(*np.diff(xy, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= length_m:
        return xy
    i = int(np.searchsorted(s, length_m, side="right")) - 1
    u = (length_m - s[i]) / max(seg[i], 1e-9)
    return np.vstack([xy[: i + 1], xy[i] + u * (xy[i + 1] - xy[i])])


def out_and_back(
    start: str, graph: RoadGraph, lanes: LanePaths, pos: dict[str, tuple[float, float]], loop_length_m: float
) -> np.ndarray | None:
    """(N, 2) a patrol along the road from junction ``start`` for half of ``loop_length_m`` and back on
    the lanes of the other direction (the other carriageway): toward the junction whose road distance
    is nearest to half the length (ties by id), cut there. None when no road leaves ``start``."""
    half = 0.5 * loop_length_m
    best: tuple[float, str] | None = None
    for goal in sorted(graph):
        if goal == start:
            continue
        path = shortest_path(graph, start, goal)
        if path is None:
            continue
        d = sum(dict(graph[a])[b] for a, b in itertools.pairwise(path))
        if best is None or abs(d - half) < best[0]:
            best = (abs(d - half), goal)
    if best is None:
        return None
    ids = shortest_path(graph, start, best[1]) or []
    out = _cut(lane_polyline(ids, lanes, pos, closed=False), half)
    back = lane_polyline(ids[::-1], lanes, pos, closed=False)
    back_len = float(np.sum(np.hypot(*np.diff(back, axis=0).T)))
    back = _cut(back[::-1], min(half, back_len))[::-1]  # its last ``half`` metres, ending at the start
    xy = np.vstack([out, back])
    keep = [0] + [i for i in range(1, len(xy)) if np.hypot(*(xy[i] - xy[i - 1])) > 0.5]
    return xy[keep]


def patrol_loop(
    world: World,
    k: int,
    loop_length_m: float,
    graph: RoadGraph | None = None,
    taken: set[frozenset[tuple[float, float]]] | None = None,
    lanes: LanePaths | None = None,
) -> np.ndarray:
    """(N, 2) closed patrol loop (last point not repeated) of about ``loop_length_m`` for patrol drone ``k``.

    Centred on the k-th ranked junction. With a road ``graph`` (:func:`road_graph`): around a city
    block at one of its corners (the k-th side first) whose perimeter is within 0.4 to 2.5 times
    the requested length and that is not in ``taken`` (vertex sets of loops other drones fly; the
    chosen one is added); otherwise around the junction itself, through one junction per
    45-degree sector at about the radius of a circle of that perimeter, joined along the roads;
    otherwise (fewer than 4 sectors filled: a highway, a country road) out along the road and back
    (:func:`out_and_back`). With ``lanes`` (:func:`lane_paths`) the way between junctions follows
    the lane centre lines. Without roads the ring's legs are straight; with fewer than 4 sectors
    filled, a square.
    """
    js = ranked_junctions(world)
    centre = np.array(js[k % len(js)].position_m) if js else world_centre(world)
    pos = {j.junction_id: j.position_m for j in world.junctions}
    roads = {a: [(b, d) for b, d in adj if b in pos] for a, adj in (graph or {}).items() if a in pos}
    lanes = lanes or {}
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
                return lane_polyline(block, lanes, pos, closed=True)
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
                return lane_polyline(ids, lanes, pos, closed=True)
        else:
            return np.array([j.position_m for j in ring], dtype=np.float64)
    if roads and js:
        xy = out_and_back(js[k % len(js)].junction_id, roads, lanes, pos, loop_length_m)
        if xy is not None and len(xy) >= 2:
            return xy
    half = loop_length_m / 8.0
    return centre + np.array([[-half, -half], [half, -half], [half, half], [-half, half]])
