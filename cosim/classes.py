"""The one class table: object classes (what gets a 3D box) and semantic classes (what a pixel or
LiDAR point can be). Ids are stable and written into every episode's metadata.
"""

from __future__ import annotations

from typing import Final

#: The paper's six road-user classes, aerial agents, pedestrians and static obstacles (cones, barriers,
#: signs of incidents). Order defines the ids; new classes are appended so existing ids stay stable.
OBJECT_CLASSES: Final[tuple[str, ...]] = (
    "car", "van", "truck", "bus", "motorcycle", "bicycle", "drone", "pedestrian", "static_obstacle",
)

#: Semantic classes for pixels and LiDAR points. 0 is "unlabelled" (sky, no return).
SEMANTIC_CLASSES: Final[tuple[str, ...]] = (
    "unlabelled",
    "road",
    "lane_marking",
    "sidewalk",
    "building",
    "vegetation",
    "terrain",
    "pole",
    "street_light",
    "rsu",
    "car",
    "van",
    "truck",
    "bus",
    "motorcycle",
    "bicycle",
    "drone",
    "pedestrian",
    "static_obstacle",
    "traffic_light",
    "traffic_sign",
)

SEMANTIC_ID: Final[dict[str, int]] = {name: i for i, name in enumerate(SEMANTIC_CLASSES)}

#: Display colours (RGB 0-255) per semantic class, used by BEV plots, semantic images, viewers.
SEMANTIC_COLOURS: Final[dict[str, tuple[int, int, int]]] = {
    "unlabelled": (0, 0, 0),
    "road": (128, 64, 128),
    "lane_marking": (255, 255, 255),
    "sidewalk": (244, 35, 232),
    "building": (70, 70, 70),
    "vegetation": (107, 142, 35),
    "terrain": (152, 251, 152),
    "pole": (153, 153, 153),
    "street_light": (250, 170, 30),
    "rsu": (220, 220, 0),
    "car": (0, 0, 142),
    "van": (0, 60, 100),
    "truck": (0, 0, 70),
    "bus": (0, 80, 100),
    "motorcycle": (0, 0, 230),
    "bicycle": (119, 11, 32),
    "drone": (255, 0, 0),
    "pedestrian": (220, 20, 60),
    "static_obstacle": (255, 120, 0),
    "traffic_light": (250, 220, 120),
    "traffic_sign": (255, 255, 140),
}


def semantic_id(name: str) -> int:
    """Semantic id of a class name; raises ``KeyError`` naming the known classes."""
    try:
        return SEMANTIC_ID[name]
    except KeyError:
        raise KeyError(f"unknown semantic class {name!r}; known: {', '.join(SEMANTIC_CLASSES)}") from None


def class_table() -> dict[str, object]:
    """The table as written into episode metadata."""
    return {
        "object_classes": list(OBJECT_CLASSES),
        "semantic_classes": [
            {"id": i, "name": n, "colour": list(SEMANTIC_COLOURS[n])} for i, n in enumerate(SEMANTIC_CLASSES)
        ],
    }
