"""What `cosim run` checks before it builds anything (cosim/preflight.py, the output folder and name) and what
its --dry-run prints: one message naming the problem, exit 2, no world built. In process and fast.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from cosim.cli import main
from cosim.scenario import load_scenario
from tests.helpers import cli_in_process as cli
from tests.helpers import killed_writer, write_file

# ------------------------------------------------------------------ --dry-run checks what the real run checks


def test_dry_run_checks_the_map_file(tmp_path, capsys):
    missing = write_file(tmp_path, "missing.yaml",
                         "extends: default\nname: m\nmap: {kind: net, file: nowhere.net.xml}\n")
    status, _, err = cli(capsys, "run", str(missing), "--dry-run", "--out", str(tmp_path / "o"))
    assert status == 2 and err.startswith("cosim: error: map.file 'nowhere.net.xml' not found"), err
    (tmp_path / "not_a_net.net.xml").write_text("<osm version='0.6'/>\n")
    wrong = write_file(tmp_path, "wrong.yaml", "extends: default\nname: w\nmap: {kind: net, file: not_a_net.net.xml}\n")
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


# ---------------------------------- output names and folders, networks, the dry run, a killed run's leftovers


@pytest.mark.parametrize("name", ["../../escape", "sub/dir", "/tmp/abs", "..", ".hidden", "-x", '"a\\0b"', "x" * 300])
def test_output_name_cannot_leave_the_output_folder(tmp_path, capsys, no_world, name):
    status, _, err = cli(capsys, "run", "default", "--out", str(tmp_path), "--set", f"output.name={name}")
    assert status == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert "output.name: output.name must be a plain file name inside the output folder" in err
    assert list(tmp_path.iterdir()) == []


def test_unwritable_out_fails_before_the_world_is_built(tmp_path, capsys, no_world):
    a_file = write_file(tmp_path, "file.txt", "x")
    for out, why in [(a_file, "is a file, not a folder"), (a_file / "sub", "Not a directory"),
                     (Path("/proc/self"), "cannot write episodes into output folder /proc/self"),
                     (Path("/proc/cosim-nowhere"), "cannot write episodes into output folder")]:
        status, _, err = cli(capsys, "run", "default", "--no-sensors", "--out", str(out))
        assert status == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
        assert why in err and str(out) in err, err


@pytest.mark.parametrize("net, expect", [
    ('<net version="1.16">\n<edge id="a"/>\n</net>\n', "no <location convBoundary=...> element"),
    ('<net version="1.9">garbage\n', "no <location convBoundary=...> element"),
    ('<?xml version="1.0"?>\n<net>\n<location netOffset="0,0" convBoundary="0,0,100,100" origBoundary="0,0,1,1" '
     'projParameter="!"/>\n<edge id="a" from="x" to="y"><lane id="a_0" index="0" speed="10" length="10" '
     'shape="0,0 10,0"/></edge>\n</net>\n', "an element lacks the required attribute 'version'"),
    ('<net version="1.9"><location netOffset="0,0" convBoundary="0,0,100,100" origBoundary="0,0,1,1" '
     'projParameter="!"/>\n<edge id="a">\n', "not well-formed XML at line 3"),
])
def test_bad_sumo_networks_get_one_message_naming_the_file_and_the_problem(tmp_path, capsys, net, expect):
    write_file(tmp_path, "bad.net.xml", net)
    f = write_file(tmp_path, "s.yaml", "name: x\nmap: {kind: net, file: bad.net.xml}\n")
    status, _, err = cli(capsys, "run", str(f), "--no-sensors", "--out", str(tmp_path / "out"))
    assert status == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert f"map.file {tmp_path / 'bad.net.xml'}: not a usable SUMO network: {expect}" in err, err


def test_dry_run_prints_the_resolved_scenario_and_builds_nothing(tmp_path, capsys, no_world):
    import yaml

    status = main(["run", "default", "--dry-run", "--out", str(tmp_path), "--set", "sensors.drone.lidar.dropout=0.1"])
    out = capsys.readouterr().out
    assert status == 0
    assert out.splitlines()[0] == f"# {tmp_path / 'default_s0.mcap'}: 15 ticks, 15 agents"
    resolved = yaml.safe_load(out)
    expected = load_scenario("default", ["sensors.drone.lidar.dropout=0.1"]).resolved
    assert resolved == {**expected, "output": {**expected["output"], "dir": str(tmp_path)}}  # the --out used
    assert list(tmp_path.iterdir()) == []


def test_run_dry_run_checks_the_folder_without_creating_it(tmp_path, capsys, no_world):
    out = tmp_path / "new" / "folder"
    status, _, err = cli(capsys, "run", "default", "--dry-run", "--out", str(out))
    assert status == 0 and not (tmp_path / "new").exists(), err
    status, _, err = cli(capsys, "run", "default", "--dry-run", "--out", "/proc/x/y")
    assert status == 2 and err.startswith("cosim: error: cannot write episodes into output folder /proc/x/y (in "
                                          "/proc)"), err


def test_the_next_run_removes_what_a_killed_run_left_and_says_so(tmp_path, monkeypatch, capsys, caplog):
    import fcntl

    import cosim.world
    from cosim.errors import InputError
    from cosim.io.writer import temporary_path

    out = tmp_path / "out"
    stale = killed_writer(out / "other_s3.mcap")
    assert stale.exists() and stale.parent == out and str(stale.name).startswith(".other_s3.mcap.")
    legacy = out / ".older_s1.mcap.partial"  # the name cosim used before
    legacy.write_bytes(b"x" * 1000)
    live = temporary_path(out / "busy_s0.mcap", 4242)  # held by a writer that is still running
    live.write_bytes(b"y")
    holder = open(live, "rb")  # noqa: SIM115
    fcntl.flock(holder.fileno(), fcntl.LOCK_EX)

    def stop(*_a, **_k):
        raise InputError("stopped after the output folder was prepared")

    monkeypatch.setattr(cosim.world, "build_world", stop)
    try:
        with caplog.at_level("WARNING"):
            status, _, err = cli(capsys, "run", "default", "--out", str(out), "--no-sensors")
    finally:
        holder.close()
    assert status == 2 and "stopped after the output folder was prepared" in err
    assert not stale.exists() and not legacy.exists() and live.exists()
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any(str(stale) in w and "left by a run that was killed" in w for w in warned), warned
    assert any(str(legacy) in w for w in warned), warned


# -------------------------------------------------------------------------------- the dry run's output folder


def test_dry_run_prints_the_output_dir_that_will_be_used(tmp_path, capsys):
    out = tmp_path / "elsewhere"
    status, text, err = cli(capsys, "run", "default", "--dry-run", "--out", str(out))
    assert status == 0, err
    header, body = text.split("\n", 1)
    assert header.startswith(f"# {out}/")
    assert yaml.safe_load(body)["output"]["dir"] == str(out)
    status, text, err = cli(capsys, "run", "default", "--dry-run")
    assert status == 0 and yaml.safe_load(text.split("\n", 1)[1])["output"]["dir"] == "out"
    status, text, err = cli(capsys, "run", "default", "--dry-run", "--progress-every", "-1")
    assert status == 2 and err == "cosim: error: --progress-every must be >= 0 seconds, got -1\n"
