"""The cameras' per-pixel shading, compiled: surface detail, wet roads, street light, fog, sensor codes.

One fused pass per image (:func:`shade_linear`) takes each pixel's global triangle index, planar depth
and sun visibility, and computes the pixel's surface point in the map (camera pose, pixel ray, depth),
its material (:attr:`cosim.sensors.meshes.TriMesh.material`), then

- **procedural surface detail** (``sensors.surface_detail``), deterministic functions of the map
  position (hashed value noise and pulse trains, no random state): asphalt grain, aggregate and
  repaired patches; worn lane paint showing the asphalt; paving tiles with grooves; facades with a
  window grid (glass darker by day; at night a hashed share of the windows, fixed per building and
  window, glows); roof grit; foliage clumps; grass patches with bare soil. Every term is filtered by
  the pixel's footprint on the surface, ``distance / (fx cos(incidence))``: a noise octave fades out
  as the footprint reaches its cell size and a window grid is box-filtered exactly (the integral of
  its pulse train), so far surfaces tend to their mean colour instead of aliasing;
- **wet roads** under rain (:attr:`Atmosphere.wet_roads`): roads, markings, paving and roofs facing up
  are darker (``WET_*_ALBEDO``) and carry a water film: Fresnel (Schlick, ``WET_F0``) reflection of the
  sky, a Blinn-Phong lobe (``WET_SHININESS``) towards the sun where it reaches the surface and towards
  every street lamp and vehicle lamp nearby (:func:`emitters`) at dusk and night, each only within the
  column spans per image row a coarse probe grid finds its lobe in (:func:`lamp_spans`);
- the street lights' and headlights' irradiance from the light map, extinction towards the fog colour,
  the rain's dimming and its streaks (drawn beforehand into a map of the light they add);
- the camera model (exposure, vignetting, seeded shot and read noise, 12-bit clipping) and the gamma
  table (:func:`sensor_codes_kernel` alone applies them to a given linear image).

Kernels are compiled lazily and cached on disk (``cache=True``) and release the GIL (``nogil=True``),
so render threads run them side by side with ray casting; each pixel is computed on its own (the
lamps' reflections row by row), so results do not depend on threads. Arithmetic is float64 with the
safe ``fastmath`` flags :data:`SAFE_FASTMATH` (fused multiply-adds, reciprocals, no signed-zero care;
never ``nnan``/``ninf``, so inf and NaN behave as IEEE says): the compiler may fuse operations by the
CPU it compiles for, so the same inputs give the same bytes on the same machine (docs/architecture.md,
"Determinism"), not across instruction sets.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from .environment import (
    LAMP_RGB,
    LIT_WINDOW_FRACTION,
    WET_F0,
    WET_FILM_PAVING,
    WET_MARKING_ALBEDO,
    WET_PAVING_ALBEDO,
    WET_ROAD_ALBEDO,
    WET_SHININESS,
    WINDOW_RADIANCE,
    WINDOW_RGB,
)
from .meshes import (
    MAT_ASPHALT,
    MAT_FACADE,
    MAT_FOLIAGE,
    MAT_GRASS,
    MAT_MARKING,
    MAT_PAVING,
    MAT_PLAIN,
    MAT_ROOF,
)

#: numba fastmath flags of the shading kernels: fused multiply-adds, reciprocal division, no signed-zero
#: care; never ``nnan`` or ``ninf`` (the kernels rely on inf for misses and on NaN checks)
SAFE_FASTMATH = {"contract", "arcp", "nsz"}

#: [m] feature sizes of the procedural detail
ASPHALT_GRAIN_M = 0.04
ASPHALT_AGGREGATE_M = 0.3
ASPHALT_PATCH_M = 4.0
#: mean share repaired (darker) patches and worn (lighter) areas take off the asphalt's albedo, what far,
#: filtered asphalt shows (negative: on average worn areas lighten it a little more)
ASPHALT_PATCH_MEAN = -0.019
MARKING_WEAR_M = 0.35
PAVING_TILE_M = 0.6
PAVING_GROOVE_M = 0.03
#: facade window grid: storey height and window column spacing, window size and its offset in the cell
FLOOR_M = 3.3
WINDOW_SPACING_M = 2.7
WINDOW_W_M, WINDOW_H_M = 1.5, 1.6
WINDOW_U0_M, WINDOW_Z0_M = 0.6, 0.9
#: window glass by day relative to the wall (dark, a little blue: it reflects the sky)
GLASS_RGB = (0.30, 0.34, 0.42)
FOLIAGE_CLUMP_M = 0.35
GRASS_BLADE_M = 0.12
GRASS_PATCH_M = 2.5

#: per material kind: albedo factor when wet, and the share of the surface the water film covers
WET_ALBEDO = np.ones(8, np.float64)
WET_ALBEDO[[MAT_ASPHALT, MAT_MARKING, MAT_PAVING, MAT_ROOF]] = (WET_ROAD_ALBEDO, WET_MARKING_ALBEDO,
                                                               WET_PAVING_ALBEDO, WET_PAVING_ALBEDO)
WET_FILM = np.zeros(8, np.float64)
WET_FILM[[MAT_ASPHALT, MAT_MARKING, MAT_PAVING, MAT_ROOF]] = (1.0, 0.7, WET_FILM_PAVING, WET_FILM_PAVING)
#: the Blinn-Phong exponent as an integer (the lobe is computed by repeated squaring)
_SHININESS = int(WET_SHININESS)
assert _SHININESS == WET_SHININESS and _SHININESS % 2 == 0, "WET_SHININESS must be an even whole number"
#: the specular lobe of a lamp is not evaluated below this fraction of its peak, nor below this linear
#: radiance (a 12-bit sensor code is 2.4e-4 at exposure 1; the read noise is larger)
_LOBE_CUT = 1e-3
_LOBE_FLOOR = 1e-4

# emitter columns (:func:`emitters`)
EMITTER_COLUMNS = ("x_m", "y_m", "z_m", "intensity", "r", "g", "b")


@dataclass(frozen=True)
class SurfaceInputs:
    """Per global triangle index (miss + 1 rows): ``material`` uint8 kind, ``normal`` (3,) float32,
    ``instance`` uint32; ``emitters`` (E, 7) float64 point lights (:data:`EMITTER_COLUMNS`: map
    position, intensity in light-map units x m^2, colour); ``detail``: draw procedural detail."""

    material: np.ndarray
    normal: np.ndarray
    instance: np.ndarray
    emitters: np.ndarray
    detail: bool = True


def surface_inputs(scene, detail: bool = True) -> SurfaceInputs:
    """:class:`SurfaceInputs` of a :class:`cosim.sensors.scene.TickScene`."""
    lab = scene.labels
    return SurfaceInputs(lab["material"], lab["normal"], lab["instance"], emitters(scene), detail)


def emitters(scene) -> np.ndarray:
    """Point lights (E, 7) of one tick (:data:`EMITTER_COLUMNS`): each glowing static lamp head (one per
    instance, under its middle, intensity h^2 so that it gives irradiance 1 at height h below, as the
    light map does) and each actor's lamp units (one per actor and colour: headlights 20, tail lights 2)."""
    rows = []
    for mesh, static in ((scene.static.mesh, True), (scene.actors, False)):
        glow = np.nonzero(mesh.emissive > 0)[0]
        if not len(glow):
            continue
        cent = mesh.vertices[mesh.triangles[glow]].astype(np.float64).mean(axis=1)
        red = mesh.albedo[glow, 1] < 0.5
        key = mesh.instance[glow].astype(np.int64) * 2 + red
        for k in np.unique(key):
            sel = key == k
            c = cent[sel]
            if static:
                z = float(c[:, 2].min())
                rows.append([*c[:, :2].mean(0), z, z * z, *LAMP_RGB])
            else:
                alb = mesh.albedo[glow[sel]].mean(0)
                rows.append([*c.mean(0), 2.0 if red[sel][0] else 20.0, *(alb / max(float(alb.max()), 1e-6))])
    return np.asarray(rows, np.float64).reshape(-1, 7)


def camera_emitters(all_emitters: np.ndarray, position: np.ndarray, forward: np.ndarray, reach_m: float = 100.0,
                    at_most: int = 32) -> np.ndarray:
    """The emitters a camera at ``position`` looking along ``forward`` may see reflected: between
    ``OWN_LAMPS_M`` (its own vehicle's lamps are not in its image) and ``reach_m`` away, not behind it
    (the mirror image of a lamp lies beyond the reflecting point); the nearest ``at_most``, nearest first."""
    if not len(all_emitters):
        return all_emitters
    rel = all_emitters[:, :3] - position
    d = np.linalg.norm(rel, axis=1)
    keep = (d > OWN_LAMPS_M) & (d < reach_m) & (rel[:, :2] @ forward[:2] > -0.2 * d)
    order = np.nonzero(keep)[0]
    order = order[np.argsort(d[order], kind="stable")][:at_most]
    return np.ascontiguousarray(all_emitters[order])


#: [m] lamps this close to a camera are its own vehicle's (not reflected in its image)
OWN_LAMPS_M = 3.5
#: [px] lamp reflections are looked for on a grid of this pitch (:func:`lamp_spans`)
LAMP_PROBE_PX = 4


# --------------------------------------------------------------------------------- kernels


@njit(cache=True, nogil=True, error_model="numpy", fastmath=SAFE_FASTMATH, inline="always")
def _hash01(ix, iy, salt):
    """Deterministic hash of two integers and a salt to [0, 1)."""
    h = (ix * 374761393 + iy * 668265263 + salt * 1442695041) & 0xFFFFFFFF
    h = ((h ^ (h >> 13)) * 1274126177) & 0xFFFFFFFF
    h = h ^ (h >> 16)
    return h / 4294967296.0


#: lattice values of the value noise: a fixed seeded table, tiled every _LATTICE cells (each octave and
#: material reads it at its own offset, so the tiling does not show)
_LATTICE = 256
_LATTICE_VALUES = np.random.default_rng(0x5EED).random((_LATTICE, _LATTICE))


@njit(cache=True, nogil=True, error_model="numpy", fastmath=SAFE_FASTMATH, inline="always")
def _noise(x, y, salt):
    """Value noise in [0, 1] (mean 0.5) on a unit lattice, smoothly interpolated."""
    fx, fy = math.floor(x), math.floor(y)
    ix = (np.int64(fx) + salt * 97) & (_LATTICE - 1)
    iy = (np.int64(fy) + salt * 57) & (_LATTICE - 1)
    ix1, iy1 = (ix + 1) & (_LATTICE - 1), (iy + 1) & (_LATTICE - 1)
    tx, ty = x - fx, y - fy
    tx = tx * tx * (3.0 - 2.0 * tx)
    ty = ty * ty * (3.0 - 2.0 * ty)
    a = _LATTICE_VALUES[iy, ix]
    ab = a + (_LATTICE_VALUES[iy, ix1] - a) * tx
    c = _LATTICE_VALUES[iy1, ix]
    cd = c + (_LATTICE_VALUES[iy1, ix1] - c) * tx
    return ab + (cd - ab) * ty


@njit(cache=True, nogil=True, error_model="numpy", fastmath=SAFE_FASTMATH, inline="always")
def _octave(x, y, inv_cell, fp, salt):
    """Zero-mean noise in [-1, 1] of feature size 1 / ``inv_cell`` [m] at (x, y) [m], faded out as the
    footprint ``fp`` [m] grows from half a cell to 1.5 cells (0 beyond: nothing to alias). (Reciprocals
    of sizes throughout the kernels: a multiplication costs a fraction of a division.)"""
    att = 1.5 - fp * inv_cell
    if att <= 0.0:
        return 0.0
    if att > 1.0:
        att = 1.0
    return att * (2.0 * _noise(x * inv_cell, y * inv_cell, salt) - 1.0)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=SAFE_FASTMATH, inline="always")
def _pulse_integral(x, a, w):
    """Integral over [0, x] of the period-1 pulse train that is 1 on [a, a + w) of each period."""
    fl = math.floor(x)
    r = x - fl - a
    return fl * w + min(max(r, 0.0), w)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=SAFE_FASTMATH, inline="always")
def _pulse(x, fw, inv_fw, a, w):
    """The pulse train of :func:`_pulse_integral` box-filtered over width ``fw`` (periods, 1 / ``inv_fw``)
    about x."""
    if fw < 1e-4:
        r = x - math.floor(x)
        return 1.0 if a <= r < a + w else 0.0
    return (_pulse_integral(x + 0.5 * fw, a, w) - _pulse_integral(x - 0.5 * fw, a, w)) * inv_fw


@njit(cache=True, nogil=True, error_model="numpy", fastmath=SAFE_FASTMATH, inline="always")
def _smooth(e0, e1, x):
    t = min(max((x - e0) * (1.0 / (e1 - e0)), 0.0), 1.0)
    return t * t * (3.0 - 2.0 * t)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=SAFE_FASTMATH, inline="always")
def _detail(m, px, py, pz, nx, ny, fp, inst, artificial):
    """Albedo factor (r, g, b) and emitted radiance (r, g, b) of material ``m`` at map point (px, py,
    pz) with unit normal (nx, ny) (horizontal part) and footprint ``fp`` [m]. (Inlined into the pixel
    loop: a call returning six floats costs ~15 % of a clear-day image.)"""
    fr = fg = fb = 1.0
    er = eg = eb = 0.0
    if m == MAT_ASPHALT:
        v = (1.0 + 0.22 * _octave(px, py, 1.0 / ASPHALT_GRAIN_M, fp, 11)
             + 0.10 * _octave(px, py, 1.0 / ASPHALT_AGGREGATE_M, fp, 12))
        # repaired (darker) patches and lighter worn areas, faded to their mean far away
        n = _noise(px * (1.0 / ASPHALT_PATCH_M), py * (1.0 / ASPHALT_PATCH_M), 13)
        att = min(max(1.5 - fp * (1.0 / ASPHALT_PATCH_M), 0.0), 1.0)
        patch = 0.12 * _smooth(0.62, 0.7, n) - 0.06 * _smooth(0.2, 0.35, 1.0 - n)
        v -= ASPHALT_PATCH_MEAN + att * (patch - ASPHALT_PATCH_MEAN)
        fr = fg = fb = v
    elif m == MAT_MARKING:
        # worn paint shows the asphalt (about 0.2 of the paint's albedo) in blotches
        att = min(max(1.5 - fp * (1.0 / MARKING_WEAR_M), 0.0), 1.0)
        n = _noise(px * (1.0 / MARKING_WEAR_M), py * (1.0 / MARKING_WEAR_M), 21)
        wear = 0.7 * _smooth(0.55, 0.8, n)
        wear = 0.06 + att * (wear - 0.06)
        v = 1.0 - wear * 0.8 + 0.08 * _octave(px, py, 1.0 / ASPHALT_GRAIN_M, fp, 22)
        fr = fg = fb = v
    elif m == MAT_PAVING:
        fw = fp * (1.0 / PAVING_TILE_M)
        inv_fw = PAVING_TILE_M / fp
        a = PAVING_GROOVE_M / PAVING_TILE_M
        tx, ty = px * (1.0 / PAVING_TILE_M), py * (1.0 / PAVING_TILE_M)
        gx = _pulse(tx, fw, inv_fw, 0.0, a)
        gy = _pulse(ty, fw, inv_fw, 0.0, a)
        groove = 1.0 - (1.0 - gx) * (1.0 - gy)
        att = min(max(1.5 - fw, 0.0), 1.0)
        tile = att * 0.12 * (_hash01(np.int64(math.floor(tx)), np.int64(math.floor(ty)), 31) - 0.5)
        v = (1.0 + tile + 0.08 * _octave(px, py, 1.0 / ASPHALT_GRAIN_M, fp, 32)) * (1.0 - 0.45 * groove)
        fr = fg = fb = v
    elif m == MAT_FACADE:
        hn = math.sqrt(nx * nx + ny * ny)
        u = (-ny * px + nx * py) / hn if hn > 1e-6 else px
        fu, fz = fp * (1.0 / WINDOW_SPACING_M), fp * (1.0 / FLOOR_M)
        inv_fp = 1.0 / fp
        uc, zc = u * (1.0 / WINDOW_SPACING_M), pz * (1.0 / FLOOR_M)
        cu = _pulse(uc, fu, WINDOW_SPACING_M * inv_fp, WINDOW_U0_M / WINDOW_SPACING_M, WINDOW_W_M / WINDOW_SPACING_M)
        cz = _pulse(zc, fz, FLOOR_M * inv_fp, WINDOW_Z0_M / FLOOR_M, WINDOW_H_M / FLOOR_M)
        c = cu * cz
        grain = 1.0 + 0.06 * _octave(u, pz, 1.0 / 0.5, fp, 41)
        fr = grain * (1.0 - c) + c * GLASS_RGB[0]
        fg = grain * (1.0 - c) + c * GLASS_RGB[1]
        fb = grain * (1.0 - c) + c * GLASS_RGB[2]
        if artificial > 0.0 and c > 0.0:
            col = np.int64(math.floor(uc))
            flr = np.int64(math.floor(zc))
            lit = 1.0 if _hash01(col, flr, 43 + np.int64(inst)) < LIT_WINDOW_FRACTION else 0.0
            level = lit * (0.5 + _hash01(col, flr, 47 + np.int64(inst)))
            # far away, a pixel covers many windows: the mean share lit
            t = _smooth(0.5, 1.5, max(fu, fz))
            level = level + t * (LIT_WINDOW_FRACTION - level)
            e = artificial * WINDOW_RADIANCE * c * level
            er, eg, eb = e * WINDOW_RGB[0], e * WINDOW_RGB[1], e * WINDOW_RGB[2]
    elif m == MAT_ROOF:
        v = 1.0 + 0.10 * _octave(px, py, 1.0 / 0.08, fp, 51) + 0.08 * _octave(px, py, 1.0 / 1.2, fp, 52)
        fr = fg = fb = v
    elif m == MAT_FOLIAGE:
        b = (0.25 * _octave(px + pz, py - pz, 1.0 / FOLIAGE_CLUMP_M, fp, 61)
             + 0.12 * _octave(px, py + pz, 1.0 / 1.5, fp, 62))
        hue = 0.15 * _octave(px - pz, py, 1.0 / 1.0, fp, 63)
        fr, fg, fb = (1.0 + b) * (1.0 + hue), 1.0 + b, (1.0 + b) * (1.0 - hue)
    elif m == MAT_GRASS:
        b = 0.14 * _octave(px, py, 1.0 / GRASS_BLADE_M, fp, 71) + 0.12 * _octave(px, py, 1.0 / GRASS_PATCH_M, fp, 72)
        att = min(max(1.5 - fp * (1.0 / 6.0), 0.0), 1.0)
        soil = _smooth(0.68, 0.8, _noise(px * (1.0 / 6.0), py * (1.0 / 6.0), 73))
        soil = 0.08 + att * (soil - 0.08)
        # bare soil: browner (relative to the grass albedo)
        fr = (1.0 + b) * (1.0 + 0.5 * soil)
        fg = (1.0 + b) * (1.0 - 0.15 * soil)
        fb = (1.0 + b) * (1.0 + 0.2 * soil)
    return fr, fg, fb, er, eg, eb


@njit(cache=True, nogil=True, error_model="numpy", fastmath=SAFE_FASTMATH, inline="always")
def _pow_int(x, n):
    """x ** n for an integer n >= 1 by repeated squaring (exp(n log x) costs several times more)."""
    out = 1.0
    while n > 0:
        if n & 1:
            out *= x
        x *= x
        n >>= 1
    return out


@njit(cache=True, nogil=True, error_model="numpy", fastmath=SAFE_FASTMATH, inline="always")
def _view_ray(x, y, r00, r01, r02, r10, r11, r12, r20, r21, r22):
    """Map direction (dx, dy, dz) of the optical-frame ray (x, y, 1) (rotation rows r0*, r1*, r2*) and the
    reciprocal of its length."""
    dx = r00 * x + r01 * y + r02
    dy = r10 * x + r11 * y + r12
    dz = r20 * x + r21 * y + r22
    return dx, dy, dz, 1.0 / math.sqrt(x * x + y * y + 1.0)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=SAFE_FASTMATH, inline="always")
def _lobe(nx, ny, nz, vx, vy, vz, lx, ly, lz, cos_cut2):
    """Specular reflection of a unit irradiance from unit direction (lx, ly, lz) towards the unit view
    direction (vx, vy, vz) on a water film with unit normal (nx, ny, nz): normalised Blinn-Phong
    (``WET_SHININESS``) x Schlick Fresnel x n.l, 0 where n.h is below ``sqrt(cos_cut2)``. With the half
    vector h = l + v, the cut is tested squared (no root) and v.h / |h| = |h| / 2 (v, l unit): one
    division and one root, side by side."""
    ndl = nx * lx + ny * ly + nz * lz
    if ndl <= 0.0:
        return 0.0
    hx, hy, hz = lx + vx, ly + vy, lz + vz
    hn2 = hx * hx + hy * hy + hz * hz
    nh = nx * hx + ny * hy + nz * hz
    if nh <= 0.0 or nh * nh < cos_cut2 * hn2 or hn2 < 1e-18:
        return 0.0
    ndh2 = nh * nh / hn2
    vdh = min(0.5 * math.sqrt(hn2), 1.0)
    fres = WET_F0 + (1.0 - WET_F0) * _pow_int(1.0 - vdh, 5)
    return fres * ((WET_SHININESS + 8.0) / 8.0) * _pow_int(ndh2, _SHININESS // 2) * ndl


@njit(cache=True, nogil=True, error_model="numpy", fastmath=SAFE_FASTMATH)
def lamp_spans(g, depth, xg, yg, rot, origin, miss, material, normal, wet_film, lamps, artificial, stride):
    """Column span (E, H, 2) int32 (first, last, inclusive; empty when first > last) of each image row
    where each lamp's specular lobe on a wet surface may reach (above ``_LOBE_CUT`` of its peak and
    above ``_LOBE_FLOOR`` absolute): probed every ``stride`` pixels, each probe inside the lobe covering
    the pixels up to a pitch away (the lobe is smooth over a few pixels). Per row rather than one
    rectangle per lamp: a reflection's streak runs slanted across the image."""
    h, w = g.shape
    n = lamps.shape[0]
    out = np.empty((n, h, 2), np.int32)
    out[:, :, 0] = w
    out[:, :, 1] = -1
    cos_cut = math.exp(math.log(_LOBE_CUT) / WET_SHININESS)
    cos_cut2 = cos_cut * cos_cut
    lobe_norm = (WET_SHININESS + 8.0) / 8.0
    r00, r01, r02 = rot[0, 0], rot[0, 1], rot[0, 2]
    r10, r11, r12 = rot[1, 0], rot[1, 1], rot[1, 2]
    r20, r21, r22 = rot[2, 0], rot[2, 1], rot[2, 2]
    o0, o1, o2 = origin[0], origin[1], origin[2]
    for i in range(stride // 2, h, stride):
        for j in range(stride // 2, w, stride):
            gi = g[i, j]
            d = depth[i, j]
            if gi >= miss or not d < np.inf or normal[gi, 2] <= 0.7 or wet_film[material[gi]] <= 0.0:
                continue
            dx, dy, dz, inv_ray = _view_ray(xg[i, j], yg[i, j], r00, r01, r02, r10, r11, r12, r20, r21, r22)
            px, py, pz = o0 + d * dx, o1 + d * dy, o2 + d * dz
            vx, vy, vz = -dx * inv_ray, -dy * inv_ray, -dz * inv_ray
            nx, ny, nz = normal[gi, 0], normal[gi, 1], normal[gi, 2]
            for q in range(n):
                lx, ly, lz = lamps[q, 0] - px, lamps[q, 1] - py, lamps[q, 2] - pz
                d2 = lx * lx + ly * ly + lz * lz + 1e-12
                inv = 1.0 / math.sqrt(d2)
                hx, hy, hz = lx * inv + vx, ly * inv + vy, lz * inv + vz
                hn2 = hx * hx + hy * hy + hz * hz
                nh = nx * hx + ny * hy + nz * hz
                if nh <= 0.0 or nh * nh < cos_cut2 * hn2:
                    continue
                # the lobe's bound (Fresnel, film and n.l at most 1): a far or weak lamp's faint tail is left out
                peak = lobe_norm * lamps[q, 3] * artificial * inv * inv
                if peak * _pow_int(nh * nh / hn2, _SHININESS // 2) >= _LOBE_FLOOR:
                    for ii in range(max(i - stride, 0), min(i + stride + 1, h)):
                        out[q, ii, 0] = min(out[q, ii, 0], j - stride)
                        out[q, ii, 1] = max(out[q, ii, 1], j + stride)
    return out


@njit(cache=True, nogil=True, error_model="numpy", fastmath=SAFE_FASTMATH)
def shade_linear(g, depth, lit, xg, yg, rot, origin, linear, albedo_lamp, rows, miss, sky_levels, material, normal,
                 instance, detail, fx_px, wet, wet_albedo, wet_film, sun_dir, sun_rgb, sky_zenith, sky_horizon,
                 light, light_x0, light_y0, light_res, artificial, beta, fog_rgb, dim, lamps, spans, streaks, out,
                 scale, vignette, noise, oy, ox, std_lut, gamma, out8):
    """Linear colour ``out`` (H, W, 3) float32 of every pixel (see the module docstring), or with
    ``out8`` (H, W, 3) uint8 (not empty) its sRGB codes through the camera model
    (:func:`sensor_codes_kernel`'s arguments ``scale`` .. ``gamma``) instead.

    ``g`` (H, W) int32: global triangle index, ``miss`` for the sky, whose colour is row
    ``miss + 1 + level`` of ``linear`` with ``level`` the ray's elevation sine x (``sky_levels`` - 1);
    ``lit`` (H, W) bool, or (0, 0) when the sun reaches everything; ``xg``, ``yg`` (H, W) optical-frame
    ray x, y at z = 1; ``rot`` (3, 3), ``origin`` (3,) the camera pose; ``linear``, ``albedo_lamp``
    (2 rows, 3) the shading tables (sun, then shadow); ``material``, ``normal``, ``instance`` per
    global index; ``light`` (ny, nx) the light map or (0, 0); ``lamps`` (E, 7) point lights and
    ``spans`` (E, H, 2) where each may be reflected (:func:`lamp_spans`); ``streaks`` (H, W) float32 the
    light a rain streak adds where it covers the pixel (which keeps 0.7 of its own; negative: no
    streak), or (0, 0)."""
    h, w = g.shape
    has_lit = lit.shape[0] > 0
    has_out8 = out8.shape[0] > 0
    has_vig = vignette.shape[0] > 0
    has_noise = noise.shape[0] > 0
    has_streaks = streaks.shape[0] > 0
    top = sky_levels - 1
    has_light = light.shape[0] > 0 and artificial > 0.0
    ny, nx = light.shape
    n_lamps = lamps.shape[0] if artificial > 0.0 else 0
    inv_res = 1.0 / light_res
    cos_cut = math.exp(math.log(_LOBE_CUT) / WET_SHININESS)
    cos_cut2 = cos_cut * cos_cut
    # the pose and colours as scalars: loads from arrays in the pixel loop are not hoisted (the output
    # might alias them as far as the compiler knows)
    r00, r01, r02 = rot[0, 0], rot[0, 1], rot[0, 2]
    r10, r11, r12 = rot[1, 0], rot[1, 1], rot[1, 2]
    r20, r21, r22 = rot[2, 0], rot[2, 1], rot[2, 2]
    o0, o1, o2 = origin[0], origin[1], origin[2]
    fog_r, fog_g, fog_b = fog_rgb[0], fog_rgb[1], fog_rgb[2]
    hor_r, hor_g, hor_b = sky_horizon[0], sky_horizon[1], sky_horizon[2]
    zen_r, zen_g, zen_b = sky_zenith[0], sky_zenith[1], sky_zenith[2]
    sun_x, sun_y, sun_z = sun_dir[0], sun_dir[1], sun_dir[2]
    sun_r, sun_g, sun_b = sun_rgb[0], sun_rgb[1], sun_rgb[2]
    # per row, the lamps' reflections summed over their spans (a pass of their own: checking each
    # lamp's span at each pixel cost as much as evaluating the lobes)
    acc_r = np.zeros(w, np.float64)
    acc_g = np.zeros(w, np.float64)
    acc_b = np.zeros(w, np.float64)
    # the lamp-independent part of each pixel of a row's spans, computed once per pixel rather than per lamp:
    # whether it can reflect (wet film facing up, seen from its front), its map point, view direction,
    # normal and film
    can = np.zeros(w, np.bool_)
    pt = np.empty((w, 3), np.float64)
    view = np.empty((w, 3), np.float64)
    nrm = np.empty((w, 3), np.float64)
    films = np.empty(w, np.float64)
    for i in range(h):
        u_lo, u_hi = w, -1
        for q in range(n_lamps):
            j0, j1 = max(spans[q, i, 0], 0), min(spans[q, i, 1], w - 1)
            if j0 <= j1:
                u_lo, u_hi = min(u_lo, j0), max(u_hi, j1)
        for j in range(u_lo, u_hi + 1):
            can[j] = False
            gi = g[i, j]
            d = depth[i, j]
            if gi == miss or not d < np.inf or not wet:
                continue
            nxx, nyy, nzz = normal[gi, 0], normal[gi, 1], normal[gi, 2]
            film = wet_film[material[gi]]
            if nzz <= 0.7 or film <= 0.0:
                continue
            dx, dy, dz, inv_ray = _view_ray(xg[i, j], yg[i, j], r00, r01, r02, r10, r11, r12, r20, r21, r22)
            vx, vy, vz = -dx * inv_ray, -dy * inv_ray, -dz * inv_ray
            if nxx * vx + nyy * vy + nzz * vz <= 0.0:
                continue
            can[j] = True
            pt[j, 0], pt[j, 1], pt[j, 2] = o0 + d * dx, o1 + d * dy, o2 + d * dz
            view[j, 0], view[j, 1], view[j, 2] = vx, vy, vz
            nrm[j, 0], nrm[j, 1], nrm[j, 2] = nxx, nyy, nzz
            films[j] = film
        j_lo, j_hi = w, -1
        for q in range(n_lamps):
            j0, j1 = max(spans[q, i, 0], 0), min(spans[q, i, 1], w - 1)
            if j0 > j1:
                continue
            if j_hi < j_lo:
                j_lo, j_hi = j0, j1
                acc_r[j0:j1 + 1] = 0.0
                acc_g[j0:j1 + 1] = 0.0
                acc_b[j0:j1 + 1] = 0.0
            else:
                for j in range(j0, j_lo):
                    acc_r[j] = acc_g[j] = acc_b[j] = 0.0
                for j in range(j_hi + 1, j1 + 1):
                    acc_r[j] = acc_g[j] = acc_b[j] = 0.0
                j_lo, j_hi = min(j_lo, j0), max(j_hi, j1)
            lamp_x, lamp_y, lamp_z = lamps[q, 0], lamps[q, 1], lamps[q, 2]
            power = lamps[q, 3] * artificial
            cr, cg, cb = lamps[q, 4], lamps[q, 5], lamps[q, 6]
            for j in range(j0, j1 + 1):
                if not can[j]:
                    continue
                lx, ly, lz = lamp_x - pt[j, 0], lamp_y - pt[j, 1], lamp_z - pt[j, 2]
                d2 = lx * lx + ly * ly + lz * lz
                if d2 < 0.25:
                    continue
                inv = 1.0 / math.sqrt(d2)
                s = films[j] * power * (inv * inv) * _lobe(nrm[j, 0], nrm[j, 1], nrm[j, 2], view[j, 0], view[j, 1],
                                                           view[j, 2], lx * inv, ly * inv, lz * inv, cos_cut2)
                acc_r[j] += s * cr
                acc_g[j] += s * cg
                acc_b[j] += s * cb
        for j in range(w):
            gi = g[i, j]
            x, y = xg[i, j], yg[i, j]
            dz = r20 * x + r21 * y + r22
            ray = math.sqrt(x * x + y * y + 1.0)
            inv_ray = 1.0 / ray
            row = gi
            if gi == miss:
                row = miss + 1 + int(min(max(dz * inv_ray * top + 0.5, 0.0), top))
            shadow = False
            if has_lit and not lit[i, j]:
                row += rows
                shadow = True
            r = linear[row, 0]
            gr = linear[row, 1]
            b = linear[row, 2]
            d = depth[i, j]
            if gi == miss or not d < np.inf:  # sky: all fog where there is fog
                if beta > 0.0:
                    r, gr, b = fog_r, fog_g, fog_b
            else:
                dx = r00 * x + r01 * y + r02
                dy = r10 * x + r11 * y + r12
                px, py, pz = o0 + d * dx, o1 + d * dy, o2 + d * dz
                dist = d * ray
                vx, vy, vz = -dx * inv_ray, -dy * inv_ray, -dz * inv_ray  # towards the camera
                m = material[gi]
                nxx, nyy, nzz = normal[gi, 0], normal[gi, 1], normal[gi, 2]
                cos_v = nxx * vx + nyy * vy + nzz * vz
                fr = fg = fb = 1.0
                er = eg = eb = 0.0
                if detail and m != MAT_PLAIN:
                    fp = dist / (fx_px * max(abs(cos_v), 0.05))
                    fr, fg, fb, er, eg, eb = _detail(m, px, py, pz, nxx, nyy, fp, instance[gi], artificial)
                film = 0.0
                if wet and nzz > 0.7:
                    wa = wet_albedo[m]
                    fr, fg, fb = fr * wa, fg * wa, fb * wa
                    film = wet_film[m]
                if has_light:
                    # light-map column and row of the point, in cells from the first cell's centre
                    cx = min(max((px - light_x0) * inv_res - 0.5, 0.0), nx - 1.001)
                    cy = min(max((py - light_y0) * inv_res - 0.5, 0.0), ny - 1.001)
                    c0, r0 = int(cx), int(cy)
                    tx, ty = cx - c0, cy - r0
                    e0 = light[r0, c0] + tx * (light[r0, c0 + 1] - light[r0, c0])
                    e1 = light[r0 + 1, c0] + tx * (light[r0 + 1, c0 + 1] - light[r0 + 1, c0])
                    e = e0 + ty * (e1 - e0)
                    fz = min(max(pz * 0.125, 0.0), 1.0)
                    e *= artificial * (1.0 - fz * fz * (3.0 - 2.0 * fz))  # pools fade over the lowest 8 m
                    r += albedo_lamp[row, 0] * e
                    gr += albedo_lamp[row, 1] * e
                    b += albedo_lamp[row, 2] * e
                r, gr, b = r * fr + er, gr * fg + eg, b * fb + eb
                if film > 0.0 and cos_v > 0.0:
                    # the sky in the mirror direction (elevation = cos_v over a level surface)
                    fres = WET_F0 + (1.0 - WET_F0) * _pow_int(1.0 - cos_v, 5)
                    k = math.sqrt(min(cos_v, 1.0))
                    s = film * fres
                    r += s * (hor_r * (1.0 - k) + zen_r * k)
                    gr += s * (hor_g * (1.0 - k) + zen_g * k)
                    b += s * (hor_b * (1.0 - k) + zen_b * k)
                    if j_lo <= j <= j_hi:
                        r += acc_r[j]
                        gr += acc_g[j]
                        b += acc_b[j]
                    if not shadow:
                        s = film * _lobe(nxx, nyy, nzz, vx, vy, vz, sun_x, sun_y, sun_z, cos_cut2)
                        r += s * sun_r
                        gr += s * sun_g
                        b += s * sun_b
                if beta > 0.0:
                    t = math.exp(-beta * dist)
                    r = fog_r + t * (r - fog_r)
                    gr = fog_g + t * (gr - fog_g)
                    b = fog_b + t * (b - fog_b)
            # (no helper function taking arrays here: numba would count references to them per pixel)
            r, gr, b = r * dim, gr * dim, b * dim
            if has_streaks:
                add = streaks[i, j]
                if add >= 0.0:
                    # a drop: nearer drops are brighter (they cover more of the pixel)
                    r, gr, b = r * 0.7 + add, gr * 0.7 + add, b * 0.7 + add
            if not has_out8:
                out[i, j, 0] = r
                out[i, j, 1] = gr
                out[i, j, 2] = b
            else:
                f = scale * vignette[i, j] if has_vig else scale
                for c in range(3):
                    v = (r if c == 0 else gr if c == 1 else b) * f
                    v = min(max(v, 0.0), 4095.0)
                    if has_noise:
                        v += std_lut[int(v)] * noise[oy + i, ox + j, c]
                        v = min(max(v, 0.0), 4095.0)
                    out8[i, j, c] = gamma[int(v)]


@njit(cache=True, nogil=True, error_model="numpy", fastmath=SAFE_FASTMATH)
def sensor_codes_kernel(rgb, scale, vignette, noise, oy, ox, std_lut, gamma, out):
    """The camera model in place on linear ``rgb`` (H, W, 3) float32: times ``scale`` (exposure x full
    scale) and ``vignette`` (H, W) (or (0, 0): none), clipped to [0, 4095], plus with ``noise`` (a
    standard normal field, or (0, 0, 3): none) cut at (``oy``, ``ox``) times ``std_lut[code]``, clipped
    again; with ``gamma`` (4096,) uint8 the sRGB codes go to ``out`` (H, W, 3) uint8."""
    h, w, _ = rgb.shape
    has_vig = vignette.shape[0] > 0
    has_noise = noise.shape[0] > 0
    has_out = out.shape[0] > 0
    for i in range(h):
        for j in range(w):
            f = scale * vignette[i, j] if has_vig else scale
            for c in range(3):
                v = rgb[i, j, c] * f
                v = min(max(v, 0.0), 4095.0)
                if has_noise:
                    v += std_lut[int(v)] * noise[oy + i, ox + j, c]
                    v = min(max(v, 0.0), 4095.0)
                rgb[i, j, c] = v
                if has_out:
                    out[i, j, c] = gamma[int(v)]
