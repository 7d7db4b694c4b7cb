"""PyBullet rigid-body quadrotor (headless, ``pybullet.DIRECT``).

The airframe is one rigid box with the airframe's mass and principal inertia. Each step applies,
in the map frame: the 4 lagged rotor thrusts (along body +z, at their hubs, as one force and the
torque they make about the CG), the rotors' reaction (drag) torques about body z, and body drag
(quadratic plus linear rotor drag) against the air-relative velocity. The static world's raised
prisms are static convex hulls and the ground a plane, so the engine reports contacts.
PyBullet works in SI units and a z-up world frame already; its world frame is cosim's map frame.
"""

from __future__ import annotations

import math

import numpy as np
import pybullet

from cosim.drones.airframe import G_MPS2, RHO_KGPM3, Airframe
from cosim.drones.backends import register_backend
from cosim.drones.backends.base import DynamicsBackend
from cosim.drones.control import BodyState
from cosim.drones.obstacles import MIN_OBSTACLE_HEIGHT_M, prism_label
from cosim.geometry import quat_from_rpy, rotation_matrix
from cosim.world.types import World


def body_half_extents_m(frame: Airframe) -> tuple[float, float, float]:
    """Collision box of the airframe [m]: arms plus propeller discs, and a flat body."""
    half = frame.arm_m / math.sqrt(2.0) + 0.5 * frame.rotor_diameter_m
    return (half, half, 0.6 * frame.arm_m * 0.5)


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
        shape = pybullet.createCollisionShape(
            pybullet.GEOM_BOX, halfExtents=body_half_extents_m(frame), physicsClientId=c
        )
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
        c = self._client
        ground = world.layout.ground_z_m
        plane = pybullet.createCollisionShape(pybullet.GEOM_PLANE, physicsClientId=c)
        gid = pybullet.createMultiBody(0.0, plane, basePosition=(0.0, 0.0, ground), physicsClientId=c)
        self._labels[gid] = "ground"
        for p in world.layout.prisms:
            if p.z1_m <= ground + MIN_OBSTACLE_HEIGHT_M:
                continue
            verts = [(x, y, z) for x, y in p.footprint for z in (p.z0_m, p.z1_m)]
            shape = pybullet.createCollisionShape(pybullet.GEOM_MESH, vertices=verts, physicsClientId=c)
            bid = pybullet.createMultiBody(0.0, shape, physicsClientId=c)
            self._labels[bid] = prism_label(p)

    def reset(self, position_m: np.ndarray, yaw_rad: float) -> None:
        c = self._client
        pybullet.resetBasePositionAndOrientation(
            self._body, [float(v) for v in position_m], quat_from_rpy(0.0, 0.0, yaw_rad), physicsClientId=c
        )
        pybullet.resetBaseVelocity(self._body, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], physicsClientId=c)
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
            self._contact = self._labels.get(cp[2], f"body {cp[2]}")
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
