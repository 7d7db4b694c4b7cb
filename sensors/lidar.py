"""LiDAR: a scan pattern's firings cast from where the sensor is when each fires.

Scan patterns are a registry (:func:`register_pattern`, :func:`scan_pattern`): ``spinning`` (a
64-channel rotating LiDAR) and ``rosette`` (a Livox-style non-repetitive pattern of two counter-rotating
prisms). A pattern gives every firing's direction in the sensor frame, its ring and its time
``t_offset_ns`` (<= 0) relative to the sweep's end, which is the tick time.

Motion distortion (``motion_distortion``, on by default): each firing is cast at its own time, the
sensor pose extrapolated from the tick's pose with the agent's velocity and body rates, the actors
moved by their velocities (in :data:`ACTOR_TIME_BINS` bins per sweep). Each point is the measurement
``direction x range`` in the sensor frame of its firing, as a real sensor reports it, and the sweep is
stamped at its end: points of a moving sensor are smeared, and :func:`cosim.io.deskew` undoes it with
the recorded poses. Off: every firing at the tick pose and time (``t_offset_ns`` = 0).

Intensity (:func:`intensity_model`) follows the LiDAR range equation for extended Lambertian
targets, P ~ rho cos(alpha) / R^2 (Hoefle and Pfeifer, 2007, "Correction of laser scanning intensity
data: data and model-driven approaches", ISPRS J. Photogramm. Remote Sens. 62(6)), reported
range-normalised as sensors' calibrated reflectivity is (the 1/R^2 divided out), times the two-way
atmospheric transmittance, plus an incidence-independent retro-reflective term for glass-bead lane
markings and vehicle reflectors. Rain wets upward-facing surfaces (lower reflectivity).

Weather (see :mod:`cosim.sensors.environment`): fog removes returns beyond the visibility distance and
thins those approaching it, dims the rest, and adds near-range backscatter; rain adds dropout, range
noise and spurious near returns from drops. Ray drop (:func:`drop_probability`): a seeded draw per
return removes it with the probability of CARLA's drop-off model (``dropoff_general_rate``,
``dropoff_intensity_limit``, ``dropoff_zero_intensity``) combined with physical terms: too little
return energy (long range, dark or grazing surfaces), glass (the beam passes through or glances off)
and wet surfaces under rain (specular); retro-reflectors never drop. Self-occlusion (``self_occlusion``,
:func:`own_body_range`): a beam whose first hit is the carrying vehicle's own body returns nothing, as the
roof and bonnet of a real car blank the lowest rings of its roof LiDAR. Dual returns (``dual_returns``): where
a beam's footprint straddles a near object's edge or a rain drop, the beam reports the strongest and the last return.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from cosim.classes import SEMANTIC_ID
from cosim.errors import CosimError
from cosim.scenario.model import LidarSpec
from cosim.snapshot import AgentState

from . import kernels
from .environment import Atmosphere
from .lidar_models import needs_retro, report_intensity, ring_elevations_deg
from .rig import Pose, body_rotation, mount_rotation, rotate, sensor_pose
from .scene import StaticHits, TickScene, cast

MIN_RANGE_M = 0.3  # [m] returns closer than this are not reported (housing, mount)
ACTOR_TIME_BINS = 8  # actors are moved to the centre of one of this many slices of a sweep
#: [m] slack of :func:`actors_in_reach` beyond its bound (an actor's mesh lies in its box within 1 cm)
REACH_SLACK_M = 1.0
#: Return kinds (``return`` field): the beam's only return, the strongest and the last of a dual pair.
RETURN_SINGLE, RETURN_STRONGEST, RETURN_LAST = 0, 1, 2
DUAL_MIN_SEPARATION_M = 1.0  # [m] a second surface nearer than this behind the first is the same return
OWN_FACES_MAX = 12  # faces of its own shape a ray may cross (then the rest counts as a hit on nothing)
#: self-occlusion's body (:func:`own_body_range`): its top this far [m] under the sensor, and this share of the
#: own box's length; fitted to the blind sectors of KITTI's lowest rings (benchmarks/realism_levers.py gaps,
#: docs/lidar_models.md section 4)
BODY_DEPTH_M = 0.9
BODY_LENGTH_SHARE = 0.98


@dataclass(frozen=True)
class LidarFrame:
    """One sweep. N returns in firing order (by firing time, then ring; a dual pair's last return after the
    other returns of its firing); every array has length N and row i describes return i.

    ``points`` (N, 3) float32 [m] in the sensor frame of the return's firing (see the module docstring);
    ``intensity`` (N,) float32 in [0, 1]; ``ring`` (N,) uint16 (0 = lowest channel); ``class_id`` (N,)
    uint8 semantic id (0 for spurious weather returns); ``instance_id`` (N,) uint32 (track id, static
    instance id, or 0); ``t_offset_ns`` (N,) int32 <= 0, firing time relative to the sweep's end;
    ``return_kind`` (N,) uint8 (:data:`RETURN_SINGLE`, :data:`RETURN_STRONGEST`, :data:`RETURN_LAST`).
    """

    agent_id: str
    points: np.ndarray
    intensity: np.ndarray
    ring: np.ndarray
    class_id: np.ndarray
    instance_id: np.ndarray
    t_offset_ns: np.ndarray | None = None
    return_kind: np.ndarray | None = None

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])


# ----------------------------------------------------------------------------- scan patterns


@dataclass(frozen=True)
class Beams:
    """Firings of one sweep: ``directions`` (N, 3) float64 unit vectors in the sensor frame, ``ring``
    (N,) uint16, ``t_offset_ns`` (N,) int64 <= 0 (firing time relative to the sweep's end).
    ``repeats``: every sweep fires the same directions (a standing sensor may keep its static hits)."""

    directions: np.ndarray
    ring: np.ndarray
    t_offset_ns: np.ndarray
    repeats: bool = False


ScanPattern = Callable[[LidarSpec, int], Beams]
_PATTERNS: dict[str, ScanPattern] = {}


def register_pattern(name: str) -> Callable[[ScanPattern], ScanPattern]:
    """Decorator: add a scan pattern ``(spec, t_end_ns) -> Beams`` under ``name``."""

    def add(fn: ScanPattern) -> ScanPattern:
        if name in _PATTERNS:
            raise CosimError(f"scan pattern {name!r} is already registered")
        _PATTERNS[name] = fn
        return fn

    return add


def scan_pattern(name: str) -> ScanPattern:
    try:
        return _PATTERNS[name]
    except KeyError:
        raise CosimError(f"unknown LiDAR scan pattern {name!r}; known: {', '.join(sorted(_PATTERNS))}") from None


def sweep_ns(spec: LidarSpec) -> int:
    """Duration [ns] of one sweep (spinning) or frame (rosette)."""
    return round(1e9 / spec.rotation_hz)


@lru_cache(maxsize=16)
def beam_pattern(spec: LidarSpec) -> tuple[np.ndarray, np.ndarray]:
    """Spinning pattern: unit ray directions (C * A, 3) float64 in the sensor frame and ring (C * A,) uint16.

    Channels at :func:`ring_elevations_deg` (the sheet's table, or evenly spaced from ``lower_fov_deg``, ring
    0, to ``upper_fov_deg``); azimuths cover 360 deg counter-clockwise from the sensor's +x at
    ``horizontal_resolution_deg``.
    """
    n_az = max(1, round(360.0 / spec.horizontal_resolution_deg))
    elev = np.radians(ring_elevations_deg(spec))
    az = np.arange(n_az) * (2 * math.pi / n_az)
    e, a = np.meshgrid(elev, az, indexing="ij")
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=-1).reshape(-1, 3)
    ring = np.repeat(np.arange(spec.channels, dtype=np.uint16), n_az)
    return d, ring


@lru_cache(maxsize=16)
def _spinning(spec: LidarSpec) -> Beams:
    d, ring = beam_pattern(spec)
    n_az = len(d) // spec.channels
    # the head turns counter-clockwise starting behind the sensor (azimuth 180 deg): the seam is at the
    # back; every channel of one azimuth fires at once; the last azimuth fires at the sweep's end
    step = (np.arange(n_az) - n_az // 2) % n_az
    t = -np.rint((n_az - 1 - step) * (sweep_ns(spec) / n_az)).astype(np.int64)
    return Beams(d, ring, np.tile(t, spec.channels), repeats=True)


@register_pattern("spinning")
def spinning_pattern(spec: LidarSpec, t_end_ns: int) -> Beams:
    """The same firings every sweep (see :func:`beam_pattern`)."""
    return _spinning(spec)


#: Rosette prism rates [Hz]: two counter-rotating deflections of equal size; an irrational ratio makes
#: the pattern non-repetitive (it keeps filling the field of view as time goes on).
ROSETTE_HZ = (1_227.0, 1_227.0 * (math.sqrt(5.0) - 1.0) / 2.0 * 1.37)


@register_pattern("rosette")
def rosette_pattern(spec: LidarSpec, t_end_ns: int) -> Beams:
    """Livox-style rosette: firing i of the frame ending at ``t_end_ns`` fires at the absolute time
    t_i (``point_rate_hz`` firings per second, the last at ``t_end_ns``); its direction is tilted from
    +x by the sum of two counter-rotating deflections of ``rosette_fov_deg`` / 4 each, so the pattern
    covers the circular field of view more densely the longer it is accumulated. Ring 0."""
    n = max(1, round(spec.point_rate_hz / spec.rotation_hz))
    dt_ns = 1e9 / spec.point_rate_hz
    k = np.arange(n, dtype=np.float64)
    t_abs_s = (t_end_ns - (n - 1 - k) * dt_ns) * 1e-9
    a = math.radians(spec.rosette_fov_deg) / 4.0
    p1, p2 = 2 * math.pi * ROSETTE_HZ[0] * t_abs_s, -2 * math.pi * ROSETTE_HZ[1] * t_abs_s
    u = a * (np.cos(p1) + np.cos(p2))
    v = a * (np.sin(p1) + np.sin(p2))
    r = np.hypot(u, v)  # angle from the axis [rad]
    phi = np.arctan2(v, u)
    d = np.stack([np.cos(r), np.sin(r) * np.cos(phi), np.sin(r) * np.sin(phi)], axis=1)
    t_off = -np.rint((n - 1 - k) * dt_ns).astype(np.int64)
    return Beams(d, np.zeros(n, np.uint16), t_off)


# ------------------------------------------------------------------------------ intensity

#: Incidence-independent retro-reflective reflectivity per semantic class (glass-bead lane markings).
_RETRO_BY_CLASS = np.zeros(256, np.float32)
_RETRO_BY_CLASS[SEMANTIC_ID["lane_marking"]] = 0.35

#: probability that a return from glazing is lost (most of the beam is transmitted or reflected away)
GLASS_DROP = 0.85
#: probability that a return from a wet upward-facing surface at grazing incidence is lost in heavy rain
WET_DROP = 0.8
#: steepness of the detection probability in the return energy (2: in range, (R / R90)^4)
DETECTION_EXPONENT = 2.0


def wet_factor(rain_mm_h: float) -> float:
    """Reflectivity factor of upward-facing surfaces under rain: a water film reflects the beam
    specularly away (down to half at 10 mm/h and more)."""
    return 1.0 - 0.5 * min(1.0, rain_mm_h / 10.0)


def intensity_model(rho_diffuse: np.ndarray, rho_retro: np.ndarray, cos_incidence: np.ndarray, range_m: np.ndarray,
                    beta_per_m: float) -> np.ndarray:
    """Reported intensity (N,) float64 in [0, 1]: (rho_d cos(alpha) + rho_r) exp(-2 beta R), clipped.

    The received power of an extended Lambertian target is P ~ rho cos(alpha) / R^2 (Hoefle and
    Pfeifer 2007); the sensor reports it range-normalised (x R^2 / R_ref^2, its calibrated reflectivity),
    so what is left of range is the two-way atmospheric loss exp(-2 beta R).
    """
    i = rho_diffuse * np.clip(cos_incidence, 0.0, 1.0) + rho_retro
    if beta_per_m > 0:
        i = i * np.exp(-2.0 * beta_per_m * range_m)
    return np.clip(i, 0.0, 1.0)


# ------------------------------------------------------------------------------- rendering


def _rotate_about(v: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    """Each row of ``v`` (N, 3) rotated by the rotation vector in the same row of ``rotvec`` (Rodrigues)."""
    theta = np.linalg.norm(rotvec, axis=1, keepdims=True)
    k = rotvec / np.where(theta > 0, theta, 1.0)
    c, s = np.cos(theta), np.sin(theta)
    return v * c + np.cross(k, v) * s + k * (k * v).sum(axis=1, keepdims=True) * (1.0 - c)


def firing_rays(d_sensor: np.ndarray, t_offset_s: np.ndarray, pose: Pose, agent: AgentState | None,
                spec: LidarSpec) -> tuple[np.ndarray, np.ndarray]:
    """Ray origins (N, 3) and unit directions (N, 3) in map of each firing: the sensor pose at
    ``t_offset_s`` from the tick (position + velocity x t; body attitude turned by the body rates x t)."""
    if agent is None or not (np.any(agent.velocity_mps) or np.any(agent.angular_rate_radps)):
        return np.broadcast_to(pose.position_m, d_sensor.shape), rotate(d_sensor, pose.rotation)
    v = np.asarray(agent.velocity_mps, np.float64)
    if not np.any(agent.angular_rate_radps):  # translation only: the attitude of the tick
        return pose.position_m + v * t_offset_s[:, None], rotate(d_sensor, pose.rotation)
    rb = body_rotation(agent)
    turn = np.asarray(agent.angular_rate_radps, np.float64)[None, :] * t_offset_s[:, None]  # body frame
    d_body = _rotate_about(rotate(d_sensor, mount_rotation(spec.mount)), turn)
    m_body = _rotate_about(np.broadcast_to(np.asarray(spec.mount.xyz_m, np.float64), d_sensor.shape), turn)
    origin = np.asarray(agent.position_m, np.float64) + v * t_offset_s[:, None] + rotate(m_body, rb)
    return origin, rotate(d_body, rb)


def reach_ball(agent: AgentState, spec: LidarSpec) -> tuple[np.ndarray, float, float]:
    """Centre (3,) [m, map], radius [m] and sweep length [s] of a ball holding every point a sweep of ``spec``
    on ``agent`` can return: each firing's origin lies within |v| T + 2 |mount| of the sensor's position at
    the tick (T = 1 / ``rotation_hz``, the longest a sweep or rosette frame lasts; 0 without motion
    distortion), and a return lies at most ``range_m`` from its origin."""
    sweep_s = 1.0 / spec.rotation_hz if spec.motion_distortion else 0.0
    radius = (spec.range_m + float(np.linalg.norm(agent.velocity_mps)) * sweep_s
              + 2.0 * float(np.linalg.norm(spec.mount.xyz_m)))
    return sensor_pose(agent, spec.mount).position_m, radius, sweep_s


def actors_in_reach(actors: tuple, balls: list[tuple[np.ndarray, float, float]]) -> tuple:
    """The actors some LiDAR can return a point from this tick (``balls`` of :func:`reach_ball`): an actor's
    box, moved by its velocity over the sweep, meets one of the balls (with :data:`REACH_SLACK_M`). Leaving
    the others out of a tick's scene changes no return: a ray's hit on them lies beyond ``range_m``, so it
    is no return, and whatever the ray meets behind them lies farther still."""
    if not actors or not balls:
        return ()
    centre = np.array([a.center_m for a in actors], np.float64)
    bound = (0.5 * np.linalg.norm(np.array([a.size_m for a in actors], np.float64), axis=1)
             + REACH_SLACK_M)
    speed = np.linalg.norm(np.array([a.velocity_mps for a in actors], np.float64), axis=1)
    keep = np.zeros(len(actors), bool)
    for pos, radius, sweep_s in balls:
        keep |= np.linalg.norm(centre - pos, axis=1) <= radius + bound + speed * sweep_s
    return tuple(a for a, k in zip(actors, keep, strict=True) if k)


def _cast_binned(scene: TickScene, rays: np.ndarray, t_offset_s: np.ndarray, exclude: int | None,
                 with_static: bool = True, near_m: float = MIN_RANGE_M,
                 lo_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Cast with the actors moved to the time of each firing (in :data:`ACTOR_TIME_BINS` slices of
    [``lo_s``, 0], by default from the earliest of ``t_offset_s``: a subset of a sweep's rays given its
    sweep's ``lo_s`` reuses the actor scenes cached for the sweep's slices)."""
    if not scene.actors_move or not np.any(t_offset_s):
        return scene.cast(rays, exclude, near_m, with_static=with_static)
    if with_static:
        t, gid = scene.cast(rays, exclude, near_m, with_actors=False)
    else:
        t = np.full(len(rays), np.inf, np.float32)
        gid = np.full(len(rays), scene.miss, np.int32)
    lo = float(t_offset_s.min()) if lo_s is None else lo_s
    width = (0.0 - lo) / ACTOR_TIME_BINS or 1.0
    # only rays that meet an actor's swept box (before the static world, unless they start inside a
    # box, where the first box hit is its far side) can meet the actor at its own time
    boxes, b_lo, b_hi = scene.swept_boxes(exclude, lo)
    t_box, _ = cast(boxes, rays)
    o_lo, o_hi = kernels.origin_bounds(rays)
    inside = bool(np.any(np.all((o_hi >= b_lo) & (o_lo <= b_hi), axis=1)))
    near = np.nonzero(np.isfinite(t_box) if inside else t_box < t)[0]
    bins = np.minimum(((t_offset_s[near] - lo) / width).astype(np.int64), ACTOR_TIME_BINS - 1)
    for b in np.unique(bins):
        idx = near[bins == b]
        ta, ga = _cast_actors_without(scene, rays[idx], exclude, lo + (b + 0.5) * width, near_m)
        nearer = ta < t[idx]
        t[idx[nearer]] = ta[nearer]
        gid[idx[nearer]] = ga[nearer]
    return t, gid


def _cast_actors_without(scene: TickScene, rays: np.ndarray, exclude: int | None,
                         dt_s: float, near_m: float = MIN_RANGE_M) -> tuple[np.ndarray, np.ndarray]:
    """Actors alone at ``dt_s`` from the tick, ignoring ``exclude``'s own shape: one scene of all actors
    per time (shared by every sensor); rays that meet the own shape go on from just past each of its
    faces (its parts, body, cabin and wheels, are closed boxes and cylinders: a few faces each)."""
    t, gid = scene.cast(rays, None, near_m, with_static=False, dt_s=dt_s)
    if exclude is None:
        return t, gid
    track = np.concatenate([scene.actor_track, [-1]])
    for _ in range(OWN_FACES_MAX):
        own = np.nonzero(np.take(track, np.clip(gid - scene.n_static, 0, len(track) - 1)) == exclude)[0]
        own = own[gid[own] < scene.miss]
        if not len(own):
            break
        past = t[own] + np.float32(1e-3)
        again = rays[own].copy()
        again[:, :3] += again[:, 3:] * past[:, None]
        t2, g2 = scene.cast(again, None, 0.0, with_static=False, dt_s=dt_s)
        t[own] = past + t2
        gid[own] = g2
    else:
        left = np.take(track, np.clip(gid - scene.n_static, 0, len(track) - 1)) == exclude
        t[left], gid[left] = np.inf, scene.miss
    return t, gid


def _column_order(spec: LidarSpec, beams: Beams) -> np.ndarray:
    """The firings (N,) int64 in firing-time order (stable: a column's channels from ring 0 up)."""
    if beams.repeats:
        return _repeating_order(spec)
    return np.argsort(beams.t_offset_ns, kind="stable")


@lru_cache(maxsize=16)
def _repeating_order(spec: LidarSpec) -> np.ndarray:
    out = np.argsort(scan_pattern(spec.pattern)(spec, 0).t_offset_ns, kind="stable")
    out.flags.writeable = False
    return out


def render_lidar(
    agent_id: str,
    spec: LidarSpec,
    pose: Pose,
    scene: TickScene,
    atm: Atmosphere,
    rng: np.random.Generator,
    exclude_track: int | None = None,
    noise: bool = True,
    fixed: StaticHits | None = None,
    agent: AgentState | None = None,
    t_ns: int = 0,
) -> LidarFrame:
    """Cast one sweep ending at ``t_ns`` from ``pose`` (map <- sensor at the tick) and apply the sensor
    and weather models. ``agent`` (its velocity and body rates) moves the sensor within the sweep when
    ``spec.motion_distortion`` is on.

    Random draws (in this order, always the full firing count so the stream does not depend on the
    scene): range noise, dropout, weather thinning, spurious returns. ``noise=False`` turns every
    random effect off (exact ranges, for tests). ``fixed``: the sensor's :class:`StaticHits` when
    it does not move between ticks (same result, the static world cast once).
    """
    beams = scan_pattern(spec.pattern)(spec, t_ns)
    d_sensor, ring = beams.directions, beams.ring
    n = d_sensor.shape[0]
    t_off_ns = beams.t_offset_ns if spec.motion_distortion else np.zeros(n, np.int64)
    t_off_s = t_off_ns * 1e-9
    origin, d_map = firing_rays(d_sensor, t_off_s, pose, agent if spec.motion_distortion else None, spec)
    rays = np.empty((n, 6), np.float32)
    rays[:, :3] = origin
    rays[:, 3:] = d_map
    # cast column by column (the firings in time order: every channel of one azimuth together), so that
    # consecutive rays visit the same BVH nodes
    col = _column_order(spec, beams)
    c_rays, c_off_s = rays[col], t_off_s[col]
    if fixed is not None and beams.repeats and origin.strides[0] == 0:  # a standing sensor, the same firings
        key = pose.rotation.tobytes() + pose.position_m.tobytes() + spec.pattern.encode()
        ct, cgid = fixed.cast(scene, key, c_rays, exclude_track, MIN_RANGE_M,
                              lambda r: _cast_binned(scene, r, c_off_s, exclude_track, with_static=False))
    else:
        ct, cgid = _cast_binned(scene, c_rays, c_off_s, exclude_track)
    t, gid = np.empty_like(ct), np.empty_like(cgid)
    t[col], gid[col] = ct, cgid
    if noise:  # foliage lets part of the beams through (drawn first: the crowns decide what a beam hits)
        t, gid = _through_crowns(scene, rays, t, gid, rng.random(n), exclude_track, t_off_s)
    hit = t <= spec.range_m
    if spec.self_occlusion and exclude_track is not None:
        own_t = own_body_range(scene, exclude_track, pose, d_sensor)
        if own_t is not None:
            hit &= ~(own_t < t)
    r = np.where(hit, t, 0.0).astype(np.float64)

    # what the hits are (misses are no return, whatever their values): gathered once, for the hits only
    at = np.nonzero(hit)[0]
    surface = _Surface.of(scene, gid[at], rays[at, 3:])
    intensity = np.zeros(n)
    cls = np.zeros(n, surface.cls.dtype)
    inst = np.zeros(n, surface.inst.dtype)
    intensity[at], cls[at], inst[at] = _intensity_of(atm, surface, r[at])

    spur = np.zeros(n, bool)
    spur_r = spur_i = np.zeros(n)
    sigma = 0.0
    if noise:
        u_noise = rng.standard_normal(n)
        u_drop = rng.random(n)
        u_weather = rng.random(n)
        u_spur = rng.random(n)
        u_spur_r = rng.random(n)
        u_ray_drop = rng.random(n)
        rain = atm.rain_rate_mm_h
        sigma = spec.range_noise_m + 0.0015 * rain
        r = np.where(hit, r + sigma * u_noise, r)
        p_drop = spec.dropout + min(0.5, 0.004 * rain)
        hit &= u_drop >= p_drop
        p_ray_drop = np.zeros(n)
        p_ray_drop[at] = _ray_drop(spec, atm, surface, r[at], intensity[at])
        hit &= u_ray_drop >= p_ray_drop
        if atm.beta_fog > 0:
            vis = atm.visibility_m
            # detection probability falls towards the visibility distance, zero beyond
            p_keep = np.clip(1.0 - (r / vis) ** 3, 0.0, 1.0) * (r <= vis)
            hit &= u_weather < p_keep
            p_back = min(0.2, 1.5 / vis)
            spur = u_spur < p_back
            spur_r = 0.5 + u_spur_r * min(6.0, 0.1 * vis)
        elif rain > 0:
            spur = u_spur < min(0.05, 0.0008 * rain)
            spur_r = 0.5 + u_spur_r * 9.5
        spur &= ~hit | (spur_r < r)
        spur_i = 0.02 + 0.05 * u_spur_r
    # dual returns: the near return of a pair is RETURN_STRONGEST, the far one RETURN_LAST
    behind = spur & hit if spec.dual_returns else np.zeros(n, bool)  # a drop in front of a surface
    surf = (r, intensity, cls, inst)
    r = np.where(spur, spur_r, r)
    intensity = np.where(spur, spur_i, intensity)
    cls = np.where(spur, 0, cls)
    inst = np.where(spur, 0, inst)
    hit |= spur
    kind = np.where(behind, RETURN_STRONGEST, RETURN_SINGLE).astype(np.uint8)
    # without dual returns, firing order (below) up front: one return per beam needs no second gather (the
    # beams in firing order, kept where they return, are the stable sort of the returns by firing time)
    idx = np.nonzero(hit)[0] if spec.dual_returns else col[hit[col]]
    parts = [(d_sensor[idx] * r[idx, None], intensity[idx], ring[idx], cls[idx], inst[idx], t_off_ns[idx],
              kind[idx], idx)]
    if behind.any():
        j = np.nonzero(behind)[0]
        parts.append((d_sensor[j] * surf[0][j, None], surf[1][j], ring[j], surf[2][j], surf[3][j], t_off_ns[j],
                      np.full(len(j), RETURN_LAST, np.uint8), j))
    if spec.dual_returns:
        parts += _edge_returns(scene, spec, atm, rays, d_sensor, ring, t_off_ns, exclude_track,
                               np.where(hit & ~spur, r, np.inf), hit, parts, rng if noise else None, sigma)
    cat = [np.concatenate([p[k] for p in parts]) for k in range(8)]
    # firing order: by the firing time of the beam, the channels of one firing from the lowest ring up (a
    # dual pair's last return after the firing's other returns), as a sensor sends its packets; the records
    # of one firing then share their time, so the stored sweep compresses 4 % smaller than ring by ring
    if len(parts) > 1:
        order = np.argsort(beams.t_offset_ns[np.concatenate([p[7] for p in parts])], kind="stable")
        cat = [c[order] for c in cat]
    retro = _retro_hits(scene, gid)[cat[7]] & (cat[3] != 0) if needs_retro(spec) else None
    return LidarFrame(
        agent_id,
        cat[0].astype(np.float32),
        report_intensity(spec, cat[1], retro, None if spec.intensity_transfer == "linear"  # (range unused)
                         else np.linalg.norm(cat[0], axis=1)).astype(np.float32),
        cat[2].astype(np.uint16),
        cat[3].astype(np.uint8),
        cat[4].astype(np.uint32),
        cat[5].astype(np.int32),
        cat[6].astype(np.uint8),
    )


def own_body_range(scene: TickScene, track: int, pose: Pose, d_sensor: np.ndarray,
                   depth_m: float = BODY_DEPTH_M) -> np.ndarray | None:
    """Range (N,) float64 [m] from the sensor along each beam ``d_sensor`` (N, 3) (unit vectors, sensor frame)
    to the own body of the actor ``track`` (its shape at the tick in ``scene``), inf where the beam clears it;
    None when the scene has no such actor.

    The body a roof LiDAR sees is its car below the windows (bonnet, boot, shoulders, mirrors; the sensor on
    its rack looks over the roof's crown): a slab of the own shape's tight box in the sensor frame, its full
    width and :data:`BODY_LENGTH_SHARE` of its length about the box's centre, its top ``depth_m`` under the
    sensor whatever the mount and the model (both fitted to KITTI's lowest rings). The body moves with the
    sensor, so the ranges hold for every firing of the sweep."""
    own = scene.actor_track == track
    if not own.any():
        return None
    used = np.unique(scene.actors.triangles[own])
    v = rotate(np.asarray(scene.actors.vertices[used], np.float64) - pose.position_m, pose.rotation.T)
    lo, hi = v.min(axis=0), v.max(axis=0)
    centre_x, half_x = 0.5 * (lo[0] + hi[0]), 0.5 * BODY_LENGTH_SHARE * (hi[0] - lo[0])
    d = np.asarray(d_sensor, np.float64)
    out = np.full(len(d), np.inf)
    down = np.nonzero(d[:, 2] < 0)[0]
    s = depth_m / -d[down, 2]
    x, y = s * d[down, 0], s * d[down, 1]
    on = (np.abs(x - centre_x) <= half_x) & (y >= lo[1]) & (y <= hi[1])
    out[down[on]] = s[on]
    return out


@dataclass(frozen=True)
class _Surface:
    """What the label tables say about hits ``gid`` seen along ``d_map`` (gathered once for the intensity and
    the ray drop): normals (N, 3), incidence cosines (N,), class, instance, reflectivity, retro-reflection
    (the class's and the surface's, the larger) and glass."""

    normals: np.ndarray
    cos_inc: np.ndarray
    cls: np.ndarray
    inst: np.ndarray
    rho: np.ndarray
    retro: np.ndarray
    glass: np.ndarray

    @classmethod
    def of(cls, scene: TickScene, gid: np.ndarray, d_map: np.ndarray) -> _Surface:
        lab = scene.labels
        normals = np.take(lab["normal"], gid, axis=0)
        sem = np.take(lab["semantic"], gid)
        return cls(normals, np.abs((normals * d_map).sum(axis=1)), sem, np.take(lab["instance"], gid),
                   np.take(lab["reflectivity"], gid), np.maximum(_RETRO_BY_CLASS[sem], np.take(lab["retro"], gid)),
                   np.take(lab["glass"], gid))


def _surface_intensity(scene: TickScene, atm: Atmosphere, gid: np.ndarray, d_map: np.ndarray,
                       r: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Intensity, class and instance of hits ``gid`` seen along ``d_map`` (N, 3) at ranges ``r``."""
    return _intensity_of(atm, _Surface.of(scene, gid, d_map), r)


def _intensity_of(atm: Atmosphere, s: _Surface, r: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Intensity, class and instance of hits (their :class:`_Surface` ``s``) at ranges ``r``."""
    rho = s.rho.astype(np.float64)
    retro = s.retro.astype(np.float64)
    if atm.rain_rate_mm_h > 0:
        wet = np.where(s.normals[:, 2] > 0.5, wet_factor(atm.rain_rate_mm_h), 1.0)
        rho, retro = rho * wet, retro * wet
    return intensity_model(rho, retro, s.cos_inc, r, atm.beta), s.cls, s.inst


def _retro_hits(scene: TickScene, gid: np.ndarray) -> np.ndarray:
    """Whether each hit ``gid`` (N,) is on a retro-reflective surface (lane markings, plates, lamp units)."""
    lab = scene.labels
    cls = np.take(lab["semantic"], gid)
    return np.maximum(_RETRO_BY_CLASS[cls], np.take(lab["retro"], gid)) > 0


def _through_crowns(scene: TickScene, rays: np.ndarray, t: np.ndarray, gid: np.ndarray, u: np.ndarray,
                    exclude_track: int | None, t_offset_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Beams into a porous crown (leaf density mu > 0, :mod:`cosim.sensors.assets.vegetation`): each
    travels a free path -ln(1 - u) / mu into it (Beer-Lambert); shorter than the way to the crown's far
    side (or a branch inside), it returns from the leaves there; else it goes on, to the branch or on
    through the crown to whatever lies behind, the actors there at each firing's time ``t_offset_s``
    (N,) [s from the tick; zeros: at the tick]. ``rays`` have unit directions; ``t``, ``gid`` are the
    first hits, returned updated."""
    dens = np.take(scene.labels["leaf_density"], gid)
    idx = np.nonzero((dens > 0) & np.isfinite(t))[0]
    if not len(idx):
        return t, gid
    t, gid = t.copy(), gid.copy()
    eps = np.float32(1e-3)
    r = rays[idx].copy()
    entry = t[idx]
    r[:, :3] += (entry + eps)[:, None] * r[:, 3:]
    t2, g2 = scene.cast(r, exclude_track, with_actors=False)  # the crown's far side, or a branch in it
    depth = -np.log1p(-np.minimum(u[idx], 1 - 1e-9)) / dens[idx]
    inside = depth < t2
    t[idx[inside]] = entry[inside] + depth[inside].astype(np.float32)
    # through the leaves to a branch or trunk: that is the hit
    branch = ~inside & np.isfinite(t2) & (np.take(scene.labels["leaf_density"], g2) <= 0)
    t[idx[branch]] = entry[branch] + eps + t2[branch]
    gid[idx[branch]] = g2[branch]
    # out of the far side: on to whatever lies behind (a second crown behind it is taken as solid)
    out = np.nonzero(~inside & ~branch)[0]
    if len(out):
        r3 = r[out].copy()
        far = np.where(np.isfinite(t2[out]), t2[out], 0.0) + eps
        r3[:, :3] += far[:, None] * r3[:, 3:]
        t3, g3 = _cast_binned(scene, r3, t_offset_s[idx[out]], exclude_track, near_m=0.0,
                              lo_s=float(t_offset_s.min()))
        t[idx[out]] = entry[out] + eps + far + t3
        gid[idx[out]] = g3
    return t, gid


def _ray_drop(spec: LidarSpec, atm: Atmosphere, s: _Surface, r: np.ndarray, intensity: np.ndarray) -> np.ndarray:
    """:func:`drop_probability` of hits (their :class:`_Surface` ``s``) at ranges ``r``."""
    energy = s.rho * s.cos_inc
    wet = np.zeros(len(r))
    if atm.rain_rate_mm_h > 0:
        wet = np.where(s.normals[:, 2] > 0.5, WET_DROP * min(1.0, atm.rain_rate_mm_h / 10.0) * (1.0 - s.cos_inc), 0.0)
    return drop_probability(spec, intensity, r, energy, s.retro, s.glass, wet)


def drop_probability(spec: LidarSpec, intensity: np.ndarray, range_m: np.ndarray, energy: np.ndarray,
                     retro: np.ndarray, glass: np.ndarray, wet_grazing: np.ndarray) -> np.ndarray:
    """Probability (N,) that each return is lost.

    - CARLA's drop-off (``sensor.lidar.ray_cast``): a share ``dropoff_general_rate`` is dropped at random;
      below ``dropoff_intensity_limit`` a return is dropped with a probability falling linearly from
      ``dropoff_zero_intensity`` at zero intensity to none at the limit.
    - Return energy: ``energy`` (N,) is rho cos(alpha) (diffuse reflectivity times the incidence cosine);
      the received power is energy / R^2, and the detection probability 1 / (1 + (P90 / P)^k / 9), with
      P90 that of a 10 % target at ``detection_range_10pct_m`` (detected 9 times in 10 there).
    - Glass drops with :data:`GLASS_DROP`; a wet upward surface with ``wet_grazing`` (N,) (0..1).
    - A retro-reflector (``retro`` > 0) never drops.
    """
    keep = np.full(len(intensity), 1.0 - spec.dropoff_general_rate)
    lim = spec.dropoff_intensity_limit
    if lim > 0:
        keep *= np.where(intensity >= lim, 1.0, 1.0 - spec.dropoff_zero_intensity * (1.0 - intensity / lim))
    p90 = 0.1 / spec.detection_range_10pct_m ** 2
    power = np.maximum(energy, 1e-9) / np.maximum(range_m, MIN_RANGE_M) ** 2
    keep /= 1.0 + (p90 / power) ** DETECTION_EXPONENT / 9.0
    keep *= np.where(glass, 1.0 - GLASS_DROP, 1.0) * (1.0 - wet_grazing)
    return np.where(retro > 0, 0.0, 1.0 - keep)


def _edge_returns(scene: TickScene, spec: LidarSpec, atm: Atmosphere, rays: np.ndarray, d_sensor: np.ndarray,
                  ring: np.ndarray, t_off_ns: np.ndarray, exclude: int | None, r_first: np.ndarray,
                  hit: np.ndarray, parts: list, rng: np.random.Generator | None, sigma: float) -> list:
    """Last returns of beams whose footprint straddles a near object's edge (a pole, a crown, a car).

    A beam is at an edge when the next or previous firing of its ring reached more than
    :data:`DUAL_MIN_SEPARATION_M` farther (or nothing); the half of its footprint towards that
    neighbour is cast (the ray midway between the two) and, when it meets a surface that much farther,
    the beam reports it as its last return, the near one as its strongest. Each return carries the
    intensity of the half footprint it comes from. Changes ``parts[0]`` (the kind and intensity of the
    near returns; its rows are the beams of ``hit`` in order) and gives the far returns.
    """
    n = len(r_first)
    first = np.isfinite(r_first)
    partner = np.full(n, -1)
    for step in (1, -1):
        nb = np.clip(np.arange(n) + step, 0, n - 1)
        jump = first & (ring[nb] == ring) & (nb != np.arange(n)) & ~(r_first[nb] <= r_first + DUAL_MIN_SEPARATION_M)
        partner = np.where(jump & (partner < 0), nb, partner)
    idx = np.nonzero(partner >= 0)[0]
    if not len(idx):
        return []
    mid = rays[idx, 3:].astype(np.float64) + rays[partner[idx], 3:]
    mid /= np.linalg.norm(mid, axis=1, keepdims=True)
    mrays = np.concatenate([rays[idx, :3], mid], axis=1).astype(np.float32)
    t2, g2 = _cast_binned(scene, mrays, t_off_ns[idx] * 1e-9, exclude)
    far = (t2 <= spec.range_m) & (t2 > r_first[idx] + DUAL_MIN_SEPARATION_M)
    idx, t2, g2, mid = idx[far], t2[far].astype(np.float64), g2[far], mid[far]
    if not len(idx):
        return []
    if rng is not None:
        t2 = t2 + sigma * rng.standard_normal(len(idx))
    i2, c2, n2 = _surface_intensity(scene, atm, g2, mid, t2)
    # the near returns of these beams: parts[0] holds the returns of beams with a first hit, in beam order
    pts, inten, rng_, cls, inst, toff, kind, beam = parts[0]
    order = np.cumsum(hit) - 1  # row of each beam's return in parts[0]
    rows = order[idx]
    inten = inten.copy()
    kind = kind.copy()
    inten[rows] *= 0.5
    kind[rows] = RETURN_STRONGEST
    parts[0] = (pts, inten, rng_, cls, inst, toff, kind, beam)
    return [(d_sensor[idx] * t2[:, None], 0.5 * i2, ring[idx], c2, n2, t_off_ns[idx],
             np.full(len(idx), RETURN_LAST, np.uint8), idx)]
