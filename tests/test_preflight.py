"""What `cosim run` checks before it builds anything (cosim/preflight.py, the output folder and name) and what
its --dry-run prints: one message naming the problem, exit 2, no world built. In process and fast.
"""

from __future__ import annotations

from tests.helpers import cli_in_process as cli
from tests.helpers import write_file

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
