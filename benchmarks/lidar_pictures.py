"""Pictures of the LiDAR model for docs/img (synthetic town, noise on):

    PYTHONPATH=. .venv/bin/python benchmarks/lidar_pictures.py --out docs/img

- lidar_distortion.png: BEV of one 64-channel sweep from a car at 30 m/s, motion distortion on and off;
- lidar_rosette.png: the rosette pattern (100 000 points/s, 70.4 deg) accumulated over 0.1 s and 1 s;
- lidar_intensity.png: a sweep of a street coloured by intensity (markings, cars' reflectors, asphalt).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from cosim.sensors import SensorSuite
from cosim.sensors.lidar import rosette_pattern, sweep_ns
from cosim.sensors.synthetic import synthetic_scenario, synthetic_snapshot, synthetic_world

from cosim.geometry import quat_from_rpy
from cosim.scenario.model import (
    LidarSpec,
    RigSpec,
    SensorsSpec,
)
from cosim.snapshot import AgentState, WorldSnapshot


def _sweep(lidar: LidarSpec, speed_mps: float, seed: int = 0):
    rig = RigSpec(lidar=lidar, cameras=[], gnss=None, imu=None)
    sc = synthetic_scenario(name="pictures", sensors=SensorsSpec(vehicle=rig, bev=False))
    base = synthetic_snapshot(n_vehicles=0, n_rsus=0, n_drones=0)
    agent = AgentState("vehicle_0", "vehicle", (-20.0, -3.5, 0.02), quat_from_rpy(0.0, 0.0, 0.0),
                       (speed_mps, 0.0, 0.0))
    with SensorSuite(sc, synthetic_world(), encode_images=False) as suite:
        frames = suite.render(WorldSnapshot(5, 1_000_000_000, base.actors, (agent,)), np.random.default_rng(seed))
    return frames.agents["vehicle_0"].lidar


def distortion(out: Path) -> None:
    on = LidarSpec()
    fig, axes = plt.subplots(1, 2, figsize=(12, 6), sharex=True, sharey=True)
    for ax, spec, title in ((axes[0], on.model_copy(update={"motion_distortion": False}), "motion distortion off"),
                            (axes[1], on, "motion distortion on (30 m/s, 50 ms sweep)")):
        f = _sweep(spec, 30.0)
        keep = f.points[:, 2] > -1.6  # above the ground
        ax.scatter(f.points[keep, 0], f.points[keep, 1], s=0.3, c=f.t_offset_ns[keep] * 1e-6, cmap="viridis",
                   vmin=-50, vmax=0)
        ax.set_title(title)
        ax.set_xlim(-40, 40)
        ax.set_ylim(-40, 40)
        ax.set_aspect("equal")
        ax.set_xlabel("x [m] (sensor frame)")
    axes[0].set_ylabel("y [m]")
    sm = plt.cm.ScalarMappable(cmap="viridis", norm=plt.Normalize(-50, 0))
    fig.colorbar(sm, ax=axes, label="t_offset [ms]", shrink=0.8)
    fig.savefig(out / "lidar_distortion.png", dpi=90, bbox_inches="tight")
    plt.close(fig)


def rosette(out: Path) -> None:
    spec = LidarSpec(pattern="rosette", rotation_hz=10.0)
    period = sweep_ns(spec)
    fig, axes = plt.subplots(1, 2, figsize=(12, 6))
    for ax, frames, title in ((axes[0], 1, "0.1 s (one frame)"), (axes[1], 10, "1 s (ten frames)")):
        d = np.concatenate([rosette_pattern(spec, k * period).directions for k in range(1, frames + 1)])
        r = np.degrees(np.arccos(np.clip(d[:, 0], -1, 1)))
        phi = np.arctan2(d[:, 2], d[:, 1])
        ax.scatter(r * np.cos(phi), r * np.sin(phi), s=0.05 if frames > 1 else 0.2, c="k")
        ax.set_title(f"rosette, 100 000 points/s, {spec.rosette_fov_deg} deg: {title}")
        ax.set_aspect("equal")
        ax.set_xlabel("left [deg]")
    axes[0].set_ylabel("up [deg]")
    fig.savefig(out / "lidar_rosette.png", dpi=90, bbox_inches="tight")
    plt.close(fig)


def intensity(out: Path) -> None:
    f = _sweep(LidarSpec(horizontal_resolution_deg=0.2), 0.0)
    fig, ax = plt.subplots(figsize=(10, 8))
    order = np.argsort(f.intensity)
    sc = ax.scatter(f.points[order, 0], f.points[order, 1], s=0.4, c=f.intensity[order], cmap="inferno", vmin=0,
                    vmax=0.6)
    fig.colorbar(sc, ax=ax, label="intensity")
    ax.set_xlim(-45, 45)
    ax.set_ylim(-30, 30)
    ax.set_aspect("equal")
    ax.set_facecolor("#202020")
    ax.set_title("one sweep by intensity: markings, reflectors bright; asphalt dark")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    fig.savefig(out / "lidar_intensity.png", dpi=90, bbox_inches="tight")
    plt.close(fig)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("docs/img"))
    args = p.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    distortion(args.out)
    rosette(args.out)
    intensity(args.out)
    print(f"wrote lidar_distortion.png, lidar_rosette.png, lidar_intensity.png to {args.out}")


if __name__ == "__main__":
    main()
