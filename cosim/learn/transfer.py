"""``cosim learn transfer``: how detectors transfer to real scans (docs/realism.md).

Given runs by name (``--run cosim=RUN --run real=RUN --run finetuned=RUN``, a name given again for each seed)
and KITTI-layout folders (``--kitti DIR``, several), each run's model detects on each folder's scans and is
scored as ``cosim learn score`` scores (:func:`cosim.learn.kitti.score_source`): recall at score >= 0.3 by range
band (0-20, 20-40, 40-60 m), false positives per frame, BEV AP30 / AP50 / AP70 (cosim eval's definition)
within the range asked, and the recall at 1 false positive per frame with the score cut that gives it, over the
vehicles with >= 5 points in the front camera's view. Per folder and name: the mean over the seeds and their
spread (lowest to highest). Writes ``transfer.md`` and ``transfer.json``
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
from cosim.learn.kitti import (
    OPERATING_RECALL,
    OPERATING_SCORE,
    ScoreOptions,
    box_point_counts,
    in_view,
    options_dict,
    points_in_box,
    predict_source,
    score_source,
    score_title,
    with_class_names,
)

#: The summary columns of the report, in order (keys of :meth:`cosim.learn.kitti.KittiScore.summary`).
REPORT_COLUMNS = ("recall 0-20 m", "recall 20-40 m", "recall 40-60 m", "false positives per frame", "AP30", "AP50",
                  "AP70", OPERATING_RECALL, OPERATING_SCORE)


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
    from cosim.learn.train import load_run

    keep: dict[str, list] = {}
    per_run: list[dict[str, Any]] = []
    for name, run in runs:
        model, setup, ckpt = load_run(run, device)
        if setup.fusion != "none":
            raise InputError(f"--run {name}={run}: a model of fusion {setup.fusion}; real scans need fusion none")
        for k, s in enumerate(sources):
            t0 = time.perf_counter()
            preds = with_class_names(predict_source(model, setup, s, device), setup.classes)
            frames: list = []
            summary = score_source(s, preds, o, keep=frames).summary()
            if picture is not None and k == 0 and name not in keep:
                keep[name] = frames
            per_run.append({"name": name, "run": str(run), "folder": s.id, "step": int(ckpt.get("step", 0)),
                            "model_height_m": setup.lidar_height_m, "folder_height_m": s.height_m, **summary,
                            "errors": errors(frames, s, o)})
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
            folder["names"][n] = {"seeds": len(mine), **{c: spread([r[c] for r in mine]) for c in cols},
                                  "errors": _error_counts([r["errors"] for r in mine])}
        folders.append(folder)
    report = {"options": options_dict(o), "runs": per_run, "folders": folders, "names": names}
    if picture is not None and keep:
        draw(keep, sources[0], o, picture, picture_scans)
        report["picture"] = str(picture)
    return report


#: What a false positive stands on: the top of the scan's points in its footprint [m above the road] (up to
#: :data:`COLUMN_TOP_M`), in these bands; "empty" when fewer than :data:`EMPTY_POINTS` points are there.
TOP_BANDS_M = ((0.0, 1.0), (1.0, 2.2), (2.2, COLUMN_TOP_M := 6.0))
EMPTY_POINTS = 5
NEAR_M = 2.0  # [m] a missed vehicle's best score is that of the best detection centred this close to it


def errors(frames: list, source: Any, o: Any) -> dict[str, list[dict[str, Any]]]:
    """Where one run's errors are on a folder, from :func:`cosim.learn.kitti.score_source`'s kept frames:
    every false positive at score >= ``o.min_score`` within ``o.max_range_m`` (scan, centre, range, score,
    points in its footprint above the road's lowest 0.15 m and their top above the road, the best BEV IoU
    with a scored vehicle: above 0, a misplaced box rather than background) and every missed scored vehicle
    within the range (scan, centre, range, its points, the best score of a detection centred within
    :data:`NEAR_M`)."""
    from cosim.eval.boxes import footprints, iou_matrix

    fps, missed = [], []
    for stem, fs in frames:
        pts = source.frame(stem).points[:, :3].astype(np.float64)
        strong = (fs.det_scores >= o.min_score) & ~fs.det_tp & (np.hypot(fs.det[:, 0], fs.det[:, 1]) <= o.max_range_m)
        gt_fp = footprints(fs.gt[:, :2], fs.gt[:, 3:5], fs.gt[:, 6])
        for b, score in zip(fs.det[strong], fs.det_scores[strong], strict=True):
            column = b.copy()
            column[2], column[5] = COLUMN_TOP_M / 2 - source.height_m, COLUMN_TOP_M  # the road to 6 m up
            inside = points_in_box(pts, column, margin_m=0.0)
            iou = float(iou_matrix(footprints(b[None, :2], b[None, 3:5], b[None, 6]), gt_fp).max()) if len(gt_fp) \
                else 0.0
            fps.append({"scan": stem, "x_m": round(float(b[0]), 2), "y_m": round(float(b[1]), 2),
                        "range_m": round(float(np.hypot(b[0], b[1])), 2), "score": round(float(score), 3),
                        "points": int(inside.sum()),
                        "top_m": round(float(pts[inside, 2].max() + source.height_m), 2) if inside.any() else None,
                        "iou_with_a_vehicle": round(iou, 3)})
        counts = box_point_counts(pts, fs.gt) if len(fs.gt) else np.zeros(0, np.int64)
        for g, n, found, r in zip(fs.gt, counts, fs.found, fs.gt_range_m, strict=True):
            if found or r > o.max_range_m:
                continue
            near = np.hypot(fs.det[:, 0] - g[0], fs.det[:, 1] - g[1]) <= NEAR_M
            missed.append({"scan": stem, "x_m": round(float(g[0]), 2), "y_m": round(float(g[1]), 2),
                           "range_m": round(float(r), 2), "points": int(n),
                           "best_score_near": round(float(fs.det_scores[near].max()), 3) if near.any() else 0.0})
    return {"false_positives": fps, "missed": missed}


def error_kind(fp: dict[str, Any]) -> str:
    """A false positive's kind: on a vehicle (a misplaced box), empty, or by the top of what it stands on."""
    if fp["iou_with_a_vehicle"] > 0:
        return "on a vehicle (misplaced)"
    if fp["points"] < EMPTY_POINTS:
        return "empty"
    return next(f"top {lo:g}-{hi:g} m" for lo, hi in TOP_BANDS_M if fp["top_m"] < hi or hi == TOP_BANDS_M[-1][1])


ERROR_KINDS = ("on a vehicle (misplaced)", "empty", *(f"top {lo:g}-{hi:g} m" for lo, hi in TOP_BANDS_M))


def _error_counts(per_seed: list[dict[str, list]]) -> dict[str, Any]:
    """False positives per frame-folder by kind and range band, and missed vehicles by range band and by
    whether a detection under the cut stood near them, summed over the seeds (and their number)."""
    fp_kind = {k: 0 for k in ERROR_KINDS}
    fp_band: dict[str, int] = {}
    miss_band: dict[str, int] = {}
    miss_near = 0
    for e in per_seed:
        for fp in e["false_positives"]:
            fp_kind[error_kind(fp)] += 1
            b = _band_10m(fp["range_m"])
            fp_band[b] = fp_band.get(b, 0) + 1
        for m in e["missed"]:
            b = _band_10m(m["range_m"])
            miss_band[b] = miss_band.get(b, 0) + 1
            miss_near += m["best_score_near"] > 0.05

    def key(band: str) -> int:
        return int(band.split("-")[0])

    return {"seeds": len(per_seed), "false positives by kind": fp_kind,
            "false positives by range": {b: fp_band[b] for b in sorted(fp_band, key=key)},
            "missed by range": {b: miss_band[b] for b in sorted(miss_band, key=key)},
            "missed with a detection near (score > 0.05)": int(miss_near),
            "missed": sum(len(e["missed"]) for e in per_seed)}


def _band_10m(range_m: float) -> str:
    """The 10 m range band of a distance, as "20-30 m"."""
    lo = int(range_m // 10) * 10
    return f"{lo}-{lo + 10} m"


def _fmt(s: dict[str, float], pct: bool = False) -> str:
    if s["n"] == 0:
        return "-"
    f = (lambda v: f"{v:.1f}") if pct else (lambda v: f"{v:.2f}")
    return f(s["mean"]) if s["n"] == 1 or s["min"] == s["max"] else f"{f(s['mean'])} ({f(s['min'])}-{f(s['max'])})"


def markdown(report: dict[str, Any]) -> str:
    """The report as markdown: one table per folder, a row per name (mean over its seeds, lowest-highest)."""
    opts = report["options"]
    o = ScoreOptions(fov=opts["fov"], max_range_m=opts["max_range_m"], min_points=opts["min_points"],
                     min_score=opts["min_score"], iou=opts["iou"], det_classes=opts.get("det_classes", "types"))
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
        lines += ["", f"Where the errors are (summed over the seeds): false positives at score >= {o.min_score:g} "
                      f"by what stands in their footprint (the top of the scan's points there), and missed vehicles.",
                  "", "| model | seeds | " + " | ".join(f"false: {k}" for k in ERROR_KINDS)
                  + " | false by range | missed | missed by range | missed with a detection near |",
                  "|---|---:" + "|---:" * len(ERROR_KINDS) + "|---|---:|---|---:|"]
        for n, row in f["names"].items():
            e = row["errors"]

            def bands(d: dict[str, int]) -> str:
                return ", ".join(f"{b}: {v}" for b, v in d.items()) or "-"

            lines.append(f"| {n} | {e['seeds']} | " + " | ".join(str(e["false positives by kind"][k])
                                                               for k in ERROR_KINDS)
                         + f" | {bands(e['false positives by range'])} | {e['missed']} | "
                           f"{bands(e['missed by range'])} | {e['missed with a detection near (score > 0.05)']} |")
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
