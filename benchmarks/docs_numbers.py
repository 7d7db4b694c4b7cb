"""Regenerate the number tables of docs/*.md from real runs and diff them against the docs.

    nice -n 10 .venv/bin/python -m benchmarks.docs_numbers [--update] [--work DIR] [--only NAME ...]

Every documented table sits between two HTML comments in its .md file, with the command that
produces it written just above:

    <!-- docs_numbers:NAME -->
    | ... the table ... |
    <!-- /docs_numbers:NAME -->

and this script has one producer function per NAME (``PRODUCERS``) that runs the documented
commands (``cosim batch``, ``cosim coverage``, ``cosim eval``, ``cosim run``, ``cosim comm``) and
returns the text between the markers. Without ``--update`` it prints a unified diff of the docs
against the fresh text and exits 1 when they differ (0 when they agree); with ``--update`` it
rewrites the blocks in place. Runs go into a temporary folder, or into ``--work DIR``, where the
episodes already written are reused (delete the folder after a code change). The whole set took
6 min 15 s on 2 cores shared with a test run, most of it the ``sweeps/eval_small.yaml`` batch.
"""

from __future__ import annotations

import argparse
import difflib
import json
import re
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
MARKER = re.compile(r"^<!-- (/?)docs_numbers:(\S*) -->$", re.M)
NAME = re.compile(r"^[a-z0-9_]+$")

EVAL_SWEEP = "sweeps/eval_small.yaml"
EVAL_EPISODES = 6
COMM_SCENARIO = "scenarios/town_urban_day_clear.yaml"
SETTINGS = ("ego", "vehicles", "vehicles+rsus", "vehicles+drones", "all")
#: (position sigma m, yaw sigma deg) of the oracle-noise ladder in docs/evaluation.md
NOISE_LADDER = ((0, 0), (0.1, 1), (0.2, 2), (0.4, 4), (0.8, 8))

PRODUCERS: dict[str, Callable[[Work], str]] = {}


class MarkerError(ValueError):
    """A docs file whose markers are not well formed (unpaired, nested, repeated, badly named)."""


def blocks(text: str, where: str = "") -> list[tuple[str, int, int]]:
    """The marked blocks of one file: (name, start, end) with text[start:end] the body between the
    opening marker's line and the closing marker."""
    out: list[tuple[str, int, int]] = []
    open_: tuple[str, int] | None = None
    for m in MARKER.finditer(text):
        closing, name = m.group(1) == "/", m.group(2)
        line = text.count("\n", 0, m.start()) + 1
        if not NAME.match(name):
            raise MarkerError(f"{where}:{line}: marker name {name!r} is not [a-z0-9_]+")
        if not closing:
            if open_ is not None:
                raise MarkerError(f"{where}:{line}: docs_numbers:{name} opens inside docs_numbers:{open_[0]}")
            open_ = (name, m.end() + 1)
            continue
        if open_ is None or open_[0] != name:
            raise MarkerError(f"{where}:{line}: /docs_numbers:{name} closes a block that is not open")
        if any(b[0] == name for b in out):
            raise MarkerError(f"{where}:{line}: docs_numbers:{name} appears twice")
        out.append((name, open_[1], m.start()))
        open_ = None
    if open_ is not None:
        raise MarkerError(f"{where}: docs_numbers:{open_[0]} is never closed")
    if text.count("<!-- docs_numbers:") + text.count("<!-- /docs_numbers:") != len(MARKER.findall(text)):
        raise MarkerError(f"{where}: a docs_numbers marker is not alone on its line as <!-- docs_numbers:NAME -->")
    return out


def doc_blocks() -> dict[Path, list[tuple[str, int, int]]]:
    """Every marked block of docs/*.md, per file (files without markers left out)."""
    found = {p: blocks(p.read_text(encoding="utf-8"), str(p.relative_to(REPO))) for p in sorted(DOCS.glob("*.md"))}
    return {p: b for p, b in found.items() if b}


def producer(name: str):
    def add(fn: Callable[[Work], str]) -> Callable[[Work], str]:
        PRODUCERS[name] = fn
        return fn

    return add


class Work:
    """The runs the producers share, each made once, in ``root``."""

    def __init__(self, root: Path) -> None:
        self.root = root

    def cosim(self, *args: str) -> str:
        """Run ``cosim ARGS`` from the repository root; its stdout."""
        cmd = [sys.executable, "-m", "cosim.cli", *args]
        print("$ cosim " + " ".join(args), file=sys.stderr, flush=True)
        done = subprocess.run(cmd, cwd=REPO, stdout=subprocess.PIPE, text=True)
        if done.returncode != 0:
            raise SystemExit(f"cosim {' '.join(args)} failed with exit status {done.returncode}")
        return done.stdout

    def eval_small(self) -> Path:
        """The ``sweeps/eval_small.yaml`` batch (kept when all its episodes are there)."""
        out = self.root / "eval_small"
        if len(list(out.rglob("*.mcap"))) < EVAL_EPISODES:
            self.cosim("batch", EVAL_SWEEP, "--out", str(out), "--workers", "1")
        return out

    def json(self, folder: Path, stem: str, *args: str) -> dict:
        """``<folder>/<stem>.json`` of a ``cosim coverage`` / ``cosim eval`` run (kept once written)."""
        path = folder / f"{stem}.json"
        if not path.exists():
            self.cosim(*args, "--out", str(folder))
        return json.loads(path.read_text(encoding="utf-8"))


def _table(report: dict, name: str) -> dict:
    return next(t for t in report["tables"] if t["name"] == name)


def _markdown(columns: list[str], rows: list[list]) -> str:
    def cell(v) -> str:
        return "n/a" if v is None else f"{v:.1f}" if isinstance(v, float) else str(v)

    lines = ["| " + " | ".join(columns) + " |",
             "|" + "|".join("---" if i == 0 else "---:" for i in range(len(columns))) + "|"]
    return "\n".join(lines + ["| " + " | ".join(cell(c) for c in row) + " |" for row in rows]) + "\n"


def _coverage(work: Work, folder: str, *rule: str) -> str:
    """Coverage rows without the ego-ticks column: overall, then per lighting, weather, environment, strategy."""
    data = work.eval_small()
    report = work.json(work.root / folder, "coverage", "coverage", str(data), *rule)
    rows = []
    columns: list[str] = []
    for breakdown in ("overall", "lighting", "weather", "environment", "strategy"):
        t = _table(report, f"coverage_{breakdown}")
        columns = [c for c in t["columns"] if c != "ego-ticks"]
        keep = [i for i, c in enumerate(t["columns"]) if c != "ego-ticks"]
        rows += [[r[i] for i in keep] for r in t["rows"]]
    return _markdown(columns, rows)


@producer("eval_coverage")
def eval_coverage(work: Work) -> str:
    """docs/evaluation.md: ``cosim coverage out/eval_small`` (default rule)."""
    return _coverage(work, "coverage")


@producer("eval_coverage_strict")
def eval_coverage_strict(work: Work) -> str:
    """docs/evaluation.md: ``cosim coverage out/eval_small --min-points 5 --min-pixels 20``."""
    return _coverage(work, "coverage5", "--min-points", "5", "--min-pixels", "20")


def _oracle_overall(work: Work, folder: str, *args: str) -> dict[str, list]:
    data = work.eval_small()
    report = work.json(work.root / folder, "eval", "eval", "--gt", str(data), "--baseline", "oracle-noise",
                       "--metric", "detection", "--no-bev", *args)
    t = _table(report, "overall")
    return {r[0]: r for r in t["rows"]}


@producer("eval_oracle_ladder")
def eval_oracle_ladder(work: Work) -> str:
    """docs/evaluation.md: the oracle-noise baseline, setting ``all``, ``--visible-only``, growing noise."""
    rows = []
    for pos, yaw in NOISE_LADDER:
        r = _oracle_overall(work, f"oracle_visible_{pos}_{yaw}", "--visible-only", "--pos-sigma-m", str(pos),
                            "--yaw-sigma-deg", str(yaw))["all"]
        rows.append([f"{pos}, {yaw}", r[2], r[4], r[5], r[6]])
    return _markdown(["position sigma (m), yaw sigma (deg)", "GT boxes", "AP30", "AP50", "AP70"], rows)


@producer("eval_oracle")
def eval_oracle(work: Work) -> str:
    """docs/evaluation.md: the oracle-noise baseline on all objects, one row per collaboration setting."""
    by = _oracle_overall(work, "oracle", "--pos-sigma-m", "0.2", "--yaw-sigma-deg", "2", "--size-sigma", "0.05")
    return _markdown(["agents", "GT boxes", "AP30", "AP50", "AP70"],
                     [[s, by[s][2], by[s][4], by[s][5], by[s][6]] for s in SETTINGS if s in by])


#: docs/evaluation.md "Collaboration": the LiDAR-only part's scenarios and simulated seconds (LiDAR on every
#: agent costs about 10 s of 2 cores per simulated second, so not all 18 scenarios at their full length)
COLLAB_LIDAR = (("town_rural_night", "town_rural_day_foggy", "strategy_hover"), 8.0)


@producer("collab_range")
def collab_range(work: Work) -> str:
    """docs/evaluation.md: ``python -m benchmarks.collaboration`` (labels only, every shipped scenario)."""
    from benchmarks.collaboration import measure, range_table
    from cosim.scenario.loader import shipped_scenarios

    return range_table(measure(work.root / "collab", [n for n, _ in shipped_scenarios()], "none", None))


@producer("collab_coverage")
def collab_coverage(work: Work) -> str:
    """docs/evaluation.md: ``python -m benchmarks.collaboration --sensors lidar --duration 8 --scenarios ...``."""
    from benchmarks.collaboration import coverage_table, measure

    names, duration = COLLAB_LIDAR
    return coverage_table(measure(work.root / "collab", list(names), "lidar", duration))


@producer("comm_urban")
def comm_urban(work: Work) -> str:
    """docs/comm.md: ``cosim comm`` on the shipped urban scenario without sensors."""
    out = work.root / "comm"
    episode = out / f"{Path(COMM_SCENARIO).stem}_s0.mcap"
    if not episode.exists():
        work.cosim("run", COMM_SCENARIO, "--no-sensors", "--out", str(out))
    return "```\n" + work.cosim("comm", str(episode)).rstrip("\n") + "\n```\n"


PEDESTRIANS = 200  # the keys ped_0000 .. ped_0199, as SUMO names the pedestrians `cosim run` labels


@producer("pedestrian_boxes")
def pedestrian_boxes(work: Work | None = None) -> str:
    """docs/events.md: the label boxes of pedestrians (``people.posed_box``, the box the traffic worker writes),
    walking at 1.4 m/s at four gait phases and standing; min / median / max per dimension. Runs nothing."""
    import numpy as np
    from cosim.sensors.assets import people

    keys = [f"ped_{i:04d}" for i in range(PEDESTRIANS)]
    cases = {"walking, 1.4 m/s (4 gait phases)": [(k, ph, 1.4) for k in keys for ph in (0.0, 0.25, 0.5, 0.75)],
             "standing": [(k, 0.0, 0.0) for k in keys]}
    rows = []
    for label, args in cases.items():
        sizes = np.array([people.posed_box(*a)[0] for a in args])
        rows.append([label, *(f"{lo:.2f} / {med:.2f} / {hi:.2f}" for lo, med, hi in
                               zip(sizes.min(0), np.median(sizes, 0), sizes.max(0), strict=True))])
    return _markdown(["pedestrian", "length [m]", "width [m]", "height [m]"], rows)


def check(names: list[str] | None, work: Work, update: bool) -> int:
    """Regenerate the blocks (all, or those named), print the diff, rewrite when ``update``; 1 if they differed."""
    found = doc_blocks()
    missing = sorted({n for b in found.values() for n, _, _ in b} - PRODUCERS.keys())
    if missing:
        raise SystemExit(f"docs_numbers: no producer for {', '.join(missing)}")
    differs = False
    for path, bs in found.items():
        old = path.read_text(encoding="utf-8")
        new = old
        for name, start, end in sorted(bs, key=lambda b: -b[1]):  # from the end: offsets stay valid
            if names and name not in names:
                continue
            new = new[:start] + PRODUCERS[name](work) + new[end:]
        if new != old:
            differs = True
            rel = str(path.relative_to(REPO))
            sys.stdout.writelines(difflib.unified_diff(old.splitlines(True), new.splitlines(True), rel,
                                                       f"{rel} (regenerated)"))
            if update:
                path.write_text(new, encoding="utf-8")
    return 1 if differs and not update else 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--update", action="store_true", help="rewrite the tables in docs/ in place")
    ap.add_argument("--work", type=Path, help="keep the runs here and reuse them (default: a temporary folder)")
    ap.add_argument("--only", nargs="+", metavar="NAME", help="only these tables")
    args = ap.parse_args(argv)
    unknown = [n for n in args.only or () if n not in PRODUCERS]
    if unknown:
        print(f"docs_numbers: unknown table {unknown[0]!r}; known: {', '.join(PRODUCERS)}", file=sys.stderr)
        return 2
    if args.work is not None:
        args.work.mkdir(parents=True, exist_ok=True)
        return check(args.only, Work(args.work), args.update)
    with tempfile.TemporaryDirectory(prefix="docs_numbers_") as tmp:
        return check(args.only, Work(Path(tmp)), args.update)


if __name__ == "__main__":
    sys.exit(main())
