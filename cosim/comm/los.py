"""Line of sight between antennas: LOS, NLOSv (an actor in between) or NLOS (the static world).

The static world is the sensor suite's Open3D scene (:class:`cosim.sensors.scene.StaticScene`, one
BVH per episode, triangles tagged with their semantic class): the segment between two antennas is
cast as a ray whose direction is the segment itself (so ``t`` in [0, 1] lies between the ends) and
every crossing is listed. Thin static parts (poles, street lights, lane markings, the RSU masts)
do not block a radio link and are skipped; anything else (buildings, vegetation, terrain, road
bodies) makes the link NLOS.

Actors are tested as their oriented 3D label boxes (a slab test per segment and box, vectorised),
without the two ends' own boxes: a box crossed by the segment makes the link NLOSv, and the highest
top of those boxes is the blocker height of TR 37.885's blockage loss. A building wins over a
vehicle (NLOS), as in TR 37.885 where NLOSv means "blocked by vehicles only".
"""

from __future__ import annotations

import logging
import time

import numpy as np

from cosim.classes import SEMANTIC_CLASSES
from cosim.geometry import rotation_matrix
from cosim.snapshot import Actor

log = logging.getLogger(__name__)

LOS, NLOSV, NLOS = 0, 1, 2
LOS_STATES: tuple[str, ...] = ("los", "nlosv", "nlos")  # index = state code
#: Static classes a radio link passes: thin (poles, lamps, masts) or flat (markings).
SEE_THROUGH: frozenset[str] = frozenset({"unlabelled", "pole", "street_light", "lane_marking", "rsu"})
END_MARGIN_M = 0.05  # [m] crossings this close to an antenna are the antenna's own mount, not a blocker


class LinkScene:
    """The static scene for line-of-sight tests: an Open3D scene and the semantic class per triangle.

    ``scene`` is a :class:`cosim.sensors.scene.StaticScene` (built by the sensor suite, or once by
    :meth:`from_layout` when sensors are off).
    """

    def __init__(self, static, ground_z_m: float = 0.0):
        self.static = static
        self.ground_z_m = float(ground_z_m)
        see_through = np.array([name in SEE_THROUGH for name in SEMANTIC_CLASSES], bool)
        self._blocks = ~see_through[np.asarray(static.mesh.semantic, np.int64)] if static.n_triangles else \
            np.zeros(0, bool)

    @classmethod
    def from_layout(cls, layout) -> LinkScene:
        """Build the static scene of a :class:`cosim.world.types.StaticLayout` (logs the time it takes)."""
        from cosim.sensors.meshes import static_mesh
        from cosim.sensors.scene import StaticScene

        t0 = time.perf_counter()
        static = StaticScene(static_mesh(layout))
        log.info("link scene: %d static triangles built in %.2f s", static.n_triangles, time.perf_counter() - t0)
        return cls(static, layout.ground_z_m)

    def static_blocked(self, a_m: np.ndarray, b_m: np.ndarray) -> np.ndarray:
        """(N,) bool: a blocking static triangle crosses the open segment a -> b (both (N, 3) in map)."""
        n = len(a_m)
        scene = self.static.scene
        if n == 0 or scene is None:
            return np.zeros(n, bool)
        import open3d as o3d

        d = b_m - a_m
        length = np.maximum(np.linalg.norm(d, axis=1), 1e-9)
        rays = np.ascontiguousarray(np.hstack([a_m, d]), np.float32)
        ans = scene.list_intersections(o3d.core.Tensor(rays))
        splits = ans["ray_splits"].numpy()
        ray_ids = ans["ray_ids"].numpy().astype(np.int64)
        t = ans["t_hit"].numpy().astype(np.float64)
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        del splits
        margin = END_MARGIN_M / length[ray_ids]
        hit = (t > margin) & (t < 1.0 - margin) & self._blocks[prim]
        out = np.zeros(n, bool)
        out[ray_ids[hit]] = True
        return out


def actor_boxes(actors: tuple[Actor, ...] | list[Actor]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Label boxes as arrays: centres (K, 3), rotations map <- body (K, 3, 3), half sizes (K, 3), tracks (K,)."""
    if not actors:
        return np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0, np.int64)
    centres = np.array([a.center_m for a in actors], np.float64)
    rots = np.array([rotation_matrix(a.rotation) for a in actors], np.float64)
    halves = np.array([a.size_m for a in actors], np.float64) / 2.0
    tracks = np.array([a.track_id for a in actors], np.int64)
    return centres, rots, halves, tracks


def actors_blocking(a_m: np.ndarray, b_m: np.ndarray, own_a: np.ndarray, own_b: np.ndarray,
                    boxes: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
    """(N, K) bool: box k crosses segment n (slab test), the ends' own boxes (tracks ``own_a``,
    ``own_b`` (N,), -1 for none) excluded."""
    centres, rots, halves, tracks = boxes
    n, k = len(a_m), len(centres)
    if n == 0 or k == 0:
        return np.zeros((n, k), bool)
    # segment ends in every box's frame: (N, K, 3)
    pa = np.einsum("kji,nkj->nki", rots, a_m[:, None, :] - centres[None])
    pb = np.einsum("kji,nkj->nki", rots, b_m[:, None, :] - centres[None])
    d = pb - pa
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (-halves[None] - pa) * inv
        t2 = (halves[None] - pa) * inv
    tlo = np.where(np.isnan(t1), -np.inf, np.minimum(t1, t2))
    thi = np.where(np.isnan(t2), np.inf, np.maximum(t1, t2))
    # a segment parallel to a slab misses it when it starts outside that slab
    parallel = d == 0.0
    outside = np.abs(pa) > halves[None]
    tlo = np.where(parallel, np.where(outside, np.inf, -np.inf), tlo)
    thi = np.where(parallel, np.where(outside, -np.inf, np.inf), thi)
    enter = np.maximum(tlo.max(axis=2), 0.0)
    leave = np.minimum(thi.min(axis=2), 1.0)
    crosses = enter < leave
    own = (tracks[None, :] == own_a[:, None]) | (tracks[None, :] == own_b[:, None])
    return crosses & ~own


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
