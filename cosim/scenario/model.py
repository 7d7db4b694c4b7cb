"""Scenario schema: frozen pydantic models, validated once at load.

Every model forbids unknown keys; cross-field rules live on the model that owns the fields.
Defaults reproduce the AirV2X-Perception setting (paper Table 2, docs/conventions.md section 5).
"""

from __future__ import annotations

import json
import re
import types
from fractions import Fraction
from typing import Annotated, Any, Literal, Union, get_args, get_origin

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_serializer, model_validator

from .lidar_presets import LIDAR_PRESETS, expand_lidar
from .merge import merge_fields

TICK_NS_PER_S = 1_000_000_000
#: What ``output.name`` may be: a file stem that cannot leave the output folder or hide the file.
FILE_STEM_PATTERN = r"[A-Za-z0-9][A-Za-z0-9_.+=-]{0,199}"

ObjectClass = Literal["car", "van", "truck", "bus", "motorcycle", "bicycle"]
Weather = Literal["clear", "cloudy", "foggy", "rainy"]
Lighting = Literal["day", "dusk", "night"]
MapKind = Literal["urban", "suburban", "rural", "highway", "net", "osm"]
DynamicsBackend = Literal["jsbsim", "pybullet"]
LidarModelName = Literal[tuple(LIDAR_PRESETS)]  # type: ignore[valid-type]  # generic, hdl64e, ... (datasheets)

#: [m] largest map coordinate: networks lie about the origin (generated ones span at most 5 km, netconvert
#: moves imported ones there); a point farther out is a typo, not a place.
MAX_MAP_COORD_M = 1_000_000.0
MapCoord = Annotated[float, Field(ge=-MAX_MAP_COORD_M, le=MAX_MAP_COORD_M)]
MapXY = tuple[MapCoord, MapCoord]  # [m] map x, y
MountCoord = Annotated[float, Field(ge=-50.0, le=50.0)]  # [m] a sensor's place on its agent
Angle = Annotated[float, Field(ge=-360.0, le=360.0)]  # [deg]


class RuleError(ValueError):
    """A cross-field rule failed; ``path`` is the offending key relative to the model checking it."""

    def __init__(self, path: str, message: str):
        super().__init__(message)
        self.path = path


class Model(BaseModel):
    """Base: immutable, no unknown keys, no NaN or infinity in any number, validated on assignment-free
    construction only; numbers must be numbers and switches booleans (:class:`WrongKind`)."""

    model_config = ConfigDict(frozen=True, extra="forbid", validate_default=True, allow_inf_nan=False)

    @model_validator(mode="before")
    @classmethod
    def _strict_scalars(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        out = dict(data)
        for name, field in cls.model_fields.items():
            if name in out:
                out[name] = _strict(field.annotation, out[name])
        return out


class WrongKind:
    """A scalar of the wrong kind for its field (``true`` or ``"20"`` for a number, ``1`` for a switch), put in
    its place by :meth:`Model._strict_scalars`: pydantic then reports it at its key path along with every other
    problem, and the loader's message is :attr:`message` (pydantic's lax mode would have turned ``true`` into
    1 s and ``"20"`` into 20)."""

    __slots__ = ("message", "value")

    def __init__(self, value: Any, message: str):
        self.value = value
        self.message = message

    def __repr__(self) -> str:
        return json.dumps(self.value)


def _strict(annotation: Any, value: Any) -> Any:
    """``value`` with every scalar of the wrong kind for ``annotation`` replaced by a :class:`WrongKind`;
    containers are checked item by item, other mismatches left to pydantic."""
    origin = get_origin(annotation)
    if origin is Annotated:
        return _strict(get_args(annotation)[0], value)
    if origin in (Union, types.UnionType):
        options = [a for a in get_args(annotation) if a is not type(None)]
        if value is None or len(options) != 1:
            return value
        return _strict(options[0], value)
    if origin in (tuple, list) and isinstance(value, list | tuple):
        args = get_args(annotation)
        items = args[:1] * len(value) if origin is list or (len(args) == 2 and args[1] is Ellipsis) else args
        checked = [_strict(item, v) for item, v in zip(items, value, strict=False)] + list(value[len(items):])
        return value if all(a is b for a, b in zip(checked, value, strict=True)) else type(value)(checked)
    if origin is dict and isinstance(value, dict):
        item = get_args(annotation)[1]
        checked = {k: _strict(item, v) for k, v in value.items()}
        return value if all(checked[k] is v for k, v in value.items()) else checked
    if not isinstance(value, bool | int | float | str):
        return value
    shown = json.dumps(value)
    shown = shown if len(shown) <= 80 else f"{shown[:60]}... ({len(shown)} characters)"
    if annotation is bool and not isinstance(value, bool):
        return WrongKind(value, f"expected true or false, got {shown}")
    if annotation is float and isinstance(value, bool | str):
        return WrongKind(value, f"expected a number, got {shown}")
    if annotation is int and isinstance(value, bool | str | float):
        return WrongKind(value, f"expected a whole number, got {shown}")
    return value


def _unique(names: list[str], rule: str) -> None:
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise ValueError(f"{rule}; repeated: {', '.join(dupes)}")


def _rate_divides_tick(name: str, rate_hz: float, tick_hz: float) -> None:
    ratio = Fraction(rate_hz).limit_denominator(10_000) / Fraction(tick_hz).limit_denominator(10_000)
    if ratio.denominator != 1 or ratio < 1:
        raise RuleError(
            name,
            f"{name} = {rate_hz:g} Hz does not divide the tick: it must be a whole multiple of "
            f"tick_hz = {tick_hz:g} Hz (for example {tick_hz * 4:g} or {tick_hz * 20:g})"
        )


# --------------------------------------------------------------------------------------- world


class MapSpec(Model):
    """Road network. Generated kinds are deterministic from the scenario seed."""

    kind: MapKind = "urban"
    file: str | None = None  # .net.xml (kind net) or .osm (kind osm); relative to the scenario file
    size_m: float = Field(400.0, gt=50.0, le=5000.0)  # [m] side of the generated square area
    lanes: int | None = Field(None, ge=1, le=5)  # lanes per direction; None = the kind's default
    # roadside clutter (cosim/world/clutter.py): kitti adds walls, fences, hedges, bushes, poles, bollards,
    # signs, banks and close houses beyond the kerbs; none (the default) leaves the world as it was
    clutter: Literal["none", "kitti"] = "none"

    @model_serializer(mode="wrap")
    def _dump(self, handler: Any) -> Any:
        out = handler(self)
        if self.clutter == "none":  # worlds and resolved scenarios without clutter keep their bytes
            out.pop("clutter", None)
        return out

    @model_validator(mode="after")
    def _file_matches_kind(self) -> MapSpec:
        if self.kind in ("net", "osm") and not self.file:
            raise RuleError("file", f"map.kind {self.kind!r} needs map.file")
        if self.kind not in ("net", "osm") and self.file:
            raise RuleError("file", f"map.file is only used with kind 'net' or 'osm', not {self.kind!r}")
        return self


class GeoOrigin(Model):
    lat_deg: float = Field(37.3352, ge=-90, le=90)
    lon_deg: float = Field(-121.8811, ge=-180, le=180)
    alt_m: float = Field(20.0, ge=-500.0, le=9000.0)  # [m] above the WGS84 ellipsoid


class EnvironmentSpec(Model):
    weather: Weather = "clear"
    lighting: Lighting = "day"
    fog_visibility_m: float | None = Field(None, gt=0, le=100_000.0)  # None = weather's default
    rain_rate_mm_h: float | None = Field(None, ge=0, le=500.0)
    wind_mps: float = Field(3.0, ge=0, le=20)  # mean wind at drone altitude
    gust_mps: float = Field(1.5, ge=0, le=15)  # gust standard deviation


class TrafficSpec(Model):
    density_veh_per_km: float = Field(12.0, ge=0, le=200)  # background vehicles per km of road
    mix: dict[ObjectClass, float] = Field(
        default_factory=lambda: {
            "car": 0.6,
            "van": 0.1,
            "truck": 0.08,
            "bus": 0.05,
            "motorcycle": 0.1,
            "bicycle": 0.07,
        }
    )
    step_hz: float = Field(20.0, gt=0, le=1000.0)  # SUMO sub-step rate; whole multiple of tick_hz
    # signal plans (cosim/world/signals.py): actuated (gap-based, cycle by junction size, seeded offsets),
    # fixed (the same plan at fixed times) or as_built (the network's own programs, e.g. a map.file's)
    signals: Literal["actuated", "fixed", "as_built"] = "actuated"

    @field_validator("mix")
    @classmethod
    def _mix_is_distribution(cls, mix: dict[str, float]) -> dict[str, float]:
        if not mix:
            raise ValueError("traffic.mix needs at least one class")
        if any(not 0 <= v <= 1e6 for v in mix.values()):
            raise ValueError("traffic.mix shares must lie in [0, 1e6] (they are normalised to sum to 1)")
        total = sum(mix.values())
        if total <= 0:
            raise ValueError("traffic.mix shares must not all be 0")
        return {k: v / total for k, v in sorted(mix.items())}


# -------------------------------------------------------------------------------------- agents


class AgentRigs(Model):
    """What a group of counted agents (vehicles, RSUs) shares: ``rigs``, one agent's own rig by agent id
    (``vehicle_1: {lidar: {model: vlp16}}``, ``vehicle_2: {lidar: null}``), given partly and completed field
    by field from its kind's rig ``sensors.<kind>`` (:func:`complete_agent_rigs`). Left out of the resolved
    scenario while empty (:meth:`_dump`), so episodes without per-agent rigs keep their bytes."""

    count: int = Field(4, ge=0, le=32)
    rigs: dict[str, RigSpec] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _rig_ids_exist(self) -> AgentRigs:
        prefix = AGENT_KIND_OF_GROUP[type(self).__name__]
        for agent_id in self.rigs:
            stem, _, index = agent_id.rpartition("_")
            if stem != prefix or not index.isdigit() or str(int(index)) != index:
                raise RuleError(f"rigs.{agent_id}", f"{agent_id!r} is not a {prefix} id (expected {prefix}_0, "
                                                    f"{prefix}_1, ...)")
            if int(index) >= self.count:
                have = (f"{self.count} ({prefix}_0..{prefix}_{self.count - 1})" if self.count else
                        f"none (agents.{prefix}s.count is 0)")
                raise RuleError(f"rigs.{agent_id}", f"no agent {agent_id!r}: the scenario's {prefix} agents are "
                                                    f"{have}")
        return self

    @model_serializer(mode="wrap")
    def _dump(self, handler: Any) -> Any:
        out = handler(self)
        if not self.rigs:
            out.pop("rigs", None)
        return out


class VehicleAgents(AgentRigs):
    vclass: ObjectClass = "car"


class RsuAgents(AgentRigs):
    height_m: tuple[float, float] = (6.0, 10.0)  # [m] pole height range, drawn per RSU

    @model_validator(mode="after")
    def _range(self) -> RsuAgents:
        lo, hi = self.height_m
        if not 0 < lo <= hi <= 100:
            raise RuleError("height_m", f"rsus.height_m must be 0 < low <= high <= 100, got {list(self.height_m)}")
        return self


#: The agent kind (id prefix) of each group of counted agents.
AGENT_KIND_OF_GROUP = {"VehicleAgents": "vehicle", "RsuAgents": "rsu"}


class DroneBase(Model):
    backend: DynamicsBackend | None = None  # None = agents.drone_backend
    altitude_m: float = Field(60.0, ge=5.0, le=300.0)  # [m] above ground
    max_speed_mps: float = Field(15.0, gt=0, le=40)
    start: MapXY | None = None  # [m] map x, y; None = chosen by the strategy
    clearance_m: float = Field(10.0, ge=0.0, le=200.0)  # [m] kept above obstacle tops along the path
    plan_altitude: bool = True  # False: fly at altitude_m whatever is below (can collide; for tests)
    #: this drone's own rig, given partly and completed field by field from ``sensors.drone``
    #: (:func:`complete_agent_rigs`); None: ``sensors.drone`` itself (left out of the resolved scenario)
    rig: RigSpec | None = None

    @model_serializer(mode="wrap")
    def _dump(self, handler: Any) -> Any:
        out = handler(self)
        if self.rig is None:
            out.pop("rig", None)
        return out


class HoverDrone(DroneBase):
    strategy: Literal["hover"] = "hover"
    point: MapXY | None = None  # [m] map x, y; None = above a junction


class PatrolDrone(DroneBase):
    strategy: Literal["patrol"] = "patrol"
    waypoints: list[MapXY] | None = Field(None, max_length=10_000)  # [m] map x, y; None = generated along roads
    loop_length_m: float = Field(400.0, gt=20, le=100_000.0)  # for generated loops
    speed_mps: float = Field(8.0, gt=0, le=40)
    reach_radius_m: float = Field(2.0, gt=0, le=100.0)

    @model_validator(mode="after")
    def _enough_waypoints(self) -> PatrolDrone:
        if self.waypoints is not None and len(self.waypoints) < 2:
            raise RuleError("waypoints", "a patrol needs at least 2 waypoints")
        if self.speed_mps > self.max_speed_mps:
            raise RuleError("speed_mps", f"speed_mps {self.speed_mps} exceeds max_speed_mps {self.max_speed_mps}")
        return self


class EscortDrone(DroneBase):
    strategy: Literal["escort"] = "escort"
    target: str = "vehicle_0"  # agent id of a connected vehicle
    # [m] in the target's body frame (forward, left)
    offset_m: tuple[Annotated[float, Field(ge=-500.0, le=500.0)], Annotated[float, Field(ge=-500.0, le=500.0)]] = (
        -8.0, 0.0)
    altitude_m: float = Field(40.0, ge=5.0, le=300.0)

    @field_validator("target")
    @classmethod
    def _vehicle_target(cls, target: str) -> str:
        prefix, _, index = target.partition("_")
        if prefix != "vehicle" or not index.isdigit():
            raise ValueError(f"escort target must be a connected vehicle id like 'vehicle_0', got {target!r}")
        return target


DroneSpec = Annotated[HoverDrone | PatrolDrone | EscortDrone, Field(discriminator="strategy")]


def union_tags(union: Any) -> tuple[str, ...]:
    """The tag values of a discriminated union of models (``Annotated[A | B, Field(discriminator=...)]``), in
    declaration order: a new kind is a new member of the union and every list of kinds follows from it."""
    members, info = get_args(union)[:2]
    return tuple(tag for cls in get_args(members) for tag in get_args(cls.model_fields[info.discriminator].annotation))


#: ``hover``, ``patrol``, ``escort``: the drone strategies of :data:`DroneSpec`.
DRONE_STRATEGIES = union_tags(DroneSpec)


class AgentsSpec(Model):
    #: where the connected agents go (docs/evaluation.md, "Collaboration"): ``cooperative`` departs the
    #: connected vehicles as a group on one shared route, stands the RSUs at the junctions of that route and
    #: sends hover and patrol drones over it; ``spread`` draws every agent independently over the map
    layout: Literal["cooperative", "spread"] = "cooperative"
    vehicles: VehicleAgents = Field(default_factory=VehicleAgents)
    rsus: RsuAgents = Field(default_factory=RsuAgents)
    drones: list[DroneSpec] = Field(
        default_factory=lambda: [HoverDrone(), PatrolDrone(), EscortDrone(target="vehicle_0")]
    )
    drone_backend: DynamicsBackend = "jsbsim"
    drone_physics_hz: float = Field(50.0, gt=0, le=10_000.0)  # dynamics rate; whole multiple of tick_hz
    drone_mass_kg: float = Field(3.5, gt=0.2, le=30)
    #: [m] kept between any two drones in flight (altitude layers, yielding); 0 turns it off
    drone_separation_m: float = Field(15.0, ge=0.0, le=200.0)

    def drone_backend_of(self, index: int) -> DynamicsBackend:
        return self.drones[index].backend or self.drone_backend

    @model_validator(mode="after")
    def _escort_targets_exist(self) -> AgentsSpec:
        for i, d in enumerate(self.drones):
            if isinstance(d, EscortDrone):
                n = int(d.target.split("_")[1])
                if n >= self.vehicles.count:
                    have = (f"{self.vehicles.count} connected vehicles (vehicle_0..vehicle_{self.vehicles.count - 1})"
                            if self.vehicles.count > 1 else
                            "1 connected vehicle (vehicle_0)" if self.vehicles.count == 1 else
                            "no connected vehicles (agents.vehicles.count is 0)")
                    raise RuleError(f"drones.{i}.target", f"escort target {d.target!r} does not exist: the scenario "
                                                          f"has {have}")
        return self


# ------------------------------------------------------------------------------------- sensors


class Mount(Model):
    """Sensor pose in its agent's body frame (FLU), metres and degrees."""

    xyz_m: tuple[MountCoord, MountCoord, MountCoord] = (0.0, 0.0, 0.0)
    rpy_deg: tuple[Angle, Angle, Angle] = (0.0, 0.0, 0.0)


class LidarSpec(Model):
    """A LiDAR (docs/episode_format.md 3.4). ``pattern`` names a scan pattern of the registry in
    ``cosim.sensors.lidar``: ``spinning`` (``channels`` rings from ``lower_fov_deg`` to ``upper_fov_deg``,
    evenly spaced or at the elevations of ``elevations_deg``, ``horizontal_resolution_deg`` apart, one sweep
    per 1/``rotation_hz``) or ``rosette`` (a Livox-style non-repetitive pattern: ``point_rate_hz`` points
    per second over a circular ``rosette_fov_deg`` about the sensor's +x; one frame per 1/``rotation_hz``).

    ``model`` names a datasheet preset (:mod:`cosim.scenario.lidar_presets`, docs/lidar_models.md) that the
    loader expands into these fields; fields set beside it override it. ``intensity_transfer`` is how the
    sensor reports intensity (``cosim.sensors.lidar_models``). ``self_occlusion``: beams whose first hit is
    the carrying vehicle's own body return nothing. The four fields that came with the presets and levers
    are left out of the resolved scenario while they hold their defaults (:meth:`_dump`), so episodes of
    the generic rig keep their bytes."""

    model: LidarModelName = "generic"
    pattern: Literal["spinning", "rosette"] = "spinning"
    channels: int = Field(64, ge=1, le=256)
    # [deg] ring elevations, ascending (ring 0 the lowest); null: evenly spaced from lower to upper FOV
    elevations_deg: tuple[Annotated[float, Field(ge=-90.0, le=90.0)], ...] | None = None
    intensity_transfer: Literal["linear", "kitti", "calibrated_100", "livox_150"] = "linear"
    upper_fov_deg: float = 10.0
    lower_fov_deg: float = -38.0
    horizontal_resolution_deg: float = Field(0.35, gt=0.01, le=10)
    rotation_hz: float = Field(20.0, gt=0, le=1000.0)  # sweeps (spinning) or frames (rosette) per second
    point_rate_hz: float = Field(100_000.0, gt=0, le=5_000_000)  # rosette: points per second
    rosette_fov_deg: float = Field(70.4, gt=1, lt=180)  # rosette: circular field of view (full angle)
    range_m: float = Field(120.0, gt=1, le=500)
    range_noise_m: float = Field(0.02, ge=0, le=10.0)
    dropout: float = Field(0.0, ge=0, lt=1)
    # ray drop (cosim.sensors.lidar, docs/assets.md): CARLA's three parameters in CARLA's meaning, and the
    # range [m] at which a 10 % Lambertian target at normal incidence is still detected 9 times in 10
    dropoff_general_rate: float = Field(0.02, ge=0, le=1)
    dropoff_intensity_limit: float = Field(0.1, ge=0, le=1)
    dropoff_zero_intensity: float = Field(0.3, ge=0, le=1)
    detection_range_10pct_m: float = Field(50.0, gt=1, le=5000)
    motion_distortion: bool = True  # each firing at its own time within the sweep (false: one snapshot)
    dual_returns: bool = False  # strongest and last return where a beam partly hits a near object
    # the carrying vehicle's own body blocks the beams that meet it first (no return), as on a real roof
    # mount (docs/lidar_models.md, "What real scans lose"); on in the hdl64e preset
    self_occlusion: bool = False
    mount: Mount = Mount(xyz_m=(0.0, 0.0, 1.9))

    @model_validator(mode="after")
    def _fov(self) -> LidarSpec:
        if not -90.0 <= self.lower_fov_deg < self.upper_fov_deg <= 90.0:
            raise RuleError(
                "lower_fov_deg",
                f"lidar vertical FOV must satisfy -90 <= lower < upper <= 90, "
                f"got lower {self.lower_fov_deg}, upper {self.upper_fov_deg}"
            )
        table = self.elevations_deg
        if table is not None:
            if len(table) != self.channels:
                raise RuleError("elevations_deg", f"elevations_deg gives {len(table)} rings but channels is "
                                                  f"{self.channels}")
            if list(table) != sorted(table) or (table[0], table[-1]) != (self.lower_fov_deg, self.upper_fov_deg):
                raise RuleError("elevations_deg",
                                f"elevations_deg must ascend from lower_fov_deg ({self.lower_fov_deg:g}) to "
                                f"upper_fov_deg ({self.upper_fov_deg:g}), got {table[0]:g} .. {table[-1]:g}")
        return self

    @model_serializer(mode="wrap")
    def _dump(self, handler: Any) -> Any:
        out = handler(self)
        for name in ("model", "elevations_deg", "intensity_transfer", "self_occlusion"):
            if getattr(self, name) == LidarSpec.model_fields[name].default:
                out.pop(name, None)
        return out


CameraOutput = Literal["rgb", "depth", "semantic", "instance"]


class CameraSpec(Model):
    name: str = Field(pattern=r"^[a-z][a-z0-9_]*$")
    width: int = Field(1280, ge=16, le=8192)
    height: int = Field(720, ge=16, le=8192)
    fov_deg: float = Field(110.0, gt=1, lt=179)  # horizontal
    mount: Mount = Mount()
    gimbal: bool = False  # True: orientation held in the map frame (nadir), yaw follows the body
    outputs: tuple[CameraOutput, ...] = ("rgb", "depth", "semantic", "instance")
    # camera model (docs/architecture.md, "Sensors"): noise std in full-scale units (read) and variance per unit
    # signal (shot), seeded; vignetting: light lost at the image corners (fraction, e.g. 0.25). Off by default:
    # noise makes lossless PNG ~50x larger, and either takes the per-pixel floating-point colour path by day
    read_noise: float = Field(0.0, ge=0, le=0.5)
    shot_noise: float = Field(0.0, ge=0, le=0.5)
    vignetting: float = Field(0.0, ge=0, lt=1)
    # Brown-Conrady lens distortion (k1, k2, p1, p2, k3), OpenCV / ROS plumb_bob convention; null: a pinhole
    distortion: tuple[float, float, float, float, float] | None = None


def _check_lens(cam: CameraSpec) -> None:
    """A camera's ``distortion`` must map its picture one to one onto rays (the renderer inverts it per pixel,
    ``cosim.geometry.undistort``): over a grid of the image, undistorting converges and keeps the order of
    pixels (a lens polynomial that folds over inside the picture is rejected)."""
    import math

    import numpy as np

    from cosim.geometry import distort, undistort

    if cam.distortion is None or not any(cam.distortion):
        return
    f = 0.5 * cam.width / math.tan(math.radians(cam.fov_deg) / 2)
    u, v = np.meshgrid(np.linspace(-cam.width / 2, cam.width / 2, 33) / f,
                       np.linspace(-cam.height / 2, cam.height / 2, 33) / f)
    xy_d = np.stack([u.ravel(), v.ravel()], axis=1)
    with np.errstate(all="ignore"):
        xy = undistort(xy_d, cam.distortion)  # as the renderer does
        residual = np.abs(distort(xy, cam.distortion) - xy_d).max()
    x, y = xy[:, 0].reshape(33, 33), xy[:, 1].reshape(33, 33)
    if not (residual < 1e-6 and (np.diff(x, axis=1) > 0).all() and (np.diff(y, axis=0) > 0).all()):
        raise ValueError(f"camera {cam.name!r}: distortion {list(cam.distortion)} does not map its "
                         f"{cam.width} x {cam.height} px, {cam.fov_deg:g} deg picture one to one onto rays (the "
                         "lens polynomial folds over or cannot be inverted there): use smaller coefficients or a "
                         "narrower fov_deg")


class GnssSpec(Model):
    noise_m: float = Field(0.5, ge=0, le=1000.0)


class ImuSpec(Model):
    accel_noise_mps2: float = Field(0.02, ge=0, le=100.0)
    gyro_noise_radps: float = Field(0.002, ge=0, le=10.0)
    accel_bias_mps2: float = Field(0.05, ge=0, le=100.0)
    gyro_bias_radps: float = Field(0.001, ge=0, le=10.0)


class RigSpec(Model):
    lidar: LidarSpec | None = LidarSpec()
    cameras: list[CameraSpec] = Field(default_factory=list)
    gnss: GnssSpec | None = GnssSpec()
    imu: ImuSpec | None = None

    @field_validator("cameras")
    @classmethod
    def _unique_names(cls, cams: list[CameraSpec]) -> list[CameraSpec]:
        _unique([c.name for c in cams], "camera names must be unique within a rig")
        return cams

    @field_validator("cameras")
    @classmethod
    def _lenses_invertible(cls, cams: list[CameraSpec]) -> list[CameraSpec]:
        for cam in cams:
            _check_lens(cam)
        return cams


def _surround(names_yaw: list[tuple[str, float]], xyz: tuple[float, float, float], pitch: float) -> list[CameraSpec]:
    return [CameraSpec(name=n, mount=Mount(xyz_m=xyz, rpy_deg=(0.0, pitch, yaw))) for n, yaw in names_yaw]


def default_vehicle_rig() -> RigSpec:
    cams = _surround(
        [("front", 0), ("front_left", 55), ("front_right", -55), ("rear", 180), ("rear_left", 125),
         ("rear_right", -125)],
        (0.0, 0.0, 1.6),
        0.0,
    )
    return RigSpec(lidar=LidarSpec(), cameras=cams, gnss=GnssSpec(), imu=ImuSpec())


def default_rsu_rig() -> RigSpec:
    cams = _surround([("front", 0), ("left", 90), ("right", -90), ("rear", 180)], (0.0, 0.0, 0.0), 15.0)
    return RigSpec(lidar=LidarSpec(mount=Mount(xyz_m=(0.0, 0.0, 0.3))), cameras=cams, gnss=GnssSpec(), imu=None)


def default_drone_rig() -> RigSpec:
    down = CameraSpec(name="down", mount=Mount(xyz_m=(0.0, 0.0, -0.15), rpy_deg=(0.0, 90.0, 0.0)), gimbal=True)
    lidar = LidarSpec(upper_fov_deg=-30.0, lower_fov_deg=-90.0, mount=Mount(xyz_m=(0.0, 0.0, -0.2)))
    return RigSpec(lidar=lidar, cameras=[down], gnss=GnssSpec(), imu=ImuSpec())


DEFAULT_RIGS = {"vehicle": default_vehicle_rig, "rsu": default_rsu_rig, "drone": default_drone_rig}


def complete_rigs(sensors: Any, lidar: bool = True) -> Any:
    """``sensors`` data with every partly given rig completed from its agent kind's default rig, field by field.

    A rig's defaults depend on the agent kind (a drone's LiDAR looks down, an RSU has no IMU), so a partial
    ``sensors.drone: {lidar: {range_noise_m: 0}}`` must keep the drone's cameras, IMU and LiDAR field of view
    and mount rather than fall back to a generic rig. Lists (``cameras``) are replaced as a whole. A LiDAR
    ``model`` (:func:`cosim.scenario.lidar_presets.expand_lidar`) comes between the kind's default and the
    fields given. ``lidar=False`` leaves every LiDAR as given (the loader completes the rest before ``--set``,
    and the LiDARs at validation, once every field beside a ``model`` is known).
    """
    if not isinstance(sensors, dict):
        return sensors
    out = dict(sensors)
    for kind, default in DEFAULT_RIGS.items():
        given = out.get(kind, {})
        if isinstance(given, dict):
            rig = default().model_dump(mode="json")
            if not lidar:
                rig.pop("lidar")
            elif "lidar" in given:  # a LiDAR model's preset sits between the kind's default and the given fields
                given = {**given, "lidar": expand_lidar(kind, rig["lidar"], given["lidar"])}
            out[kind] = merge_fields(rig, given)
    return out


def complete_agent_rigs(data: Any) -> Any:
    """Scenario ``data`` with every per-agent rig (``agents.vehicles.rigs.<id>``, ``agents.rsus.rigs.<id>``,
    ``agents.drones.<i>.rig``) completed field by field from its kind's rig ``sensors.<kind>``, as
    :func:`complete_rigs` completes a kind's rig from the kind's default: ``vehicle_1: {lidar: {model:
    vlp16}}`` keeps the vehicle rig's cameras, GNSS, IMU and LiDAR mount and levers and takes the preset's
    rings and ranges (:func:`cosim.scenario.lidar_presets.expand_lidar`, with the kind's LiDAR, or the kind's
    default LiDAR where the kind has none, beneath it); ``{lidar: null}`` drops the LiDAR. A kind's rig that
    is itself invalid is reported at ``sensors.<kind>`` alone: its agents' rigs are then completed from the
    kind's default rig. Anything not a mapping is left for validation to report."""
    if not isinstance(data, dict) or not isinstance(data.get("agents"), dict):
        return data
    agents = dict(data["agents"])
    bases: dict[str, dict[str, Any]] = {}

    def complete(kind: str, given: Any) -> Any:
        if not isinstance(given, dict):
            return given
        if kind not in bases:
            kinds = complete_rigs(data.get("sensors", {}))
            own = kinds.get(kind) if isinstance(kinds, dict) else None
            bases[kind] = _valid_rig(own) or DEFAULT_RIGS[kind]().model_dump(mode="json")
        base = bases[kind]
        if isinstance(given.get("lidar"), dict):
            under = base["lidar"] or DEFAULT_RIGS[kind]().model_dump(mode="json")["lidar"]
            given = {**given, "lidar": expand_lidar(kind, under, given["lidar"])}
        return merge_fields(base, given)

    for group, kind in (("vehicles", "vehicle"), ("rsus", "rsu")):
        spec = agents.get(group)
        if isinstance(spec, dict) and isinstance(spec.get("rigs"), dict):
            agents[group] = {**spec, "rigs": {k: complete(kind, v) for k, v in spec["rigs"].items()}}
    if isinstance(agents.get("drones"), list):
        agents["drones"] = [{**d, "rig": complete("drone", d["rig"])} if isinstance(d, dict) and "rig" in d else d
                            for d in agents["drones"]]
    return {**data, "agents": agents}


def _valid_rig(data: Any) -> dict[str, Any] | None:
    """``data`` as a complete rig's JSON when it is a valid rig, else None."""
    try:
        return RigSpec.model_validate(data).model_dump(mode="json")
    except ValueError:
        return None


def rig_data_of(resolved: dict[str, Any], agent_id: str) -> dict[str, Any]:
    """The plain data of an agent's rig in a resolved scenario (an episode's ``scenario.yaml``): its own rig
    where it has one (``agents.vehicles.rigs``, ``agents.rsus.rigs``, a drone's ``rig``), else its kind's
    ``sensors.<kind>``; ``{}`` where the data holds neither (a reader's fallback to the defaults)."""
    kind, _, index = agent_id.rpartition("_")
    agents = resolved.get("agents") or {}
    if kind == "drone":
        drones = agents.get("drones") or []
        own = (drones[int(index)] or {}).get("rig") if index.isdigit() and int(index) < len(drones) else None
    else:
        own = ((agents.get(f"{kind}s") or {}).get("rigs") or {}).get(agent_id)
    return own or (resolved.get("sensors") or {}).get(kind) or {}


class SensorsSpec(Model):
    """Per agent type rigs. ``enabled: false`` turns all sensor rendering off (labels only). A partly given rig
    is completed from its kind's default rig field by field (:func:`complete_rigs`)."""

    enabled: bool = True
    vehicle: RigSpec = Field(default_factory=default_vehicle_rig)
    rsu: RigSpec = Field(default_factory=default_rsu_rig)
    drone: RigSpec = Field(default_factory=default_drone_rig)
    image_scale: float = Field(1.0, gt=0.0, le=1.0)  # scales every camera's width and height (previews, tests)
    bev: bool = True  # write /<agent>/bev grids (the paper's BEV segmentation labels); false saves their bytes
    bev_cell_m: float = Field(0.25, gt=0.01, le=5)
    # [m] half extents x, y (paper section 4.2)
    bev_range_m: tuple[Annotated[float, Field(gt=0, le=1000.0)], Annotated[float, Field(gt=0, le=1000.0)]] = (
        64.0, 40.0)
    # LiDAR x, y, z as stored (docs/episode_format.md 3.4): float32 metres (what viewers such as Foxglove
    # draw at true scale), or integer 1/256 m counts ("quantized", about a quarter fewer LiDAR bytes)
    lidar_positions: Literal["float32", "quantized"] = "float32"
    # render processes (docs/architecture.md, "Sensors"): 0 = render in the runner's process, null = automatic
    # (one per core, at most 2, for rigs of at least 2 Mpx of cameras); the output does not depend on it
    render_processes: int | None = Field(0, ge=0, le=16)
    # cameras trace the sun's shadows by day and dusk (about 1.7x the rays of a frame); false: no sun shadows
    sun_shadows: bool = True
    # cameras draw procedural surface detail (asphalt grain, worn markings, window grids, lit windows at
    # night, vegetation and terrain variation); false: flat colour per surface
    surface_detail: bool = True
    # the engine that casts every ray (docs/architecture.md, "Ray backends"): embree (Embree 4 called
    # directly, the default) or open3d (the reference); images and labels agree but for rays through shared
    # triangle edges
    ray_backend: Literal["embree", "open3d"] = "embree"

    @model_validator(mode="before")
    @classmethod
    def _complete_rigs(cls, data: Any) -> Any:
        return complete_rigs(data)



class ParkedSpec(Model):
    """Parked vehicles beside the kerbs (cosim/world/parking.py): classes drawn by ``traffic.mix``."""

    density_veh_per_km: float = Field(0.0, ge=0.0, le=150.0)  # per km of road edge, as many as fit


class PedestrianSpec(Model):
    """Pedestrians of SUMO's pedestrian model on sidewalks and crossings (cosim/traffic/pedestrians.py)."""

    density_per_km: float = Field(0.0, ge=0.0, le=200.0)  # per km of road edge with a sidewalk
    jaywalk_share: float = Field(0.0, ge=0.0, le=1.0)  # share that crosses the road outside crossings
    jaywalk_every_s: float = Field(30.0, gt=0.0, le=3600.0)  # [s] mean time between a jaywalker's crossings


# -------------------------------------------------------------------------------------- events


class EventBase(Model):
    """One incident of the timeline (docs/events.md): when, and where, either a map point or ahead of a
    connected vehicle along its route (resolved at ``at_s``)."""

    at_s: float = Field(0.0, ge=0.0, le=24 * 3600)  # [s] episode time the event starts; a whole number of ticks
    position_m: MapXY | None = None  # [m] map x, y: the nearest lane
    ahead_of: str | None = None  # connected vehicle id: its lane, ``ahead_m`` in front of it
    ahead_m: float = Field(40.0, ge=5.0, le=1000.0)

    @field_validator("ahead_of")
    @classmethod
    def _vehicle_id(cls, agent: str | None) -> str | None:
        if agent is not None:
            prefix, _, index = agent.partition("_")
            if prefix != "vehicle" or not index.isdigit():
                raise ValueError(f"ahead_of must be a connected vehicle id like 'vehicle_0', got {agent!r}")
        return agent

    @model_validator(mode="after")
    def _one_place(self) -> EventBase:
        if (self.position_m is None) == (self.ahead_of is None):
            raise RuleError("position_m", "an event needs exactly one of position_m (map x, y) and ahead_of "
                                          "(a connected vehicle id)")
        return self


class BreakdownEvent(EventBase):
    """A car stops in its lane and stays; hazard lights on (None: on at dusk and night)."""

    kind: Literal["breakdown"] = "breakdown"
    hazard_lights: bool | None = None


class AccidentEvent(EventBase):
    """Two cars stopped in the lane, the second turned by ``angle_deg`` with its front corner touching the
    first one's rear."""

    kind: Literal["accident"] = "accident"
    angle_deg: float = Field(25.0, ge=5.0, le=60.0)  # [deg] yaw of the rear car relative to the lane


class LaneClosureEvent(EventBase):
    """One lane closed over ``length_m`` from the placement on: a barrier, cones along the open side and a
    sign (``static_obstacle``); traffic merges into the other lanes or waits."""

    kind: Literal["lane_closure", "construction_zone"] = "lane_closure"
    length_m: float = Field(40.0, ge=10.0, le=300.0)
    cone_spacing_m: float = Field(5.0, ge=1.0, le=50.0)


class RoadBlockEvent(EventBase):
    """The edge at the placement closed to all traffic (barriers across it); routes through it are rerouted."""

    kind: Literal["road_block"] = "road_block"


class JaywalkEvent(EventBase):
    """A pedestrian steps off the kerb at the placement and crosses the road outside any crossing."""

    kind: Literal["jaywalk"] = "jaywalk"
    speed_mps: float = Field(1.4, ge=0.3, le=4.0)  # [m/s] walking (or running) speed across
    from_side: Literal["right", "left"] = "right"  # the kerb it starts from, seen along the lane


class CutInEvent(EventBase):
    """A car appears in the lane beside ``ahead_of`` and changes into its lane ``gap_m`` ahead of it."""

    kind: Literal["cut_in"] = "cut_in"
    ahead_m: float = Field(0.0, ge=0.0, le=50.0)  # [m] how far ahead of the connected vehicle it appears
    gap_m: float = Field(6.0, ge=1.0, le=30.0)  # [m] from the connected vehicle's front to its rear
    side: Literal["left", "right", "any"] = "any"  # the neighbouring lane it comes from

    @model_validator(mode="after")
    def _needs_vehicle(self) -> CutInEvent:
        if self.ahead_of is None:
            raise RuleError("ahead_of", "a cut_in needs ahead_of: the connected vehicle it cuts in front of")
        return self


EventSpec = Annotated[
    BreakdownEvent | AccidentEvent | LaneClosureEvent | RoadBlockEvent | JaywalkEvent | CutInEvent,
    Field(discriminator="kind"),
]
#: The event kinds of :data:`EventSpec` (the ``/events`` schema and the loader's messages follow from it).
EVENT_KINDS = union_tags(EventSpec)

# -------------------------------------------------------------------------------------- output


class OutputSpec(Model):
    dir: str = "out"
    name: str | None = None  # file stem inside the output folder; None = "<scenario name>_s<seed>"
    compression: Literal["zstd", "lz4", "none"] = "zstd"
    # camera RGB images (docs/episode_format.md 3.5): jpeg (libjpeg-turbo, 4:2:0, at jpeg_quality) or png (lossless)
    image_format: Literal["jpeg", "png"] = "jpeg"
    jpeg_quality: int = Field(80, ge=10, le=100)
    # depth images: compressed (CompressedImage "cosim-depth", lossless, 2.7x fewer bytes) or raw (RawImage
    # 32FC1, which Foxglove displays)
    depth_format: Literal["compressed", "raw"] = "compressed"

    @field_validator("name")
    @classmethod
    def _stays_in_the_folder(cls, name: str | None) -> str | None:
        if name is not None and not re.fullmatch(FILE_STEM_PATTERN, name):
            raise ValueError(f"output.name must be a plain file name inside the output folder (1-200 letters, "
                             f"digits and _ . + = -, not starting with . or -; no / or ..), got {name!r}")
        return name


class RuntimeSpec(Model):
    startup_timeout_s: float = Field(60.0, gt=0, le=24 * 3600)  # workers ready (processes started, world loaded)
    tick_timeout_s: float = Field(10.0, gt=0, le=24 * 3600)  # one lockstep query


# ------------------------------------------------------------------------------------- clients


class ClientSpec(Model):
    """A closed-loop client (``cosim.client``): the conductor waits for its action after every tick."""

    name: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_-]*$", max_length=64)
    # [s] for its action per tick; None = runtime.tick_timeout_s
    timeout_s: float | None = Field(None, gt=0, le=24 * 3600)


# ---------------------------------------------------------------------------------------- comm

#: Modulation and coding schemes of the link model (their Qm and R: cosim/comm/phy.py).
McsName = Literal["qpsk_1_3", "qpsk_1_2", "qpsk_3_4", "16qam_1_2", "16qam_3_4", "64qam_2_3", "64qam_3_4"]


class CommSpec(Model):
    """V2X links per tick (``/comm/links``, docs/comm.md). Defaults: 5.9 GHz C-V2X sidelink (PC5),
    20 MHz, 23 dBm, 3 dBi antennas, 9 dB noise figure (the TR 37.885 evaluation assumptions).
    ``enabled: false`` writes no ``/comm/links`` topic (the episode is as without a link model)."""

    enabled: bool = True
    carrier_ghz: float = Field(5.9, gt=0.4, le=100.0)  # [GHz] carrier frequency
    bandwidth_mhz: float = Field(20.0, gt=0.0, le=400.0)  # [MHz] channel bandwidth (noise and rate)
    tx_power_dbm: float = Field(23.0, ge=-30.0, le=50.0)  # [dBm] transmit power of every agent
    antenna_gain_dbi: float = Field(3.0, ge=-20.0, le=30.0)  # [dBi] gain of each end's antenna
    noise_figure_db: float = Field(9.0, ge=0.0, le=30.0)  # [dB] receiver noise figure
    environment: Literal["auto", "urban", "highway"] = "auto"  # TR 37.885 setting; auto: from map.kind
    air_ground_model: Literal["auto", "umi_av", "uma_av", "rma_av"] = "auto"  # TR 36.777 Annex B; auto: by setting
    #: link type ("vehicle-drone") -> a path-loss model registered by name (cosim/comm/models.py) for all its
    #: links instead of the 3GPP default; checked when the link model starts
    link_models: dict[str, str] = Field(default_factory=dict)
    vehicle_antenna_z_m: float = Field(1.6, ge=0.0, le=10.0)  # [m] antenna above a vehicle's base_link (ground)
    rsu_antenna_z_m: float = Field(0.5, ge=0.0, le=10.0)  # [m] antenna above an RSU's base_link (mast top)
    drone_antenna_z_m: float = Field(0.0, ge=-2.0, le=2.0)  # [m] antenna above a drone's base_link (centre)
    shadow_fading: bool = True  # False: no shadow fading (path loss only; for tests and comparisons)
    mcs: McsName = "qpsk_1_2"  # modulation and coding of every message
    overhead_share: float = Field(0.42, ge=0.0, lt=1.0)  # [1] resources not carrying data (DMRS, guard, band edges)
    shannon_efficiency: float = Field(0.6, gt=0.0, le=1.0)  # [1] alpha of the attenuated Shannon bound
    per_waterfall_db: float = Field(2.0, gt=0.0, le=20.0)  # [dB] SNR span in which PER falls from 90 % to 10 %
    message_bytes: int = Field(1600, ge=1, le=100_000_000)  # [B] size of the message each agent sends per tick
    processing_delay_ms: float = Field(2.0, ge=0.0, le=10_000.0)  # [ms] encoding + decoding at the two ends
    access_delay_ms: float = Field(10.0, ge=0.0, le=10_000.0)  # [ms] waiting for the sidelink resource


# ------------------------------------------------------------------------------------ scenario


class Scenario(Model):
    name: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
    description: str = ""
    seed: int = Field(0, ge=0, lt=2**31)
    duration_s: float = Field(20.0, gt=0, le=24 * 3600)
    tick_hz: float = Field(5.0, gt=0, le=100)
    map: MapSpec = MapSpec()
    geo_origin: GeoOrigin = GeoOrigin()
    environment: EnvironmentSpec = EnvironmentSpec()
    traffic: TrafficSpec = TrafficSpec()
    agents: AgentsSpec = AgentsSpec()
    sensors: SensorsSpec = SensorsSpec()
    output: OutputSpec = OutputSpec()
    runtime: RuntimeSpec = RuntimeSpec()
    events: list[EventSpec] = Field(default_factory=list)
    parked: ParkedSpec = ParkedSpec()
    pedestrians: PedestrianSpec = PedestrianSpec()
    comm: CommSpec = CommSpec()
    clients: list[ClientSpec] = Field(default_factory=list)

    @model_validator(mode="before")
    @classmethod
    def _complete_agent_rigs(cls, data: Any) -> Any:
        return complete_agent_rigs(data)

    @field_validator("clients")
    @classmethod
    def _unique_clients(cls, clients: list[ClientSpec]) -> list[ClientSpec]:
        _unique([c.name for c in clients], "client names must be unique")
        return clients

    @model_validator(mode="after")
    def _rates(self) -> Scenario:
        tick_ns = TICK_NS_PER_S / self.tick_hz
        if abs(tick_ns - round(tick_ns)) > 1e-6:
            raise RuleError("tick_hz", f"tick_hz = {self.tick_hz:g} gives a tick that is not a whole number of ns")
        _rate_divides_tick("traffic.step_hz", self.traffic.step_hz, self.tick_hz)
        _rate_divides_tick("agents.drone_physics_hz", self.agents.drone_physics_hz, self.tick_hz)
        ticks = self.duration_s * self.tick_hz
        if abs(ticks - round(ticks)) > 1e-6 or round(ticks) < 1:
            raise RuleError(
                "duration_s",
                f"duration_s = {self.duration_s:g} is not a whole number of ticks at {self.tick_hz:g} Hz"
            )
        self._check_events()
        return self

    def _check_events(self) -> None:
        for i, e in enumerate(self.events):
            ticks = e.at_s * self.tick_hz
            if abs(ticks - round(ticks)) > 1e-6:  # after the end is allowed: it stays pending (--duration)
                raise RuleError(
                    f"events.{i}.at_s",
                    f"event at_s = {e.at_s:g} is not a whole number of ticks at {self.tick_hz:g} Hz"
                )
            if e.ahead_of is not None and int(e.ahead_of.split("_")[1]) >= self.agents.vehicles.count:
                raise RuleError(
                    f"events.{i}.ahead_of",
                    f"event ahead_of {e.ahead_of!r} does not exist: the scenario has "
                    f"{self.agents.vehicles.count} connected vehicles"
                )

    @property
    def tick_ns(self) -> int:
        """Tick period [ns]."""
        return round(TICK_NS_PER_S / self.tick_hz)

    @property
    def n_ticks(self) -> int:
        """Number of ticks written: t = 0, tick, ..., duration - tick."""
        return round(self.duration_s * self.tick_hz)

    def agent_ids(self) -> list[str]:
        a = self.agents
        return (
            [f"vehicle_{i}" for i in range(a.vehicles.count)]
            + [f"rsu_{i}" for i in range(a.rsus.count)]
            + [f"drone_{i}" for i in range(len(a.drones))]
        )

    def rig_for(self, agent_id: str) -> RigSpec:
        """The sensor rig of an agent: its own (``agents.vehicles.rigs``, ``agents.rsus.rigs``, a drone's
        ``rig``), else its kind's (by id prefix); with ``sensors.image_scale`` applied to its cameras."""
        kind, _, index = agent_id.rpartition("_")
        drones = self.agents.drones
        own = {"vehicle": lambda: self.agents.vehicles.rigs.get(agent_id),
               "rsu": lambda: self.agents.rsus.rigs.get(agent_id),
               # an id beyond the scenario's drones (a sensor rendered for a test or a tool) has its kind's rig
               "drone": lambda: drones[int(index)].rig if index.isdigit() and int(index) < len(drones) else None,
               }[kind]()
        kinds = {"vehicle": self.sensors.vehicle, "rsu": self.sensors.rsu, "drone": self.sensors.drone}
        rig = own if own is not None else kinds[kind]
        scale = self.sensors.image_scale
        if scale == 1.0:
            return rig
        cams = [c.model_copy(update={"width": max(16, round(c.width * scale / 2) * 2),
                                     "height": max(16, round(c.height * scale / 2) * 2)}) for c in rig.cameras]
        return rig.model_copy(update={"cameras": cams})
