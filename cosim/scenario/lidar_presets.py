"""LiDAR presets from datasheets: what ``sensors.<kind>.lidar.model`` expands to (docs/lidar_models.md).

A preset is plain data (numbers from the maker's sheet and the dataset that made the sensor known); the
scenario loader expands it into :class:`cosim.scenario.model.LidarSpec` fields before validation, so the
resolved scenario of an episode spells out every number the renderer used. Fields set beside ``model``
override the preset's (:func:`expand_lidar`). The renderer's side of a preset (ring tables turned into
firings, the intensity transfer) is :mod:`cosim.sensors.lidar_models`.

The rig ticks at 5 Hz while the sensors spin at 10 Hz or faster: every tick records the one sweep that
ends at the tick (1 / ``rotation_hz`` long), as a dataset keyframe does; the sweeps in between are not
written. The azimuth step is the sheet's point rate at the sheet's rotation rate.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from .merge import merge_fields


def _uniform(lo_deg: float, hi_deg: float, n: int) -> tuple[float, ...]:
    """``n`` elevations [deg] evenly spaced from ``lo_deg`` to ``hi_deg``, rounded to 1/1000 deg as sheets are."""
    step = (hi_deg - lo_deg) / (n - 1)
    return tuple(round(lo_deg + i * step, 3) for i in range(n))


@dataclass(frozen=True)
class LidarPreset:
    """One sensor as its datasheet gives it.

    ``elevations_deg``: ring elevations [deg], ascending (ring 0 the lowest), or None for a non-spinning
    pattern; ``rotation_hz`` sweeps (or frames) per second; ``point_rate_hz`` the sheet's single-return
    points per second (every firing that returns); ``range_m`` the largest range; ``range_noise_m`` the sheet's
    range accuracy taken as a 1-sigma Gaussian; ``detection_range_10pct_m`` where a 10 % target is still seen;
    ``return_modes`` what the sensor can report (cosim renders the first one; ``dual_returns: true`` adds
    the last return where a beam splits); ``intensity_transfer`` how it reports intensity
    (:mod:`cosim.sensors.lidar_models`); ``mount_height_m`` [m above the ground] in the dataset named by
    ``mount_source``, the suggested vehicle mount (None: no dataset to take it from); ``extra`` further
    :class:`LidarSpec` fields (the rosette's).

    A preset drops returns only by the physical terms of the ray drop (return energy against the sheet's
    10 % range, glass, wet surfaces, the small random share): CARLA's intensity rule
    (``dropoff_intensity_limit``) is off, as real scans show no loss of near dark road (docs/realism.md).
    """

    sensor: str
    datasheet: str
    elevations_deg: tuple[float, ...] | None
    rotation_hz: float
    point_rate_hz: float
    range_m: float
    range_noise_m: float
    detection_range_10pct_m: float
    return_modes: tuple[str, ...]
    intensity_transfer: str
    mount_height_m: float | None = None
    mount_source: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def channels(self) -> int:
        return len(self.elevations_deg) if self.elevations_deg else 1

    @property
    def horizontal_resolution_deg(self) -> float:
        """Azimuth step [deg]: 360 deg over the firings of one sweep (point rate / channels / rotation rate)."""
        return round(360.0 * self.rotation_hz * self.channels / self.point_rate_hz, 5)

    def fields(self) -> dict[str, Any]:
        """The :class:`LidarSpec` fields this preset sets (JSON types, as a scenario file would give them)."""
        out: dict[str, Any] = {
            "rotation_hz": self.rotation_hz,
            "range_m": self.range_m,
            "range_noise_m": self.range_noise_m,
            "detection_range_10pct_m": self.detection_range_10pct_m,
            "dual_returns": False,
            "intensity_transfer": self.intensity_transfer,
            "dropoff_intensity_limit": 0.0,
        }
        if self.elevations_deg is not None:
            out.update(pattern="spinning", channels=self.channels, elevations_deg=list(self.elevations_deg),
                       lower_fov_deg=self.elevations_deg[0], upper_fov_deg=self.elevations_deg[-1],
                       horizontal_resolution_deg=self.horizontal_resolution_deg)
        else:
            out.update(pattern="rosette", point_rate_hz=self.point_rate_hz)
        return {**out, **self.extra}


#: HDL-64E (S2, as in KITTI): two blocks of 32 lasers, the upper from +2 to -8.33 deg (1/3 deg apart), the
#: lower from -8.83 to -24.33 deg (1/2 deg apart)
_HDL64E = tuple(sorted(_uniform(-8.333, 2.0, 32) + _uniform(-24.333, -8.833, 32)))

#: VLP-32C: the sheet's vertical angles of its 32 lasers (dense near the horizon, 0.333 deg at the finest)
_VLP32C = (-25.0, -15.639, -11.31, -8.843, -7.254, -6.148, -5.333, -4.667, -4.0, -3.667, -3.333, -3.0, -2.667,
           -2.333, -2.0, -1.667, -1.333, -1.0, -0.667, -0.333, 0.0, 0.333, 0.667, 1.0, 1.333, 1.667, 2.333,
           3.333, 4.667, 7.0, 10.333, 15.0)

#: Pandar64: 1/6 deg near the horizon (-6 to +2 deg), 1 deg and wider beyond
_PANDAR64 = (-24.897, -18.889, -13.93, -12.974, -12.006, -11.032, -9.885, -9.06, -8.059, -7.063, -6.061, -5.898,
             -5.726, -5.565, -5.391, -5.229, -5.057, -4.892, -4.72, -4.558, -4.385, -4.221, -4.05, -3.884,
             -3.712, -3.548, -3.375, -3.21, -3.04, -2.873, -2.7, -2.536, -2.365, -2.198, -2.028, -1.86, -1.688,
             -1.522, -1.351, -1.184, -1.013, -0.846, -0.675, -0.508, -0.337, -0.169, 0.0, 0.169, 0.337, 0.508,
             0.675, 0.846, 1.013, 1.184, 1.351, 1.522, 1.688, 1.86, 2.028, 3.04, 5.057, 8.059, 11.032, 14.882)

#: name -> preset; ``generic`` is the paper's rig (cosim's default, every field the kind's default).
LIDAR_PRESETS: dict[str, LidarPreset | None] = {
    "generic": None,
    "hdl64e": LidarPreset(
        sensor="Velodyne HDL-64E S2",
        datasheet="Velodyne HDL-64E S2 datasheet and user's manual (63-HDL64ES2)",
        elevations_deg=_HDL64E, rotation_hz=10.0, point_rate_hz=1_333_000.0, range_m=120.0, range_noise_m=0.02,
        detection_range_10pct_m=50.0, return_modes=("strongest",), intensity_transfer="kitti",
        mount_height_m=1.73, mount_source="KITTI (Geiger et al. 2013, IJRR 32(11))",
        extra={"self_occlusion": True}),
    "vlp32c": LidarPreset(
        sensor="Velodyne VLP-32C (Ultra Puck)",
        datasheet="Velodyne VLP-32C user manual 63-9325 (laser table) and datasheet",
        elevations_deg=_VLP32C, rotation_hz=10.0, point_rate_hz=578_704.0, range_m=200.0, range_noise_m=0.03,
        detection_range_10pct_m=100.0, return_modes=("strongest", "last", "dual"),
        intensity_transfer="calibrated_100",
        mount_height_m=1.84, mount_source="nuScenes' 32-channel roof LiDAR (HDL-32E, Caesar et al. 2020)"),
    "vlp16": LidarPreset(
        sensor="Velodyne VLP-16 (Puck)",
        datasheet="Velodyne VLP-16 datasheet 63-9229 and user manual",
        elevations_deg=_uniform(-15.0, 15.0, 16), rotation_hz=10.0, point_rate_hz=289_352.0, range_m=100.0,
        range_noise_m=0.03, detection_range_10pct_m=60.0, return_modes=("strongest", "last", "dual"),
        intensity_transfer="calibrated_100"),
    "os1_64": LidarPreset(
        sensor="Ouster OS1-64",
        datasheet="Ouster OS1 datasheet (OS1-64: 33.2 deg vertical, 1,310,720 points/s, 2048 x 10 Hz)",
        elevations_deg=_uniform(-16.6, 16.6, 64), rotation_hz=10.0, point_rate_hz=1_310_720.0, range_m=120.0,
        range_noise_m=0.03, detection_range_10pct_m=40.0, return_modes=("strongest",),
        intensity_transfer="calibrated_100"),
    "os1_128": LidarPreset(
        sensor="Ouster OS1-128",
        datasheet="Ouster OS1 datasheet (OS1-128: 45 deg vertical, 2,621,440 points/s, 2048 x 10 Hz)",
        elevations_deg=_uniform(-22.5, 22.5, 128), rotation_hz=10.0, point_rate_hz=2_621_440.0, range_m=120.0,
        range_noise_m=0.03, detection_range_10pct_m=40.0, return_modes=("strongest",),
        intensity_transfer="calibrated_100"),
    "pandar64": LidarPreset(
        sensor="Hesai Pandar64",
        datasheet="Hesai Pandar64 user's manual (channel distribution appendix) and datasheet",
        elevations_deg=_PANDAR64, rotation_hz=10.0, point_rate_hz=1_152_000.0, range_m=200.0, range_noise_m=0.02,
        detection_range_10pct_m=200.0, return_modes=("last", "strongest", "dual"),
        intensity_transfer="calibrated_100"),
    "avia": LidarPreset(
        sensor="Livox Avia",
        datasheet="Livox Avia user manual and specs (non-repetitive scan, 70.4 x 77.2 deg, 240,000 points/s)",
        elevations_deg=None, rotation_hz=10.0, point_rate_hz=240_000.0, range_m=190.0, range_noise_m=0.02,
        detection_range_10pct_m=190.0, return_modes=("first", "strongest", "dual", "triple"),
        intensity_transfer="livox_150", extra={"rosette_fov_deg": 70.4}),
}

#: the geometry fields a ring table decides; one of them set beside ``model`` (without ``elevations_deg``)
#: gives evenly spaced rings over the span given instead of the table
RING_FIELDS = ("channels", "lower_fov_deg", "upper_fov_deg")


def expand_lidar(kind: str, default: dict[str, Any], given: Any) -> Any:
    """The LiDAR data of a ``kind`` rig: ``default`` (the kind's default LiDAR, as JSON) overlaid with the
    preset named by ``given["model"]`` and then with every field of ``given``. A vehicle takes the
    preset's suggested mount height unless ``given`` sets a mount. ``given`` with ``elevations_deg`` and
    no ring count or span gets both from the table. Anything else (``null``, an unknown model) is
    left for validation to report."""
    if not isinstance(given, dict):
        return given
    base = dict(default)
    name = given.get("model")
    preset = LIDAR_PRESETS.get(name) if isinstance(name, str) else None
    if preset is not None:
        base.update(preset.fields())
        if kind == "vehicle" and preset.mount_height_m is not None:
            xyz = list(base["mount"]["xyz_m"])
            base["mount"] = {**base["mount"], "xyz_m": [xyz[0], xyz[1], preset.mount_height_m]}
    out = merge_fields(base, given)
    table = given.get("elevations_deg")
    if "elevations_deg" not in given and any(k in given for k in RING_FIELDS):
        out.pop("elevations_deg", None)
    elif isinstance(table, list) and table and all(isinstance(e, int | float) for e in table):
        derived = {"channels": len(table), "lower_fov_deg": min(table), "upper_fov_deg": max(table)}
        out.update({k: v for k, v in derived.items() if k not in given})
    return out
