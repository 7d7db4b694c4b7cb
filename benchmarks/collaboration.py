"""The collaboration numbers of issue 34 for every shipped scenario, before (``agents.layout: spread``) and after
(``cooperative``), measured in one run (docs/evaluation.md, "Collaboration").

    nice -n 10 .venv/bin/python -m benchmarks.collaboration [--work DIR] [--scenarios NAME ...]
        [--duration S] [--sensors none|lidar] [--workers N]

Every scenario runs twice, once per layout, with ``cosim run NAME --set agents.layout=L`` (labels only with
``--sensors none``, the default: the collaborators in range need only the agents' poses; LiDAR only, no
cameras and no BEV grids, with ``--sensors lidar``: then the objects' visibility too). Per scenario and layout
it prints the share of ego-ticks with >= 1 and >= 2 collaborators in range (any kind) and with a drone in
range, and with ``lidar`` the coverage points drones and RSUs add over the other agents (default rule >= 1
LiDAR point, strict rule >= 5 points) and the share of objects seen by nobody. Episodes already in
``--work`` are reused (delete it after a code change). Labels only, all 18 shipped scenarios: about 5 min on
2 cores; LiDAR only costs about 10 s of 2 cores per simulated second of a rural scenario.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
LAYOUTS = ("spread", "cooperative")
LIDAR_ONLY = ("sensors.vehicle.cameras=[]", "sensors.rsu.cameras=[]", "sensors.drone.cameras=[]", "sensors.bev=false")


def episode(work: Path, scenario: str, layout: str, sensors: str, duration: float | None) -> Path:
    """Run (or reuse) one episode; its file."""
    out = work / sensors / layout / scenario
    found = sorted(out.glob("*.mcap"))
    if found:
        return found[0]
    args = ["run", scenario, "--out", str(out), "-q", "--set", f"agents.layout={layout}"]
    args += ["--no-sensors"] if sensors == "none" else [a for s in LIDAR_ONLY for a in ("--set", s)]
    if duration is not None:
        args += ["--duration", f"{duration:g}"]
    print("$ cosim " + " ".join(args), file=sys.stderr, flush=True)
    done = subprocess.run([sys.executable, "-m", "cosim.cli", *args], cwd=REPO, stdout=subprocess.DEVNULL)
    if done.returncode != 0:
        raise SystemExit(f"cosim {' '.join(args)} failed with exit status {done.returncode}")
    (path,) = sorted(out.glob("*.mcap"))
    return path


def numbers(path: Path, sensors: str) -> dict[str, float]:
    """The collaboration numbers of one episode (see the module doc)."""
    from cosim.eval.collaboration import compute_collaboration
    from cosim.eval.coverage import compute_coverage
    from cosim.eval.dataset import VisibilityRule, load_dataset

    refs = load_dataset(path)
    c = compute_collaboration(refs)[("overall", "all")]
    out = {"ego_ticks": c.ego_ticks, "any1": c.share("any", 1), "any2": c.share("any", 2),
           "drone1": c.share("drone", 1)}
    if sensors == "lidar":
        for tag, points in (("", 1), ("_strict", 5)):
            rule = VisibilityRule(points, 10**9)  # LiDAR only: no pixels
            cov = compute_coverage(refs, rule).counts[("overall", "all")]
            out[f"drones_add{tag}"] = cov.recall("all") - cov.recall("vehicles+rsus")
            out[f"rsus_add{tag}"] = cov.recall("all") - cov.recall("vehicles+drones")
            out[f"nobody{tag}"] = 100.0 - cov.recall("all")
    return out


def measure(work: Path, scenarios: list[str], sensors: str, duration: float | None, workers: int = 1
            ) -> dict[tuple[str, str], dict[str, float]]:
    """(scenario, layout) -> :func:`numbers`, every episode run first (``workers`` at a time)."""
    jobs = [(s, lay) for s in scenarios for lay in LAYOUTS]
    with ThreadPoolExecutor(max(1, workers)) as pool:
        paths = list(pool.map(lambda j: episode(work, j[0], j[1], sensors, duration), jobs))
    return {j: numbers(p, sensors) for j, p in zip(jobs, paths, strict=True)}


def range_table(res: dict[tuple[str, str], dict[str, float]]) -> str:
    """Markdown: per scenario, >= 2 and >= 1 collaborators in range and a drone in range, spread -> cooperative."""
    lines = ["| scenario | ego-ticks | >= 2 in range (%) spread | cooperative | >= 1 in range spread | cooperative "
             "| drone in range spread | cooperative |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for s in dict.fromkeys(k[0] for k in res):
        a, b = res[(s, "spread")], res[(s, "cooperative")]
        lines.append(f"| {s} | {b['ego_ticks']} | {a['any2']:.1f} | {b['any2']:.1f} | {a['any1']:.1f} | "
                     f"{b['any1']:.1f} | {a['drone1']:.1f} | {b['drone1']:.1f} |")
    return "\n".join(lines) + "\n"


def coverage_table(res: dict[tuple[str, str], dict[str, float]]) -> str:
    """Markdown: per scenario, drones add / RSUs add / seen by nobody (default and strict rule), spread -> coop."""
    lines = ["| scenario | layout | drones add | RSUs add | seen by nobody (%) | drones add, >= 5 points "
             "| RSUs add, >= 5 points | seen by nobody, >= 5 points (%) |", "|---|---|---:|---:|---:|---:|---:|---:|"]
    for (s, layout), r in res.items():
        lines.append(f"| {s} | {layout} | {r['drones_add']:.1f} | {r['rsus_add']:.1f} | {r['nobody']:.1f} | "
                     f"{r['drones_add_strict']:.1f} | {r['rsus_add_strict']:.1f} | {r['nobody_strict']:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    from cosim.scenario.loader import shipped_scenarios

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, help="folder for the episodes (kept; default: a temporary one)")
    ap.add_argument("--scenarios", nargs="+", metavar="NAME", help="shipped scenario names (default: all)")
    ap.add_argument("--duration", type=float, help="simulated seconds (default: each scenario's own)")
    ap.add_argument("--sensors", choices=("none", "lidar"), default="none")
    ap.add_argument("--workers", type=int, default=1, help="episodes run at once (default 1)")
    args = ap.parse_args(argv)
    scenarios = args.scenarios or [name for name, _ in shipped_scenarios()]
    with tempfile.TemporaryDirectory() as tmp:
        res = measure(args.work or Path(tmp), scenarios, args.sensors, args.duration, args.workers)
        print(range_table(res))
        if args.sensors == "lidar":
            print(coverage_table(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
