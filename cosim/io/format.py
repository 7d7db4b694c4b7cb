"""The episode format as data: topics and their schemas, metadata keys, attachments.

docs/episode_format.md is the prose version of these tables; ``cosim validate`` checks files
against them. Topic patterns use ``<agent>`` and ``<cam>`` placeholders.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

#: Format version this code writes and reads (major.minor; readers refuse another major).
FORMAT_VERSION = "1.4"

MAP_FRAME = "map"
#: Instance ids at or above this are static scene parts (buildings, poles...), not tracks; 0 is "nothing".
STATIC_INSTANCE_MIN = 1_000_000


@dataclass(frozen=True)
class TopicSpec:
    """One row of the topic contract."""

    pattern: str  # e.g. "/<agent>/<cam>/image"
    schemas: tuple[str, ...]  # accepted schema names
    frame: str
    description: str

    @property
    def regex(self) -> re.Pattern[str]:
        body = re.escape(self.pattern).replace(re.escape("<agent>"), r"(?P<agent>[a-z]+_\d+)")
        body = body.replace(re.escape("<cam>"), r"(?P<cam>[a-z][a-z0-9_]*)")
        return re.compile(f"^{body}$")


TOPICS: tuple[TopicSpec, ...] = (
    TopicSpec(
        "/tf",
        ("foxglove.FrameTransforms",),
        "map (root)",
        "map -> <agent>/base_link -> <agent>/<sensor> (-> <agent>/<cam>/optical)",
    ),
    TopicSpec("/labels/objects", ("cosim.ObjectArray",), "map", "every actor's 3D box; every agent's pose"),
    TopicSpec("/labels/boxes", ("foxglove.SceneUpdate",), "map", "the same boxes for viewers; entity id = track id"),
    TopicSpec("/events", ("cosim.Events",), "map", "the scenario timeline's incidents: state, place, track ids"),
    TopicSpec(
        "/<agent>/lidar",
        ("foxglove.PointCloud",),
        "<agent>/lidar",
        "x, y, z (1/256 m counts or float32 m), intensity, ring, class_id, instance_id, t_offset_ns, return",
    ),
    TopicSpec(
        "/<agent>/<cam>/image",
        ("foxglove.CompressedImage", "foxglove.RawImage"),
        "<agent>/<cam>/optical",
        "RGB",
    ),
    TopicSpec(
        "/<agent>/<cam>/depth",
        ("foxglove.RawImage", "foxglove.CompressedImage"),
        "<agent>/<cam>/optical",
        "planar depth along the optical z axis",
    ),
    TopicSpec(
        "/<agent>/<cam>/semantic",
        ("foxglove.RawImage", "foxglove.CompressedImage"),
        "<agent>/<cam>/optical",
        "semantic class id per pixel",
    ),
    TopicSpec(
        "/<agent>/<cam>/instance",
        ("foxglove.RawImage", "foxglove.CompressedImage"),
        "<agent>/<cam>/optical",
        "track id per pixel (0 none, >= 1e6 static)",
    ),
    TopicSpec(
        "/<agent>/<cam>/calibration",
        ("foxglove.CameraCalibration",),
        "<agent>/<cam>/optical",
        "pinhole intrinsics",
    ),
    TopicSpec("/<agent>/gnss", ("foxglove.LocationFix",), "<agent>/gnss", "WGS84 fix"),
    TopicSpec("/<agent>/imu", ("cosim.Imu",), "<agent>/imu", "specific force, angular rate (body FLU)"),
    TopicSpec("/<agent>/bev", ("foxglove.Grid",), "map", "ego-centred semantic BEV, one uint8 field per layer"),
    TopicSpec("/<agent>/visibility", ("cosim.Visibility",), "-", "per object seen: LiDAR hits, pixels per camera"),
    TopicSpec("/actions", ("cosim.ActionArray",), "-", "closed-loop clients' actions applied in the step to this tick"),
    TopicSpec("/comm/links", ("cosim.LinkArray",), "map", "every ordered link: LOS, path loss, SNR, PER, rate, delay"),
)

#: Every episode has these topics on every tick.
LABEL_TOPICS: tuple[str, ...] = ("/tf", "/labels/objects", "/labels/boxes")

#: Keys of the ``episode`` metadata record every episode must have.
REQUIRED_METADATA: tuple[str, ...] = (
    "format_version",
    "generator",
    "scenario",
    "seed",
    "weather",
    "lighting",
    "environment",
    "strategies",
    "tick_hz",
    "tick_ns",
    "n_ticks",
    "duration_s",
    "agents",
    "sensors_enabled",
    "geo_origin",
    "class_table",
    "versions",
)

#: Attachments every episode carries.
REQUIRED_ATTACHMENTS: tuple[str, ...] = ("scenario.yaml", "map.net.xml", "routes.rou.xml", "world.json")


#: Camera output -> topic suffix.
CAMERA_TOPICS: dict[str, str] = {"rgb": "image", "depth": "depth", "semantic": "semantic", "instance": "instance"}


def expected_topics(scenario: Any, agents: list[str]) -> set[str]:
    """Every topic an episode of ``scenario`` (a :class:`cosim.scenario.model.Scenario`) must hold."""
    out = set(LABEL_TOPICS)
    if getattr(scenario, "events", None):
        out.add("/events")
    if scenario.clients:
        out.add("/actions")
    comm = getattr(scenario, "comm", None)
    if comm is not None and comm.enabled:
        out.add("/comm/links")
    if not scenario.sensors.enabled:
        return out
    for agent in agents:
        rig = scenario.rig_for(agent)
        if rig.lidar is not None:
            out.add(f"/{agent}/lidar")
        for cam in rig.cameras:
            out.update(f"/{agent}/{cam.name}/{CAMERA_TOPICS[o]}" for o in cam.outputs)
            out.add(f"/{agent}/{cam.name}/calibration")
        # every other rig field is a per-agent sensor (GNSS, IMU, a sensor kind of cosim.sensors.kinds): one topic
        out.update(f"/{agent}/{name}" for name, spec in rig if name not in ("lidar", "cameras") and spec is not None)
        out.add(f"/{agent}/visibility")
        if scenario.sensors.bev:
            out.add(f"/{agent}/bev")
    return out


def topic_spec(topic: str) -> tuple[TopicSpec, dict[str, str]] | None:
    """The contract row a topic falls under and its placeholders (agent, cam), or None."""
    for spec in TOPICS:
        m = spec.regex.match(topic)
        if m:
            return spec, {k: v for k, v in m.groupdict().items() if v is not None}
    return None
