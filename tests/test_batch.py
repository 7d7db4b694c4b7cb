"""Batch generation with injected fake episodes: sweep validation, deterministic plans, the local
process pool, retries, crashes, the manifest and resume (the real pipeline is in test_batch_real.py)."""

from __future__ import annotations

import itertools
import os
import re
from collections import Counter
from pathlib import Path

import pytest

from cosim.batch.estimate import calibrate
from cosim.batch.executors import make_executor
from cosim.batch.manifest import Manifest
from cosim.batch.plan import balanced_allocation, derive_seed, largest_remainder, plan_file
from cosim.batch.runner import run_batch
from cosim.batch.sweep import SweepError, load_sweep
from cosim.errors import InputError
from cosim.io.manifest import deterministic_view, latest_records, read_records, sha256_file, verify
from tests.fakes import fake_episode, niceness_episode, spawning_episode
from tests.helpers import (
    PAPER,
    REPO,
    SCENARIOS,
    SIX,
    batch_folder,
    killed_writer,
    run_cli,
    six_plan,
    write_file,
    write_sweep,
)
from tests.helpers import cli_in_process as cli
from tests.helpers import run_fake_batch as run

# ------------------------------------------------------------------------------------ helpers


FAULTS = """\
name: faults
set: {sensors.enabled: false, duration_s: 1}
axes:
  weather: {key: environment.weather, values: [clear, foggy]}
  mode:
    levels:
      - {label: ok}
      - {label: crash, set: {description: crash_once}}
      - {label: fail, set: {description: always_fail}}
count: 6
"""





# ------------------------------------------------------------------------------ sweep files


def test_sweep_unknown_key_names_path_line_and_suggestion(tmp_path):
    path = write_sweep(tmp_path, "name: s\naxes:\n  weather:\n    key: environment.weather\n    valuse: [clear]\n")
    with pytest.raises(SweepError) as err:
        load_sweep(path)
    assert err.value.path == "axes.weather.valuse"
    assert err.value.line == 6
    assert "did you mean 'values'" in str(err.value)
    assert isinstance(err.value, InputError)


def test_sweep_rule_errors_and_duplicate_keys(tmp_path):
    p = write_sweep(tmp_path, "name: s\naxes:\n  w: {key: environment.weather, values: [clear, foggy], weights: [1]}\n")
    with pytest.raises(SweepError, match="1 weights for 2 values") as err:
        load_sweep(p)
    assert err.value.path == "axes.w.weights" and err.value.line == 4
    p = write_sweep(tmp_path, "name: s\ncount: 2\ncount: 3\n", "dup.yaml")
    with pytest.raises(SweepError, match="appears twice") as err:
        load_sweep(p)
    assert err.value.line == 4
    p = write_sweep(tmp_path, "name: s\ncount: 2\nhours: 1\n", "both.yaml")
    with pytest.raises(SweepError, match="count or hours"):
        load_sweep(p)


def test_vary_errors_name_the_draw(tmp_path):
    p = write_sweep(tmp_path, "name: s\nvary:\n  traffic.density_veh_per_km: {uniform: [5, 1]}\n")
    with pytest.raises(SweepError, match="low <= high") as err:
        load_sweep(p)
    assert err.value.path == "vary.traffic.density_veh_per_km.uniform" and err.value.line == 4


def test_invalid_episode_scenario_points_at_the_sweep_line(tmp_path):
    body = "name: s\ncount: 2\naxes:\n  weather: {key: environment.weather, values: [clear, snowy]}\n"
    with pytest.raises(SweepError) as err:
        plan_file(write_sweep(tmp_path, body))
    assert err.value.path == "axes.weather" and err.value.line == 5
    assert "snowy" in str(err.value) and "environment.weather" in str(err.value)


# ------------------------------------------------------------------------------------- planner


def test_largest_remainder_sums_and_is_proportional():
    alloc = largest_remainder(1000, [2.19, 1.02, 3.52], ["train", "val", "test"])
    assert sum(alloc) == 1000
    assert alloc == [325, 152, 523]


def test_balanced_allocation_covers_balances_and_grows_by_extension():
    levels = [[1, 1, 1, 1], [1, 1, 1], [1, 1, 1, 1], [1, 1, 1]]  # 144 combinations
    small = balanced_allocation(24, levels)
    assert sum(small) == 24 and max(small) == 1
    combos = [c for c, n in zip(itertools.product(*(range(len(w)) for w in levels)), small, strict=True) if n]
    for j, w in enumerate(levels):  # 24 episodes: every level of every axis equally often
        assert sorted(Counter(c[j] for c in combos).values()) == [24 // len(w)] * len(w)
    full = balanced_allocation(400, levels)
    assert min(full) >= 2 and max(full) <= 3  # all 144 covered, then evenly repeated
    assert all(a <= b for a, b in zip(small, full, strict=True))  # growing keeps the smaller plan
    weighted = balanced_allocation(300, [[2, 1], [1, 1, 1]], cover_all=False)
    assert sum(weighted[:3]) == 200 and sum(weighted[3:]) == 100


def test_plan_is_deterministic_and_seeds_depend_only_on_the_id(tmp_path):
    a, b = six_plan(tmp_path), six_plan(tmp_path)
    assert [(e.id, e.seed, e.params) for e in a.episodes] == [(e.id, e.seed, e.params) for e in b.episodes]
    assert len(a.episodes) == 6 and a.combinations == 6
    assert {e.labels["weather"] for e in a.episodes} == {"clear", "foggy", "rainy"}
    for e in a.episodes:
        assert e.seed == derive_seed(0, e.id) == e.scenario["seed"]
        assert e.scenario["environment"]["weather"] == e.labels["weather"]
        assert e.scenario["output"]["name"] == e.id
        assert e.scenario["agents"]["vehicles"]["count"] == e.params["agents.vehicles.count"] in (3, 4, 5)
    # growing the sweep keeps the episodes it had (same ids, seeds and draws)
    bigger = {e.id: e for e in six_plan(tmp_path, count=18).episodes}
    assert all(bigger[e.id].seed == e.seed and bigger[e.id].params == e.params for e in a.episodes)


def test_split_proportions_hours_budget_and_cover_all(tmp_path):
    body = SIX.replace("count: 6\n", "hours: 0.1\nsplit: {train: 2.19, val: 1.02, test: 3.52}\n")
    plan = six_plan(tmp_path, body)
    assert len(plan.episodes) == 360  # 0.1 h of 1 s episodes
    per = {s: [e for e in plan.episodes if e.split == s] for s in ("train", "val", "test")}
    assert [len(v) for v in per.values()] == largest_remainder(360, [2.19, 1.02, 3.52], list(per))
    for eps in per.values():  # every split sees every combination
        assert len({(e.labels["weather"], e.labels["env"]) for e in eps}) == 6
    assert len({e.id for e in plan.episodes}) == 360
    assert abs(plan.sim_seconds - 360.0) < 1e-9


def test_shards_partition_the_plan(tmp_path):
    plan = six_plan(tmp_path, count=20)
    shards = [plan.sharded(i, 3) for i in range(3)]
    ids = [e.id for s in shards for e in s.episodes]
    assert sorted(ids) == sorted(e.id for e in plan.episodes)
    assert len(set(ids)) == len(ids)
    with pytest.raises(SweepError):
        plan.sharded(3, 3)


def test_a_seed_axis_sets_the_scenario_seed(tmp_path):
    body = SIX.replace("  env: {key: map.kind, values: [urban, rural]}\n", "  seeds: {key: seed, values: [11, 12]}\n")
    plan = six_plan(tmp_path, body)
    assert sorted({(e.labels["seeds"], e.seed, e.scenario["seed"], e.params["seed"]) for e in plan.episodes}) == [
        ("11", 11, 11, 11), ("12", 12, 12, 12)]


def test_multiple_bases_become_an_axis(tmp_path):
    body = (f"name: s\nbase: [{PAPER}, {REPO / 'scenarios' / 'town_rural_night.yaml'}]\n"
            "set: {sensors.enabled: false}\ncount: 4\n")
    path = tmp_path / "bases.yaml"
    path.write_text(body)
    plan = plan_file(path)
    assert sorted({e.labels["base"] for e in plan.episodes}) == ["paper", "town_rural_night"]
    lighting = {e.labels["base"]: e.scenario["environment"]["lighting"] for e in plan.episodes}
    assert lighting == {"paper": "day", "town_rural_night": "night"}


# ------------------------------------------------------------------------------ local executor


def test_six_episodes_two_workers_complete_and_verify(tmp_path):
    plan = six_plan(tmp_path)
    out = tmp_path / "out"
    summary = run(plan, out)
    assert summary.ok and summary.done == 6 and summary.skipped == 0
    recs = latest_records(out)
    assert len(recs) == 6 and all(r["status"] == "done" and verify(out, r) for r in recs.values())
    for e in plan.episodes:
        assert recs[e.id]["sha256"] == sha256_file(out / e.file)
        assert recs[e.id]["seed"] == e.seed and recs[e.id]["attempts"] == 1
        assert "python" in recs[e.id]["versions"]
    # running again does nothing
    again = run(plan, out)
    assert again.skipped == 6 and again.done == 0


def test_episode_processes_may_start_their_own_processes(tmp_path):
    """Pool processes are not daemonic: an episode can spawn workers as the conductor does."""
    plan = six_plan(tmp_path, count=2)
    out = tmp_path / "out"
    summary = run(plan, out, fn=spawning_episode, retries=0)
    assert summary.ok, summary.failed
    assert all(verify(out, r) for r in latest_records(out).values())


def test_crash_is_retried_and_permanent_failure_is_reported(tmp_path):
    plan = plan_file(write_sweep(tmp_path, FAULTS))
    out = tmp_path / "out"
    summary = run(plan, out, retries=2)
    assert not summary.ok
    assert sorted(summary.failed) == sorted(e.id for e in plan.episodes if e.labels["mode"] == "fail")
    assert all("forced failure" in err for err in summary.failed.values())
    assert summary.done == 4
    recs = latest_records(out)
    for e in plan.episodes:
        r = recs[e.id]
        if e.labels["mode"] == "crash":
            assert r["status"] == "done" and r["attempts"] == 2 and verify(out, r)
        elif e.labels["mode"] == "fail":
            assert r["status"] == "failed" and r["attempts"] == 3 and not (out / e.file).exists()
    crashes = [r for r in read_records(out / "manifest.jsonl") if r.get("retrying")]
    assert any("exited with code 3" in r["error"] for r in crashes)


@pytest.mark.integration  # starts a local Ray
@pytest.mark.resource("ray")
def test_ray_executor_retries_a_crashed_worker_and_reports_failures(tmp_path):
    pytest.importorskip("ray")
    body = FAULTS.replace("values: [clear, foggy]", "values: [clear]").replace("      - {label: ok}\n", "")
    plan = plan_file(write_sweep(tmp_path, body.replace("count: 6", "count: 2")))
    out = tmp_path / "out"
    summary = run_batch(plan, out, make_executor("ray", workers=2, episode_fn=niceness_episode), retries=1,
                        show_progress=False)
    assert list(summary.failed) == ["all-clear-fail-0000"] and "forced failure" in summary.failed["all-clear-fail-0000"]
    crash = latest_records(out)["all-clear-crash-0000"]  # its worker process died; Ray reports it, we retry
    assert crash["status"] == "done" and crash["attempts"] == 2 and verify(out, crash)
    errors = [r["error"] for r in read_records(out / "manifest.jsonl") if r.get("retrying")]
    assert any("WorkerCrashedError" in e for e in errors)
    # Ray's workers run at niceness 15 by default, starved beside any busy process; ours at the driver's
    assert {int(f.read_text()) for f in out.glob(".nice-*")} == {os.nice(0)}


def test_resume_redoes_missing_and_corrupt_files_only(tmp_path):
    plan = six_plan(tmp_path, count=4)
    out = tmp_path / "out"
    assert run(plan, out).ok
    before = deterministic_view(latest_records(out).values())
    first, second = plan.episodes[0], plan.episodes[1]
    (out / first.file).unlink()
    data = bytearray((out / second.file).read_bytes())
    data[10] ^= 0xFF  # same size, different content: presence alone must not count
    (out / second.file).write_bytes(bytes(data))
    summary = run(plan, out)
    assert summary.skipped == 2 and summary.done == 2
    assert deterministic_view(latest_records(out).values()) == before
    assert latest_records(out)[second.id]["attempts"] == 2
    # a different --set is a different episode under the same id: it runs again
    longer = six_plan(tmp_path, count=4, cli_set=["duration_s=2"])
    assert [e.id for e in longer.episodes] == [e.id for e in plan.episodes]
    assert run(longer, out).done == 4


def test_a_second_writer_of_the_same_manifest_is_refused(tmp_path):
    with Manifest(tmp_path / "manifest.jsonl"), pytest.raises(InputError, match="already writing"):
        Manifest(tmp_path / "manifest.jsonl")
    with Manifest(tmp_path / "manifest.jsonl") as m:  # released when the first one closed
        m.append({"episode": "a", "status": "done"})


def test_manifest_tolerates_a_torn_last_line_and_last_record_wins(tmp_path):
    path = tmp_path / "manifest.jsonl"
    with Manifest(path) as m:
        m.append({"episode": "a", "status": "running"})
        m.append({"episode": "a", "status": "done"})
    with open(path, "ab") as f:
        f.write(b'{"episode": "a", "status": "fai')  # a crash mid-write
    assert latest_records(tmp_path)["a"]["status"] == "done"
    with Manifest(path) as m:  # appending after a torn line starts a fresh line
        m.append({"episode": "b", "status": "done"})
    assert set(latest_records(tmp_path)) == {"a", "b"}


def test_shards_write_their_own_manifests_and_a_full_run_sees_them(tmp_path):
    plan = six_plan(tmp_path, count=4)
    out = tmp_path / "out"
    for i in range(2):
        assert run(plan.sharded(i, 2), out).done == 2
    assert sorted(p.name for p in out.glob("manifest*.jsonl")) == [
        "manifest.shard000of002.jsonl", "manifest.shard001of002.jsonl"]
    assert len(latest_records(out)) == 4
    assert run(plan, out).skipped == 4


def test_one_split_alone_makes_the_same_episodes_and_a_full_run_keeps_them(tmp_path):
    plan = six_plan(tmp_path, SIX.replace("count: 6\n", "count: 6\nsplit: {train: 2, test: 1}\n"))
    test = plan.only_splits(["test"])
    assert test.episodes == tuple(e for e in plan.episodes if e.split == "test") and len(test.episodes) == 2
    out = tmp_path / "out"
    assert run(test, out).done == 2
    assert sorted(p.parent.name for p in out.rglob("*.mcap")) == ["test", "test"]
    assert run(plan, out).skipped == 2  # the same ids, seeds and scenarios: nothing made twice
    with pytest.raises(SweepError, match="no split 'tset' in sweep 'six' \\(its splits: train, test\\)"):
        plan.only_splits(["tset"])


def test_cli_split_plans_one_split_and_refuses_an_unknown_one(tmp_path):
    path = write_sweep(tmp_path, SIX.replace("count: 6\n", "count: 6\nsplit: {train: 2, test: 1}\n"))
    r = run_cli("batch", str(path), "--out", str(tmp_path / "o"), "--dry-run", "--calibrate-s", "0",
                "--split", "test", timeout=120)
    assert r.returncode == 0, r.stderr
    assert "six: 2 episodes" in r.stdout
    assert re.search(r"split +train +0 episodes", r.stdout) and re.search(r"split +test +2 episodes", r.stdout)
    r = run_cli("batch", str(path), "--out", str(tmp_path / "o"), "--dry-run", "--split", "tset", timeout=120)
    assert r.returncode == 2 and "--split" in r.stderr and "no split 'tset'" in r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "o").exists()


def test_calibration_extrapolates_to_the_plan(tmp_path):
    plan = six_plan(tmp_path, count=3)
    est = calibrate(plan, tmp_path / "cal", seconds=1.0, workers=2, episode_fn=fake_episode)
    assert est.calibration_s == 1.0 and est.per_tick_s >= 0 and est.startup_s >= 0
    assert est.bytes == pytest.approx(3 * est.bytes_per_tick * 5)  # 3 episodes of 5 ticks, no attachments
    assert est.wall_s == pytest.approx(est.cpu_s / 2)
    # CPU-seconds per tick of the episode's process tree, measured at the same tick marks, and the dataset cost
    assert est.cpu_per_tick_s is not None and 0 <= est.cpu_per_tick_s < 10
    cpu_h, size = est.dataset_cost(7200)
    assert cpu_h == pytest.approx(2 * est.cpu_per_tick_s) and size == pytest.approx(7200 * est.bytes_per_tick)


def test_unknown_backend_lists_the_known_ones():
    with pytest.raises(InputError, match="known: local, ray"):
        make_executor("slurm")


# ------------------------------------------------------------------------------------------ CLI


def test_cli_bad_sweep_exits_2_with_line(tmp_path):
    path = write_sweep(tmp_path, "name: s\ncount: -1\n")
    r = run_cli("batch", str(path), "--out", str(tmp_path / "o"), "--dry-run", timeout=120)
    assert r.returncode == 2
    assert "count" in r.stderr and ":3:" in r.stderr and "Traceback" not in r.stderr


def test_cli_dry_run_prints_the_plan(tmp_path):
    path = write_sweep(tmp_path, SIX)
    r = run_cli("batch", str(path), "--out", str(tmp_path / "o"), "--dry-run", "--calibrate-s", "0",
                "--shard", "1/2", timeout=120)
    assert r.returncode == 0, r.stderr
    assert "3 episodes" in r.stdout and "shard 1/2" in r.stdout
    assert not (tmp_path / "o").exists()


def test_dry_run_shows_the_conditions_and_draws_of_each_planned_episode(tmp_path, capsys):
    """Each planned episode's line names the weather, lighting and environment it got (axes or draws) and
    the values its `vary` draws gave, as its resolved scenario has them."""
    from tests.helpers import cli_in_process

    plan = six_plan(tmp_path)
    status, out, err = cli_in_process(capsys, "batch", str(tmp_path / "sweep.yaml"), "--out", str(tmp_path / "o"),
                                      "--dry-run", "--calibrate-s", "0")
    assert status == 0, err
    lines = [line for line in out.splitlines() if line.startswith("episode  ") and ".mcap" in line]
    assert len(lines) == len(plan.episodes) == 6
    for ep, line in zip(plan.episodes, lines, strict=True):
        env = ep.scenario["environment"]
        cond = f"{env['weather']}/{env['lighting']}/{ep.scenario['map']['kind']}"
        assert line == (f"episode  {ep.file}  seed {ep.seed}  {ep.duration_s:g} s  {cond}  "
                        f"agents.vehicles.count={ep.scenario['agents']['vehicles']['count']}"), line
    assert len({line.split("  ")[4] for line in lines}) == 6  # the axes' six weather x map combinations


# ------------------------------------------------------------- the batch dry run checks what the batch checks


def test_batch_dry_run_checks_that_ray_is_installed(tmp_path, capsys, monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "ray" else real(name, *a))
    for dry in (["--dry-run", "--calibrate-s", "0"], []):
        status, _, err = cli(capsys, "batch", "smoke", "--backend", "ray", "--out", str(tmp_path / "b"), *dry)
        assert status == 2
        assert err.strip() == "cosim: error: --backend ray needs Ray: pip install -e '.[ray]' (or pip install " \
                              "'ray>=2.9')"


def test_batch_dry_run_checks_the_map_files_of_its_episodes(tmp_path, capsys):
    sweep = write_file(tmp_path, "nets.yaml", f"""\
        name: nets
        base: {SCENARIOS / "default.yaml"}
        axes:
          town:
            levels:
              - {{label: a, set: {{map.kind: net, map.file: {tmp_path / "town_a.net.xml"}}}}}
              - {{label: b, set: {{map.kind: net, map.file: {tmp_path / "town_b.net.xml"}}}}}
        count: 2
        """)
    (tmp_path / "town_a.net.xml").write_text("<net version='1.20'/>\n")
    status, _, err = cli(capsys, "batch", str(sweep), "--dry-run", "--calibrate-s", "0", "--out", str(tmp_path / "b"))
    assert status == 2 and err.startswith(f"cosim: error: map.file '{tmp_path / 'town_b.net.xml'}' not found"), err


# -------------------------------------- sweeps that cannot be planned; unusable output folders; partial files


@pytest.mark.parametrize("size, expect", [
    (f"count: {2**63}", ":3: count: Input should be less than or equal to 100000"),
    (f"count: {2**64 + 5}", ":3: count: Input should be less than or equal to 100000"),
    ("hours: 1.0e+12", ":3: hours: 1.8e+14 episodes cannot be planned: at most 100000 per plan"),
    ("hours: .inf", ":3: hours: Input should be a finite number"),
    ("count: .nan", ":3: count:"),
])
def test_sweep_sizes_that_cannot_be_planned_are_rejected_with_key_and_line(tmp_path, capsys, size, expect):
    f = write_file(tmp_path, "sweep.yaml", f"name: big\nbase: {PAPER}\n{size}\n")
    status, _, err = cli(capsys, "batch", str(f), "--out", str(tmp_path / "out"), "--dry-run", "--calibrate-s", "0")
    assert status == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert f"{f}{expect}" in err, err


def test_scale_and_count_flags_that_cannot_be_planned_are_rejected(tmp_path, capsys):
    f = write_file(tmp_path, "sweep.yaml", f"name: ok\nbase: {PAPER}\ncount: 2\n")
    for flags, expect in [(["--scale", "inf"], "--scale: scale must be a finite number > 0"),
                          (["--scale", "1e300"], "--count" if False else "episodes cannot be planned"),
                          (["--count", str(2**63)], "--count: 9.22337e+18 episodes cannot be planned")]:
        status, _, err = cli(capsys, "batch", str(f), "--out", str(tmp_path / "out"), "--dry-run", "--calibrate-s", "0",
                          *flags)
        assert status == 2 and "Traceback" not in err, err
        assert expect in err, err


@pytest.fixture
def read_only_dir(tmp_path):
    """A folder on a read-only file system (a read-only tmpfs): root ignores permission bits, not that.
    Skipped where mounting is not allowed."""
    import shutil
    import subprocess

    folder = tmp_path / "ro"
    folder.mkdir()
    if not shutil.which("mount"):
        pytest.skip("no mount(8) here")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(folder)], capture_output=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a read-only tmpfs here: {r.stderr.decode().strip()}")
    yield folder
    subprocess.run(["umount", str(folder)], check=True)


def bad_out_dirs(tmp_path: Path, read_only: Path | None) -> dict[str, Path]:
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    out = {"/proc": Path("/proc/x"), "regular file": a_file, "under a file": a_file / "sub" / "dir"}
    if read_only is not None:
        out |= {"read-only folder": read_only, "under a read-only folder": read_only / "sub"}
    return out


@pytest.mark.parametrize("dry_run", [False, True])
def test_batch_into_an_unusable_output_folder_is_one_message_and_exit_2(tmp_path, capsys, read_only_dir, dry_run):
    for what, out in bad_out_dirs(tmp_path, read_only_dir).items():
        args = ["batch", "smoke", "--out", str(out), "--count", "1", *(["--dry-run", "--calibrate-s", "0"]
                                                                       if dry_run else [])]
        status, _, err = cli(capsys, *args)
        assert status == 2, (what, status, err)
        lines = err.strip().splitlines()
        assert len(lines) == 1, (what, err)
        assert lines[0].startswith((f"cosim: error: cannot write episodes into output folder {out}",
                                    f"cosim: error: output folder {out} is a file")), (what, err)
        assert "Traceback" not in err
    assert not (read_only_dir / "sub").exists()


def test_a_batch_removes_partial_files_left_in_its_folders(tmp_path, monkeypatch, caplog):
    from cosim.batch import runner
    from cosim.batch.plan import plan_file

    plan = plan_file("smoke", count=2)
    out = tmp_path / "batch"
    leftovers = [killed_writer(out / plan.episodes[0].file), killed_writer(out / "unrelated_s9.mcap")]
    assert all(p.exists() for p in leftovers)

    class NoExecutor:
        status_lines = 0

        def busy(self):
            return False

        def has_capacity(self):
            raise AssertionError("stop before running anything")

        def shutdown(self):
            pass

    with caplog.at_level("WARNING"), pytest.raises(AssertionError, match="stop before running"):
        runner.run_batch(plan, out, NoExecutor(), show_progress=False)
    assert not any(p.exists() for p in leftovers)
    assert sum("left by a run that was killed" in r.getMessage() for r in caplog.records) == 2


# ---------------------------------------------------------------- cosim report: sizes per split and condition


def test_report_gives_bytes_frames_and_visible_objects_per_split_and_condition(synthetic_episodes, tmp_path):
    from cosim.batch.report import build_report
    from cosim.io.reader import open_episode

    root = batch_folder(tmp_path / "batch", synthetic_episodes, ["train", "val"])
    report = build_report(root, md_path=tmp_path / "report.md", img_dir=tmp_path / "img")
    rows = report.stats["size_per_split_condition"]
    expected = {}
    for ep, split in zip(synthetic_episodes, ["train", "val"], strict=True):
        with open_episode(ep) as e:
            md = e.metadata
            visible = 0
            for tick in e.ticks():
                seen: set[int] = set()
                for agent in e.agents:
                    if f"/{agent}/visibility" in tick:
                        seen.update(int(o["track_id"]) for o in tick[f"/{agent}/visibility"]["objects"])
                visible += len(seen)
            cond = f"{md['weather']}/{md['lighting']}/{md['environment']}"
            expected[f"{split} {cond}"] = {"split": split, "condition": cond, "episodes": 1,
                                           "bytes": ep.stat().st_size, "frames": len(e), "visible": visible,
                                           "visible_per_frame": visible / len(e)}
    assert rows == expected and all(r["visible"] > 0 for r in rows.values())
    text = report.md_path.read_text()
    assert "| split | condition (weather/lighting/environment) | episodes | bytes on disk | frames |" in text
    r = expected[next(iter(expected))]
    assert (f"| {r['split']} | {r['condition']} | 1 | {r['bytes']:,} | {r['frames']} | "
            f"{r['visible_per_frame']:.1f} |") in text
