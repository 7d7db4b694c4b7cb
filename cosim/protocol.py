"""What the conductor and the workers say to each other over Zenoh.

Messages are JSON (exact float round trip, readable in a Zenoh tool, no shared memory or files),
versioned by :data:`PROTOCOL_VERSION`. Keys live under a per-episode prefix::

    <prefix>/alive/<role>          liveliness token of a worker (traffic | drones)
    <prefix>/<role>/init           queryable: load the world, reply "ready" (payload: InitRequest)
    <prefix>/<role>/step           queryable: advance to t_ns, reply the states (payload: StepRequest)
    <prefix>/<role>/close          queryable: release the engine and exit

A worker replies to a failed request with a Zenoh error reply carrying ``{"error": message}``.
"""

from __future__ import annotations

import base64
import json
from dataclasses import dataclass, field
from typing import Any

PROTOCOL_VERSION = 1
ROLES = ("traffic", "drones")


@dataclass(frozen=True, slots=True)
class VehicleState:
    """One SUMO vehicle at a tick, already converted to the box convention (docs/conventions.md section 4)."""

    sumo_id: str
    cls: str
    center_m: tuple[float, float, float]
    size_m: tuple[float, float, float]  # length, width, height
    yaw_rad: float
    pitch_rad: float
    speed_mps: float
    velocity_mps: tuple[float, float, float]
    accel_mps2: float
    yaw_rate_radps: float
    agent_id: str | None = None
    gait_phase: float = 0.0  # pedestrians: walked distance over the stride, 0..1 (the legs' pose)
    hazard_lamps_on: bool = False  # hazard lights lit at this instant (they blink)


@dataclass(frozen=True, slots=True)
class DroneState:
    """One drone at a tick (map frame, SI units; body rates and specific force in FLU)."""

    agent_id: str
    position_m: tuple[float, float, float]
    rotation: tuple[float, float, float, float]
    velocity_mps: tuple[float, float, float]
    angular_rate_radps: tuple[float, float, float]
    specific_force_mps2: tuple[float, float, float]
    gimbal_rotation: tuple[float, float, float, float]
    energy_used_j: float
    strategy: str
    strategy_state: str
    size_m: tuple[float, float, float] = (1.0, 1.0, 0.35)


@dataclass(frozen=True, slots=True)
class EscortTarget:
    """What a drone needs to know about the vehicle it escorts."""

    center_m: tuple[float, float, float]
    yaw_rad: float
    velocity_mps: tuple[float, float, float]


@dataclass(frozen=True, slots=True)
class InitRequest:
    """Everything a worker needs to build its engine; carried inline, no shared files."""

    scenario: dict[str, Any]  # the resolved scenario (plain data)
    world: dict[str, Any]  # World.to_wire()
    protocol: int = PROTOCOL_VERSION


@dataclass(frozen=True, slots=True)
class StepRequest:
    tick: int
    t_ns: int
    escort_targets: dict[str, EscortTarget] = field(default_factory=dict)
    #: closed-loop clients' actions for this worker's agents, applied before the step (cosim.actions)
    actions: list[dict[str, Any]] = field(default_factory=list)


def encode(obj: Any) -> bytes:
    """JSON bytes of a message: dataclasses become objects, bytes become ``{"__b64__": ...}``."""
    return json.dumps(obj, separators=(",", ":"), default=_json_default).encode()


def decode(data: bytes) -> Any:
    return json.loads(data)


def _json_default(obj: Any) -> Any:
    """What json cannot write itself; shallow, so no deep copy of large payloads (the world)."""
    fields = getattr(obj, "__dataclass_fields__", None)
    if fields is not None:
        return {k: getattr(obj, k) for k in fields}
    if isinstance(obj, bytes):
        return {"__b64__": base64.b64encode(obj).decode()}
    raise TypeError(f"cannot encode {type(obj).__name__} in a protocol message")


def unbytes(obj: Any) -> Any:
    """Undo the bytes wrapping of :func:`encode` in decoded data."""
    if isinstance(obj, dict):
        if set(obj) == {"__b64__"}:
            return base64.b64decode(obj["__b64__"])
        return {k: unbytes(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [unbytes(v) for v in obj]
    return obj


def vehicle_from_dict(d: dict[str, Any]) -> VehicleState:
    return VehicleState(**{**d, "center_m": tuple(d["center_m"]), "size_m": tuple(d["size_m"]),
                           "velocity_mps": tuple(d["velocity_mps"])})


def drone_from_dict(d: dict[str, Any]) -> DroneState:
    return DroneState(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


def step_request_from_dict(d: dict[str, Any]) -> StepRequest:
    targets = {
        k: EscortTarget(tuple(v["center_m"]), v["yaw_rad"], tuple(v["velocity_mps"]))
        for k, v in d.get("escort_targets", {}).items()
    }
    return StepRequest(d["tick"], d["t_ns"], targets, d.get("actions", []))
