"""Where strategies fly when the scenario does not say: hover points and patrol loops from the world.

Pure functions of the world (and an index), so every run picks the same places. Generated patrols
fly over lane centre lines (:func:`lane_paths`): around a block, around a junction, or, where the
roads form no loop of the right size (a highway), out along the road and back on the other
carriageway.
"""

from __future__ import annotations

import dataclasses
import heapq
import itertools
import math
import tempfile
from pathlib import Path

import numpy as np
import sumolib

from cosim.drones.strategies import polyline_points
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


def focus_junctions(world: World) -> list[Junction]:
    """:func:`ranked_junctions`, the cooperative group's junctions first (``world.group_junctions``, in the
    order the group meets them; dead ends left out)."""
    ranked = ranked_junctions(world)
    by_id = {j.junction_id: j for j in ranked}
    first = [by_id[i] for i in world.group_junctions if i in by_id and by_id[i].kind not in _MINOR_KINDS]
    return first + [j for j in ranked if j not in first]


def hover_point(world: World, k: int) -> np.ndarray:
    """(2,) map x, y [m] of the ``k``-th hover drone: the k-th ranked junction (wrapping), else the centre;
    in a cooperative world (``world.group_junctions``), the k-th of :func:`cover_points`."""
    if world.group_junctions:
        return cover_points(world, k + 1)[k]
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

    Centred on the k-th of :func:`focus_junctions` (a cooperative group's first). With a road ``graph``
    (:func:`road_graph`): around a city
    block at one of its corners (the k-th side first) whose perimeter is within 0.4 to 2.5 times
    the requested length and that is not in ``taken`` (vertex sets of loops other drones fly; the
    chosen one is added); otherwise around the junction itself, through one junction per
    45-degree sector at about the radius of a circle of that perimeter, joined along the roads;
    otherwise (fewer than 4 sectors filled: a highway, a country road) out along the road and back
    (:func:`out_and_back`). With ``lanes`` (:func:`lane_paths`) the way between junctions follows
    the lane centre lines. Without roads the ring's legs are straight; with fewer than 4 sectors
    filled, a square.
    """
    js = focus_junctions(world)
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


# ------------------------------------------------------------------ hover points where the ground sees least

OCCLUDERS = frozenset({"building", "vegetation"})  # prism classes that block a ground sensor's view
OCCLUDER_MIN_M = 2.0  # [m] lower prisms (hedges, crops) do not hide a vehicle from a sensor
GROUND_RANGE_M = 120.0  # [m] the paper's range of vehicles and RSUs
VIEWER_Z_M = 1.8  # [m] a vehicle's LiDAR over the road
TARGET_Z_M = 1.0  # [m] the middle of a car
FOCUS_JUNCTIONS = 4  # the group's first junctions whose surroundings hover drones watch ...
FOCUS_PATH_M = 300.0  # [m] ... as far as the group gets along them in an episode (about 20 s)
FOCUS_M = 100.0  # [m] road this close to a focus junction is watched
HOVER_SEES_M = 60.0  # [m] a hovering drone counts road within this horizontal distance as its own
HOVER_APART_M = 60.0  # [m] hover points stand at least this far apart
CELL_M = 2.0  # [m] raster cell of the occluder heights and the road surface
ROAD_CLEAR_M = 3.0  # [m] a hover point is this far off the road surface at least


def _height_raster(world: World) -> tuple[np.ndarray, float, float]:
    """(H, W) top [m] of the occluders (:data:`OCCLUDERS` at least :data:`OCCLUDER_MIN_M` tall) per
    :data:`CELL_M` cell over the world bounds, with the grid origin x0, y0."""
    from PIL import Image, ImageDraw

    x0, y0, x1, y1 = world.bounds_m
    w, h = math.ceil((x1 - x0) / CELL_M) + 1, math.ceil((y1 - y0) / CELL_M) + 1
    img = Image.new("F", (w, h), 0.0)
    draw = ImageDraw.Draw(img)
    tall = [p for p in world.layout.prisms if p.cls in OCCLUDERS and p.z1_m - world.layout.ground_z_m >= OCCLUDER_MIN_M]
    for p in sorted(tall, key=lambda p: p.z1_m):
        pix = [((x - x0) / CELL_M, (y - y0) / CELL_M) for x, y in p.footprint]
        if len(pix) >= 3:
            draw.polygon(pix, fill=float(p.z1_m - world.layout.ground_z_m))
    return np.asarray(img, dtype=np.float64), x0, y0


def _visible(viewers: np.ndarray, targets: np.ndarray, heights: np.ndarray, x0: float, y0: float) -> np.ndarray:
    """Bool (T,): whether any viewer (V, 3) within :data:`GROUND_RANGE_M` sees target (T, 3) over the
    occluder ``heights`` (sight line sampled every cell; its last 2 m, the target's own surroundings, not)."""
    seen = np.zeros(len(targets), dtype=bool)
    if not len(viewers) or not len(targets):
        return seen
    steps = np.arange(0.0, 1.0, 1.0 / (GROUND_RANGE_M / CELL_M))[1:]
    hh, ww = heights.shape
    for v in viewers:
        d = np.hypot(targets[:, 0] - v[0], targets[:, 1] - v[1])
        near = np.flatnonzero((d <= GROUND_RANGE_M) & ~seen)
        if not len(near):
            continue
        t = targets[near]
        pts = v[None, None, :] + (t[:, None, :] - v[None, None, :]) * steps[None, :, None]  # (N, S, 3)
        col = np.clip(((pts[..., 0] - x0) / CELL_M).astype(int), 0, ww - 1)
        row = np.clip(((pts[..., 1] - y0) / CELL_M).astype(int), 0, hh - 1)
        blocked = heights[row, col] > pts[..., 2]
        blocked &= (steps[None, :] * d[near, None]) < d[near, None] - 2.0
        seen[near[~blocked.any(axis=1)]] = True
    return seen


def _focus(world: World) -> list[tuple[float, float]]:
    """Positions of the group's first junctions: the first one, then the next while the way through
    them (straight legs) stays within :data:`FOCUS_PATH_M`, at most :data:`FOCUS_JUNCTIONS`."""
    by_id = {j.junction_id: j for j in world.junctions}
    out: list[tuple[float, float]] = []
    way = 0.0
    for i in world.group_junctions:
        if i not in by_id:
            continue
        p = by_id[i].position_m
        way += math.dist(out[-1], p) if out else 0.0
        if out and (way > FOCUS_PATH_M or len(out) >= FOCUS_JUNCTIONS):
            break
        out.append(p)
    return out


def cover_points(world: World, n: int) -> list[np.ndarray]:
    """``n`` hover points (2,) map x, y [m] for a cooperative world, where the ground sensors see least.

    The road near the group's first junctions (:func:`_focus`; lane centre lines within
    :data:`FOCUS_M` of them, every 5 m) is checked against the world's occluders (buildings and trees)
    for a line of sight from any ground sensor within :data:`GROUND_RANGE_M`: the RSU heads and vehicle
    LiDARs along the group's route. Candidate points (every 8 m within 80 m of those junctions, at least
    :data:`ROAD_CLEAR_M` off the road surface) are picked greedily: each next one covers the most road
    that no ground sensor and no point picked before sees within :data:`HOVER_SEES_M`, at least
    :data:`HOVER_APART_M` from the others; ties (as where the ground sees everything) go to the point
    nearest the group's first junction, so a drone is never sent away from the group for nothing."""
    from cosim.world.geom import Raster

    focus = np.array(_focus(world))
    if not len(focus):
        return [hover_point(dataclasses.replace(world, group_junctions=()), k) for k in range(n)]
    lanes = lane_paths(world.net_xml)
    road_pts = [polyline_points(xy) for xy in lanes.values()]
    road_xy = np.concatenate(road_pts) if road_pts else np.zeros((0, 2))
    d_focus = np.min(np.linalg.norm(road_xy[:, None, :] - focus[None], axis=2), axis=1) if len(road_xy) else np.zeros(0)
    watched = road_xy[d_focus <= FOCUS_M]
    gj = list(world.group_junctions)
    route_legs = [lanes[(a, b)] for a, b in itertools.pairwise(gj) if (a, b) in lanes]
    route_xy = np.concatenate([polyline_points(xy, 20.0) for xy in route_legs]) if route_legs else focus
    viewers = np.vstack([
        np.column_stack([route_xy, np.full(len(route_xy), VIEWER_Z_M)]),
        np.array([r.position_m for r in world.rsus], dtype=np.float64).reshape(-1, 3),
    ])
    heights, x0, y0 = _height_raster(world)
    seen = _visible(viewers, np.column_stack([watched, np.full(len(watched), TARGET_Z_M)]), heights, x0, y0)
    hidden = watched[~seen]
    road = Raster.empty(world.bounds_m, CELL_M).with_polygons(
        [np.array(p.footprint) for p in world.layout.prisms if p.cls == "road"]).dilated(ROAD_CLEAR_M)
    g = np.arange(-80.0, 80.01, 8.0)
    grid = (focus[:, None, None, :] + np.stack(np.meshgrid(g, g), axis=-1)[None]).reshape(-1, 2)
    grid = np.unique(np.round(grid, 3), axis=0)
    cand = grid[~road.lookup(grid)]
    if not len(cand):
        cand = focus.copy()
    to_first = np.linalg.norm(cand - focus[0], axis=1)
    covered = np.zeros(len(hidden), dtype=bool)
    chosen: list[np.ndarray] = []
    for _ in range(n):
        ok = np.ones(len(cand), dtype=bool)
        for c in chosen:
            ok &= np.linalg.norm(cand - c, axis=1) >= HOVER_APART_M
        if not ok.any():
            ok[:] = True
        gain = np.array([np.count_nonzero(~covered & (np.linalg.norm(hidden - c, axis=1) <= HOVER_SEES_M))
                         for c in cand]) if len(hidden) else np.zeros(len(cand))
        order = np.lexsort((cand[:, 1], cand[:, 0], to_first, -gain))
        best = next(int(i) for i in order if ok[i])
        chosen.append(cand[best].astype(np.float64))
        if len(hidden):
            covered |= np.linalg.norm(hidden - cand[best], axis=1) <= HOVER_SEES_M
    return chosen
