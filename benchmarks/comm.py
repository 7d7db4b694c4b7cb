"""Link model cost per tick for the paper's full 5+5+5 rig, against the sensor frame time.

    PYTHONPATH=. .venv/bin/python benchmarks/comm.py [--frames 3] [--ticks 50] [--background 40]
    PYTHONPATH=. .venv/bin/python benchmarks/comm.py --smoke

``--smoke`` runs every step on a small input (a 300 m map, cameras at 1/20 of their size, one frame, two
ticks, five road users) so that the suite sees the script work (tests/test_benchmarks.py); its numbers mean
nothing.

World: what ``build_world`` makes for scenarios/default.yaml; agents: 5 vehicles, 5 RSUs, 5 drones
(``benchmarks/sensors.py``'s rig) among ``--background`` other road users, placed by
``world_snapshot``. Measured in one run:

- the link model per tick (210 ordered links: line of sight through the static scene and the
  actors' boxes, path loss, fading, PER, rate, delay, and the ``/comm/links`` payload), the mean
  over ``--ticks`` snapshots (cycling through ``--frames`` placements, so the fading state carries);
- the sensor frame time: ``SensorSuite.render`` of the full rig (55 cameras at 1280x720, 15 LiDARs)
  on ``--frames`` of those snapshots, without encoding and writing (so the frame time is
  underestimated and the printed share is an upper bound);
- the static scene the link model builds when sensors are off (once per episode).

Prints the link model's share of the frame time (the target is under 5 %).
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from pathlib import Path

import numpy as np
from cosim.sensors import SensorSuite
from cosim.sensors.synthetic import world_snapshot

from benchmarks.sensors import paper_rig_scenario
from cosim.comm.links import LinkModel
from cosim.comm.los import LinkScene
from cosim.world.build import build_world

ROOT = Path(__file__).resolve().parents[1]
#: What ``--smoke`` sets: a small map and small cameras.
SMOKE_SETS = ("map.size_m=300", "sensors.image_scale=0.05")


def run(args: argparse.Namespace) -> None:
    loaded = paper_rig_scenario(ROOT / "scenarios" / "default.yaml", overrides=SMOKE_SETS if args.smoke else ())
    sc = loaded.scenario
    with tempfile.TemporaryDirectory() as tmp:
        world = build_world(loaded, Path(tmp))
    snaps = [world_snapshot(world, 5, 5, args.background, seed=k, tick=k) for k in range(args.frames)]
    t0 = time.perf_counter()
    own_scene = LinkScene.from_layout(world.layout)
    t_scene = time.perf_counter() - t0
    print(f"world: {len(world.layout.prisms)} prisms, {own_scene.n_triangles} wall triangles; "
          f"{len(snaps[0].agents)} agents, {len(snaps[0].actors)} actors; link scene without sensors (once per "
          f"episode) {t_scene * 1e3:.0f} ms")

    suite = SensorSuite(sc, world)
    try:
        model = LinkModel(sc.comm, own_scene, world.map_kind, sc.seed, sc.tick_ns)
        model.message(snaps[0])  # warm-up (imports)
        link_s = []
        for k in range(args.ticks):
            snap = snaps[k % len(snaps)]
            t0 = time.perf_counter()
            _, (_, _, payload) = model.message(snap)
            json.dumps(payload)  # what the writer does with it
            link_s.append(time.perf_counter() - t0)
        n_links = len(payload["links"]["tx"])
        suite.render(snaps[0], np.random.default_rng(0))  # untimed: RSU static hits, BVH warm-up
        frame_s = []
        for k, snap in enumerate(snaps):
            t0 = time.perf_counter()
            suite.render(snap, np.random.default_rng(k))
            frame_s.append(time.perf_counter() - t0)
    finally:
        suite.close()
    link_ms, frame_ms = 1e3 * float(np.mean(link_s)), 1e3 * float(np.mean(frame_s))
    print(f"link model: {link_ms:.2f} ms per tick ({n_links} links; median {1e3 * np.median(link_s):.2f} ms, "
          f"max {1e3 * max(link_s):.2f} ms over {args.ticks} ticks)")
    print(f"sensor frame (render only, {len(frame_s)} frames): {frame_ms:.0f} ms")
    print(f"link model / frame time: {100 * link_ms / frame_ms:.2f} % (target < 5 %)")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=3, help="snapshots rendered (default 3)")
    p.add_argument("--ticks", type=int, default=50, help="link model ticks timed (default 50)")
    p.add_argument("--background", type=int, default=40, help="other road users (default 40)")
    p.add_argument("--smoke", action="store_true", help="a small input, one frame, two ticks: checks the script runs")
    args = p.parse_args()
    if args.smoke:
        args.frames, args.ticks, args.background = 1, 2, 5
    logging.basicConfig(level=logging.WARNING)
    run(args)


if __name__ == "__main__":
    main()
