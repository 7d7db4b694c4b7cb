"""How long ``cosim render`` takes: wall and CPU seconds of :func:`cosim.io.render.render_episode`.

    .venv/bin/python benchmarks/render_speed.py EPISODE [--ticks 0,7,14] [--agents vehicle_0 ...] [--dpi 80]
                                                [--out DIR] [--profile 25]

Ticks as ``cosim render`` takes them (default first, middle, last). Prints the time to open the episode,
then the wall and CPU (user + system of this process) seconds of ``render_episode``, split into contact
sheets and BEV plots (the BEV plots are timed again alone on the same ticks afterwards: the split is
an estimate), and the files written. ``--profile N`` prints the N functions with
the most cumulative time of a second, profiled run. The pictures go to a temporary folder unless ``--out`` is
given. On a shared machine compare wall with CPU: a wall time well above CPU means the run waited for cores.
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from cosim.io.reader import open_episode
from cosim.io.render import bev_plot, layout_polygons, render_episode
from cosim.tools import parse_ticks

T = TypeVar("T")


def timed(fn: Callable[..., T], *args: Any, **kwargs: Any) -> tuple[T, float, float]:
    """(result, wall s, CPU s) of ``fn(*args, **kwargs)``."""
    w0, c0 = time.perf_counter(), time.process_time()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - w0, time.process_time() - c0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("episode", type=Path)
    p.add_argument("--ticks", help="as cosim render: '0,10,20', '0:50:10', '-1' (default first, middle, last)")
    p.add_argument("--agents", nargs="*", help="default: every agent with cameras")
    p.add_argument("--dpi", type=int, default=80)
    p.add_argument("--out", type=Path, help="where the pictures go (default a temporary folder)")
    p.add_argument("--profile", type=int, metavar="N", default=0, help="also print a profile's top N functions")
    args = p.parse_args(argv)

    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp)
        ep, wall, cpu = timed(open_episode, args.episode)
        with ep:
            print(f"open: {wall:.2f} s wall, {cpu:.2f} s CPU")
            ticks = parse_ticks(args.ticks, ep.n_ticks)
            written, wall, cpu = timed(render_episode, ep, out, ticks, agents=args.agents, dpi=args.dpi)
            sheets = [f for f in written if f.name.startswith("contact_")]
            size = sum(f.stat().st_size for f in written)
            print(f"render_episode: {wall:.2f} s wall, {cpu:.2f} s CPU for ticks {ticks}: {len(sheets)} contact sheets"
                  f" and {len(written) - len(sheets)} BEV plots, {size / 1e6:.1f} MB")
            bev_wall = bev_cpu = 0.0
            layout = layout_polygons(ep)
            for k in ticks:
                tick = ep.tick(k, topics=[t for t in ep.topics if t == "/tf" or t == "/labels/objects"
                                          or t.endswith("/lidar")])
                _, w, c = timed(bev_plot, ep, tick, out / f"bev_t{k:04d}.png", args.dpi, layout)
                bev_wall, bev_cpu = bev_wall + w, bev_cpu + c
            print(f"  BEV plots timed again alone: {bev_wall:.2f} s wall, {bev_cpu:.2f} s CPU"
                  f" ({bev_wall / max(len(ticks), 1):.2f} s each); so about {wall - bev_wall:.2f} s wall went to"
                  f" reading ticks, imports and the contact sheets")
            if args.profile:
                prof = cProfile.Profile()
                prof.runcall(render_episode, ep, out, ticks, agents=args.agents, dpi=args.dpi)
                pstats.Stats(prof, stream=sys.stdout).sort_stats("cumulative").print_stats(args.profile)
    return 0


if __name__ == "__main__":
    sys.exit(main())
