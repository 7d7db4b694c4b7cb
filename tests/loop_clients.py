"""Closed-loop clients started as real processes by tests/test_client.py: ``python -m tests.loop_clients MODE NAME``.

The conductor's endpoint and prefix come from COSIM_ENDPOINT / COSIM_PREFIX. Each mode prints one JSON
line per tick on stdout (flushed), so a test can follow it and read what it saw.
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np

from cosim.client import ActionRejected, actions, connect

GOAL_XY_M = (20.0, -15.0)  # drone_0's waypoint in the goto mode
GOAL_ALTITUDE_M = 35.0


def main(mode: str, name: str) -> int:
    with connect(name) as client:
        for obs in client.ticks():
            labels = obs.labels
            line: dict = {"tick": obs.index, "last": obs.last}
            for a in labels.agents:
                if a["agent_id"] == "drone_0":
                    line["drone_0"] = a["position_m"]
                    line["drone_0_state"] = a["extra"].get("strategy_state")
            for aid, v in zip(labels.agent_ids, labels.velocities_mps, strict=True):
                if aid == "vehicle_0":
                    line["vehicle_0_speed_mps"] = float(np.hypot(v[0], v[1]))
            if mode == "goto" and obs.index == 0:
                client.act([actions.goto("drone_0", *GOAL_XY_M, altitude_m=GOAL_ALTITUDE_M, speed_mps=8.0)])
            elif mode == "slow" and obs.index == 0:
                client.act([actions.set_speed("vehicle_0", 5.0)])
            elif mode == "missing" and obs.index == 1:
                try:
                    client.act([actions.goto("drone_9", 0.0, 0.0, 30.0, 5.0)])
                except ActionRejected as exc:
                    line["rejected"] = str(exc)
            elif mode == "silent" and obs.index == 2:
                print(json.dumps(line), flush=True)
                time.sleep(3600)
            elif mode == "script":  # deterministic: a fixed plan by tick
                plan = {1: [actions.goto("drone_0", 10.0, 10.0, 30.0, 6.0)],
                        3: [actions.slow_down("vehicle_0", 3.0, 1.0), actions.land("drone_0")]}
                client.act(plan.get(obs.index, []))
            print(json.dumps(line), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2]))
