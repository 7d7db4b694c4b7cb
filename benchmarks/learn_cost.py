"""What a finer or wider ``cosim learn`` detector and the training augmentations cost on a CPU (issue 48).

For each combination of pillar size, width and range, the same training samples (the first ``--samples`` of a
dataset's train split, read once per range and kept in memory) are trained for ``--steps`` steps of batch
``--batch-size`` on one torch thread after one warm-up step, and the script prints per combination: the
parameters, the grid and its output cells, the CPU-seconds per step of making the batches (numpy: augmenting,
voxelising, targets) and of the model (forward, loss, backward, optimiser), the occupied pillars per sample,
the peak memory (resident set of the process that measured it: one process per combination) and the ratio
of the whole step to the first row's. Every combination is measured in this one run, so the ratios share
the machine's load.

    PYTHONPATH=. .venv/bin/python benchmarks/learn_cost.py DATASET [--samples 8] [--steps 3] [--batch-size 8]
        [--only NAME,...] [--json OUT.json]

Combinations (``--only`` takes their names): ``base`` (0.8 m, width 16, cosim eval's area x +-140.8, y +-40 m:
the default), ``w32``, ``w64``, ``p0.4``, ``p0.32``, ``p0.2`` (full area), ``front0.8``, ``front0.4``,
``front0.32``, ``front0.2``, ``front0.16`` (KITTI-like x 0..70.4, y +-40 m), ``front0.32w32``, ``front0.2w32``
and ``aug`` (the default grid with every augmentation on: docs/learnability.md, "Augmentation").
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

FULL = None
FRONT = ((0.0, 70.4), (-40.0, 40.0))
AUG = {"turn_deg": 45.0, "scale_min": 0.95, "scale_max": 1.05, "translate_m": 0.2, "height_m": 0.2,
       "point_drop": 0.1, "intensity_scale": 2.0, "intensity_noise": 0.05, "gt_sample": 10}
#: name -> (pillar m, width, range, augmentations)
COMBOS: dict[str, tuple[float, int, tuple | None, dict]] = {
    "base": (0.8, 16, FULL, {}), "w32": (0.8, 32, FULL, {}), "w64": (0.8, 64, FULL, {}),
    "p0.4": (0.4, 16, FULL, {}), "p0.32": (0.32, 16, FULL, {}), "p0.2": (0.2, 16, FULL, {}),
    "front0.8": (0.8, 16, FRONT, {}), "front0.4": (0.4, 16, FRONT, {}), "front0.32": (0.32, 16, FRONT, {}),
    "front0.2": (0.2, 16, FRONT, {}), "front0.16": (0.16, 16, FRONT, {}),
    "front0.32w32": (0.32, 32, FRONT, {}), "front0.2w32": (0.2, 32, FRONT, {}),
    "aug": (0.8, 16, FULL, AUG),
}


class MemorySamples:
    """The first ``n`` samples of a :class:`cosim.learn.data.Samples`, read once (``len``, ``item``, ``setup``)."""

    def __init__(self, samples, n: int):
        self.setup = samples.setup
        self.items = [samples.item(i) for i in range(min(n, len(samples)))]

    def __len__(self) -> int:
        return len(self.items)

    def item(self, i: int) -> dict:
        return self.items[i]


def measure(samples: MemorySamples, width: int, aug: dict, steps: int, batch_size: int) -> dict:
    import torch

    from cosim.learn.augment import GtDatabase
    from cosim.learn.grid import voxelise
    from cosim.learn.model import focal_loss, regression_loss
    from cosim.learn.train import TrainOptions, model_for, run_model, step_batch, to_device

    setup = samples.setup
    opts = TrainOptions(batch_size=batch_size, width=width, seed=0, **aug)
    torch.manual_seed(0)
    model = model_for(setup, opts)
    optim = torch.optim.AdamW(model.parameters(), lr=opts.lr, weight_decay=opts.weight_decay)
    db = GtDatabase.build(samples, opts.gt_min_points) if opts.gt_sample else None
    order = np.arange(len(samples))
    batch_s = model_s = 0.0
    for step in range(steps + 1):
        c0 = time.process_time()
        batch = step_batch(samples, order, step * batch_size, opts, step, db)
        c1 = time.process_time()
        b = to_device(batch, torch.device("cpu"))
        heat, reg = run_model(model, b, batch_size)
        loss = focal_loss(heat, b["t_heatmap"]) + 2.0 * regression_loss(reg, b["t_reg"], b["t_index"], b["t_mask"])
        optim.zero_grad(set_to_none=True)
        loss.backward()
        optim.step()
        c2 = time.process_time()
        if step:  # the first step warms up
            batch_s += c1 - c0
            model_s += c2 - c1
    pillars = np.mean([len(voxelise(samples.item(i)["clouds"][0], setup.grid)[2]) for i in range(len(samples))])
    g = setup.grid
    return {"params": sum(p.numel() for p in model.parameters()), "grid": [g.nx, g.ny], "out": list(g.out_shape),
            "batch_cpu_s": batch_s / steps, "model_cpu_s": model_s / steps, "pillars": float(pillars),
            "gt_objects": None if db is None else len(db)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", help="a batch folder (its train split) or a folder of episodes")
    ap.add_argument("--samples", type=int, default=8, help="training samples kept in memory (default 8)")
    ap.add_argument("--steps", type=int, default=3, help="measured steps per combination (default 3)")
    ap.add_argument("--batch-size", type=int, default=8)
    ap.add_argument("--only", help="comma-separated combination names (default: all)")
    ap.add_argument("--json", help="also write the rows to this file")
    ap.add_argument("--one", help=argparse.SUPPRESS)  # measure one combination here, print its row as JSON
    args = ap.parse_args()
    if args.one:
        print(json.dumps(measure_one(args, args.one)))
        return 0
    names = args.only.split(",") if args.only else list(COMBOS)
    unknown = [n for n in names if n not in COMBOS]
    if unknown:
        print(f"learn_cost: unknown combination {', '.join(unknown)}; choose from {', '.join(COMBOS)}",
              file=sys.stderr)
        return 2

    rows = []
    print(f"{'combination':<14} {'pillar m':>8} {'width':>5} {'range':>5} {'params':>8} {'grid':>10} "
          f"{'pillars':>8} {'batch CPU-s':>11} {'model CPU-s':>11} {'step CPU-s':>10} {'peak MB':>8} {'x base':>7}")
    for name in names:
        argv = [sys.executable, __file__, args.dataset, "--samples", str(args.samples), "--steps", str(args.steps),
                "--batch-size", str(args.batch_size), "--one", name]
        done = subprocess.run(argv, capture_output=True, text=True)
        if done.returncode:
            print(f"learn_cost: {name} failed: {done.stderr.strip()[-2000:]}", file=sys.stderr)
            return 1
        r = json.loads(done.stdout.strip().splitlines()[-1])
        r["ratio"] = r["step_cpu_s"] / rows[0]["step_cpu_s"] if rows else 1.0
        rows.append(r)
        print(f"{name:<14} {r['pillar_m']:>8g} {r['width']:>5} {r['range']:>5} {r['params']:>8,} "
              f"{r['grid'][0]:>5}x{r['grid'][1]:<4} {r['pillars']:>8.0f} {r['batch_cpu_s']:>11.2f} "
              f"{r['model_cpu_s']:>11.2f} {r['step_cpu_s']:>10.2f} {r['peak_mb']:>8.0f} {r['ratio']:>7.1f}",
              flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")
    return 0


def measure_one(args: argparse.Namespace, name: str) -> dict:
    """One combination's row, measured in this process (one torch thread)."""
    import resource

    import torch

    from cosim.eval.dataset import load_dataset
    from cosim.learn.data import Samples, Setup, split_episodes
    from cosim.learn.grid import make_grid

    torch.set_num_threads(1)
    torch.use_deterministic_algorithms(True)
    pillar, width, rng, aug = COMBOS[name]
    refs = split_episodes(load_dataset(Path(args.dataset)), None, "train", args.dataset)
    grid = make_grid(pillar, *(rng or (None, None)))
    s = Samples(refs, Setup(grid=grid), every=5)
    mem = MemorySamples(s, args.samples)
    s.close()
    r = measure(mem, width, aug, args.steps, args.batch_size)
    r.update({"name": name, "pillar_m": pillar, "width": width, "range": "front" if rng else "full",
              "augment": bool(aug), "step_cpu_s": r["batch_cpu_s"] + r["model_cpu_s"],
              "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024})
    return r


if __name__ == "__main__":
    sys.exit(main())
