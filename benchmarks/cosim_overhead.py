"""Co-simulation overhead: the default scenario without sensors (traffic + drones + Zenoh + labels).

Prints simulated seconds per wall second for the whole run and for the tick loop, the time the loop
waits for the workers per tick (they compute tick k+1 while tick k is written), each worker's own
compute time, and the sync cost: per tick, the query round trip minus the worker's compute time
(what Zenoh, encoding, decoding and scheduling add), the worst of the two workers. Everything is measured in one run;
ratios, not absolute times, are what to compare across these shared machines.

    .venv/bin/python benchmarks/cosim_overhead.py [--duration 60] [--scenario scenarios/default.yaml]

With ``--clients N`` it runs the scenario twice, without and with N closed-loop clients (processes that
answer every tick at once with no actions), and prints the lockstep overhead per tick: the time from the
observations going out to the last action coming in, the CPU time that exchange costs the conductor's
thread and each client process (what it costs without the scheduling delays of a loaded machine), and the
tick loop's wall time per tick of both runs (with clients the workers can no longer step tick k+1 while
tick k is written).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from cosim.runner import run_episode
from cosim.scenario import load_scenario
from cosim.transport import free_loopback_endpoint


def percentile(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, round(q / 100 * (len(s) - 1)))]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default="scenarios/default.yaml")
    p.add_argument("--duration", type=float, default=60.0, help="simulated seconds")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--clients", type=int, default=0, help="closed-loop clients that answer at once")
    args = p.parse_args()
    loaded = load_scenario(args.scenario, [f"duration_s={args.duration}", "sensors.enabled=false", *args.set])
    s = loaded.scenario
    with tempfile.TemporaryDirectory() as out:
        r = run_episode(loaded, Path(out))
    step_ms = [t * 1e3 for t in r.tick_times_s]
    sync_ms = [t * 1e3 for t in r.sync_costs_s]
    print(f"scenario            {s.name}: {s.map.kind}, {s.agents.vehicles.count} vehicles, "
          f"{s.agents.rsus.count} RSUs, {len(s.agents.drones)} drones, {r.actors} tracks")
    print(f"simulated           {r.sim_time_s:.1f} s in {r.ticks} ticks; wall {r.wall_time_s:.2f} s "
          f"(incl. world build and worker start-up)")
    print(f"real-time factor    {r.sim_time_s / r.loop_wall_s:.1f}x in the tick loop "
          f"({r.real_time_factor:.1f}x including world build and start-up)")
    print(f"wait per tick       mean {statistics.mean(step_ms):.2f} ms, p99 {percentile(step_ms, 99):.2f} ms")
    print(f"sync cost per tick  mean {statistics.mean(sync_ms):.3f} ms, p99 {percentile(sync_ms, 99):.3f} ms "
          f"({statistics.mean(sync_ms) / (r.sim_time_s * 1e3 / r.ticks):.1%} of the 200 ms tick)")
    for role, times in sorted(r.compute_s.items()):
        ms = [t * 1e3 for t in times]
        print(f"{role + ' worker':<20}mean {statistics.mean(ms):.2f} ms, p99 {percentile(ms, 99):.2f} ms per tick "
              f"({r.sim_time_s / sum(times):.0f}x real time on its own)")
    print(f"episode             {r.messages} messages, {r.size_bytes / 1e6:.2f} MB")
    if args.clients:
        report_clients(args, r)


#: A client that answers every tick at once with no actions (the observation is never decoded); it prints
#: its process CPU time per tick from the first observation to the last.
CLIENT = """import sys, time
from cosim.client import connect
with connect(sys.argv[1]) as c:
    for n, obs in enumerate(c.ticks()):
        if n == 0:
            cpu = time.process_time()
print(f"{(time.process_time() - cpu) / n}")
"""


def report_clients(args: argparse.Namespace, alone: Any) -> None:
    names = [f"bench{i}" for i in range(args.clients)]
    endpoint, prefix = free_loopback_endpoint(), f"cosim/bench/{os.getpid()}"
    overrides = [f"duration_s={args.duration}", "sensors.enabled=false", *args.set,
                 "clients=" + json.dumps([{"name": n} for n in names])]
    env = {**os.environ, "COSIM_ENDPOINT": endpoint, "COSIM_PREFIX": prefix}
    procs = [subprocess.Popen([sys.executable, "-c", CLIENT, n], env=env, stdout=subprocess.PIPE, text=True)
             for n in names]
    try:
        with tempfile.TemporaryDirectory() as out:
            r = run_episode(load_scenario(args.scenario, overrides), Path(out), listen=endpoint, prefix=prefix)
    finally:
        client_cpu_ms = [float(proc.communicate(timeout=30)[0] or "nan") * 1e3 for proc in procs]
    wait_ms = [t * 1e3 for t in r.client_waits_s]
    per_tick_alone, per_tick = alone.loop_wall_s / alone.ticks * 1e3, r.loop_wall_s / r.ticks * 1e3
    print(f"clients             {args.clients}, answering at once; {r.ticks} ticks, labels only")
    print(f"client round trip   mean {statistics.mean(wait_ms):.2f} ms, p99 {percentile(wait_ms, 99):.2f} ms per tick "
          f"(observations out -> last action in)")
    print(f"CPU per tick        conductor {statistics.mean(r.client_cpu_s) * 1e3:.2f} ms (publish, wait, check), "
          f"client process {statistics.mean(client_cpu_ms):.2f} ms (receive, answer)")
    print(f"tick loop per tick  {per_tick_alone:.2f} ms without clients, {per_tick:.2f} ms with: "
          f"{per_tick - per_tick_alone:+.2f} ms per tick")


if __name__ == "__main__":
    main()
