"""Export cost: CPU seconds per agent-frame and bytes for the AirV2X and OPV2V layouts, this code against an older one.

Generates one full-rig episode (the default scenario: 5 vehicles, 5 RSUs, 5 drones, 55 cameras at 1280 x 720
unless ``--set sensors.image_scale=...``), timing ``run_episode``, or takes ``--episode``; then runs
``cosim export`` on it once per format (AirV2X also with ``--masks`` when asked), each in its own process, and
prints per run the CPU seconds (the process and its workers, start-up included, as a user pays them), CPU
seconds per agent-frame, wall time, the export's size and that size over the episode's. With ``--before DIR``
(a checkout of an older cosim, e.g. ``git worktree add /work/scratch/base d83d980``) the same exports run with
that checkout's code too, interleaved with this one's, and the ratios after / before are printed: all in one
run, so they hold on a busy machine; run it under ``nice`` beside other work.

    nice -n 10 .venv/bin/python benchmarks/export.py --episode EP.mcap --before /work/scratch/base [--repeat 2]
    nice -n 10 .venv/bin/python benchmarks/export.py [--duration 1] [--workers 1] [--masks]
"""

from __future__ import annotations

import argparse
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from cosim.io import open_episode
from cosim.runner import run_episode
from cosim.scenario import load_scenario

REPO = Path(__file__).resolve().parents[1]
#: Runs ``cosim`` with the code of the checkout named by its first argument: the three installed roots
#: (pyproject.toml package-dir) are loaded from that checkout's folders, whatever the environment installed.
BOOT = """
import importlib.util, sys
root = sys.argv.pop(1)
modules = {}
for name, folder in (("cosim", "cosim"), ("cosim.sensors", "sensors"), ("cosim.exporters", "exporters")):
    spec = importlib.util.spec_from_file_location(name, f"{root}/{folder}/__init__.py",
                                                  submodule_search_locations=[f"{root}/{folder}"])
    modules[name] = importlib.util.module_from_spec(spec)
    sys.modules[name] = modules[name]
modules["cosim"].sensors, modules["cosim"].exporters = modules["cosim.sensors"], modules["cosim.exporters"]
for module in modules.values():
    module.__spec__.loader.exec_module(module)
from cosim.cli import main
sys.exit(main(sys.argv[1:]))
"""


def cpu_s() -> float:
    """CPU seconds of this process and its finished children (the export processes and their workers)."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def children_cpu_s() -> float:
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return kids.ru_utime + kids.ru_stime


def tree_size(root: Path) -> int:
    return sum(p.stat().st_size for p in root.rglob("*") if p.is_file())


def export(code: Path, episode: Path, fmt: str, masks: bool, workers: int, out: Path) -> tuple[float, float, int]:
    """``cosim export`` with ``code``'s modules in a fresh process: (CPU s, wall s, bytes written)."""
    cmd = [sys.executable, "-c", BOOT, str(code), "export", str(episode), "--format", fmt, "--out", str(out),
           "--workers", str(workers), "-q", *(["--masks"] if masks else [])]
    c0, t0 = children_cpu_s(), time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True)
    wall, cpu = time.perf_counter() - t0, children_cpu_s() - c0
    if r.returncode != 0:
        raise SystemExit(f"{code}: cosim export --format {fmt} failed:\n{r.stderr[-2000:]}")
    size = tree_size(out)
    shutil.rmtree(out)
    return cpu, wall, size


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default="scenarios/default.yaml")
    p.add_argument("--duration", type=float, default=1.0, help="simulated seconds")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--episode", help="export this episode instead of generating one (no generation ratio)")
    p.add_argument("--before", metavar="DIR", help="a checkout of older code to export the same episode with")
    p.add_argument("--masks", action="store_true", help="also AirV2X with --masks")
    p.add_argument("--repeat", type=int, default=1, help="runs of each export (the least CPU of them is kept)")
    args = p.parse_args()
    codes = {"after": REPO} | ({"before": Path(args.before).resolve()} if args.before else {})
    cases = [("airv2x", False), *([("airv2x", True)] if args.masks else []), ("opv2v", False)]
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
        episode_bytes = episode.stat().st_size
        with open_episode(episode) as ep:
            frames = ep.n_ticks * len(ep.agents)
            cameras = sum(len(ep.cameras(a)) for a in ep.agents)
            print(f"episode     {episode.name}: {ep.n_ticks} ticks x {len(ep.agents)} agents = {frames} agent-frames, "
                  f"{cameras} cameras, {episode_bytes / 2**20:.1f} MiB")
        if generated_s is not None:
            print(f"generation  {generated_s:.1f} s ({generated_s / frames:.3f} s per agent-frame), "
                  f"{generated_cpu_s:.1f} CPU s (workers included)")
        best: dict[tuple[str, str, bool], tuple[float, float, int]] = {}
        for _ in range(args.repeat):
            for fmt, masks in cases:
                for label, code in codes.items():  # interleaved, so both see the same machine
                    run = export(code, episode, fmt, masks, args.workers, tmp_path / f"{label}-{fmt}-{masks}")
                    key = (label, fmt, masks)
                    best[key] = min(best.get(key, run), run)
        print(f"{'format':<15} {'code':<7} {'CPU s':>7} {'CPU s/agent-frame':>18} {'wall s':>7} {'MiB':>7} "
              f"{'x episode':>9}")
        for fmt, masks in cases:
            name = fmt + (" --masks" if masks else "")
            for label in codes:
                cpu, wall, size = best[(label, fmt, masks)]
                line = (f"{name:<15} {label:<7} {cpu:7.1f} {cpu / frames:18.3f} {wall:7.1f} {size / 2**20:7.0f} "
                        f"{size / episode_bytes:9.2f}")
                if generated_s is not None:
                    line += f"  ({generated_s / wall:.2f}x faster than generation)"
                print(line)
            if "before" in codes:
                (ca, _, sa), (cb, _, sb) = best[("after", fmt, masks)], best[("before", fmt, masks)]
                print(f"{name:<15} after / before: CPU {ca / cb:.2f}x, bytes {sa / sb:.2f}x")


if __name__ == "__main__":
    main()
