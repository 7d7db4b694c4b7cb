"""Co-simulation overhead: the default scenario without sensors (traffic + drones + Zenoh + labels).

Prints simulated seconds per wall second for the whole run and for the tick loop, the time the loop
waits for the workers per tick (they compute tick k+1 while tick k is written), each worker's own
compute time, and the sync cost: per tick, the query round trip minus the worker's compute time
(what Zenoh, encoding, decoding and scheduling add), the worst of the two workers. Everything is measured in one run;
ratios, not absolute times, are what to compare across these shared machines.

    .venv/bin/python benchmarks/cosim_overhead.py [--duration 60] [--scenario scenarios/default.yaml]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path

from cosim.runner import run_episode
from cosim.scenario import load_scenario


def percentile(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, round(q / 100 * (len(s) - 1)))]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default="scenarios/default.yaml")
    p.add_argument("--duration", type=float, default=60.0, help="simulated seconds")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
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


if __name__ == "__main__":
    main()
