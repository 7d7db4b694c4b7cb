"""Real ``cosim run`` episodes: same seed -> byte-identical file; every shipped scenario validates."""

from __future__ import annotations

import hashlib

import pytest

from cosim.io import open_episode
from cosim.io.validate import validate_episode
from tests.conftest import SCENARIOS, run_cli

pytestmark = pytest.mark.integration

TINY = ["--no-sensors", "--set", "map.size_m=300"]


def _run(scenario: str, out, *extra: str):
    r = run_cli("run", scenario, "--out", str(out), "-q", *TINY, *extra)
    assert r.returncode == 0, r.stderr
    (path,) = list(out.iterdir())
    return path


def test_two_runs_of_one_seed_give_byte_identical_files(tmp_path):
    a = _run("scenarios/default.yaml", tmp_path / "a", "--duration", "2")
    b = _run("scenarios/default.yaml", tmp_path / "b", "--duration", "2")
    c = _run("scenarios/default.yaml", tmp_path / "c", "--duration", "2", "--seed", "1")
    digest = [hashlib.sha256(p.read_bytes()).hexdigest() for p in (a, b, c)]
    assert digest[0] == digest[1]
    assert digest[0] != digest[2]
    report = validate_episode(a)
    assert report.ok, report.lines()
    with open_episode(a) as ep:
        assert ep.n_ticks == 10 and ep.format_version == "1.0"
        assert {t.message_count for t in ep.topics.values()} == {10}


@pytest.mark.parametrize("scenario", sorted(p.name for p in SCENARIOS.glob("*.yaml")))
def test_every_shipped_scenario_gives_a_valid_episode(tmp_path, scenario):
    path = _run(f"scenarios/{scenario}", tmp_path, "--duration", "1")
    report = validate_episode(path)
    assert report.ok, report.lines()
    r = run_cli("validate", str(path))
    assert r.returncode == 0 and "ok (5 ticks" in r.stdout, r.stdout + r.stderr
