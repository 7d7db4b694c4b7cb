"""What a closed-loop client may ask of the agents, and the check every action passes on arrival.

Actions are plain JSON objects with a ``type`` and an ``agent`` (docs/episode_format.md, ``/actions``):

- connected vehicles (libsumo in the traffic worker): ``set_speed`` (hold a speed; ``null`` gives the
  vehicle back to SUMO's car following), ``slow_down`` (reach a speed over ``duration_s``, SUMO's
  ``slowDown``), ``change_lane``, ``change_target`` (new destination edge, SUMO routes there),
  ``set_route`` (explicit edge list starting on the vehicle's current edge);
- drones (their strategy in the drone worker): ``goto`` (waypoint at an altitude and speed, then hold),
  ``strategy`` (any drone strategy of the scenario schema: hover, patrol, escort), ``escort`` (shorthand
  for an escort strategy) and ``land``.

:func:`check_actions` is the single validation: schema (pydantic, unknown keys refused), agent kind and
existence at the tick the client observed, and value ranges that need the episode (map bounds, a drone's
speed limit, the network's lanes and edges). A message with any bad action is refused whole.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated, Any, Literal

from pydantic import Field, TypeAdapter, ValidationError

from cosim.errors import ActionRejected
from cosim.scenario.model import DRONE_STRATEGIES, DroneSpec, EscortDrone, Model

MAX_VEHICLE_SPEED_MPS = 70.0  # [m/s] above any road vehicle


class _Action(Model):
    agent: str = Field(pattern=r"^[a-z]+_\d+$")


class SetSpeed(_Action):
    type: Literal["set_speed"] = "set_speed"
    speed_mps: float | None = Field(ge=0.0, le=MAX_VEHICLE_SPEED_MPS)  # None: SUMO drives again


class SlowDown(_Action):
    type: Literal["slow_down"] = "slow_down"
    speed_mps: float = Field(ge=0.0, le=MAX_VEHICLE_SPEED_MPS)
    duration_s: float = Field(gt=0.0, le=600.0)


class ChangeLane(_Action):
    type: Literal["change_lane"] = "change_lane"
    lane_index: int = Field(ge=0)  # 0 = rightmost lane
    duration_s: float = Field(3.0, gt=0.0, le=600.0)  # [s] how long SUMO keeps trying to stay there


class ChangeTarget(_Action):
    type: Literal["change_target"] = "change_target"
    edge: str = Field(min_length=1)


class SetRoute(_Action):
    type: Literal["set_route"] = "set_route"
    edges: list[str] = Field(min_length=1)


class GoTo(_Action):
    type: Literal["goto"] = "goto"
    position_m: tuple[float, float]  # map x, y [m]
    altitude_m: float = Field(ge=5.0, le=300.0)  # above ground, raised where the drone plans clearance
    speed_mps: float = Field(gt=0.0, le=40.0)


class SetStrategy(_Action):
    type: Literal["strategy"] = "strategy"
    drone: DroneSpec  # as an entry of agents.drones in a scenario


class Escort(_Action):
    type: Literal["escort"] = "escort"
    target: str
    offset_m: tuple[float, float] = (-8.0, 0.0)
    altitude_m: float = Field(40.0, ge=5.0, le=300.0)


class Land(_Action):
    type: Literal["land"] = "land"
    speed_mps: float = Field(1.0, gt=0.0, le=5.0)  # descent rate


Action = Annotated[
    SetSpeed | SlowDown | ChangeLane | ChangeTarget | SetRoute | GoTo | SetStrategy | Escort | Land,
    Field(discriminator="type"),
]
VEHICLE_ACTIONS = ("set_speed", "slow_down", "change_lane", "change_target", "set_route")
DRONE_ACTIONS = ("goto", "strategy", "escort", "land")
_ACTIONS = TypeAdapter(list[Action])


@dataclass(frozen=True)
class ActionContext:
    """What an action is checked against at one tick."""

    vehicles: frozenset[str]  # connected vehicles on the road at the observed tick
    drones: dict[str, float]  # drone id -> its max_speed_mps
    bounds_m: tuple[float, float, float, float]  # map xmin, ymin, xmax, ymax
    max_lanes: int  # most lanes of any edge
    edges: frozenset[str]  # non-internal edge ids of the network


def check_actions(actions: Any, ctx: ActionContext) -> list[Action]:
    """The validated actions, or :class:`ActionRejected` listing every bad one by index and agent."""
    if not isinstance(actions, list):
        raise ActionRejected(f"actions must be a list of objects, got {type(actions).__name__}")
    try:
        parsed = _ACTIONS.validate_python(actions)
    except ValidationError as exc:
        problems = []
        for err in exc.errors():
            loc = list(err["loc"])
            where = f"actions[{loc[0]}]" if loc else "actions"
            agent = actions[loc[0]].get("agent") if loc and isinstance(actions[loc[0]], dict) else None
            key = ".".join(str(p) for p in loc[2:] if not isinstance(p, str) or p not in DRONE_KINDS_OR_TYPES)
            detail = f"{key}: {err['msg']}" if key else err["msg"]
            problems.append(f"{where}{f' ({agent})' if agent else ''}: {detail}")
        raise ActionRejected("; ".join(problems)) from None
    problems = [f"actions[{i}] ({a.agent}): {p}" for i, a in enumerate(parsed) if (p := _problem(a, ctx))]
    if problems:
        raise ActionRejected("; ".join(problems))
    return parsed


#: Discriminator values pydantic puts into error locations; left out of the key path shown.
DRONE_KINDS_OR_TYPES = frozenset({*VEHICLE_ACTIONS, *DRONE_ACTIONS, *DRONE_STRATEGIES})


def _problem(a: Action, ctx: ActionContext) -> str | None:
    kind = a.agent.rsplit("_", 1)[0]
    if a.type in VEHICLE_ACTIONS:
        if kind != "vehicle":
            return f"{a.type} is for connected vehicles, not {kind}s"
        if a.agent not in ctx.vehicles:
            return f"no connected vehicle {a.agent} on the road (there are: {_names(ctx.vehicles)})"
        if isinstance(a, ChangeLane) and a.lane_index >= ctx.max_lanes:
            return f"lane_index {a.lane_index} does not exist: no edge of this network has more than {ctx.max_lanes}"
        if isinstance(a, ChangeTarget) and a.edge not in ctx.edges:
            return f"edge {a.edge!r} is not in the network"
        if isinstance(a, SetRoute):
            unknown = [e for e in a.edges if e not in ctx.edges]
            if unknown:
                return f"edges not in the network: {', '.join(unknown)}"
        return None
    if kind != "drone":
        return f"{a.type} is for drones, not {kind}s"
    if a.agent not in ctx.drones:
        return f"no drone {a.agent} (there are: {_names(ctx.drones)})"
    if isinstance(a, GoTo):
        x, y = a.position_m
        x0, y0, x1, y1 = ctx.bounds_m
        if not (x0 <= x <= x1 and y0 <= y <= y1):
            return f"position_m ({x:g}, {y:g}) is outside the map [{x0:g}, {x1:g}] x [{y0:g}, {y1:g}]"
        if a.speed_mps > ctx.drones[a.agent]:
            return f"speed_mps {a.speed_mps:g} exceeds the drone's max_speed_mps {ctx.drones[a.agent]:g}"
    target = a.target if isinstance(a, Escort) else a.drone.target if isinstance(a, SetStrategy) and isinstance(
        a.drone, EscortDrone) else None
    if target is not None and target not in ctx.vehicles:
        return f"escort target {target} is not a connected vehicle on the road (there are: {_names(ctx.vehicles)})"
    return None


def _names(ids: Any) -> str:
    return ", ".join(sorted(ids, key=lambda s: (len(s), s))) or "none"


def as_dicts(actions: Sequence[Action]) -> list[dict[str, Any]]:
    """Plain JSON data of validated actions (defaults filled in), as the workers and ``/actions`` get them."""
    return [a.model_dump(mode="json") for a in actions]


def parse_action(data: dict[str, Any]) -> Action:
    """One action from plain data that :func:`check_actions` already accepted (worker side)."""
    return _ACTIONS.validate_python([data])[0]


# -- constructors for client code ------------------------------------------------------------------


def set_speed(agent: str, speed_mps: float | None) -> dict[str, Any]:
    """Hold ``agent`` at ``speed_mps`` (within its acceleration limits); ``None`` gives it back to SUMO."""
    return {"type": "set_speed", "agent": agent, "speed_mps": speed_mps}


def slow_down(agent: str, speed_mps: float, duration_s: float) -> dict[str, Any]:
    return {"type": "slow_down", "agent": agent, "speed_mps": speed_mps, "duration_s": duration_s}


def change_lane(agent: str, lane_index: int, duration_s: float = 3.0) -> dict[str, Any]:
    return {"type": "change_lane", "agent": agent, "lane_index": lane_index, "duration_s": duration_s}


def change_target(agent: str, edge: str) -> dict[str, Any]:
    return {"type": "change_target", "agent": agent, "edge": edge}


def set_route(agent: str, edges: Sequence[str]) -> dict[str, Any]:
    return {"type": "set_route", "agent": agent, "edges": list(edges)}


def goto(agent: str, x_m: float, y_m: float, altitude_m: float, speed_mps: float) -> dict[str, Any]:
    """Fly ``agent`` to map (x, y) at ``altitude_m`` above ground at up to ``speed_mps``, then hold there."""
    return {"type": "goto", "agent": agent, "position_m": [x_m, y_m], "altitude_m": altitude_m,
            "speed_mps": speed_mps}


def strategy(agent: str, **drone: Any) -> dict[str, Any]:
    """Switch ``agent`` to a scenario drone strategy, e.g. ``strategy("drone_0", strategy="hover")``."""
    return {"type": "strategy", "agent": agent, "drone": drone}


def escort(agent: str, target: str, offset_m: tuple[float, float] = (-8.0, 0.0),
           altitude_m: float = 40.0) -> dict[str, Any]:
    return {"type": "escort", "agent": agent, "target": target, "offset_m": list(offset_m),
            "altitude_m": altitude_m}


def land(agent: str, speed_mps: float = 1.0) -> dict[str, Any]:
    return {"type": "land", "agent": agent, "speed_mps": speed_mps}


#: ``/actions`` payload schema (project JSON schema, docs/episode_format.md).
ACTION_ARRAY_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "cosim.ActionArray",
    "description": "Closed-loop clients' actions applied in the step that ends at this tick; engines' refusals.",
    "type": "object",
    "required": ["timestamp_ns", "tick", "actions", "failed"],
    "properties": {
        "timestamp_ns": {"type": "integer", "description": "simulation time since episode start [ns]"},
        "tick": {"type": "integer"},
        "actions": {
            "type": "array",
            "items": {
                "type": "object",
                "required": ["client", "observed_tick", "action"],
                "properties": {
                    "client": {"type": "string"},
                    "observed_tick": {"type": "integer", "description": "the tick the client acted on (tick - 1)"},
                    "action": {"type": "object", "description": "type, agent and the action's fields"},
                },
            },
        },
        "failed": {
            "type": "array",
            "description": "actions the engine could not apply (SUMO found no route...), with its reason",
            "items": {"type": "object", "required": ["action", "error"]},
        },
    },
}
