"""The smallest closed-loop client: drone_0 follows vehicle_0, with a new waypoint above it every second.

    cosim run scenarios/strategy_hover.yaml --no-sensors --clients follow \
        --listen tcp/127.0.0.1:7447 --prefix demo &
    COSIM_ENDPOINT=tcp/127.0.0.1:7447 COSIM_PREFIX=demo python examples/client_follow.py
"""

import math

from cosim.client import actions, connect

with connect("follow") as client:
    for obs in client.ticks():
        poses = {a["agent_id"]: a["position_m"] for a in obs.labels.agents}
        (cx, cy, _), (dx, dy, _) = poses["vehicle_0"], poses["drone_0"]
        print(f"tick {obs.index}: drone_0 is {math.hypot(cx - dx, cy - dy):.1f} m from vehicle_0", flush=True)
        if obs.index % 5 == 0:
            client.act([actions.goto("drone_0", cx, cy, altitude_m=40.0, speed_mps=12.0)])
