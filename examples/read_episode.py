"""Read a cosim episode with the reader API (docs/episode_format.md, section 10).

    python examples/read_episode.py out/town_rural_night_s0.mcap
    python examples/read_episode.py            # writes and reads a small synthetic episode

Prints the episode's metadata, then per tick the labelled boxes, each agent's LiDAR points moved
into the map frame, and the front camera's image and depth statistics, decoding only what it asks for.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from cosim import cli_args
from cosim.io import open_episode


def describe(path: Path, max_ticks: int) -> None:
    with open_episode(path) as ep:
        m = ep.metadata
        print(
            f"{path}: scenario {ep.scenario!r}, seed {m['seed']}, {m['environment']}/{m['weather']}/"
            f"{m['lighting']}, {ep.n_ticks} ticks at {m['tick_hz']} Hz, format {ep.format_version}"
        )
        print(f"agents: {', '.join(ep.agents)}")
        lidar = [f"/{a}/lidar" for a in ep.agents if f"/{a}/lidar" in ep.topics]
        cams = {a: ep.cameras(a)[0] for a in ep.agents if ep.cameras(a)}
        wanted = ["/labels/objects", "/tf", *lidar]
        wanted += [f"/{a}/{c}/{k}" for a, c in cams.items() for k in ("image", "depth")]
        for tick in ep.ticks(topics=[t for t in wanted if t in ep.topics], stop=min(max_ticks, ep.n_ticks)):
            labels = tick.labels
            classes, counts = np.unique(np.array(labels.classes), return_counts=True)
            print(
                f"tick {tick.index:3d} t={tick.t_ns / 1e9:5.1f} s: {len(labels)} boxes "
                f"({', '.join(f'{n} {c}' for c, n in zip(classes, counts, strict=True))})"
            )
            for agent in ep.agents:
                parts = []
                if f"/{agent}/lidar" in tick:
                    cloud = tick.points(agent)
                    m_map = tick.transforms.to_root(cloud.frame_id)  # 4x4 map <- lidar
                    xyz_map = cloud.xyz @ m_map[:3, :3].T + m_map[:3, 3]
                    parts.append(f"{len(cloud)} points, mean height {xyz_map[:, 2].mean() if len(cloud) else 0:.1f} m")
                if agent in cams:
                    cam = cams[agent]
                    rgb = tick.image(agent, cam).array
                    depth_m = tick.depth(agent, cam).depth_m  # float32 metres, NaN where nothing was hit
                    hit = ~np.isnan(depth_m)
                    parts.append(
                        f"{cam} {rgb.shape[1]}x{rgb.shape[0]}, median depth "
                        f"{np.median(depth_m[hit]) if hit.any() else float('nan'):.1f} m"
                    )
                if parts:
                    print(f"    {agent:<10} " + "; ".join(parts))
            print(f"    decoded: {len(tick.decoded_topics)} of {len(tick.topics)} topics read")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("episode", nargs="?", type=cli_args.input_file, help="episode file (default: a synthetic one)")
    p.add_argument("--ticks", type=cli_args.positive_int, default=3, help="how many ticks to print (default 3)")
    args = p.parse_args()
    if args.episode:
        describe(Path(args.episode), args.ticks)
        return 0
    from cosim.io.synthetic import write_synthetic_episode

    with tempfile.TemporaryDirectory() as tmp:
        describe(write_synthetic_episode(Path(tmp) / "synthetic.mcap", ticks=5), args.ticks)
    return 0


if __name__ == "__main__":
    sys.exit(main())
