"""How long ``cosim validate`` takes: wall and CPU seconds of :func:`cosim.io.validate.validate_episode`.

    .venv/bin/python benchmarks/validate_speed.py EPISODE [--repeats 2] [--no-pixels] [--profile 25]

Prints the wall and CPU (user + system of this process) seconds of each run (the first one also loads the
numba kernels of ``cosim.pixel_kernels`` from their on-disk cache), the episode's size and whether it
passed. ``--profile N`` prints the N functions with the most internal time of one more, profiled run.
Issue 36's target: at most 30 s for the default episode (``make run``) on a quiet 2-core machine.
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import time
from pathlib import Path

from cosim.io.validate import validate_episode


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("episode", type=Path)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--no-pixels", action="store_true", help="as cosim validate --no-pixels")
    ap.add_argument("--profile", type=int, default=0, metavar="N")
    args = ap.parse_args(argv)
    print(f"{args.episode}: {args.episode.stat().st_size / 2**20:.1f} MiB")
    for k in range(args.repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        report = validate_episode(args.episode, pixels=not args.no_pixels)
        print(f"run {k}: wall {time.perf_counter() - w0:.2f} s, CPU {time.process_time() - c0:.2f} s, "
              f"{'ok' if report.ok else f'{len(report.problems)} problems'}")
    if args.profile:
        prof = cProfile.Profile()
        prof.runcall(validate_episode, args.episode, pixels=not args.no_pixels)
        pstats.Stats(prof, stream=sys.stdout).sort_stats("tottime").print_stats(args.profile)
    return 0


if __name__ == "__main__":
    sys.exit(main())
