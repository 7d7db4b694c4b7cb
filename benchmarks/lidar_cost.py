"""Cost of the LiDAR model's options, measured against each other in one run (ratios only):

    PYTHONPATH=. .venv/bin/python benchmarks/lidar_cost.py [--repeats 3] [--speed 12]

Rig: the synthetic junction (``cosim.sensors.synthetic``) with 5 vehicles, 5 RSUs and 5 drones, each with
the paper's 64-channel LiDAR and nothing else, road users moving at ``--speed`` (drones half). Variants,
interleaved and repeated (the minimum of each is kept): snapshot sweep (``motion_distortion: false``),
motion distortion (the default), motion distortion with dual returns, and a rosette (100 000 points/s)
on every drone. Prints seconds per frame of all 15 LiDARs and each variant's ratio to the snapshot sweep.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np
from cosim.sensors import SensorSuite
from cosim.sensors.synthetic import synthetic_scenario, synthetic_snapshot, synthetic_world

from cosim.scenario.model import (
    AgentsSpec,
    LidarSpec,
    RigSpec,
    Scenario,
    SensorsSpec,
    default_drone_rig,
    default_rsu_rig,
    default_vehicle_rig,
)


def _scenario(**lidar) -> Scenario:
    rigs = {}
    for kind, rig in (("vehicle", default_vehicle_rig()), ("rsu", default_rsu_rig()), ("drone", default_drone_rig())):
        spec = rig.lidar.model_copy(update=lidar.get(kind, lidar.get("all", {})))
        rigs[kind] = RigSpec(lidar=spec, cameras=[], gnss=None, imu=None)
    return synthetic_scenario(name="lidar_cost", vehicles=5, rsus=5, drones=AgentsSpec().drones,
                              sensors=SensorsSpec(bev=False, **rigs))


def _moving(snap, speed: float):
    import math

    from cosim.geometry import rpy_from_quat

    def vel(q, s):
        yaw = rpy_from_quat(q)[2]
        return (s * math.cos(yaw), s * math.sin(yaw), 0.0)

    actors = tuple(dataclasses.replace(a, velocity_mps=vel(a.rotation, speed if a.cls != "drone" else speed / 2))
                   for a in snap.actors)
    agents = tuple(dataclasses.replace(a, velocity_mps=vel(a.rotation, speed if a.kind == "vehicle" else
                                                           (speed / 2 if a.kind == "drone" else 0.0)))
                   for a in snap.agents)
    return dataclasses.replace(snap, actors=actors, agents=agents)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--speed", type=float, default=12.0, help="road users' speed [m/s]")
    args = ap.parse_args()
    world = synthetic_world()
    variants = {
        "snapshot sweep": _scenario(all={"motion_distortion": False}),
        "motion distortion": _scenario(),
        "distortion + dual returns": _scenario(all={"dual_returns": True}),
        "drones with rosettes": _scenario(drone={"pattern": "rosette", "rotation_hz": 10.0,
                                                 "mount": LidarSpec().mount.model_copy(
                                                     update={"xyz_m": (0.0, 0.0, -0.2), "rpy_deg": (0.0, 90.0, 0.0)})}),
    }
    suites = {k: SensorSuite(sc, world, encode_images=False) for k, sc in variants.items()}
    snap = _moving(synthetic_snapshot(5, 5, 5), args.speed)
    points = {}
    for k, s in suites.items():  # warm: static hits of the RSUs, BVHs
        f = s.render(snap, np.random.default_rng(0))
        points[k] = sum(a.lidar.n_points for a in f.agents.values())
    best = {k: float("inf") for k in suites}
    for _ in range(args.repeats):
        for k, s in suites.items():
            t0 = time.perf_counter()
            s.render(snap, np.random.default_rng(0))
            best[k] = min(best[k], time.perf_counter() - t0)
    base = best["snapshot sweep"]
    for k in suites:
        print(f"{k:<28} {best[k]:7.3f} s per frame ({points[k]:>7} points)   {best[k] / base:5.2f}x the snapshot sweep")
    for s in suites.values():
        s.close()


if __name__ == "__main__":
    main()
