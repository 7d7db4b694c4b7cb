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

GOAL_XY_M = (20.0, -15.0)  # drone_0's waypoint in the main mode
GOAL_ALTITUDE_M = 35.0
SLOW_MPS = 5.0  # vehicle_0's commanded speed
MAIN_PLAN = {
    0: [actions.goto("drone_0", *GOAL_XY_M, altitude_m=GOAL_ALTITUDE_M, speed_mps=8.0),
        actions.set_speed("vehicle_0", SLOW_MPS)],
    1: [actions.strategy("drone_1", strategy="escort", target="vehicle_0", altitude_m=60.0),
        actions.land("drone_2", speed_mps=4.0)],
    4: [actions.change_lane("vehicle_0", 0)],
}


def main(mode: str, name: str) -> int:
    with connect(name) as client:
        for obs in client.ticks():
            labels = obs.labels
            line: dict = {"tick": obs.index, "last": obs.last}
            for a in labels.agents:
                if a["kind"] == "drone":
                    line[a["agent_id"]] = [*a["position_m"], a["extra"]["strategy"], a["extra"]["strategy_state"]]
            for aid, v in zip(labels.agent_ids, labels.velocities_mps, strict=True):
                if aid == "vehicle_0":
                    line["vehicle_0_speed_mps"] = float(np.hypot(v[0], v[1]))
            if mode == "main":  # every acceptance action on a fixed plan, so two runs give the same file
                line["accepted"] = client.act(MAIN_PLAN.get(obs.index, [])) if obs.index != 2 else None
                if obs.index == 2:
                    try:
                        client.act([actions.goto("drone_9", 0.0, 0.0, 30.0, 5.0)])
                    except ActionRejected as exc:
                        line["rejected"] = str(exc)
            elif mode == "silent" and obs.index == 2:
                print(json.dumps(line), flush=True)
                time.sleep(3600)
            print(json.dumps(line), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2]))
