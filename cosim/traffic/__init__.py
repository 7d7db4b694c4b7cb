"""Ground traffic: the SUMO adapter (:class:`TrafficSim`) and an in-process fake (:class:`FakeTraffic`).

Both are imported on first use, so importing this package loads neither libsumo nor the world package.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from cosim.traffic.fake import FakeTraffic
    from cosim.traffic.sumo_sim import TrafficSim

__all__ = ["FakeTraffic", "TrafficSim"]


def __getattr__(name: str) -> Any:
    if name == "TrafficSim":
        from cosim.traffic.sumo_sim import TrafficSim

        return TrafficSim
    if name == "FakeTraffic":
        from cosim.traffic.fake import FakeTraffic

        return FakeTraffic
    raise AttributeError(f"module 'cosim.traffic' has no attribute {name!r}")
