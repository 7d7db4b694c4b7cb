"""Peak memory of ``cosim run``: the whole process tree (runner, simulation workers, render processes).

    .venv/bin/python benchmarks/memory.py [--scenario scenarios/default.yaml] [-- extra cosim run args]

Starts ``cosim run`` (by default what ``make run`` generates: the full paper rig, 3 s) into a temporary
folder and samples every process of its tree every 50 ms. Prints the peak of the summed resident set
sizes (RSS, what ``/usr/bin/time -v`` reports per process, but for the whole tree at once), the
runner's own peak RSS, and the peak of the summed proportional set sizes (PSS: pages shared between
processes, such as render processes' shared-memory frames, counted once in all; read from
``/proc/PID/smaps_rollup`` every 10th sample), and each process's own peak RSS with the tree's
makeup at its peak (by process name). The target of issue 26 is at most 1.5 GB for the tree.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import psutil

ROOT = Path(__file__).resolve().parents[1]
PERIOD_S = 0.05


def _pss_bytes(pid: int) -> int:
    """Proportional set size of one process (0 when it is gone or unreadable)."""
    try:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            for line in f:
                if line.startswith("Pss:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def measure(cmd: list[str]) -> dict[str, float]:
    """Run ``cmd`` and sample its process tree until it ends; peaks in bytes, wall time in seconds."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    root = psutil.Process(proc.pid)
    peak_tree = peak_root = peak_pss = 0
    peaks: dict[str, int] = {}  # each process's own peak RSS, by name
    at_peak: dict[str, int] = {}  # the tree at its peak
    n = 0
    while proc.poll() is None:
        try:
            tree = [root, *root.children(recursive=True)]
        except psutil.NoSuchProcess:
            break
        total = 0
        now: dict[str, int] = {}
        for p in tree:
            try:
                rss = p.memory_info().rss
                name = "runner" if p.pid == root.pid else _name(p)
            except psutil.Error:
                continue
            total += rss
            now[name] = now.get(name, 0) + rss
            peaks[name] = max(peaks.get(name, 0), rss)
            if p.pid == root.pid:
                peak_root = max(peak_root, rss)
        if total > peak_tree:
            peak_tree, at_peak = total, now
        if n % 10 == 0:
            peak_pss = max(peak_pss, sum(_pss_bytes(p.pid) for p in tree))
        n += 1
        time.sleep(PERIOD_S)
    out = proc.stdout.read() if proc.stdout else ""
    if proc.wait() != 0:
        sys.exit(f"cosim run failed (exit {proc.returncode}):\n{out}")
    return {"tree_rss": peak_tree, "root_rss": peak_root, "tree_pss": peak_pss, "wall_s": time.perf_counter() - t0,
            "samples": n, "peaks": peaks, "at_peak": at_peak}


def _name(p: psutil.Process) -> str:
    """A child's role: its multiprocessing name (``cosim-traffic``, ...) or its program's name."""
    cmd = p.cmdline()
    if any("multiprocessing.resource_tracker" in c for c in cmd):
        return "resource tracker"
    try:
        with open(f"/proc/{p.pid}/comm") as f:
            comm = f.read().strip()
    except OSError:
        comm = p.name()
    return comm if comm.startswith("cosim") else p.name()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenario", type=Path, default=ROOT / "scenarios" / "default.yaml")
    ap.add_argument("extra", nargs="*", help="more arguments for cosim run (after --)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [str(Path(sys.executable).parent / "cosim"), "run", str(args.scenario), "--out", tmp, *args.extra]
        r = measure(cmd)
    gb = 1e9
    print(f"cosim run {args.scenario.name} {' '.join(args.extra)}: wall {r['wall_s']:.1f} s, {r['samples']} samples")
    print(f"RESULT peak RSS of the process tree {r['tree_rss'] / gb:.2f} GB (target <= 1.5); runner alone "
          f"{r['root_rss'] / gb:.2f} GB; peak PSS of the tree {r['tree_pss'] / gb:.2f} GB")
    print("at the tree's peak: " + ", ".join(f"{k} {v / gb:.2f}" for k, v in sorted(r["at_peak"].items())) + " GB")
    print("each one's own peak: " + ", ".join(f"{k} {v / gb:.2f}" for k, v in sorted(r["peaks"].items())) + " GB")


if __name__ == "__main__":
    main()
