"""The traffic worker's CPU with pedestrians: ``TrafficSim.step_to`` over an episode and the share spent in
the pedestrians' label boxes (``people.posed_box``). ``--old`` boxes them as before (the posed mesh's box,
through ``posed_steps`` and its 1024-entry cache), for a before/after on one machine:

    nice -n 10 .venv/bin/python benchmarks/pedestrian_boxes.py scenarios/town_urban_day_clear.yaml 60 --old
    nice -n 10 .venv/bin/python benchmarks/pedestrian_boxes.py scenarios/town_urban_day_clear.yaml 60

Arguments: a scenario and its duration [s]. CPU is this process's (libsumo runs in it).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from cosim.sensors.assets import people

import cosim.traffic.pedestrians as tp
from cosim.scenario import load_scenario
from cosim.traffic import TrafficSim
from cosim.world import build_world


def mesh_box(key: str, phase: float, speed: float):
    """The label box the way it was made before: from the whole posed mesh."""
    _, _, _, _, _, lo, hi = people.posed_steps(key, *people.quantized(phase, speed))
    return tuple(float(x) for x in hi - lo), tuple(float(x) for x in (lo + hi) / 2)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario")
    ap.add_argument("duration_s", type=float)
    ap.add_argument("--old", action="store_true", help="box the pedestrians from their posed meshes")
    args = ap.parse_args()
    loaded = load_scenario(args.scenario, [f"duration_s={args.duration_s}"])
    sc = loaded.scenario
    tmp = Path(tempfile.mkdtemp())
    sim = TrafficSim(sc, build_world(loaded, tmp / "w"), tmp / "s")
    box = mesh_box if args.old else tp.posed_box
    spent = [0.0]

    def timed(*a):
        t0 = time.process_time()
        out = box(*a)
        spent[0] += time.process_time() - t0
        return out

    tp.posed_box = timed
    c0 = time.process_time()
    peds = 0
    try:
        for k in range(sc.n_ticks):
            peds += sum(s.cls == "pedestrian" for s in sim.step_to(k * sc.tick_ns))
    finally:
        sim.close()
    cpu = time.process_time() - c0
    print(f"{'old' if args.old else 'new'}: ticks {sc.n_ticks}, pedestrian states {peds} ({peds / sc.n_ticks:.1f}"
          f"/tick), step CPU {cpu:.2f} s ({cpu / sc.n_ticks * 1e3:.1f} ms/tick), of which posed_box {spent[0]:.2f} s "
          f"({spent[0] / max(peds, 1) * 1e3:.3f} ms/call)")


if __name__ == "__main__":
    main()
