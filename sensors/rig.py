"""Where every sensor sits: mounts, gimbals, optical frames and camera intrinsics.

One function, :func:`sensor_transforms`, gives the ``/tf`` tree below ``<agent>/base_link``; the
renderer uses :func:`sensor_pose` built on the same rotations, so labels, poses and pixels agree by
construction. Rotations are 3x3 float64 matrices ``parent <- child`` or (x, y, z, w) quaternions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cosim.geometry import OPTICAL_FROM_FLU, quat_from_matrix, quat_from_rpy, rotation_matrix, rpy_from_quat
from cosim.scenario.model import CameraSpec, Mount, RigSpec, Scenario
from cosim.snapshot import AgentState

from .kinds import SENSOR_KINDS

#: Rotation optical -> camera body (FLU): columns are the optical axes written in FLU.
FLU_FROM_OPTICAL = OPTICAL_FROM_FLU.T

Transform = tuple[str, str, tuple[float, float, float], tuple[float, float, float, float]]


def mount_rotation(mount: Mount) -> np.ndarray:
    """body <- sensor rotation (3, 3) of a mount's roll, pitch, yaw [deg] (intrinsic Z-Y-X)."""
    r, p, y = (math.radians(a) for a in mount.rpy_deg)
    return rotation_matrix(quat_from_rpy(r, p, y))


def body_rotation(agent: AgentState) -> np.ndarray:
    """map <- base_link (3, 3)."""
    return rotation_matrix(agent.rotation)


def gimbal_rotation(agent: AgentState) -> np.ndarray:
    """map <- gimbal (3, 3): the agent's stabilised frame; level with the body's yaw when not given."""
    if agent.gimbal_rotation is not None:
        return rotation_matrix(agent.gimbal_rotation)
    _, _, yaw = rpy_from_quat(agent.rotation)
    return rotation_matrix(quat_from_rpy(0.0, 0.0, yaw))


def camera_rotation_in_body(agent: AgentState, cam: CameraSpec) -> np.ndarray:
    """base_link <- camera (FLU) rotation (3, 3); a gimbal camera's is expressed through the gimbal."""
    if cam.gimbal:
        return body_rotation(agent).T @ gimbal_rotation(agent) @ mount_rotation(cam.mount)
    return mount_rotation(cam.mount)


#: rows from which :func:`rotate` runs a compiled loop (one pass) instead of numpy's five
ROTATE_KERNEL_ROWS = 4096


def rotate(v: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """``v @ rot.T`` for tall (N, 3) arrays, without BLAS (whose threads crawl on busy machines)."""
    if len(v) >= ROTATE_KERNEL_ROWS and v.dtype.kind == "f" and rot.dtype.kind == "f":
        from .kernels import rotate_rows

        out = np.empty((len(v), 3), np.result_type(v.dtype, rot.dtype))
        rotate_rows(v, np.asarray(rot), out)
        return out
    return v[:, 0:1] * rot[:, 0] + v[:, 1:2] * rot[:, 1] + v[:, 2:3] * rot[:, 2]


@dataclass(frozen=True)
class Pose:
    """map <- frame: ``rotation`` (3, 3) float64, ``position_m`` (3,) float64."""

    rotation: np.ndarray
    position_m: np.ndarray

    def to_frame(self, points_map: np.ndarray) -> np.ndarray:
        """Points (N, 3) from map into this frame."""
        return rotate(points_map - self.position_m, self.rotation.T)


def sensor_pose(agent: AgentState, mount: Mount, rot_in_body: np.ndarray | None = None) -> Pose:
    """map <- sensor pose of a sensor mounted on ``agent``; ``rot_in_body`` overrides the mount's rpy."""
    rb = body_rotation(agent)
    r = rot_in_body if rot_in_body is not None else mount_rotation(mount)
    return Pose(rb @ r, np.asarray(agent.position_m, np.float64) + rb @ np.asarray(mount.xyz_m, np.float64))


def camera_pose(agent: AgentState, cam: CameraSpec) -> Pose:
    """map <- camera optical frame (x right, y down, z forward)."""
    body = sensor_pose(agent, cam.mount, camera_rotation_in_body(agent, cam))
    return Pose(body.rotation @ FLU_FROM_OPTICAL, body.position_m)


def intrinsics(cam: CameraSpec) -> np.ndarray:
    """Pinhole K (3, 3) float64: square pixels, horizontal FOV ``fov_deg``, principal point at the centre.

    Pixel (u, v) covers [u, u+1) x [v, v+1); its centre is (u + 0.5, v + 0.5).
    """
    f = 0.5 * cam.width / math.tan(math.radians(cam.fov_deg) / 2)
    return np.array([[f, 0.0, cam.width / 2], [0.0, f, cam.height / 2], [0.0, 0.0, 1.0]])


def projection(cam: CameraSpec) -> np.ndarray:
    """P (3, 4) = [K | 0] for the optical frame."""
    return np.hstack([intrinsics(cam), np.zeros((3, 1))])


def _quat(m: np.ndarray) -> tuple[float, float, float, float]:
    return quat_from_matrix(m)


def _t(v) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))


def rig_transforms(rig: RigSpec, agent: AgentState) -> list[Transform]:
    """Static-ish transforms of one rig below ``<agent>/base_link`` (see :func:`sensor_transforms`)."""
    a = agent.agent_id
    base = f"{a}/base_link"
    out: list[Transform] = []
    if rig.lidar is not None:
        out.append((base, f"{a}/lidar", _t(rig.lidar.mount.xyz_m), _quat(mount_rotation(rig.lidar.mount))))
    for cam in rig.cameras:
        out.append((base, f"{a}/{cam.name}", _t(cam.mount.xyz_m), _quat(camera_rotation_in_body(agent, cam))))
        out.append((f"{a}/{cam.name}", f"{a}/{cam.name}/optical", (0.0, 0.0, 0.0), _quat(FLU_FROM_OPTICAL)))
    for kind, _ in SENSOR_KINDS.items():
        if getattr(rig, kind, None) is not None:
            out.append((base, f"{a}/{kind}", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)))
    if rig.imu is not None:
        out.append((base, f"{a}/imu", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)))
    return out


def sensor_transforms(scenario: Scenario, agent_state: AgentState) -> list[Transform]:
    """``(parent, child, translation [m], rotation (x, y, z, w))`` for base_link -> sensor and
    sensor -> optical, for the agent's rig. A gimbal camera's rotation is expressed so that
    map -> base_link -> camera composes to ``gimbal_rotation`` x mount rotation.
    """
    return rig_transforms(scenario.rig_for(agent_state.agent_id), agent_state)
