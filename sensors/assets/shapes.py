"""Closed low-poly primitives the procedural assets are made of, and a builder that collects them.

Every primitive is a closed, outward-wound triangle mesh (a *part*), so a model's volume is the union
of its parts and a ray cast from inside a part always meets that part's surface. Parts carry a
material id (``PART_*`` of :mod:`cosim.sensors.meshes`) and convex-face groups for adaptive casting.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class Builder:
    """Accumulates closed parts: vertices, triangles, material part id and face group per triangle."""

    verts: list[np.ndarray] = field(default_factory=list)
    tris: list[np.ndarray] = field(default_factory=list)
    parts: list[np.ndarray] = field(default_factory=list)
    groups: list[np.ndarray] = field(default_factory=list)
    component: list[np.ndarray] = field(default_factory=list)
    _nv: int = 0
    _ng: int = 0
    _nc: int = 0

    def add(self, v: np.ndarray, t: np.ndarray, part, group: np.ndarray | None = None) -> None:
        """Add one closed part; ``part`` is one id or one per triangle; ``group`` per triangle (default:
        each triangle its own)."""
        t = np.asarray(t, np.int64).reshape(-1, 3)
        g = np.arange(len(t), dtype=np.int64) if group is None else np.asarray(group, np.int64)
        self.verts.append(np.asarray(v, np.float64).reshape(-1, 3))
        self.tris.append(t + self._nv)
        self.parts.append(np.broadcast_to(np.asarray(part, np.int64), (len(t),)).copy())
        self.groups.append(g + self._ng)
        self.component.append(np.full(len(t), self._nc, np.int64))
        self._nv += len(v)
        self._ng += int(g.max()) + 1 if len(g) else 0
        self._nc += 1

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """vertices (V, 3) float64, triangles (T, 3), part (T,), group (T,), component (T,)."""
        return (np.concatenate(self.verts), np.concatenate(self.tris), np.concatenate(self.parts),
                np.concatenate(self.groups), np.concatenate(self.component))


_BOX_T = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5],
                   [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]], np.int64)
_BOX_G = np.arange(12) // 2


def box(b: Builder, lo, hi, part) -> None:
    """Axis-aligned box [lo, hi]."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    v = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0], [x0, y0, z1], [x1, y0, z1],
                  [x1, y1, z1], [x0, y1, z1]], np.float64)
    b.add(v, _BOX_T, part, _BOX_G)


def _frame(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors perpendicular to ``axis`` (unit) and to each other, right-handed with it."""
    ref = np.array([0.0, 0.0, 1.0]) if abs(axis[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(axis, ref)
    u /= np.linalg.norm(u)
    return u, np.cross(axis, u)


def frustum(b: Builder, p0, p1, r0: float, r1: float, part, n: int = 6, squash: float = 1.0) -> None:
    """Closed n-sided frustum from ``p0`` (radius ``r0``) to ``p1`` (radius ``r1``): limbs, masts,
    wheels (``squash`` scales the second cross-section axis: elliptic limbs)."""
    p0, p1 = np.asarray(p0, np.float64), np.asarray(p1, np.float64)
    axis = p1 - p0
    length = float(np.linalg.norm(axis))
    if length < 1e-9:
        return
    axis /= length
    u, w = _frame(axis)
    ang = (np.arange(n) + 0.5) * (2 * math.pi / n)
    ring = np.cos(ang)[:, None] * u + squash * np.sin(ang)[:, None] * w
    v = np.concatenate([p0 + r0 * ring, p1 + r1 * ring, [p0, p1]])
    i = np.arange(n)
    j = (i + 1) % n
    side = np.concatenate([np.stack([i, j, n + j], 1), np.stack([i, n + j, n + i], 1)])
    cap0 = np.stack([np.full(n, 2 * n), j, i], 1)
    cap1 = np.stack([np.full(n, 2 * n + 1), n + i, n + j], 1)
    t = np.concatenate([side, cap0, cap1])
    g = np.concatenate([i, i, np.full(n, n), np.full(n, n + 1)])
    # the ring runs counter-clockwise about the axis, so these windings face outward
    b.add(v, t, part, g)


def cylinder(b: Builder, center, radius: float, half_len: float, axis: str, part, n: int = 12) -> None:
    """Closed n-gon cylinder around the body axis ``axis`` ('x', 'y' or 'z') through ``center``."""
    c = np.asarray(center, np.float64)
    e = {"x": np.array([1.0, 0, 0]), "y": np.array([0, 1.0, 0]), "z": np.array([0, 0, 1.0])}[axis]
    frustum(b, c - half_len * e, c + half_len * e, radius, radius, part, n)


def ellipsoid(b: Builder, center, radii, part, n_lat: int = 5, n_lon: int = 8) -> None:
    """Closed low-poly ellipsoid (a UV sphere): heads, helmets, tanks' ends."""
    c = np.asarray(center, np.float64)
    r = np.asarray(radii, np.float64)
    lat = np.linspace(0, math.pi, n_lat + 1)[1:-1]
    lon = np.arange(n_lon) * (2 * math.pi / n_lon)
    ring = np.stack([np.sin(lat)[:, None] * np.cos(lon), np.sin(lat)[:, None] * np.sin(lon),
                     np.cos(lat)[:, None] * np.ones_like(lon)], -1).reshape(-1, 3)
    v = np.concatenate([[[0, 0, 1.0]], ring, [[0, 0, -1.0]]]) * r + c
    top, bot = 0, len(v) - 1
    tris = []
    k = np.arange(n_lon)
    kn = (k + 1) % n_lon
    tris.append(np.stack([np.full(n_lon, top), 1 + k, 1 + kn], 1))
    for a in range(n_lat - 2):
        r0, r1 = 1 + a * n_lon, 1 + (a + 1) * n_lon
        tris.append(np.stack([r0 + k, r1 + k, r1 + kn], 1))
        tris.append(np.stack([r0 + k, r1 + kn, r0 + kn], 1))
    last = 1 + (n_lat - 2) * n_lon
    tris.append(np.stack([np.full(n_lon, bot), last + kn, last + k], 1))
    b.add(v, np.concatenate(tris), part)


def loft(b: Builder, sections: np.ndarray, part_quads: np.ndarray | int, part_caps) -> None:
    """Closed surface through cross-sections ``sections`` (S, M, 3): section s is a closed polygon of M
    points, counter-clockwise seen from +x (the sections run along +x), convex. Quads between sections
    s and s + 1 take ``part_quads`` (S - 1, M) (or one id); the two end caps ``part_caps``."""
    s_n, m, _ = sections.shape
    v = sections.reshape(-1, 3)
    pq = np.broadcast_to(np.asarray(part_quads, np.int64), (s_n - 1, m))
    i = np.arange(m)
    j = (i + 1) % m
    tris, parts, groups = [], [], []
    g = 0
    for s in range(s_n - 1):
        a, c = s * m, (s + 1) * m
        tris.append(np.stack([a + i, a + j, c + j], 1))
        tris.append(np.stack([a + i, c + j, c + i], 1))
        parts += [pq[s], pq[s]]
        groups += [g + i, g + i]
        g += m
    fan = np.arange(1, m - 1)
    tris.append(np.stack([np.zeros(m - 2, np.int64), fan + 1, fan], 1))  # rear cap faces -x
    last = (s_n - 1) * m
    tris.append(np.stack([np.full(m - 2, last), last + fan, last + fan + 1], 1))  # front cap faces +x
    parts += [np.full(m - 2, part_caps[0]), np.full(m - 2, part_caps[1])]
    groups += [np.full(m - 2, g), np.full(m - 2, g + 1)]
    b.add(v, np.concatenate(tris), np.concatenate(parts), np.concatenate(groups))


def smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def union_volume(vertices: np.ndarray, triangles: np.ndarray, component: np.ndarray,
                 lo: np.ndarray, hi: np.ndarray, n_xy: int = 48) -> float:
    """Volume [m^3] of the union of the closed components, by vertical rays on an ``n_xy`` x ``n_xy``
    grid over the box [lo, hi]: along each ray, every component's crossings pair into inside
    intervals; the union of the intervals is that column's filled length."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(triangles.astype(np.uint32)))
    xs = lo[0] + (np.arange(n_xy) + 0.5) * (hi[0] - lo[0]) / n_xy
    ys = lo[1] + (np.arange(n_xy) + 0.5) * (hi[1] - lo[1]) / n_xy
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    rays = np.zeros((gx.size, 6), np.float32)
    rays[:, 0], rays[:, 1], rays[:, 2] = gx.ravel(), gy.ravel(), lo[2] - 1.0
    rays[:, 5] = 1.0
    ans = scene.list_intersections(o3d.core.Tensor(rays))
    split = ans["ray_splits"].numpy()
    ray_ids = np.repeat(np.arange(len(rays)), np.diff(split))
    t_hit = ans["t_hit"].numpy()
    comp = component[ans["primitive_ids"].numpy().astype(np.int64)]
    order = np.lexsort((t_hit, comp, ray_ids))
    ray_ids, t_hit, comp = ray_ids[order], t_hit[order], comp[order]
    total = 0.0
    cell = (hi[0] - lo[0]) * (hi[1] - lo[1]) / (n_xy * n_xy)
    start = 0
    for r in range(len(rays)):
        end = start
        while end < len(ray_ids) and ray_ids[end] == r:
            end += 1
        if end > start:
            iv = []
            tc, cc = t_hit[start:end], comp[start:end]
            for c in np.unique(cc):
                tt = tc[cc == c]
                iv += [(tt[k], tt[k + 1]) for k in range(0, len(tt) - 1, 2)]
            iv.sort()
            cur_a, cur_b, length = None, None, 0.0
            for a, bb in iv:
                if cur_b is None or a > cur_b:
                    if cur_b is not None:
                        length += cur_b - cur_a
                    cur_a, cur_b = a, bb
                else:
                    cur_b = max(cur_b, bb)
            if cur_b is not None:
                length += cur_b - cur_a
            total += length * cell
        start = end
    return float(total)
