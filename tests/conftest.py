"""Shared fixtures of the suite (shared helper functions: tests/helpers.py)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from tests.helpers import REPO, run_cli

#: ``make test-fast`` sets this: the lane of unit tests (``-m "not integration ..."``) must start no engine.
FAST_LANE = os.environ.get("COSIM_TEST_FAST") == "1"
_ENGINE_SUBCOMMANDS = {"run"}


def _refuse(what: str):
    def refuse(*_args, **_kwargs):
        raise RuntimeError(f"{what} in the fast lane (make test-fast): mark this test @pytest.mark.integration")

    return refuse


def _starts_an_episode(args) -> bool:
    """``cosim run ...`` (as a console script or ``python -m cosim.cli``)."""
    argv = [str(a) for a in ([args] if isinstance(args, str | os.PathLike) else list(args))]
    for i, a in enumerate(argv):
        if (a == "cosim.cli" or a.endswith("/cosim") or a == "cosim") and i + 1 < len(argv):
            return bool(_ENGINE_SUBCOMMANDS & set(argv[i + 1:i + 2]))
    return False


@pytest.fixture(scope="session", autouse=True)
def _fast_lane_guard():
    """In the fast lane, starting SUMO, JSBSim, PyBullet or a `cosim run` process fails the test
    with a message saying to mark it ``integration``: the lane stays a lane of unit tests."""
    if not FAST_LANE:
        yield
        return
    import jsbsim
    import libsumo
    import pybullet

    popen_init = subprocess.Popen.__init__

    def guarded_popen(self, args, *rest, **kwargs):
        if _starts_an_episode(args):
            _refuse(f"`{' '.join(map(str, args))}`")()
        popen_init(self, args, *rest, **kwargs)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(libsumo, "start", _refuse("SUMO (libsumo.start)"))
        mp.setattr(jsbsim, "FGFDMExec", _refuse("JSBSim"))
        mp.setattr(pybullet, "connect", _refuse("PyBullet"))
        mp.setattr(subprocess.Popen, "__init__", guarded_popen)
        yield


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
