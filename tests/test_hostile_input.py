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
        assert len(err.replace(str(f), "F")) < 400, (name, err)  # a 10 000-character value is shortened


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
    expected = load_scenario("default", ["sensors.drone.lidar.dropout=0.1"]).resolved
    assert resolved == {**expected, "output": {**expected["output"], "dir": str(tmp_path)}}  # the --out used
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------- issue 27 item 8: strict kinds, bounds, long values


@pytest.mark.parametrize("assignment, key, message", [
    ("duration_s=true", "duration_s", "expected a number, got true"),
    ("duration_s='20'", "duration_s", 'expected a number, got "20"'),
    ("sensors.enabled=1", "sensors.enabled", "expected true or false, got 1"),
    ("comm.shadow_fading=yes_please", "comm.shadow_fading", 'expected true or false, got "yes_please"'),
    ("agents.vehicles.count=3.0", "agents.vehicles.count", "expected a whole number, got 3.0"),
    ("seed=false", "seed", "expected a whole number, got false"),
    ("sensors.vehicle.lidar.mount.xyz_m=[0, true, 0]", "sensors.vehicle.lidar.mount.xyz_m.1",
     "expected a number, got true"),
    ("traffic.mix.car=false", "traffic.mix.car", "expected a number, got false"),
])
def test_numbers_and_booleans_are_strict(capsys, no_world, assignment, key, message):
    status, err = cli(capsys, "run", "default", "--dry-run", "--set", assignment)
    assert status == 2
    assert err.strip().splitlines() == [f"cosim: error: --set {assignment}: {key}: {message}"]


def test_every_wrong_kind_in_a_file_is_listed(tmp_path, no_world):
    f = write(tmp_path, "kinds.yaml", """\
        extends: default
        name: kinds
        duration_s: true
        sensors: {enabled: 0}
        agents: {vehicles: {count: "4"}}
        """)
    with pytest.raises(ScenarioError) as err:
        load_scenario(f)
    assert [(p.line, p.path, p.detail) for p in err.value.problems] == [
        (3, "duration_s", "expected a number, got true"),
        (4, "sensors.enabled", "expected true or false, got 0"),
        (5, "agents.vehicles.count", 'expected a whole number, got "4"')]


def test_a_plain_exponent_is_a_number_as_in_yaml_1_2(tmp_path):
    f = write(tmp_path, "exp.yaml", "extends: default\nname: exp\nduration_s: 2e1\n")
    assert load_scenario(f).scenario.duration_s == 20.0


@pytest.mark.parametrize("assignment, key", [
    ("agents.drones.2.offset_m=[1.2e21, 0]", "agents.drones.2.offset_m.0"),
    ("agents.drones.0.start=[0, -5e8]", "agents.drones.0.start.1"),
    ("agents.drones.1.waypoints=[[0, 0], [1e12, 0]]", "agents.drones.1.waypoints.1.0"),
    ("events=[{kind: breakdown, position_m: [3e7, 0]}]", "events.0.position_m.0"),
    ("sensors.vehicle.lidar.mount.xyz_m=[0, 0, 1e4]", "sensors.vehicle.lidar.mount.xyz_m.2"),
    ("sensors.drone.gnss.noise_m=1e9", "sensors.drone.gnss.noise_m"),
    ("geo_origin.alt_m=1e30", "geo_origin.alt_m"),
    ("runtime.tick_timeout_s=1e300", "runtime.tick_timeout_s"),
    ("agents.rsus.height_m=[6, 1e6]", "agents.rsus.height_m"),
    ("traffic.mix.car=1e300", "traffic.mix"),
])
def test_physical_quantities_have_bounds(capsys, no_world, assignment, key):
    status, err = cli(capsys, "run", "default", "--dry-run", "--set", assignment)
    assert status == 2
    assert err.startswith(f"cosim: error: --set {assignment}: {key}: "), err


def test_a_long_bad_value_is_cut_in_the_message(tmp_path, capsys, no_world):
    long = "x" * 10_000
    f = write(tmp_path, "long.yaml", f"extends: default\nname: long\nduration_s: {long}\noutput: {{name: {long}}}\n"
                                     f"{'k' * 1000}: 1\n")  # PyYAML's longest plain key
    status, err = cli(capsys, "run", str(f), "--dry-run")
    assert status == 2 and "Traceback" not in err
    lines = err.strip().splitlines()
    assert lines[0] == f"cosim: error: {f}: 3 problems:"
    # the file's path (longer under an xdist worker's temporary folder) is not the value being cut
    assert all(len(line.replace(str(f), "F")) < 500 for line in lines), [len(line) for line in lines]
    assert "(10002 characters)" in err and "output.name: " in err and "(1000 characters)" in err


# --------------------------------------------------------------------- issue 27 item 8: unusable output folders


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
        status, err = cli(capsys, *args)
        assert status == 2, (what, status, err)
        lines = err.strip().splitlines()
        assert len(lines) == 1, (what, err)
        assert lines[0].startswith((f"cosim: error: cannot write episodes into output folder {out}",
                                    f"cosim: error: output folder {out} is a file")), (what, err)
        assert "Traceback" not in err
    assert not (read_only_dir / "sub").exists()


def test_run_dry_run_checks_the_folder_without_creating_it(tmp_path, capsys, no_world):
    out = tmp_path / "new" / "folder"
    status, err = cli(capsys, "run", "default", "--dry-run", "--out", str(out))
    assert status == 0 and not (tmp_path / "new").exists(), err
    status, err = cli(capsys, "run", "default", "--dry-run", "--out", "/proc/x/y")
    assert status == 2 and err.startswith("cosim: error: cannot write episodes into output folder /proc/x/y (in "
                                          "/proc)"), err


# ------------------------------------------------------------- issue 27 item 8: a killed conductor's leftovers

WRITER = """
import sys, time
from pathlib import Path
from cosim.io.writer import EpisodeWriter
w = EpisodeWriter(Path(sys.argv[1]))
print(w.tmp_path, flush=True)
time.sleep(120)
"""


def killed_writer(final: Path) -> Path:
    """Start an episode writer in another process, SIGKILL it; returns the partial file it left."""
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(final)], stdout=subprocess.PIPE, text=True)
    partial = Path(proc.stdout.readline().strip())
    proc.kill()
    proc.wait(10)
    return partial


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
            status, err = cli(capsys, "run", "default", "--out", str(out), "--no-sensors")
    finally:
        holder.close()
    assert status == 2 and "stopped after the output folder was prepared" in err
    assert not stale.exists() and not legacy.exists() and live.exists()
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any(str(stale) in w and "left by a run that was killed" in w for w in warned), warned
    assert any(str(legacy) in w for w in warned), warned


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


def test_netconvert_and_other_sumo_tools_die_with_the_conductor(tmp_path):
    """A process running a SUMO tool through the world builder is SIGKILLed: the tool goes too."""
    import subprocess
    import sys
    import time

    import psutil

    script = ("import sys\nfrom pathlib import Path\nimport cosim.world.netgen as n\n"
              "n.sumo_binary = lambda name: '/bin/sleep'\nprint('go', flush=True)\n"
              "n._run_tool('netconvert', ['60'], Path('.'))\n")
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, cwd=tmp_path)
    assert proc.stdout.readline().strip() == "go"
    deadline = time.monotonic() + 20
    children: list[psutil.Process] = []
    while not children and time.monotonic() < deadline:
        children = psutil.Process(proc.pid).children()
        time.sleep(0.02)
    assert children and children[0].name() == "sleep", children
    proc.kill()
    proc.wait(10)
    _, alive = psutil.wait_procs(children, timeout=5)
    assert not alive, alive
