"""The traffic lights' static mesh (geometry: :mod:`cosim.sensors.assets.signals`)."""

from __future__ import annotations

import numpy as np

from cosim.classes import semantic_id

from .assets.signals import BOX_TRIANGLES, POLE_RGB, SignalParts, oriented_box
from .meshes import TriMesh


def signal_mesh(parts: SignalParts) -> TriMesh:
    """The :class:`cosim.sensors.meshes.TriMesh` of ``parts``: heads and lamps of class ``traffic_light``,
    poles and arms ``pole``."""
    t = len(parts.triangles)
    return TriMesh(parts.vertices, parts.triangles,
                   np.where(parts.pole, semantic_id("pole"), semantic_id("traffic_light")).astype(np.uint8),
                   parts.instance, parts.albedo, parts.reflectivity, np.zeros(t, np.float32),
                   np.arange(t, dtype=np.int64) // 2)


#: [m] height of a sign face's centre above the road; thickness of a sign plate
SIGN_CENTRE_M = 2.3
#: first static instance id of the signs
FIRST_SIGN_INSTANCE = 4_000_000
SIGN_PLATE_M = 0.02
#: retro-reflective sheeting of sign faces (EN 12899-1 class RA2, as the licence plates)
SIGN_RETRO = 0.9
_RED, _WHITE = (0.70, 0.04, 0.05), (0.90, 0.90, 0.88)


def _ngon(n: int, r: float, phase: float) -> np.ndarray:
    a = phase + np.arange(n) * 2 * np.pi / n
    return np.stack([r * np.cos(a), r * np.sin(a)], 1)


#: each kind's face: (outline (K, 2) in the sign plane (lateral, up), colour) from back to front
SIGN_FACES = {
    "stop": [(_ngon(8, 0.40, np.pi / 8), _RED)],
    "give_way": [(_ngon(3, 0.52, -np.pi / 2), _RED), (_ngon(3, 0.38, -np.pi / 2), _WHITE)],
    "speed_limit": [(_ngon(16, 0.32, 0.0), _RED), (_ngon(16, 0.24, 0.0), _WHITE)],
}


def _plate(outline: np.ndarray, depth0: float, depth1: float) -> tuple[np.ndarray, np.ndarray]:
    """A closed convex plate (local x from ``depth0`` to ``depth1``, y, z the outline) wound outward."""
    k = len(outline)
    ring = np.concatenate([np.column_stack([np.full(k, d), outline]) for d in (depth0, depth1)])
    v = np.concatenate([ring, [[depth0, 0.0, 0.0], [depth1, 0.0, 0.0]]])
    i = np.arange(k)
    j = (i + 1) % k
    t = np.concatenate([np.stack([i, j, k + j], 1), np.stack([i, k + j, k + i], 1),
                        np.stack([np.full(k, 2 * k), j, i], 1), np.stack([np.full(k, 2 * k + 1), k + i, k + j], 1)])
    centre = v.mean(0)
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    inward = (np.cross(b - a, c - a) * ((a + b + c) / 3 - centre)).sum(1) < 0
    t[inward] = t[inward][:, ::-1]
    return v, t


def sign_mesh(signs) -> TriMesh | None:
    """The posts and faces of ``signs`` (:class:`cosim.world.traffic_signs.TrafficSign`): faces of class
    ``traffic_sign`` with retro-reflective fronts, posts ``pole``; static instance ids from
    :data:`FIRST_SIGN_INSTANCE`; None without signs."""
    from cosim.world.layout import ROAD_Z

    verts, tris, sem, inst, alb, refl, retro = [], [], [], [], [], [], []
    n_v = 0
    for k, s in enumerate(signs):
        c, sn = np.cos(s.yaw_rad), np.sin(s.yaw_rad)
        rot = np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])
        base = np.array([s.xy[0], s.xy[1], ROAD_Z[1]])
        top = SIGN_CENTRE_M + 0.3
        parts = [((oriented_box((-0.035, 0.0, top / 2), 0.0, (0.03, 0.035, top / 2)), BOX_TRIANGLES), None, "pole")]
        for m, (outline, colour) in enumerate(SIGN_FACES[s.kind]):
            v, t = _plate(outline, 0.01 + m * SIGN_PLATE_M, 0.01 + (m + 1) * SIGN_PLATE_M)
            parts.append(((v + np.array([0.0, 0.0, SIGN_CENTRE_M]), t), colour, "sign"))
        for (v, t), colour, what in parts:
            world_v = v @ rot.T + base
            verts.append(world_v)
            tris.append(t + n_v)
            n_v += len(v)
            nt = len(t)
            sem.append(np.full(nt, semantic_id("pole" if what == "pole" else "traffic_sign"), np.uint8))
            inst.append(np.full(nt, FIRST_SIGN_INSTANCE + k, np.uint32))
            alb.append(np.tile(np.asarray(POLE_RGB if colour is None else colour, np.float32), (nt, 1)))
            refl.append(np.full(nt, 0.5, np.float32))
            if what == "pole":
                retro.append(np.zeros(nt, np.float32))
            else:  # the sheeting is on the front (the faces looking along +x, the sign's facing)
                a, b, cc = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
                nrm = np.cross(b - a, cc - a)
                front = nrm[:, 0] > 0.9 * np.linalg.norm(nrm, axis=1)
                retro.append(np.where(front, SIGN_RETRO, 0.0).astype(np.float32))
    if not verts:
        return None
    t_all = np.concatenate(tris)
    return TriMesh(np.concatenate(verts).astype(np.float32), t_all.astype(np.uint32), np.concatenate(sem),
                   np.concatenate(inst), np.concatenate(alb), np.concatenate(refl),
                   np.zeros(len(t_all), np.float32), np.arange(len(t_all), dtype=np.int64),
                   retro=np.concatenate(retro))
