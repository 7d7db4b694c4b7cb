"""Learning curves of ``cosim learn`` runs: validation AP30 and AP50 against training steps, and the
training loss, from each run's ``log.jsonl`` (matplotlib, no torch)."""

from __future__ import annotations

import json
from pathlib import Path

from cosim.errors import InputError


def _log(run: Path) -> list[dict]:
    path = run / "log.jsonl"
    if not path.is_file():
        raise InputError(f"{run}: no log.jsonl: not a run folder of cosim learn train")
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def own_validations(rows: list[dict]) -> list[dict]:
    """The training's own validations of a run's log, in step order: not the lines `cosim learn validate`
    appends (they carry a ``split`` and score other frames, so they would zigzag the curve)."""
    return sorted((r for r in rows if "val" in r and "split" not in r), key=lambda r: r["step"])


def plot_curves(runs: list[Path], out: Path, title: str) -> Path:
    """One PNG: loss (smoothed over 20 steps), validation AP30 and AP50 against steps, one line per run
    (labelled by its folder name)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    for run in runs:
        rows = _log(run)
        steps = np.array([r["step"] for r in rows if "loss" in r])
        loss = np.array([r["loss"] for r in rows if "loss" in r])
        if len(loss):
            k = min(20, len(loss))
            smooth = np.convolve(loss, np.ones(k) / k, mode="valid")
            axes[0].plot(steps[k - 1:], smooth, label=run.name)
        val = own_validations(rows)
        for ax, key in zip(axes[1:], ("AP30", "AP50"), strict=True):
            ax.plot([r["step"] for r in val], [r["val"][key] for r in val], marker="o", label=run.name)
    axes[0].set(title="training loss (20-step mean)", xlabel="step", yscale="log")
    axes[1].set(title="val AP30 (%), vehicle", xlabel="step", ylim=(0, None))
    axes[2].set(title="val AP50 (%), vehicle", xlabel="step", ylim=(0, None))
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[2].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out
