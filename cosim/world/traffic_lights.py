"""Traffic lights at SUMO's signalised junctions: where their heads stand and what colour they show.

Every vehicle lane that enters a signalised junction (a ``<connection>`` with ``tl`` and ``linkIndex``
in the network) gets one signal head above the lane's end, the stop line, facing the traffic that
approaches on it. The heads of one approach (one incoming edge) hang from a mast arm on a pole at the
right kerb. A head shows the state of the links that leave its lane (SUMO's ``tlLogic`` state string,
one character per link index): green when any of them may go (``G``, ``g``), else yellow when any is
in its amber or red-amber phase (``y``, ``Y``, ``u``), else red (``r``, ``s``); ``o`` and ``O``
(signal off) leave it dark.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from functools import lru_cache

from cosim.world.layout import ROAD_Z

#: [m] height of a head's lowest point above the road (overhead signals leave 4.5-5.5 m of clearance)
HEAD_BOTTOM_M = 5.0
#: [m] housing of a head: depth (along the lane), width, height; three lamps from top: red, yellow, green
HEAD_SIZE_M = (0.35, 0.40, 1.05)
#: [m] the pole stands this far right of the approach's rightmost lane edge
POLE_OFFSET_M = 0.8
#: the colour a head shows, by SUMO signal character
COLOUR_OF_SIGNAL = {"G": "green", "g": "green", "y": "yellow", "Y": "yellow", "u": "yellow", "r": "red",
                    "s": "red", "o": "off", "O": "off"}
LAMP_COLOURS = ("red", "yellow", "green")  # top to bottom


@dataclass(frozen=True)
class SignalHead:
    """One head: ``head_id`` ``<tls>/<lane>``, the junction's traffic-light id ``tls``, the link indices it
    shows, its housing's centre (map, m), the yaw [rad] of the direction it faces (against its lane's
    traffic), and the pole it hangs from (x, y at the kerb)."""

    head_id: str
    tls: str
    links: tuple[int, ...]
    center_m: tuple[float, float, float]
    yaw_rad: float
    pole_xy: tuple[float, float]


def head_colour(state: str, links: tuple[int, ...]) -> str:
    """``green``, ``yellow``, ``red`` or ``off``: what a head over ``links`` shows for the junction's SUMO
    state string ``state`` (module docstring)."""
    colours = {COLOUR_OF_SIGNAL.get(state[i], "off") for i in links if i < len(state)}
    for c in ("green", "yellow", "red"):
        if c in colours:
            return c
    return "off"


def first_phases(net_xml: bytes) -> dict[str, str]:
    """Each traffic light's state in the first phase of its program (pictures and benchmarks without SUMO)."""
    if b"<tlLogic" not in net_xml:
        return {}
    out: dict[str, str] = {}
    for tl in ET.fromstring(net_xml).iter("tlLogic"):
        phase = tl.find("phase")
        if phase is not None:
            out.setdefault(tl.get("id", ""), phase.get("state", ""))
    return out


@lru_cache(maxsize=4)  # keyed by the network's bytes (their hash is computed once per bytes object)
def signal_heads(net_xml: bytes) -> tuple[SignalHead, ...]:
    """Every signal head of the network, in a stable order (traffic light id, lane id)."""
    if b"<tlLogic" not in net_xml:
        return ()
    root = ET.fromstring(net_xml)
    lanes: dict[str, tuple[list[tuple[float, float]], float]] = {}
    edge_lanes: dict[str, list[str]] = {}
    for edge in root.iter("edge"):
        if edge.get("function") == "internal":
            continue
        for lane in edge.iter("lane"):
            pts = [tuple(float(c) for c in p.split(",")[:2]) for p in lane.get("shape", "").split()]
            lanes[lane.get("id", "")] = (pts, float(lane.get("width", "3.2")))  # type: ignore[misc]
            edge_lanes.setdefault(edge.get("id", ""), []).append(lane.get("id", ""))
    links: dict[tuple[str, str], set[int]] = {}
    for c in root.iter("connection"):
        tls, idx, frm = c.get("tl"), c.get("linkIndex"), c.get("from", "")
        if tls is None or idx is None or frm.startswith(":"):
            continue
        lane_id = f"{frm}_{c.get('fromLane')}"
        if lane_id in lanes:
            links.setdefault((tls, lane_id), set()).add(int(idx))
    heads = []
    for (tls, lane_id), idx in sorted(links.items()):
        pts, _ = lanes[lane_id]
        if len(pts) < 2:
            continue
        (x0, y0), (x1, y1) = pts[-2], pts[-1]
        heading = math.atan2(y1 - y0, x1 - x0)
        # the pole: right of the edge's rightmost lane (lane 0), at this lane's stop line
        edge = lane_id.rsplit("_", 1)[0]
        right_pts, right_w = lanes[min(edge_lanes[edge], key=lambda s: int(s.rsplit("_", 1)[1]))]
        rx, ry = right_pts[-1]
        off = right_w / 2 + POLE_OFFSET_M
        pole = (rx + off * math.sin(heading), ry - off * math.cos(heading))
        z = ROAD_Z[1] + HEAD_BOTTOM_M + HEAD_SIZE_M[2] / 2
        heads.append(SignalHead(f"{tls}/{lane_id}", tls, tuple(sorted(idx)), (x1, y1, z),
                                math.atan2(math.sin(heading + math.pi), math.cos(heading + math.pi)), pole))
    return tuple(heads)
