"""Traffic signs placed by a pass over SUMO's network: stop, give way and speed limits.

- ``give_way`` (Vienna Convention B,1, the inverted triangle): at the right kerb of the stop line of every
  approach whose links all yield at an unsignalised junction (SUMO link state ``m``, minor);
- ``stop`` (B,2, the octagon): where they must stop (``s``, stop; ``w``, all-way stop);
- ``speed_limit`` (C,14, the red ring): at the start of every road whose speed differs from the speed of
  a road leading into it, showing its limit rounded to 10 km/h.
Signs face the traffic they are for; their faces are retro-reflective sheeting (EN 12899-1).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from functools import lru_cache

SIGN_KINDS = ("stop", "give_way", "speed_limit")
#: [m] a sign stands this far right of its road's rightmost lane edge
KERB_OFFSET_M = 1.0
#: [m] a speed sign stands this far into its road (past the junction it leaves)
SPEED_SIGN_INTO_M = 6.0


@dataclass(frozen=True)
class TrafficSign:
    """One sign: id ``<kind>/<edge>``, kind (:data:`SIGN_KINDS`), the limit it shows [km/h] (speed signs,
    else 0), where its post stands (x, y, map) and the yaw [rad] its face looks along (against the traffic)."""

    sign_id: str
    kind: str
    value_kmh: int
    xy: tuple[float, float]
    yaw_rad: float


def _right_of(x: float, y: float, heading: float, off: float) -> tuple[float, float]:
    return (x + off * math.sin(heading), y - off * math.cos(heading))


@lru_cache(maxsize=4)
def traffic_signs(net_xml: bytes) -> tuple[TrafficSign, ...]:
    """Every sign of the network (module docstring), in a stable order (kind, edge)."""
    if b"<edge" not in net_xml:
        return ()
    root = ET.fromstring(net_xml)
    lanes: dict[str, list[tuple[float, list[tuple[float, float]], float]]] = {}  # edge -> (index, shape, width)
    speed: dict[str, float] = {}
    for edge in root.iter("edge"):
        eid = edge.get("id", "")
        if edge.get("function") in ("internal", "crossing", "walkingarea"):
            continue
        for lane in edge.iter("lane"):
            if lane.get("allow") == "pedestrian":
                continue
            pts = [(float(p.split(",")[0]), float(p.split(",")[1])) for p in lane.get("shape", "").split()]
            if len(pts) >= 2:
                lanes.setdefault(eid, []).append((int(lane.get("index", "0")), pts, float(lane.get("width", "3.2"))))
                speed[eid] = float(lane.get("speed", "13.89"))
    states: dict[str, set[str]] = {}
    feeds: dict[str, set[str]] = {}
    for c in root.iter("connection"):
        frm, to = c.get("from", ""), c.get("to", "")
        if frm not in lanes or to not in lanes:
            continue
        feeds.setdefault(to, set()).add(frm)
        if c.get("tl") is None:
            states.setdefault(frm, set()).add(c.get("state", ""))
    out = []

    def place(kind: str, eid: str, value: int, at_end: bool) -> None:
        _, pts, width = min(lanes[eid])  # lane 0: the rightmost
        if at_end:
            (x0, y0), (x1, y1) = pts[-2], pts[-1]
            heading = math.atan2(y1 - y0, x1 - x0)
            x, y = x1, y1
        else:
            (x0, y0), (x1, y1) = pts[0], pts[1]
            heading = math.atan2(y1 - y0, x1 - x0)
            into = min(SPEED_SIGN_INTO_M, 0.5 * math.hypot(x1 - x0, y1 - y0))
            x, y = x0 + into * math.cos(heading), y0 + into * math.sin(heading)
        px, py = _right_of(x, y, heading, width / 2 + KERB_OFFSET_M)
        back = heading + math.pi
        out.append(TrafficSign(f"{kind}/{eid}", kind, value, (px, py), math.atan2(math.sin(back), math.cos(back))))

    for eid in sorted(states):
        st = states[eid]
        if st and st <= {"s", "w"}:
            place("stop", eid, 0, True)
        elif st and st <= {"m", "s", "w"}:
            place("give_way", eid, 0, True)
    for eid in sorted(feeds):
        v = speed[eid]
        if any(abs(speed[f] - v) > 0.5 for f in feeds[eid]):
            place("speed_limit", eid, round(v * 3.6 / 10.0) * 10, False)
    return tuple(sorted(out, key=lambda s: (SIGN_KINDS.index(s.kind), s.sign_id)))
