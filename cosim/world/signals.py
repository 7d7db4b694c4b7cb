"""Traffic signal plans (scenario key ``traffic.signals``, README's scenario keys table).

netconvert gives every signalised junction the same static program: a 90 s cycle of 42 s green and 3 s
yellow per direction, offset 0, so all lights switch in lockstep and a red lasts 45 s whatever the
junction. :func:`plan_signals` rewrites the network's ``tlLogic`` programs, keeping their phase order
and signal states (which links move together, which netconvert derived from the geometry):

- the cycle follows the junction's size, :func:`cycle_s` (controlled links: a T of two-lane streets has
  about 9, a crossing of two avenues 24 or more): 30 s for the smallest, up to 50 s for the largest
  (shorter cycles lost more to yellow and pedestrian clearance in measurements, longer ones stopped
  more vehicles: benchmarks/data_quality.py);
- the green time (the cycle less the yellow and all-red phases, which keep their durations) is split
  over the green phases in proportion to the links each one releases, at least :data:`MIN_GREEN_S`;
- each junction's offset is drawn from the scenario's generator (uniform over its cycle), so that
  neighbouring lights do not switch in lockstep;
- ``actuated`` (the default): SUMO's gap-based actuated control (``type="actuated"``, detectors that
  SUMO places on the incoming lanes when it loads the network): a green phase lasts from
  ``minDur`` (:data:`MIN_GREEN_S`) to ``maxDur`` (:data:`MAX_GREEN_FACTOR` times its planned green) and
  ends early when its approaches empty; ``fixed``: the fixed-time plan; ``as_built``: the network's
  programs as netconvert (or the user's ``map.file``) made them, untouched.
"""

from __future__ import annotations

import re

import numpy as np

SIGNAL_MODES = ("actuated", "fixed", "as_built")
MIN_CYCLE_S = 30.0  # [s] cycle of the smallest signalised junctions
MAX_CYCLE_S = 50.0  # [s] cycle of the largest
CYCLE_PER_LINK_S = 2.0  # [s] cycle added per controlled link above the smallest junction's
MIN_GREEN_S = 5.0  # [s] shortest green of a phase (and the least an actuated phase may last)
MAX_GREEN_FACTOR = 2.5  # an actuated green may stretch to this many times its planned length

_TL = re.compile(rb"<tlLogic\b[^>]*>.*?</tlLogic>", re.S)
_PHASE = re.compile(rb"<phase\b[^>]*/>")
_ATTR = re.compile(rb'(\w+)="([^"]*)"')


def cycle_s(links: int) -> float:
    """Cycle length [s] of a junction with ``links`` controlled links (see the module docstring)."""
    return float(np.clip(MIN_CYCLE_S + CYCLE_PER_LINK_S * (links - 9), MIN_CYCLE_S, MAX_CYCLE_S))


def _is_green(state: str) -> bool:
    return any(c in "Gg" for c in state) and not any(c in "yYu" for c in state)


def _fmt(v: float) -> str:
    return f"{v:.0f}" if float(v).is_integer() else f"{v:.1f}"


def _plan(logic: bytes, mode: str, rng: np.random.Generator) -> bytes:
    head = logic[: logic.index(b">") + 1]
    attrs = {k.decode(): v.decode() for k, v in _ATTR.findall(head)}
    phases = [{k.decode(): v.decode() for k, v in _ATTR.findall(p)} for p in _PHASE.findall(logic)]
    if not phases:
        return logic
    links = len(phases[0]["state"])
    cycle = cycle_s(links)
    fixed = sum(float(p["duration"]) for p in phases if not _is_green(p["state"]))
    greens = [p for p in phases if _is_green(p["state"])]
    weights = np.array([sum(c in "Gg" for c in p["state"]) for p in greens], dtype=float)
    budget = max(cycle - fixed, MIN_GREEN_S * len(greens))
    for p, w in zip(greens, weights, strict=True):
        g = max(MIN_GREEN_S, round(budget * w / weights.sum()))
        p["duration"] = _fmt(g)
        if mode == "actuated":
            p["minDur"] = _fmt(MIN_GREEN_S)
            p["maxDur"] = _fmt(round(MAX_GREEN_FACTOR * g))
    total = sum(float(p["duration"]) for p in phases)
    attrs["type"] = "actuated" if mode == "actuated" else "static"
    attrs["offset"] = _fmt(round(float(rng.uniform(0.0, total))))
    order = ("duration", "minDur", "maxDur", "state")
    out = [b"<tlLogic " + " ".join(f'{k}="{v}"' for k, v in attrs.items()).encode() + b">"]
    for p in phases:
        keys = [k for k in order if k in p] + [k for k in p if k not in order]
        out.append(b"        <phase " + " ".join(f'{k}="{p[k]}"' for k in keys).encode() + b"/>")
    return b"\n".join(out) + b"\n    </tlLogic>"


def plan_signals(net_xml: bytes, mode: str, rng: np.random.Generator) -> bytes:
    """``net_xml`` with every ``tlLogic`` program replanned for ``mode`` (one of :data:`SIGNAL_MODES`),
    in document order; ``as_built`` returns it unchanged."""
    if mode not in SIGNAL_MODES:
        raise ValueError(f"unknown traffic.signals {mode!r}; known: {', '.join(SIGNAL_MODES)}")
    if mode == "as_built":
        return net_xml
    return _TL.sub(lambda m: _plan(m.group(0), mode, rng), net_xml)
