"""Turn the workers' replies for one tick into an immutable :class:`WorldSnapshot` (pure code)."""

from __future__ import annotations

from collections.abc import Sequence

from cosim.geometry import quat_from_rpy
from cosim.protocol import DroneState, EscortTarget, VehicleState
from cosim.snapshot import Actor, AgentState, TrafficLight, WorldSnapshot
from cosim.world.traffic_lights import head_colour, signal_heads
from cosim.world.types import World

GRAVITY_MPS2 = 9.80665


class TrackRegistry:
    """Hands out track ids: one integer per actor for its lifetime in the episode, never reused.

    Ids are given in order of first appearance, and within a tick in the order the actors are
    passed (workers reply sorted by id), so they depend only on the simulation, not on timing.
    """

    def __init__(self) -> None:
        self._ids: dict[tuple[str, str], int] = {}

    def __len__(self) -> int:
        return len(self._ids)

    def get(self, source: str, source_id: str) -> int | None:
        """The track id of an actor already seen, or None (hands out nothing)."""
        return self._ids.get((source, source_id))

    def __call__(self, source: str, source_id: str) -> int:
        key = (source, source_id)
        track = self._ids.get(key)
        if track is None:
            track = len(self._ids) + 1
            self._ids[key] = track
        return track


def vehicle_actor(v: VehicleState, track_id: int) -> Actor:
    return Actor(
        track_id=track_id,
        cls=v.cls,
        center_m=tuple(v.center_m),
        size_m=tuple(v.size_m),
        rotation=quat_from_rpy(0.0, v.pitch_rad, v.yaw_rad),
        velocity_mps=tuple(v.velocity_mps),
        agent_id=v.agent_id,
        source_id=v.sumo_id,
        gait_phase=v.gait_phase,
        hazard_lamps_on=v.hazard_lamps_on,
    )


def vehicle_agent(v: VehicleState, track_id: int) -> AgentState:
    """A connected vehicle's platform: base_link on the ground under the box centre, FLU."""
    cx, cy, cz = v.center_m
    return AgentState(
        agent_id=v.agent_id or v.sumo_id,
        kind="vehicle",
        position_m=(cx, cy, cz - 0.5 * v.size_m[2]),
        rotation=quat_from_rpy(0.0, v.pitch_rad, v.yaw_rad),
        velocity_mps=tuple(v.velocity_mps),
        angular_rate_radps=(0.0, 0.0, v.yaw_rate_radps),
        # body-frame specific force: longitudinal accel, centripetal, gravity reaction
        specific_force_mps2=(v.accel_mps2, v.speed_mps * v.yaw_rate_radps, GRAVITY_MPS2),
        track_id=track_id,
        extra={"speed_mps": v.speed_mps},
    )


def drone_actor(d: DroneState, track_id: int) -> Actor:
    return Actor(
        track_id=track_id,
        cls="drone",
        center_m=tuple(d.position_m),
        size_m=tuple(d.size_m),
        rotation=tuple(d.rotation),
        velocity_mps=tuple(d.velocity_mps),
        agent_id=d.agent_id,
        source_id=d.agent_id,
    )


def drone_agent(d: DroneState, track_id: int) -> AgentState:
    return AgentState(
        agent_id=d.agent_id,
        kind="drone",
        position_m=tuple(d.position_m),
        rotation=tuple(d.rotation),
        velocity_mps=tuple(d.velocity_mps),
        angular_rate_radps=tuple(d.angular_rate_radps),
        specific_force_mps2=tuple(d.specific_force_mps2),
        track_id=track_id,
        gimbal_rotation=tuple(d.gimbal_rotation),
        extra={"strategy": d.strategy, "strategy_state": d.strategy_state, "energy_used_j": d.energy_used_j},
    )


def build_snapshot(
    tick: int,
    t_ns: int,
    vehicles: Sequence[VehicleState],
    drones: Sequence[DroneState],
    world: World,
    tracks: TrackRegistry,
    signals: dict[str, str] | None = None,
) -> WorldSnapshot:
    """One tick's snapshot: drones first (stable ids), then vehicles, then the RSUs' static poses; with
    ``signals`` (SUMO's state string per traffic-light id, the traffic worker's reply) every signal head
    of the network and the colour it shows."""
    actors: list[Actor] = []
    agents: list[AgentState] = []
    for d in drones:
        tid = tracks("drone", d.agent_id)
        actors.append(drone_actor(d, tid))
        agents.append(drone_agent(d, tid))
    for v in vehicles:
        tid = tracks("sumo", v.sumo_id)
        actors.append(vehicle_actor(v, tid))
        if v.agent_id:
            agents.append(vehicle_agent(v, tid))
    for p in world.parked:
        actors.append(Actor(track_id=tracks("parked", p.parked_id), cls=p.cls, center_m=p.center_m, size_m=p.size_m,
                            rotation=quat_from_rpy(0.0, 0.0, p.yaw_rad), velocity_mps=(0.0, 0.0, 0.0),
                            source_id=p.parked_id, parked=True))
    for r in world.rsus:
        agents.append(AgentState(agent_id=r.agent_id, kind="rsu", position_m=tuple(r.position_m),
                                 rotation=quat_from_rpy(0.0, 0.0, r.yaw_rad), specific_force_mps2=(0.0, 0.0, 0.0),
                                 extra={"junction_id": r.junction_id, "height_m": r.height_m}))
    agents.sort(key=_agent_order)
    return WorldSnapshot(tick=tick, t_ns=t_ns, actors=tuple(actors), agents=tuple(agents),
                         traffic_lights=traffic_lights(world, signals) if signals else ())


def traffic_lights(world: World, signals: dict[str, str]) -> tuple[TrafficLight, ...]:
    """Every signal head of ``world``'s network showing ``signals`` (tls id -> SUMO state string)."""
    out = []
    for h in signal_heads(world.net_xml):
        state = signals.get(h.tls, "")
        chars = "".join(state[i] for i in h.links if i < len(state))
        out.append(TrafficLight(h.head_id, h.center_m, h.yaw_rad, head_colour(state, h.links), chars))
    return tuple(out)


def _agent_order(a: AgentState) -> tuple[int, int]:
    kind, _, index = a.agent_id.rpartition("_")
    return ({"vehicle": 0, "rsu": 1, "drone": 2}.get(kind, 3), int(index) if index.isdigit() else 0)


def escort_targets_of(vehicles: Sequence[VehicleState], assignments: dict[str, str]) -> dict[str, EscortTarget]:
    """What each escorting drone needs of its vehicle (drone id -> target), from the traffic worker's reply."""
    by_agent = {v.agent_id: v for v in vehicles if v.agent_id}
    return {
        drone_id: EscortTarget(tuple(v.center_m), v.yaw_rad, tuple(v.velocity_mps))
        for drone_id, vehicle_id in assignments.items()
        if (v := by_agent.get(vehicle_id)) is not None
    }
