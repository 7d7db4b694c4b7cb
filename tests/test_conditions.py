"""An episode's description and ``cosim info`` say the conditions it was generated in, overrides included."""

from __future__ import annotations

import pytest

from cosim.scenario import load_scenario
from tests.helpers import REPO, run_cli


def test_overridden_conditions_are_named_in_the_description():
    plain = load_scenario("town_rural_night").scenario
    assert "night" in plain.description and "overridden" not in plain.description
    s = load_scenario("town_rural_night", ["environment.lighting=day", "environment.weather=foggy"]).scenario
    assert s.description == f"{plain.description} [overridden: weather foggy, not clear; lighting day, not night]"
    s = load_scenario("town_rural_night", ["environment={weather: rainy}", "map.kind=urban"]).scenario
    assert s.description.endswith("[overridden: environment urban, not rural; weather rainy, not clear; "
                                  "lighting day, not night]")  # the whole mapping replaced: lighting's default
    assert load_scenario("town_rural_night", ["environment.lighting=night"]).scenario.description == plain.description
    assert load_scenario("town_rural_night", ["seed=3"]).scenario.description == plain.description
    own = load_scenario("town_rural_night", ["environment.lighting=day", "description=my day run"]).scenario
    assert own.description == "my day run"


def test_a_sweeps_episodes_describe_their_own_conditions():
    from cosim.batch.plan import plan_file

    plan = plan_file(REPO / "sweeps" / "smoke.yaml")
    assert plan.episodes
    for e in plan.episodes:
        s = e.scenario
        changed = [f"{name} {s[a][b]}, not {base}" for name, (a, b), base in (
            ("environment", ("map", "kind"), "urban"),
            ("weather", ("environment", "weather"), "clear"),
            ("lighting", ("environment", "lighting"), "day"),
        ) if s[a][b] != base]  # scenarios/base/paper.yaml: urban, clear, day
        expected = f"AirV2X-Perception rig at 5 Hz [overridden: {'; '.join(changed)}]" if changed else None
        assert s["description"] == (expected or "AirV2X-Perception rig at 5 Hz"), e.id


@pytest.mark.integration
def test_cosim_info_says_the_conditions_set_on_the_command_line(tmp_path):
    run = run_cli("run", "town_rural_night", "--out", str(tmp_path), "--duration", "0.4", "--no-sensors", "-q",
                  "--set", "environment.lighting=day", "--set", "map.size_m=300",
                  "--set", "traffic.density_veh_per_km=6", "--set", "agents.rsus.count=1")
    assert run.returncode == 0, run.stderr
    info = run_cli("info", str(tmp_path / "town_rural_night_s0.mcap"))
    assert info.returncode == 0, info.stderr
    lines = {line.split()[0]: line for line in info.stdout.splitlines() if line.strip()}
    assert lines["conditions"].split(None, 1)[1].startswith("rural, clear, day;")
    assert lines["scenario"].endswith("rural roads at night: few lights, drones matter most "
                                      "[overridden: lighting day, not night]")
