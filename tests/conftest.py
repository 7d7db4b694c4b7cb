"""Shared fixtures and helpers for the suite."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import psutil
import pytest

REPO = Path(__file__).resolve().parents[1]
SCENARIOS = REPO / "scenarios"


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


def run_cli(*args: str, cwd: Path | None = None, timeout: float = 600,
            env: dict | None = None) -> subprocess.CompletedProcess:
    """Run ``cosim`` in a fresh interpreter, as a user would."""
    full_env = {**os.environ, **(env or {})}
    return subprocess.run([sys.executable, "-m", "cosim.cli", *args], cwd=cwd or REPO, capture_output=True,
                          text=True, timeout=timeout, env=full_env)


@pytest.fixture
def tiny_overrides() -> list[str]:
    """Overrides that make any shipped scenario small and fast: short, no sensors, small map."""
    return ["duration_s=2", "sensors.enabled=false", "map.size_m=300", "traffic.density_veh_per_km=6"]


@pytest.fixture(scope="session")
def smoke_batch(tmp_path_factory) -> Path:
    """One local batch of ``sweeps/smoke.yaml`` (6 tiny episodes, 2 workers): the reference every other way of
    running that sweep (resumed, Ray, a Ray cluster, shard containers) must reproduce. Read it, never write it."""
    out = tmp_path_factory.mktemp("smoke-batch") / "ref"
    r = run_cli("batch", str(REPO / "sweeps" / "smoke.yaml"), "--out", str(out), "--workers", "2", timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "6 generated, 0 failed" in r.stdout
    return out
