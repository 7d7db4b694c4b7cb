"""Ray casting over the static world (one scene per episode) plus the actors of one tick.

The static scene's BVH is built once; the actors go into a small second scene rebuilt per tick (one
per time a LiDAR casts at, cached, shared by every sensor; the few rays that meet a sensor's own
shape first are cast again in a scene without it, made only for the sensors that need one), and each
ray takes the nearer of the two hits. Hits are reported as a *global triangle index*: static
triangles first, then the tick's actor triangles, then one sentinel row meaning "no hit"
(:attr:`TickScene.miss`), so every per-triangle table (class, instance, colour...) is a single gather.

The scenes are built and cast by a ray backend (:mod:`cosim.sensors.raycast`, scenario key
``sensors.ray_backend``): the static world at build quality ``high``, a tick's actors ``medium``,
the actors moved to a LiDAR firing's time ``low``.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from cosim.classes import semantic_id
from cosim.geometry import rotation_matrix
from cosim.snapshot import Actor

from .meshes import TriMesh, actor_material, actor_template, concat, empty_mesh, part_optics
from .raycast import DEFAULT_BACKEND, Built, Quality, RayBackend, build, misses, ray_backend
from .rig import rotate


def _scene(backend: RayBackend, mesh: TriMesh, quality: Quality) -> Built | None:
    return build(backend, mesh.vertices, mesh.triangles, quality)


def cast(scene: Built | None, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hits of ``rays`` (N, 6) float32 [origin, direction] in ``scene``.

    Returns ``t`` (N,) float32 in units of the direction's length (inf on a miss) and the primitive
    index (N,) int32 (-1 on a miss).
    """
    if scene is None or rays.shape[0] == 0:
        return misses(rays.shape[0])
    return scene.closest(rays)


@dataclass
class CastTimer:
    """Accumulates the seconds spent inside the ray backend and the rays cast (benchmarking)."""

    seconds: float = 0.0
    rays: int = 0


def place_actors(actors: tuple[Actor, ...] | list[Actor], with_faces: bool = False):
    """Actor shapes placed in the map frame: mesh and the track id per triangle (T,) int64 (and, with
    ``with_faces``, a function giving the face id per triangle (T,) int32 of :meth:`TriMesh.faces` from the
    templates' ids, made on demand: only cameras need them, and a posed person's are made anew, and the vertex
    and triangle counts per actor)."""
    parts: list[TriMesh] = []
    tracks: list[np.ndarray] = []
    templates = []
    counts: list[int] = []
    for a in actors:
        tpl = actor_template(a)
        v = tpl.vertices.astype(np.float64) * np.asarray(a.size_m, np.float64)
        v = rotate(v, rotation_matrix(a.rotation)) + np.asarray(a.center_m, np.float64)
        alb, refl, emis = actor_material(a.cls, a.track_id, tpl.part, a.hazard_lamps_on, tpl.palette)
        retro, glass = part_optics(tpl.part)
        t = len(tpl.triangles)
        parts.append(
            TriMesh(v.astype(np.float32), tpl.triangles, np.full(t, semantic_id(a.cls), np.uint8),
                    np.full(t, a.track_id, np.uint32), alb, refl, emis, tpl.group, retro, glass)
        )
        tracks.append(np.full(t, a.track_id, np.int64))
        if with_faces:
            templates.append(tpl)
            counts.append((len(tpl.vertices), t))
    mesh = concat(parts) if parts else empty_mesh()
    track = np.concatenate(tracks) if tracks else np.zeros(0, np.int64)
    if not with_faces:
        return mesh, track

    def faces() -> np.ndarray:
        out, f_off = [], 0
        for tpl in templates:
            out.append(tpl.faces + f_off)
            f_off += int(tpl.faces.max(initial=-1)) + 1
        return np.concatenate(out) if out else np.zeros(0, np.int32)

    return mesh, track, faces, counts


class StaticScene:
    """The episode's static mesh and its scene, built by the ray backend named ``backend``."""

    def __init__(self, mesh: TriMesh, backend: str = DEFAULT_BACKEND):
        self.mesh = mesh
        self.normals = mesh.normals()
        self.faces = mesh.faces()
        self.backend = ray_backend(backend)
        self.scene = _scene(self.backend, mesh, "high")

    @property
    def n_triangles(self) -> int:
        return self.mesh.n_triangles


@dataclass
class TickScene:
    """Static scene plus one tick's actors; see the module docstring for the global index."""

    static: StaticScene
    actors: TriMesh
    actor_track: np.ndarray  # (Ta,) int64 track id per actor triangle
    actor_velocity: np.ndarray | None = None  # (Va,) x 3 float64 [m/s] map velocity of each actor vertex
    actor_spheres: np.ndarray | None = None  # (A, 8): centre (3), radius, velocity (3), track id per actor
    # (Ta,) int32 face ids of the actor triangles, or a function making them (None: computed from the mesh)
    actor_faces: np.ndarray | Callable[[], np.ndarray] | None = None
    actor_counts: tuple[tuple[int, int], ...] | None = None  # (vertices, triangles) per actor, as actor_spheres
    timer: CastTimer = field(default_factory=CastTimer)
    _cache: dict = field(default_factory=dict)
    _lock: threading.RLock = field(default_factory=threading.RLock)  # re-entrant: scenes are made of prototypes

    @classmethod
    def build(cls, static: StaticScene, actors) -> TickScene:
        mesh, track, faces, counts = place_actors(actors, with_faces=True)
        vel = [np.broadcast_to(np.asarray(a.velocity_mps, np.float64), (n, 3)) for a, (n, _) in zip(actors, counts,
                                                                                                 strict=True)]
        spheres = np.array([[*a.center_m, 0.5 * float(np.linalg.norm(a.size_m)), *a.velocity_mps, a.track_id]
                            for a in actors], np.float64).reshape(-1, 8)
        return cls(static, mesh, track, np.concatenate(vel) if vel else np.zeros((0, 3)), spheres,
                   actor_faces=faces, actor_counts=tuple(counts))

    def _prototypes(self) -> tuple[list, np.ndarray] | None:
        """One scene per actor (its triangles at the tick, None for an actor without any) and the index of each
        one's first triangle among the actors', for backends that instance scenes (``instances``, see
        :mod:`cosim.sensors.raycast`); None for others or when the actor counts are unknown."""
        backend = self.static.backend
        if not hasattr(backend, "instances") or self.actor_counts is None:
            return None
        with self._lock:
            if "prototypes" in self._cache:
                return self._cache["prototypes"]
        counts = np.asarray(self.actor_counts, np.int64).reshape(-1, 2)
        v_end, t_end = np.cumsum(counts, axis=0).T
        v_start, t_start = v_end - counts[:, 0], t_end - counts[:, 1]
        tris = self.actors.triangles
        protos = [backend.build(self.actors.vertices[v0:v1], (tris[t0:t1] - v0).astype(np.uint32), "medium")
                  if t1 > t0 else None
                  for v0, v1, t0, t1 in zip(v_start, v_end, t_start, t_end, strict=True)]
        entry = (protos, t_start)
        with self._lock:
            return self._cache.setdefault("prototypes", entry)

    def _moved(self, dt_s: float, exclude_track: int | None = None) -> Built | None:
        """The actors moved by their velocity x ``dt_s``, as translated instances of :meth:`_prototypes`
        (without ``exclude_track``'s); None when the backend has no instances."""
        found = self._prototypes()
        if found is None:
            return None
        protos, offsets = found
        sp = self.actor_spheres
        if exclude_track is not None:
            protos = [None if int(track) == exclude_track else p for p, track in zip(protos, sp[:, 7], strict=True)]
        backend = self.static.backend
        return Built(backend, backend.instances(protos, sp[:, 4:7] * dt_s, offsets))

    def swept_boxes(self, exclude_track: int | None, dt_min_s: float):
        """Scene of one axis-aligned box per actor (without ``exclude_track``) holding it over
        [``dt_min_s``, 0] from the tick, and the boxes' corners ``lo``, ``hi`` (B, 3): a ray that misses
        every box misses the actors at every time."""
        key = ("swept", -1 if exclude_track is None else int(exclude_track), float(dt_min_s))
        with self._lock:
            if key in self._cache:
                return self._cache[key]
            sp = self.actor_spheres if self.actor_spheres is not None else np.zeros((0, 8))
            if exclude_track is not None:
                sp = sp[sp[:, 7] != exclude_track]
            c0, c1 = sp[:, :3], sp[:, :3] + sp[:, 4:7] * dt_min_s
            pad = sp[:, 3:4] + 0.05
            lo, hi = np.minimum(c0, c1) - pad, np.maximum(c0, c1) + pad
            parts = [_box_mesh(a, b) for a, b in zip(lo, hi, strict=True)]
            if parts:
                v = np.concatenate([p[0] for p in parts]).astype(np.float32)
                t = np.concatenate([p[1] + 8 * k for k, p in enumerate(parts)]).astype(np.uint32)
                scene = build(self.static.backend, v, t, "low")
            else:
                scene = None
            self._cache[key] = (scene, lo, hi)
            return self._cache[key]

    @cached_property
    def actors_move(self) -> bool:
        """True when some actor has a velocity (then casts at other times see it elsewhere)."""
        return self.actor_velocity is not None and bool(np.any(self.actor_velocity))

    @property
    def n_static(self) -> int:
        return self.static.n_triangles

    @property
    def miss(self) -> int:
        """Global index meaning "no hit" (one past the last triangle)."""
        return self.static.n_triangles + self.actors.n_triangles

    def table(self, static_values: np.ndarray, actor_values: np.ndarray, miss_value) -> np.ndarray:
        """A per-global-index lookup table (miss + 1 rows): static rows, actor rows, the miss row."""
        miss = np.asarray(miss_value, static_values.dtype).reshape((1, *static_values.shape[1:]))
        return np.concatenate([static_values, actor_values.astype(static_values.dtype), miss])

    def _actor_scene(self, dt_s: float = 0.0):
        """Scene of all the actors moved by their velocity x ``dt_s`` (one per time, shared by every
        sensor: a sensor's own shape is dealt with by :meth:`_cast_actors` for the rays that meet it, so that a
        tick builds one BVH of all the actors rather than one per sensor-carrying actor)."""
        key = float(dt_s) if self.actors_move else 0.0
        with self._lock:
            if key in self._cache:
                return self._cache[key]
            verts = self.actors.vertices
            if dt_s and self.actors_move:
                moved = self._moved(dt_s)
                if moved is not None:
                    self._cache[key] = moved
                    return moved
                verts = (verts + self.actor_velocity * dt_s).astype(np.float32)
            sub = self.actors if verts is self.actors.vertices else TriMesh(
                verts, *(getattr(self.actors, f) for f in ("triangles", "semantic", "instance", "albedo",
                                                            "reflectivity", "emissive", "group", "retro", "glass")))
            scene = _scene(self.static.backend, sub, "medium" if key == 0.0 else "low")
            self._cache[key] = scene
            return scene

    def _without(self, exclude_track: int, dt_s: float):
        """Scene of the actors at ``dt_s`` without ``exclude_track``'s shape and the actor triangle index
        of each of its triangles (None: the actors' own, a scene of instances) (made on demand: only sensors
        whose rays meet their own shape need one)."""
        key = ("without", int(exclude_track), float(dt_s) if self.actors_move else 0.0)
        with self._lock:
            if key in self._cache:
                return self._cache[key]
            if key[2]:
                moved = self._moved(dt_s, exclude_track)
                if moved is not None:  # instances keep the actors' triangle indices
                    return self._cache.setdefault(key, (moved, None))
        keep = np.nonzero(self.actor_track != exclude_track)[0].astype(np.int32)
        verts = self.actors.vertices
        if dt_s and self.actors_move:
            verts = (verts + self.actor_velocity * dt_s).astype(np.float32)
        a = self.actors
        sub = TriMesh(verts, a.triangles[keep], a.semantic[keep], a.instance[keep], a.albedo[keep],
                      a.reflectivity[keep], a.emissive[keep], a.group[keep])
        entry = (_scene(self.static.backend, sub, "medium" if key[2] == 0.0 else "low"), keep)
        with self._lock:
            return self._cache.setdefault(key, entry)

    def _cast_actors(self, rays: np.ndarray, exclude_track: int | None,
                     dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Nearest actor hits of ``rays`` at ``dt_s`` (``t``, actor triangle index, -1 on a miss), ignoring
        ``exclude_track``'s own shape: the rays whose nearest hit is on it are cast again in a scene without
        it (:meth:`_without`), which gives what that scene gives for every ray."""
        scene = self._actor_scene(dt_s)
        t, prim = cast(scene, rays)
        if exclude_track is None or scene is None:
            return t, prim
        track = np.concatenate([self.actor_track, [-1]])
        own = np.nonzero(np.take(track, prim) == exclude_track)[0]
        if not len(own):
            return t, prim
        other, keep = self._without(exclude_track, dt_s)
        t2, p2 = cast(other, rays[own])
        t[own] = t2
        prim[own] = p2 if keep is None or not len(keep) else np.where(p2 >= 0, keep[np.maximum(p2, 0)], -1)
        return t, prim

    def _actor_face_ids(self) -> np.ndarray:
        f = self.actor_faces
        if f is None:
            return self.actors.faces()
        return f() if callable(f) else f

    @cached_property
    def labels(self) -> dict[str, np.ndarray]:
        """Per-global-index tables: ``semantic`` uint8, ``instance`` uint32, ``reflectivity`` float32,
        ``normal`` (3,) float32, ``albedo`` (3,) float32, ``emissive`` float32, ``material`` uint8, ``face``
        int32 (see :meth:`TriMesh.faces`; -1 for the miss row), ``retro`` float32, ``glass`` bool,
        ``leaf_density`` float32 (each miss + 1 rows). Each is made on first use (a LiDAR-only tick never
        makes the cameras' ones)."""
        a, m = self.actors, self.static.mesh
        return _Tables({
            "semantic": lambda: self.table(m.semantic, a.semantic, 0),
            "instance": lambda: self.table(m.instance, a.instance, 0),
            "reflectivity": lambda: self.table(m.reflectivity, a.reflectivity, 0.0),
            "normal": lambda: self.table(self.static.normals, a.normals(), (0.0, 0.0, 1.0)),
            "albedo": lambda: self.table(m.albedo, a.albedo, (0.0, 0.0, 0.0)),
            "emissive": lambda: self.table(m.emissive, a.emissive, 0.0),
            "material": lambda: self.table(m.material, a.material, 0),
            "face": lambda: self.table(self.static.faces, self._actor_face_ids()
                                       + (int(self.static.faces.max(initial=-1)) + 1), -1),
            "retro": lambda: self.table(m.retro_values(), a.retro_values(), 0.0),
            "glass": lambda: self.table(m.glass_values(), a.glass_values(), False),
            "leaf_density": lambda: self.table(m.leaf_density_values(), a.leaf_density_values(), 0.0),
        })

    def occluded(self, rays: np.ndarray, with_static: bool = True, with_actors: bool = True) -> np.ndarray:
        """(N,) bool: whether each ray (N, 6) float32 meets anything at all (static or any actor; shadow rays)."""
        t0 = time.perf_counter()
        out = np.zeros(rays.shape[0], bool)
        if rays.shape[0]:
            if with_static and self.static.scene is not None:
                out |= self.static.scene.occluded(rays)
            scene = self._actor_scene() if with_actors else None
            if scene is not None:
                rest = np.nonzero(~out)[0]
                if len(rest):
                    out[rest] = scene.occluded(rays[rest])
        with self._lock:
            self.timer.seconds += time.perf_counter() - t0
            self.timer.rays += rays.shape[0]
        return out

    def cast(self, rays: np.ndarray, exclude_track: int | None = None, near_m: float = 0.0,
             with_static: bool = True, with_actors: bool = True, dt_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Nearest hit over static + actors (minus ``exclude_track``'s own shape).

        ``rays`` (N, 6) float32. Surfaces closer than ``near_m`` (in units of each ray's direction
        length) are skipped (sensor housings, the RSU's own pole top); ``with_static`` and
        ``with_actors`` choose the scenes; ``dt_s`` casts at that time from the tick (actors moved by
        their velocity; a cached scene per value). Returns ``t`` (N,) float32
        (inf on a miss) and the global triangle index (N,) int32 (``miss`` on a miss).
        """
        t0 = time.perf_counter()
        if near_m > 0:
            rays = rays.copy()
            rays[:, :3] += np.float32(near_m) * rays[:, 3:]
        if with_static:
            t, prim = cast(self.static.scene, rays)
            gid = np.where(prim >= 0, prim, np.int32(self.miss))
        else:
            t = np.full(rays.shape[0], np.inf, np.float32)
            gid = np.full(rays.shape[0], self.miss, np.int32)
        if with_actors and self.actors.n_triangles and rays.shape[0]:
            ta, pa = self._cast_actors(rays, exclude_track, dt_s)
            nearer = np.nonzero(ta < t)[0]
            t[nearer] = ta[nearer]
            gid[nearer] = self.n_static + pa[nearer]
        if near_m > 0:
            t += np.float32(near_m)
        with self._lock:
            self.timer.seconds += time.perf_counter() - t0
            self.timer.rays += rays.shape[0]
        return t, gid


class _Tables(dict):
    """A dict whose entries are made by their maker on first lookup (once, under a lock: render threads
    share it)."""

    def __init__(self, makers: dict):
        super().__init__()
        self._makers = makers
        self._lock = threading.Lock()

    def __missing__(self, key: str) -> np.ndarray:
        with self._lock:
            if not dict.__contains__(self, key):
                self[key] = self._makers[key]()  # KeyError for an unknown table
            return dict.__getitem__(self, key)


def _box_mesh(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (8, 3) and triangles (12, 3) of the axis-aligned box [lo, hi]."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    v = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0], [x0, y0, z1], [x1, y0, z1], [x1, y1, z1],
                  [x0, y1, z1]])
    t = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5], [2, 3, 7],
                  [2, 7, 6], [3, 0, 4], [3, 4, 7]])
    return v, t


class StaticHits:
    """The static-world hits of a sensor that does not move (an RSU's LiDAR), kept across ticks.

    :meth:`cast` gives what :meth:`TickScene.cast` gives for the same rays, but casts the static
    world only when ``key`` (the sensor pose and ray count) changes; every tick it casts the rays
    against the actors alone and keeps the nearer hit.
    """

    def __init__(self) -> None:
        self.key: bytes | None = None
        self.t = np.zeros(0, np.float32)
        self.gid = np.zeros(0, np.int32)  # static triangle index, -1 for a miss

    def cast(self, scene: TickScene, key: bytes, rays: np.ndarray, exclude_track: int | None,
             near_m: float, actor_cast=None) -> tuple[np.ndarray, np.ndarray]:
        """``actor_cast(rays)``: how to cast against the actors alone (default: at the tick time)."""
        if key != self.key or len(self.t) != len(rays):
            t, gid = scene.cast(rays, exclude_track, near_m, with_actors=False)
            self.key, self.t, self.gid = key, t, np.where(gid == scene.miss, np.int32(-1), gid)
        t = self.t.copy()
        gid = np.where(self.gid < 0, np.int32(scene.miss), self.gid)
        if actor_cast is None:
            ta, ga = scene.cast(rays, exclude_track, near_m, with_static=False)
        else:
            ta, ga = actor_cast(rays)
        nearer = np.nonzero(ta < t)[0]
        t[nearer] = ta[nearer]
        gid[nearer] = ga[nearer]
        return t, gid


def static_bare_mesh(static: StaticScene, actors) -> TriMesh:
    """Static + actor triangles in one mesh (the single-scene reference the benchmark casts against)."""
    mesh, _ = place_actors(actors)
    return concat([static.mesh, mesh])
