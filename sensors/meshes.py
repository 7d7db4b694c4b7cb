"""Triangle meshes for the ray caster: static prisms (built once per episode) and actor shapes.

Every mesh carries one row per triangle of labels and material:

- ``semantic`` (T,) uint8: :data:`cosim.classes.SEMANTIC_ID` of the surface;
- ``instance`` (T,) uint32: track id for actors, ``Prism.instance_id`` for static things (0 = stuff);
- ``albedo`` (T, 3) float32 in [0, 1]: diffuse colour;
- ``reflectivity`` (T,) float32 in [0, 1]: LiDAR reflectivity at normal incidence;
- ``emissive`` (T,) float32 >= 0: self-luminance at night (lamp heads, headlights, tail lights);
- ``material`` (T,) uint8 (derived, :func:`material_kinds`): which procedural surface detail the
  cameras draw on the triangle (:mod:`cosim.sensors.surface`).

Vertices are float32 metres in ``map`` (static) or in the actor's body frame FLU, box-centred
(templates); triangles are wound counter-clockwise seen from outside (normals point out).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from cosim.classes import SEMANTIC_ID, semantic_id
from cosim.errors import CosimError
from cosim.world.types import Prism, StaticLayout


@dataclass(frozen=True)
class TriMesh:
    """Triangles with per-triangle labels and material (see the module docstring)."""

    vertices: np.ndarray  # (V, 3) float32 [m]
    triangles: np.ndarray  # (T, 3) uint32 vertex indices
    semantic: np.ndarray  # (T,) uint8
    instance: np.ndarray  # (T,) uint32
    albedo: np.ndarray  # (T, 3) float32
    reflectivity: np.ndarray  # (T,) float32
    emissive: np.ndarray  # (T,) float32
    group: np.ndarray  # (T,) int64: triangles of one convex planar polygon share a group (see faces())

    @property
    def n_triangles(self) -> int:
        return int(self.triangles.shape[0])

    def faces(self) -> np.ndarray:
        """Face id (T,) int32: triangles of one convex planar polygon (same ``group``, same plane) with
        identical labels and material share an id.

        Adaptive casting may interpolate across triangles of one face (the plane's depth is exact, every
        label and colour is the same and the face has no holes), so triangulation diagonals are not edges.
        """
        if self.n_triangles == 0:
            return np.zeros(0, np.int32)
        v = self.vertices.astype(np.float64)[self.triangles]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        off = (n * v[:, 0]).sum(axis=1)
        key = np.column_stack([
            self.group, np.round(n * 1e4), np.round(off * 1e3), self.semantic, self.instance,
            np.round(self.albedo * 1e4),
            np.round(self.reflectivity * 1e4), np.round(self.emissive * 1e4),
        ])
        _, face = np.unique(key, axis=0, return_inverse=True)
        return face.astype(np.int32).ravel()

    @cached_property
    def material(self) -> np.ndarray:
        """Surface material kind (T,) uint8 (:func:`material_kinds`), computed once per mesh."""
        return material_kinds(self.semantic, self.normals())

    def normals(self) -> np.ndarray:
        """Unit face normals (T, 3) float32 from the winding (outward)."""
        v = self.vertices[self.triangles]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        return (n / np.maximum(norm, 1e-12)).astype(np.float32)


def empty_mesh() -> TriMesh:
    return TriMesh(
        np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32), np.zeros(0, np.uint8), np.zeros(0, np.uint32),
        np.zeros((0, 3), np.float32), np.zeros(0, np.float32), np.zeros(0, np.float32), np.zeros(0, np.int64),
    )


def concat(meshes: Sequence[TriMesh]) -> TriMesh:
    """One mesh holding all of ``meshes`` in order (triangle order preserved)."""
    meshes = [m for m in meshes if m.n_triangles]
    if not meshes:
        return empty_mesh()
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    g_off = np.cumsum([0] + [int(m.group.max()) + 1 for m in meshes[:-1]])
    return TriMesh(
        np.concatenate([m.vertices for m in meshes]).astype(np.float32),
        np.concatenate([m.triangles + np.uint32(o) for m, o in zip(meshes, offsets, strict=True)]).astype(np.uint32),
        np.concatenate([m.semantic for m in meshes]),
        np.concatenate([m.instance for m in meshes]),
        np.concatenate([m.albedo for m in meshes]),
        np.concatenate([m.reflectivity for m in meshes]),
        np.concatenate([m.emissive for m in meshes]),
        np.concatenate([m.group + o for m, o in zip(meshes, g_off, strict=True)]).astype(np.int64),
    )


def _labelled(vertices: np.ndarray, triangles: np.ndarray, cls: str, instance: int, albedo, refl: float,
              emissive: float = 0.0, group: np.ndarray | None = None) -> TriMesh:
    t = len(triangles)
    alb = np.broadcast_to(np.asarray(albedo, np.float32), (t, 3))
    return TriMesh(
        np.asarray(vertices, np.float32), np.asarray(triangles, np.uint32).reshape(-1, 3),
        np.full(t, semantic_id(cls), np.uint8), np.full(t, instance, np.uint32), np.array(alb, np.float32),
        np.full(t, refl, np.float32), np.full(t, emissive, np.float32),
        np.arange(t, dtype=np.int64) if group is None else np.asarray(group, np.int64),
    )


# ------------------------------------------------------------------------------ triangulation


def _clean_polygon(poly: np.ndarray) -> np.ndarray:
    """Drop repeated and collinear points, make counter-clockwise. ``poly`` (N, 2) float64."""
    p = np.asarray(poly, np.float64)
    if len(p) > 1 and np.allclose(p[0], p[-1]):
        p = p[:-1]
    for _ in range(3):
        if len(p) < 3:
            return p
        nxt = np.roll(p, -1, axis=0)
        keep = np.linalg.norm(nxt - p, axis=1) > 1e-7
        p = p[keep]
        if len(p) < 3:
            return p
        prv, nxt = np.roll(p, 1, axis=0), np.roll(p, -1, axis=0)
        cross = (p[:, 0] - prv[:, 0]) * (nxt[:, 1] - p[:, 1]) - (p[:, 1] - prv[:, 1]) * (nxt[:, 0] - p[:, 0])
        scale = np.linalg.norm(p - prv, axis=1) * np.linalg.norm(nxt - p, axis=1)
        keep = np.abs(cross) > 1e-9 * np.maximum(scale, 1e-12)
        if keep.all():
            break
        p = p[keep]
    x, y = p[:, 0], p[:, 1]
    if np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y) < 0:
        p = p[::-1].copy()
    return p


def triangulate_polygon(poly: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ear-clipping triangulation of a simple (possibly concave) polygon.

    ``poly`` (N, 2) [m], any orientation, optionally with a repeated last point. Returns the cleaned
    counter-clockwise points (M, 2) float64 and triangles (M - 2, 3) int64 into them, each triangle CCW.
    Degenerate input (self-touching, slightly self-intersecting) still terminates: when no clean ear
    exists the most convex vertex is clipped.
    """
    p = _clean_polygon(poly)
    n = len(p)
    if n < 3:
        return p, np.zeros((0, 3), np.int64)
    idx = list(range(n))
    tris: list[tuple[int, int, int]] = []
    x, y = p[:, 0], p[:, 1]
    guard = 0
    while len(idx) > 3:
        guard += 1
        if guard > 4 * n * n + 100:
            raise CosimError(f"triangulation did not terminate for a polygon with {n} points")
        m = len(idx)
        ia = np.asarray(idx)
        prv, nxt = np.roll(ia, 1), np.roll(ia, -1)
        ax, ay, bx, by, cx, cy = x[prv], y[prv], x[ia], y[ia], x[nxt], y[nxt]
        cross = (bx - ax) * (cy - by) - (by - ay) * (cx - bx)
        convex = np.nonzero(cross > 1e-12)[0]
        clipped = False
        for k in convex:
            a, b, c = prv[k], ia[k], nxt[k]
            others = ia[(ia != a) & (ia != b) & (ia != c)]
            ox, oy = x[others], y[others]
            d1 = (x[b] - x[a]) * (oy - y[a]) - (y[b] - y[a]) * (ox - x[a])
            d2 = (x[c] - x[b]) * (oy - y[b]) - (y[c] - y[b]) * (ox - x[b])
            d3 = (x[a] - x[c]) * (oy - y[c]) - (y[a] - y[c]) * (ox - x[c])
            inside = (d1 >= -1e-12) & (d2 >= -1e-12) & (d3 >= -1e-12)
            if not inside.any():
                tris.append((int(a), int(b), int(c)))
                del idx[int(k)]
                clipped = True
                break
        if not clipped:
            k = int(np.argmax(cross)) if m else 0
            if cross[k] > 1e-12:
                tris.append((int(prv[k]), int(ia[k]), int(nxt[k])))
            del idx[k]
    a, b, c = idx
    if (x[b] - x[a]) * (y[c] - y[a]) - (y[b] - y[a]) * (x[c] - x[a]) > 1e-12:
        tris.append((a, b, c))
    return p, np.asarray(tris, np.int64).reshape(-1, 3)


def prism_groups(footprint: np.ndarray, n_triangles: int) -> np.ndarray:
    """Convex-face group per triangle (T,) of :func:`prism_geometry`'s output: one group for a convex
    cap (each triangle its own for a concave one), one per wall quad, the bottom like the cap."""
    pts = _clean_polygon(footprint)
    m = len(pts)
    if m < 3 or n_triangles == 0:
        return np.zeros(n_triangles, np.int64)
    prv, nxt = np.roll(pts, 1, axis=0), np.roll(pts, -1, axis=0)
    cross = (pts[:, 0] - prv[:, 0]) * (nxt[:, 1] - pts[:, 1]) - (pts[:, 1] - prv[:, 1]) * (nxt[:, 0] - pts[:, 0])
    n_cap = m - 2
    cap = np.zeros(n_cap, np.int64) if np.all(cross > 0) else np.arange(n_cap, dtype=np.int64)
    groups = [cap]
    rest = n_triangles - n_cap
    if rest >= 2 * m:
        wall = n_cap + np.arange(m, dtype=np.int64)
        groups += [wall, wall]
        rest -= 2 * m
    if rest == n_cap:
        groups.append(cap + n_cap + m)
    out = np.concatenate(groups)
    return out if len(out) == n_triangles else np.arange(n_triangles, dtype=np.int64)


def prism_geometry(footprint: np.ndarray, z0: float, z1: float, bottom: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) and outward-wound triangles (T, 3) of a vertical extrusion.

    Top cap at ``z1``, side walls from ``z0`` to ``z1`` (skipped when the prism is flat, thinner
    than 1 mm), bottom cap only when ``bottom``.
    """
    pts, cap = triangulate_polygon(footprint)
    n = len(pts)
    if n < 3 or len(cap) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    top = np.column_stack([pts, np.full(n, z1)])
    bot = np.column_stack([pts, np.full(n, z0)])
    verts = np.concatenate([top, bot])
    tris = [cap]
    if z1 - z0 > 1e-3:
        i = np.arange(n)
        j = (i + 1) % n
        # CCW footprint: the wall (i -> j) faces outward when wound bot_i, bot_j, top_j
        tris.append(np.stack([n + i, n + j, j], axis=1))
        tris.append(np.stack([n + i, j, i], axis=1))
        if bottom:
            tris.append(cap[:, ::-1] + n)
    return verts, np.concatenate(tris)


# --------------------------------------------------------------------------------- materials

#: Diffuse albedo (linear RGB 0..1) and diffuse LiDAR reflectivity at 905 nm per semantic class (asphalt
#: dark, concrete and buildings middling, vegetation moderate in the near infrared; lane markings also
#: carry a retro-reflective term, see cosim.sensors.lidar).
_MATERIAL: dict[str, tuple[tuple[float, float, float], float]] = {
    "unlabelled": ((0.5, 0.5, 0.5), 0.3),
    "road": ((0.16, 0.16, 0.17), 0.10),
    "lane_marking": ((0.85, 0.85, 0.80), 0.45),
    "sidewalk": ((0.50, 0.48, 0.45), 0.30),
    "building": ((0.55, 0.50, 0.45), 0.35),
    "vegetation": ((0.15, 0.35, 0.10), 0.30),
    "terrain": ((0.32, 0.42, 0.18), 0.25),
    "pole": ((0.45, 0.45, 0.47), 0.50),
    "street_light": ((0.40, 0.40, 0.42), 0.50),
    "rsu": ((0.70, 0.70, 0.20), 0.55),
}

_BUILDING_TINTS = np.array(
    [(0.62, 0.55, 0.47), (0.50, 0.50, 0.52), (0.70, 0.64, 0.55), (0.45, 0.38, 0.33), (0.60, 0.60, 0.58),
     (0.55, 0.45, 0.40)], np.float32,
)
_PAINTS = np.array(
    [(0.75, 0.75, 0.78), (0.08, 0.08, 0.09), (0.55, 0.05, 0.05), (0.10, 0.20, 0.45), (0.85, 0.85, 0.85),
     (0.35, 0.36, 0.38), (0.70, 0.55, 0.15), (0.15, 0.35, 0.20)], np.float32,
)


#: Surface material kinds (per triangle, :attr:`TriMesh.material`): the procedural detail the cameras
#: draw (:mod:`cosim.sensors.surface`). Plain: none (poles, actors...).
MAT_PLAIN, MAT_ASPHALT, MAT_MARKING, MAT_PAVING, MAT_FACADE, MAT_ROOF, MAT_FOLIAGE, MAT_GRASS = range(8)
MATERIAL_KINDS = ("plain", "asphalt", "marking", "paving", "facade", "roof", "foliage", "grass")
_MATERIAL_OF_CLASS = {"road": MAT_ASPHALT, "lane_marking": MAT_MARKING, "sidewalk": MAT_PAVING,
                      "building": MAT_FACADE, "vegetation": MAT_FOLIAGE, "terrain": MAT_GRASS}


def material_kinds(semantic: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Material kind (T,) uint8 of triangles from their semantic class and unit normal: roads are
    asphalt, lane markings paint, sidewalks paving, buildings facade on their walls and roof on faces
    turned up (normal z > 0.5), vegetation foliage, terrain grass; anything else plain."""
    table = np.zeros(256, np.uint8)
    for cls, kind in _MATERIAL_OF_CLASS.items():
        table[SEMANTIC_ID[cls]] = kind
    out = table[np.asarray(semantic, np.uint8)]
    out[(out == MAT_FACADE) & (np.asarray(normals)[:, 2] > 0.5)] = MAT_ROOF
    return out


def _hash01(value: int, salt: int) -> float:
    return (zlib.crc32(f"{salt}:{value}".encode()) & 0xFFFF) / 65535.0


def material_of(cls: str, instance: int) -> tuple[np.ndarray, float]:
    """Albedo (3,) and reflectivity of a static prism (buildings get a per-instance tint)."""
    alb, refl = _MATERIAL.get(cls, _MATERIAL["unlabelled"])
    if cls == "building":
        alb = _BUILDING_TINTS[int(_hash01(instance, 1) * len(_BUILDING_TINTS)) % len(_BUILDING_TINTS)]
    return np.asarray(alb, np.float32), refl


# ------------------------------------------------------------------------------ static scene

#: A ``street_light`` prism that starts this high is a lamp arm: it glows at night.
LAMP_ARM_MIN_Z_M = 2.0
LAMP_ALBEDO = (0.9, 0.85, 0.7)


def is_lamp(prism: Prism) -> bool:
    """True for the luminous part of a street light (its arm, above :data:`LAMP_ARM_MIN_Z_M`)."""
    return prism.cls == "street_light" and prism.z0_m >= LAMP_ARM_MIN_Z_M


#: [m] how far the flat terrain continues beyond the map's edge (:func:`far_ground`): farther than any
#: LiDAR reaches (``range_m`` <= 500 m), and far enough that a camera 10 m up sees ground up to 0.06 deg
#: below the horizon.
FAR_GROUND_M = 10_000.0


def static_mesh(layout: StaticLayout) -> TriMesh:
    """Mesh of every prism of ``layout`` (map frame), in prism order, then :func:`far_ground`."""
    return concat([*(_prism_mesh(p) for p in layout.prisms), far_ground(layout)])


def far_ground(layout: StaticLayout, reach_m: float = FAR_GROUND_M) -> TriMesh:
    """Flat terrain around the map: four trapezoids (8 triangles, normals up) from the edge of the
    terrain prisms (all prisms if there is none) out to ``reach_m`` beyond it, at the terrain's top.

    The layout ends a few tens of metres past the outer roads; without this, cameras looking outward
    saw sky (class 0, no depth) below the horizon and downward LiDAR beams found nothing. The ring is
    renderer-only (not a prism of the layout), so the BEV raster and the light map keep the map's size.
    """
    terrain = [p for p in layout.prisms if p.cls == "terrain"] or list(layout.prisms)
    if not terrain:
        return empty_mesh()
    pts = np.array([q for p in terrain for q in p.footprint], np.float64)
    x0, y0 = pts.min(0)
    x1, y1 = pts.max(0)
    z = max(p.z1_m for p in terrain) if terrain[0].cls == "terrain" else layout.ground_z_m
    X0, Y0, X1, Y1 = x0 - reach_m, y0 - reach_m, x1 + reach_m, y1 + reach_m
    quads = [
        [(X0, Y0), (X1, Y0), (x1, y0), (x0, y0)],  # south
        [(X1, Y0), (X1, Y1), (x1, y1), (x1, y0)],  # east
        [(X1, Y1), (X0, Y1), (x0, y1), (x1, y1)],  # north
        [(X0, Y1), (X0, Y0), (x0, y0), (x0, y1)],  # west
    ]
    v = np.array([(x, y, z) for q in quads for x, y in q], np.float64)
    t = np.array([[4 * k, 4 * k + 1, 4 * k + 2, 4 * k, 4 * k + 2, 4 * k + 3] for k in range(4)]).reshape(-1, 3)
    alb, refl = material_of("terrain", 0)
    return _labelled(v, t, "terrain", 0, alb, refl, group=np.repeat(np.arange(4), 2))


def _prism_mesh(prism: Prism) -> TriMesh:
    if prism.cls not in SEMANTIC_ID:
        raise CosimError(f"prism class {prism.cls!r} is not a semantic class; known: {', '.join(SEMANTIC_ID)}")
    fp = np.asarray(prism.footprint, np.float64)
    alb, refl = material_of(prism.cls, prism.instance_id)
    lamp = is_lamp(prism)
    v, t = prism_geometry(fp, prism.z0_m, prism.z1_m, bottom=lamp or prism.z0_m > 0.5)
    g = prism_groups(fp, len(t))
    if lamp:
        return _labelled(v, t, prism.cls, prism.instance_id, LAMP_ALBEDO, refl, emissive=1.0, group=g)
    return _labelled(v, t, prism.cls, prism.instance_id, alb, refl, group=g)


# ------------------------------------------------------------------------------ actor shapes
# Templates live in a unit box [-0.5, 0.5]^3 (body FLU, box centred) and are scaled by the actor's
# (length, width, height), so every shape stays inside its labelled 3D box.

_PART_BODY, _PART_GLASS, _PART_TYRE, _PART_LAMP_FRONT, _PART_LAMP_REAR, _PART_DARK = range(6)


def _box(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    v = np.array(
        [[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0], [x0, y0, z1], [x1, y0, z1], [x1, y1, z1],
         [x0, y1, z1]], np.float64,
    )
    t = np.array(
        [[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5], [2, 3, 7],
         [2, 7, 6], [3, 0, 4], [3, 4, 7]], np.int64,
    )
    return v, t


def _cylinder(center, radius: float, half_len: float, axis: str, n: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Closed n-gon cylinder around ``axis`` ('x', 'y' or 'z') through ``center``."""
    ang = np.arange(n) * (2 * math.pi / n)
    ring = np.stack([radius * np.cos(ang), radius * np.sin(ang)], axis=1)
    v, t = prism_geometry(ring, -half_len, half_len, bottom=True)
    if axis == "y":  # local z -> y: (a, b, c) -> (a, c, -b) keeps handedness
        v = np.stack([v[:, 0], v[:, 2], -v[:, 1]], axis=1)
    elif axis == "x":  # local z -> x: (a, b, c) -> (c, a, b)
        v = np.stack([v[:, 2], v[:, 0], v[:, 1]], axis=1)
    return v + np.asarray(center, np.float64), t


@dataclass(frozen=True)
class ActorTemplate:
    """A class shape in the unit box: vertices (V, 3), triangles (T, 3), part id per triangle (T,)."""

    vertices: np.ndarray
    triangles: np.ndarray
    part: np.ndarray
    group: np.ndarray  # (T,) convex-face group (box faces: the quad's two triangles)


def _assemble(parts: list[tuple[tuple[np.ndarray, np.ndarray], int]]) -> ActorTemplate:
    vs, ts, ps, gs, off, goff = [], [], [], [], 0, 0
    for (v, t), part in parts:
        vs.append(v)
        ts.append(t + off)
        ps.append(np.full(len(t), part, np.int64))
        g = np.arange(len(t)) // 2 if len(t) == 12 else np.arange(len(t))  # a box: quads
        gs.append(g + goff)
        goff += len(t)
        off += len(v)
    v = np.concatenate(vs)
    if np.abs(v).max() > 0.5 + 1e-9:
        raise CosimError("actor template leaves its unit box")
    return ActorTemplate(v.astype(np.float32), np.concatenate(ts).astype(np.uint32), np.concatenate(ps),
                         np.concatenate(gs).astype(np.int64))


def _wheels(xs: Sequence[float], radius: float, width: float) -> list:
    out = []
    for x in xs:
        for side in (-1, 1):
            yc = side * (0.5 - width / 2)
            out.append((_cylinder((x, yc, -0.5 + radius), radius, width / 2, "y"), _PART_TYRE))
    return out


#: vehicle bodies stop this far inside the box ends so the lamp units there are the outermost surface (a
#: lamp face level with the body's would lose the ray-cast tie and never show, nor glow, nor blink)
_BODY_X = 0.49


def _lamps(x_front: float, x_rear: float, z: float, h: float) -> list:
    return [
        (_box((x_front - 0.02, -0.42, z), (x_front, -0.28, z + h)), _PART_LAMP_FRONT),
        (_box((x_front - 0.02, 0.28, z), (x_front, 0.42, z + h)), _PART_LAMP_FRONT),
        (_box((x_rear, -0.42, z), (x_rear + 0.02, -0.30, z + h)), _PART_LAMP_REAR),
        (_box((x_rear, 0.30, z), (x_rear + 0.02, 0.42, z + h)), _PART_LAMP_REAR),
    ]


def _car() -> ActorTemplate:
    r = 0.16  # wheel radius as a fraction of height
    return _assemble(
        [
            (_box((-_BODY_X, -0.5, -0.5 + 0.6 * r), (_BODY_X, 0.5, 0.02)), _PART_BODY),
            (_box((-0.33, -0.44, 0.02), (0.17, 0.44, 0.5)), _PART_GLASS),
            (_box((-0.32, -0.40, 0.46), (0.15, 0.40, 0.5)), _PART_BODY),
            *_wheels((-0.32, 0.32), r * 1.0, 0.16),
            *_lamps(0.5, -0.5, -0.12, 0.08),
        ]
    )


def _van() -> ActorTemplate:
    r = 0.13
    return _assemble(
        [
            (_box((-_BODY_X, -0.5, -0.5 + 0.6 * r), (_BODY_X, 0.5, -0.1)), _PART_BODY),
            (_box((-_BODY_X, -0.49, -0.1), (0.22, 0.49, 0.5)), _PART_BODY),
            (_box((0.22, -0.47, -0.1), (0.36, 0.47, 0.3)), _PART_GLASS),
            *_wheels((-0.33, 0.33), r, 0.14),
            *_lamps(0.5, -0.5, -0.25, 0.08),
        ]
    )


def _truck() -> ActorTemplate:
    r = 0.12
    return _assemble(
        [
            (_box((0.22, -0.48, -0.5 + 0.7 * r), (_BODY_X, 0.48, 0.25)), _PART_BODY),
            (_box((0.40, -0.46, 0.0), (0.5, 0.46, 0.22)), _PART_GLASS),
            (_box((-_BODY_X, -0.5, -0.5 + 0.9 * r), (0.19, 0.5, 0.5)), _PART_DARK),
            (_box((0.15, -0.2, -0.5 + 0.9 * r), (0.22, 0.2, -0.1)), _PART_TYRE),
            *_wheels((-0.36, -0.22, 0.36), r, 0.14),
            *_lamps(0.5, -0.5, -0.28, 0.06),
        ]
    )


def _bus() -> ActorTemplate:
    r = 0.1
    return _assemble(
        [
            (_box((-_BODY_X, -0.5, -0.5 + 0.8 * r), (_BODY_X, 0.5, 0.05)), _PART_BODY),
            (_box((-0.48, -0.5, 0.05), (0.49, 0.5, 0.35)), _PART_GLASS),
            (_box((-0.5, -0.49, 0.05), (0.5, 0.49, 0.5)), _PART_BODY),
            *_wheels((-0.32, 0.36), r, 0.12),
            *_lamps(0.5, -0.5, -0.3, 0.05),
        ]
    )


def _two_wheeler(motor: bool) -> ActorTemplate:
    r = 0.19 if motor else 0.2
    parts = [
        (_cylinder((-0.5 + r, 0.0, -0.5 + r), r, 0.08, "y", 12), _PART_TYRE),
        (_cylinder((0.5 - r, 0.0, -0.5 + r), r, 0.08, "y", 12), _PART_TYRE),
    ]
    if motor:
        parts.append((_box((-0.3, -0.22, -0.35), (0.32, 0.22, -0.05)), _PART_BODY))
        parts.append((_box((0.44, -0.1, -0.2), (0.5, 0.1, -0.12)), _PART_LAMP_FRONT))
    else:
        parts.append((_box((-0.3, -0.04, -0.25), (0.3, 0.04, -0.19)), _PART_BODY))
        parts.append((_box((0.18, -0.04, -0.3), (0.24, 0.04, -0.05)), _PART_BODY))
    parts.append((_box((0.2, -0.5, 0.0), (0.26, 0.5, 0.05)), _PART_DARK))  # handlebar
    parts.append((_box((-0.18, -0.3, -0.08), (0.06, 0.3, 0.3)), _PART_DARK))  # rider torso
    parts.append((_box((-0.10, -0.12, 0.3), (0.04, 0.12, 0.5)), _PART_GLASS))  # helmet/head
    return _assemble(parts)


def _drone() -> ActorTemplate:
    parts = [(_box((-0.16, -0.16, -0.3), (0.16, 0.16, 0.12)), _PART_DARK)]  # fuselage
    for sx in (-1, 1):
        for sy in (-1, 1):
            cx, cy = sx * 0.32, sy * 0.32
            # arm: an L of two bars from the fuselage to the motor
            parts.append((_box((min(0, cx) - 0.03, cy - 0.03, 0.02), (max(0, cx) + 0.03, cy + 0.03, 0.1)), _PART_BODY))
            parts.append((_box((-0.03, min(0, cy), 0.02), (0.03, max(0, cy), 0.1)), _PART_BODY))
            parts.append((_cylinder((cx, cy, 0.25), 0.04, 0.15, "z", 6), _PART_DARK))  # motor mast
            parts.append((_cylinder((cx, cy, 0.44), 0.17, 0.03, "z", 12), _PART_GLASS))  # rotor disc
    parts.append((_box((-0.08, -0.08, -0.5), (0.08, 0.08, -0.3)), _PART_DARK))  # camera gimbal
    return _assemble(parts)


def _pedestrian(stride: float = 1.0) -> ActorTemplate:
    """A walker in the unit box (x forward): legs (``stride`` 1: right leg forward in a full stride, 0: side
    by side, -1: left leg forward), torso, arms, head."""
    x = 0.31 * stride  # the right leg's centre along x; the left one's is -x
    parts = [
        (_box((x - 0.19, -0.32, -0.5), (x + 0.19, -0.06, -0.02)), _PART_DARK),  # right leg
        (_box((-x - 0.19, 0.06, -0.5), (-x + 0.19, 0.32, -0.02)), _PART_DARK),  # left leg
        (_box((-0.25, -0.38, -0.02), (0.25, 0.38, 0.3)), _PART_BODY),  # torso
        (_box((-0.12, -0.5, -0.05), (0.12, -0.38, 0.28)), _PART_BODY),  # arms
        (_box((-0.12, 0.38, -0.05), (0.12, 0.5, 0.28)), _PART_BODY),
        (_box((-0.2, -0.22, 0.3), (0.2, 0.22, 0.5)), _PART_GLASS),  # head
    ]
    return _assemble(parts)


def _static_obstacle() -> ActorTemplate:
    """A traffic cone / barrier post in the unit box: a base plate and a tapering body in two bands."""
    parts = [
        (_box((-0.5, -0.5, -0.5), (0.5, 0.5, -0.42)), _PART_DARK),  # base plate
        (_box((-0.32, -0.32, -0.42), (0.32, 0.32, -0.05)), _PART_BODY),
        (_box((-0.22, -0.22, -0.05), (0.22, 0.22, 0.2)), _PART_LAMP_FRONT),  # reflective band
        (_box((-0.12, -0.12, 0.2), (0.12, 0.12, 0.5)), _PART_BODY),
    ]
    return _assemble(parts)


#: the walker through one gait cycle (two steps): pose k for gait phase in [k / n, (k + 1) / n)
PEDESTRIAN_POSES: tuple[ActorTemplate, ...] = tuple(_pedestrian(math.cos(2 * math.pi * k / 8)) for k in range(8))

ACTOR_TEMPLATES: dict[str, ActorTemplate] = {
    "car": _car(),
    "van": _van(),
    "truck": _truck(),
    "bus": _bus(),
    "motorcycle": _two_wheeler(True),
    "bicycle": _two_wheeler(False),
    "drone": _drone(),
    "pedestrian": _pedestrian(),
    "static_obstacle": _static_obstacle(),
}


def template_for(cls: str, gait_phase: float = 0.0) -> ActorTemplate:
    """The class's shape; a pedestrian's legs in the pose of its ``gait_phase`` (0..1)."""
    if cls == "pedestrian":
        return PEDESTRIAN_POSES[int(gait_phase * len(PEDESTRIAN_POSES)) % len(PEDESTRIAN_POSES)]
    try:
        return ACTOR_TEMPLATES[cls]
    except KeyError:
        raise CosimError(f"no actor shape for class {cls!r}; known: {', '.join(ACTOR_TEMPLATES)}") from None


HAZARD_AMBER = (1.0, 0.5, 0.0)


def actor_material(cls: str, track_id: int, part: np.ndarray, hazard_lamps_on: bool = False
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Albedo (T, 3), reflectivity (T,), emissive (T,) of an actor's triangles from their part ids; with
    ``hazard_lamps_on`` every lamp unit (front and rear) glows amber (a blinking hazard light, lit)."""
    paint = _PAINTS[int(_hash01(track_id, 7) * len(_PAINTS)) % len(_PAINTS)]
    if cls == "bus":
        paint = np.array((0.85, 0.65, 0.10), np.float32) if _hash01(track_id, 3) > 0.5 else paint
    if cls == "drone":
        paint = np.array((0.9, 0.9, 0.92), np.float32)
    if cls == "static_obstacle":
        paint = np.array((0.95, 0.35, 0.02), np.float32)  # safety orange
    table = np.array([paint, (0.05, 0.07, 0.09), (0.03, 0.03, 0.03), (0.95, 0.95, 0.9), (0.7, 0.05, 0.05),
                      (0.12, 0.12, 0.13)], np.float32)
    # diffuse LiDAR reflectivity: paint by its brightness (dark paint low), glass and tyres low, lamp
    # units middling (their reflectors add a retro-reflective term, see cosim.sensors.lidar)
    paint_refl = 0.05 + 0.7 * float(paint @ np.array([0.2126, 0.7152, 0.0722], np.float32))
    refl_t = np.array([paint_refl, 0.05, 0.03, 0.3, 0.3, 0.08], np.float32)
    emis_t = np.array([0.0, 0.0, 0.0, 1.0, 0.6, 0.0], np.float32)
    if hazard_lamps_on:
        table[_PART_LAMP_FRONT] = table[_PART_LAMP_REAR] = HAZARD_AMBER
        emis_t[_PART_LAMP_FRONT] = emis_t[_PART_LAMP_REAR] = 0.6
    return table[part], refl_t[part], emis_t[part]
