"""The ``open3d`` ray backend: Open3D's ``RaycastingScene`` (the reference engine of cosim's first
renderers, kept for comparison; :mod:`cosim.sensors.raycast`).

Open3D builds its BVH lazily on the first cast; :meth:`Open3dBackend.build` casts one ray so that the
scene is built before threads share it. ``cast_rays`` and ``test_occlusions`` hold the GIL and use
every core themselves. ``quality`` is ignored.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from .raycast import RAY_BACKENDS, Quality, misses


class Open3dBackend:
    name = "open3d"

    def build(self, vertices: np.ndarray, triangles: np.ndarray,
              quality: Quality = "high") -> o3d.t.geometry.RaycastingScene | None:
        if len(triangles) == 0:
            return None
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, np.float32)),
                            o3d.core.Tensor(np.ascontiguousarray(triangles, np.uint32)))
        scene.cast_rays(o3d.core.Tensor(np.array([[0, 0, 1e4, 0, 0, 1]], np.float32)))  # build the BVH now
        return scene

    def closest(self, scene: o3d.t.geometry.RaycastingScene | None,
                rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = rays.shape[0]
        if scene is None or n == 0:
            return misses(n)
        ans = scene.cast_rays(o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays, np.float32)))
        return ans["t_hit"].numpy(), ans["primitive_ids"].numpy().view(np.int32)  # INVALID_ID reads as -1

    def occluded(self, scene: o3d.t.geometry.RaycastingScene | None, rays: np.ndarray) -> np.ndarray:
        if scene is None or rays.shape[0] == 0:
            return np.zeros(rays.shape[0], bool)
        return scene.test_occlusions(o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays, np.float32))).numpy()


RAY_BACKENDS.add("open3d", Open3dBackend())
