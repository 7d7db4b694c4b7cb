"""Images of a distorting camera resampled onto its pinhole intrinsic, for layouts that carry only K.

The AirV2X and OPV2V files hold one 3 x 3 ``intrinsic`` per camera and no lens model. A cosim camera
with Brown-Conrady distortion (``distortion``; its ``/calibration`` has ``plumb_bob`` and a non-zero
``D``, docs/episode_format.md 3.6) is therefore exported as the image an ideal pinhole camera with the
same ``K`` would have taken: the pixel (col, row) of the exported image shows the ray through its
centre, ``K^-1 [col + 0.5, row + 0.5, 1]``, read from the recorded image where the lens put that ray,
``project_to_image(ray, K, D)``. So ``intrinsic`` = ``K`` is exact for every exported image, and a 3D
point projected with K alone lands where the object is in the picture.

RGB is interpolated bilinearly; depth, semantic and instance images take the nearest recorded pixel
(labels never blend). Pixels whose ray the lens did not record (outside the recorded image, at the
corners under pincushion distortion) are black, no depth (NaN), class 0 and instance 0. One
:class:`PinholeRemap` is computed per camera geometry and reused for every tick.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from cosim.geometry import has_distortion, project_to_image


@dataclass(frozen=True)
class PinholeRemap:
    """Where each pixel of the pinhole image lies in the recorded (distorted) image of the same size.

    ``nearest`` (H * W,) int32 flat index of the recorded pixel holding the ray's position;
    ``corners`` (4, H * W) int32 flat indices and ``weights`` (4, H * W) float32 of the bilinear taps
    (pixel centres at + 0.5); ``inside`` (H * W,) bool: the ray falls on the recorded image.
    """

    width: int
    height: int
    D: tuple[float, ...]  # the lens undone: plumb_bob k1, k2, p1, p2, k3
    nearest: np.ndarray
    corners: np.ndarray
    weights: np.ndarray
    inside: np.ndarray

    def bilinear(self, image: np.ndarray) -> np.ndarray:
        """(H, W[, C]) uint8 recorded image -> the pinhole image, same shape and dtype (rounded)."""
        flat = image.reshape(self.width * self.height, -1)
        acc = self.weights[0][:, None] * flat[self.corners[0]]  # float32
        for k in range(1, 4):
            acc += self.weights[k][:, None] * flat[self.corners[k]]
        acc[~self.inside] = 0.0
        return np.clip(np.rint(acc), 0, 255).astype(np.uint8).reshape(image.shape)

    def nearest_of(self, image: np.ndarray, fill: float | int) -> np.ndarray:
        """(H, W) recorded image -> the pinhole image, nearest pixel; ``fill`` where no ray was recorded."""
        out = image.reshape(-1)[self.nearest]
        out[~self.inside] = fill
        return out.reshape(image.shape)


@lru_cache(maxsize=8)  # about 30 MB each at 1280 x 720; a rig has few distinct camera geometries
def _remap(width: int, height: int, K: tuple[float, ...], D: tuple[float, ...]) -> PinholeRemap:
    k = np.asarray(K, np.float64).reshape(3, 3)
    col, row = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    y = (row.ravel() - k[1, 2]) / k[1, 1]
    x = (col.ravel() - k[0, 2] - k[0, 1] * y) / k[0, 0]
    uv, _ = project_to_image(np.stack([x, y, np.ones_like(x)], axis=1), k, D)  # where the lens put each ray
    u, v = uv[:, 0], uv[:, 1]
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    cu = np.clip(np.floor(u), 0, width - 1).astype(np.int32)
    cv = np.clip(np.floor(v), 0, height - 1).astype(np.int32)
    # Bilinear taps between the four recorded pixel centres around (u, v), clamped at the image border.
    su, sv = u - 0.5, v - 0.5
    u0, v0 = np.floor(su), np.floor(sv)
    fu, fv = (su - u0).astype(np.float32), (sv - v0).astype(np.float32)
    u0i = np.clip(u0, 0, width - 1).astype(np.int32)
    u1i = np.clip(u0 + 1, 0, width - 1).astype(np.int32)
    v0i = np.clip(v0, 0, height - 1).astype(np.int32)
    v1i = np.clip(v0 + 1, 0, height - 1).astype(np.int32)
    corners = np.stack([v0i * width + u0i, v0i * width + u1i, v1i * width + u0i, v1i * width + u1i])
    weights = np.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv])
    return PinholeRemap(width, height, D, cv * width + cu, corners, weights, inside)


def pinhole_remap(width: int, height: int, K: np.ndarray, D: np.ndarray | None) -> PinholeRemap | None:
    """The :class:`PinholeRemap` of a camera (cached per geometry), or None when ``D`` bends no ray."""
    if not has_distortion(D):
        return None
    return _remap(int(width), int(height), tuple(float(v) for v in np.asarray(K, np.float64).ravel()),
                  tuple(float(v) for v in np.asarray(D, np.float64).ravel()))
