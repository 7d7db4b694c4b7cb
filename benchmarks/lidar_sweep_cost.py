"""CPU-seconds of the LiDAR-only learnability sweep (issue 36, item 5), whole process tree, with a reference.

    PYTHONPATH=. .venv/bin/python benchmarks/lidar_sweep_cost.py [--scale 0.25] [--workers 2] [--rounds 1]
        [--python /path/to/other/venv/bin/python]

Runs ``cosim batch sweeps/learnability.yaml --scale S --workers W`` into a temporary folder and prints the
user + system CPU-seconds of the batch and everything it started (episode processes, simulation workers,
netgenerate), per episode and per simulated second, and that figure scaled to the whole sweep (24 episodes
of 20 s). ``--python`` names the interpreter of another checkout (e.g. a venv with an older commit installed
editable): both are run ``--rounds`` times, alternating, and the ratio of the means is printed, so that load
changes on a shared machine hit both alike. Episodes differ in content between versions only where the
versions differ; the plan (episode ids, seeds, splits) is the sweep's.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SWEEP = ROOT / "sweeps" / "learnability.yaml"
FULL_EPISODES = 24


def run_once(python: str, scale: float, workers: int) -> dict:
    """One batch run: CPU-seconds of the tree, wall seconds, episodes and simulated seconds written."""
    with tempfile.TemporaryDirectory(prefix="lidar_sweep_") as tmp:
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        w0 = time.perf_counter()
        subprocess.run([python, "-m", "cosim.cli", "batch", str(SWEEP), "--out", tmp, "--scale", str(scale),
                        "--workers", str(workers), "-q"], check=True, cwd=tmp)
        wall = time.perf_counter() - w0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        done = [json.loads(line) for p in Path(tmp).glob("manifest*.jsonl") for line in p.read_text().splitlines()]
        done = [d for d in done if d.get("status") == "done"]
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"cpu_s": cpu, "wall_s": wall, "episodes": len(done), "sim_s": sum(d["duration_s"] for d in done)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scale", type=float, default=0.25, help="share of the sweep's 24 episodes")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--python", help="a reference interpreter (another checkout's venv)")
    args = ap.parse_args()
    runs: dict[str, list[dict]] = {"this": [], "reference": []}
    for _ in range(args.rounds):
        for name, py in (("this", sys.executable), ("reference", args.python)):
            if py is None:
                continue
            r = run_once(py, args.scale, args.workers)
            runs[name].append(r)
            print(f"{name:9s} {r['episodes']} episodes, {r['sim_s']:.0f} s simulated: {r['cpu_s']:.1f} CPU-s "
                  f"({r['cpu_s'] / max(r['episodes'], 1):.1f} per episode, {r['cpu_s'] / max(r['sim_s'], 1):.2f} "
                  f"per simulated second), wall {r['wall_s']:.0f} s; whole sweep "
                  f"{r['cpu_s'] / max(r['episodes'], 1) * FULL_EPISODES:.0f} CPU-s", flush=True)
    mean = {k: sum(r["cpu_s"] for r in v) / len(v) for k, v in runs.items() if v}
    if "reference" in mean:
        print(f"reference / this: {mean['reference'] / mean['this']:.2f}x CPU-seconds")


if __name__ == "__main__":
    main()
