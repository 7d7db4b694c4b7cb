"""Renderer v2 (issue 14): render processes, sun shadows, smooth night light, the camera model."""

from __future__ import annotations

import numpy as np
from cosim.sensors import SensorSuite
from cosim.sensors.synthetic import synthetic_snapshot, synthetic_world

from cosim.scenario.model import (
    AgentsSpec,
    CameraSpec,
    LidarSpec,
    RigSpec,
    RsuAgents,
    Scenario,
    SensorsSpec,
    VehicleAgents,
    default_rsu_rig,
    default_vehicle_rig,
)


def _small_rig_scenario(**env) -> Scenario:
    vcams = [CameraSpec(name=c.name, width=96, height=64, mount=c.mount) for c in default_vehicle_rig().cameras[:2]]
    rcams = [CameraSpec(name=c.name, width=96, height=64, mount=c.mount) for c in default_rsu_rig().cameras[:2]]
    lidar = LidarSpec(horizontal_resolution_deg=2.0)
    return Scenario(
        name="t", environment=env or {},
        agents=AgentsSpec(vehicles=VehicleAgents(count=3), rsus=RsuAgents(count=2), drones=[]),
        sensors=SensorsSpec(vehicle=RigSpec(lidar=lidar, cameras=vcams),
                            rsu=RigSpec(lidar=lidar, cameras=rcams)),
    )


def _frame_bytes(frames) -> list[tuple[str, bytes]]:
    from cosim.exporters.sensor_messages import frame_messages

    return [(topic, msg.SerializeToString() if hasattr(msg, "SerializeToString") else repr(msg).encode())
            for topic, msg in frame_messages(frames, frames.t_ns)]


def test_render_processes_give_the_same_bytes_as_one_process():
    sc = _small_rig_scenario(weather="rainy", lighting="dusk")
    world = synthetic_world()
    snaps = [synthetic_snapshot(3, 2, 0), synthetic_snapshot(3, 2, 0, tick=1)]
    out = []
    for processes in (0, 2):
        with SensorSuite(sc, world, processes=processes) as suite:
            rng = np.random.default_rng(7)
            out.append([_frame_bytes(suite.render(s, rng)) for s in snaps])
    assert [len(x) for x in out[0]] == [len(x) for x in out[1]]
    assert out[0] == out[1]
    assert any(t.endswith("/image") for t, _ in out[0][0])
