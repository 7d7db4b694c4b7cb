"""Vehicle types of the six road-user classes: SUMO vClass, dimensions and driving parameters.

Each vehicle model of the asset catalogue (:mod:`cosim.sensors.assets.vehicles`, docs/assets.md) is
one SUMO vType, whose length, width and height [m] are the model's tight box, so traffic and sensors
agree on every vehicle's size.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

#: SUMO vehicle class per object class.
SUMO_VCLASS: dict[str, str] = {
    "car": "passenger",
    "van": "delivery",
    "truck": "truck",
    "bus": "bus",
    "motorcycle": "motorcycle",
    "bicycle": "bicycle",
}


@dataclass(frozen=True, slots=True)
class VehicleVariant:
    """One SUMO vType: ``type_id`` is ``<class>_<k>``."""

    cls: str
    k: int
    length_m: float
    width_m: float
    height_m: float
    max_speed_mps: float
    accel_mps2: float
    decel_mps2: float
    min_gap_m: float = 2.5
    model: str = ""  # the catalogue model (cosim.sensors.assets.vehicles)

    @property
    def type_id(self) -> str:
        return f"{self.cls}_{self.k}"

    @property
    def vclass(self) -> str:
        return SUMO_VCLASS[self.cls]


#: driving parameters per class: max speed [m/s], acceleration, deceleration [m/s^2], min gap [m]
_DRIVING: dict[str, tuple[float, float, float, float]] = {
    "car": (45.0, 2.6, 4.5, 2.5), "van": (40.0, 2.0, 4.0, 2.5), "truck": (25.0, 1.1, 4.0, 3.0),
    "bus": (25.0, 1.2, 4.0, 3.0), "motorcycle": (45.0, 4.0, 7.0, 2.0), "bicycle": (6.5, 1.2, 3.0, 1.5),
}
#: styles that drive unlike their class
_STYLE_SPEED: dict[str, float] = {"microcar": 25.0, "suv": 50.0, "saloon": 50.0, "coupe": 55.0, "scooter": 25.0,
                                  "sport": 55.0, "touring": 50.0, "road": 9.0, "cargo": 6.0}


@cache
def variants() -> dict[str, tuple[VehicleVariant, ...]]:
    """Variants per class (index k is part of the SUMO type id): one per model of the catalogue
    (cosim.sensors.assets.vehicles), its box the model's tight box (read from the catalogue's table, no mesh is
    built). Made at the first call, not at import."""
    from cosim.sensors.assets import vehicles

    out: dict[str, list[VehicleVariant]] = {cls: [] for cls in SUMO_VCLASS}
    for m in vehicles.MODELS:
        length, width, height = vehicles.dims(m.name)
        vmax, acc, dec, gap = _DRIVING[m.cls]
        k = len(out[m.cls])
        out[m.cls].append(VehicleVariant(m.cls, k, length, width, height, _STYLE_SPEED.get(m.style, vmax), acc, dec,
                                         gap, m.name))
    return {cls: tuple(vs) for cls, vs in out.items()}


@cache
def by_type_id() -> dict[str, VehicleVariant]:
    """Every variant by SUMO type id."""
    return {v.type_id: v for vs in variants().values() for v in vs}


def class_of_type(type_id: str) -> str:
    """Object class of a SUMO type id written by :mod:`cosim.world.routes`."""
    try:
        return by_type_id()[type_id].cls
    except KeyError:
        return type_id.rsplit("_", 1)[0]
