"""``/events`` messages: the scenario timeline's incidents at one tick (docs/episode_format.md section 3.13).

The traffic worker reports each event with SUMO ids; here they become track ids of the same tick's
``/labels/objects`` (vehicles involved, static obstacles placed).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from cosim.scenario.model import EVENT_KINDS

_ID_LIST = {"type": "array", "items": {"type": "integer", "minimum": 1}}

EVENTS_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "cosim.Events",
    "type": "object",
    "required": ["timestamp_ns", "tick", "frame_id", "events"],
    "properties": {
        "timestamp_ns": {"type": "integer"},
        "tick": {"type": "integer"},
        "frame_id": {"const": "map"},
        "events": {
            "type": "array",
            "items": {
                "type": "object",
                "required": ["id", "kind", "at_ns", "state"],
                "properties": {
                    "id": {"type": "string"},
                    "kind": {"enum": list(EVENT_KINDS)},
                    "at_ns": {"type": "integer"},
                    "state": {"enum": ["pending", "starting", "active", "failed"]},
                    "active_from_ns": {"type": ["integer", "null"]},
                    "vehicle_track_ids": _ID_LIST,
                    "obstacle_track_ids": _ID_LIST,
                    "pedestrian_track_ids": _ID_LIST,
                    "zone_m": {"type": "array", "items": {"type": "array", "items": {"type": "number"},
                                                          "minItems": 2, "maxItems": 2}},
                    "edge": {"type": "string"},
                    "lane": {"type": "integer"},
                    "lane_pos_m": {"type": "number"},
                    "hazard_lights": {"type": "boolean"},
                    "note": {"type": "string"},
                },
            },
        },
    },
}


def events_payload(tick: int, t_ns: int, records: Sequence[dict[str, Any]],
                   track_of: Callable[[str], int | None]) -> dict[str, Any]:
    """The ``/events`` message of a tick from the traffic worker's records; ``track_of(sumo_id)`` gives the
    track id of an actor in this tick's labels (None when it is not on the road yet)."""
    events = []
    for r in records:
        e = {k: v for k, v in r.items() if k not in ("vehicles", "obstacles", "pedestrians")}
        if "vehicles" in r:
            e["vehicle_track_ids"] = [t for t in map(track_of, r["vehicles"]) if t is not None]
            e["obstacle_track_ids"] = [t for t in map(track_of, r["obstacles"]) if t is not None]
        if "pedestrians" in r:
            e["pedestrian_track_ids"] = [t for t in map(track_of, r["pedestrians"]) if t is not None]
        events.append(e)
    return {"timestamp_ns": t_ns, "tick": tick, "frame_id": "map", "events": events}
