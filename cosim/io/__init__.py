"""Reading cosim episodes (docs/episode_format.md): ``open_episode(path)`` and the decoded types."""

from cosim.comm.message import LinkSet
from cosim.io.decode import (
    Boxes,
    Calibration,
    GnssFix,
    Grid,
    Image,
    Objects,
    PointCloud,
    Transform,
    TransformTree,
    decode,
)
from cosim.io.deskew import deskew, deskew_tick
from cosim.io.reader import Episode, RawMessage, Tick, TopicInfo, check_format_version, open_episode

__all__ = [
    "Boxes",
    "Calibration",
    "Episode",
    "GnssFix",
    "Grid",
    "Image",
    "LinkSet",
    "Objects",
    "PointCloud",
    "RawMessage",
    "Tick",
    "TopicInfo",
    "Transform",
    "TransformTree",
    "check_format_version",
    "decode",
    "deskew",
    "deskew_tick",
    "open_episode",
]
