"""Escort tracking in real episodes: SUMO drives the cars, the conductor feeds the drones.

Runs scenarios (labels only) and prints, per escorting drone, the RMS and max horizontal distance to
its commanded offset point, and the wall time of the run.

    PYTHONPATH=. .venv/bin/python benchmarks/escort_tracking.py [--duration 60] [SCENARIO ...]
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from mcap.reader import make_reader

from benchmarks.drone_tracking import escort_errors, rms
from cosim.runner import run_episode
from cosim.scenario import load_scenario

DEFAULT = ["scenarios/strategy_escort.yaml", "scenarios/town_rural_night.yaml", "scenarios/highway_day_clear.yaml"]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scenarios", nargs="*", default=DEFAULT)
    p.add_argument("--duration", type=float, default=60.0)
    args = p.parse_args()
    for path in args.scenarios:
        loaded = load_scenario(path, [f"duration_s={args.duration}", "sensors.enabled=false"])
        with tempfile.TemporaryDirectory() as out:
            result = run_episode(loaded, Path(out))
            with open(result.path, "rb") as f:
                labels = [json.loads(m.data) for _, _, m in make_reader(f).iter_messages(topics=["/labels/objects"])]
        for drone_id, e in escort_errors(labels, loaded.scenario).items():
            print(f"{loaded.scenario.name:<22} {drone_id}  escort error RMS {rms(e):5.2f} m, max {max(e):6.2f} m "
                  f"over {len(e)} ticks  (run {result.wall_time_s:.1f} s wall)")


if __name__ == "__main__":
    main()
