"""Shared fixtures of the suite (shared helper functions: tests/helpers.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.helpers import REPO, run_cli


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
