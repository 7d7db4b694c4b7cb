"""Bad and hostile input: one message naming the file (and key path and line), exit 2, never a traceback.

In-process and fast: nothing here builds a world or starts a worker (``build_world`` is made to fail the
test if a check happens too late).
"""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import pytest

from cosim.cli import main
from cosim.errors import ScenarioError
from cosim.scenario import load_scenario
from tests.helpers import SCENARIOS

BASE = SCENARIOS / "base" / "paper.yaml"


def leaves(value, path=()):
    """(key path, value) of every scalar in plain data."""
    if isinstance(value, dict):
        for k, v in value.items():
            yield from leaves(v, (*path, k))
    elif isinstance(value, list | tuple):
        for i, v in enumerate(value):
            yield from leaves(v, (*path, i))
    else:
        yield path, value


def changed(a: dict, b: dict) -> dict[tuple, tuple]:
    fa, fb = dict(leaves(a)), dict(leaves(b))
    return {k: (fa.get(k, "<absent>"), fb.get(k, "<absent>")) for k in fa.keys() | fb.keys()
            if fa.get(k, "<absent>") != fb.get(k, "<absent>")}


def cli(capsys, *args: str) -> tuple[int, str]:
    """``cosim ARGS`` in this process: (exit status, stderr)."""
    try:
        status = main(list(args))
    except SystemExit as exc:  # argparse
        status = exc.code
    return status, capsys.readouterr().err


@pytest.fixture
def no_world(monkeypatch):
    """Fail if a command gets as far as building the world."""
    import cosim.world

    def refuse(*_a, **_k):
        raise AssertionError("the world was built before the input was checked")

    monkeypatch.setattr(cosim.world, "build_world", refuse)


def write(tmp_path: Path, name: str, text: str | bytes) -> Path:
    p = tmp_path / name
    if isinstance(text, bytes):
        p.write_bytes(text)
    else:
        p.write_text(textwrap.dedent(text))
    return p


# ------------------------------------------------------------------------- 4: overrides merge field by field


@pytest.mark.parametrize("assignment, key", [
    ("sensors.drone.lidar.range_noise_m=0", ("sensors", "drone", "lidar", "range_noise_m")),
    ("sensors.vehicle.lidar.mount.xyz_m=[0, 0, 2.2]", ("sensors", "vehicle", "lidar", "mount", "xyz_m", 2)),
    ("sensors.rsu.cameras.1.fov_deg=90", ("sensors", "rsu", "cameras", 1, "fov_deg")),
    ("sensors.drone.imu.gyro_noise_radps=0.01", ("sensors", "drone", "imu", "gyro_noise_radps")),
])
def test_set_on_a_sensor_field_changes_exactly_that_field(assignment, key):
    before = load_scenario("default").resolved
    after = load_scenario("default", [assignment]).resolved
    assert list(changed(before, after)) == [key]


def test_partial_sensors_block_in_a_file_and_in_an_extends_overlay_merge_field_by_field(tmp_path):
    base = write(tmp_path, "base.yaml", f"""
        extends: {BASE}
        name: base
        sensors:
          drone:
            lidar: {{range_noise_m: 0.0}}
    """)
    write(tmp_path, "over.yaml", """
        extends: base.yaml
        name: over
        sensors:
          drone:
            lidar: {mount: {rpy_deg: [0, 0, 90]}}
          vehicle:
            imu: {accel_noise_mps2: 0.5}
    """)
    paper = load_scenario(BASE).resolved
    diff = changed(paper, load_scenario(base).resolved)
    assert set(diff) == {("name",), ("sensors", "drone", "lidar", "range_noise_m")}
    diff = changed(paper, load_scenario(tmp_path / "over.yaml").resolved)
    assert set(diff) == {("name",), ("sensors", "drone", "lidar", "range_noise_m"),
                         ("sensors", "drone", "lidar", "mount", "rpy_deg", 2),
                         ("sensors", "vehicle", "imu", "accel_noise_mps2")}
    s = load_scenario(tmp_path / "over.yaml").scenario
    assert [c.name for c in s.sensors.drone.cameras] == ["down"] and s.sensors.drone.imu is not None
    assert s.sensors.drone.lidar.lower_fov_deg == -90.0 and s.sensors.drone.lidar.mount.xyz_m == (0.0, 0.0, -0.2)


# ----------------------------------------------------------------------------------- 5: no NaN or infinity


def test_nan_and_infinity_are_rejected_in_every_float_field_with_the_key_path():
    resolved = load_scenario("default").resolved
    floats = [(p, v) for p, v in leaves(resolved) if isinstance(v, float)]
    assert len(floats) > 100  # every float of the full rig: geometry, noise, mounts, rates, limits
    for n, (path, _) in enumerate(floats):
        key = ".".join(str(k) for k in path)
        bad = (".nan", ".inf", "-.inf")[n % 3]
        assignment = f"{key}={bad}"
        if isinstance(path[-1], int):  # an item of a list (a vector): give the whole list, one item bad
            items = [bad if i == path[-1] else repr(v) for i, v in enumerate(_at(resolved, path[:-1]))]
            assignment = f"{'.'.join(str(k) for k in path[:-1])}=[{', '.join(items)}]"
        with pytest.raises(ScenarioError) as err:
            load_scenario("default", [assignment])
        assert err.value.path == key, (assignment, str(err.value))
        assert "finite number" in err.value.detail, (assignment, str(err.value))


def _at(data, path):
    for k in path:
        data = data[k]
    return data


def test_nan_in_a_file_is_named_with_its_line(tmp_path, capsys, no_world):
    f = write(tmp_path, "nan.yaml", f"""
        extends: {BASE}
        name: nan
        sensors:
          drone:
            lidar:
              mount: {{xyz_m: [0, 0, .nan]}}
    """)
    status, err = cli(capsys, "run", str(f), "--out", str(tmp_path / "out"))
    assert status == 2 and "Traceback" not in err
    assert err.strip() == f"cosim: error: {f}:7: sensors.drone.lidar.mount.xyz_m.2: Input should be a finite number, " \
                          "got NaN"


def test_validate_rejects_non_finite_transforms_and_labels(tmp_path):
    from cosim.io.synthetic import write_synthetic_episode
    from cosim.io.validate import validate_episode

    def poison(tick, topic, msg):
        if tick == 3 and topic == "/tf":
            msg.transforms[0].translation.x = math.nan
        if tick == 4 and topic == "/labels/objects":
            payload = msg[2]
            payload["objects"][0]["center_m"][2] = math.inf
        return msg

    good = validate_episode(write_synthetic_episode(tmp_path / "good.mcap", ticks=6, sensors=False))
    assert good.ok, good.lines()
    report = validate_episode(write_synthetic_episode(tmp_path / "bad.mcap", ticks=6, sensors=False, edit=poison))
    lines = report.lines()
    assert any("tick 3" in line and "/tf" in line and "is not finite" in line for line in lines), lines
    assert any("tick 4" in line and "objects.0.center_m.2 is not finite (inf)" in line for line in lines), lines


# ------------------------------------------------------------------------------------------------ 6: paths


@pytest.mark.parametrize("name", ["../../escape", "sub/dir", "/tmp/abs", "..", ".hidden", "-x", '"a\\0b"', "x" * 300])
def test_output_name_cannot_leave_the_output_folder(tmp_path, capsys, no_world, name):
    status, err = cli(capsys, "run", "default", "--out", str(tmp_path), "--set", f"output.name={name}")
    assert status == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert "output.name: output.name must be a plain file name inside the output folder" in err
    assert list(tmp_path.iterdir()) == []


def test_a_control_character_in_a_set_value_is_one_escaped_line(tmp_path, capsys, no_world):
    status, err = cli(capsys, "run", "default", "--out", str(tmp_path), "--set", "output.name=a\x00b")
    assert status == 2 and "\x00" not in err and len(err.strip().splitlines()) == 1, err
    assert "--set output.name=a\\x00b: output.name: value is not valid YAML: control character U+0000" in err, err


def test_unwritable_out_fails_before_the_world_is_built(tmp_path, capsys, no_world):
    a_file = write(tmp_path, "file.txt", "x")
    for out, why in [(a_file, "is a file, not a folder"), (a_file / "sub", "Not a directory"),
                     (Path("/proc/self"), "cannot write episodes into output folder /proc/self"),
                     (Path("/proc/cosim-nowhere"), "cannot write episodes into output folder")]:
        status, err = cli(capsys, "run", "default", "--no-sensors", "--out", str(out))
        assert status == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
        assert why in err and str(out) in err, err


# ------------------------------------------------------------------------------------------ 7: hostile files


def test_hostile_scenario_files_get_one_message_naming_the_file(tmp_path, capsys, no_world):
    cases = {
        "nul.yaml": (b"name: x\x00\nseed: 1\n", ":1: invalid YAML: control character U+0000"),
        "late_nul.yaml": (f"extends: {BASE}\nname: x\nseed: 1\x00\n".encode(), ":3: invalid YAML: control character"),
        "binary.yaml": (bytes(range(256)) * 4, "not a text file: byte 128 is not UTF-8"),
        "long_extends.yaml": (("name: x\nextends: " + "a" * 10_000 + "\n").encode(),
                              ":2: extends: cannot open the base scenario"),
        "nul_extends.yaml": (b'name: x\nextends: "a\\0b"\n', ":2: extends: cannot open the base scenario"),
        "deep.yaml": (("name: x\ndescription: " + "[" * 5000 + "]" * 5000 + "\n").encode(),
                      ":2: invalid YAML: brackets nested more than 100 levels deep"),
        "deep_block.yaml": (("name: x\ndescription:\n" + "".join(" " * i + "- \n" for i in range(0, 3000, 2))).encode(),
                            ":204: invalid YAML: indented more than 400 columns (nested too deeply)"),
        "tagged.yaml": (b"name: x\nseed: !!int nope\n", ":2: seed: invalid value 'nope'"),
        "date.yaml": (b"name: x\nduration_s: 2024-13-45\n", "duration_s"),
    }
    for name, (content, expect) in cases.items():
        f = write(tmp_path, name, content)
        status, err = cli(capsys, "run", str(f), "--out", str(tmp_path / "out"))
        assert status == 2, (name, err)
        assert "Traceback" not in err and len(err.strip().splitlines()) == 1, (name, err)
        assert str(f) in err and expect in err, (name, err)
        assert len(err) < 400, (name, err)  # a 10 000-character value is shortened


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
    write(tmp_path, "bad.net.xml", net)
    f = write(tmp_path, "s.yaml", "name: x\nmap: {kind: net, file: bad.net.xml}\n")
    status, err = cli(capsys, "run", str(f), "--no-sensors", "--out", str(tmp_path / "out"))
    assert status == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert f"map.file {tmp_path / 'bad.net.xml'}: not a usable SUMO network: {expect}" in err, err


# ----------------------------------------------------------------------------------------- 8: sweep sizes


@pytest.mark.parametrize("size, expect", [
    (f"count: {2**63}", ":3: count: Input should be less than or equal to 100000"),
    (f"count: {2**64 + 5}", ":3: count: Input should be less than or equal to 100000"),
    ("hours: 1.0e+12", ":3: hours: 1.8e+14 episodes cannot be planned: at most 100000 per plan"),
    ("hours: .inf", ":3: hours: Input should be a finite number"),
    ("count: .nan", ":3: count:"),
])
def test_sweep_sizes_that_cannot_be_planned_are_rejected_with_key_and_line(tmp_path, capsys, size, expect):
    f = write(tmp_path, "sweep.yaml", f"name: big\nbase: {BASE}\n{size}\n")
    status, err = cli(capsys, "batch", str(f), "--out", str(tmp_path / "out"), "--dry-run", "--calibrate-s", "0")
    assert status == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert f"{f}{expect}" in err, err


def test_scale_and_count_flags_that_cannot_be_planned_are_rejected(tmp_path, capsys):
    f = write(tmp_path, "sweep.yaml", f"name: ok\nbase: {BASE}\ncount: 2\n")
    for flags, expect in [(["--scale", "inf"], "--scale: scale must be a finite number > 0"),
                          (["--scale", "1e300"], "--count" if False else "episodes cannot be planned"),
                          (["--count", str(2**63)], "--count: 9.22337e+18 episodes cannot be planned")]:
        status, err = cli(capsys, "batch", str(f), "--out", str(tmp_path / "out"), "--dry-run", "--calibrate-s", "0",
                          *flags)
        assert status == 2 and "Traceback" not in err, err
        assert expect in err, err


# ------------------------------------------------------------------------------ issue 11 item 10: messages


def test_escort_target_with_no_connected_vehicles_says_so():
    with pytest.raises(ScenarioError) as err:
        load_scenario("default", ["agents.vehicles.count=0"])
    assert "the scenario has no connected vehicles (agents.vehicles.count is 0)" in str(err.value)
    assert "vehicle_-1" not in str(err.value)
    with pytest.raises(ScenarioError, match=r"has 1 connected vehicle \(vehicle_0\)"):
        load_scenario("default", ["agents.vehicles.count=1"])


def test_info_on_a_file_that_is_not_an_episode_exits_2(tmp_path, capsys):
    for content in (b"hello\n", bytes(range(256))):
        f = write(tmp_path, "x.mcap", content)
        status, err = cli(capsys, "info", str(f))
        assert status == 2 and "Traceback" not in err and f"{f}: not a readable MCAP file" in err, err


def test_dry_run_prints_the_resolved_scenario_and_builds_nothing(tmp_path, capsys, no_world):
    import yaml

    status = main(["run", "default", "--dry-run", "--out", str(tmp_path), "--set", "sensors.drone.lidar.dropout=0.1"])
    out = capsys.readouterr().out
    assert status == 0
    assert out.splitlines()[0] == f"# {tmp_path / 'default_s0.mcap'}: 15 ticks, 15 agents"
    resolved = yaml.safe_load(out)
    assert resolved == load_scenario("default", ["sensors.drone.lidar.dropout=0.1"]).resolved
    assert list(tmp_path.iterdir()) == []
