"""Pinhole cameras: RGB, planar depth, semantic and instance images from one set of hits.

Rays leave the optical centre through pixel centres (u + 0.5, v + 0.5) with direction
``R @ K^-1 [u + 0.5, v + 0.5, 1]`` (optical z = 1), so the cast distance is the planar depth.

Adaptive casting (``block_px`` > 1): rays are first cast on a coarse grid of pixel centres every
``block_px`` pixels. A block whose four corner samples hit the same face (one plane, one set of
labels and material: :meth:`TriMesh.faces`), and that no actor, no
thin static object (pole, light, marking, RSU) and no static mesh vertex projects into, is filled
from that face: its class, instance and material are the face's and its inverse depth,
which is affine in the image over a plane, is interpolated exactly. Every other block is split in
four and refined the same way, down to single pixels (a quadtree). All outputs of a camera come
from the same per-pixel triangle index, so they agree.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np

from cosim.geometry import project_to_image, undistort
from cosim.scenario.model import CameraSpec

from . import kernels
from .encoding import PackedLabels
from .environment import LAMP_RGB, Atmosphere
from .rig import Pose
from .scene import TickScene
from .surface import (
    LAMP_PROBE_PX,
    WET_ALBEDO,
    WET_FILM,
    SurfaceInputs,
    camera_emitters,
    lamp_spans,
    sensor_codes_kernel,
    shade_linear,
)

if TYPE_CHECKING:
    from .encoding import Encodes

#: Box edges (pairs of corner indices into the 8 corners of :func:`box_corners`).
_EDGES = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4], [0, 4], [1, 5], [2, 6],
                   [3, 7]])
_NEAR_M = 0.05
#: [m] planar near clip of the cameras: surfaces closer than this (housing, an RSU's own pole top)
#: are not seen.
NEAR_CLIP_M = 0.5


@dataclass(frozen=True)
class CameraFrame:
    """One camera at one tick. H x W images; pixel (v, u) is row v, column u.

    ``rgb`` (H, W, 3) uint8 sRGB or None; ``depth`` (H, W) float32 planar depth [m] along the optical
    axis, inf where nothing was hit; ``semantic`` (H, W) uint8 class id; ``instance`` (H, W) uint32
    (track id, static instance id, 0); ``K`` (3, 3) float64 and ``P`` (3, 4) float64 intrinsics;
    ``pose``: map <- optical frame. ``encoded``: the encodes the suite started (a
    :class:`~cosim.sensors.encoding.Encodes`, not part of the data); a suite that releases pixels
    leaves ``rgb`` (and ``depth``) None once their encodes hold them.
    """

    agent_id: str
    name: str
    width: int
    height: int
    K: np.ndarray
    P: np.ndarray
    pose: Pose
    rgb: np.ndarray | None
    depth: np.ndarray | None
    semantic: np.ndarray | None
    instance: np.ndarray | None
    encoded: Encodes | None = field(default=None, compare=False, repr=False)
    D: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)  # Brown-Conrady k1, k2, p1, p2, k3 (plumb_bob)


def box_corners(center: np.ndarray, size: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """Corners (B, 8, 3) of boxes: centres (B, 3), sizes (B, 3) (l, w, h), rotations (B, 3, 3) map <- box."""
    sgn = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1], [-1, -1, 1], [1, -1, 1], [1, 1, 1],
                    [-1, 1, 1]], np.float64) * 0.5
    local = sgn[None] * size[:, None, :]
    return np.einsum("bij,bkj->bki", rotation, local) + center[:, None, :]


def project_boxes(corners_map: np.ndarray, pose: Pose, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Image bounding rectangles of boxes, clipped at the near plane.

    ``corners_map`` (B, 8, 3) in map. Returns ``rects`` (B, 4) float64 (umin, vmin, umax, vmax) in pixels
    and ``valid`` (B,) bool (False when the box is entirely behind the camera).
    """
    if len(corners_map) == 0:
        return np.zeros((0, 4)), np.zeros(0, bool)
    p = pose.to_frame(corners_map.reshape(-1, 3)).reshape(-1, 8, 3)
    a, b = p[:, _EDGES[:, 0]], p[:, _EDGES[:, 1]]
    straddle = (a[..., 2] - _NEAR_M) * (b[..., 2] - _NEAR_M) < 0
    with np.errstate(divide="ignore", invalid="ignore"):
        tcut = (_NEAR_M - a[..., 2]) / (b[..., 2] - a[..., 2])
    x = a + np.where(straddle, tcut, 0.0)[..., None] * (b - a)
    pts = np.concatenate([p, x], axis=1)
    ok = np.concatenate([p[..., 2] >= _NEAR_M, straddle], axis=1)
    z = np.where(ok, pts[..., 2], 1.0)
    u = K[0, 0] * pts[..., 0] / z + K[0, 2]
    v = K[1, 1] * pts[..., 1] / z + K[1, 2]
    inf = np.inf
    rects = np.stack([np.where(ok, u, inf).min(1), np.where(ok, v, inf).min(1), np.where(ok, u, -inf).max(1),
                      np.where(ok, v, -inf).max(1)], axis=1)
    return rects, ok.any(axis=1)


def project_points(points_map: np.ndarray, pose: Pose, K: np.ndarray,
                   D: tuple[float, ...] | np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (N, 2) of map points and whether each lies in front of the camera (N,);
    ``D``: Brown-Conrady k1, k2, p1, p2, k3 of a distorting lens (``cosim.geometry.project_to_image``)."""
    p = pose.to_frame(points_map)
    uv, _ = project_to_image(p, K, D)
    return uv, p[:, 2] > _NEAR_M


@lru_cache(maxsize=16)
def _distorted_grid(w: int, h: int, fx: float, fy: float, cx: float, cy: float,
                    D: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) optical-frame x and y (z = 1) of the rays through the pixel centres of a distorted image."""
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    xy = undistort(np.stack([(u.ravel() - cx) / fx, (v.ravel() - cy) / fy], axis=1), D)
    x, y = xy[:, 0].reshape(h, w), xy[:, 1].reshape(h, w)
    x.flags.writeable = y.flags.writeable = False
    return x, y


def pixel_grid(cam: CameraSpec, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Optical-frame x and y (z = 1) of every pixel-centre ray, broadcastable to (H, W): (1, W) and
    (H, 1) for a pinhole, (H, W) each with ``cam.distortion``."""
    if cam.distortion is not None and any(cam.distortion):
        return _distorted_grid(cam.width, cam.height, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]),
                               float(K[1, 2]), tuple(float(v) for v in cam.distortion))
    xs, ys = _pixel_dirs(cam, K)
    return xs[None, :], ys[:, None]


def _pixel_dirs(cam: CameraSpec, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Optical-frame x and y (per column (W,), per row (H,)) of pixel-centre rays with z = 1."""
    x = (np.arange(cam.width) + 0.5 - K[0, 2]) / K[0, 0]
    y = (np.arange(cam.height) + 0.5 - K[1, 2]) / K[1, 1]
    return x, y


def _rays(pose: Pose, xs: np.ndarray, ys: np.ndarray, near: float = 0.0) -> np.ndarray:
    """Rays (N, 6) float32 through optical-frame points (xs, ys, 1) (each (N,)), starting ``near``
    (planar depth) in front of the optical centre."""
    return kernels.rays(np.asarray(xs, np.float64), np.asarray(ys, np.float64), pose.rotation, pose.position_m,
                        float(near))


@dataclass(frozen=True)
class Occluders:
    """What adaptive casting must not interpolate across, in map: centre lines of thin static
    things (S, 2, 3) (poles, lamp arms, lane markings, trunks, and with a sun their shadows on the
    ground), static mesh vertices (V, 3), and the tick's actor boxes (A, 8, 3).

    ``sun_dir`` (3,): unit vector towards the sun when the cameras trace sun shadows (else None);
    ``shadow_boxes`` (A, 8, 3): the volumes the actors' shadows may fall in (:func:`shadow_boxes`),
    where a standing camera tests its kept static pixels against the actors."""

    segments: np.ndarray
    points: np.ndarray
    actor_boxes: np.ndarray
    sun_dir: np.ndarray | None = None
    shadow_boxes: np.ndarray | None = None


#: [m] shadow rays start this far off the surface, along its normal (no self-shadowing)
SHADOW_BIAS_M = 0.02


def ground_shadow(points: np.ndarray, sun_dir: np.ndarray, ground_z_m: float = 0.0) -> np.ndarray:
    """Where the sun throws points (..., 3) onto the plane z = ``ground_z_m``."""
    k = (points[..., 2:3] - ground_z_m) / sun_dir[2]
    out = points - k * sun_dir
    out[..., 2] = ground_z_m
    return out


def shadow_boxes(corners: np.ndarray, sun_dir: np.ndarray) -> np.ndarray:
    """(A, 8, 3) sheared boxes from each box's top face (corners 4..7 of (A, 8, 3)) down to its
    shadow on the ground: every point of the box's shadow on the ground lies in it (walls in between
    too, up to the top face)."""
    top = corners[:, 4:8]
    return np.concatenate([ground_shadow(top, sun_dir, float(corners[..., 2].min(initial=0.0))), top], axis=1)


def sun_lit(scene: TickScene, rays: np.ndarray, t: np.ndarray, gid: np.ndarray, sun_dir: np.ndarray,
            with_static: bool = True, with_actors: bool = True) -> np.ndarray:
    """(N,) bool: whether the sun reaches the hit of each ray (``t`` inf: a miss, lit). Hits on
    surfaces turned away from the sun count as lit (the sun adds nothing to them either way)."""
    lit = np.ones(len(t), bool)
    sh, k = kernels.shadow_rays(rays, t, gid, scene.labels["normal"], sun_dir.astype(np.float32),
                                np.float32(SHADOW_BIAS_M))
    if len(k):
        lit[k] = ~scene.occluded(sh, with_static, with_actors)
    return lit


_MAX_SEGMENT_SAMPLES = 4096


def segment_pixels(segs: np.ndarray, pose: Pose, K: np.ndarray, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (rows, cols) along the projections of 3D segments ``segs`` (S, 2, 3), clipped at the
    near plane, sampled every pixel (at most 4096 samples per segment) and kept inside the image."""
    if len(segs) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    p = pose.to_frame(segs.reshape(-1, 3)).reshape(-1, 2, 3)
    a, b = p[:, 0], p[:, 1]
    keep = (a[:, 2] > _NEAR_M) | (b[:, 2] > _NEAR_M)
    a, b = a[keep], b[keep]
    with np.errstate(divide="ignore", invalid="ignore"):
        tcut = (_NEAR_M - a[:, 2]) / (b[:, 2] - a[:, 2])
        a = np.where((a[:, 2] < _NEAR_M)[:, None], a + tcut[:, None] * (b - a), a)
        tcut = (_NEAR_M - b[:, 2]) / (a[:, 2] - b[:, 2])
        b = np.where((b[:, 2] < _NEAR_M)[:, None], b + tcut[:, None] * (a - b), b)
    za, zb = np.maximum(a[:, 2], _NEAR_M), np.maximum(b[:, 2], _NEAR_M)
    ua = np.stack([K[0, 0] * a[:, 0] / za + K[0, 2], K[1, 1] * a[:, 1] / za + K[1, 2]], axis=1)
    ub = np.stack([K[0, 0] * b[:, 0] / zb + K[0, 2], K[1, 1] * b[:, 1] / zb + K[1, 2]], axis=1)
    # Liang-Barsky clip to the image rectangle
    d = ub - ua
    t0, t1 = np.zeros(len(d)), np.ones(len(d))
    ok = np.ones(len(d), bool)
    for p_, q_ in ((-d[:, 0], ua[:, 0]), (d[:, 0], w - ua[:, 0]), (-d[:, 1], ua[:, 1]), (d[:, 1], h - ua[:, 1])):
        with np.errstate(divide="ignore", invalid="ignore"):
            r = q_ / p_
        ok &= ~((p_ == 0) & (q_ < 0))
        t0 = np.where(p_ < 0, np.maximum(t0, r), t0)
        t1 = np.where(p_ > 0, np.minimum(t1, r), t1)
    ok &= t0 <= t1
    ua, ub = ua[ok] + t0[ok, None] * d[ok], ua[ok] + t1[ok, None] * d[ok]
    n = np.minimum(np.ceil(np.linalg.norm(ub - ua, axis=1)).astype(np.int64) + 1, _MAX_SEGMENT_SAMPLES)
    seg = np.repeat(np.arange(len(n)), n)
    start = np.concatenate([[0], np.cumsum(n)[:-1]]).astype(np.int64)
    t = (np.arange(int(n.sum())) - start[seg]) / np.maximum(n[seg] - 1, 1)
    uv = ua[seg] + t[:, None] * (ub[seg] - ua[seg])
    m = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    return uv[m, 1].astype(np.int64), uv[m, 0].astype(np.int64)


def _clip_rects(rects: np.ndarray, h: int, w: int, margin: float = 1.0) -> list[tuple[int, int, int, int]]:
    """Pixel rectangles (umin, vmin, umax, vmax) grown by ``margin`` and clipped to the sample grid
    (h + 1) x (w + 1), as inclusive (i0, i1, j0, j1); rectangles outside it are dropped."""
    out = []
    for umin, vmin, umax, vmax in rects:
        if umax < -margin or vmax < -margin or umin > w + margin or vmin > h + margin:
            continue
        out.append((max(0, math.floor(vmin - margin)), min(h, math.ceil(vmax + margin)),
                    max(0, math.floor(umin - margin)), min(w, math.ceil(umax + margin))))
    return out


def _largest_block(h: int, w: int, block_px: int) -> int:
    s = 1
    while s * 2 <= block_px and h % (s * 2) == 0 and w % (s * 2) == 0:
        s *= 2
    return s


class StaticImage:
    """What a camera that does not move (an RSU's) keeps across ticks: its image of the static world
    alone, cast once (adaptively) for the pose it was made at: the static triangle index (H, W) int32
    (-1 for a miss), planar depth (H, W) float32 and, with a sun, whether it reaches each pixel (H, W)
    bool. They are kept zstd-packed (:class:`~cosim.sensors.encoding.PackedLabels`, lossless: a
    1280x720 camera's 8.3 MB keep about 0.2 MB) and unpacked into fresh arrays each tick
    (:meth:`arrays`, about 3 ms)."""

    def __init__(self) -> None:
        self.key: bytes | None = None
        self.shape: tuple[int, int] = (0, 0)
        self._packed: tuple[PackedLabels, PackedLabels, PackedLabels | None] | None = None

    def keep(self, key: bytes, gid: np.ndarray, depth: np.ndarray, lit: np.ndarray | None) -> None:
        self.key, self.shape = key, gid.shape
        self._packed = (PackedLabels.of(gid), PackedLabels.of(depth), None if lit is None else PackedLabels.of(lit))

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """New (writable) ``gid``, ``depth`` and ``lit`` (None without a sun) arrays of the kept image."""
        assert self._packed is not None, "StaticImage.arrays before keep"
        g, d, li = self._packed
        gid, depth = np.empty(self.shape, np.int32), np.empty(self.shape, np.float32)
        g.into(gid)
        d.into(depth)
        lit = None
        if li is not None:
            lit = np.empty(self.shape, bool)
            li.into(lit)
        return gid, depth, lit


def cast_image(
    cam: CameraSpec,
    K: np.ndarray,
    pose: Pose,
    scene: TickScene,
    occ: Occluders,
    exclude_track: int | None,
    block_px: int,
    fixed: StaticImage | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Per-pixel global triangle index (H, W) int32, planar depth (H, W) float32 (inf on a miss) and,
    when ``occ.sun_dir`` is set, whether the sun reaches the pixel's surface (H, W) bool (else None).

    With ``block_px`` > 1 the image is refined as a quadtree from blocks of ``block_px`` (a power of
    two dividing H and W, else the largest that does) down to single pixels (module docstring).
    Actor triangles are only cast for samples inside some actor's projected box.

    ``fixed``: the camera's :class:`StaticImage` when it does not move between ticks. Its static
    image is made once; every tick then casts one ray per pixel inside the actors' projected boxes
    against the actors alone and keeps the nearer hit, so the work follows what moves; with a sun,
    the pixels inside the actors' shadow volumes that the static world leaves lit test their shadow
    rays against the actors.
    """
    if cam.distortion is not None and any(cam.distortion):
        return _cast_distorted(cam, K, pose, scene, occ, exclude_track)
    if fixed is None:
        return _cast_adaptive(cam, K, pose, scene, occ, exclude_track, block_px)
    h, w = cam.height, cam.width
    key = pose.rotation.tobytes() + pose.position_m.tobytes() + K.tobytes()
    if key != fixed.key or fixed.shape != (h, w):
        g, d, lit = _cast_adaptive(cam, K, pose, scene, occ, exclude_track, block_px, with_actors=False)
        fixed.keep(key, np.where(g == scene.miss, np.int32(-1), g), d, lit)
    gid, depth, lit = fixed.arrays()
    gid[gid < 0] = np.int32(scene.miss)
    xs, ys = _pixel_dirs(cam, K)
    rects, valid = project_boxes(occ.actor_boxes, pose, K)
    under = np.zeros((h, w), bool)
    for i0, i1, j0, j1 in _clip_rects(rects[valid], h - 1, w - 1):
        under[i0:i1 + 1, j0:j1 + 1] = True
    idx = np.flatnonzero(under)
    if len(idx):
        rr, cc = np.divmod(idx, w)
        rays = _rays(pose, xs[cc], ys[rr], NEAR_CLIP_M)
        ta, ga = scene.cast(rays, exclude_track, with_static=False)
        nearer = np.nonzero(ta + np.float32(NEAR_CLIP_M) < depth.ravel()[idx])[0]
        depth.ravel()[idx[nearer]] = ta[nearer] + np.float32(NEAR_CLIP_M)
        gid.ravel()[idx[nearer]] = ga[nearer]
        if lit is not None and len(nearer):
            lit.ravel()[idx[nearer]] = sun_lit(scene, rays[nearer], ta[nearer], ga[nearer], occ.sun_dir)
    if lit is not None and occ.shadow_boxes is not None and len(occ.shadow_boxes):
        rects, valid = project_boxes(occ.shadow_boxes, pose, K)
        shade_px = np.zeros((h, w), bool)
        for i0, i1, j0, j1 in _clip_rects(rects[valid], h - 1, w - 1):
            shade_px[i0:i1 + 1, j0:j1 + 1] = True
        shade_px &= lit & np.isfinite(depth) & ((gid < scene.n_static) | (gid == scene.miss))
        idx = np.flatnonzero(shade_px)
        if len(idx):
            rr, cc = np.divmod(idx, w)
            rays = _rays(pose, xs[cc], ys[rr], NEAR_CLIP_M)
            t = depth.ravel()[idx] - np.float32(NEAR_CLIP_M)
            lit.ravel()[idx] = sun_lit(scene, rays, t, gid.ravel()[idx], occ.sun_dir, with_static=False)
    return gid, depth, lit


def _cast_distorted(cam: CameraSpec, K: np.ndarray, pose: Pose, scene: TickScene, occ: Occluders,
                    exclude_track: int | None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """:func:`cast_image` through a distorting lens: one ray per pixel along its undistorted direction
    (the depth stays planar: along the optical axis)."""
    h, w = cam.height, cam.width
    x, y = pixel_grid(cam, K)
    rays = _rays(pose, x.ravel(), y.ravel(), NEAR_CLIP_M)
    t, gid = scene.cast(rays, exclude_track)
    lit = None if occ.sun_dir is None else sun_lit(scene, rays, t, gid, occ.sun_dir).reshape(h, w)
    return gid.reshape(h, w), (t + np.float32(NEAR_CLIP_M)).reshape(h, w), lit


def _cast_adaptive(
    cam: CameraSpec,
    K: np.ndarray,
    pose: Pose,
    scene: TickScene,
    occ: Occluders,
    exclude_track: int | None,
    block_px: int,
    with_actors: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """:func:`cast_image` for a camera without a kept static image (``with_actors=False``: the static
    world alone, ignoring ``occ.actor_boxes``). With a sun, a block is coherent only when its corners
    agree on the sun's reaching them too, so shadow edges are refined down to single pixels."""
    h, w = cam.height, cam.width
    xs, ys = _pixel_dirs(cam, K)
    top = _largest_block(h, w, block_px)
    sun = occ.sun_dir
    if top == 1:
        gx, gy = np.meshgrid(xs, ys)
        rays = _rays(pose, gx.ravel(), gy.ravel(), NEAR_CLIP_M)
        t, gid = scene.cast(rays, exclude_track, with_actors=with_actors)
        lit = None if sun is None else sun_lit(scene, rays, t, gid, sun, with_actors=with_actors).reshape(h, w)
        return gid.reshape(h, w), (t + np.float32(NEAR_CLIP_M)).reshape(h, w), lit

    # samples live on the (h + 1) x (w + 1) grid of pixel centres (the last row/column just outside)
    gw = w + 1
    xs_ext = (np.arange(w + 1) + 0.5 - K[0, 2]) / K[0, 0]
    ys_ext = (np.arange(h + 1) + 0.5 - K[1, 2]) / K[1, 1]
    a_rects, a_valid = project_boxes(occ.actor_boxes, pose, K)
    a_rects = _clip_rects(a_rects[a_valid], h, w) if with_actors else []
    actor_px = np.zeros((h + 1, w + 1), bool)
    for i0, i1, j0, j1 in a_rects:
        actor_px[i0:i1 + 1, j0:j1 + 1] = True
    actor_px = actor_px.ravel()
    rr, cc = segment_pixels(occ.segments, pose, K, h, w)
    if len(occ.points):
        uv, front = project_points(occ.points, pose, K)
        m = front & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        rr = np.concatenate([rr, uv[m, 1].astype(np.int64)])
        cc = np.concatenate([cc, uv[m, 0].astype(np.int64)])
    any_actor = len(a_rects) > 0

    G = np.full((h + 1) * gw, -2, np.int32)
    T = np.full((h + 1) * gw, np.inf, np.float32)
    S = np.ones((h + 1) * gw, bool)  # the sun reaches the sample

    def sample(idx: np.ndarray) -> None:
        rays = kernels.grid_rays(idx, gw, xs_ext, ys_ext, pose.rotation, pose.position_m, NEAR_CLIP_M)
        t, g = scene.cast(rays, exclude_track, with_actors=False)
        if any_actor:
            sel = np.nonzero(actor_px[idx])[0]
            if len(sel):
                ta, ga = scene.cast(rays[sel], exclude_track, with_static=False)
                nearer = ta < t[sel]
                t[sel[nearer]] = ta[nearer]
                g[sel[nearer]] = ga[nearer]
        G[idx] = g
        T[idx] = t + np.float32(NEAR_CLIP_M)
        if sun is not None:
            S[idx] = sun_lit(scene, rays, t, g, sun, with_actors=with_actors)

    sample((np.arange(0, h + 1, top)[:, None] * gw + np.arange(0, w + 1, top)[None, :]).ravel())

    # 2 px blocks holding a forced pixel or the pixel below or right of one; each coarser level ORs
    # the four blocks it is made of
    forced = {2: np.zeros((h // 2, w // 2), bool)}
    forced[2][rr // 2, cc // 2] = True
    forced[2][np.minimum(rr + 1, h - 1) // 2, cc // 2] = True
    forced[2][rr // 2, np.minimum(cc + 1, w - 1) // 2] = True
    s = 2
    while s < top:
        f = forced[s]
        forced[2 * s] = f[0::2, 0::2] | f[1::2, 0::2] | f[0::2, 1::2] | f[1::2, 1::2]
        s *= 2

    def forced_at(s: int) -> np.ndarray:
        """(h / s, w / s) bool: blocks holding a forced pixel or, down to 4 px blocks, touching an
        actor's rectangle (so every actor is sampled at least every 2 px)."""
        if s == 2:
            return forced[2]
        f = forced[s].copy()
        for i0, i1, j0, j1 in a_rects:
            f[i0 // s:min(i1, h - 1) // s + 1, j0 // s:min(j1, w - 1) // s + 1] = True
        return f

    gid = np.empty((h, w), np.int32)
    depth = np.empty((h, w), np.float32)
    lit = np.empty((h, w), bool) if sun is not None else None
    lit_k = lit if lit is not None else np.empty((0, 0), bool)
    Gv, Tv, Sv = G.reshape(h + 1, gw), T.reshape(h + 1, gw), S.reshape(h + 1, gw)
    # top level: dense fill of the whole image (pixels of mixed blocks are overwritten below)
    kernels.fill_top(Gv, Tv, Sv, top, gid, depth, lit_k, lit is not None)
    face = scene.labels["face"]
    s = top
    mixed = np.ones((1, 1), bool)
    while s >= 2:
        # coherent blocks of mixed parents are filled from their corners (exact for planes), the
        # mixed ones get new samples
        mixed, cand = kernels.refine_level(Gv, Tv, Sv, face, s, s == top, mixed, forced_at(s), s != top, gid, depth,
                                           lit_k, lit is not None)
        if len(cand):
            sample(cand)
        s //= 2
    # pixels of mixed 2-px blocks (the last ``mixed``) are samples themselves
    kernels.copy_mixed(mixed, Gv, Tv, Sv, gid, depth, lit_k, lit is not None)
    return gid, depth, lit


# ----------------------------------------------------------------------------------- shading


@dataclass(frozen=True)
class LightMap:
    """Artificial irradiance on the ground (relative units, 1 = under a street lamp) on a raster.

    ``values`` (ny, nx) float32; cell (i, j) covers x0 + j*res .. , y0 + i*res .. [m].
    """

    values: np.ndarray
    x0: float
    y0: float
    res_m: float


_GAMMA_LUT = (np.linspace(0.0, 1.0, 4096) ** (1 / 2.2) * 255 + 0.5).astype(np.uint8)
SKY_LEVELS = 1024


def to_srgb(linear: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """Linear colour (..., 3) float -> sRGB uint8 (gamma 2.2, clipped)."""
    idx = np.clip(linear * np.float32(exposure * 4095.0), 0, 4095).astype(np.int16)
    return np.take(_GAMMA_LUT, idx)


def sky_table(atm: Atmosphere) -> np.ndarray:
    """Sky colour (SKY_LEVELS, 3) float32, linear, from the horizon (level 0) to the zenith."""
    k = np.sqrt(np.linspace(0.0, 1.0, SKY_LEVELS))[:, None]
    return (atm.sky_horizon * (1 - k) + atm.sky_zenith * k).astype(np.float32)


@dataclass(frozen=True)
class ShadingTables:
    """Per global triangle index (rows 0..miss-1), then ``miss`` (unused), then the sky levels: R
    rows lit by the sun, then the same R rows in the sun's shadow (row + ``rows``).

    ``linear`` (2 R, 3) float32 colour under sun and sky, plus the lamps' own glow when artificial
    light is on; ``srgb`` (2 R, 3) uint8 the same after exposure and gamma; ``albedo`` (2 R, 3)
    float32; ``albedo_lamp`` (2 R, 3) float32 albedo times the street lights' colour; ``surface``
    the material, normal and instance per global index and the tick's point lights.
    """

    linear: np.ndarray
    srgb: np.ndarray
    albedo: np.ndarray
    albedo_lamp: np.ndarray
    miss: int
    rows: int
    surface: SurfaceInputs


def shading_tables(lut_rgb: np.ndarray, lut_albedo: np.ndarray, lut_emissive: np.ndarray, miss: int,
                   atm: Atmosphere, lut_rgb_shadow: np.ndarray | None = None,
                   surface: SurfaceInputs | None = None) -> ShadingTables:
    """Tables for :func:`shade` from per-global-index colour (miss + 1, 3) in the sun and in its
    shadow (``lut_rgb_shadow``; default: the same), albedo and emissive rows, and the surface inputs
    (:func:`cosim.sensors.surface.surface_inputs`; default: plain, facing up, no detail)."""
    sky = sky_table(atm)
    shadow = lut_rgb if lut_rgb_shadow is None else lut_rgb_shadow
    linear = np.concatenate([lut_rgb.astype(np.float32), sky, shadow.astype(np.float32), sky])
    albedo = np.concatenate([lut_albedo.astype(np.float32), np.zeros_like(sky)] * 2)
    if atm.artificial > 0:  # lamps glow in their own colour: a constant per triangle
        glow = np.concatenate([lut_emissive.astype(np.float32), np.zeros(len(sky), np.float32)] * 2)
        linear += albedo * (glow * np.float32(2.0 * atm.artificial))[:, None]
    if surface is None:
        n = miss + 1
        surface = SurfaceInputs(np.zeros(n, np.uint8), np.tile(np.float32([0, 0, 1]), (n, 1)), np.zeros(n, np.uint32),
                                np.zeros((0, 7)), detail=False)
    return ShadingTables(linear, to_srgb(linear, atm.exposure), albedo, albedo * LAMP_RGB, miss, len(linear) // 2,
                         surface)


def shade(
    gid: np.ndarray,
    depth: np.ndarray,
    lit: np.ndarray | None,
    cam: CameraSpec,
    K: np.ndarray,
    pose: Pose,
    tables: ShadingTables,
    atm: Atmosphere,
    light: LightMap | None,
    rng: np.random.Generator,
    block_px: int = 4,
    noise: bool = True,
) -> np.ndarray:
    """sRGB image (H, W, 3) uint8 from per-pixel global triangle index ``gid`` (H, W) int32,
    planar ``depth`` (H, W) float32 [m] and whether the sun reaches each pixel (``lit`` (H, W) bool,
    None: everywhere).

    Sun and sky light come baked per triangle; one compiled pass (:func:`cosim.sensors.surface.shade_linear`)
    adds the sky gradient, procedural surface detail, wet roads under rain, artificial light (street
    lights and headlights from ``light``, lamps' own glow, lit windows), extinction by distance towards
    the fog colour, the rain's dimming and its streaks (drawn from ``rng`` first), and the camera model
    (:func:`sensor_codes`'s; its noise offsets from ``rng`` next, unless ``noise`` is False) with the
    gamma table.
    """
    h, w = gid.shape
    xg, yg = (np.broadcast_to(np.asarray(a, np.float64), (h, w)) for a in pixel_grid(cam, K))
    surf = tables.surface
    rot, origin = np.asarray(pose.rotation, np.float64), np.asarray(pose.position_m, np.float64)
    lamps, spans = _NO_LAMPS, _NO_SPANS
    if atm.wet_roads and atm.artificial > 0:
        lamps = camera_emitters(surf.emitters, origin, rot[:, 2])
        if len(lamps):
            spans = lamp_spans(gid, depth, xg, yg, rot, origin, tables.miss, surf.material, surf.normal, WET_FILM,
                               lamps, float(atm.artificial), LAMP_PROBE_PX)
    out = np.empty((h, w, 3), np.uint8)
    streaks = _NO_STREAKS
    rain = atm.rain_rate_mm_h > 0
    if rain:
        # what each streak pixel adds (nearer drops are brighter: they cover more of the pixel); where
        # streaks cross, the last one drawn counts
        vv, uu, dd = rain_streaks(depth, atm.rain_rate_mm_h, float(K[0, 0]), rng)
        streaks = np.full((h, w), -1.0, np.float32)
        streaks[vv, uu] = np.float32(0.6) / np.maximum(dd, np.float32(2.0))
    model = _camera_model_inputs(cam, K, h, w, rng if noise else None)
    values = light.values if light is not None and atm.artificial > 0 else _NO_LIGHT
    shade_linear(
        gid, depth, _NO_LIT if lit is None else lit, xg, yg, rot, origin, tables.linear, tables.albedo_lamp,
        tables.rows, tables.miss, SKY_LEVELS, surf.material, surf.normal, surf.instance, surf.detail, float(K[0, 0]),
        atm.wet_roads, WET_ALBEDO, WET_FILM, _f64(atm.sun_dir), _f64(atm.sun_rgb), _f64(atm.sky_zenith),
        _f64(atm.sky_horizon), values, float(light.x0) if light is not None else 0.0,
        float(light.y0) if light is not None else 0.0, float(light.res_m) if light is not None else 1.0,
        float(atm.artificial), float(atm.beta), _f64(atm.fog_rgb), 0.8 if rain else 1.0, lamps, spans,
        streaks, _NO_RGB, float(np.float32(atm.exposure * FULL_SCALE)), *model, out,
    )
    return out


_NO_LIT = np.zeros((0, 0), bool)
_NO_LIGHT = np.zeros((0, 0), np.float32)
_NO_LAMPS = np.zeros((0, 7), np.float64)
_NO_SPANS = np.zeros((0, 0, 2), np.int32)
_NO_NOISE = np.zeros((0, 0, 3), np.float32)
_NO_VIGNETTE = np.zeros((0, 0), np.float32)
_NO_OUT = np.zeros((0, 0, 3), np.uint8)
_NO_RGB = np.zeros((0, 0, 3), np.float32)
_NO_STREAKS = np.zeros((0, 0), np.float32)


def _f64(a) -> np.ndarray:
    return np.asarray(a, np.float64)


#: codes of the sensor's linear output (12 bit)
FULL_SCALE = 4095.0
#: side of the seeded noise field a camera's noise is cut from (at a per-frame random offset)
_NOISE_PAD = 97


@lru_cache(maxsize=8)
def _noise_field(h: int, w: int) -> np.ndarray:
    """(H + pad, W + pad, 3) float32 standard normal, the same in every process (fixed seed); read-only."""
    out = np.random.default_rng([0x15E, h, w]).standard_normal((h + _NOISE_PAD, w + _NOISE_PAD, 3), np.float32)
    out.flags.writeable = False
    return out


@lru_cache(maxsize=16)
def _vignette(w: int, h: int, cx: float, cy: float, strength: float) -> np.ndarray:
    """(H, W) float32 relative illumination 1 - strength (r / r_corner)^2 about the principal point."""
    xs = (np.arange(w) + 0.5 - cx).astype(np.float32)
    ys = (np.arange(h) + 0.5 - cy).astype(np.float32)
    r2 = xs[None, :] ** 2 + ys[:, None] ** 2
    out = (1.0 - strength * r2 / r2.max()).astype(np.float32)
    out.flags.writeable = False
    return out


@lru_cache(maxsize=16)
def _noise_std_lut(read: float, shot: float) -> np.ndarray:
    """Noise std [codes] per 12-bit code: sqrt(shot x signal + read^2), in full-scale units x FULL_SCALE."""
    v = np.arange(4096, dtype=np.float64) / FULL_SCALE
    return (np.sqrt(shot * v + read * read) * FULL_SCALE).astype(np.float32)


def sensor_codes(rgb: np.ndarray, cam: CameraSpec, K: np.ndarray, exposure: float,
                 rng: np.random.Generator | None) -> np.ndarray:
    """The camera model, in place on linear colour ``rgb`` (H, W, 3) float32: exposure, vignetting
    (``cam.vignetting``), then with ``rng`` shot and read noise (``cam.shot_noise``, ``cam.read_noise``:
    std sqrt(shot x signal + read^2) in full-scale units), clipped to the sensor's 12-bit codes
    [0, FULL_SCALE]. The noise is a seeded standard normal field cut at an offset drawn from ``rng``."""
    _camera_model(rgb, cam, K, exposure, rng, _NO_OUT)
    return rgb


def _camera_model_inputs(cam: CameraSpec, K: np.ndarray, h: int, w: int, rng: np.random.Generator | None):
    """Vignette, noise field, its offsets (drawn from ``rng``), noise std table and gamma table of a camera."""
    vig = _NO_VIGNETTE
    if cam.vignetting > 0:
        vig = _vignette(w, h, float(K[0, 2]), float(K[1, 2]), float(cam.vignetting))
    field, std, oy, ox = _NO_NOISE, _noise_std_lut(0.0, 0.0), 0, 0
    if rng is not None and (cam.read_noise > 0 or cam.shot_noise > 0):
        oy, ox = (int(x) for x in rng.integers(0, _NOISE_PAD, 2))
        field, std = _noise_field(h, w), _noise_std_lut(float(cam.read_noise), float(cam.shot_noise))
    return vig, field, oy, ox, std, _GAMMA_LUT


def _camera_model(rgb: np.ndarray, cam: CameraSpec, K: np.ndarray, exposure: float,
                  rng: np.random.Generator | None, out: np.ndarray) -> None:
    """:func:`sensor_codes`, and with ``out`` (H, W, 3) uint8 (not empty) its sRGB codes (gamma table)."""
    h, w = rgb.shape[:2]
    sensor_codes_kernel(rgb, float(np.float32(exposure * FULL_SCALE)), *_camera_model_inputs(cam, K, h, w, rng), out)


#: [m] nearest and farthest rain streak the cameras draw
RAIN_NEAR_M, RAIN_FAR_M = 1.0, 25.0


def rain_streaks(depth: np.ndarray, rate_mm_h: float, fx: float,
                 rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Falling drops as slanted streaks placed in depth: (rows, cols, streak depth [m]) of every streak
    pixel that is in front of the scene there (``depth`` (H, W) planar [m]); a drop behind nearer
    geometry is hidden by it. Drops lie uniformly in volume between RAIN_NEAR_M and RAIN_FAR_M; a
    streak's length on the image is its fall during the exposure (1/30 s at 6 m/s) over its depth."""
    h, w = depth.shape
    n = int(min(4000, 60 * rate_mm_h * (h * w) / (1280 * 720)))
    u0 = rng.random(n) * w
    v0 = rng.random(n) * h
    slope = 0.15 + 0.1 * rng.random(n)
    # uniform in volume: depth^3 uniform between the limits
    d = np.cbrt(RAIN_NEAR_M**3 + rng.random(n) * (RAIN_FAR_M**3 - RAIN_NEAR_M**3))
    length = np.clip(0.2 * fx / d, 3, 0.1 * h).astype(np.int64)
    k = np.arange(int(length.max(initial=2)))
    uu = (u0[:, None] + slope[:, None] * k).astype(np.int64)
    vv = (v0[:, None] + k).astype(np.int64)
    dd = np.broadcast_to(d[:, None], uu.shape)
    m = (k[None, :] < length[:, None]) & (uu < w) & (vv < h)
    uu, vv, dd = uu[m], vv[m], dd[m]
    front = dd < depth[vv, uu]
    return vv[front], uu[front], dd[front].astype(np.float32)


