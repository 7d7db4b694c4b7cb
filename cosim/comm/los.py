"""Line of sight between antennas: LOS, NLOSv (an actor in between) or NLOS (the static world).

The static world is a ray-backend scene (:class:`LinkScene`: the side walls of the layout's blocking
prisms, one BVH per episode, whether sensors run or not; :mod:`cosim.sensors.raycast`, the episode's
``sensors.ray_backend``): the segment between two antennas is cast as a ray whose direction is the
segment itself (so ``t`` in [0, 1] lies between the ends), from just past the first end, and its
nearest crossing decides. Thin static parts (poles, street lights, lane markings, the RSU
masts) do not block a radio link and are skipped; anything else (buildings, vegetation, terrain,
road bodies) makes the link NLOS.

Actors are tested as their oriented 3D label boxes (a slab test per segment and box, vectorised),
without the two ends' own boxes: a box crossed by the segment makes the link NLOSv, and the highest
top of those boxes is the blocker height of TR 37.885's blockage loss. A building wins over a
vehicle (NLOS), as in TR 37.885 where NLOSv means "blocked by vehicles only".
"""

from __future__ import annotations

import logging
import time

import numpy as np

from cosim.snapshot import Actor

log = logging.getLogger(__name__)

LOS, NLOSV, NLOS = 0, 1, 2
LOS_STATES: tuple[str, ...] = ("los", "nlosv", "nlos")  # index = state code
#: Static classes a radio link passes: thin (poles, lamps, masts) or flat (markings).
SEE_THROUGH: frozenset[str] = frozenset({"unlabelled", "pole", "street_light", "lane_marking", "rsu"})
END_MARGIN_M = 0.05  # [m] crossings this close to an antenna are the antenna's own mount, not a blocker
_MAX_PASSES = 16  # non-blocking crossings a segment is followed through


class LinkScene:
    """A ray-backend scene of the static world for line-of-sight tests and, per triangle, whether it blocks.

    :meth:`from_layout` builds only the side walls of the layout's blocking prisms (a segment whose
    ends lie outside a vertical prism can only enter and leave it through its walls: top and bottom
    are planes it crosses at most once each), which needs no polygon triangulation. The links use it
    whether sensors run or not: the renderer's procedural trees (porous crowns, branches) are for
    cameras and LiDAR, and a radio link sees a tree as its crown's prism.
    """

    def __init__(self, scene, blocks: np.ndarray, ground_z_m: float = 0.0):
        self.scene = scene
        self.blocks = np.asarray(blocks, bool)  # (T,) per triangle of ``scene``
        self.ground_z_m = float(ground_z_m)

    @property
    def n_triangles(self) -> int:
        return len(self.blocks)

    @classmethod
    def from_layout(cls, layout, backend: str | None = None) -> LinkScene:
        """The walls of a :class:`cosim.world.types.StaticLayout`'s blocking prisms, built by the ray backend
        ``backend`` (default: the renderer's; logs the time)."""
        from cosim.sensors.raycast import DEFAULT_BACKEND, build, ray_backend

        t0 = time.perf_counter()
        verts, tris = wall_mesh(layout)
        scene = build(ray_backend(backend or DEFAULT_BACKEND), verts, tris, "high")
        log.info("link scene: %d wall triangles built in %.2f s", len(tris), time.perf_counter() - t0)
        return cls(scene, np.ones(len(tris), bool), layout.ground_z_m)

    def static_blocked(self, a_m: np.ndarray, b_m: np.ndarray) -> np.ndarray:
        """(N,) bool: a blocking static triangle crosses the open segment a -> b (both (N, 3) in map)."""
        n = len(a_m)
        if n == 0 or self.scene is None:
            return np.zeros(n, bool)
        d = b_m - a_m
        margin = END_MARGIN_M / np.maximum(np.linalg.norm(d, axis=1), 1e-9)
        start = margin.copy()  # [segment lengths] where the search goes on from
        out = np.zeros(n, bool)
        todo = np.arange(n)
        for _ in range(_MAX_PASSES):  # past crossings that do not block, on to the next
            rays = np.ascontiguousarray(np.hstack([a_m[todo] + start[todo, None] * d[todo], d[todo]]), np.float32)
            t, prim = self.scene.closest(rays)
            t_seg = start[todo] + t
            inside = (prim >= 0) & (t_seg < 1.0 - margin[todo])
            blocking = inside & self.blocks[np.maximum(prim, 0)]
            out[todo[blocking]] = True
            again = inside & ~blocking
            start[todo[again]] = t_seg[again] + 1e-6
            todo = todo[again]
            if not len(todo):
                break
        return out


def wall_mesh(layout) -> tuple[np.ndarray, np.ndarray]:
    """Side walls of the layout's blocking prisms: vertices (V, 3) float32 and triangles (T, 3) uint32."""
    verts: list[np.ndarray] = []
    tris: list[np.ndarray] = []
    base = 0
    for p in layout.prisms:
        if p.cls in SEE_THROUGH or p.z1_m <= p.z0_m or len(p.footprint) < 3:
            continue
        fp = np.asarray(p.footprint, np.float64)
        k = len(fp)
        v = np.empty((2 * k, 3))
        v[:k, :2] = fp
        v[:k, 2] = p.z0_m
        v[k:, :2] = fp
        v[k:, 2] = p.z1_m
        i = np.arange(k)
        j = (i + 1) % k
        tris.append(np.concatenate([np.stack([i, j, k + j], 1), np.stack([i, k + j, k + i], 1)]) + base)
        verts.append(v)
        base += 2 * k
    if not tris:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32)
    return np.concatenate(verts).astype(np.float32), np.concatenate(tris).astype(np.uint32)


def actor_boxes(actors: tuple[Actor, ...] | list[Actor]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Label boxes as arrays: centres (K, 3), rotations map <- body (K, 3, 3), half sizes (K, 3), tracks (K,)."""
    if not actors:
        return np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0, np.int64)
    centres = np.array([a.center_m for a in actors], np.float64)
    x, y, z, w = np.array([a.rotation for a in actors], np.float64).T
    rots = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], 1)
    halves = np.array([a.size_m for a in actors], np.float64) / 2.0
    tracks = np.array([a.track_id for a in actors], np.int64)
    return centres, rots, halves, tracks


def actors_blocking(a_m: np.ndarray, b_m: np.ndarray, own_a: np.ndarray, own_b: np.ndarray,
                    boxes: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
    """(N, K) bool: box k crosses segment n, the ends' own boxes (tracks ``own_a``, ``own_b`` (N,),
    -1 for none) excluded. Boxes whose bounding sphere misses the segment are culled first; the
    rest get a slab test in the box frame."""
    centres, rots, halves, tracks = boxes
    n, k = len(a_m), len(centres)
    out = np.zeros((n, k), bool)
    if n == 0 or k == 0:
        return out
    seg = b_m - a_m
    seg_len2 = np.maximum((seg**2).sum(1), 1e-18)
    rel = centres[None] - a_m[:, None]  # (N, K, 3)
    t = np.clip((rel * seg[:, None]).sum(2) / seg_len2[:, None], 0.0, 1.0)
    gap2 = ((rel - t[..., None] * seg[:, None]) ** 2).sum(2)
    own = (tracks[None, :] == own_a[:, None]) | (tracks[None, :] == own_b[:, None])
    ni, ki = np.nonzero((gap2 <= (halves**2).sum(1)[None]) & ~own)
    if len(ni) == 0:
        return out
    r = rots[ki]  # (M, 3, 3) map <- body
    pa = np.einsum("mji,mj->mi", r, a_m[ni] - centres[ki])  # segment ends in the box frame
    d = np.einsum("mji,mj->mi", r, seg[ni])
    h = halves[ki]
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-h - pa) / d
        t2 = (h - pa) / d
    parallel = d == 0.0
    inside = np.abs(pa) <= h
    tlo = np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
    thi = np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
    enter = np.maximum(tlo.max(1), 0.0)
    leave = np.minimum(thi.min(1), 1.0)
    out[ni[enter < leave], ki[enter < leave]] = True
    return out


def box_tops_m(boxes: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
    """(K,) highest z [m] of each box."""
    centres, rots, halves, _ = boxes
    if len(centres) == 0:
        return np.zeros(0)
    return centres[:, 2] + np.abs(rots[:, 2, :] * halves).sum(axis=1)


def line_of_sight(scene: LinkScene, a_m: np.ndarray, b_m: np.ndarray, own_a: np.ndarray, own_b: np.ndarray,
                  actors: tuple[Actor, ...] | list[Actor]) -> tuple[np.ndarray, np.ndarray]:
    """State code (N,) int8 (:data:`LOS`, :data:`NLOSV`, :data:`NLOS`) of each segment a -> b, and the
    blocker top z [m] (N,) of NLOSv segments (NaN elsewhere)."""
    boxes = actor_boxes(actors)
    by_actor = actors_blocking(a_m, b_m, own_a, own_b, boxes)
    by_static = scene.static_blocked(a_m, b_m)
    tops = box_tops_m(boxes)
    blocker = np.where(by_actor, tops[None, :], -np.inf).max(axis=1) if by_actor.size else np.full(len(a_m), -np.inf)
    state = np.where(by_static, NLOS, np.where(np.isfinite(blocker), NLOSV, LOS)).astype(np.int8)
    return state, np.where(state == NLOSV, blocker, np.nan)
