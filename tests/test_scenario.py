"""Scenario loading: schema, overlays, overrides and the messages users see for bad input."""

from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

from cosim.errors import ScenarioError
from cosim.scenario import load_scenario, shipped_scenarios
from cosim.scenario.model import EscortDrone, HoverDrone, PatrolDrone, Scenario
from tests.helpers import PAPER, SCENARIOS, run_cli, write_file
from tests.helpers import cli_in_process as cli


def write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(textwrap.dedent(text).lstrip())
    return p


def test_every_shipped_scenario_loads_and_covers_the_papers_conditions():
    loaded = [load_scenario(p).scenario for _, p in shipped_scenarios()]
    names = {s.name for s in loaded}
    assert "town_rural_night" in names and "default" in names
    assert {s.environment.weather for s in loaded} == {"clear", "cloudy", "foggy", "rainy"}
    assert {s.environment.lighting for s in loaded} == {"day", "dusk", "night"}
    assert {s.map.kind for s in loaded} >= {"urban", "suburban", "rural", "highway"}
    assert {d.strategy for s in loaded for d in s.agents.drones} == {"hover", "patrol", "escort"}
    assert {s.agents.drone_backend_of(i) for s in loaded for i in range(len(s.agents.drones))} == {"jsbsim", "pybullet"}


def _leaves(data, path=()):
    if isinstance(data, dict):
        for k, v in data.items():
            yield from _leaves(v, (*path, k))
    else:
        yield path, data


def test_shipped_scenarios_are_overlays_of_one_base():
    """Variants by override, never by copy: each scenario extends the base and restates none of its values."""
    from cosim.scenario.loader import load_with_extends, parse_yaml

    base = load_with_extends(SCENARIOS / "base" / "paper.yaml").data
    for _, path in shipped_scenarios():
        own = parse_yaml(path).data
        assert own.pop("extends") == "base/paper.yaml", path.name
        for key, value in _leaves(own):
            node = base
            for k in key:
                node = node.get(k) if isinstance(node, dict) else None
            assert node != value, f"{path.name} restates {'.'.join(key)} = {value!r} from the base"


def test_defaults_match_the_paper_rig():
    s = Scenario(name="x")
    assert s.tick_hz == 5 and s.tick_ns == 200_000_000
    v, r, d = s.sensors.vehicle, s.sensors.rsu, s.sensors.drone
    assert [c.name for c in v.cameras] == ["front", "front_left", "front_right", "rear", "rear_left", "rear_right"]
    assert [c.name for c in r.cameras] == ["front", "left", "right", "rear"]
    assert [c.name for c in d.cameras] == ["down"] and d.cameras[0].gimbal
    for rig in (v, r, d):
        assert rig.lidar.channels == 64 and rig.lidar.rotation_hz == 20
        assert all((c.width, c.height, c.fov_deg) == (1280, 720, 110) for c in rig.cameras)
        assert rig.gnss is not None
    assert (v.lidar.upper_fov_deg, v.lidar.lower_fov_deg) == (10, -38)
    assert (d.lidar.upper_fov_deg, d.lidar.lower_fov_deg) == (-30, -90)
    assert v.imu is not None and d.imu is not None and r.imu is None


def test_extends_overlays_and_set_overrides(tmp_path):
    write(tmp_path, "base.yaml", """
        name: base
        seed: 1
        environment: {weather: rainy, lighting: dusk}
        agents:
          drones:
            - {strategy: hover}
        """)
    child = write(tmp_path, "child.yaml", """
        extends: base.yaml
        name: child
        environment: {lighting: night}
        """)
    s = load_scenario(child, ["seed=9", "agents.drones.0.altitude_m=75", "map.kind=rural"]).scenario
    assert (s.name, s.seed) == ("child", 9)
    assert (s.environment.weather, s.environment.lighting) == ("rainy", "night")
    assert isinstance(s.agents.drones[0], HoverDrone) and s.agents.drones[0].altitude_m == 75
    assert s.map.kind == "rural"
    s2 = load_scenario(child, ["agents.drones=[{strategy: patrol}, {strategy: escort, target: vehicle_1}]"]).scenario
    assert isinstance(s2.agents.drones[0], PatrolDrone) and isinstance(s2.agents.drones[1], EscortDrone)


def test_scenarios_are_frozen():
    s = Scenario(name="x")
    with pytest.raises(Exception, match="frozen"):
        s.seed = 3  # type: ignore[misc]


@pytest.mark.parametrize(
    ("text", "path", "line", "words"),
    [
        ("name: t\nenvironment:\n  wether: foggy\n", "environment.wether", 3,
         ["unknown key", "did you mean 'weather'"]),
        ("name: t\nenvironment:\n  weather: snowy\n", "environment.weather", 3, ["'clear'", '"snowy"']),
        ("name: t\ntraffic:\n  step_hz: 7\n", "traffic.step_hz", 3, ["does not divide the tick"]),
        ("name: t\nagents:\n  drone_physics_hz: 12\n", "agents.drone_physics_hz", 3, ["does not divide"]),
        ("name: t\nduration_s: 1.1\n", "duration_s", 2, ["whole number of ticks"]),
        ("name: t\nagents:\n  vehicles: {count: 1}\n  drones:\n    - strategy: escort\n      target: vehicle_4\n",
         "agents.drones.0.target", 6, ["does not exist"]),
        ("name: t\nagents:\n  drones:\n    - strategy: orbit\n", "agents.drones.0", 4, ["orbit"]),
        ("name: t\nseed: -1\n", "seed", 2, ["greater than or equal to 0"]),
        ("name: t\nname: u\n", "name", 2, ["appears twice"]),
        ("name: t\nmap:\n  kind: net\n", "map.file", 2, ["needs map.file"]),
    ],
)
def test_bad_input_names_key_path_and_line(tmp_path, text, path, line, words):
    f = tmp_path / "bad.yaml"
    f.write_text(text)
    with pytest.raises(ScenarioError) as err:
        load_scenario(f)
    assert err.value.path == path
    assert err.value.line == line
    for w in words:
        assert w in str(err.value)
    assert f"bad.yaml:{line}: {path}:" in str(err.value)


def test_error_in_a_base_file_points_into_the_base(tmp_path):
    write(tmp_path, "base.yaml", "name: b\nenvironment:\n  lighting: noon\n")
    child = write(tmp_path, "child.yaml", "extends: base.yaml\nname: c\n")
    with pytest.raises(ScenarioError) as err:
        load_scenario(child)
    assert err.value.source.endswith("base.yaml") and err.value.line == 3


def test_bad_set_override_is_named():
    with pytest.raises(ScenarioError, match=r"--set agents.drones.9.altitude_m=3: agents.drones.9"):
        load_scenario(SCENARIOS / "default.yaml", ["agents.drones.9.altitude_m=3"])
    with pytest.raises(ScenarioError, match=r"environment.weather"):
        load_scenario(SCENARIOS / "default.yaml", ["environment.weather=hail"])


def test_extends_cycle_is_reported(tmp_path):
    write(tmp_path, "a.yaml", "extends: b.yaml\nname: a\n")
    write(tmp_path, "b.yaml", "extends: a.yaml\nname: b\n")
    with pytest.raises(ScenarioError, match="cycle"):
        load_scenario(tmp_path / "a.yaml")


@pytest.mark.parametrize(
    ("text", "expect"),
    [
        ("name: t\nenvironment:\n  wether: foggy\n", "bad.yaml:3: environment.wether: unknown key 'wether'"),
        ("name: t\nenvironment:\n  weather: snowy\n", "bad.yaml:3: environment.weather: Input should be"),
        ("name: t\ntraffic:\n  step_hz: 7\n", "bad.yaml:3: traffic.step_hz: traffic.step_hz = 7 Hz does not divide"),
    ],
)
@pytest.mark.integration  # a `cosim run` process (refused before any engine starts)
def test_cli_exits_2_with_one_message_and_no_traceback(tmp_path, text, expect):
    f = tmp_path / "bad.yaml"
    f.write_text(text)
    out = tmp_path / "out"
    r = run_cli("run", str(f), "--out", str(out), timeout=60)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    assert expect in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert not out.exists() or not any(out.iterdir())


def test_cli_lists_shipped_scenarios_and_version():
    r = run_cli("scenarios", timeout=60)
    assert r.returncode == 0
    lines = r.stdout.strip().splitlines()
    assert len(lines) == len(shipped_scenarios())
    assert any(line.startswith("town_rural_night ") and "rural" in line and "night" in line for line in lines)
    assert "INVALID" not in r.stdout
    v = run_cli("--version", timeout=60)
    assert v.returncode == 0 and v.stdout.startswith("cosim ")


def test_image_scale_shrinks_every_camera_of_every_rig():
    s = load_scenario(SCENARIOS / "default.yaml", ["sensors.image_scale=0.25"]).scenario
    for agent in ("vehicle_0", "rsu_1", "drone_2"):
        cams = s.rig_for(agent).cameras
        assert cams and all((c.width, c.height) == (320, 180) for c in cams)
        assert [c.fov_deg for c in cams] == [c.fov_deg for c in Scenario(name="x").rig_for(agent).cameras]
    assert all(c.width == 1280 for c in Scenario(name="x").rig_for("vehicle_0").cameras)


# ---------------------------------------------- extends:, scenario names, several problems, --set attribution


@pytest.mark.parametrize("parent", ["base/paper", "base/paper.yaml", "default", "town_rural_night.yaml"])
def test_extends_takes_a_shipped_scenario_name_from_any_folder(tmp_path, parent):
    f = write_file(tmp_path / "elsewhere", "mine.yaml", f"extends: {parent}\nname: mine\nduration_s: 1\n")
    loaded = load_scenario(f)
    assert loaded.scenario.name == "mine" and loaded.scenario.duration_s == 1


def test_extends_prefers_a_file_beside_the_scenario_to_a_shipped_one(tmp_path):
    write_file(tmp_path, "default.yaml", "name: local_base\nseed: 77\n")
    f = write_file(tmp_path, "child.yaml", "extends: default\nname: child\n")
    assert load_scenario(f).scenario.seed == 77


def test_a_misspelt_base_scenario_gets_a_did_you_mean(tmp_path):
    f = write_file(tmp_path, "child.yaml", "name: child\nextends: town_rual_night\n")
    with pytest.raises(ScenarioError) as err:
        load_scenario(f)
    assert err.value.line == 2 and err.value.path == "extends"
    assert "did you mean 'town_rural_night'?" in str(err.value)


def test_a_misspelt_scenario_name_gets_a_did_you_mean(capsys):
    status, _, err = cli(capsys, "run", "town_rual_nigth", "--dry-run")
    assert status == 2
    assert err.startswith("cosim: error: ") and "did you mean 'town_rural_night'?" in err


def test_a_scenario_with_several_problems_lists_them_all_with_file_line_and_key(tmp_path, capsys):
    f = write_file(tmp_path, "bad.yaml", """\
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
    f = write_file(tmp_path, "many.yaml", f"name: many\ntraffic:\n{keys}")
    with pytest.raises(ScenarioError) as err:
        load_scenario(f)
    assert len(err.value.problems) == MAX_PROBLEMS and err.value.more == 5
    assert str(err.value).endswith("... and 5 more")


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
    f = write_file(tmp_path, "bad.yaml", "extends: default\nname: bad\nduration_s: -1\n")
    with pytest.raises(ScenarioError) as err:
        load_scenario(f, ["environment.weather=foggy"])
    assert err.value.source == str(f.resolve()) and err.value.line == 3


# ----------------------------- overrides merge field by field; no NaN; strict kinds and bounds; hostile files


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
    base = write_file(tmp_path, "base.yaml", f"""
        extends: {PAPER}
        name: base
        sensors:
          drone:
            lidar: {{range_noise_m: 0.0}}
    """)
    write_file(tmp_path, "over.yaml", """
        extends: base.yaml
        name: over
        sensors:
          drone:
            lidar: {mount: {rpy_deg: [0, 0, 90]}}
          vehicle:
            imu: {accel_noise_mps2: 0.5}
    """)
    paper = load_scenario(PAPER).resolved
    diff = changed(paper, load_scenario(base).resolved)
    assert set(diff) == {("name",), ("sensors", "drone", "lidar", "range_noise_m")}
    diff = changed(paper, load_scenario(tmp_path / "over.yaml").resolved)
    assert set(diff) == {("name",), ("sensors", "drone", "lidar", "range_noise_m"),
                         ("sensors", "drone", "lidar", "mount", "rpy_deg", 2),
                         ("sensors", "vehicle", "imu", "accel_noise_mps2")}
    s = load_scenario(tmp_path / "over.yaml").scenario
    assert [c.name for c in s.sensors.drone.cameras] == ["down"] and s.sensors.drone.imu is not None
    assert s.sensors.drone.lidar.lower_fov_deg == -90.0 and s.sensors.drone.lidar.mount.xyz_m == (0.0, 0.0, -0.2)


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
    f = write_file(tmp_path, "nan.yaml", f"""
        extends: {PAPER}
        name: nan
        sensors:
          drone:
            lidar:
              mount: {{xyz_m: [0, 0, .nan]}}
    """)
    status, _, err = cli(capsys, "run", str(f), "--out", str(tmp_path / "out"))
    assert status == 2 and "Traceback" not in err
    assert err.strip() == f"cosim: error: {f}:7: sensors.drone.lidar.mount.xyz_m.2: Input should be a finite number, " \
                          "got NaN"


def test_a_control_character_in_a_set_value_is_one_escaped_line(tmp_path, capsys, no_world):
    status, _, err = cli(capsys, "run", "default", "--out", str(tmp_path), "--set", "output.name=a\x00b")
    assert status == 2 and "\x00" not in err and len(err.strip().splitlines()) == 1, err
    assert "--set output.name=a\\x00b: output.name: value is not valid YAML: control character U+0000" in err, err


def test_hostile_scenario_files_get_one_message_naming_the_file(tmp_path, capsys, no_world):
    cases = {
        "nul.yaml": (b"name: x\x00\nseed: 1\n", ":1: invalid YAML: control character U+0000"),
        "late_nul.yaml": (f"extends: {PAPER}\nname: x\nseed: 1\x00\n".encode(), ":3: invalid YAML: control character"),
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
        f = write_file(tmp_path, name, content)
        status, _, err = cli(capsys, "run", str(f), "--out", str(tmp_path / "out"))
        assert status == 2, (name, err)
        assert "Traceback" not in err and len(err.strip().splitlines()) == 1, (name, err)
        assert str(f) in err and expect in err, (name, err)
        assert len(err.replace(str(f), "F")) < 400, (name, err)  # a 10 000-character value is shortened


def test_escort_target_with_no_connected_vehicles_says_so():
    with pytest.raises(ScenarioError) as err:
        load_scenario("default", ["agents.vehicles.count=0"])
    assert "the scenario has no connected vehicles (agents.vehicles.count is 0)" in str(err.value)
    assert "vehicle_-1" not in str(err.value)
    with pytest.raises(ScenarioError, match=r"has 1 connected vehicle \(vehicle_0\)"):
        load_scenario("default", ["agents.vehicles.count=1"])


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
    status, _, err = cli(capsys, "run", "default", "--dry-run", "--set", assignment)
    assert status == 2
    assert err.strip().splitlines() == [f"cosim: error: --set {assignment}: {key}: {message}"]


def test_every_wrong_kind_in_a_file_is_listed(tmp_path, no_world):
    f = write_file(tmp_path, "kinds.yaml", """\
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
    f = write_file(tmp_path, "exp.yaml", "extends: default\nname: exp\nduration_s: 2e1\n")
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
    status, _, err = cli(capsys, "run", "default", "--dry-run", "--set", assignment)
    assert status == 2
    assert err.startswith(f"cosim: error: --set {assignment}: {key}: "), err


def test_a_long_bad_value_is_cut_in_the_message(tmp_path, capsys, no_world):
    long = "x" * 10_000
    f = write_file(tmp_path, "long.yaml",
                   f"extends: default\nname: long\nduration_s: {long}\noutput: {{name: {long}}}\n"
                   f"{'k' * 1000}: 1\n")  # PyYAML's longest plain key
    status, _, err = cli(capsys, "run", str(f), "--dry-run")
    assert status == 2 and "Traceback" not in err
    lines = err.strip().splitlines()
    assert lines[0] == f"cosim: error: {f}: 3 problems:"
    # the file's path (longer under an xdist worker's temporary folder) is not the value being cut
    assert all(len(line.replace(str(f), "F")) < 500 for line in lines), [len(line) for line in lines]
    assert "(10002 characters)" in err and "output.name: " in err and "(1000 characters)" in err
