"""``cosim learn transfer``: how detectors transfer to real scans (docs/realism.md).

Given runs by name (``--run cosim=RUN --run real=RUN --run finetuned=RUN``, a name given again for each seed)
and KITTI-layout folders (``--kitti DIR``, several), each run's model detects on each folder's scans and is
scored as ``cosim learn score`` scores (:func:`cosim.learn.kitti.score_source`): recall at score >= 0.3 by range
band (0-20, 20-40, 40-60 m), false positives per frame, BEV AP30 / AP50 / AP70 (cosim eval's definition)
within the range asked, over the vehicles with >= 5 points in the front camera's view. Per folder and name:
the mean over the seeds and their spread (lowest to highest). Writes ``transfer.md`` and ``transfer.json``
(every run's own numbers too) and, with ``--picture``, real scans in bird's eye view with the labels (found:
green, missed: red, ignored: grey) and the detections (true: blue, false: orange), one row per name.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np

from cosim.errors import InputError

#: The summary columns of the report, in order (keys of :meth:`cosim.learn.kitti.KittiScore.summary`).
REPORT_COLUMNS = ("recall 0-20 m", "recall 20-40 m", "recall 40-60 m", "false positives per frame", "AP30", "AP50",
                  "AP70")


def parse_runs(specs: list[str]) -> list[tuple[str, Path]]:
    """``NAME=RUN`` pairs in the order given (a bare RUN is named by its folder)."""
    out = []
    for spec in specs:
        name, sep, run = spec.partition("=")
        if not sep:
            name, run = Path(spec).name, spec
        if not name or not run:
            raise InputError(f"--run {spec!r}: give NAME=RUN (e.g. cosim=runs/cosim_s0)")
        if not Path(run).exists():
            raise InputError(f"--run {spec}: no run at {run}")
        out.append((name, Path(run)))
    return out


def spread(values: list[float]) -> dict[str, float]:
    """Mean, standard deviation, lowest and highest of the finite values (NaN when none)."""
    v = np.array([x for x in values if x == x], np.float64)
    if not len(v):
        nan = float("nan")
        return {"mean": nan, "sd": nan, "min": nan, "max": nan, "n": 0}
    return {"mean": round(float(v.mean()), 3), "sd": round(float(v.std()), 3), "min": round(float(v.min()), 3),
            "max": round(float(v.max()), 3), "n": len(v)}


def transfer(runs: list[tuple[str, Path]], sources: list[Any], o: Any, device: Any, picture: Path | None = None,
             picture_scans: int = 4, log: Any = print) -> dict[str, Any]:
    """The report's numbers: per folder, per name, every run's :meth:`KittiScore.summary` and the spread of each
    column; the picture of the first run of each name on the first folder."""
    from cosim.learn.kitti import score_source
    from cosim.learn.train import load_run

    keep: dict[str, list] = {}
    per_run: list[dict[str, Any]] = []
    for name, run in runs:
        model, setup, ckpt = load_run(run, device)
        if setup.fusion != "none":
            raise InputError(f"--run {name}={run}: a model of fusion {setup.fusion}; real scans need fusion none")
        from cosim.learn.kitti import predict_source

        for k, s in enumerate(sources):
            t0 = time.perf_counter()
            preds = {t: p[:2] for t, p in predict_source(model, setup, s, device).items()}
            frames = [] if (picture is not None and k == 0 and name not in keep) else None
            summary = score_source(s, preds, o, keep=frames).summary()
            if frames is not None:
                keep[name] = frames
            per_run.append({"name": name, "run": str(run), "folder": s.id, "step": int(ckpt.get("step", 0)),
                            "model_height_m": setup.lidar_height_m, "folder_height_m": s.height_m, **summary})
            log(f"{name:>10} {run}: {s.id} AP30 {summary['AP30']:.1f} AP50 {summary['AP50']:.1f}, recall 0-"
                f"{o.max_range_m:g} m {summary[f'recall 0-{o.max_range_m:g} m']}, "
                f"{summary['false positives per frame']} false positives per frame ({time.perf_counter() - t0:.0f} s)")
    names = list(dict.fromkeys(n for n, _ in runs))
    cols = (*REPORT_COLUMNS, f"recall 0-{o.max_range_m:g} m")
    folders = []
    for s in sources:
        rows = [r for r in per_run if r["folder"] == s.id]
        first = rows[0]
        nothing = {int(t): (np.zeros((0, 7)), np.zeros(0)) for t in s.stems}
        front = score_source(s, nothing, dataclasses.replace(o, fov="front90")).summary()["cars"]
        folder = {"folder": s.id, "scans": len(s), "height_m": s.height_m, "height_given": s.height_given,
                  "cars": first["cars"], **{k: first[k] for k in first if k.startswith("cars ")},
                  "cars front 90 deg": front, "names": {}}
        for n in names:
            mine = [r for r in rows if r["name"] == n]
            folder["names"][n] = {"seeds": len(mine), **{c: spread([r[c] for r in mine]) for c in cols}}
        folders.append(folder)
    report = {"options": _options(o), "runs": per_run, "folders": folders, "names": names}
    if picture is not None and keep:
        draw(keep, sources[0], o, picture, picture_scans)
        report["picture"] = str(picture)
    return report


def _options(o: Any) -> dict[str, Any]:
    from cosim.learn.kitti import options_dict

    return options_dict(o)


def _fmt(s: dict[str, float], pct: bool = False) -> str:
    if s["n"] == 0:
        return "-"
    f = (lambda v: f"{v:.1f}") if pct else (lambda v: f"{v:.2f}")
    return f(s["mean"]) if s["n"] == 1 or s["min"] == s["max"] else f"{f(s['mean'])} ({f(s['min'])}-{f(s['max'])})"


def markdown(report: dict[str, Any]) -> str:
    """The report as markdown: one table per folder, a row per name (mean over its seeds, lowest-highest)."""
    from cosim.learn.kitti import ScoreOptions, score_title

    opts = report["options"]
    o = ScoreOptions(fov=opts["fov"], max_range_m=opts["max_range_m"], min_points=opts["min_points"],
                     min_score=opts["min_score"], iou=opts["iou"])
    cols = (*REPORT_COLUMNS[:3], f"recall 0-{o.max_range_m:g} m", *REPORT_COLUMNS[3:])
    lines = ["# Transfer to real scans", "", score_title(o) + "; mean over seeds (lowest-highest).", ""]
    for f in report["folders"]:
        bands = ", ".join(f"{k.removeprefix('cars ')}: {v}" for k, v in f.items()
                          if k.startswith("cars ") and k.endswith(" m"))
        lines += [f"## {f['folder']}", "",
                  f"{f['scans']} scans, LiDAR {f['height_m']:.3f} m above the road "
                  f"({'given' if f['height_given'] else 'estimated'}); {f['cars']} vehicles within "
                  f"{o.max_range_m:g} m ({bands}); {f['cars front 90 deg']} in the front 90 deg within "
                  f"{o.max_range_m:g} m.", "",
                  "| model | seeds | " + " | ".join(cols) + " |", "|---|---:" + "|---:" * len(cols) + "|"]
        for n, row in f["names"].items():
            lines.append(f"| {n} | {row['seeds']} | " + " | ".join(_fmt(row[c], c.startswith("AP")) for c in cols)
                         + " |")
        lines.append("")
    if report.get("picture"):
        lines += [f"![real scans with each model's boxes and the labels]({report['picture']})", ""]
    return "\n".join(lines)


def draw(keep: dict[str, list], source: Any, o: Any, out: Path, scans: int) -> None:
    """BEV of the ``scans`` scans with the most scored vehicles (columns), for each name's first run (rows)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cosim.eval.boxes import footprints
    from cosim.learn.kitti import in_view

    first = next(iter(keep.values()))
    order = sorted(range(len(first)), key=lambda i: (-len(first[i][1].gt), i))[:scans]
    names = list(keep)
    fig, axes = plt.subplots(len(names), len(order), figsize=(4.2 * len(order), 4.4 * len(names)), squeeze=False)
    reach = max(hi for _lo, hi in o.bands_m)
    for r, name in enumerate(names):
        for c, i in enumerate(order):
            stem, fs = keep[name][i]
            ax = axes[r, c]
            frame = source.frame(stem)
            p = frame.points
            near = (p[:, 0] > -5) & (p[:, 0] < reach) & (np.abs(p[:, 1]) < reach / 2)
            view = in_view(p[near, :3], frame, o.fov)
            ax.scatter(p[near, 1], p[near, 0], s=0.05, c=np.where(view, 0.35, 0.8), cmap="gray", vmin=0, vmax=1,
                       rasterized=True)

            def poly(boxes: np.ndarray, ax: Any = ax, **kw: Any) -> None:
                for fp in footprints(boxes[:, :2], boxes[:, 3:5], boxes[:, 6]):
                    ax.fill(fp[:, 1], fp[:, 0], fill=False, **kw)

            poly(fs.ignored_gt, edgecolor="0.5", linestyle=":", linewidth=0.8)
            poly(fs.gt[fs.found], edgecolor="tab:green", linewidth=1.6)
            poly(fs.gt[~fs.found], edgecolor="tab:red", linewidth=1.6)
            strong = fs.det_scores >= o.min_score
            poly(fs.det[strong & fs.det_tp], edgecolor="tab:blue", linewidth=0.9)
            poly(fs.det[strong & ~fs.det_tp], edgecolor="tab:orange", linewidth=0.9)
            ax.set_xlim(reach / 2, -reach / 2)
            ax.set_ylim(-5, reach)
            ax.set_aspect("equal")
            ax.set_title(f"{name}: {stem} - {int(fs.found.sum())}/{len(fs.gt)} found, "
                         f"{int((strong & ~fs.det_tp).sum())} false", fontsize=9)
            ax.tick_params(labelsize=7)
            if c == 0:
                ax.set_ylabel("x [m] (forward)")
            if r == len(names) - 1:
                ax.set_xlabel("y [m] (left)")
    fig.suptitle(f"{source.id}: labels found (green), missed (red), ignored (grey dotted); detections at score >= "
                 f"{o.min_score:g} true (blue), false (orange); dark points: in view", fontsize=10)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
