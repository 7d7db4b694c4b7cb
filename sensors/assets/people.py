"""Articulated people: a procedural body of 17 closed parts posed by joint angles every tick.

A person (:class:`Person`) is a height, a build and clothing colours drawn from a key (a pedestrian's
SUMO id, a rider's model). Segment lengths follow the anthropometric fractions of stature of Drillis
and Contini (1966) as tabulated by Winter, "Biomechanics and Motor Control of Human Movement": hip
0.530 H, knee 0.285 H, ankle 0.039 H, shoulder 0.818 H, shoulder width 0.259 H, hip width 0.191 H,
upper arm 0.186 H, forearm 0.146 H, hand 0.108 H, foot 0.152 H; children get a larger head.

The body frame is x forward, y left, z up, the origin on the ground under the pelvis. The walk cycle
(:func:`walk_pose`) is continuous in the gait phase (0..1 per two steps) and scales with speed: hips
swing up to +-24 degrees, knees flex in swing, arms swing against the legs; a still person stands.
The posed body is shifted so that its lowest point touches the ground, and its tight box is what the
labels report (:func:`posed_box`), so a box follows the pose.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .shapes import Builder, ellipsoid, frustum

#: material part ids (match cosim.sensors.meshes)
PART_SKIN, PART_HAIR, PART_TOP, PART_BOTTOM, PART_SHOES = 10, 11, 12, 13, 14

_SKIN = np.array([(0.87, 0.70, 0.58), (0.76, 0.57, 0.43), (0.58, 0.41, 0.30), (0.40, 0.27, 0.19),
                  (0.93, 0.78, 0.67), (0.66, 0.48, 0.36)], np.float32)
_HAIR = np.array([(0.08, 0.06, 0.05), (0.30, 0.20, 0.10), (0.55, 0.42, 0.25), (0.70, 0.62, 0.45),
                  (0.45, 0.45, 0.45)], np.float32)
_CLOTH = np.array([(0.10, 0.12, 0.20), (0.60, 0.10, 0.10), (0.15, 0.35, 0.60), (0.85, 0.85, 0.82),
                   (0.20, 0.20, 0.22), (0.35, 0.45, 0.25), (0.75, 0.60, 0.20), (0.50, 0.30, 0.45),
                   (0.90, 0.45, 0.10), (0.30, 0.25, 0.20)], np.float32)


def _u(key: str, salt: int) -> float:
    """A uniform number in [0, 1] from ``key`` and ``salt`` (a hash, so similar keys draw unrelated values)."""
    h = hashlib.blake2b(f"{salt}:{key}".encode(), digest_size=8).digest()
    return int.from_bytes(h, "little") / float(2**64 - 1)


@dataclass(frozen=True)
class Person:
    """Stature [m], build (girth factor, 0.85 slim .. 1.25 heavy), child flag, colours (5, 3) for skin,
    hair, top, bottom and shoes."""

    name: str
    height_m: float
    build: float
    child: bool
    colours: np.ndarray

    @classmethod
    def from_key(cls, key: str) -> Person:
        """A person drawn from ``key``: one in five a child (1.0-1.3 m), adults 1.5-1.95 m."""
        child = _u(key, 1) < 0.2
        h = 1.0 + 0.3 * _u(key, 2) if child else 1.5 + 0.45 * _u(key, 2) ** 0.9
        build = 0.85 + 0.4 * _u(key, 3)
        pick = [_SKIN[int(_u(key, 4) * len(_SKIN)) % len(_SKIN)], _HAIR[int(_u(key, 5) * len(_HAIR)) % len(_HAIR)],
                _CLOTH[int(_u(key, 6) * len(_CLOTH)) % len(_CLOTH)],
                _CLOTH[int(_u(key, 7) * len(_CLOTH)) % len(_CLOTH)],
                _CLOTH[[0, 4, 9][int(_u(key, 8) * 3) % 3]]]
        return cls(key, round(h, 3), round(build, 3), child, np.array(pick, np.float32))


@dataclass(frozen=True)
class Pose:
    """Joint angles [rad]: flexion is positive forward (hips, shoulders), knees and elbows bend by
    their flexion; ``torso_pitch`` leans the trunk forward about the hips; ``hip_abd`` spreads the legs
    (riders astride), ``arm_abd`` the arms."""

    hip: tuple[float, float] = (0.0, 0.0)  # right, left
    knee: tuple[float, float] = (0.0, 0.0)
    shoulder: tuple[float, float] = (0.0, 0.0)
    elbow: tuple[float, float] = (0.15, 0.15)
    torso_pitch: float = 0.0
    hip_abd: float = 0.0
    arm_abd: float = 0.05
    ankle: tuple[float, float] = (0.0, 0.0)


#: [m/s] speed at which the walk cycle reaches its full amplitude
FULL_STRIDE_SPEED_MPS = 1.4
#: steps of the gait phase and speed the posed bodies are cached at (finer than a tick's change)
PHASE_STEPS = 256


def walk_pose(phase: float, speed_mps: float) -> Pose:
    """The pose at gait ``phase`` (0..1, two steps) walking at ``speed_mps``; standing when still."""
    a = min(1.0, max(0.0, speed_mps) / FULL_STRIDE_SPEED_MPS)
    if a <= 0.0:
        return Pose()
    w = 2 * math.pi * phase
    hip = math.radians(24) * a * math.sin(w)
    # the knee flexes in swing (leg moving forward), most just after the hip passes vertical
    kr = math.radians(8) + math.radians(50) * a * max(0.0, math.sin(w + 1.1)) ** 2
    kl = math.radians(8) + math.radians(50) * a * max(0.0, math.sin(w + 1.1 + math.pi)) ** 2
    sh = math.radians(20) * a * math.sin(w)
    return Pose(hip=(hip, -hip), knee=(kr * a, kl * a), shoulder=(-sh, sh),
                elbow=(0.2 + 0.25 * a * max(0.0, -math.sin(w)), 0.2 + 0.25 * a * max(0.0, math.sin(w))),
                torso_pitch=math.radians(3) * a, ankle=(0.25 * a * math.sin(w + 0.6), -0.25 * a * math.sin(w + 0.6)))


def _rot_y(v: np.ndarray, ang: float) -> np.ndarray:
    """Rotate (3,) about +y by ``ang`` such that positive flexion swings a downward limb forward (+x)."""
    c, s = math.cos(ang), math.sin(ang)
    x, y, z = v
    return np.array([c * x - s * z, y, s * x + c * z])


def skeleton(p: Person, pose: Pose) -> dict[str, np.ndarray]:
    """Joint positions [m] in the body frame (pelvis centre above the origin, before grounding)."""
    H = p.height_m
    hip_z = 0.530 * H
    sh_z = 0.818 * H
    neck_len = sh_z - hip_z
    head_r = (0.082 if p.child else 0.064) * H
    hip_w = 0.191 * H * (0.9 + 0.1 * p.build) / 2
    sh_w = 0.8 * 0.259 * H * (0.9 + 0.1 * p.build) / 2  # joint centres, inside the shoulders' breadth
    j: dict[str, np.ndarray] = {}
    pelvis = np.array([0.0, 0.0, hip_z])
    j["pelvis"] = pelvis
    up = _rot_y(np.array([0.0, 0.0, 1.0]), -pose.torso_pitch)  # lean forward: the top goes +x
    j["neck"] = pelvis + up * neck_len
    j["head"] = pelvis + up * (neck_len + 0.04 * H + head_r)
    j["head_r"] = np.array([head_r])
    thigh, shank, foot = 0.245 * H, 0.246 * H, 0.152 * H
    for k, side in enumerate((-1.0, 1.0)):  # right (y < 0), left
        name = "r" if side < 0 else "l"
        hip = pelvis + np.array([0.0, side * hip_w * 0.8, 0.0])
        down = np.array([0.0, side * math.sin(pose.hip_abd), -math.cos(pose.hip_abd)])
        d_thigh = _rot_y(down, pose.hip[k])
        knee = hip + thigh * d_thigh
        d_shank = _rot_y(down, pose.hip[k] - pose.knee[k])
        ankle = knee + shank * d_shank
        d_foot = _rot_y(np.array([1.0, 0.0, 0.0]), pose.hip[k] - pose.knee[k] + pose.ankle[k])
        heel = ankle - 0.22 * foot * d_foot - np.array([0, 0, 0.035 * H])
        toe = heel + foot * d_foot
        j[f"hip_{name}"], j[f"knee_{name}"], j[f"ankle_{name}"] = hip, knee, ankle
        j[f"heel_{name}"], j[f"toe_{name}"] = heel, toe
        sh = j["neck"] + np.array([0.0, side * sh_w, -0.03 * H])
        a_down = np.array([0.0, side * math.sin(pose.arm_abd), -math.cos(pose.arm_abd)])
        a_down = _rot_y(a_down, -pose.torso_pitch)
        d_upper = _rot_y(a_down, pose.shoulder[k])
        elbow = sh + 0.186 * H * d_upper
        d_fore = _rot_y(a_down, pose.shoulder[k] + pose.elbow[k])
        wrist = elbow + 0.146 * H * d_fore
        j[f"shoulder_{name}"], j[f"elbow_{name}"], j[f"wrist_{name}"] = sh, elbow, wrist
        j[f"hand_{name}"] = wrist + 0.09 * H * d_fore
    return j


def _body_parts(p: Person, pose: Pose, offset=(0.0, 0.0, 0.0)) -> tuple[list[tuple], list[tuple]]:
    """The posed body's primitives: frustums ``(p0, p1, r0, r1, part, n, squash)`` and ellipsoids
    ``(centre, radii, part, n_lat, n_lon)``, ``part`` one of skin, hair, top, bottom, shoes."""
    j = {k: v + np.asarray(offset) for k, v in skeleton(p, pose).items() if k != "head_r"}
    H, g = p.height_m, p.build
    head_r = (0.082 if p.child else 0.064) * H  # skeleton()'s head radius
    hip_w = 0.191 * H * (0.9 + 0.1 * g) / 2
    # pelvis, torso (elliptic: depth about 0.6 of the width), neck, head with hair
    up = j["neck"] - j["pelvis"]
    up /= np.linalg.norm(up)
    fr = [(j["pelvis"] - 0.06 * H * up, j["pelvis"] + 0.05 * H * up, hip_w * 1.05, hip_w * 1.1, "bottom", 8, 0.62),
          (j["pelvis"] + 0.05 * H * up, j["neck"], hip_w * 1.05 * g ** 0.5, 0.13 * H * g ** 0.3, "top", 8, 0.55),
          (j["neck"] - 0.01 * H * up, j["neck"] + 0.05 * H * up, 0.03 * H, 0.028 * H, "skin", 6, 1.0)]
    el = [(j["head"], (head_r * 0.95, head_r * 0.85, head_r * 1.1), "skin", 5, 8),
          (j["head"] + up * 0.25 * head_r - np.array([0.2 * head_r, 0, 0]),
           (head_r * 0.9, head_r * 0.88, head_r * 0.9), "hair", 4, 8)]
    limb = 0.032 * H * g ** 0.5
    for s in ("r", "l"):
        fr += [(j[f"hip_{s}"], j[f"knee_{s}"], limb * 1.9, limb * 1.3, "bottom", 6, 1.0),
               (j[f"knee_{s}"], j[f"ankle_{s}"], limb * 1.25, limb * 0.8, "bottom", 6, 1.0),
               (j[f"heel_{s}"] + np.array([0, 0, 0.018 * H]), j[f"toe_{s}"] + np.array([0, 0, 0.012 * H]),
                0.030 * H, 0.026 * H, "shoes", 6, 0.6),
               (j[f"shoulder_{s}"], j[f"elbow_{s}"], limb * 1.05, limb * 0.85, "top", 6, 1.0),
               (j[f"elbow_{s}"], j[f"wrist_{s}"], limb * 0.8, limb * 0.6, "skin", 6, 1.0),
               (j[f"wrist_{s}"], j[f"hand_{s}"], limb * 0.6, limb * 0.45, "skin", 4, 1.0)]
    return fr, el


def build_body(b: Builder, p: Person, pose: Pose, offset=(0.0, 0.0, 0.0), parts: dict | None = None) -> None:
    """Add the posed body's 17 closed parts to ``b`` (shifted by ``offset``); ``parts`` maps skin, hair,
    top, bottom, shoes to material ids (default: the person's own PART_* ids)."""
    P = {"skin": PART_SKIN, "hair": PART_HAIR, "top": PART_TOP, "bottom": PART_BOTTOM, "shoes": PART_SHOES}
    P.update(parts or {})
    fr, el = _body_parts(p, pose, offset)
    # the mesh's part order (frustums and ellipsoids interleaved as they were first written)
    for k in (0, 1, 2):
        frustum(b, *fr[k][:4], P[fr[k][4]], fr[k][5], squash=fr[k][6])
    for c, r, part, n_lat, n_lon in el:
        ellipsoid(b, c, r, P[part], n_lat, n_lon)
    for p0, p1, r0, r1, part, n, squash in fr[3:]:
        frustum(b, p0, p1, r0, r1, P[part], n, squash=squash)


@lru_cache(maxsize=8)
def _ring_table(layout: tuple[tuple[int, float], ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For frustums of ``(n, squash)``: per ring vertex its frustum, cos and squash * sin of its angle,
    computed as :func:`cosim.sensors.assets.shapes.frustum` does."""
    idx, cos, sin = [], [], []
    for f, (n, squash) in enumerate(layout):
        ang = (np.arange(n) + 0.5) * (2 * math.pi / n)
        idx.append(np.full(n, f))
        cos.append(np.cos(ang))
        sin.append(squash * np.sin(ang))
    return np.concatenate(idx), np.concatenate(cos)[:, None], np.concatenate(sin)[:, None]


@lru_cache(maxsize=8)
def _unit_ellipsoid(n_lat: int, n_lon: int) -> np.ndarray:
    """The unit vertices of :func:`cosim.sensors.assets.shapes.ellipsoid`."""
    lat = np.linspace(0, math.pi, n_lat + 1)[1:-1]
    lon = np.arange(n_lon) * (2 * math.pi / n_lon)
    ring = np.stack([np.sin(lat)[:, None] * np.cos(lon), np.sin(lat)[:, None] * np.sin(lon),
                     np.cos(lat)[:, None] * np.ones_like(lon)], -1).reshape(-1, 3)
    return np.concatenate([[[0, 0, 1.0]], ring, [[0, 0, -1.0]]])


def body_points(p: Person, pose: Pose) -> np.ndarray:
    """Every vertex of the posed body (before grounding), without building its triangles: the same
    points :func:`build_body` makes, by the same arithmetic, in a few array operations."""
    fr, el = _body_parts(p, pose)
    p0 = np.array([f[0] for f in fr])
    p1 = np.array([f[1] for f in fr])
    r0 = np.array([f[2] for f in fr])[:, None]
    r1 = np.array([f[3] for f in fr])[:, None]
    axis = p1 - p0
    # row by row, as frustum() takes them (np.linalg.norm of a vector is sqrt(v.dot(v)))
    axis /= np.array([math.sqrt(a.dot(a)) for a in axis])[:, None]
    ref = np.where((np.abs(axis[:, 2]) < 0.9)[:, None], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    u = np.cross(axis, ref)
    u /= np.array([math.sqrt(a.dot(a)) for a in u])[:, None]
    w = np.cross(axis, u)
    idx, cos, sin = _ring_table(tuple((f[5], f[6]) for f in fr))
    ring = cos * u[idx] + sin * w[idx]
    pts = [p0[idx] + r0[idx] * ring, p1[idx] + r1[idx] * ring, p0, p1]
    pts += [_unit_ellipsoid(n_lat, n_lon) * np.asarray(r, np.float64) + c for c, r, _, n_lat, n_lon in el]
    return np.concatenate(pts)


def person_mesh(p: Person, pose: Pose) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The posed body grounded (lowest point at z = 0): vertices, triangles, part, group, component."""
    b = Builder()
    build_body(b, p, pose)
    v, t, part, grp, comp = b.arrays()
    v[:, 2] -= v[:, 2].min()
    return v, t, part, grp, comp


def quantized(phase: float, speed: float) -> tuple[int, int]:
    """The cache steps of a gait phase and a speed: (phase step of PHASE_STEPS, speed in 5 cm/s)."""
    return round((phase % 1.0) * PHASE_STEPS) % PHASE_STEPS, round(min(max(speed, 0.0), 3.0) * 20)


def posed_steps(key: str, q_phase: int, q_speed: int):
    """:func:`posed` at cache steps (:func:`quantized`): the mesh :func:`person_mesh` builds, its
    vertices from :func:`body_points` (the same arithmetic) in the builder's order, the triangles, parts
    and groups (the same at every pose) made once per person. Not cached: a walker is at a new phase
    step nearly every tick, so a cache of posed meshes missed nearly always (0.5 ms a body instead of 3)."""
    p = _person(key)
    t, part, grp, order = _topology(key)
    v = body_points(p, walk_pose(q_phase / PHASE_STEPS, q_speed / 20))[order]
    v[:, 2] -= v[:, 2].min()
    lo, hi = v.min(0), v.max(0)
    return p, v, t, part, grp, lo, hi


@lru_cache(maxsize=256)
def _topology(key: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Triangles, part and group of person ``key``'s body (:func:`build_body`; the same at every pose) and
    the row of :func:`body_points` of each of its vertices (the builder's order: frustums 0-2, the
    ellipsoids, the other frustums; per frustum its two rings, then its two axis ends)."""
    p = _person(key)
    b = Builder()
    build_body(b, p, Pose())
    _, t, part, grp, _ = b.arrays()
    fr, el = _body_parts(p, Pose())
    ns = np.array([f[5] for f in fr])
    first = np.concatenate([[0], np.cumsum(ns)[:-1]])
    rings, nf = int(ns.sum()), len(fr)

    def frustum_rows(f: int) -> list[np.ndarray]:
        ring = first[f] + np.arange(ns[f])
        return [ring, rings + ring, [2 * rings + f], [2 * rings + nf + f]]

    rows = [r for f in (0, 1, 2) for r in frustum_rows(f)]
    start = 2 * rings + 2 * nf
    for _, _, _, n_lat, n_lon in el:
        size = 2 + (n_lat - 1) * n_lon
        rows.append(start + np.arange(size))
        start += size
    rows += [r for f in range(3, nf) for r in frustum_rows(f)]
    order = np.concatenate(rows).astype(np.int64)
    for a in (t, part, grp, order):
        a.flags.writeable = False
    return t, part, grp, order


Vec3 = tuple[float, float, float]


def posed_box(key: str, phase: float, speed_mps: float) -> tuple[Vec3, Vec3]:
    """Tight box of person ``key`` walking: size (length, width, height) [m] and the box centre in the
    body frame (origin on the ground under the pelvis). The box of the mesh :func:`posed` gives, from the
    body's points alone (:func:`body_points`, no triangles; cached per person and cache step)."""
    return _posed_box_steps(key, *quantized(phase, speed_mps))


@lru_cache(maxsize=256)
def _person(key: str) -> Person:
    return Person.from_key(key)


@lru_cache(maxsize=16384)  # a few MB: dozens of walkers over all their phase steps
def _posed_box_steps(key: str, q_phase: int, q_speed: int) -> tuple[Vec3, Vec3]:
    v = body_points(_person(key), walk_pose(q_phase / PHASE_STEPS, q_speed / 20))
    lo, hi = v.min(0), v.max(0)
    # person_mesh grounds the body (z -= min z): the same subtraction, on the extremes only
    lo_g = np.array([lo[0], lo[1], lo[2] - lo[2]])
    hi_g = np.array([hi[0], hi[1], hi[2] - lo[2]])
    size = tuple(float(x) for x in (hi_g - lo_g))
    centre = tuple(float(x) for x in (lo_g + hi_g) / 2)
    return size, centre  # type: ignore[return-value]


def posed(key: str, phase: float, speed_mps: float):
    """(person, vertices, triangles, part, group, lo, hi) of person ``key`` at this gait phase and speed
    (cached at :data:`PHASE_STEPS` phases and 5 cm/s of speed)."""
    return posed_steps(key, *quantized(phase, speed_mps))


def seated_pose(lean_deg: float, knee_deg: float, reach: float) -> Pose:
    """A rider's pose: trunk leaning ``lean_deg`` forward, hips flexed to sit, knees bent ``knee_deg``,
    arms reaching forward (``reach`` 0..1) to the handlebar."""
    lean = math.radians(lean_deg)
    return Pose(hip=(math.radians(75), math.radians(75)), knee=(math.radians(knee_deg), math.radians(knee_deg)),
                shoulder=(math.radians(35 + 40 * reach) + lean, math.radians(35 + 40 * reach) + lean),
                elbow=(0.35, 0.35), torso_pitch=lean, hip_abd=math.radians(8), arm_abd=0.15,
                ankle=(math.radians(20), math.radians(20)))
