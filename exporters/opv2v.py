"""The OPV2V / V2XSet layout (``DerrickXuNu/OpenCOOD``, read by ``opencood/data_utils/datasets/basedataset.py``,
documented in ``docs/md_files/data_intro.md``); docs/exports.md describes every file.

```
<out>/<split>/<YYYY_MM_DD_HH_MM_SS>/data_protocol.yaml
    <tick:06d>_cosim.json
    <agent>/<tick:06d>.yaml  <tick:06d>.pcd  <tick:06d>_camera0.png .. _camera3.png  <tick:06d>_<camera>.png
<out>/additional/<split>/<YYYY_MM_DD_HH_MM_SS>/<agent>/<tick:06d>_bev_{dynamic,static,lane}.png
```
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import yaml
from cosim.exporters import carla_frames as cf
from cosim.exporters.export import AgentView, ExportFormat, SequenceInfo, TickView, register_format
from cosim.exporters.export_io import SPARSE_PNG_LEVEL, json_text, plain, png_bytes, write_bytes, yaml_text

from cosim.io import Episode

#: The classes OPV2V's ``vehicles`` holds (the loaders treat every entry as a vehicle).
VEHICLE_CLASSES = ("car", "van", "truck", "bus", "motorcycle", "bicycle")
#: cosim camera -> OPV2V camera index per agent kind (0 front, 1 right rear, 2 left rear, 3 back).
CAMERA_INDEX: dict[str, dict[str, int]] = {
    "vehicle": {"front": 0, "rear_right": 1, "rear_left": 2, "rear": 3},
    "rsu": {"front": 0, "right": 1, "left": 2, "rear": 3},
    "drone": {},
}
#: Beside each tick's agent folders: ``<sequence>/<tick:06d>_cosim.json``, cosim's extras of the tick (every
#: object, each agent's ids, other cameras and returns per object). A file, not a folder: OpenCOOD takes every
#: folder of a sequence for an agent; and once per tick, not in each agent's yaml, which OpenCOOD parses whole.
TICK_FILE_SUFFIX = "_cosim.json"
#: OpenCOOD's default ``train_params.max_cav``: it reads the first this many agent folders (in string order) of
#: a sequence, prints ``too many cavs`` and drops the rest.
OPENCOOD_MAX_CAV = 7


def agent_folders(seq: SequenceInfo) -> dict[str, str]:
    """Agent folder names: vehicles ``+<track id>``, RSUs ``-<i+1>``, drones ``<track id>``.

    OpenCOOD sorts the folders as strings, takes the first as ego and moves only that one to the end
    when it is negative; ``+`` sorts before ``-`` and digits, so a vehicle is always first (ego) and
    every name still parses with ``int()`` (V2XSet's negative RSU ids stay negative).
    """
    out = {}
    for a in seq.agents:
        kind, track = seq.kinds[a], seq.track_ids[a]
        if kind == "rsu" or track is None:
            out[a] = f"-{int(a.rsplit('_', 1)[1]) + 1}"
        elif kind == "vehicle":
            out[a] = f"+{track}"
        else:
            out[a] = str(track)
    return out


def box_entry(view: TickView, i: int, rot: np.ndarray) -> dict[str, Any]:
    """One object as OPV2V's ``vehicles`` entries: location + center = box centre, angle [roll, yaw, pitch]
    in degrees, half extents, speed in km/h."""
    labels = view.labels
    pose = cf.carla_pose(labels.centers_m[i], rot)
    loc, centre = cf.box_location_center(labels.centers_m[i], rot, labels.sizes_m[i])
    return {"location": loc, "center": centre, "angle": pose[3:], "extent": cf.half_extent(labels.sizes_m[i]),
            "speed": cf.speed_kmh(labels.velocities_mps[i])}


@register_format
class Opv2vFormat(ExportFormat):
    name: ClassVar[str] = "opv2v"
    split_names: ClassVar[dict[str, str]] = {"val": "validate"}

    def __init__(self, seq: SequenceInfo, options: Any, root: Path):
        super().__init__(seq, options, root)
        self.folders = agent_folders(seq)

    @classmethod
    def extra_roots(cls, split: str, sequence: str) -> list[Path]:
        return [Path("additional") / cls.split_dir(split) / sequence]

    def write_sequence(self, ep: Episode) -> None:
        scenario = yaml.safe_load(ep.attachment("scenario.yaml")) if "scenario.yaml" in ep.attachments else {}
        protocol = {
            "cosim": {"generator": self.seq.metadata.get("generator"), "format": "opv2v"},
            "conditions": self.seq.conditions(),
            "agent_folders": dict(self.folders),
            "opencood": {"agent_folders": len(self.folders), "default_max_cav": OPENCOOD_MAX_CAV,
                         "note": self.max_cav_note() or f"every agent folder within OpenCOOD's default max_cav "
                                                         f"({OPENCOOD_MAX_CAV})"},
            "scenario": scenario,
        }
        write_bytes(self.root / "data_protocol.yaml", yaml_text(plain(protocol)).encode())

    def max_cav_note(self) -> str | None:
        """The line saying that OpenCOOD's default ``max_cav`` drops agents of this sequence, or None."""
        n = len(self.folders)
        if n <= OPENCOOD_MAX_CAV:
            return None
        dropped = sorted(self.folders.values())[OPENCOOD_MAX_CAV:]
        return (f"{n} agent folders; OpenCOOD reads the first {OPENCOOD_MAX_CAV} (default max_cav) in string "
                f"order, prints 'too many cavs' and drops {', '.join(dropped)}: set train_params.max_cav: {n} "
                "(docs/exports.md)")

    def warnings(self) -> list[str]:
        note = self.max_cav_note()
        return [f"{self.seq.name}: {note}"] if note else []

    def write_tick(self, view: TickView) -> None:
        labels = view.labels
        boxes = {int(labels.track_ids[i]): box_entry(view, i, rot) for i, rot in enumerate(view.object_rotations())}
        extras: dict[str, dict[str, Any]] = {}
        view.for_each_agent(lambda agent: extras.__setitem__(agent.agent_id, self.write_agent(view, agent, boxes)))
        doc = {
            "tick": view.index,
            "objects": {track: {**boxes[track], "class": labels.classes[i]}
                        for i, track in enumerate(int(t) for t in labels.track_ids)},
            "agents": {self.folders[a]: extras[a] for a in self.seq.agents},
        }
        write_bytes(self.root / f"{view.index:06d}{TICK_FILE_SUFFIX}", json_text(plain(doc)).encode())

    def write_agent(self, view: TickView, agent: AgentView, boxes: dict[int, dict[str, Any]]) -> dict[str, Any]:
        """Write one agent's files of the tick; return its entry of the tick's ``_cosim.json``."""
        folder = self.root / self.folders[agent.agent_id]
        stem = f"{view.index:06d}"
        ego_pos = cf.carla_pose_of_matrix(agent.map_from_base)
        lidar_t = agent.map_from_cloud
        doc: dict[str, Any] = {}
        extra_cams: dict[str, Any] = {}
        index = CAMERA_INDEX[agent.kind]
        undistorted: dict[str, list[float]] = {}
        for cam in agent.cameras(view.camera_names[agent.agent_id]):
            if cam.lens is not None:
                undistorted[cam.name] = list(cam.lens.D)
            entry = {
                "cords": cf.carla_pose_of_matrix(cam.map_from_camera),
                "intrinsic": cam.K.tolist(),
                "extrinsic": (cf.lidar_to_camera(lidar_t, cam.map_from_camera) if lidar_t is not None
                              else np.eye(4)).tolist(),
            }
            image = cam.image_file(keep_jpeg=not self.options.png_images)
            if cam.name in index:
                doc[f"camera{index[cam.name]}"] = entry
                write_bytes(folder / f"{stem}_camera{index[cam.name]}.png", image)
            else:
                extra_cams[cam.name] = entry
                write_bytes(folder / f"{stem}_{cam.name}.png", image)
        doc = dict(sorted(doc.items()))
        doc["ego_speed"] = cf.speed_kmh(agent.velocity_mps)
        doc["lidar_pose"] = cf.carla_pose_of_matrix(lidar_t if lidar_t is not None else agent.map_from_base)
        doc["plan_trajectory"] = []
        doc["predicted_ego_pos"] = ego_pos
        doc["true_ego_pos"] = ego_pos
        doc["RSU"] = agent.kind == "rsu"
        seen = {t: int(v.get("lidar_points", 0)) for t, v in agent.visibility().items()}
        classes = dict(zip((int(t) for t in view.labels.track_ids), view.labels.classes, strict=True))
        doc["vehicles"] = {t: boxes[t] for t in boxes
                           if classes[t] in VEHICLE_CLASSES and seen.get(t, 0) > 0 and t != agent.track_id}
        write_bytes(folder / f"{stem}.yaml", yaml_text(plain(doc)).encode())
        if lidar_t is not None:
            pcd, lidar_labels = agent.lidar_files()
            write_bytes(folder / f"{stem}.pcd", pcd)
            write_bytes(folder / f"{stem}_lidar_labels.npz", lidar_labels)
        self.write_bev(view, agent, stem)
        extra: dict[str, Any] = {"agent_id": agent.agent_id, "kind": agent.kind, "track_id": agent.track_id,
                                 "cameras": extra_cams,
                                 "lidar_points": {t: n for t, n in sorted(seen.items()) if n > 0 and t in boxes}}
        if undistorted:
            extra["undistorted"] = undistorted
        return extra

    def write_bev(self, view: TickView, agent: AgentView, stem: str) -> None:
        layers = view.bev_maps(agent)
        zero = np.zeros(next(iter(layers.values())).shape, bool)
        dynamic = zero.copy()
        for name in VEHICLE_CLASSES:
            dynamic |= layers.get(name, zero)
        static = layers.get("road", zero) | layers.get("lane_marking", zero)
        folder = self.staged(self.extra_roots(self.seq.split, self.seq.name)[0]) / self.folders[agent.agent_id]
        for name, img in (("dynamic", dynamic), ("static", static), ("lane", layers.get("lane_marking", zero))):
            write_bytes(folder / f"{stem}_bev_{name}.png", png_bytes(img, SPARSE_PNG_LEVEL))
