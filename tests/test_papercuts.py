"""Papercuts a new user hit (issue 27, item 7): each test fails on the code before the fix.

In-process and fast: scenarios are checked with ``--dry-run`` or the loader, episodes are the small
synthetic ones of :mod:`cosim.io.synthetic`.
"""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import pytest

from cosim.errors import ScenarioError
from cosim.scenario import load_scenario
from tests.helpers import SCENARIOS
from tests.helpers import cli_in_process as cli


def write(folder: Path, name: str, text: str) -> Path:
    p = folder / name
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(textwrap.dedent(text))
    return p


# ------------------------------------------------------------------------------ extends: and scenario names


@pytest.mark.parametrize("parent", ["base/paper", "base/paper.yaml", "default", "town_rural_night.yaml"])
def test_extends_takes_a_shipped_scenario_name_from_any_folder(tmp_path, parent):
    f = write(tmp_path / "elsewhere", "mine.yaml", f"extends: {parent}\nname: mine\nduration_s: 1\n")
    loaded = load_scenario(f)
    assert loaded.scenario.name == "mine" and loaded.scenario.duration_s == 1


def test_extends_prefers_a_file_beside_the_scenario_to_a_shipped_one(tmp_path):
    write(tmp_path, "default.yaml", "name: local_base\nseed: 77\n")
    f = write(tmp_path, "child.yaml", "extends: default\nname: child\n")
    assert load_scenario(f).scenario.seed == 77


def test_a_misspelt_base_scenario_gets_a_did_you_mean(tmp_path):
    f = write(tmp_path, "child.yaml", "name: child\nextends: town_rual_night\n")
    with pytest.raises(ScenarioError) as err:
        load_scenario(f)
    assert err.value.line == 2 and err.value.path == "extends"
    assert "did you mean 'town_rural_night'?" in str(err.value)


def test_a_misspelt_scenario_name_gets_a_did_you_mean(capsys):
    status, _, err = cli(capsys, "run", "town_rual_nigth", "--dry-run")
    assert status == 2
    assert err.startswith("cosim: error: ") and "did you mean 'town_rural_night'?" in err


# ------------------------------------------------------------------------------------- several problems


def test_a_scenario_with_several_problems_lists_them_all_with_file_line_and_key(tmp_path, capsys):
    f = write(tmp_path, "bad.yaml", """\
        extends: default
        name: bad
        duration_s: -1
        seed: x
        agents:
          vehicles: {count: 99}
          wat: 3
        """)
    with pytest.raises(ScenarioError) as err:
        load_scenario(f)
    listed = [(p.line, p.path) for p in err.value.problems]
    assert listed == [(3, "duration_s"), (4, "seed"), (6, "agents.vehicles.count"), (7, "agents.wat")]
    status, _, text = cli(capsys, "run", str(f), "--dry-run")
    lines = text.strip().splitlines()
    assert status == 2 and lines[0] == f"cosim: error: {f}: 4 problems:"
    assert lines[1:] == [f"  {p}" for p in err.value.problems]
    assert lines[4].startswith(f"  {f}:7: agents.wat: unknown key 'wat'")


def test_the_list_of_problems_stops_at_a_limit(tmp_path):
    from cosim.scenario.loader import MAX_PROBLEMS

    keys = "".join(f"  bad_{i}: 1\n" for i in range(MAX_PROBLEMS + 5))
    f = write(tmp_path, "many.yaml", f"name: many\ntraffic:\n{keys}")
    with pytest.raises(ScenarioError) as err:
        load_scenario(f)
    assert len(err.value.problems) == MAX_PROBLEMS and err.value.more == 5
    assert str(err.value).endswith("... and 5 more")


# ------------------------------------------------------------------------------------ --set attribution


@pytest.mark.parametrize("assignment, key", [
    ("map.kind=net", "map.file"),  # a rule on a sibling key the override did not write
    ("tick_hz=7", "tick_hz"),
    ("agents.vehicles.count=0", "agents.drones.2.target"),  # the file's line is fine; the --set broke it
    ("traffic.step_hz=7", "traffic.step_hz"),
])
def test_an_error_caused_by_a_set_names_that_set(capsys, assignment, key):
    status, _, err = cli(capsys, "run", "default", "--dry-run", "--set", assignment)
    assert status == 2
    assert err.startswith(f"cosim: error: --set {assignment}: {key}: "), err
    assert "default.yaml" not in err and "paper.yaml" not in err


def test_an_error_already_in_the_file_still_names_the_file_despite_a_set(tmp_path):
    f = write(tmp_path, "bad.yaml", "extends: default\nname: bad\nduration_s: -1\n")
    with pytest.raises(ScenarioError) as err:
        load_scenario(f, ["environment.weather=foggy"])
    assert err.value.source == str(f.resolve()) and err.value.line == 3


# ----------------------------------------------------------------------------------------- cosim eval ego


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory) -> Path:
    from cosim.io.synthetic import write_synthetic_episode

    return write_synthetic_episode(tmp_path_factory.mktemp("syn") / "syn.mcap", ticks=2, sensors=True)


@pytest.mark.parametrize("ego", ["rsu_0", "drone_0"])
def test_eval_rejects_an_ego_that_is_not_a_vehicle(synthetic, tmp_path, capsys, ego):
    f = tmp_path / "p.jsonl"
    f.write_text(json.dumps({"episode": "syn", "tick": 0, "ego": ego, "boxes": []}) + "\n")
    status, _, err = cli(capsys, "eval", "--gt", str(synthetic), "--pred", str(f), "--out", str(tmp_path / "ev"))
    assert status == 2
    assert err.strip().splitlines() == [f"cosim: error: {f}:1: ego: {ego!r} is not a vehicle: the ego of a frame "
                                        "is a connected vehicle (vehicle_0)"]


# ------------------------------------------------------------------------------------------ truncated files


@pytest.mark.parametrize("command", [["info"], ["render", "--out", "R"], ["export", "--format", "airv2x", "--out", "E"],
                                     ["export", "--format", "opv2v", "--out", "E"], ["comm"]])
def test_a_truncated_file_gives_the_same_status_and_message_in_every_command(synthetic, tmp_path, capsys, command):
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(synthetic.read_bytes()[: synthetic.stat().st_size * 2 // 3])
    args = [str(tmp_path / a) if a in ("R", "E") else a for a in command[1:]]
    status, _, err = cli(capsys, command[0], str(cut), *args)
    assert status == 2
    assert err.startswith(f"cosim: error: {cut}: truncated or corrupt MCAP") and len(err.strip().splitlines()) == 1


# ------------------------------------------------------------------ --dry-run checks what the real run checks


def test_dry_run_checks_the_map_file(tmp_path, capsys):
    missing = write(tmp_path, "missing.yaml", "extends: default\nname: m\nmap: {kind: net, file: nowhere.net.xml}\n")
    status, _, err = cli(capsys, "run", str(missing), "--dry-run", "--out", str(tmp_path / "o"))
    assert status == 2 and err.startswith("cosim: error: map.file 'nowhere.net.xml' not found"), err
    (tmp_path / "not_a_net.net.xml").write_text("<osm version='0.6'/>\n")
    wrong = write(tmp_path, "wrong.yaml", "extends: default\nname: w\nmap: {kind: net, file: not_a_net.net.xml}\n")
    status, _, err = cli(capsys, "run", str(wrong), "--dry-run", "--out", str(tmp_path / "o"))
    assert status == 2 and "is not a SUMO network (.net.xml)" in err, err


def test_dry_run_checks_that_the_drone_backends_are_installed(tmp_path, capsys, monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "pybullet" else real(name, *a))
    status, _, err = cli(capsys, "run", "default", "--dry-run", "--out", str(tmp_path / "o"))
    assert status == 2
    assert err.strip() == ("cosim: error: the drones fly with the pybullet backend, which is not installed: "
                           "pip install pybullet")
    status, _, err = cli(capsys, "batch", "smoke", "--dry-run", "--calibrate-s", "0", "--out", str(tmp_path / "b"),
                         "--set", "agents.drone_backend=pybullet")
    assert status == 2 and "pybullet backend, which is not installed" in err, err


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
    sweep = write(tmp_path, "nets.yaml", f"""\
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


# ------------------------------------------------------------------------------------------------ cosim info


@pytest.fixture
def counted_reads(monkeypatch) -> list[int]:
    """Messages read through Episode.messages (one entry per message)."""
    from cosim.io.reader import Episode

    read: list[int] = []
    real = Episode.messages

    def counting(self, *a, **k):
        for m in real(self, *a, **k):
            read.append(1)
            yield m

    monkeypatch.setattr(Episode, "messages", counting)
    return read


def test_info_prints_summary_and_family_bytes_first_and_topics_per_agent_without_reading_the_file(
        synthetic, capsys, counted_reads):
    from cosim.io import open_episode

    with open_episode(synthetic) as ep:
        per_tick = len(ep.topics)
        total = ep.message_count
    status, out, _ = cli(capsys, "info", str(synthetic))
    assert status == 0
    lines = out.splitlines()
    family_at = next(i for i, ln in enumerate(lines) if ln.startswith("bytes by topic family"))
    topics_at = next(i for i, ln in enumerate(lines) if ln.startswith("topics "))
    assert family_at < topics_at and lines[topics_at] == f"topics       {per_tick} (per agent; --full lists each)"
    per_agent = lines[topics_at + 1:]
    assert [ln.split()[0] for ln in per_agent] == ["episode", "vehicle_0", "rsu_0", "drone_0"]
    assert "1 camera (down) x image depth semantic instance calibration" in per_agent[3]
    assert len(counted_reads) <= per_tick < total  # one tick read, for the compression ratios

    counted_reads.clear()
    status, out, _ = cli(capsys, "info", str(synthetic), "--full")
    assert status == 0 and len(counted_reads) == total
    assert "/drone_0/down/image" in out and "(payloads; stored = compressed alone" in out


def test_info_estimates_family_bytes_close_to_the_full_count(synthetic):
    from cosim.io.info import episode_info

    quick = {f.family: f for f in episode_info(synthetic).families}
    exact = {f.family: f for f in episode_info(synthetic, full=True).families}
    assert quick.keys() == exact.keys()
    for fam, f in exact.items():
        assert quick[fam].messages == f.messages
        assert abs(quick[fam].raw_bytes - f.raw_bytes) <= 0.05 * f.raw_bytes + 2048, (fam, quick[fam], f)
        assert abs(quick[fam].stored_bytes - f.stored_bytes) <= 0.5 * f.stored_bytes + 2048, (fam, quick[fam], f)


def test_info_json_writes_the_seed_as_a_number(synthetic, capsys):
    status, out, _ = cli(capsys, "info", str(synthetic), "--json", "--no-bytes")
    info = json.loads(out)
    assert status == 0 and info["seed"] == 0 and isinstance(info["seed"], int)


# ------------------------------------------------------------------------------------------ normal waiting


@pytest.mark.integration  # a `cosim run` process that builds its world
def test_waiting_for_external_workers_is_a_notice_not_a_warning(tmp_path):
    import socket

    from tests.helpers import run_cli

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    r = run_cli("run", "default", "--no-sensors", "--duration", "1", "--set", "map.kind=rural", "--set",
                "map.size_m=300", "--set", "runtime.startup_timeout_s=1", "--external-workers", "--listen",
                f"tcp/127.0.0.1:{port}", "--out", str(tmp_path), timeout=120)
    assert r.returncode == 1 and "did not come up within 1 s" in r.stderr, r.stderr[-2000:]
    assert f"NOTICE cosim.conductor: waiting for external workers: cosim worker traffic|drones --connect " \
           f"tcp/127.0.0.1:{port}" in r.stderr
    assert "WARNING" not in r.stderr

