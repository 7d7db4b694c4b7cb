"""Procedural low-poly vehicles: hulls lofted from side and plan profiles, per body style.

A hull (:func:`_hull`) is a loft of convex cross-sections along the vehicle's x axis. At each station
the side profile gives the roof line (hood, windscreen, roof, rear screen, boot or hatch), the sill
(ground clearance, lifted over the wheel arches and at the overhangs) and the belt line; the plan
profile gives the half width (tapered at the nose and tail) and the tumblehome of the glasshouse.
Side windows, windscreen and rear screen are the hull's quads above the belt line (steep ones on the
roof line are screens), with pillars left in paint. Wheels (tyre and rim), bumpers, mirrors, lamps
and licence plates are closed parts added on top. Trucks, buses and two-wheelers reuse the hull for
their cabs and bodies and add load boxes, tanks, frames and a posed rider
(:mod:`cosim.sensors.assets.people`).

Every model (:data:`MODELS`) is a style plus continuous parameters drawn from the catalogue seed;
its dimensions are those of its tight box, rounded to centimetres, and the SUMO vTypes take them
(:mod:`cosim.world.vtypes`), so traffic and sensors agree.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field
from functools import cache

import numpy as np

from .people import Person, build_body, seated_pose, skeleton
from .shapes import Builder, box, cylinder, ellipsoid, frustum, loft, smoothstep

# material part ids (cosim.sensors.meshes)
BODY, GLASS, TYRE, LAMP_F, LAMP_R, DARK, RIM, PLATE, TRIM, CARGO = range(10)


@dataclass(frozen=True)
class Axle:
    x: float  # [m] from the hull's rear end
    radius: float
    dual: bool = False


def _interp(knots, x):
    k = np.asarray(knots, np.float64)
    return np.interp(x, k[:, 0], k[:, 1])


def _hull(b: Builder, length: float, width: float, height: float, roof: list, belt: float, clearance: float,
          axles: list[Axle], x0: float = 0.0, taper=(0.08, 0.05), tumble: float = 0.78, pillar_every: int = 0,
          glass_top: float = 0.0, slope_glass: float = 0.5, caps=(BODY, BODY), z0: float = 0.0,
          n_stations: int = 26, glass: bool = True) -> dict:
    """Loft a hull from ``x0`` (rear) to ``x0 + length``; ``roof`` knots (fraction of length from the rear,
    height [m]); ``belt`` [m]; ``taper`` the plan taper (front, rear) as fractions of the half width."""
    hw = width / 2
    xs = set(np.linspace(0.0, 1.0, n_stations).round(4))
    xs |= {float(k[0]) for k in roof}
    for a in axles:
        ra = a.radius + 0.05
        for ang in np.linspace(-1, 1, 9):
            xs.add(round((a.x + ra * math.sin(ang * 1.35)) / length, 4))
    f = np.array(sorted(x for x in xs if 0.0 <= x <= 1.0))
    x = f * length
    zt = _interp(roof, f) + z0
    # sill: clearance, lifted towards the overhang ends and over the arches
    end = np.minimum(f, 1 - f) * length
    zb = z0 + clearance + (0.22 * (belt - clearance)) * (1 - smoothstep(end / 0.3))
    for a in axles:
        ra = a.radius + 0.05
        dx = x - a.x
        inside = np.abs(dx) < ra
        arch = z0 + a.radius + np.sqrt(np.maximum(ra * ra - dx * dx, 0.0))
        zb = np.where(inside, np.maximum(zb, arch), zb)
    zbelt = np.minimum(belt + z0, zt - 0.04)
    zb = np.minimum(zb, zbelt - 0.06)
    w = hw * (1 - taper[0] * (1 - smoothstep((1 - f) * length / 0.5)) - taper[1] * (1 - smoothstep(f * length / 0.4)))
    rise = smoothstep((zt - zbelt) / 0.2)
    tw = w * (0.94 - (0.94 - tumble) * rise)
    lower = zb + 0.25 * (zbelt - zb)
    ws = 0.97 * w
    sec = np.stack([
        np.stack([x, ws, zb], 1), np.stack([x, w, lower], 1), np.stack([x, w, zbelt], 1), np.stack([x, tw, zt], 1),
        np.stack([x, -tw, zt], 1), np.stack([x, -w, zbelt], 1), np.stack([x, -w, lower], 1),
        np.stack([x, -ws, zb], 1)], 1) + np.array([x0, 0.0, 0.0])
    parts = np.full((len(x) - 1, 8), BODY, np.int64)
    parts[:, 7] = DARK  # underside
    if glass:
        gh = (zt - zbelt) > 0.16 + glass_top
        house = gh[:-1] & gh[1:]
        idx = np.nonzero(house)[0]
        side = house.copy()
        if len(idx):
            side[idx[0]] = side[idx[-1]] = False  # A and C pillars
            if pillar_every:
                side[idx[::pillar_every]] = False
            else:
                mid = idx[len(idx) // 2]
                side[mid] = False  # B pillar
        parts[side, 2] = GLASS
        parts[side, 4] = GLASS
        slope = np.abs(np.diff(zt)) / np.maximum(np.diff(x), 1e-6)
        screen = (slope > slope_glass) & ((zt[:-1] - zbelt[:-1]) > 0.05) & ((zt[1:] - zbelt[1:]) > 0.05)
        parts[screen, 3] = GLASS
    loft(b, sec, parts, caps)
    return {"x": x + x0, "zt": zt, "zb": zb, "belt": zbelt, "w": w, "f": f}


def _wheels(b: Builder, axles: list[Axle], half_track: float, tyre_w: float, x0: float = 0.0, n: int = 14) -> None:
    for a in axles:
        for side in (-1, 1):
            reps = (0.0, -tyre_w * 1.05) if a.dual else (0.0,)
            for k, off in enumerate(reps):
                yc = side * (half_track - tyre_w / 2 + off)
                cylinder(b, (x0 + a.x, yc, a.radius), a.radius, tyre_w / 2, "y", TYRE, n)
                if k == 0:
                    cylinder(b, (x0 + a.x, yc + side * tyre_w * 0.05, a.radius), a.radius * 0.62, tyre_w / 2, "y",
                             RIM, n)


def _liners(b: Builder, axles: list[Axle], half_track: float, tyre_w: float, clearance: float, x0: float = 0.0
            ) -> None:
    """The wheel wells' inner liners: dark boxes between a pair of wheels, up into the arch."""
    for a in axles:
        y = half_track - tyre_w - 0.02
        box(b, (x0 + a.x - a.radius, -y, clearance), (x0 + a.x + a.radius, y, 2 * a.radius + 0.06), DARK)


def _ends(b: Builder, hull: dict, x_front: float, x_rear: float, lamp_h: float, plate: bool = True,
          bumper_h: float = 0.22, bumper_d: float = 0.06, lamp_in: float = 0.55) -> None:
    """Bumpers, plates and lamps at both ends of a hull whose end sections are ``hull``'s first and last."""
    for end, xe, sgn in (("front", x_front, 1), ("rear", x_rear, -1)):
        k = -1 if end == "front" else 0
        w, zb, zt = hull["w"][k], hull["zb"][k], hull["zt"][k]
        # bumper: from the hull's end face out by bumper_d
        bz0 = zb - 0.02
        xa, xb = sorted((xe, xe + sgn * bumper_d))
        box(b, (xa, -0.93 * w, bz0), (xb, 0.93 * w, bz0 + bumper_h), TRIM)
        if plate:
            pz = bz0 + 0.3 * bumper_h
            pa, pb = sorted((xe + sgn * bumper_d, xe + sgn * (bumper_d + 0.012)))
            box(b, (pa, -0.26, pz), (pb, 0.26, pz + 0.11), PLATE)
        lz1 = min(zt - 0.04, bz0 + bumper_h + lamp_h + 0.25)
        lz0 = max(bz0 + bumper_h + 0.02, lz1 - lamp_h)
        la, lb = sorted((xe - sgn * 0.01, xe + sgn * 0.025))
        for side in (-1, 1):
            y0, y1 = sorted((side * lamp_in * w, side * 0.9 * w))
            box(b, (la, y0, lz0), (lb, y1, lz1), LAMP_F if end == "front" else LAMP_R)


def _mirrors(b: Builder, x: float, y: float, z: float, size: float = 0.16) -> None:
    for side in (-1, 1):
        y0, y1 = sorted((side * (y - 0.02), side * (y + size)))
        box(b, (x - 0.08, y0, z), (x + 0.02, y1, z + 0.11), BODY)


# ------------------------------------------------------------------------------ styles


def _car(b: Builder, s: str, p: dict) -> None:
    L, W, H, R = p["L"], p["W"], p["H"], p["R"]
    c = p["clear"]
    hood = p["hood"] * H
    belt = p["belt"] * H
    wf, wr = p["wb_front"], p["wb_rear"]
    ws_len, rs = p["screen"], p["rear"]
    # roof-line knots: fraction of the hull length from the rear -> height [m]
    if s == "hatchback":
        roof = [(0, belt + 0.06), (0.02, 0.8 * H), (0.11 + 0.04 * rs, 0.97 * H), (0.17, H), (0.58, H),
                (0.55 + ws_len, hood + 0.04), (0.97, hood - 0.04), (1.0, hood - 0.15)]
    elif s == "saloon":
        roof = [(0, hood + 0.02), (0.02, hood + 0.08), (0.15 + 0.03 * rs, hood + 0.1), (0.27, 0.99 * H),
                (0.30, H), (0.60, H), (0.58 + ws_len, hood + 0.04), (0.97, hood - 0.04), (1.0, hood - 0.15)]
    elif s == "estate":
        roof = [(0, belt + 0.04), (0.015, 0.85 * H), (0.04, 0.98 * H), (0.07, H), (0.58, H),
                (0.58 + ws_len, hood + 0.04), (0.97, hood - 0.03), (1.0, hood - 0.14)]
    elif s == "suv":
        roof = [(0, belt + 0.1), (0.015, 0.9 * H), (0.04, 0.99 * H), (0.06, H), (0.63, H),
                (0.63 + 0.7 * ws_len, hood + 0.03), (0.97, hood), (1.0, hood - 0.12)]
    elif s == "pickup":
        bed = 0.40 + 0.04 * rs
        roof = [(0, belt + 0.12), (bed, belt + 0.14), (bed + 0.005, 0.96 * H), (bed + 0.02, H), (0.66, H),
                (0.66 + 0.6 * ws_len, hood + 0.03), (0.97, hood), (1.0, hood - 0.12)]
    elif s == "coupe":
        roof = [(0, hood + 0.08), (0.03, hood + 0.14), (0.16 + 0.04 * rs, 0.92 * H), (0.32, H), (0.57, H),
                (0.57 + ws_len, hood + 0.03), (0.97, hood - 0.05), (1.0, hood - 0.16)]
    else:  # microcar: a bubble with a front door
        roof = [(0, belt + 0.1), (0.04, 0.86 * H), (0.14, 0.98 * H), (0.3, H), (0.62, H), (0.86, 0.78 * H),
                (0.96, hood), (1.0, hood - 0.1)]
    bd = 0.06  # bumper depth: the hull stops short of the box ends
    Lh = L - 2 * bd - 0.012 * 2
    x0 = -Lh / 2
    axles = [Axle(wr * Lh, R), Axle((1 - wf) * Lh, R)]
    hull = _hull(b, Lh, W, H, roof, belt, c, axles, x0=x0, taper=(0.08, 0.05), tumble=p["tumble"])
    _wheels(b, [Axle(a.x + x0, a.radius) for a in axles], 0.5 * W - 0.03, 0.18 + 0.04 * R)
    _liners(b, axles, 0.5 * W - 0.03, 0.18 + 0.04 * R, c, x0)
    _ends(b, hull, Lh / 2, -Lh / 2, 0.10, bumper_d=bd, bumper_h=min(0.24, 0.5 * (belt - c)))
    # mirrors at the windscreen's foot
    xa = x0 + (roof[-3][0] if s != "micro" else 0.8) * Lh
    _mirrors(b, min(xa, Lh / 2 - 0.3), 0.5 * W * 0.97, belt + 0.04, 0.12)


def _van(b: Builder, s: str, p: dict) -> None:
    L, W, H, R = p["L"], p["W"], p["H"], p["R"]
    hood = p["hood"] * H
    belt = p["belt"] * H
    roof = [(0, 0.96 * H), (0.01, H), (0.76, H), (0.86, 0.62 * H + 0.2), (0.97, hood), (1.0, hood - 0.12)]
    bd = 0.06
    Lh = L - 2 * bd - 0.024
    x0 = -Lh / 2
    axles = [Axle(0.17 * Lh, R, dual=p["L"] > 5.6), Axle(0.83 * Lh, R)]
    b2 = Builder()
    hull = _hull(b2, Lh, W, H, roof, belt, p["clear"], axles, x0=x0, taper=(0.06, 0.02), tumble=0.9,
                 pillar_every=3 if s == "minibus" else 0, n_stations=30)
    _merge(b, b2, panel_from=x0 + 0.62 * Lh if s == "panel_van" else None)
    _wheels(b, [Axle(a.x + x0, a.radius, a.dual) for a in axles], 0.5 * W - 0.03, 0.21)
    _liners(b, axles, 0.5 * W - 0.03, 0.21 * (2.05 if p["L"] > 5.6 else 1), p["clear"], x0)
    _ends(b, hull, Lh / 2, -Lh / 2, 0.12, bumper_d=bd)
    _mirrors(b, x0 + 0.85 * Lh, 0.5 * W, belt + 0.05, 0.15)


def _merge(b: Builder, other: Builder, panel_from: float | None = None) -> None:
    """Copy ``other``'s parts into ``b``; with ``panel_from``, glass behind x = panel_from becomes paint
    (a panel van's load area)."""
    for v, t, part, g in zip(other.verts, other.tris, other.parts, other.groups, strict=True):
        t = t - (t.min() if len(t) else 0)
        part = part.copy()
        if panel_from is not None:
            cx = v[t].mean(axis=1)[:, 0]
            part[(part == GLASS) & (cx < panel_from) & (np.abs(v[t][:, :, 1].mean(1)) > 0.3)] = BODY
        b.add(v, t, part, g - g.min())


def _cab(b: Builder, x0: float, Lc: float, W: float, H: float, R: float, clear: float) -> dict:
    """A cab-over truck cab from ``x0`` (its rear) forward."""
    roof = [(0, H), (0.82, H), (0.90, 0.72 * H), (0.97, 0.48 * H), (1.0, 0.44 * H)]
    return _hull(b, Lc, W, H, roof, 0.48 * H, clear, [], x0=x0, taper=(0.05, 0.0), tumble=0.92, glass_top=-0.05,
                 slope_glass=0.9, n_stations=10)


def _truck(b: Builder, s: str, p: dict) -> None:
    L, W, H, R = p["L"], p["W"], p["H"], p["R"]
    Hc = p["Hc"]
    Lc = 2.2
    bd = 0.06
    xf = L / 2 - bd - 0.012
    xr = -L / 2 + bd + 0.012
    cab = _cab(b, xf - Lc, Lc, W, Hc, R, 0.55)
    chassis_z = R * 1.6
    box(b, (xr, -0.42 * W, chassis_z - 0.25), (xf - Lc + 0.05, 0.42 * W, chassis_z), DARK)
    axles = [Axle(xf - 0.55 * Lc, R)]
    rear_len = xf - Lc - xr
    if s == "semi":
        gap = 0.5
        tr0, tr1 = xr, xf - Lc - gap
        box(b, (tr0, -W / 2, chassis_z + 0.1), (tr1, W / 2, H), CARGO)
        box(b, (tr1 - 0.6, -0.3 * W, chassis_z), (tr1 + gap + 0.05, 0.3 * W, chassis_z + 0.12), DARK)
        axles += [Axle(xf - Lc - 0.6, R, True), Axle(xr + 0.7, R, True), Axle(xr + 0.7 + 2.2 * R + 0.1, R, True)]
        box(b, (tr0 + 0.3, -0.48 * W, chassis_z + 0.1 - 0.7), (tr0 + 1.8, -0.47 * W + 0.05, chassis_z + 0.1), DARK)
    elif s == "box":
        box(b, (xr, -W / 2, chassis_z + 0.05), (xf - Lc - 0.15, W / 2, H), CARGO)
        axles += [Axle(xr + 0.3 * rear_len, R, True)]
    elif s == "flatbed":
        box(b, (xr, -W / 2, chassis_z), (xf - Lc - 0.1, W / 2, chassis_z + 0.15), DARK)
        for side in (-1, 1):  # side boards
            y0, y1 = sorted((side * W / 2, side * (W / 2 - 0.05)))
            box(b, (xr, y0, chassis_z + 0.15), (xf - Lc - 0.1, y1, chassis_z + 0.6), CARGO)
        box(b, (xr + 0.3, -0.45 * W, chassis_z + 0.15), (xr + 0.3 + 0.45 * rear_len, 0.45 * W, chassis_z + 1.2 + 0.6
                                                          * p["load"]), TRIM)
        axles += [Axle(xr + 0.3 * rear_len, R, True)]
    elif s == "tanker":
        r = min(W / 2, (H - chassis_z) / 2) * 0.98
        cylinder(b, (0.5 * (xr + 0.3 + xf - Lc - 0.2), 0.0, H - r), r, 0.5 * (xf - Lc - 0.2 - xr - 0.3), "x", CARGO, 16)
        ellipsoid(b, (xr + 0.3, 0.0, H - r), (0.3, r, r), CARGO, 5, 16)
        axles += [Axle(xr + 0.3 * rear_len, R, True), Axle(xr + 0.3 * rear_len + 2.1 * R + 0.1, R, True)]
    else:  # tipper: a tapered steel body
        sec = []
        for xx in (xr, xf - Lc - 0.2):
            sec.append([(xx, 0.42 * W, chassis_z + 0.05), (xx, W / 2, H), (xx, -W / 2, H),
                        (xx, -0.42 * W, chassis_z + 0.05)])
        loft(b, np.array(sec), CARGO, (CARGO, CARGO))
        axles += [Axle(xr + 0.3 * rear_len, R, True), Axle(xr + 0.3 * rear_len + 2.1 * R + 0.1, R, True)]
    _wheels(b, axles, 0.5 * W - 0.03, 0.3)
    _ends(b, cab, xf, xf - Lc, 0.14, bumper_d=bd, bumper_h=0.35, lamp_in=0.6)
    rz = chassis_z - 0.25
    box(b, (xr - bd, -0.45 * W, rz), (xr, 0.45 * W, rz + 0.2), TRIM)
    box(b, (xr - bd - 0.012, -0.26, rz + 0.04), (xr - bd, 0.26, rz + 0.15), PLATE)
    for side in (-1, 1):
        y0, y1 = sorted((side * 0.3 * W, side * 0.45 * W))
        box(b, (xr - bd - 0.01, y0, rz + 0.2), (xr, y1, rz + 0.32), LAMP_R)
    _mirrors(b, xf - 0.35, 0.5 * W - 0.02, 0.62 * Hc, 0.19)


def _bus(b: Builder, s: str, p: dict) -> None:
    L, W, H, R = p["L"], p["W"], p["H"], p["R"]
    bd = 0.06
    Lh = L - 2 * bd - 0.024
    x0 = -Lh / 2
    belt = p["belt"] * H
    if s == "coach":
        roof = [(0, 0.96 * H), (0.01, H), (0.96, H), (0.985, 0.9 * H), (1.0, 0.55 * H)]
        axles = [Axle(0.18 * Lh, R), Axle(0.18 * Lh + 2.1 * R + 0.2, R), Axle(0.82 * Lh, R)]
    else:
        roof = [(0, 0.97 * H), (0.01, H), (0.985, H), (1.0, 0.96 * H)]
        axles = [Axle(0.22 * Lh, R), Axle(0.80 * Lh, R)]
    hull = _hull(b, Lh, W, H, roof, belt, p["clear"], axles, x0=x0, taper=(0.02, 0.02), tumble=0.94,
                 pillar_every=3, glass_top=0.1, slope_glass=0.8, n_stations=40)
    # windscreen and rear window on the end faces
    box(b, (Lh / 2 - 0.005, -0.44 * W, belt + 0.05), (Lh / 2 + 0.01, 0.44 * W, H - 0.2), GLASS)
    box(b, (-Lh / 2 - 0.01, -0.4 * W, H * 0.7), (-Lh / 2 + 0.005, 0.4 * W, H - 0.2), GLASS)
    _wheels(b, [Axle(a.x + x0, a.radius) for a in axles], 0.5 * W - 0.04, 0.3)
    _liners(b, axles, 0.5 * W - 0.04, 0.3, p["clear"], x0)
    _ends(b, hull, Lh / 2, -Lh / 2, 0.14, bumper_d=bd, bumper_h=0.3, lamp_in=0.62)
    for side in (-1, 1):  # forward-hanging mirrors, within the body's width
        y0, y1 = sorted((side * 0.40 * W, side * 0.48 * W))
        box(b, (Lh / 2 + 0.02, y0, H - 0.75), (Lh / 2 + bd, y1, H - 0.45), DARK)


def _rim_ring(b: Builder, cx: float, cz: float, r: float, thick: float, part, n: int = 12) -> None:
    """A spoked wheel's tyre as a ring of n closed segments, with a hub."""
    ang = np.arange(n + 1) * 2 * math.pi / n
    pts = np.stack([cx + r * np.cos(ang), np.zeros(n + 1), cz + r * np.sin(ang)], 1)
    for k in range(n):
        frustum(b, pts[k], pts[k + 1], thick, thick, part, 4)
    cylinder(b, (cx, 0.0, cz), 0.05, 0.05, "y", RIM, 8)


def _two_wheeler(b: Builder, s: str, p: dict) -> None:
    L, R = p["L"], p["R"]
    rider = Person.from_key(f"rider:{p['name']}")
    motor = s in ("sport", "scooter", "touring")
    xr, xf = -L / 2 + R, L / 2 - R
    if motor:
        Rr = R if s != "scooter" else 0.85 * R
        for x, rr in ((xr, Rr), (xf, R)):
            cylinder(b, (x, 0.0, rr), rr, 0.08 if s != "scooter" else 0.06, "y", TYRE, 16)
            cylinder(b, (x, 0.0, rr), 0.6 * rr, 0.085 if s != "scooter" else 0.065, "y", RIM, 16)
        seat_z = p["seat"]
        if s == "scooter":
            box(b, (xr - 0.1, -0.17, Rr + 0.05), (xr + 0.55, 0.17, seat_z - 0.08), BODY)  # rear body
            box(b, (xr + 0.5, -0.14, 0.22), (xf - 0.25, 0.14, 0.32), DARK)  # floorboard
            box(b, (xf - 0.32, -0.2, 0.25), (xf - 0.18, 0.2, 0.95), BODY)  # leg shield
            box(b, (xr - 0.05, -0.15, seat_z - 0.08), (xr + 0.55, 0.15, seat_z), DARK)  # seat
            frustum(b, (xf - 0.2, 0, 0.9), (xf - 0.05, 0, R), 0.04, 0.03, DARK, 6)
            bar = (xf - 0.22, 1.05)
        else:
            frustum(b, (xr, 0, Rr), (xr + 0.55, 0, Rr + 0.25), 0.05, 0.05, DARK, 6)  # swing arm
            box(b, (xr + 0.45, -0.17, 0.25), (xr + 0.95, 0.17, 0.62), DARK)  # engine
            ellipsoid(b, (xr + 0.95, 0, seat_z + 0.08), (0.27, 0.19, 0.15), BODY, 4, 8)  # tank
            box(b, (xr - 0.1, -0.15, seat_z - 0.1), (xr + 0.72, 0.15, seat_z), DARK)  # seat
            frustum(b, (xf - 0.3, 0, seat_z + 0.28), (xf, 0, R), 0.045, 0.04, DARK, 6)  # fork
            if s == "sport":
                frustum(b, (xr + 1.05, 0, seat_z - 0.2), (xf - 0.12, 0, seat_z + 0.05), 0.22, 0.14, BODY, 8, 0.9)
                bar = (xf - 0.32, seat_z + 0.22)
            else:  # touring: fairing with a screen, panniers and a top case
                frustum(b, (xr + 1.0, 0, seat_z - 0.1), (xf - 0.12, 0, seat_z + 0.1), 0.3, 0.22, BODY, 8, 0.9)
                box(b, (xf - 0.32, -0.2, seat_z + 0.25), (xf - 0.22, 0.2, seat_z + 0.5), GLASS)
                for side in (-1, 1):
                    y0, y1 = sorted((side * 0.18, side * 0.42))
                    box(b, (xr - 0.15, y0, Rr + 0.05), (xr + 0.35, y1, Rr + 0.45), BODY)
                box(b, (xr - 0.3, -0.2, seat_z + 0.02), (xr + 0.05, 0.2, seat_z + 0.32), BODY)
                bar = (xf - 0.4, seat_z + 0.3)
        box(b, (bar[0] - 0.03, -0.36, bar[1] - 0.03), (bar[0] + 0.03, 0.36, bar[1] + 0.03), DARK)  # handlebar
        box(b, (bar[0] + 0.02, -0.07, bar[1] - 0.16), (bar[0] + 0.12, 0.07, bar[1] - 0.06), LAMP_F)
        tail = xr - 0.12 if s != "touring" else xr - 0.32
        box(b, (tail, -0.1, seat_z - 0.3), (tail + 0.015, 0.1, seat_z - 0.19), PLATE)
        box(b, (tail, -0.07, seat_z - 0.18), (tail + 0.25, 0.07, seat_z - 0.1), LAMP_R)
        lean = {"sport": 38, "scooter": 8, "touring": 15}[s]
        hip_x = xr + (0.35 if s != "scooter" else 0.25)
        pose = seated_pose(lean, 95 if s != "scooter" else 80, 0.8 if s == "sport" else 0.5)
        helmet = True
    else:
        for x in (xr, xf):
            _rim_ring(b, x, R, R - 0.02, 0.02, TYRE, 14)
        seat_z = p["seat"]
        crank = (xr + 0.45 * (xf - xr), 0.3)
        head = (xf - 0.12, seat_z + 0.02)
        seat = (crank[0] - 0.18, seat_z)
        for a, c in ((crank, seat), (crank, head), (seat, head), ((xr, R), crank), ((xr, R), seat),
                     (head, (xf, R))):
            frustum(b, (a[0], 0, a[1]), (c[0], 0, c[1]), 0.022, 0.022, BODY, 4)
        box(b, (seat[0] - 0.1, -0.07, seat_z), (seat[0] + 0.12, 0.07, seat_z + 0.06), DARK)
        bar_z = seat_z + (0.15 if s == "city" else 0.02)
        frustum(b, (head[0], 0, head[1]), (head[0] - 0.05, 0, bar_z), 0.02, 0.02, DARK, 4)
        box(b, (head[0] - 0.08, -0.3, bar_z - 0.02), (head[0] - 0.03, 0.3, bar_z + 0.02), DARK)
        if s == "cargo":  # a box between the rider and the front wheel
            box(b, (crank[0] + 0.25, -0.33, 0.25), (xf - R - 0.05, 0.33, 0.75), CARGO)
        if s == "city":
            box(b, (xr - 0.1, -0.12, R + 0.35), (xr + 0.2, 0.12, R + 0.38), DARK)  # rack
        box(b, (head[0] + 0.02, -0.05, head[1] - 0.1), (head[0] + 0.08, 0.05, head[1] - 0.04), LAMP_F)
        box(b, (seat[0] - 0.08, -0.04, seat_z - 0.14), (seat[0] - 0.02, 0.04, seat_z - 0.08), LAMP_R)
        lean = {"city": 12, "road": 45, "cargo": 15}[s]
        hip_x = seat[0]
        pose = seated_pose(lean, 70, 0.9 if s == "road" else 0.6)
        bar = (head[0], bar_z)
        helmet = s == "road"
    # the rider: pelvis over the seat
    sk = skeleton(rider, pose)
    off = np.array([hip_x, 0.0, seat_z + 0.06 * rider.height_m]) - sk["pelvis"]
    build_body(b, rider, pose, offset=off, parts={"hair": DARK} if helmet else None)


# ------------------------------------------------------------------------------ catalogue

CLASS_OF_STYLE = {
    "hatchback": "car", "saloon": "car", "estate": "car", "suv": "car", "pickup": "car", "coupe": "car",
    "microcar": "car", "panel_van": "van", "minibus": "van", "box": "truck", "flatbed": "truck", "semi": "truck",
    "tanker": "truck", "tipper": "truck", "city_bus": "bus", "coach": "bus", "sport": "motorcycle",
    "scooter": "motorcycle", "touring": "motorcycle", "city": "bicycle", "road": "bicycle", "cargo": "bicycle",
}

#: per style: how many models, and the ranges (lo, hi) their continuous parameters are drawn from
#: (L, W, H [m] of the hull, wheel radius R, ground clearance, hood and belt heights as fractions of H...)
_RANGES: dict[str, tuple[int, dict[str, tuple[float, float]]]] = {
    "hatchback": (4, {"L": (3.70, 4.20), "W": (1.70, 1.80), "H": (1.42, 1.55), "R": (0.30, 0.33)}),
    "saloon": (4, {"L": (4.50, 4.95), "W": (1.78, 1.88), "H": (1.40, 1.50), "R": (0.31, 0.35)}),
    "estate": (3, {"L": (4.50, 4.90), "W": (1.78, 1.86), "H": (1.45, 1.55), "R": (0.31, 0.34)}),
    "suv": (4, {"L": (4.40, 5.10), "W": (1.84, 1.98), "H": (1.62, 1.85), "R": (0.35, 0.39)}),
    "pickup": (3, {"L": (5.20, 5.55), "W": (1.88, 1.98), "H": (1.78, 1.92), "R": (0.37, 0.40)}),
    "coupe": (3, {"L": (4.30, 4.70), "W": (1.80, 1.90), "H": (1.26, 1.36), "R": (0.32, 0.35)}),
    "microcar": (2, {"L": (2.20, 2.55), "W": (1.45, 1.55), "H": (1.38, 1.50), "R": (0.23, 0.26)}),
    "panel_van": (3, {"L": (4.80, 5.95), "W": (1.90, 2.02), "H": (1.95, 2.60), "R": (0.33, 0.36)}),
    "minibus": (2, {"L": (5.30, 5.95), "W": (1.95, 2.02), "H": (2.20, 2.50), "R": (0.33, 0.36)}),
    "box": (2, {"L": (7.00, 8.50), "W": (2.45, 2.55), "H": (3.20, 3.50), "R": (0.48, 0.52)}),
    "flatbed": (2, {"L": (7.00, 8.50), "W": (2.45, 2.55), "H": (3.00, 3.20), "R": (0.48, 0.52)}),
    "semi": (2, {"L": (12.5, 14.0), "W": (2.55, 2.55), "H": (3.80, 4.00), "R": (0.50, 0.52)}),
    "tanker": (1, {"L": (9.00, 10.0), "W": (2.50, 2.55), "H": (3.40, 3.60), "R": (0.50, 0.52)}),
    "tipper": (1, {"L": (7.50, 8.50), "W": (2.50, 2.55), "H": (3.20, 3.40), "R": (0.50, 0.52)}),
    "city_bus": (2, {"L": (10.5, 12.0), "W": (2.55, 2.55), "H": (3.00, 3.20), "R": (0.48, 0.50)}),
    "coach": (2, {"L": (12.0, 12.8), "W": (2.55, 2.55), "H": (3.50, 3.70), "R": (0.50, 0.52)}),
    "sport": (2, {"L": (2.00, 2.15), "R": (0.30, 0.32), "seat": (0.80, 0.86)}),
    "scooter": (2, {"L": (1.85, 2.00), "R": (0.26, 0.28), "seat": (0.76, 0.80)}),
    "touring": (2, {"L": (2.25, 2.40), "R": (0.32, 0.34), "seat": (0.78, 0.84)}),
    "city": (2, {"L": (1.70, 1.85), "R": (0.33, 0.35), "seat": (0.90, 0.98)}),
    "road": (2, {"L": (1.65, 1.78), "R": (0.33, 0.34), "seat": (0.95, 1.02)}),
    "cargo": (1, {"L": (2.30, 2.45), "R": (0.25, 0.33), "seat": (0.88, 0.95)}),
}

#: the seed of the catalogue: every model's parameters are drawn from it and the model's name
CATALOGUE_SEED = 28


@dataclass(frozen=True)
class VehicleModel:
    """One catalogue model: name, class, style, parameters; its mesh and tight box come from :func:`build`."""

    name: str
    cls: str
    style: str
    params: dict = field(hash=False, compare=False)


def _draw(style: str, k: int) -> dict:
    n, rng_ = _RANGES[style]
    rng = np.random.default_rng([CATALOGUE_SEED, zlib.crc32(style.encode()), k])
    t = (k + rng.uniform(0.15, 0.85)) / n  # spread the models of a style over its ranges
    p = {key: lo + (hi - lo) * (t if key in ("L", "H") else rng.uniform()) for key, (lo, hi) in rng_.items()}
    p.update(clear=float(rng.uniform(0.13, 0.17)), hood=float(rng.uniform(0.64, 0.69)),
             belt=float(rng.uniform(0.66, 0.70)), wb_front=float(rng.uniform(0.16, 0.2)),
             wb_rear=float(rng.uniform(0.15, 0.2)), screen=float(rng.uniform(0.14, 0.2)),
             rear=float(rng.uniform(0, 1)), tumble=float(rng.uniform(0.82, 0.88)), load=float(rng.uniform()))
    if style == "suv" or style == "pickup":
        p.update(clear=float(rng.uniform(0.19, 0.23)), hood=float(rng.uniform(0.64, 0.68)),
                 belt=float(rng.uniform(0.62, 0.66)))
    if style == "microcar":
        p.update(hood=0.5, belt=0.5, wb_front=0.2, wb_rear=0.18, clear=0.12)
    if CLASS_OF_STYLE[style] == "van":
        p.update(hood=float(rng.uniform(0.42, 0.5)), belt=float(rng.uniform(0.45, 0.5)), clear=0.18)
    if CLASS_OF_STYLE[style] == "truck":
        p["Hc"] = min(p["H"], 3.0 + 0.1 * rng.uniform())
    if CLASS_OF_STYLE[style] == "bus":
        p.update(belt=float(rng.uniform(0.36, 0.42)) if style == "city_bus" else float(rng.uniform(0.5, 0.55)),
                 clear=0.3)
    return {k: float(v) for k, v in p.items()}


def _catalogue() -> tuple[VehicleModel, ...]:
    out = []
    for style, (n, _) in _RANGES.items():
        for k in range(n):
            p = _draw(style, k)
            name = f"{style}_{k}"
            p["name"] = name
            out.append(VehicleModel(name, CLASS_OF_STYLE[style], style, p))
    return tuple(out)


#: every vehicle model, in a fixed order (class by class, style by style)
MODELS: tuple[VehicleModel, ...] = _catalogue()
BY_NAME: dict[str, VehicleModel] = {m.name: m for m in MODELS}


@cache
def build(name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The model's mesh in metres, box-centred (its tight box is centred on the origin): vertices,
    triangles, part, group, component."""
    m = BY_NAME[name]
    b = Builder()
    {"car": _car, "van": _van, "truck": _truck, "bus": _bus}.get(m.cls, _two_wheeler)(b, m.style, m.params)
    v, t, part, grp, comp = b.arrays()
    lo, hi = v.min(0), v.max(0)
    v = v - (lo + hi) / 2
    return v, t, part, grp, comp


#: Every model's tight box (length, width, height) [m], as :func:`mesh_dims` measures it on the built mesh. SUMO's
#: vTypes and the renderer's model lookup read it in every episode process; measuring all the meshes there cost
#: 0.3 CPU-s a process. tests/test_assets.py checks each entry against its mesh (and prints the line to put here
#: when a model changes); a model not listed is measured.
TIGHT_BOX_M: dict[str, tuple[float, float, float]] = {
    "hatchback_0": (3.72, 1.93, 1.43),
    "hatchback_1": (3.89, 1.91, 1.47),
    "hatchback_2": (4.01, 1.93, 1.5),
    "hatchback_3": (4.12, 1.92, 1.53),
    "saloon_0": (4.55, 1.98, 1.41),
    "saloon_1": (4.7, 2.04, 1.44),
    "saloon_2": (4.76, 2.03, 1.46),
    "saloon_3": (4.89, 2.04, 1.49),
    "estate_0": (4.54, 2.04, 1.46),
    "estate_1": (4.74, 1.99, 1.51),
    "estate_2": (4.85, 1.97, 1.54),
    "suv_0": (4.49, 2.13, 1.65),
    "suv_1": (4.72, 2.07, 1.73),
    "suv_2": (4.9, 2.15, 1.78),
    "suv_3": (5.07, 2.03, 1.84),
    "pickup_0": (5.24, 2.08, 1.8),
    "pickup_1": (5.36, 2.11, 1.84),
    "pickup_2": (5.5, 2.14, 1.9),
    "coupe_0": (4.34, 2.02, 1.27),
    "coupe_1": (4.49, 2.02, 1.31),
    "coupe_2": (4.6, 2.0, 1.33),
    "microcar_0": (2.24, 1.72, 1.4),
    "microcar_1": (2.43, 1.71, 1.46),
    "panel_van_0": (4.96, 2.32, 2.04),
    "panel_van_1": (5.38, 2.24, 2.28),
    "panel_van_2": (5.64, 2.3, 2.43),
    "minibus_0": (5.48, 2.26, 2.28),
    "minibus_1": (5.8, 2.28, 2.43),
    "box_0": (7.21, 2.84, 3.24),
    "box_1": (7.93, 2.87, 3.39),
    "flatbed_0": (7.45, 2.82, 3.01),
    "flatbed_1": (8.26, 2.86, 3.04),
    "semi_0": (12.99, 2.89, 3.87),
    "semi_1": (13.45, 2.89, 3.93),
    "tanker_0": (9.83, 2.86, 3.57),
    "tipper_0": (8.06, 2.85, 3.31),
    "city_bus_0": (10.74, 2.55, 3.03),
    "city_bus_1": (11.78, 2.55, 3.17),
    "coach_0": (12.17, 2.55, 3.54),
    "coach_1": (12.62, 2.55, 3.65),
    "sport_0": (2.03, 0.72, 1.64),
    "sport_1": (2.08, 0.72, 1.68),
    "scooter_0": (1.85, 0.72, 1.77),
    "scooter_1": (1.92, 0.72, 1.43),
    "touring_0": (2.3, 0.84, 1.64),
    "touring_1": (2.36, 0.84, 1.79),
    "city_0": (1.73, 0.67, 1.92),
    "city_1": (1.82, 0.6, 1.73),
    "road_0": (1.79, 0.67, 1.76),
    "road_1": (1.75, 0.6, 1.6),
    "cargo_0": (2.39, 0.66, 1.79),
}


def dims(name: str) -> tuple[float, float, float]:
    """(length, width, height) [m] of the model's tight box, rounded to centimetres (:data:`TIGHT_BOX_M`)."""
    box = TIGHT_BOX_M.get(name)
    return box if box is not None else mesh_dims(name)


def mesh_dims(name: str) -> tuple[float, float, float]:
    """:func:`dims` measured on the model's mesh (:func:`build`)."""
    v = build(name)[0]
    return tuple(round(float(x), 2) for x in (v.max(0) - v.min(0)))  # type: ignore[return-value]
