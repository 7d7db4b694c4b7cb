"""The AirV2X-Perception layout (``taco-group/AirV2X-Perception``, read by ``opencood/utils/airv2x_utils.py``
and ``opencood/data_utils/datasets/airv2x/``); docs/exports.md describes every file.

```
<out>/<split>/<YYYY_MM_DD_HH_MM_SS>/conditions.json
    timestamp_<tick:06d>/objects.pkl
    timestamp_<tick:06d>/agent_<number:06d>/metadata.pkl lidar.pcd <camera>.png <cam>_depth.png map_*.png ...
```
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from cosim.exporters import carla_frames as cf
from cosim.exporters.export import AgentView, ExportFormat, SequenceInfo, TickView, register_format
from cosim.exporters.export_io import (
    SPARSE_PNG_LEVEL,
    depth_png,
    json_text,
    pickle_bytes,
    plain,
    png_bytes,
    write_bytes,
)

from cosim.errors import CosimError
from cosim.io import Episode

#: AirV2X object classes (``opencood/utils/airv2x_utils.py: filter_objects`` keeps 1 to 6). cosim classes
#: map by name; every other class (drone, static obstacles, anything added later) is 7 "other".
CLASS_IDS: dict[str, int] = {
    "pedestrian": 0, "bicycle": 1, "motorcycle": 2, "car": 3, "van": 4, "truck": 5, "bus": 6,
}
OTHER_CLASS = 7
#: Static map layers in the loader's order (the road layer is last, so it wins where layers overlap).
STATIC_MAPS = ("background", "lane", "road")
#: The devkit's camera names per agent type, from cosim's camera names (docs/episode_format.md section 3).
CAMERA_NAMES: dict[str, dict[str, str]] = {
    "vehicle": {"front": "front_camera", "front_left": "front_left_camera", "front_right": "front_right_camera",
                "rear": "rear_camera", "rear_left": "rear_left_camera", "rear_right": "rear_right_camera"},
    "rsu": {"front": "front_camera", "rear": "back_camera", "left": "left_camera", "right": "right_camera"},
    "drone": {"down": "bev_camera"},
}
#: RSUs have no track; their agent folders are numbered from here (track ids must stay below it).
RSU_NUMBER_BASE = 900_000


def class_id(name: str) -> int:
    """AirV2X class id of a cosim object class name (7 "other" for classes the format lacks)."""
    return CLASS_IDS.get(name, OTHER_CLASS)


def agent_numbers(seq: SequenceInfo) -> dict[str, int]:
    """Agent folder numbers: a vehicle's or drone's track id (its key in ``objects.pkl``, as CARLA's
    actor ids are), ``RSU_NUMBER_BASE + i`` for ``rsu_i``."""
    out: dict[str, int] = {}
    for a in seq.agents:
        track = seq.track_ids[a]
        if seq.kinds[a] == "rsu" or track is None:
            out[a] = RSU_NUMBER_BASE + int(a.rsplit("_", 1)[1])
        elif track >= RSU_NUMBER_BASE:
            raise CosimError(f"{a}: track id {track} collides with the RSU agent numbers (>= {RSU_NUMBER_BASE})")
        else:
            out[a] = int(track)
    return out


def object_table(view: TickView) -> dict[int, dict[str, Any]]:
    """``objects.pkl``: every labelled object of the tick, keyed by track id."""
    labels = view.labels
    out: dict[int, dict[str, Any]] = {}
    for i, rot in enumerate(view.object_rotations()):
        pose = cf.carla_pose(labels.centers_m[i], rot)
        loc, centre = cf.box_location_center(labels.centers_m[i], rot, labels.sizes_m[i])
        name = labels.classes[i]
        out[int(labels.track_ids[i])] = {
            "bp_id": f"cosim.{name}",
            "location": loc + pose[3:],
            "center": [*centre, 0.0, 0.0, 0.0],
            "extent": cf.half_extent(labels.sizes_m[i]),
            "class": class_id(name),
            "speed": cf.speed_mps(labels.velocities_mps[i]),
            "cosim_class": name,
        }
    return out


@register_format
class AirV2XFormat(ExportFormat):
    name: ClassVar[str] = "airv2x"

    def __init__(self, seq: SequenceInfo, options: Any, root: Path):
        super().__init__(seq, options, root)
        self.numbers = agent_numbers(seq)

    def write_sequence(self, ep: Episode) -> None:
        cond = self.seq.conditions()
        cond["agent_numbers"] = {a: self.numbers[a] for a in self.seq.agents}
        write_bytes(self.root / "conditions.json", json_text(cond).encode())

    def write_tick(self, view: TickView) -> None:
        folder = self.root / f"timestamp_{view.index:06d}"
        write_bytes(folder / "objects.pkl", pickle_bytes(plain(object_table(view))))
        view.for_each_agent(lambda agent: self.write_agent(view, agent,
                                                           folder / f"agent_{self.numbers[agent.agent_id]:06d}"))

    def write_agent(self, view: TickView, agent: AgentView, folder: Path) -> None:
        ego_pos = cf.carla_pose_of_matrix(agent.map_from_base)
        meta: dict[str, Any] = {
            "agent_type": agent.kind,
            "odometry": {"ego_pos": ego_pos, "ego_speed": cf.speed_mps(agent.velocity_mps)},
        }
        cosim_meta: dict[str, Any] = {"agent_id": agent.agent_id, "track_id": agent.track_id, "cameras": {}}
        lidar_t = agent.map_from_cloud
        if lidar_t is not None:
            meta["lidar"] = {"lidar_pose": cf.relative_pose(cf.carla_pose_of_matrix(lidar_t), ego_pos)}
            pcd, labels = agent.lidar_files()
            write_bytes(folder / "lidar.pcd", pcd)
            write_bytes(folder / "lidar_labels.npz", labels)
        devkit = CAMERA_NAMES[agent.kind]
        for cam in agent.cameras(view.camera_names[agent.agent_id]):
            entry = {
                "cords": cf.relative_pose(cf.carla_pose_of_matrix(cam.map_from_camera), ego_pos),
                "intrinsic": cam.K.tolist(),
                "extrinsic": (cf.lidar_to_camera(lidar_t, cam.map_from_camera) if lidar_t is not None
                              else np.eye(4)).tolist(),
            }
            if cam.name in devkit:
                key = devkit[cam.name]
                meta[key] = entry
                base = key.removesuffix("_camera")
            else:
                cosim_meta["cameras"][cam.name] = entry
                key = base = f"cosim_{cam.name}"
            write_bytes(folder / f"{key}.png", cam.image_file(keep_jpeg=not self.options.png_images))
            if cam.lens is not None:
                cosim_meta.setdefault("undistorted", {})[cam.name] = list(cam.lens.D)
            if cam.has("depth"):
                write_bytes(folder / f"{base}_depth.png", depth_png(cam.depth_m()))
            if self.options.masks and cam.has("semantic"):
                write_bytes(folder / f"{base}_semantic.png", png_bytes(cam.semantic().astype(np.uint8)))
            if self.options.masks and cam.has("instance"):
                ids = np.clip(cam.instance(), 0, None)
                write_bytes(folder / f"{base}_instance.png", png_bytes(cf.encode_id_rgb24(ids)))
        cosim_meta["visibility"] = {t: {"lidar_points": int(v.get("lidar_points", 0)),
                                        "pixels": dict(v.get("pixels", {}))}
                                    for t, v in sorted(agent.visibility().items())}
        imu = agent.optional("imu")
        if imu is not None:
            cosim_meta["imu"] = {k: imu[k] for k in ("linear_acceleration_mps2", "angular_velocity_radps",
                                                     "orientation") if k in imu}
        gnss = agent.optional("gnss")
        if gnss is not None:
            cosim_meta["gnss"] = {"latitude_deg": gnss.latitude_deg, "longitude_deg": gnss.longitude_deg,
                                  "altitude_m": gnss.altitude_m}
        meta["cosim"] = cosim_meta
        write_bytes(folder / "metadata.pkl", pickle_bytes(plain(meta)))
        self.write_maps(view, agent, folder)

    def write_maps(self, view: TickView, agent: AgentView, folder: Path) -> None:
        layers = view.bev_maps(agent)
        zero = np.zeros(next(iter(layers.values())).shape, bool)
        lane = layers.get("lane_marking", zero)
        road = layers.get("road", zero) & ~lane
        background = ~(lane | road)
        for name, img in zip(STATIC_MAPS, (background, lane, road), strict=True):
            write_bytes(folder / f"map_static_{name}.png", png_bytes(img, SPARSE_PNG_LEVEL))
        for k in range(7):
            img = zero.copy()
            for name, layer in layers.items():
                if CLASS_IDS.get(name) == k:
                    img |= layer
            write_bytes(folder / f"map_dynamic_bev_layer_{k}.png", png_bytes(img, SPARSE_PNG_LEVEL))
