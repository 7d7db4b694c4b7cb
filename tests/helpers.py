"""Helpers shared by the test files (fixtures live in conftest.py; fake engines and episodes in fakes.py).

A test file imports helpers from here, never from another test file. Scenarios for the synthetic worlds:
:func:`cosim.sensors.synthetic.synthetic_scenario`.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import psutil

from cosim.batch.executors import LocalExecutor
from cosim.batch.plan import plan_file
from cosim.batch.runner import run_batch
from cosim.world.types import Prism, StaticLayout, World
from tests.fakes import fake_episode

REPO = Path(__file__).resolve().parents[1]
SCENARIOS = REPO / "scenarios"
#: Import name -> folder of the three installed roots (pyproject.toml package-dir).
SOURCE_ROOTS = {"cosim": REPO / "cosim", "cosim.sensors": REPO / "sensors", "cosim.exporters": REPO / "exporters"}


# ------------------------------------------------------------------------------ a busy machine


def load_factor() -> float:
    """How many times busier than its cores this machine is: the larger of the 1- and 5-minute load averages
    over the CPU count, at least 1. A quiet machine gives 1; two cores at load 12 give 6."""
    return max(1.0, max(os.getloadavg()[:2]) / (os.cpu_count() or 1))


def load_bound(seconds: float) -> float:
    """A wall-clock bound for a test: ``seconds`` (what a quiet machine must meet; the product's deadline, which
    benchmarks/fault_exit_times.py holds it to) times :func:`load_factor` measured now, at the check. A test
    asserts behaviour (status, message, no orphans, no partial file); its bounds only catch a hang."""
    return seconds * load_factor()


def source_modules() -> dict[str, Path]:
    """Every module of the installed package in the checkout: import name -> file."""
    out = {}
    for name, folder in SOURCE_ROOTS.items():
        for path in sorted(folder.rglob("*.py")):
            parts = path.relative_to(folder).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join([name, *parts])] = path
    return out


def children_of(pid: int) -> list[psutil.Process]:
    """Live (non-zombie) descendants of a process, except multiprocessing's resource tracker
    (spawn starts one per parent; it lives exactly as long as the parent)."""
    try:
        procs = psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return []
    out = []
    for p in procs:
        try:
            if p.status() == psutil.STATUS_ZOMBIE or "resource_tracker" in " ".join(p.cmdline()):
                continue
        except psutil.NoSuchProcess:
            continue
        out.append(p)
    return out


def cli_in_process(capsys, *args: str) -> tuple[int, str, str]:
    """``cosim ARGS`` in this process (pytest's ``capsys`` captures): (exit status, stdout, stderr)."""
    from cosim.cli import main

    try:
        status = main(list(args))
    except SystemExit as exc:  # argparse
        status = exc.code
    out = capsys.readouterr()
    return status, out.out, out.err


def write_file(folder: Path, name: str, text: str | bytes) -> Path:
    """``folder / name`` (parents made) holding ``text`` dedented (bytes as given): a scenario, sweep or other
    input file of a test."""
    p = folder / name
    p.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(text, bytes):
        p.write_bytes(text)
    else:
        p.write_text(textwrap.dedent(text))
    return p


def run_cli(*args: str, cwd: Path | None = None, timeout: float = 600,
            env: dict | None = None) -> subprocess.CompletedProcess:
    """Run ``cosim`` in a fresh interpreter, as a user would; ``timeout`` is for a quiet machine and grows with
    the load (:func:`load_factor`), as the tests' own time limits do."""
    full_env = {**os.environ, **(env or {})}
    return subprocess.run([sys.executable, "-m", "cosim.cli", *args], cwd=cwd or REPO, capture_output=True,
                          text=True, timeout=timeout * load_factor(), env=full_env)


# ------------------------------------------------------------------------------ synthetic geometry

WALL_ID = 1_000_001


def rect(x0, y0, x1, y1):
    """The corners of an axis-aligned rectangle, counter-clockwise."""
    return ((x0, y0), (x1, y0), (x1, y1), (x0, y1))


def wall_world(wall_x: float = 50.0) -> World:
    """Flat ground 600 m square and one wall (instance :data:`WALL_ID`) 5 m thick from x = ``wall_x``."""
    prisms = (
        Prism("terrain", rect(-300, -300, 300, 300), -1.0, 0.0),
        Prism("building", rect(wall_x, -40, wall_x + 5, 40), 0.0, 30.0, WALL_ID),
    )
    return World("synthetic", b"", b"", (-300, -300, 300, 300), (), (), StaticLayout(prisms), (37.0, -122.0, 10.0))


def convex_hull(p: np.ndarray) -> np.ndarray:
    """Counter-clockwise convex hull of points p (N, 2) (monotone chain)."""
    pts = sorted(map(tuple, p))
    def half(seq):
        h = []
        for q in seq:
            while len(h) >= 2 and ((h[-1][0] - h[-2][0]) * (q[1] - h[-2][1])
                                   - (h[-1][1] - h[-2][1]) * (q[0] - h[-2][0])) <= 0:
                h.pop()
            h.append(q)
        return h
    lower, upper = half(pts), half(pts[::-1])
    return np.array(lower[:-1] + upper[:-1])


def signed_dist_inside(hull: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Min signed distance of points q (N, 2) to the edges of a CCW convex hull (positive inside)."""
    a, b = hull, np.roll(hull, -1, axis=0)
    e = b - a
    n = np.stack([-e[:, 1], e[:, 0]], axis=1) / np.linalg.norm(e, axis=1)[:, None]
    return np.min(np.einsum("nij,ij->ni", q[:, None, :] - a[None], n), axis=1)


# ------------------------------------------------------------------------------------ episodes

def lidar_box_excess(tick, objects: dict, keep):
    """(topic, object, metres) per LiDAR sweep of ``tick`` and per object ``keep(object)`` selects among its
    returns' instance ids: how far the returns (deskewed, in the map frame) reach outside the object's box."""
    from cosim.geometry import rotation_matrix
    from cosim.io.deskew import deskew_tick

    for topic in tick.topics:
        if not topic.endswith("/lidar"):
            continue
        cloud = tick[topic]
        to_map = tick.transforms.to_root(cloud.frame_id)
        # each firing at its own time: back into the sweep-end sensor frame first (cosim.io.deskew)
        xyz = deskew_tick(tick, topic.split("/")[1]) @ to_map[:3, :3].T + to_map[:3, 3]
        for tid in np.unique(cloud.points["instance_id"]):
            o = objects.get(int(tid))
            if o is None or not keep(o):
                continue
            rot = rotation_matrix(tuple(o["rotation"]))
            local = (xyz[cloud.points["instance_id"] == tid] - np.array(o["center_m"])) @ rot
            yield topic, o, float((np.abs(local) - np.array(o["size_m"]) / 2).max())


# ------------------------------------------------------------------------- batches of fake episodes

PAPER = REPO / "scenarios" / "base" / "paper.yaml"


def run_sweep(root: Path, sweep_text: str) -> Path:
    """A real ``cosim batch`` of ``sweep_text`` (a whole sweep file) with one worker; its output folder."""
    sweep = root / "sweep.yaml"
    sweep.write_text(sweep_text)
    out = root / "batch"
    r = run_cli("batch", str(sweep), "--out", str(out), "--workers", "1", "-q", timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    return out


def write_sweep(tmp_path: Path, body: str, name: str = "sweep.yaml") -> Path:
    path = tmp_path / name
    path.write_text(f"base: {PAPER}\n" + body)
    return path


SIX = """\
name: six
set: {sensors.enabled: false, duration_s: 1}
axes:
  weather: {key: environment.weather, values: [clear, foggy, rainy]}
  env: {key: map.kind, values: [urban, rural]}
vary:
  agents.vehicles.count: {choice: [3, 4, 5]}
count: 6
"""


def six_plan(tmp_path: Path, body: str = SIX, **kw):
    return plan_file(write_sweep(tmp_path, body), **kw)


def run_fake_batch(plan, out, fn=fake_episode, workers=2, retries=1):
    """Run a plan on the local process pool with a fake episode function (tests/fakes.py)."""
    return run_batch(plan, out, LocalExecutor(workers, fn), retries=retries, show_progress=False)


def batch_folder(root: Path, episodes: list[Path], splits: list[str], sweep: str = "my_sweep") -> Path:
    """A batch folder as `cosim batch` leaves it: the episodes under their splits and a manifest."""
    root.mkdir(parents=True)
    lines = []
    for i, (ep, split) in enumerate(zip(episodes, splits, strict=True)):
        rel = Path(split) / f"{sweep}-{i:04d}.mcap"
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_bytes(ep.read_bytes())
        lines.append(json.dumps({"episode": f"{sweep}-{i:04d}", "sweep": sweep, "split": split, "file": str(rel),
                                 "status": "done", "duration_s": 1.0}))
    (root / "manifest.jsonl").write_text("\n".join(lines) + "\n")
    return root


_WRITER = """
import sys, time
from pathlib import Path
from cosim.io.writer import EpisodeWriter
w = EpisodeWriter(Path(sys.argv[1]))
print(w.tmp_path, flush=True)
time.sleep(120)
"""


def killed_writer(final: Path) -> Path:
    """Start an episode writer in another process, SIGKILL it; returns the partial file it left."""
    proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(final)], stdout=subprocess.PIPE, text=True)
    partial = Path(proc.stdout.readline().strip())
    proc.kill()
    proc.wait(10)
    return partial
