"""Batch generation with the real pipeline (SUMO + drones + Zenoh), through the `cosim` CLI.

One uninterrupted run of ``sweeps/smoke.yaml`` (6 tiny episodes, 2 workers) is the reference; a run
killed midway and resumed, and a run on a local Ray cluster, must reproduce its manifest and files.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cosim.batch.report import build_report
from cosim.io.manifest import deterministic_view, latest_records, verify
from tests.helpers import REPO, run_cli

pytestmark = pytest.mark.integration

SMOKE = REPO / "sweeps" / "smoke.yaml"


@pytest.fixture(scope="module")
def reference(smoke_batch) -> Path:
    return smoke_batch


def _done(out: Path) -> int:
    if not out.exists():
        return 0
    return sum(r["status"] == "done" for r in latest_records(out).values())


def test_six_episodes_on_two_workers_are_complete_and_verified(reference):
    recs = latest_records(reference)
    assert len(recs) == 6
    assert all(r["status"] == "done" and verify(reference, r) for r in recs.values())
    assert not list(reference.rglob("*.partial"))


def test_killed_batch_resumes_only_the_missing_episodes(reference, tmp_path):
    """Half the sweep (a shard: the rest of the path is the same), killed with a machine crash once one of its
    three episodes is done, then resumed: the missing ones only, each file byte for byte the reference's."""
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "cosim.cli", "batch", str(SMOKE), "--out", str(out), "--workers", "2", "-q",
           "--shard", "0/2"]
    proc = subprocess.Popen(cmd, cwd=REPO, start_new_session=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 300
    while _done(out) < 1 and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.1)
    os.killpg(proc.pid, signal.SIGKILL)  # the batch, its episodes and their workers: a machine crash
    proc.wait(30)
    finished_before = _done(out)
    assert 1 <= finished_before < 3
    r = run_cli("batch", str(SMOKE), "--out", str(out), "--workers", "2", "--shard", "0/2", timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    assert f"{finished_before} already finished, {3 - finished_before} generated, 0 failed" in r.stdout
    mine, reference_records = latest_records(out), latest_records(reference)
    assert len(mine) == 3
    assert deterministic_view(mine.values()) == deterministic_view(reference_records[k] for k in mine)
    for rec in mine.values():
        assert (out / rec["file"]).read_bytes() == (reference / rec["file"]).read_bytes()
    assert not list(out.rglob("*.partial"))


@pytest.mark.resource("ray")
def test_local_ray_cluster_gives_identical_episode_files(reference, tmp_path):
    pytest.importorskip("ray")
    out = tmp_path / "ray"
    # two of the six episodes (a shard: the rest of the path is the same); all six on a two-node cluster in
    # tests/test_ray_cluster.py
    r = run_cli("batch", str(SMOKE), "--out", str(out), "--backend", "ray", "--workers", "2", "--shard", "0/3",
                timeout=600, env={"RAY_USAGE_STATS_ENABLED": "0"})
    assert r.returncode == 0, r.stderr[-3000:]
    mine = latest_records(out)
    assert len(mine) == 2
    reference_records = latest_records(reference)
    assert deterministic_view(mine.values()) == deterministic_view(reference_records[k] for k in mine)


def test_always_failing_episode_is_reported_and_the_others_finish(tmp_path):
    """A map file that passes the batch's up-front check (it exists and opens as a SUMO network) but that
    SUMO cannot use fails its episode alone; a missing map file stops the batch before any episode."""
    broken = tmp_path / "broken.net.xml"
    broken.write_text('<?xml version="1.0"?>\n<net version="1.20">\n  <edge id="half" from="nowhere"\n</net>\n')

    def sweep(name: str, file: Path) -> Path:
        path = tmp_path / f"{name}.yaml"
        path.write_text(
            f"name: bad\nbase: {REPO / 'scenarios' / 'base' / 'paper.yaml'}\n"
            "set: {duration_s: 1, sensors.enabled: false, map.size_m: 300, traffic.density_veh_per_km: 6}\n"
            "axes:\n  map:\n    levels:\n      - {label: ok}\n"
            f"      - {{label: {name}, set: {{map.kind: net, map.file: {file}}}}}\n"
            "count: 2\n")
        return path

    out = tmp_path / "out"
    r = run_cli("batch", str(sweep("broken", broken)), "--out", str(out), "--workers", "2", "--retries", "1",
                timeout=600)
    assert r.returncode == 1
    assert "FAILED   all-broken-0000" in r.stdout and "broken.net.xml" in r.stdout
    recs = latest_records(out)
    assert recs["all-ok-0000"]["status"] == "done" and verify(out, recs["all-ok-0000"])
    assert recs["all-broken-0000"]["status"] == "failed"
    assert recs["all-broken-0000"]["attempts"] == 1  # bad input is not retried

    missing = tmp_path / "out_missing"
    r = run_cli("batch", str(sweep("missing", tmp_path / "does_not_exist.net.xml")), "--out", str(missing),
                "--workers", "2", timeout=600)
    assert r.returncode == 2 and "does_not_exist.net.xml" in r.stderr and "not found" in r.stderr, r.stderr
    assert not list(missing.glob("**/*.mcap"))


def test_report_counts_match_the_manifest(reference, tmp_path):
    report = build_report(reference, md_path=tmp_path / "report.md", img_dir=tmp_path / "img")
    recs = latest_records(reference)
    stats = report.stats
    assert stats["episodes"] == len(recs) == 6
    assert stats["episodes_per_split"] == {"all": 6}
    hours = sum(r["duration_s"] for r in recs.values()) / 3600
    assert stats["hours"] == pytest.approx(hours)
    env = {r["labels"]["environment"] for r in recs.values()}
    assert set(stats["shares"]["environment"]) == env
    assert set(stats["shares"]["strategy"]) == {r["labels"]["strategy"] for r in recs.values()}
    assert stats["objects_per_class"]["drone"] == 6 * 2  # two drones per scene, one track each
    assert sum(stats["agents_per_scene"].values()) == 6
    assert sum(stats["shares"]["weather"].values()) == pytest.approx(1.0)
    assert len(report.images) == 4 and all(p.stat().st_size > 1000 for p in report.images)
    text = report.md_path.read_text()
    assert "| all | 6 |" in text
    r = run_cli("report", str(reference), "--md", str(tmp_path / "cli.md"), timeout=300)
    assert r.returncode == 0 and "6 episodes" in r.stdout
