"""Labels and transforms of one snapshot as episode messages (docs/episode_format.md sections 3.1-3.3).

- ``/tf`` (foxglove.FrameTransforms): ``map -> <agent>/base_link`` for every connected agent, plus
  the rig's ``<agent>/base_link -> <agent>/<sensor>`` (and camera optical frames) when given.
- ``/labels/objects`` (JSON, schema ``cosim.ObjectArray``): every actor's 3D box and every agent's pose.
- ``/labels/boxes`` (foxglove.SceneUpdate): the same boxes for a viewer; entity id = track id.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.CubePrimitive_pb2 import CubePrimitive
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.KeyValuePair_pb2 import KeyValuePair
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.timestamp_pb2 import Timestamp

from cosim.classes import SEMANTIC_COLOURS
from cosim.snapshot import WorldSnapshot

#: (parent frame, child frame, translation [m], rotation (x, y, z, w)): one rigid transform.
Transform = tuple[str, str, Sequence[float], Sequence[float]]

MAP_FRAME = "map"

_VEC3 = {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3}
_QUAT = {"type": "array", "items": {"type": "number"}, "minItems": 4, "maxItems": 4}

OBJECT_ARRAY_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "cosim.ObjectArray",
    "description": "Every labelled actor (3D box in map, ENU metres) and every connected agent's pose at one tick.",
    "type": "object",
    "required": ["timestamp_ns", "tick", "frame_id", "objects", "agents"],
    "properties": {
        "timestamp_ns": {"type": "integer", "description": "simulation time since episode start [ns]"},
        "tick": {"type": "integer"},
        "frame_id": {"type": "string", "const": MAP_FRAME},
        "objects": {
            "type": "array",
            "items": {
                "type": "object",
                "required": ["track_id", "class", "center_m", "size_m", "rotation", "velocity_mps"],
                "properties": {
                    "track_id": {"type": "integer", "description": "unique per actor and episode, never reused"},
                    "class": {"type": "string", "description": "car|van|truck|bus|motorcycle|bicycle|drone"},
                    "center_m": {**_VEC3, "description": "box centre in map [m]"},
                    "size_m": {**_VEC3, "description": "length, width, height along body x, y, z [m]"},
                    "rotation": {**_QUAT, "description": "map <- body quaternion (x, y, z, w)"},
                    "velocity_mps": {**_VEC3, "description": "velocity in map [m/s]"},
                    "agent_id": {"type": ["string", "null"], "description": "set for connected agents"},
                    "parked": {"type": "boolean", "description": "true for parked vehicles; absent otherwise"},
                },
            },
        },
        "agents": {
            "type": "array",
            "items": {
                "type": "object",
                "required": ["agent_id", "kind", "position_m", "rotation"],
                "properties": {
                    "agent_id": {"type": "string"},
                    "kind": {"type": "string", "enum": ["vehicle", "rsu", "drone"]},
                    "track_id": {"type": ["integer", "null"]},
                    "position_m": {**_VEC3, "description": "<agent>/base_link origin in map [m]"},
                    "rotation": {**_QUAT, "description": "map <- base_link (x, y, z, w)"},
                    "velocity_mps": _VEC3,
                    "extra": {"type": "object"},
                },
            },
        },
        "traffic_lights": {
            "type": "array",
            "description": "every signal head at SUMO's signalised junctions and what it shows (format 1.3); "
                           "absent when the map has none",
            "items": {
                "type": "object",
                "required": ["light_id", "state", "signal", "center_m", "yaw_rad"],
                "properties": {
                    "light_id": {"type": "string", "description": "<SUMO traffic light id>/<SUMO lane id>"},
                    "state": {"type": "string", "enum": ["green", "yellow", "red", "off"]},
                    "signal": {"type": "string", "description": "SUMO's signal characters of the head's links"},
                    "center_m": {**_VEC3, "description": "centre of the head's housing in map [m]"},
                    "yaw_rad": {"type": "number", "description": "direction the lamps face, about +z from +x"},
                },
            },
        },
    },
}


def timestamp(t_ns: int) -> Timestamp:
    return Timestamp(seconds=t_ns // 1_000_000_000, nanos=t_ns % 1_000_000_000)


def frame_transform(t_ns: int, parent: str, child: str, xyz: Sequence[float], q: Sequence[float]) -> FrameTransform:
    return FrameTransform(
        timestamp=timestamp(t_ns),
        parent_frame_id=parent,
        child_frame_id=child,
        translation=Vector3(x=xyz[0], y=xyz[1], z=xyz[2]),
        rotation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]),
    )


def tf_message(snapshot: WorldSnapshot, rig_transforms: Iterable[Transform] = ()) -> FrameTransforms:
    """``/tf`` for one tick: map -> every agent's base_link, then the rig transforms given."""
    t = snapshot.t_ns
    transforms = [frame_transform(t, MAP_FRAME, f"{a.agent_id}/base_link", a.position_m, a.rotation)
                  for a in snapshot.agents]
    transforms += [frame_transform(t, p, c, xyz, q) for p, c, xyz, q in rig_transforms]
    return FrameTransforms(transforms=transforms)


def objects_payload(snapshot: WorldSnapshot) -> dict[str, Any]:
    """``/labels/objects`` payload (schema :data:`OBJECT_ARRAY_SCHEMA`)."""
    return {
        "timestamp_ns": snapshot.t_ns,
        "tick": snapshot.tick,
        "frame_id": MAP_FRAME,
        "objects": [
            {
                "track_id": a.track_id,
                "class": a.cls,
                "center_m": list(a.center_m),
                "size_m": list(a.size_m),
                "rotation": list(a.rotation),
                "velocity_mps": list(a.velocity_mps),
                "agent_id": a.agent_id,
                **({"parked": True} if a.parked else {}),
            }
            for a in snapshot.actors
        ],
        "agents": [
            {
                "agent_id": a.agent_id,
                "kind": a.kind,
                "track_id": a.track_id,
                "position_m": list(a.position_m),
                "rotation": list(a.rotation),
                "velocity_mps": list(a.velocity_mps),
                "extra": dict(a.extra),
            }
            for a in snapshot.agents
        ],
        **({"traffic_lights": [{"light_id": t.light_id, "state": t.state, "signal": t.signal,
                                "center_m": list(t.center_m), "yaw_rad": t.yaw_rad}
                               for t in snapshot.traffic_lights]} if snapshot.traffic_lights else {}),
    }


def boxes_message(snapshot: WorldSnapshot) -> SceneUpdate:
    """``/labels/boxes``: delete everything, then one cube entity per actor, coloured by class."""
    ts = timestamp(snapshot.t_ns)
    entities = []
    for a in snapshot.actors:
        r, g, b = SEMANTIC_COLOURS.get(a.cls, (255, 255, 255))
        meta = [KeyValuePair(key="class", value=a.cls)]
        if a.agent_id:
            meta.append(KeyValuePair(key="agent_id", value=a.agent_id))
        entities.append(
            SceneEntity(
                timestamp=ts,
                frame_id=MAP_FRAME,
                id=str(a.track_id),
                frame_locked=False,
                metadata=meta,
                cubes=[
                    CubePrimitive(
                        pose=Pose(
                            position=Vector3(x=a.center_m[0], y=a.center_m[1], z=a.center_m[2]),
                            orientation=Quaternion(x=a.rotation[0], y=a.rotation[1], z=a.rotation[2],
                                                   w=a.rotation[3]),
                        ),
                        size=Vector3(x=a.size_m[0], y=a.size_m[1], z=a.size_m[2]),
                        color=Color(r=r / 255, g=g / 255, b=b / 255, a=0.6),
                    )
                ],
            )
        )
    return SceneUpdate(deletions=[SceneEntityDeletion(timestamp=ts, type=SceneEntityDeletion.ALL)],
                       entities=entities)


def label_messages(snapshot: WorldSnapshot, rig_transforms: Iterable[Transform] = ()) -> list[tuple[str, Any]]:
    """(topic, message) pairs of one tick's transforms and labels, ready for the episode writer."""
    return [
        ("/tf", tf_message(snapshot, rig_transforms)),
        ("/labels/objects", ("cosim.ObjectArray", OBJECT_ARRAY_SCHEMA, objects_payload(snapshot))),
        ("/labels/boxes", boxes_message(snapshot)),
    ]
