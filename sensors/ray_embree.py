"""The ``embree`` ray backend: Embree 4 called directly from compiled code.

The library is the ``libembree4`` shipped inside the ``embreex`` wheel (``embreex.libs/``; no system
package). Scenes are built through ctypes (which releases the GIL): one triangle geometry per scene,
robust mode (:data:`SCENE_FLAGS`), build quality from the seam's hint (``high`` the static world,
``medium`` a tick's actors and each actor's own scene, ``low`` the swept boxes); the actors at a LiDAR
firing's time are a scene of translated instances of the actors' own scenes (:class:`EmbreeInstances`).
Rays are cast by numba ``nogil`` kernels (compiled on first use, cached on disk): nearest hits one ray at a
time (``rtcIntersect1``), occlusion 16 rays at a time (``rtcOccluded16``, the ``COHERENT`` flag on a packet
whose directions share an octant). Measured on every ray of a full-rig tick, replayed with the two kinds of
query alternating call by call: single rays cost 0.91-0.94x what 16-ray packets did for the cameras' nearest
hits and the same for the LiDAR sweeps, but the sun-shadow rays, which share one direction, cost 1.3x more
one at a time than as packets. Callers emit rays in spatially coherent order (image rows, LiDAR columns), so
that consecutive rays visit the same BVH nodes while they are in cache; casting threads run in parallel
(the GIL is released).

Embree is the engine inside Open3D's ``RaycastingScene`` too: the two backends hit the same triangles
but where a ray meets an edge shared by two triangles (then either is the nearest).
"""

from __future__ import annotations

import ctypes
import importlib.util
import threading
import weakref
from pathlib import Path

import llvmlite.binding as llvm
import numba
import numpy as np
from numba import types

from cosim.errors import CosimError

from .raycast import RAY_BACKENDS, Quality, misses

_QUALITY = {"low": 0, "medium": 1, "high": 2}  # RTC_BUILD_QUALITY_*
_GEOMETRY_TRIANGLE = 0  # RTC_GEOMETRY_TYPE_TRIANGLE
_BUFFER_INDEX, _BUFFER_VERTEX = 0, 1  # RTC_BUFFER_TYPE_*
_FORMAT_UINT3, _FORMAT_FLOAT3 = 0x5003, 0x9003  # RTC_FORMAT_*
#: RTCSceneFlags of every scene: ``RTC_SCENE_FLAG_ROBUST`` (no ray slips through an edge two triangles share).
#: Without it a tick's camera casting costs 0.79x the CPU (3.51 -> 2.76 CPU-s), but grazing rays slip between
#: the far-ground trapezoids at the map's edge (voids below the horizon, tests/test_sensors_data.py) and a
#: LiDAR beam in 0.8 M through other edges
SCENE_FLAGS = 1 << 2
_INVALID = 0xFFFFFFFF  # RTC_INVALID_GEOMETRY_ID
_QUERY_COHERENT = 1  # RTC_RAY_QUERY_FLAG_COHERENT

#: RTCRayHit as 4-byte slots: the ray (org xyz, tnear, dir xyz, time, tfar, mask, id, flags), the hit (Ng
#: xyz, u, v, primID, geomID, instID, instPrimID); 24 slots (96 bytes, 16-byte aligned). RTCRay16 has the
#: ray's slots as rows of 16 lanes.
_TFAR, _MASK, _ID, _FLAGS, _PRIM, _GEOM, _INST = 8, 9, 10, 11, 17, 18, 19
_GEOMETRY_INSTANCE = 121  # RTC_GEOMETRY_TYPE_INSTANCE
_FORMAT_FLOAT3X4_ROW_MAJOR = 0x9134
_SLOTS = 24


def library_path() -> Path:
    """The ``libembree4`` of the installed ``embreex`` wheel."""
    spec = importlib.util.find_spec("embreex")
    if spec is None or not spec.submodule_search_locations:
        raise CosimError("the embree ray backend needs the embreex wheel (pip install 'embreex>=4.3')")
    pkg = Path(next(iter(spec.submodule_search_locations)))
    found = sorted(pkg.parent.glob("embreex.libs/libembree4*.so*")) + sorted(pkg.glob("libembree4*.so*"))
    if not found:
        raise CosimError(f"no libembree4 in the embreex wheel at {pkg.parent} (embreex.libs/ is missing)")
    return found[0]


_LIB_PATH = str(library_path())
llvm.load_library_permanently(_LIB_PATH)  # the kernels' calls resolve rtcIntersect16 etc. by name
_lib = ctypes.CDLL(_LIB_PATH, mode=ctypes.RTLD_GLOBAL)
_p, _u, _i, _z = ctypes.c_void_p, ctypes.c_uint, ctypes.c_int, ctypes.c_size_t
for _name, _res, _args in (
    ("rtcNewDevice", _p, [ctypes.c_char_p]),
    ("rtcGetDeviceError", _i, [_p]),
    ("rtcNewScene", _p, [_p]),
    ("rtcSetSceneFlags", None, [_p, _i]),
    ("rtcSetSceneBuildQuality", None, [_p, _i]),
    ("rtcNewGeometry", _p, [_p, _i]),
    ("rtcSetNewGeometryBuffer", _p, [_p, _i, _u, _i, _z, _z]),
    ("rtcSetGeometryBuildQuality", None, [_p, _i]),
    ("rtcCommitGeometry", None, [_p]),
    ("rtcAttachGeometry", _u, [_p, _p]),
    ("rtcReleaseGeometry", None, [_p]),
    ("rtcCommitScene", None, [_p]),
    ("rtcReleaseScene", None, [_p]),
    ("rtcSetGeometryInstancedScene", None, [_p, _p]),
    ("rtcSetGeometryTransform", None, [_p, _u, _i, _p]),
    ("rtcAttachGeometryByID", None, [_p, _p, _u]),
):
    _fn = getattr(_lib, _name)
    _fn.restype, _fn.argtypes = _res, _args

_device = None
_device_lock = threading.Lock()


def _get_device() -> int:
    global _device
    with _device_lock:
        if _device is None:
            _device = _lib.rtcNewDevice(None)
            if not _device:
                raise CosimError("Embree could not create a device (rtcNewDevice returned NULL)")
        return _device


def _commit(owner: object, dev: int, scene: int, what: str) -> int:
    """Commit ``scene`` (its handle, released with ``owner``), or release it and raise on a device error."""
    _lib.rtcCommitScene(scene)
    err = _lib.rtcGetDeviceError(dev)
    if err:
        _lib.rtcReleaseScene(scene)
        raise CosimError(f"Embree failed to build a scene of {what} (error {err})")
    weakref.finalize(owner, _lib.rtcReleaseScene, scene)
    return int(scene)


class EmbreeScene:
    """One committed Embree scene of one triangle geometry (released when garbage collected); ``handle``
    is its ``RTCScene`` pointer."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, quality: Quality):
        dev = _get_device()
        q = _QUALITY[quality]
        scene = _lib.rtcNewScene(dev)
        _lib.rtcSetSceneFlags(scene, SCENE_FLAGS)
        _lib.rtcSetSceneBuildQuality(scene, q)
        geom = _lib.rtcNewGeometry(dev, _GEOMETRY_TRIANGLE)
        _lib.rtcSetGeometryBuildQuality(geom, q)
        v = np.ascontiguousarray(vertices, np.float32)
        t = np.ascontiguousarray(triangles, np.uint32)
        # Embree's own buffers (padded as its SIMD loads need); filled in place
        vp = _lib.rtcSetNewGeometryBuffer(geom, _BUFFER_VERTEX, 0, _FORMAT_FLOAT3, 12, len(v))
        tp = _lib.rtcSetNewGeometryBuffer(geom, _BUFFER_INDEX, 0, _FORMAT_UINT3, 12, len(t))
        if not vp or not tp:
            raise CosimError(f"Embree could not allocate a mesh of {len(v)} vertices and {len(t)} triangles "
                             f"(error {_lib.rtcGetDeviceError(dev)})")
        ctypes.memmove(vp, v.ctypes.data, v.nbytes)
        ctypes.memmove(tp, t.ctypes.data, t.nbytes)
        _lib.rtcCommitGeometry(geom)
        _lib.rtcAttachGeometry(scene, geom)
        _lib.rtcReleaseGeometry(geom)
        self.handle = _commit(self, dev, scene, f"{len(t)} triangles")
        self.n_triangles = len(t)


# ----------------------------------------------------------------------------------- kernels

_intersect1 = types.ExternalFunction("rtcIntersect1", types.void(types.uintp, types.uintp, types.uintp))
_occluded16 = types.ExternalFunction("rtcOccluded16", types.void(types.uintp, types.uintp, types.uintp, types.uintp))
_jit = numba.njit(cache=True, nogil=True, error_model="numpy")


@_jit
def _aligned(n, dtype):
    """A zeroed array of ``n`` items of 4 bytes starting on a 64-byte boundary."""
    buf = np.zeros(n + 16, dtype)
    off = ((64 - (buf.ctypes.data & 63)) & 63) >> 2
    return buf[off:off + n]


@_jit
def _fill(rays, i, f, u):
    """The ray slots of ``f`` (float32 view) / ``u`` (uint32 view of the same bytes) from ray ``i``: no hit yet."""
    f[0], f[1], f[2], f[3] = rays[i, 0], rays[i, 1], rays[i, 2], 0.0
    f[4], f[5], f[6], f[7] = rays[i, 3], rays[i, 4], rays[i, 5], 0.0
    f[_TFAR] = np.inf
    u[_MASK] = _INVALID
    u[_ID] = 0
    u[_FLAGS] = 0
    u[_GEOM] = _INVALID
    u[_INST] = _INVALID


@_jit
def _closest(scene, rays, t, prim, offsets):
    """Nearest hits; in a scene of instances (``offsets`` (I,) not empty) the triangle index is the hit
    instance's offset plus the triangle's index in its prototype."""
    f = _aligned(_SLOTS, np.float32)
    u = f.view(np.uint32)
    args = _aligned(16, np.uint32)  # RTCIntersectArguments: flags (incoherent), feature mask (all), NULL pointers
    args[1] = _INVALID
    for i in range(rays.shape[0]):
        _fill(rays, i, f, u)
        _intersect1(scene, f.ctypes.data, args.ctypes.data)
        if u[_GEOM] != _INVALID:
            t[i] = f[_TFAR]
            prim[i] = np.int32(u[_PRIM])
            if len(offsets):
                prim[i] += np.int32(offsets[u[_INST]])
        else:
            t[i] = np.inf
            prim[i] = -1


@_jit
def _coherent(rays, p, m):
    """Whether rays p .. p + m - 1 have directions in one octant."""
    sx, sy, sz = rays[p, 3] < 0, rays[p, 4] < 0, rays[p, 5] < 0
    for i in range(p + 1, p + m):
        if (rays[i, 3] < 0) != sx or (rays[i, 4] < 0) != sy or (rays[i, 5] < 0) != sz:
            return False
    return True


@_jit
def _occluded(scene, rays, out):
    """Occlusion of each ray, 16 at a time (``rtcOccluded16``): the sun-shadow rays of a batch all share one
    direction, and as packets they cost 0.73-0.76x what single rays do (lanes past the end switched off)."""
    n = rays.shape[0]
    f = _aligned(_SLOTS * 16, np.float32)
    u = f.view(np.uint32)
    valid = _aligned(16, np.int32)
    args = _aligned(16, np.uint32)  # RTCOccludedArguments: flags, feature mask (all), NULL pointers
    args[1] = _INVALID
    for p in range(0, n, 16):
        m = min(16, n - p)
        for k in range(16):  # RTCRay16: each slot a row of 16 lanes
            if k < m:
                i = p + k
                for j in range(3):
                    f[j * 16 + k] = rays[i, j]
                    f[(4 + j) * 16 + k] = rays[i, 3 + j]
                f[3 * 16 + k] = 0.0
                f[7 * 16 + k] = 0.0
                f[_TFAR * 16 + k] = np.inf
                u[_MASK * 16 + k] = _INVALID
                u[_ID * 16 + k] = 0
                u[_FLAGS * 16 + k] = 0
                valid[k] = -1
            else:
                valid[k] = 0
        args[0] = _QUERY_COHERENT if _coherent(rays, p, m) else 0
        _occluded16(valid.ctypes.data, scene, f.ctypes.data, args.ctypes.data)
        for k in range(m):
            out[p + k] = f[_TFAR * 16 + k] < 0  # Embree sets tfar to -inf on an occluded ray


class EmbreeInstances:
    """A committed Embree scene of translated instances of prototype scenes (released when garbage
    collected): instance i is ``prototypes[i]`` moved by ``translations[i]`` (None: no instance); a hit's
    triangle index is ``offsets[i]`` plus its index in the prototype."""

    def __init__(self, prototypes: list[EmbreeScene | None], translations: np.ndarray, offsets: np.ndarray):
        dev = _get_device()
        scene = _lib.rtcNewScene(dev)
        _lib.rtcSetSceneFlags(scene, SCENE_FLAGS)
        xfm = np.zeros(12, np.float32)
        xfm[[0, 5, 10]] = 1.0
        for i, proto in enumerate(prototypes):
            if proto is None:
                continue
            geom = _lib.rtcNewGeometry(dev, _GEOMETRY_INSTANCE)
            _lib.rtcSetGeometryInstancedScene(geom, proto.handle)
            xfm[[3, 7, 11]] = translations[i]
            _lib.rtcSetGeometryTransform(geom, 0, _FORMAT_FLOAT3X4_ROW_MAJOR, xfm.ctypes.data)
            _lib.rtcCommitGeometry(geom)
            _lib.rtcAttachGeometryByID(scene, geom, i)
            _lib.rtcReleaseGeometry(geom)
        self.handle = _commit(self, dev, scene, f"{len(prototypes)} instances")
        self.prototypes = prototypes  # kept alive while instanced
        self.offsets = np.ascontiguousarray(offsets, np.int64)


_FLAT = np.zeros(0, np.int64)  # the offsets of a scene that is not one of instances


class EmbreeBackend:
    name = "embree"

    def instances(self, prototypes: list[EmbreeScene | None], translations: np.ndarray,
                  offsets: np.ndarray) -> EmbreeInstances:
        """A scene of the ``prototypes`` (handles of :meth:`build`) each translated by its row of
        ``translations`` (N, 3) [m]; hits report ``offsets[i]`` plus the prototype's triangle index."""
        return EmbreeInstances(prototypes, translations, offsets)

    def build(self, vertices: np.ndarray, triangles: np.ndarray, quality: Quality = "high") -> EmbreeScene | None:
        if len(triangles) == 0:
            return None
        return EmbreeScene(vertices, triangles, quality)

    def closest(self, scene: EmbreeScene | None, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = rays.shape[0]
        if scene is None or n == 0:
            return misses(n)
        t = np.empty(n, np.float32)
        prim = np.empty(n, np.int32)
        _closest(scene.handle, np.ascontiguousarray(rays, np.float32), t, prim, getattr(scene, "offsets", _FLAT))
        return t, prim

    def occluded(self, scene: EmbreeScene | None, rays: np.ndarray) -> np.ndarray:
        out = np.zeros(rays.shape[0], bool)
        if scene is not None and len(out):
            _occluded(scene.handle, np.ascontiguousarray(rays, np.float32), out)
        return out


RAY_BACKENDS.add("embree", EmbreeBackend())
