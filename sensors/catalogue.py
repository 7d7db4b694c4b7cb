"""The asset catalogue a user can see: a table, catalogue.json, gallery.png and lidar_gallery.png.

``cosim assets [--out DIR]`` (:func:`write_catalogue`) lists every vehicle model and a set of people
(name, class, style, dimensions, triangle count, mesh volume over box volume), draws every model lit by
day from the side and at three quarters, and scans one model per class with the paper's vehicle LiDAR
(64 channels, 0.35 deg, the scenario default) from 10 m and 40 m.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from .assets import people, vehicles
from .assets.shapes import union_volume

#: how many people the catalogue lists (drawn from these keys; pedestrians get theirs from the SUMO id)
N_PEOPLE = 16


def people_keys() -> list[str]:
    return [f"person_{k}" for k in range(N_PEOPLE)]


def _entry(name: str, cls: str, style: str, v, t, comp) -> dict:
    lo, hi = v.min(0), v.max(0)
    vol = union_volume(v, t, comp, lo, hi)
    size = hi - lo
    return {"name": name, "class": cls, "style": style, "length_m": round(float(size[0]), 2),
            "width_m": round(float(size[1]), 2), "height_m": round(float(size[2]), 2), "triangles": len(t),
            "volume_ratio": round(vol / float(np.prod(size)), 3)}


def catalogue() -> list[dict]:
    """One row per model: every vehicle model, then :data:`N_PEOPLE` people standing."""
    rows = []
    for m in vehicles.MODELS:
        v, t, _, _, comp = vehicles.build(m.name)
        rows.append(_entry(m.name, m.cls, m.style, v, t, comp))
    for key in people_keys():
        p = people.Person.from_key(key)
        v, t, _, _, comp = people.person_mesh(p, people.walk_pose(0.0, 0.0))
        rows.append(_entry(key, "pedestrian", "child" if p.child else "adult", v, t, comp) | {"build": p.build})
    return rows


def table(rows: list[dict]) -> str:
    head = f"{'name':<14} {'class':<11} {'style':<10} {'L x W x H [m]':<18} {'triangles':>9} {'vol/box':>7}"
    lines = [head, "-" * len(head)]
    for r in rows:
        dims = f"{r['length_m']:.2f} x {r['width_m']:.2f} x {r['height_m']:.2f}"
        lines.append(f"{r['name']:<14} {r['class']:<11} {r['style']:<10} {dims:<18} {r['triangles']:>9} "
                     f"{r['volume_ratio']:>7.3f}")
    return "\n".join(lines)


# ------------------------------------------------------------------------------ pictures


#: street furniture drawn after the models: a signal head (its green lamp lit) and the three signs
FURNITURE = ("traffic_light", "sign_stop", "sign_give_way", "sign_speed_limit")


def _furniture_mesh(name: str):
    """(vertices, triangles, albedo, emissive) of a :data:`FURNITURE` item, box-centred."""
    from cosim.sensors.assets.signals import LAMP_RGB, signal_parts
    from cosim.sensors.signals import sign_mesh

    from cosim.world.traffic_lights import SignalHead
    from cosim.world.traffic_signs import TrafficSign

    if name == "traffic_light":
        head = SignalHead("j/l_0", "j", (0,), (0.0, 0.0, 5.5), 0.0, (0.0, -4.0))
        p = signal_parts((head,))
        v, t, alb = p.vertices.astype(np.float64), p.triangles, p.albedo.copy()
        emis = np.zeros(len(t), np.float32)
        lit = p.lamp_colour == 2
        alb[lit] = LAMP_RGB[2] * 2.5  # self-luminous: bright whatever the shading
    else:
        m = sign_mesh([TrafficSign("s", name[len("sign_"):], 50, (0.0, 0.0), 0.0)])
        v, t, alb, emis = m.vertices.astype(np.float64), m.triangles, m.albedo, m.emissive
    return v - (v.min(0) + v.max(0)) / 2, np.asarray(t), alb, emis


def _model_mesh(name: str):
    """(vertices, triangles, albedo (T, 3)) in metres, box-centred, of a vehicle model, a person key or a
    :data:`FURNITURE` item."""
    from cosim.sensors.meshes import actor_material, person_template, vehicle_template

    if name in FURNITURE:
        return _furniture_mesh(name)
    if name in vehicles.BY_NAME:
        tpl = vehicle_template(name)
        v, t, _, _, _ = vehicles.build(name)
        cls = vehicles.BY_NAME[name].cls
    else:
        tpl = person_template(name, 0.0, 0.0)
        _, v, t, _, _, lo, hi = people.posed(name, 0.0, 0.0)
        v = v - (lo + hi) / 2
        cls = "pedestrian"
    alb, _, emis = actor_material(cls, 1 + sum(map(ord, name)), tpl.part, palette=tpl.palette)
    return np.asarray(v, np.float64), np.asarray(t), alb, emis


def render_view(v: np.ndarray, t: np.ndarray, albedo: np.ndarray, emissive: np.ndarray, azimuth_deg: float,
                elevation_deg: float, px: int = 160, span_m: float | None = None) -> np.ndarray:
    """An orthographic picture (px, px, 3) uint8 of a mesh lit by a day sun and sky, seen from
    ``azimuth_deg`` (0: from the front, 90: from the left side) and ``elevation_deg``."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(t.astype(np.uint32)))
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    d = -np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])  # view direction
    right = np.cross(d, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, d)
    span = span_m or 1.1 * float(np.linalg.norm(v.max(0) - v.min(0)))
    s = (np.arange(px) + 0.5) / px - 0.5
    gx, gy = np.meshgrid(s * span, -s * span)
    origin = -d * 100 + gx[..., None] * right + gy[..., None] * up
    rays = np.concatenate([origin.reshape(-1, 3), np.broadcast_to(d, (px * px, 3))], 1).astype(np.float32)
    ans = scene.cast_rays(o3d.core.Tensor(rays))
    hit = np.isfinite(ans["t_hit"].numpy())
    prim = ans["primitive_ids"].numpy().astype(np.int64)
    n = ans["primitive_normals"].numpy()
    sun = np.array([0.4, -0.5, 0.77])
    sun /= np.linalg.norm(sun)
    lam = np.clip(n @ sun, 0, 1)
    sky = 0.55 + 0.25 * n[:, 2]
    col = np.where(hit[:, None], albedo[np.where(hit, prim, 0)] * (0.75 * lam + 0.45 * sky)[:, None], 0.0)
    col += np.where(hit, emissive[np.where(hit, prim, 0)] * 0.3, 0)[:, None]
    bg = np.array([0.93, 0.94, 0.96])
    col = np.where(hit[:, None], np.clip(col, 0, 1) ** (1 / 2.2), bg)
    return (col.reshape(px, px, 3) * 255).astype(np.uint8)


def gallery(names: list[str], path: Path, px: int = 150, cols: int = 6) -> None:
    """Every model by day, side (left) and three-quarter (front left, from above) views side by side."""
    from PIL import Image, ImageDraw

    cell_w, cell_h = 2 * px, px + 14
    rows = math.ceil(len(names) / cols)
    img = Image.new("RGB", (cols * cell_w, rows * cell_h), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    for k, name in enumerate(names):
        v, t, alb, emis = _model_mesh(name)
        span = 1.08 * float(max(v.max(0) - v.min(0)))
        side = render_view(v, t, alb, emis, 90.0, 3.0, px, span)
        tq = render_view(v, t, alb, emis, 40.0, 22.0, px, span)
        x, y = (k % cols) * cell_w, (k // cols) * cell_h
        img.paste(Image.fromarray(side), (x, y + 14))
        img.paste(Image.fromarray(tq), (x + px, y + 14))
        draw.text((x + 4, y + 1), name, fill=(0, 0, 0))
    img.save(path)


def lidar_scan(name: str, distance_m: float) -> np.ndarray:
    """Points (N, 3) [m, model frame] of the paper's vehicle LiDAR (64 channels, the scenario default
    pattern, mounted 1.9 m up) scanning model ``name`` from ``distance_m`` ahead-left at 30 deg."""
    import open3d as o3d
    from cosim.sensors.lidar import beam_pattern

    from cosim.scenario.model import LidarSpec

    v, t, _, _ = _model_mesh(name)
    v = v.copy()
    v[:, 2] -= v[:, 2].min()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(t.astype(np.uint32)))
    spec = LidarSpec()
    d, _ = beam_pattern(spec)
    az = math.radians(30.0)
    origin = np.array([distance_m * math.cos(az), distance_m * math.sin(az), spec.mount.xyz_m[2]])
    rays = np.concatenate([np.broadcast_to(origin, d.shape), d], 1).astype(np.float32)
    th = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    ok = np.isfinite(th)
    return origin + d[ok] * th[ok, None]


def lidar_gallery(names: list[str], path: Path, px: int = 220) -> None:
    """Each model in ``names`` scanned from 10 m and 40 m: the points seen from the sensor's side."""
    from PIL import Image, ImageDraw

    img = Image.new("RGB", (2 * px, len(names) * (px + 14)), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    for k, name in enumerate(names):
        for j, dist in enumerate((10.0, 40.0)):
            pts = lidar_scan(name, dist)
            v = _model_mesh(name)[0]
            ext = v.max(0) - v.min(0)
            span = 1.15 * float(max(ext[0], ext[1], ext[2]))
            # project along the line of sight (30 deg azimuth): horizontal axis across it, vertical z
            az = math.radians(30.0)
            u = pts[:, 0] * -math.sin(az) + pts[:, 1] * math.cos(az)
            w = pts[:, 2] - ext[2] / 2
            canvas = np.full((px, px, 3), 250, np.uint8)
            ix = ((u / span + 0.5) * px).astype(int)
            iy = ((0.5 - w / span) * px).astype(int)
            ok = (ix >= 1) & (ix < px - 1) & (iy >= 1) & (iy < px - 1)
            for dx in (-1, 0, 1):
                for dy in (-1, 0, 1):
                    canvas[iy[ok] + dy, ix[ok] + dx] = (20, 60, 160)
            x0, y0 = j * px, k * (px + 14)
            img.paste(Image.fromarray(canvas), (x0, y0 + 14))
            draw.text((x0 + 4, y0 + 1), f"{name} at {dist:.0f} m: {len(pts)} points", fill=(0, 0, 0))
    img.save(path)


#: the model per class the LiDAR gallery scans
LIDAR_GALLERY = ("saloon_1", "panel_van_1", "box_0", "city_bus_1", "sport_0", "city_0", "person_1", "traffic_light",
                 "sign_give_way")


def write_catalogue(out: Path, pictures: bool = True) -> list[dict]:
    """Write catalogue.json (and gallery.png, lidar_gallery.png) under ``out``; return the rows."""
    out.mkdir(parents=True, exist_ok=True)
    rows = catalogue()
    (out / "catalogue.json").write_text(json.dumps({"models": rows}, indent=1) + "\n")
    if pictures:
        gallery([r["name"] for r in rows] + list(FURNITURE), out / "gallery.png")
        lidar_gallery(list(LIDAR_GALLERY), out / "lidar_gallery.png")
    return rows


def cmd_assets(args) -> int:
    """``cosim assets [--out DIR] [--no-pictures]``: print the table, write catalogue.json and the pictures."""
    from cosim.preflight import check_output_dir

    out = Path(args.out)
    check_output_dir(out)  # a file, /proc, a NUL, no permission: one message, exit 2, before any work
    rows = write_catalogue(out, pictures=not args.no_pictures)
    print(table(rows))
    n_veh = sum(r["class"] != "pedestrian" for r in rows)
    written = "catalogue.json" + ("" if args.no_pictures else ", gallery.png, lidar_gallery.png")
    print(f"{n_veh} vehicle models, {len(rows) - n_veh} people; wrote {written} to {out}")
    return 0


def register(sub) -> None:
    """Add ``assets`` to the ``cosim`` command."""
    from cosim.cli_args import output_folder

    p = sub.add_parser("assets", help="the procedural asset catalogue: a table, catalogue.json, gallery.png and "
                                      "lidar_gallery.png")
    p.add_argument("--out", default="assets", type=output_folder, help="output folder (default: ./assets)")
    p.add_argument("--no-pictures", action="store_true", help="the table and catalogue.json only")
    p.set_defaults(func=cmd_assets)
