"""The scene and sensor realism levers of issue 48 against real KITTI scans: measured gaps, cost, a picture.

    PYTHONPATH=. .venv/bin/python benchmarks/realism_levers.py gaps --kitti /work/scratch/kitti_object/velodyne
    PYTHONPATH=. .venv/bin/python benchmarks/realism_levers.py cost --out /tmp/levers [--duration 4]
    PYTHONPATH=. .venv/bin/python benchmarks/realism_levers.py picture --episodes /tmp/levers \\
        --kitti /work/scratch/kitti_object/velodyne/000000.bin --out /tmp/levers/levers_bev.png

- ``gaps``: the lowest rings' blind sectors. In a real HDL-64E scan (KITTI's ``velodyne/*.bin``, float32 x, y,
  z, reflectance; the points of each laser stored together, each laser's sweep starting ahead of the car) a
  ring is told by the one wrap of its azimuth (+180 to -180 deg, behind the car) and the rings ordered by
  their median elevation; the blind sectors straight ahead and straight behind the car (the run of 1-degree
  bins with less than one return on average over the frames that holds azimuth 0, resp. 180 deg), ring by
  ring from the lowest, beside the ground radius of the ring. cosim's: the same of the beams of the
  ``hdl64e`` preset that ``self_occlusion`` does not block on the catalogue's estate (KITTI's car is a
  Passat estate), from :func:`cosim.sensors.lidar.own_body_range`, the renderer's own test; the ground
  radius of the ring at the 1.73 m mount.
- ``cost``: two LiDAR-only ``hdl64e`` episodes of the suburban town (5 vehicles, one ``cosim run`` process
  each, the same seed), the levers off (``self_occlusion: false``, ``map.clutter: none``) and on (the
  preset's ``self_occlusion``, ``map.clutter: kitti``); CPU-seconds of the whole process tree, episode bytes,
  both per tick, and their ratios (on / off). Real KITTI scans (their points per frame) beside them.
- ``picture``: BEV of one sweep of ``vehicle_0`` from each ``cost`` episode beside a real KITTI scan, the
  points within 30 m coloured by height.
"""

from __future__ import annotations

import argparse
import math
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

RINGS = 12  # the lowest rings compared
SCENARIO = "scenarios/base/paper.yaml"
COMMON = ["map.kind=suburban", "agents.vehicles.count=5", "agents.rsus.count=3", "sensors.bev=false",
          "sensors.vehicle.cameras=[]", "sensors.rsu.cameras=[]", "sensors.drone.cameras=[]", "sensors.rsu.lidar=null",
          "sensors.drone.lidar=null", "sensors.vehicle.lidar.model=hdl64e"]
LEVERS = {"off": ["sensors.vehicle.lidar.self_occlusion=false", "map.clutter=none"],
          "on": ["map.clutter=kitti"]}


def kitti_rings(points: np.ndarray) -> np.ndarray:
    """Ring (N,) int of each point of a KITTI scan (N, 4), 0..63 in file order: a ring's azimuth wraps once."""
    az = np.arctan2(points[:, 1], points[:, 0])
    wraps = np.cumsum(np.concatenate([[0], (np.diff(az) < -5.0).astype(int)]))
    return np.where(az >= 0, wraps, wraps - 1)


def kitti_gaps(files: list[Path]) -> list[tuple[float, float, int, int]]:
    """Per lowest ring: (elevation [deg], ground radius [m], blind degrees ahead, blind degrees behind)."""
    counts = np.zeros((RINGS, 360))
    elev, radius = np.zeros(RINGS), np.zeros(RINGS)
    for f in files:
        p = np.fromfile(f, np.float32).reshape(-1, 4)
        ring = kitti_rings(p)
        el = np.degrees(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])))
        med = np.array([np.median(el[ring == k]) if (ring == k).any() else 99.0 for k in range(64)])
        rho = np.hypot(p[:, 0], p[:, 1])
        for lo, k in enumerate(np.argsort(med)[:RINGS]):
            m = ring == k
            np.add.at(counts[lo], np.floor(np.degrees(np.arctan2(p[m, 1], p[m, 0]))).astype(int) % 360, 1)
            elev[lo] += med[k] / len(files)
            radius[lo] += float(np.median(rho[m])) / len(files)
    counts /= len(files)
    return [(elev[lo], radius[lo], sector(counts[lo], 0), sector(counts[lo], 180)) for lo in range(RINGS)]


def sector(counts: np.ndarray, centre_deg: int) -> int:
    """Width [deg] of the run of bins of ``counts`` (360,) (returns per 1-degree bin of azimuth, bin 0 from 0 to
    1 deg) under 1 that holds ``centre_deg``: a blind sector; 0 where the centre's bins see."""
    blind = counts < 1.0
    width = 0
    for side in (1, -1):
        k = 0 if side == 1 else -1
        while width < 360 and blind[(centre_deg + k) % 360]:
            width += 1
            k += side
    return width


def cosim_gaps(size_m=(4.74, 1.99, 1.51)) -> list[tuple[float, float, int, int]]:
    """The same of cosim's hdl64e on a car of ``size_m`` (the estate by default), from the renderer's mask."""
    from cosim.sensors.lidar import beam_pattern, own_body_range
    from cosim.sensors.lidar_models import ring_elevations_deg
    from cosim.sensors.meshes import empty_mesh
    from cosim.sensors.rig import sensor_pose
    from cosim.sensors.scene import StaticScene, TickScene

    from cosim.geometry import quat_from_rpy
    from cosim.scenario.model import Scenario
    from cosim.snapshot import Actor, AgentState

    sc = Scenario.model_validate({"name": "g", "sensors": {"vehicle": {"lidar": {"model": "hdl64e"}}}})
    spec = sc.sensors.vehicle.lidar
    d, ring = beam_pattern(spec)
    car = Actor(1, "car", (0.0, 0.0, size_m[2] / 2), size_m, quat_from_rpy(0.0, 0.0, 0.0), (0.0, 0.0, 0.0), "v")
    ego = AgentState("v", "vehicle", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), track_id=1)
    blocked = np.isfinite(own_body_range(TickScene.build(StaticScene(empty_mesh()), (car,)), 1,
                                         sensor_pose(ego, spec.mount), d))
    bins = np.floor(np.degrees(np.arctan2(d[:, 1], d[:, 0]))).astype(int) % 360
    elev = ring_elevations_deg(spec)
    out = []
    for k in range(RINGS):
        seen = np.bincount(bins[(ring == k) & ~blocked], minlength=360).astype(float)
        out.append((float(elev[k]), spec.mount.xyz_m[2] / math.tan(math.radians(-elev[k])), sector(seen, 0),
                    sector(seen, 180)))
    return out


def gaps(args) -> None:
    files = sorted(Path(args.kitti).glob("*.bin"))
    real, sim = kitti_gaps(files), cosim_gaps()
    print(f"lowest rings' blind sectors [deg of azimuth], KITTI ({len(files)} scans of {args.kitti}) against cosim's "
          f"hdl64e with self_occlusion on the estate")
    print("| ring from the lowest | KITTI elevation [deg] | KITTI ground radius [m] | KITTI blind ahead | KITTI blind "
          "behind | cosim elevation [deg] | cosim ground radius [m] | cosim blind ahead | cosim blind behind |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for k, (r, s) in enumerate(zip(real, sim, strict=True)):
        print(f"| {k} | {r[0]:.2f} | {r[1]:.2f} | {r[2]} | {r[3]} | {s[0]:.2f} | {s[1]:.2f} | {s[2]} | {s[3]} |")


def _episode(out: Path, name: str, duration_s: float, seed: int) -> tuple[float, int, int]:
    """Run one episode; (CPU-seconds of its process tree, bytes, ticks)."""
    folder = out / name
    sets = [a for kv in COMMON + LEVERS[name] for a in ("--set", kv)]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run([sys.executable, "-m", "cosim.cli", "run", SCENARIO, "--out", str(folder), "--duration",
                    str(duration_s), "--seed", str(seed), "-q", *sets], check=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    mcap = next(folder.glob("*.mcap"))
    from cosim.io.reader import open_episode

    with open_episode(mcap) as ep:
        ticks = ep.n_ticks
    return cpu, mcap.stat().st_size, ticks


def cost(args) -> None:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = {}
    for name in ("off", "on"):
        t0 = time.perf_counter()
        rows[name] = _episode(out, name, args.duration, args.seed)
        print(f"{name}: {rows[name][0]:.1f} CPU-s, {rows[name][1]:,} bytes, {rows[name][2]} ticks "
              f"({time.perf_counter() - t0:.0f} s wall)", flush=True)
    print("| levers | CPU-s per tick (whole process tree) | bytes per tick |")
    print("|---|---:|---:|")
    for name, (cpu, size, ticks) in rows.items():
        print(f"| {name} | {cpu / ticks:.2f} | {size / ticks:,.0f} |")
    (c0, b0, n0), (c1, b1, n1) = rows["off"], rows["on"]
    print(f"| on / off | {(c1 / n1) / (c0 / n0):.2f} | {(b1 / n1) / (b0 / n0):.2f} |")


def _sweep_points(folder: Path, tick: int) -> np.ndarray:
    from cosim.io.reader import open_episode

    with open_episode(next(folder.glob("*.mcap"))) as ep:
        return np.asarray(ep.tick(tick).points("vehicle_0").xyz, np.float64)


def picture(args) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    eps = Path(args.episodes)
    real = np.fromfile(args.kitti, np.float32).reshape(-1, 4)[:, :3].astype(np.float64)
    panels = [(_sweep_points(eps / "off", args.tick), "cosim hdl64e, levers off"),
              (_sweep_points(eps / "on", args.tick), "cosim hdl64e, self-occlusion + clutter (kitti)"),
              (real, f"KITTI {Path(args.kitti).name}, a real HDL-64E")]
    fig, axes = plt.subplots(1, 3, figsize=(18, 6.4), sharex=True, sharey=True)
    for ax, (p, title) in zip(axes, panels, strict=True):
        keep = np.hypot(p[:, 0], p[:, 1]) < 30.0
        ax.scatter(p[keep, 0], p[keep, 1], s=0.15, c=np.clip(p[keep, 2], -2.0, 1.5), cmap="turbo", vmin=-2.0, vmax=1.5)
        ax.set_title(f"{title}\n{len(p):,} points", fontsize=10)
        ax.set_xlim(-30, 30)
        ax.set_ylim(-30, 30)
        ax.set_aspect("equal")
        ax.set_xlabel("x [m] (LiDAR frame, forward)")
    axes[0].set_ylabel("y [m]")
    sm = plt.cm.ScalarMappable(cmap="turbo", norm=plt.Normalize(-2.0, 1.5))
    fig.colorbar(sm, ax=axes, label="z [m] above the sensor's horizontal", shrink=0.8)
    fig.savefig(args.out, dpi=110, bbox_inches="tight")
    print(f"wrote {args.out}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    g = sub.add_parser("gaps")
    g.add_argument("--kitti", required=True, help="folder of KITTI velodyne .bin scans")
    c = sub.add_parser("cost")
    c.add_argument("--out", required=True)
    c.add_argument("--duration", type=float, default=4.0)
    c.add_argument("--seed", type=int, default=48)
    p = sub.add_parser("picture")
    p.add_argument("--episodes", required=True, help="the --out folder of `cost`")
    p.add_argument("--kitti", required=True, help="one KITTI velodyne .bin scan")
    p.add_argument("--tick", type=int, default=10)
    p.add_argument("--out", required=True)
    args = ap.parse_args()
    {"gaps": gaps, "cost": cost, "picture": picture}[args.what](args)


if __name__ == "__main__":
    main()
