"""A training loop over cosim episodes with :class:`cosim.io.dataset.CooperativeDataset`.

    python examples/train_loop.py out/default_s0.mcap [more.mcap ...] [--steps 10] [--batch 2]

With PyTorch installed the samples go through a ``torch.utils.data.DataLoader`` (a list-of-samples
collate, as cooperative samples hold a different number of agents and points); without it the same loop
runs over plain Python batches. The "model" is a stand-in: a per-class mean box size fitted by gradient
steps, so the loop shows where boxes and points come from without needing a network.
"""

from __future__ import annotations

import argparse
import importlib.util
from collections.abc import Iterator

import numpy as np

from cosim import cli_args
from cosim.io.dataset import CooperativeDataset


def batches(ds: CooperativeDataset, batch: int) -> Iterator[list[dict]]:
    if importlib.util.find_spec("torch") is not None:
        from torch.utils.data import DataLoader

        yield from DataLoader(ds, batch_size=batch, shuffle=False, collate_fn=list)
    else:
        for start in range(0, len(ds), batch):
            yield [ds[i] for i in range(start, min(start + batch, len(ds)))]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("episodes", nargs="+", type=cli_args.input_file)
    p.add_argument("--steps", type=cli_args.positive_int, default=10)
    p.add_argument("--batch", type=cli_args.positive_int, default=2)
    p.add_argument("--lr", type=cli_args.positive_float, default=0.5)
    args = p.parse_args()

    ds = CooperativeDataset(args.episodes)
    size = np.zeros(3)  # the "model": one (l, w, h) for every box
    print(f"{len(ds)} samples; backend: {'torch' if importlib.util.find_spec('torch') else 'plain python'}")
    for step, samples in enumerate(batches(ds, args.batch)):
        if step >= args.steps:
            break
        boxes = np.concatenate([s["boxes"] for s in samples])
        points = sum(sum(len(p) for p in s["lidar"]) for s in samples)
        if len(boxes):
            grad = 2 * (size - boxes[:, 3:6]).mean(axis=0)
            size -= args.lr * grad
            loss = float(((boxes[:, 3:6] - size) ** 2).mean())
        else:
            loss = float("nan")
        print(f"step {step}: {len(samples)} samples, {len(boxes)} boxes, {points} points, loss {loss:.3f}")
    print(f"mean box size (l, w, h): {np.round(size, 2).tolist()}")


if __name__ == "__main__":
    main()
