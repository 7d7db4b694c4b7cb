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
from functools import cache, cached_property, lru_cache

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
    retro: np.ndarray | None = None  # (T,) float32: retro-reflective LiDAR reflectivity (plates, lamps); None: 0
    glass: np.ndarray | None = None  # (T,) bool: glazing (the LiDAR mostly loses its returns); None: none
    leaf_density: np.ndarray | None = None  # (T,) float32 [1/m]: a porous crown's foliage (0: solid); None: 0

    def retro_values(self) -> np.ndarray:
        return np.zeros(self.n_triangles, np.float32) if self.retro is None else self.retro

    def glass_values(self) -> np.ndarray:
        return np.zeros(self.n_triangles, bool) if self.glass is None else self.glass

    def leaf_density_values(self) -> np.ndarray:
        return np.zeros(self.n_triangles, np.float32) if self.leaf_density is None else self.leaf_density

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
        # the rank of each row among the distinct rows in lexicographic order: what
        # np.unique(key, axis=0, return_inverse=True) gives, 10-50x faster
        order = np.lexsort(key.T[::-1])
        k = key[order]
        new = np.ones(len(k), bool)
        new[1:] = np.any(k[1:] != k[:-1], axis=1)
        face = np.empty(len(k), np.int32)
        face[order] = np.cumsum(new) - 1
        return face

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
        np.concatenate([m.retro_values() for m in meshes]).astype(np.float32)
        if any(m.retro is not None for m in meshes) else None,
        np.concatenate([m.glass_values() for m in meshes]) if any(m.glass is not None for m in meshes) else None,
        np.concatenate([m.leaf_density_values() for m in meshes]).astype(np.float32)
        if any(m.leaf_density is not None for m in meshes) else None,
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
    """Mesh of every prism of ``layout`` (map frame), in prism order, then :func:`far_ground`. A tree's
    trunk and crown prisms become one procedural tree (:func:`cosim.sensors.assets.vegetation.tree_mesh`)
    where the crown was; hedges get a porous foliage."""
    trees = _tree_pairs(layout)
    parts = []
    for k, p in enumerate(layout.prisms):
        if k in trees:
            if trees[k] >= 0:
                parts.append(_tree(p, layout.prisms[trees[k]]))
            continue
        parts.append(_prism_mesh(p))
    return concat([*parts, far_ground(layout)])


def _tree_pairs(layout: StaticLayout) -> dict[int, int]:
    """Crown prism index -> its trunk's index, and trunk index -> -1, for every tree of the layout (a
    vegetation prism raised off the ground above a square vegetation prism of the same centre)."""
    trunks: dict[tuple[float, float], int] = {}
    for k, p in enumerate(layout.prisms):
        if p.cls == "vegetation" and len(p.footprint) == 4 and p.z0_m <= layout.ground_z_m + 0.01:
            c = np.mean(np.asarray(p.footprint), axis=0)
            trunks[(round(float(c[0]), 1), round(float(c[1]), 1))] = k
    out: dict[int, int] = {}
    for k, p in enumerate(layout.prisms):
        if p.cls == "vegetation" and p.z0_m > layout.ground_z_m + 0.5:
            c = np.mean(np.asarray(p.footprint), axis=0)
            t = trunks.get((round(float(c[0]), 1), round(float(c[1]), 1)))
            if t is not None and abs(layout.prisms[t].z1_m - p.z0_m) < 0.01:
                out[k] = t
                out[t] = -1
    return out


#: bark colour and LiDAR reflectivity of trunks and branches
_BARK = ((0.22, 0.16, 0.11), 0.35)


def _tree(crown: Prism, trunk: Prism) -> TriMesh:
    from .assets import vegetation

    fp = np.asarray(crown.footprint, np.float64)
    c = fp.mean(axis=0)
    radius = float(np.linalg.norm(fp - c, axis=1).max())
    v, t, part, grp, species = vegetation.tree_mesh(float(c[0]), float(c[1]), trunk.z0_m, crown.z0_m, crown.z1_m,
                                                    radius)
    alb, refl = material_of("vegetation", 0)
    albedo = np.where((part == vegetation.PART_CROWN)[:, None], alb, np.asarray(_BARK[0], np.float32))
    mesh = _labelled(v, t, "vegetation", 0, albedo, refl, group=grp)
    density = np.where(part == vegetation.PART_CROWN, vegetation.SPECIES[species][1], 0.0).astype(np.float32)
    return TriMesh(mesh.vertices, mesh.triangles, mesh.semantic, mesh.instance, mesh.albedo,
                   np.where(part == vegetation.PART_CROWN, refl, _BARK[1]).astype(np.float32), mesh.emissive,
                   mesh.group, None, None, density)


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
    mesh = _labelled(v, t, prism.cls, prism.instance_id, alb, refl, group=g)
    if prism.cls == "vegetation":  # a hedge or bush: porous foliage
        from .assets.vegetation import HEDGE_DENSITY

        return TriMesh(*(getattr(mesh, f) for f in ("vertices", "triangles", "semantic", "instance", "albedo",
                                                    "reflectivity", "emissive", "group")), None, None,
                       np.full(len(t), HEDGE_DENSITY, np.float32))
    return mesh


# ------------------------------------------------------------------------------ actor shapes
# Templates live in a unit box [-0.5, 0.5]^3 (body FLU, box centred) and are scaled by the actor's
# (length, width, height). Each touches all six faces, so a template scaled to a label box is that box's
# tight content. Vehicles and people are the procedural models of cosim.sensors.assets; drones and
# obstacles are a few boxes.

#: material part ids of actor triangles (the procedural assets use the same numbers)
(_PART_BODY, _PART_GLASS, _PART_TYRE, _PART_LAMP_FRONT, _PART_LAMP_REAR, _PART_DARK, _PART_RIM, _PART_PLATE,
 _PART_TRIM, _PART_CARGO, _PART_SKIN, _PART_HAIR, _PART_TOP, _PART_BOTTOM, _PART_SHOES) = range(15)
N_PARTS = 15


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
    """A shape in the unit box: vertices (V, 3), triangles (T, 3), part id per triangle (T,), convex-face
    group (T,); ``palette`` (N_PARTS, 3) overrides the part colours (a person's skin and clothes);
    ``name`` the catalogue model."""

    vertices: np.ndarray
    triangles: np.ndarray
    part: np.ndarray
    group: np.ndarray
    palette: np.ndarray | None = None
    name: str = ""

    @cached_property
    def faces(self) -> np.ndarray:
        """Face ids (T,) int32 of :meth:`TriMesh.faces` (invariant under the actor's placement)."""
        t = len(self.triangles)
        mesh = TriMesh(self.vertices, self.triangles, np.zeros(t, np.uint8), np.zeros(t, np.uint32),
                       np.zeros((t, 3), np.float32), self.part.astype(np.float32), np.zeros(t, np.float32),
                       self.group)
        return mesh.faces()


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


def unit_template(vertices: np.ndarray, triangles: np.ndarray, part: np.ndarray, group: np.ndarray,
                  palette: np.ndarray | None = None, name: str = "") -> ActorTemplate:
    """A template from a mesh in metres: scaled and centred so that its tight box is the unit box."""
    v = np.asarray(vertices, np.float64)
    lo, hi = v.min(0), v.max(0)
    v = (v - (lo + hi) / 2) / np.maximum(hi - lo, 1e-9)
    return ActorTemplate(v.astype(np.float32), np.asarray(triangles, np.uint32), np.asarray(part, np.int64),
                         np.asarray(group, np.int64), palette, name)


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


def _static_obstacle() -> ActorTemplate:
    """A traffic cone / barrier post in the unit box: a base plate and a tapering body in two bands."""
    parts = [
        (_box((-0.5, -0.5, -0.5), (0.5, 0.5, -0.42)), _PART_DARK),  # base plate
        (_box((-0.32, -0.32, -0.42), (0.32, 0.32, -0.05)), _PART_BODY),
        (_box((-0.22, -0.22, -0.05), (0.22, 0.22, 0.2)), _PART_LAMP_FRONT),  # reflective band
        (_box((-0.12, -0.12, 0.2), (0.12, 0.12, 0.5)), _PART_BODY),
    ]
    return _assemble(parts)


#: classes drawn with a catalogue model of cosim.sensors.assets.vehicles
VEHICLE_CLASSES = ("car", "van", "truck", "bus", "motorcycle", "bicycle")

#: shapes of the classes that are not procedural models
ACTOR_TEMPLATES: dict[str, ActorTemplate] = {"drone": _drone(), "static_obstacle": _static_obstacle()}


@cache
def vehicle_template(name: str) -> ActorTemplate:
    """The unit-box template of vehicle model ``name`` (built once per process)."""
    from .assets import vehicles

    v, t, part, grp, _ = vehicles.build(name)
    palette = None
    if vehicles.BY_NAME[name].cls in ("motorcycle", "bicycle"):  # the rider's skin and clothes
        from .assets.people import Person

        palette = np.zeros((N_PARTS, 3), np.float32)
        palette[_PART_SKIN:_PART_SHOES + 1] = Person.from_key(f"rider:{name}").colours
    return unit_template(v, t, part, grp, palette, name)


@cache
def _models_by_dims() -> dict[tuple, str]:
    from .assets import vehicles

    return {(m.cls, *vehicles.dims(m.name)): m.name for m in vehicles.MODELS}


def vehicle_model(cls: str, size_m, key: str) -> str:
    """The catalogue model of a vehicle: the one whose dimensions its box has (a SUMO vType made from
    that model), else one of the class's models picked by ``key`` (scaled into the box)."""
    from .assets import vehicles

    name = _models_by_dims().get((cls, *(round(float(x), 2) for x in size_m)))
    if name is not None:
        return name
    names = [m.name for m in vehicles.MODELS if m.cls == cls]
    return names[zlib.crc32(key.encode()) % len(names)]


def person_template(key: str, gait_phase: float, speed_mps: float) -> ActorTemplate:
    """The unit-box template of person ``key`` posed at ``gait_phase`` walking at ``speed_mps`` (at the
    steps the traffic worker's boxes use, :func:`cosim.sensors.assets.people.posed_box`)."""
    from .assets import people

    return _person_template(key, *people.quantized(gait_phase, speed_mps))


@lru_cache(maxsize=1024)  # about 20 MB (19 kB a posed person)
def _person_template(key: str, q_phase: int, q_speed: int) -> ActorTemplate:
    from .assets import people

    p, v, t, part, grp, _, _ = people.posed_steps(key, q_phase, q_speed)
    palette = np.zeros((N_PARTS, 3), np.float32)
    palette[_PART_SKIN:_PART_SHOES + 1] = p.colours
    return unit_template(v, t, part, grp, palette, f"person:{key}")


def person_key(actor) -> str:
    """Which person a pedestrian is: its engine id (the SUMO person id), else its track id."""
    return actor.source_id or f"track:{actor.track_id}"


def actor_template(actor) -> ActorTemplate:
    """The shape of ``actor`` (a :class:`cosim.snapshot.Actor`) at its tick."""
    if actor.cls in VEHICLE_CLASSES:
        return vehicle_template(vehicle_model(actor.cls, actor.size_m, person_key(actor)))
    if actor.cls == "pedestrian":
        speed = math.hypot(actor.velocity_mps[0], actor.velocity_mps[1])
        return person_template(person_key(actor), actor.gait_phase, speed)
    return template_for(actor.cls)


def template_for(cls: str, gait_phase: float = 0.0) -> ActorTemplate:
    """A shape of the class: its first catalogue model, a walking person at ``gait_phase``, a drone..."""
    if cls in VEHICLE_CLASSES:
        from .assets import vehicles

        return vehicle_template(next(m.name for m in vehicles.MODELS if m.cls == cls))
    if cls == "pedestrian":
        return person_template("pedestrian", gait_phase, 1.4)
    try:
        return ACTOR_TEMPLATES[cls]
    except KeyError:
        known = ", ".join([*VEHICLE_CLASSES, "pedestrian", *ACTOR_TEMPLATES])
        raise CosimError(f"no actor shape for class {cls!r}; known: {known}") from None


HAZARD_AMBER = (1.0, 0.5, 0.0)

#: the paints vehicles come in, with the share of each (white, black, grey and silver are three in four
#: new European cars); a vehicle's paint is one of them, lightened or darkened a little per track id
_PAINT_SHARES = np.array([0.24, 0.20, 0.17, 0.12, 0.09, 0.07, 0.04, 0.04, 0.03], np.float64)
_PAINT_TABLE = np.array(
    [(0.85, 0.85, 0.85), (0.05, 0.05, 0.06), (0.35, 0.36, 0.38), (0.70, 0.71, 0.74), (0.10, 0.20, 0.45),
     (0.55, 0.05, 0.05), (0.15, 0.35, 0.20), (0.70, 0.55, 0.15), (0.85, 0.40, 0.08)], np.float32,
)
_PAINT_CDF = np.cumsum(_PAINT_SHARES) / _PAINT_SHARES.sum()

#: per part: albedo (linear RGB), diffuse LiDAR reflectivity, emissive, retro-reflectivity, glass
_PART_ALBEDO = np.array([
    (0.5, 0.5, 0.5), (0.05, 0.07, 0.09), (0.03, 0.03, 0.03), (0.95, 0.95, 0.9), (0.7, 0.05, 0.05),
    (0.12, 0.12, 0.13), (0.55, 0.56, 0.58), (0.92, 0.92, 0.86), (0.09, 0.09, 0.10), (0.86, 0.86, 0.84),
    (0.76, 0.57, 0.43), (0.15, 0.10, 0.07), (0.20, 0.25, 0.40), (0.15, 0.15, 0.20), (0.10, 0.10, 0.10)],
    np.float32)
_PART_REFL = np.array([0.0, 0.05, 0.03, 0.3, 0.3, 0.08, 0.45, 0.5, 0.06, 0.6, 0.45, 0.15, 0.4, 0.35, 0.1],
                      np.float32)
_PART_EMIS = np.array([0.0, 0.0, 0.0, 1.0, 0.6] + [0.0] * 10, np.float32)
#: lamp units carry reflectors; licence plates are retro-reflective sheeting (EN 12899 / ECE R 69 class)
_PART_RETRO = np.array([0.0, 0.0, 0.0, 0.6, 0.6, 0.0, 0.0, 0.9] + [0.0] * 7, np.float32)
_PART_GLASS_FLAG = np.zeros(N_PARTS, bool)
_PART_GLASS_FLAG[_PART_GLASS] = True


def vehicle_paint(track_id: int) -> np.ndarray:
    """A vehicle's paint (3,): a colour drawn by the market shares, its brightness varied per track."""
    k = int(np.searchsorted(_PAINT_CDF, _hash01(track_id, 7), side="right"))
    shade = 0.88 + 0.24 * _hash01(track_id, 11)
    return np.clip(_PAINT_TABLE[min(k, len(_PAINT_TABLE) - 1)] * shade, 0.0, 1.0).astype(np.float32)


def actor_material(cls: str, track_id: int, part: np.ndarray, hazard_lamps_on: bool = False,
                   palette: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Albedo (T, 3), reflectivity (T,), emissive (T,) of an actor's triangles from their part ids; with
    ``hazard_lamps_on`` every lamp unit (front and rear) glows amber (a blinking hazard light, lit);
    ``palette`` (N_PARTS, 3): colours of the person parts (skin, hair, clothes)."""
    paint = vehicle_paint(track_id)
    if cls == "bus":
        paint = np.array((0.85, 0.65, 0.10), np.float32) if _hash01(track_id, 3) > 0.5 else paint
    if cls == "drone":
        paint = np.array((0.9, 0.9, 0.92), np.float32)
    if cls == "static_obstacle":
        paint = np.array((0.95, 0.35, 0.02), np.float32)  # safety orange
    table = _PART_ALBEDO.copy()
    table[_PART_BODY] = paint
    if palette is not None:
        table[_PART_SKIN:] = palette[_PART_SKIN:]
    # diffuse LiDAR reflectivity: paint by its brightness (dark paint low), glass and tyres low, lamp
    # units middling (their reflectors add a retro-reflective term, see cosim.sensors.lidar)
    refl_t = _PART_REFL.copy()
    refl_t[_PART_BODY] = 0.05 + 0.7 * float(paint @ np.array([0.2126, 0.7152, 0.0722], np.float32))
    emis_t = _PART_EMIS.copy()
    if hazard_lamps_on:
        table[_PART_LAMP_FRONT] = table[_PART_LAMP_REAR] = HAZARD_AMBER
        emis_t[_PART_LAMP_FRONT] = emis_t[_PART_LAMP_REAR] = 0.6
    return table[part], refl_t[part], emis_t[part]


def part_optics(part: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Retro-reflectivity (T,) float32 and glass flag (T,) bool of actor triangles from their part ids."""
    return _PART_RETRO[part], _PART_GLASS_FLAG[part]
