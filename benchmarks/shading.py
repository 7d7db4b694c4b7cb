"""Shading cost per 1280x720 camera: ``shade()`` alone on frames cast once, per weather x lighting.

    PYTHONPATH=. .venv/bin/python benchmarks/shading.py [--repeats 5] [--save DIR]
    PYTHONPATH=. .venv/bin/python benchmarks/shading.py --closeups docs/img
    PYTHONPATH=. .venv/bin/python benchmarks/shading.py --compare-fastmath [--repeats 5]

Builds the world of scenarios/default.yaml, places the actors of ``world_snapshot`` (seed 3), casts
the front cameras of vehicle_0 and rsu_0 at 1280x720 once, then times ``shade`` on those hits
(median of ``--repeats``, wall and the thread's CPU time, after one warm-up call that also compiles any
kernels) for clear day,
clear night, rainy dusk and rainy night. ``--save DIR`` writes the images as PNG and their sha256
(to compare outputs before and after a change). ``--compare-fastmath`` also times the shading kernel
compiled without ``fastmath`` (:data:`cosim.sensors.surface.SAFE_FASTMATH` off), alternating the two on
the same hits, and prints the CPU ratio and whether the images are the same bytes.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import tempfile
import time
from pathlib import Path

import numba
import numpy as np
from cosim.sensors import SensorSuite, camera, surface
from cosim.sensors.camera import Occluders, cast_image, shade
from cosim.sensors.rig import camera_pose, intrinsics
from cosim.sensors.surface import SAFE_FASTMATH
from cosim.sensors.synthetic import world_snapshot

from cosim.scenario.loader import load_scenario, load_scenario_data
from cosim.world.build import build_world

ROOT = Path(__file__).resolve().parents[1]
CASES = (("clear", "day"), ("clear", "night"), ("rainy", "dusk"), ("rainy", "night"))


def scenario(weather: str, lighting: str, detail: bool = True):
    data = json.loads(json.dumps(load_scenario(ROOT / "scenarios" / "default.yaml").resolved))
    data["agents"]["vehicles"]["count"] = 5
    data["agents"]["rsus"]["count"] = 5
    data["agents"]["drones"] = []
    data["environment"].update({"weather": weather, "lighting": lighting})
    if not detail:
        data["sensors"]["surface_detail"] = False
    for kind in ("vehicle", "rsu"):
        rig = data["sensors"][kind]
        rig["lidar"] = None
        rig["cameras"] = [dict(c, width=1280, height=720) for c in rig["cameras"] if c["name"] == "front"]
    return load_scenario_data(data)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--save", type=Path)
    ap.add_argument("--no-detail", action="store_true", help="sensors.surface_detail: false")
    ap.add_argument("--closeups", type=Path, help="write the surface detail and wet road close-ups here and exit")
    ap.add_argument("--compare-fastmath", action="store_true", help="also time the kernel without fastmath")
    args = ap.parse_args()
    if args.closeups:
        closeups(args.closeups)
        return
    with tempfile.TemporaryDirectory() as tmp:
        world = build_world(scenario("clear", "day"), Path(tmp))
    snap = world_snapshot(world, 5, 0, 60, seed=3)
    agents = {a.agent_id: a for a in snap.agents}
    digests = {}
    for weather, lighting in CASES:
        plain_cpu: list[float] = []
        fast_cpu: list[float] = []
        same: list[bool] = []
        sc = scenario(weather, lighting, not args.no_detail).scenario
        with SensorSuite(sc, world, encode_images=False, workers=1) as suite:
            tick = suite._prepare(snap)
            times, cpu = [], []
            for agent_id in ("vehicle_0", "rsu_0"):
                agent = agents[agent_id]
                cam = sc.rig_for(agent_id).cameras[0]
                K, pose = intrinsics(cam), camera_pose(agent, cam)
                own = tick.own_track.get(agent_id)
                occ = Occluders(suite._thin, suite._static_points, tick.a_corners[tick.a_tracks != own],
                                suite._sun, tick.shadow_boxes)
                gid, depth, lit = cast_image(cam, K, pose, tick.scene, occ, own, suite.block_px)

                def once(gid=gid, depth=depth, lit=lit, cam=cam, K=K, pose=pose, tick=tick):
                    return shade(gid, depth, lit, cam, K, pose, tick.tables, suite.atm, tick.light,
                                 np.random.default_rng(0), 1, True)

                rgb = once()
                t, c = [], []
                for _ in range(args.repeats):
                    t0, c0 = time.perf_counter(), time.thread_time()
                    once()
                    t.append(time.perf_counter() - t0)
                    c.append(time.thread_time() - c0)
                    if args.compare_fastmath:  # the same call without fastmath, right after
                        with _plain_kernel():
                            c0 = time.thread_time()
                            plain = once()
                            plain_cpu.append(time.thread_time() - c0)
                        fast_cpu.append(c[-1])
                        same.append(bool(np.array_equal(plain, rgb)))
                times.append(float(np.median(t)))
                cpu.append(float(np.median(c)))
                key = f"{weather}_{lighting}_{agent_id}"
                digests[key] = hashlib.sha256(rgb.tobytes()).hexdigest()
                if args.save:
                    from PIL import Image

                    args.save.mkdir(parents=True, exist_ok=True)
                    Image.fromarray(rgb).save(args.save / f"{key}.png")
        print(f"{weather:6s} {lighting:6s}: shade {1000 * np.mean(times):6.1f} ms per 1280x720 camera "
              f"(vehicle front {1000 * times[0]:.1f}, rsu front {1000 * times[1]:.1f}); "
              f"CPU {1000 * np.mean(cpu):.1f} ms")
        if args.compare_fastmath:
            print(f"               fastmath {sorted(SAFE_FASTMATH)}: CPU {1000 * np.median(fast_cpu):.1f} ms, "
                  f"without {1000 * np.median(plain_cpu):.1f} ms: {np.median(plain_cpu) / np.median(fast_cpu):.2f}x; "
                  f"same bytes in {sum(same)} of {len(same)} images")
    if args.save:
        (args.save / "sha256.json").write_text(json.dumps(digests, indent=1))


_PLAIN = []


@contextlib.contextmanager
def _plain_kernel():
    """The shading kernel compiled without fastmath, in place of the shipped one (its inlined helpers
    compile with the caller's flags)."""
    if not _PLAIN:
        _PLAIN.append(numba.njit(nogil=True, error_model="numpy")(surface.shade_linear.py_func))
    shipped = camera.shade_linear
    camera.shade_linear = _PLAIN[0]
    try:
        yield
    finally:
        camera.shade_linear = shipped


def closeups(out_dir: Path) -> None:
    """render_surface_detail.png (clear day, vehicle_0's front camera: asphalt, worn markings, paving,
    facades, foliage, grass) and render_wet_road_night.png (rainy night: lamp and headlight reflections
    on the wet road, lit windows), 960x540 crops of the default town."""
    from PIL import Image

    with tempfile.TemporaryDirectory() as tmp:
        world = build_world(scenario("clear", "day"), Path(tmp))
    snap = world_snapshot(world, 5, 0, 60, seed=3)
    out_dir.mkdir(parents=True, exist_ok=True)
    for (weather, lighting), name in ((("clear", "day"), "render_surface_detail.png"),
                                      (("rainy", "night"), "render_wet_road_night.png")):
        sc = scenario(weather, lighting).scenario
        with SensorSuite(sc, world, encode_images=False) as suite:
            f = suite.render(snap, np.random.default_rng(0)).agents["vehicle_0"].cameras["front"]
        Image.fromarray(f.rgb[180:, 160:1120]).save(out_dir / name, optimize=True)
        print(f"wrote {out_dir / name}")


if __name__ == "__main__":
    main()
