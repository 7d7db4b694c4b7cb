"""The immutable world snapshot: every actor and agent at one tick.

Sensors and labels are pure functions of a snapshot plus the static world; they never reach back
into SUMO or the dynamics engines. A snapshot can be rebuilt from an episode file.
Frames: positions in ``map`` (ENU, metres); rotations are (x, y, z, w) quaternions map <- body.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]

AgentKind = Literal["vehicle", "rsu", "drone"]


@dataclass(frozen=True, slots=True)
class Actor:
    """A labelled object: a road user or a drone.

    ``center_m`` is the 3D box centre, ``size_m`` is (length, width, height) along body x, y, z,
    ``rotation`` is map <- body. ``agent_id`` is set for connected agents (``vehicle_0``, ``drone_2``).
    """

    track_id: int
    cls: str
    center_m: Vec3
    size_m: Vec3
    rotation: Quat
    velocity_mps: Vec3
    agent_id: str | None = None
    source_id: str = ""  # the engine's own id (SUMO vehicle id, drone id)
    parked: bool = False  # a parked vehicle (never moves; not in SUMO)
    gait_phase: float = 0.0  # pedestrians: 0..1 through the gait cycle (which leg pose the sensors draw)
    hazard_lamps_on: bool = False  # the amber hazard lamps are lit at this instant


@dataclass(frozen=True, slots=True)
class AgentState:
    """A connected agent's platform state, the origin of its sensor rig (``<agent>/base_link``).

    ``angular_rate_radps`` and ``specific_force_mps2`` are in the body frame (FLU) and feed the IMU.
    ``gimbal_rotation`` is map <- gimbal for a stabilised camera mount (drones), else None.
    """

    agent_id: str
    kind: AgentKind
    position_m: Vec3
    rotation: Quat
    velocity_mps: Vec3 = (0.0, 0.0, 0.0)
    angular_rate_radps: Vec3 = (0.0, 0.0, 0.0)
    specific_force_mps2: Vec3 = (0.0, 0.0, 9.80665)
    track_id: int | None = None
    gimbal_rotation: Quat | None = None
    extra: dict[str, float | str] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class TrafficLight:
    """One signal head at a tick (:mod:`cosim.world.traffic_lights`): its id ``<tls>/<lane>``, the housing's
    centre, the yaw it faces, the colour it shows (``green``, ``yellow``, ``red`` or ``off``) and SUMO's
    signal characters of the links it shows (``signal``, e.g. ``"Gg"``)."""

    light_id: str
    center_m: Vec3
    yaw_rad: float
    state: str
    signal: str


@dataclass(frozen=True, slots=True)
class WorldSnapshot:
    """Everything that moves, at simulation time ``t_ns`` (= tick * tick_ns)."""

    tick: int
    t_ns: int
    actors: tuple[Actor, ...]
    agents: tuple[AgentState, ...]
    traffic_lights: tuple[TrafficLight, ...] = ()  # every signal head and what it shows

    def agent(self, agent_id: str) -> AgentState:
        for a in self.agents:
            if a.agent_id == agent_id:
                return a
        raise KeyError(f"no agent {agent_id!r} at tick {self.tick}")

    def actor_by_track(self) -> dict[int, Actor]:
        return {a.track_id: a for a in self.actors}
