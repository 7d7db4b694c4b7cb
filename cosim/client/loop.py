"""The runner's side of the closed loop: one object per episode with clients.

Per tick k: :meth:`ClosedLoop.record` gives the ``/actions`` message (what the clients asked after
tick k-1 and what the engines refused in the step to tick k), :meth:`ClosedLoop.publish` sends the
tick's messages to the clients, and :meth:`ClosedLoop.collect` waits for their actions and returns
them per worker role for the step request of tick k+1 (it also keeps the escort map in step with
strategy changes, so escorting drones get their new target's state).
"""

from __future__ import annotations

import time
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from typing import Any

from cosim.actions import ACTION_ARRAY_SCHEMA, VEHICLE_ACTIONS, ActionContext
from cosim.client.hub import ClientAction, ClientHub
from cosim.protocol import VehicleState
from cosim.scenario import LoadedScenario


def network_facts(net_xml: bytes) -> tuple[frozenset[str], int]:
    """Non-internal edge ids and the most lanes of any of them, from a SUMO network."""
    edges, max_lanes = set(), 0
    for edge in ET.fromstring(net_xml).iter("edge"):
        if edge.get("function") == "internal":
            continue
        edges.add(edge.get("id", ""))
        max_lanes = max(max_lanes, sum(1 for _ in edge.iter("lane")))
    return frozenset(edges), max_lanes


class ClosedLoop:
    def __init__(self, conductor: Any, loaded: LoadedScenario, world: Any, escorts: dict[str, str]):
        s = loaded.scenario
        self._escorts = escorts  # the runner's drone -> escorted vehicle map, updated in place
        self._drones = {f"drone_{i}": d.max_speed_mps for i, d in enumerate(s.agents.drones)}
        self._bounds = tuple(world.bounds_m)
        self._edges, self._max_lanes = network_facts(world.net_xml)
        self._applied: list[ClientAction] = []
        self._failed: list[dict[str, Any]] = []
        self._publish_s = 0.0
        self._publish_cpu_s = 0.0
        self.waits_s: list[float] = []  # per tick: publish + wait for every client's action [s] (telemetry)
        self.cpu_s: list[float] = []  # per tick: this thread's CPU time in publish + collect [s] (telemetry)
        self.endpoint = conductor.endpoint
        self.hub = ClientHub(conductor.session, conductor.prefix, s.clients,
                             default_timeout_s=s.runtime.tick_timeout_s,
                             episode={"scenario": s.name, "seed": s.seed, "agents": s.agent_ids(),
                                      "tick_ns": s.tick_ns, "n_ticks": s.n_ticks, "bounds_m": list(self._bounds)})
        self._startup_timeout_s = s.runtime.startup_timeout_s

    def wait_connected(self) -> None:
        self.hub.wait_connected(self._startup_timeout_s, self.endpoint)

    def wants_sensor_topics(self) -> bool:
        return self.hub.wants_sensor_topics()

    def record(self, tick: int, t_ns: int, replies: dict[str, Any]) -> tuple[str, Any]:
        """The ``/actions`` message of tick ``tick``."""
        self._failed = [f for role in sorted(replies) for f in replies[role].get("failed", [])]
        payload = {
            "timestamp_ns": t_ns,
            "tick": tick,
            "actions": [{"client": a.client, "observed_tick": a.observed_tick, "action": a.action}
                        for a in self._applied],
            "failed": self._failed,
        }
        return "/actions", ("cosim.ActionArray", ACTION_ARRAY_SCHEMA, payload)

    def publish(self, tick: int, t_ns: int, vehicles: Sequence[VehicleState], messages: Sequence[tuple[str, Any]],
                *, last: bool) -> None:
        context = ActionContext(
            vehicles=frozenset(v.agent_id for v in vehicles if v.agent_id),
            drones=self._drones,
            bounds_m=self._bounds,  # type: ignore[arg-type]
            max_lanes=self._max_lanes,
            edges=self._edges,
        )
        started, cpu = time.perf_counter(), time.thread_time()
        self.hub.publish(tick, t_ns, messages, context, last=last, failed=self._failed)
        self._publish_s, self._publish_cpu_s = time.perf_counter() - started, time.thread_time() - cpu

    def collect(self, tick: int) -> dict[str, list[dict[str, Any]]]:
        """The clients' actions after tick ``tick``, per worker role."""
        started, cpu = time.perf_counter(), time.thread_time()
        self._applied = self.hub.collect(tick)
        self.waits_s.append(time.perf_counter() - started + self._publish_s)  # telemetry only
        self.cpu_s.append(time.thread_time() - cpu + self._publish_cpu_s)
        out: dict[str, list[dict[str, Any]]] = {"traffic": [], "drones": []}
        for a in self._applied:
            kind = a.action["type"]
            if kind in VEHICLE_ACTIONS:
                out["traffic"].append(a.action)
                continue
            out["drones"].append(a.action)
            agent = a.action["agent"]
            target = a.action.get("target") if kind == "escort" else (a.action["drone"].get("target") if kind ==
                                                                       "strategy" else None)
            if target is not None:
                self._escorts[agent] = target
            else:
                self._escorts.pop(agent, None)
        return out
