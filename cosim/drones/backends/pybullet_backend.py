"""PyBullet rigid-body quadrotor (headless, ``pybullet.DIRECT``).

The airframe is one rigid box with the airframe's mass and principal inertia. Each step applies,
in the map frame: the 4 lagged rotor thrusts (along body +z, at their hubs, as one force and the
torque they make about the CG), the rotors' reaction (drag) torques about body z, and body drag
(quadratic plus linear rotor drag) against the air-relative velocity. The static world's raised
prisms are static boxes (each footprint's smallest enclosing rectangle: exact for the rectangular
buildings and poles of generated towns, conservative for other shapes) packed into compound bodies,
and the ground a plane, so the engine reports contacts; :mod:`cosim.drones.obstacles` adds an exact
geometric check for both backends.
PyBullet works in SI units and a z-up world frame already; its world frame is cosim's map frame.
"""

from __future__ import annotations

import ctypes
import math
import os
import sys

import numpy as np

from cosim.drones.airframe import G_MPS2, RHO_KGPM3, Airframe
from cosim.drones.backends.base import DynamicsBackend, register_backend
from cosim.drones.control import BodyState
from cosim.drones.obstacles import MIN_OBSTACLE_HEIGHT_M, prism_label
from cosim.geometry import quat_from_rpy, rotation_matrix
from cosim.world.types import Prism, World


def _quiet_import():
    """Import pybullet without the "pybullet build time" banner its C code writes at import."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        os.dup2(devnull, 2)
        import pybullet as module

        ctypes.CDLL(None).fflush(None)  # anything still in C's stdio buffers goes to /dev/null
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in [*saved, devnull]:
            os.close(fd)
    return module


pybullet = _quiet_import()

CHUNK = 512  # static boxes per compound body (one broadphase entry each)


def footprint_box(footprint: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Smallest-area rectangle around a footprint (K, 2) [m], trying each edge direction:
    centre (2,), half extents (2,) [m] and yaw [rad]. Exact for rectangles, conservative otherwise."""
    best = None
    for a, b in zip(footprint, np.roll(footprint, -1, axis=0), strict=True):
        yaw = math.atan2(b[1] - a[1], b[0] - a[0])
        c, s = math.cos(yaw), math.sin(yaw)
        local = footprint @ np.array([[c, -s], [s, c]])  # rotate by -yaw
        lo, hi = local.min(axis=0), local.max(axis=0)
        area = float(np.prod(hi - lo))
        if best is None or area < best[0]:
            mid = 0.5 * (lo + hi)
            best = (area, np.array([c * mid[0] - s * mid[1], s * mid[0] + c * mid[1]]), 0.5 * (hi - lo), yaw)
    assert best is not None
    return best[1], best[2], best[3]


@register_backend("pybullet")
class PyBulletBackend(DynamicsBackend):
    def __init__(self, frame: Airframe, dt_s: float, world: World):
        super().__init__(frame, dt_s, world)
        self._client = pybullet.connect(pybullet.DIRECT)
        c = self._client
        pybullet.resetSimulation(physicsClientId=c)
        pybullet.setGravity(0.0, 0.0, -G_MPS2, physicsClientId=c)
        pybullet.setPhysicsEngineParameter(fixedTimeStep=dt_s, numSubSteps=1, physicsClientId=c)
        self._labels: dict[int, str] = {}
        self._add_world(world)
        shape = pybullet.createCollisionShape(pybullet.GEOM_BOX, halfExtents=frame.half_extents_m, physicsClientId=c)
        self._body = pybullet.createMultiBody(
            baseMass=frame.mass_kg,
            baseCollisionShapeIndex=shape,
            basePosition=(0.0, 0.0, 100.0),
            physicsClientId=c,
        )
        pybullet.changeDynamics(
            self._body,
            -1,
            linearDamping=0.0,
            angularDamping=0.0,
            localInertiaDiagonal=frame.inertia_kgm2,
            physicsClientId=c,
        )
        self._specific_force = np.array([0.0, 0.0, G_MPS2])
        self._contact: str | None = None

    def _add_world(self, world: World) -> None:
        """The ground plane and every raised prism as an oriented box, packed into compound bodies
        (thousands of separate static bodies make each step ~1000x slower)."""
        c = self._client
        ground = world.layout.ground_z_m
        plane = pybullet.createCollisionShape(pybullet.GEOM_PLANE, physicsClientId=c)
        gid = pybullet.createMultiBody(0.0, plane, basePosition=(0.0, 0.0, ground), physicsClientId=c)
        self._labels[gid] = "ground"
        self._chunks: dict[int, tuple[list[Prism], np.ndarray]] = {}
        raised = [p for p in world.layout.prisms if p.z1_m > ground + MIN_OBSTACLE_HEIGHT_M]
        for start in range(0, len(raised), CHUNK):
            part = raised[start : start + CHUNK]
            centres, halves, quats = [], [], []
            for p in part:
                xy, half, yaw = footprint_box(np.asarray(p.footprint, dtype=np.float64))
                centres.append([xy[0], xy[1], 0.5 * (p.z0_m + p.z1_m)])
                halves.append([half[0], half[1], 0.5 * (p.z1_m - p.z0_m)])
                quats.append(quat_from_rpy(0.0, 0.0, yaw))
            shape = pybullet.createCollisionShapeArray(
                [pybullet.GEOM_BOX] * len(part),
                halfExtents=halves,
                collisionFramePositions=centres,
                collisionFrameOrientations=quats,
                physicsClientId=c,
            )
            bid = pybullet.createMultiBody(0.0, shape, physicsClientId=c)
            self._chunks[bid] = (part, np.array(centres))

    def _label_contact(self, body: int, point: tuple[float, float, float]) -> str:
        """Name what was hit: the ground, or the prism of that compound nearest the contact point."""
        if body in self._labels:
            return self._labels[body]
        if body not in self._chunks:
            return f"static body {body}"
        part, centres = self._chunks[body]
        d = np.hypot(centres[:, 0] - point[0], centres[:, 1] - point[1])
        return prism_label(part[int(np.argmin(d))])

    def reset(self, position_m: np.ndarray, yaw_rad: float, velocity_mps: np.ndarray | None = None) -> None:
        c = self._client
        pybullet.resetBasePositionAndOrientation(
            self._body, [float(v) for v in position_m], quat_from_rpy(0.0, 0.0, yaw_rad), physicsClientId=c
        )
        v = [0.0, 0.0, 0.0] if velocity_mps is None else [float(x) for x in velocity_mps]
        pybullet.resetBaseVelocity(self._body, v, [0.0, 0.0, 0.0], physicsClientId=c)
        self.rotors.thrust_n = np.full(4, self.frame.hover_thrust_n)
        self._specific_force = np.array([0.0, 0.0, G_MPS2])
        self._contact = None

    def step(self, rotor_command_n: np.ndarray, wind_mps: np.ndarray) -> None:
        c = self._client
        pos, quat = pybullet.getBasePositionAndOrientation(self._body, physicsClientId=c)
        vel, _ = pybullet.getBaseVelocity(self._body, physicsClientId=c)
        r = rotation_matrix(quat)
        self.rotors.step(rotor_command_n)
        force_b, torque_b = self.rotors.body_wrench()
        v_rel = np.asarray(vel) - wind_mps
        speed = float(np.linalg.norm(v_rel))
        drag_w = -(0.5 * RHO_KGPM3 * self.frame.drag_area_m2 * speed + self.frame.drag_linear_nspm) * v_rel
        force_w = r @ force_b + drag_w
        self._specific_force = force_b + r.T @ drag_w
        self._specific_force = self._specific_force / self.frame.mass_kg
        pybullet.applyExternalForce(self._body, -1, force_w.tolist(), pos, pybullet.WORLD_FRAME, physicsClientId=c)
        pybullet.applyExternalTorque(self._body, -1, (r @ torque_b).tolist(), pybullet.WORLD_FRAME, physicsClientId=c)
        pybullet.stepSimulation(physicsClientId=c)
        self._contact = None
        for cp in pybullet.getContactPoints(bodyA=self._body, physicsClientId=c):
            if cp[8] <= 0.0:  # penetration, not just inside the contact margin
                self._contact = self._label_contact(cp[2], cp[6])
                break

    def state(self) -> BodyState:
        c = self._client
        pos, quat = pybullet.getBasePositionAndOrientation(self._body, physicsClientId=c)
        vel, ang = pybullet.getBaseVelocity(self._body, physicsClientId=c)
        r = rotation_matrix(quat)
        return BodyState(
            position_m=np.array(pos),
            rotation=r,
            velocity_mps=np.array(vel),
            rate_radps=r.T @ np.array(ang),
            specific_force_mps2=self._specific_force.copy(),
        )

    def contact(self) -> str | None:
        return self._contact

    def close(self) -> None:
        if self._client is not None and pybullet.isConnected(physicsClientId=self._client):
            pybullet.disconnect(physicsClientId=self._client)
        self._client = None
