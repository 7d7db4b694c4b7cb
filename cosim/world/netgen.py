"""Road networks per map kind, made with SUMO's own tools (netconvert, polyconvert).

Generated kinds (urban, suburban, rural, highway) write SUMO plain XML (nodes, edges) drawn from the
scenario's random generator and build the network with netconvert; kind ``net`` loads a user's
.net.xml, kind ``osm`` imports OpenStreetMap through netconvert (and building outlines through
polyconvert). A generator returns the network bytes and, for OSM, building footprints.

Registry: :data:`MAP_GENERATORS`, name -> function; :func:`generate_network` looks a kind up.
"""

from __future__ import annotations

import logging
import math
import os
import re
import signal
import subprocess
import sys
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import sumo

from cosim.errors import InputError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class NetworkResult:
    net_xml: bytes
    #: building outlines from OSM: footprint (N, 2) [m] and height [m] when the file tags one
    buildings: list[tuple[np.ndarray, float | None]] = field(default_factory=list)


@dataclass(frozen=True)
class MapRequest:
    kind: str
    size_m: float
    lanes: int | None
    file: Path | None
    workdir: Path
    #: pedestrian crossings at junctions (netconvert --crossings.guess); only when the scenario has
    #: pedestrians, so episodes without them keep their network bytes
    crossings: bool = False


Generator = Callable[[MapRequest, np.random.Generator], NetworkResult]
MAP_GENERATORS: dict[str, Generator] = {}


def register(name: str) -> Callable[[Generator], Generator]:
    def deco(fn: Generator) -> Generator:
        if name in MAP_GENERATORS:
            raise ValueError(f"map generator {name!r} registered twice")
        MAP_GENERATORS[name] = fn
        return fn

    return deco


def generate_network(req: MapRequest, rng: np.random.Generator) -> NetworkResult:
    try:
        gen = MAP_GENERATORS[req.kind]
    except KeyError:
        raise InputError(f"unknown map kind {req.kind!r}; known: {', '.join(sorted(MAP_GENERATORS))}") from None
    req.workdir.mkdir(parents=True, exist_ok=True)
    return gen(req, rng)


# ------------------------------------------------------------------------------------ tools


def sumo_binary(name: str) -> str:
    return str(Path(sumo.SUMO_HOME) / "bin" / name)


def _die_with_parent() -> Callable[[], None] | None:
    """A ``preexec_fn`` that makes the child SIGKILLed when the process that started it dies (Linux
    PR_SET_PDEATHSIG; a conductor killed while netconvert runs must not leave it behind); None elsewhere."""
    if not sys.platform.startswith("linux"):
        return None
    import ctypes

    try:
        prctl = ctypes.CDLL("libc.so.6", use_errno=True).prctl  # looked up before the fork, called after it
    except OSError:
        return None
    parent = os.getpid()

    def arm() -> None:
        prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG
        if os.getppid() != parent:  # the parent died before the signal was armed
            os._exit(1)

    return arm


def _run_tool(name: str, args: list[str], cwd: Path) -> None:
    env = {**os.environ, "SUMO_HOME": sumo.SUMO_HOME}
    proc = subprocess.run([sumo_binary(name), *args], cwd=cwd, env=env, capture_output=True, text=True, check=False,
                          preexec_fn=_die_with_parent())  # prctl only after the fork: no locks taken
    if proc.returncode != 0:
        msg = (proc.stderr or proc.stdout).strip().splitlines()
        raise InputError(f"{name} failed (exit {proc.returncode}): {' | '.join(msg[-5:])}")
    for line in proc.stderr.splitlines():
        if line.startswith("Warning") and "SUMO_HOME" not in line:
            log.debug("%s: %s", name, line)


_HEADER = re.compile(rb"<!--.*?-->\s*", re.S)


def strip_header(xml: bytes) -> bytes:
    """Remove SUMO's leading comment (it carries the wall-clock date and local paths)."""
    head, sep, rest = xml.partition(b"?>")
    if not sep:
        return _HEADER.sub(b"", xml, count=1)
    return head + sep + b"\n" + _HEADER.sub(b"", rest.lstrip(), count=1)


def _netconvert_plain(nodes: list[dict], edges: list[dict], req: MapRequest, extra: list[str]) -> bytes:
    root_n = ET.Element("nodes")
    for n in nodes:
        ET.SubElement(root_n, "node", {k: _fmt(v) for k, v in n.items()})
    root_e = ET.Element("edges")
    for e in edges:
        ET.SubElement(root_e, "edge", {k: _fmt(v) for k, v in e.items()})
    nod = req.workdir / f"{req.kind}.nod.xml"
    edg = req.workdir / f"{req.kind}.edg.xml"
    out = req.workdir / f"{req.kind}.net.xml"
    ET.ElementTree(root_n).write(nod)
    ET.ElementTree(root_e).write(edg)
    _run_tool(
        "netconvert",
        [
            "-n",
            nod.name,
            "-e",
            edg.name,
            "-o",
            out.name,
            "--offset.disable-normalization",
            "--no-turnarounds.except-deadend",
            "--junctions.corner-detail",
            "5",
            "--xml-validation",
            "never",
            *(["--crossings.guess", "true"] if req.crossings else []),
            *extra,
        ],
        req.workdir,
    )
    return strip_header(out.read_bytes())


def _fmt(v: object) -> str:
    if isinstance(v, float):
        return f"{v:.2f}"
    if isinstance(v, list):  # shape: list of (x, y)
        return " ".join(f"{x:.2f},{y:.2f}" for x, y in v)
    return str(v)


# ------------------------------------------------------------------------------- grid towns


def _grid_lines(size_m: float, block_m: float, rng: np.random.Generator, jitter: float) -> np.ndarray:
    n = max(2, round(size_m / block_m)) + 1
    xs = np.linspace(0.0, size_m, n)
    spacing = size_m / (n - 1)
    xs[1:-1] += rng.uniform(-jitter, jitter, n - 2) * spacing
    return xs


@dataclass(frozen=True)
class GridStyle:
    block_m: tuple[float, float]  # block side range [m]
    main_lanes: int
    minor_lanes: int
    main_speed_mps: float
    minor_speed_mps: float
    lane_width_m: float
    sidewalk_m: float
    drop_fraction: float  # share of interior street segments removed (irregular blocks)
    #: a junction of three or more roads gets traffic lights when at least this many main roads (avenues)
    #: pass through it; the others keep priority rules (the main road first, then the straighter pair)
    tls_mains: int
    minor_disallow: str  # vClasses kept off the minor streets (besides pedestrians, who use sidewalks)


ALL_RED_S = 2  # [s] all-red clearance interval after each yellow of a generated town's traffic lights
# urban: lights along the avenues, priority rules where two side streets cross (as towns sign them; a light at
# every crossing of the grid stopped 41-44 % of the traffic at once, single cars at reds: benchmarks/data_quality.py)
URBAN = GridStyle((75.0, 95.0), 3, 2, 13.89, 13.89, 3.2, 3.0, 0.0, 1, "")
# residential streets: no buses or lorries (they also could not turn in such narrow junctions)
SUBURBAN = GridStyle((100.0, 130.0), 2, 1, 13.89, 11.11, 3.3, 2.0, 0.2, 2, "bus truck")


def _grid_network(req: MapRequest, rng: np.random.Generator, style: GridStyle) -> NetworkResult:
    s = req.size_m
    block = rng.uniform(*style.block_m)
    xs = _grid_lines(s, block, rng, 0.12)
    ys = _grid_lines(s, block, rng, 0.12)
    nx, ny = len(xs), len(ys)
    main_lanes = req.lanes or style.main_lanes
    minor_lanes = max(1, main_lanes - (style.main_lanes - style.minor_lanes)) if req.lanes else style.minor_lanes

    # main roads: the interior lines nearest the middle (one per direction, two on large maps)
    def mains(n: int) -> set[int]:
        interior = list(range(1, n - 1)) or [0]
        k = 1 if n < 7 else 2
        centre = (n - 1) / 2
        return set(sorted(interior, key=lambda i: (abs(i - centre), i))[:k])

    main_x, main_y = mains(nx), mains(ny)

    # segments: ("v", i, j) joins (i, j)-(i, j+1); ("h", i, j) joins (i, j)-(i+1, j)
    segments = [("h", i, j) for j in range(ny) for i in range(nx - 1)] + [
        ("v", i, j) for i in range(nx) for j in range(ny - 1)
    ]

    def is_main(seg: tuple[str, int, int]) -> bool:
        d, i, j = seg
        if style.minor_disallow and ((d == "h" and j in (0, ny - 1)) or (d == "v" and i in (0, nx - 1))):
            return True  # where minor streets are restricted, the outer ring is a main road
        return (d == "h" and j in main_y) or (d == "v" and i in main_x)

    def is_perimeter(seg: tuple[str, int, int]) -> bool:
        d, i, j = seg
        return (d == "h" and j in (0, ny - 1)) or (d == "v" and i in (0, nx - 1))

    droppable = [g for g in segments if not is_main(g) and not is_perimeter(g)]
    n_drop = round(style.drop_fraction * len(droppable))
    keep = set(segments)
    for idx in rng.permutation(len(droppable)):
        if n_drop == 0:
            break
        seg = droppable[idx]
        trial = keep - {seg}
        if _connected(trial, nx, ny):
            keep = trial
            n_drop -= 1

    degree: dict[tuple[int, int], int] = {}
    for d, i, j in keep:
        a, b = ((i, j), (i + 1, j)) if d == "h" else ((i, j), (i, j + 1))
        degree[a] = degree.get(a, 0) + 1
        degree[b] = degree.get(b, 0) + 1
    nodes = []
    for (i, j), deg in sorted(degree.items()):
        on_main = (i in main_x) + (j in main_y)
        kind = "traffic_light" if deg >= 3 and on_main >= style.tls_mains else "priority"
        nodes.append({"id": f"n{i}_{j}", "x": float(xs[i]), "y": float(ys[j]), "type": kind})
    edges = []
    for seg in sorted(keep):
        d, i, j = seg
        a, b = (f"n{i}_{j}", f"n{i + 1}_{j}") if d == "h" else (f"n{i}_{j}", f"n{i}_{j + 1}")
        main = is_main(seg)
        attrs = {
            "numLanes": main_lanes if main else minor_lanes,
            "speed": style.main_speed_mps if main else style.minor_speed_mps,
            "priority": 3 if main else 1,
            "width": style.lane_width_m,
            "sidewalkWidth": style.sidewalk_m,
            "disallow": "pedestrian" if main or not style.minor_disallow else f"pedestrian {style.minor_disallow}",
        }
        edges.append({"id": f"{a}_{b}", "from": a, "to": b, **attrs})
        edges.append({"id": f"{b}_{a}", "from": b, "to": a, **attrs})
    # an all-red interval after each yellow lets a vehicle caught inside the junction clear it (left turners
    # waiting for a gap were passed by the next phase's turners within centimetres)
    tls = ["--tls.default-type", "static", "--tls.allred.time", str(ALL_RED_S)]
    return NetworkResult(_netconvert_plain(nodes, edges, req, tls))


def _connected(segments: set[tuple[str, int, int]], nx: int, ny: int) -> bool:
    adj: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for d, i, j in segments:
        a, b = ((i, j), (i + 1, j)) if d == "h" else ((i, j), (i, j + 1))
        adj.setdefault(a, []).append(b)
        adj.setdefault(b, []).append(a)
    if not adj:
        return False
    start = next(iter(adj))
    seen = {start}
    stack = [start]
    while stack:
        for m in adj[stack.pop()]:
            if m not in seen:
                seen.add(m)
                stack.append(m)
    return len(seen) == len(adj) and len(adj) == nx * ny


@register("urban")
def urban(req: MapRequest, rng: np.random.Generator) -> NetworkResult:
    """Dense grid of 75-95 m blocks, 3-lane avenues and 2-lane streets, traffic lights along the avenues,
    sidewalks."""
    return _grid_network(req, rng, URBAN)


@register("suburban")
def suburban(req: MapRequest, rng: np.random.Generator) -> NetworkResult:
    """Irregular grid of 100-130 m blocks, 2-lane main roads, 1-lane streets, few traffic lights."""
    return _grid_network(req, rng, SUBURBAN)


# ----------------------------------------------------------------------------- from files


@register("net")
def from_net_file(req: MapRequest, rng: np.random.Generator) -> NetworkResult:
    """A user's SUMO network, used as it is (the builder checks that vehicles can drive on it)."""
    if req.file is None:
        raise InputError(f"map.kind {req.kind!r} needs map.file")
    data = req.file.read_bytes()
    if b"<net" not in data[:4096]:
        raise InputError(f"map.file {req.file} is not a SUMO network (.net.xml): no <net> element at its start")
    return NetworkResult(data)


_POLY_TYPES = b"""<polygonTypes>
    <polygonType id="building" name="building" color="0.7,0.7,0.7" layer="1"/>
</polygonTypes>
"""


def _building_height(tags: dict[str, str]) -> float | None:
    """Height [m] from OSM ``height`` (metres, maybe with a unit) or ``building:levels`` (3 m a level)."""
    m = re.match(r"\s*([0-9]+(?:\.[0-9]+)?)", tags.get("height", ""))
    if m and float(m.group(1)) > 0:
        return float(m.group(1))
    m = re.match(r"\s*([0-9]+(?:\.[0-9]+)?)", tags.get("building:levels", ""))
    if m and float(m.group(1)) > 0:
        return 3.0 * float(m.group(1)) + 1.0
    return None


@register("osm")
def from_osm(req: MapRequest, rng: np.random.Generator) -> NetworkResult:
    """OpenStreetMap through netconvert (roads) and polyconvert (building outlines, when present)."""
    if req.file is None:
        raise InputError(f"map.kind {req.kind!r} needs map.file")
    head = req.file.read_bytes()[:4096]
    if b"<osm" not in head:
        raise InputError(f"map.file {req.file} is not an OpenStreetMap XML file: no <osm> element at its start")
    out = req.workdir / "osm.net.xml"
    _run_tool(
        "netconvert",
        [
            "--osm-files",
            str(req.file),
            "-o",
            out.name,
            "--geometry.remove",
            "--roundabouts.guess",
            "--ramps.guess",
            "--junctions.join",
            "--tls.guess-signals",
            "--tls.discard-simple",
            "--tls.join",
            "--no-turnarounds.except-deadend",
            "--remove-edges.isolated",
            "--sidewalks.guess",
            "--keep-edges.by-vclass",
            "passenger,bicycle,bus,truck,delivery,motorcycle,pedestrian",
            "--xml-validation",
            "never",
            *(["--crossings.guess", "true"] if req.crossings else []),
        ],
        req.workdir,
    )
    net_xml = strip_header(out.read_bytes())
    buildings: list[tuple[np.ndarray, float | None]] = []
    osm_text = req.file.read_bytes()
    if re.search(rb"""k=["']building["']""", osm_text):
        (req.workdir / "buildings.typ.xml").write_bytes(_POLY_TYPES)
        polys = req.workdir / "buildings.poly.xml"
        _run_tool(
            "polyconvert",
            [
                "--osm-files",
                str(req.file),
                "--net-file",
                out.name,
                "--type-file",
                "buildings.typ.xml",
                "-o",
                polys.name,
                "--all-attributes",
                "--xml-validation",
                "never",
            ],
            req.workdir,
        )
        for poly in ET.parse(polys).getroot().iter("poly"):
            if not poly.get("type", "").startswith("building"):
                continue
            pts = np.array([[float(v) for v in p.split(",")[:2]] for p in poly.get("shape", "").split()])
            if len(pts) >= 3:
                tags = {p.get("key"): p.get("value", "") for p in poly.iter("param")}
                buildings.append((pts, _building_height(tags)))
    log.info("OSM import: %d building outlines", len(buildings))
    return NetworkResult(net_xml, buildings)


# ------------------------------------------------------------------------------ countryside


def _arc(cx: float, cy: float, r: float, a0: float, a1: float, n: int) -> list[tuple[float, float]]:
    """Points strictly between angles a0 and a1 [rad] on a circle (edge shape without its end nodes)."""
    return [(cx + r * math.cos(a), cy + r * math.sin(a)) for a in np.linspace(a0, a1, n + 2)[1:-1]]


def _bezier(
    p0: tuple[float, float],
    d0: tuple[float, float],
    p1: tuple[float, float],
    d1: tuple[float, float],
    n: int = 8,
) -> list[tuple[float, float]]:
    """Inner points of a cubic Bezier from p0 (heading d0) to p1 (arriving with heading d1)."""
    k = 0.45 * math.dist(p0, p1)
    c0 = (p0[0] + k * d0[0], p0[1] + k * d0[1])
    c1 = (p1[0] - k * d1[0], p1[1] - k * d1[1])
    out = []
    for t in np.linspace(0, 1, n + 2)[1:-1]:
        u = 1 - t
        out.append(
            (
                u**3 * p0[0] + 3 * u * u * t * c0[0] + 3 * u * t * t * c1[0] + t**3 * p1[0],
                u**3 * p0[1] + 3 * u * u * t * c0[1] + 3 * u * t * t * c1[1] + t**3 * p1[1],
            )
        )
    return out


def _segment_intersection(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray) -> np.ndarray | None:
    """Crossing point of segments p0-p1 and q0-q1 away from their ends (20 %..80 %), or None."""
    d, e = p1 - p0, q1 - q0
    den = d[0] * e[1] - d[1] * e[0]
    if abs(den) < 1e-9:
        return None
    w = q0 - p0
    t = (w[0] * e[1] - w[1] * e[0]) / den
    u = (w[0] * d[1] - w[1] * d[0]) / den
    return p0 + t * d if 0.2 < t < 0.8 and 0.2 < u < 0.8 else None


def _two_way(edges: list[dict], a: str, b: str, shape: list[tuple[float, float]] | None, **attrs: object) -> None:
    fwd = {"id": f"{a}_{b}", "from": a, "to": b, **attrs}
    back = {"id": f"{b}_{a}", "from": b, "to": a, **attrs}
    if shape:
        fwd["shape"] = shape
        back["shape"] = shape[::-1]
    edges += [fwd, back]


@register("rural")
def rural(req: MapRequest, rng: np.random.Generator) -> NetworkResult:
    """A winding country-road loop with one or two cross roads: few junctions, long roads, 80 km/h."""
    s = req.size_m
    c = 0.5 * s
    lanes = req.lanes or 1
    k = int(rng.integers(5, 8))
    angles = np.sort(2 * math.pi * (np.arange(k) + rng.uniform(-0.25, 0.25, k)) / k + rng.uniform(0, 2 * math.pi))
    amp = rng.uniform(0.0, [0.06, 0.08, 0.04])
    phase = rng.uniform(0.0, 2 * math.pi, 3)

    def r_of(theta: np.ndarray | float) -> np.ndarray:
        """Smooth loop radius [m] (low harmonics only: no kinks at the junctions)."""
        wav = sum(amp[h] * np.cos((h + 1) * np.asarray(theta) - phase[h]) for h in range(3))
        return 0.36 * s * (1.0 + wav)

    radius = r_of(angles)
    nodes = [
        {
            "id": f"r{i}",
            "x": c + radius[i] * math.cos(angles[i]),
            "y": c + radius[i] * math.sin(angles[i]),
            "type": "priority",
        }
        for i in range(k)
    ]
    edges: list[dict] = []
    ring = {"numLanes": lanes, "speed": 22.22, "priority": 3, "width": 3.75, "disallow": "pedestrian"}
    for i in range(k):
        j = (i + 1) % k
        a0, a1 = angles[i], angles[j] + (2 * math.pi if j == 0 else 0.0)
        n = max(3, int((a1 - a0) * radius.mean() / 25.0))
        rr = r_of(np.linspace(a0, a1, n + 2)[1:-1])
        aa = np.linspace(a0, a1, n + 2)[1:-1]
        shape = [(c + r * math.cos(a), c + r * math.sin(a)) for r, a in zip(rr, aa, strict=True)]
        _two_way(edges, f"r{i}", f"r{j}", shape, **ring)
    # a straight cross road r0 - r(k//2); a second one crossing it near square on, when there is one
    cross = {"numLanes": lanes, "speed": 16.67, "priority": 2, "width": 3.75, "disallow": "pedestrian"}
    xy = np.array([[n["x"], n["y"]] for n in nodes])
    a0, a1 = 0, k // 2
    da = (xy[a1] - xy[a0]) / np.linalg.norm(xy[a1] - xy[a0])
    best = None
    for p in range(1, k // 2):
        for q in range(k // 2 + 1, k):
            db = (xy[q] - xy[p]) / np.linalg.norm(xy[q] - xy[p])
            cos = abs(float(np.dot(da, db)))
            hit = _segment_intersection(xy[a0], xy[a1], xy[p], xy[q])
            if hit is not None and cos < 0.35 and (best is None or cos < best[0]):
                best = (cos, p, q, hit)

    def square_on(i: int) -> list[tuple[float, float]]:
        """A shape point 25 m inside the loop along its inward normal at node i: T-junctions meet square on."""
        eps = 1e-3
        pa = np.array(
            [
                c + r_of(angles[i] - eps) * math.cos(angles[i] - eps),
                c + r_of(angles[i] - eps) * math.sin(angles[i] - eps),
            ]
        )
        pb = np.array(
            [
                c + r_of(angles[i] + eps) * math.cos(angles[i] + eps),
                c + r_of(angles[i] + eps) * math.sin(angles[i] + eps),
            ]
        )
        t = (pb - pa) / np.linalg.norm(pb - pa)
        inward = np.array([-t[1], t[0]])  # the loop runs counter-clockwise: left is inside
        q = xy[i] + 25.0 * inward
        return [(float(q[0]), float(q[1]))]

    if best is None:
        _two_way(edges, f"r{a1}", "r0", square_on(a1) + square_on(a0)[::-1], **cross)
    else:
        _, p, q, hit = best
        nodes.append({"id": "m", "x": float(hit[0]), "y": float(hit[1]), "type": "priority"})
        for end in (a0, a1, p, q):
            _two_way(edges, f"r{end}", "m", square_on(end), **cross)
    # generous corner radii: long vehicles turning at speed sweep less into the other lane
    return NetworkResult(_netconvert_plain(nodes, edges, req, ["--default.junctions.radius", "8"]))


@register("highway")
def highway(req: MapRequest, rng: np.random.Generator) -> NetworkResult:
    """A dual carriageway (3 lanes each way, 120 km/h) with a wide median, an exit and an entry ramp per
    direction to parallel local roads, and turning loops at both ends of the map so that traffic can stay."""
    s = req.size_m
    c = 0.5 * s + rng.uniform(-0.05, 0.05) * s
    lanes = req.lanes or 3
    lw = 3.6
    g = 0.5 * lanes * lw + 9.6  # carriageway centre line to the middle of the median [m]
    x_w, x_e = 0.02 * s + g, s - 0.02 * s - g
    x_d = 0.3 * s + rng.uniform(-0.03, 0.03) * s
    x_m = 0.7 * s + rng.uniform(-0.03, 0.03) * s
    dx = max(10.0, min(45.0, 0.15 * s, 0.5 * (x_m - x_d - 60.0)))  # ramp feet stay 60 m apart
    off = min(50.0, 0.2 * s)
    y_s, y_n = c - g - off, c + g + off
    east, west, north, south = (1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0)
    pts = {
        "we": (x_w, c - g),
        "de": (x_d, c - g),
        "me": (x_m, c - g),
        "ee": (x_e, c - g),
        "ew": (x_e, c + g),
        "dw": (x_m, c + g),
        "mw": (x_d, c + g),
        "ww": (x_w, c + g),
        "sa": (0.04 * s, y_s),
        "s1": (x_d + dx, y_s),
        "s2": (x_m - dx, y_s),
        "sb": (0.96 * s, y_s),
        "na": (0.04 * s, y_n),
        "n2": (x_d + dx, y_n),
        "n1": (x_m - dx, y_n),
        "nb": (0.96 * s, y_n),
    }
    nodes = [{"id": k, "x": x, "y": y, "type": "priority"} for k, (x, y) in pts.items()]
    motorway = {
        "numLanes": lanes,
        "speed": 33.33,
        "priority": 5,
        "width": lw,
        "spreadType": "center",
        "disallow": "pedestrian bicycle",
    }
    edges: list[dict] = []
    for a, b in (("we", "de"), ("de", "me"), ("me", "ee"), ("ew", "dw"), ("dw", "mw"), ("mw", "ww")):
        edges.append({"id": f"{a}_{b}", "from": a, "to": b, **motorway})
    # one wide lane through the tight turning loops: side by side, long vehicles would sweep into each other
    loop = {**motorway, "numLanes": 1, "width": 4.0, "speed": 11.0, "priority": 4}
    edges.append(
        {
            "id": "ee_ew",
            "from": "ee",
            "to": "ew",
            **loop,
            "shape": _arc(x_e, c, g, -math.pi / 2, math.pi / 2, 12),
        }
    )
    edges.append(
        {
            "id": "ww_we",
            "from": "ww",
            "to": "we",
            **loop,
            "shape": _arc(x_w, c, g, math.pi / 2, 1.5 * math.pi, 12),
        }
    )
    ramp = {
        "numLanes": 1,
        "speed": 16.67,
        "priority": 3,
        "width": lw,
        "spreadType": "center",
        "disallow": "pedestrian bicycle",
    }
    # ramps leave and join beside the outer lane (offset by half the carriageway plus half a ramp
    # lane), so that their lane never overlaps a carriageway lane
    side = 0.5 * lanes * lw + 0.5 * lw + 0.3
    for a, da, b, db in (
        ("de", east, "s1", south),
        ("s2", north, "me", east),
        ("dw", west, "n1", north),
        ("n2", south, "mw", west),
    ):
        if a in ("de", "dw"):  # exit: start beside the carriageway, 10 m past the diverge node
            right = (da[1], -da[0])
            start = (pts[a][0] + 10.0 * da[0] + side * right[0], pts[a][1] + 10.0 * da[1] + side * right[1])
            shape = [start, *_bezier(start, da, pts[b], db)]
        else:  # entry: end beside the carriageway, 10 m before the merge node
            right = (db[1], -db[0])
            end = (pts[b][0] - 10.0 * db[0] + side * right[0], pts[b][1] - 10.0 * db[1] + side * right[1])
            shape = [*_bezier(pts[a], da, end, db), end]
        edges.append({"id": f"{a}_{b}", "from": a, "to": b, **ramp, "shape": shape})
    local = {"numLanes": 1, "speed": 13.89, "priority": 1, "width": 3.75, "disallow": "pedestrian"}
    for a, b in (("sa", "s1"), ("s1", "s2"), ("s2", "sb"), ("na", "n2"), ("n2", "n1"), ("n1", "nb")):
        _two_way(edges, a, b, None, **local)
    # no guessed acceleration lanes: on a centred carriageway an added lane shifts every lane sideways at its
    # end; the ramps join beside the outer lane instead
    ramps = ["--default.junctions.radius", "8"]
    return NetworkResult(_netconvert_plain(nodes, edges, req, ramps))
