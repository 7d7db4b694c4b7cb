"""Export speed: seconds per agent-frame for the AirV2X and OPV2V layouts, against generation time.

Generates one full-rig episode (the default scenario: 5 vehicles, 5 RSUs, 5 drones, 55 cameras at
1280 x 720 unless ``--set sensors.image_scale=...``), timing ``run_episode``; then exports it in each
format (AirV2X also with ``--masks``) with ``--workers`` processes (one by default) and prints, per
format, the wall time, seconds per agent-frame, CPU seconds, the export's size, and how many times
faster than generation the export was. All in one run, so the ratios hold on a busy machine; run it
under ``nice`` beside other work.

    nice -n 10 .venv/bin/python benchmarks/export.py [--duration 2] [--workers 1] [--episode EP.mcap]
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

from cosim.exporters.export import ExportOptions, run_export

from cosim.io import open_episode
from cosim.runner import run_episode
from cosim.scenario import load_scenario


def cpu_s() -> float:
    """CPU seconds of this process and its finished children (the workers, export processes)."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def tree_size(root: Path) -> int:
    return sum(p.stat().st_size for p in root.rglob("*") if p.is_file())


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default="scenarios/default.yaml")
    p.add_argument("--duration", type=float, default=2.0, help="simulated seconds")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--episode", help="export this episode instead of generating one (no generation ratio)")
    args = p.parse_args()
    with tempfile.TemporaryDirectory(prefix="cosim-export-bench-") as tmp:
        tmp_path = Path(tmp)
        generated_s = None
        if args.episode:
            episode = Path(args.episode)
        else:
            loaded = load_scenario(args.scenario, [f"duration_s={args.duration}", *args.set])
            t0, c0 = time.perf_counter(), cpu_s()
            result = run_episode(loaded, tmp_path / "episode")
            generated_s, generated_cpu_s = time.perf_counter() - t0, cpu_s() - c0
            episode = result.path
        with open_episode(episode) as ep:
            frames = ep.n_ticks * len(ep.agents)
            cameras = sum(len(ep.cameras(a)) for a in ep.agents)
            print(f"episode     {episode.name}: {ep.n_ticks} ticks x {len(ep.agents)} agents = {frames} agent-frames, "
                  f"{cameras} cameras, {episode.stat().st_size / 2**20:.1f} MiB")
        if generated_s is not None:
            print(f"generation  {generated_s:.1f} s ({generated_s / frames:.3f} s per agent-frame), "
                  f"{generated_cpu_s:.1f} CPU s (workers included)")
        for fmt, masks in (("airv2x", False), ("airv2x", True), ("opv2v", False)):
            out = tmp_path / f"export-{fmt}-{masks}"
            t0, c0 = time.perf_counter(), cpu_s()
            r = run_export(episode, fmt, out, ExportOptions(masks=masks), workers=args.workers)
            wall, cpu = time.perf_counter() - t0, cpu_s() - c0
            name = fmt + (" --masks" if masks else "")
            line = (f"{name:<15} {wall:.1f} s with {args.workers} worker(s): {wall / r.agent_frames:.3f} s per "
                    f"agent-frame, {cpu:.1f} CPU s, {tree_size(out) / 2**20:.0f} MiB")
            if generated_s is not None:
                line += f"; {generated_s / wall:.2f}x faster than generation"
            print(line)


if __name__ == "__main__":
    main()
