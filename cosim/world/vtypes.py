"""Vehicle types of the six road-user classes: SUMO vClass, dimensions and driving parameters.

Each class has a few variants so that boxes vary within a class (a hatchback is not an SUV).
Dimensions are typical European values: length, width, height [m] of the bounding box.
"""

from __future__ import annotations

from dataclasses import dataclass

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

    @property
    def type_id(self) -> str:
        return f"{self.cls}_{self.k}"

    @property
    def vclass(self) -> str:
        return SUMO_VCLASS[self.cls]


def _v(
    cls: str,
    k: int,
    length: float,
    w: float,
    h: float,
    vmax: float,
    acc: float,
    dec: float,
    gap: float = 2.5,
) -> VehicleVariant:
    return VehicleVariant(cls, k, length, w, h, vmax, acc, dec, gap)


#: Variants per class (index k is part of the SUMO type id).
VARIANTS: dict[str, tuple[VehicleVariant, ...]] = {
    "car": (
        _v("car", 0, 4.0, 1.75, 1.50, 45.0, 2.6, 4.5),  # hatchback
        _v("car", 1, 4.6, 1.82, 1.45, 50.0, 2.6, 4.5),  # saloon
        _v("car", 2, 4.8, 1.95, 1.75, 50.0, 2.4, 4.5),  # SUV
        _v("car", 3, 4.3, 1.80, 1.55, 45.0, 2.6, 4.5),  # compact estate
    ),
    "van": (
        _v("van", 0, 5.0, 1.95, 1.95, 40.0, 2.0, 4.0),
        _v("van", 1, 5.9, 2.05, 2.50, 38.0, 1.8, 4.0),
    ),
    "truck": (
        _v("truck", 0, 7.5, 2.40, 3.20, 27.0, 1.3, 4.0, 3.0),
        _v("truck", 1, 9.5, 2.50, 3.50, 25.0, 1.1, 4.0, 3.0),
        _v("truck", 2, 11.5, 2.55, 3.80, 25.0, 1.0, 4.0, 3.0),
    ),
    "bus": (
        _v("bus", 0, 12.0, 2.55, 3.20, 25.0, 1.2, 4.0, 3.0),
        _v("bus", 1, 10.5, 2.50, 3.10, 25.0, 1.2, 4.0, 3.0),
    ),
    "motorcycle": (
        _v("motorcycle", 0, 2.1, 0.80, 1.50, 45.0, 4.0, 7.0, 2.0),
        _v("motorcycle", 1, 2.25, 0.90, 1.40, 50.0, 4.5, 7.0, 2.0),
    ),
    "bicycle": (
        _v("bicycle", 0, 1.75, 0.65, 1.70, 6.5, 1.2, 3.0, 1.5),
        _v("bicycle", 1, 1.85, 0.60, 1.75, 7.5, 1.2, 3.0, 1.5),
    ),
}

#: Every variant by SUMO type id.
BY_TYPE_ID: dict[str, VehicleVariant] = {v.type_id: v for vs in VARIANTS.values() for v in vs}


def class_of_type(type_id: str) -> str:
    """Object class of a SUMO type id written by :mod:`cosim.world.routes`."""
    try:
        return BY_TYPE_ID[type_id].cls
    except KeyError:
        return type_id.rsplit("_", 1)[0]
