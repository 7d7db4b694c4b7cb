"""Scenario loading: schema, overlays, overrides and the messages users see for bad input."""

from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

from cosim.errors import ScenarioError
from cosim.scenario import load_scenario, shipped_scenarios
from cosim.scenario.model import EscortDrone, HoverDrone, PatrolDrone, Scenario
from tests.helpers import SCENARIOS, run_cli, write_file
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
