"""``cosim learn recall``: where collaboration helps a trained detector. For each prediction file (one setting
of ``cosim learn predict``), the vehicles in the ego's evaluation area that the ego has no LiDAR return on
(``/<ego>/visibility``), how many of them the setting's agents see, and how many the model finds (a
prediction of at least ``min_score`` matched one-to-one, best score first, at BEV IoU >= ``iou``), beside the
same for the objects the ego does see; and how tight the found boxes are (:data:`ERROR_COLUMNS`: medians over
the found vehicles of the centre's error along and across the true box, of the length and width errors, of
the yaw error up to a half turn, and the share whose heading is off by more than a quarter turn). With ``by`` (a
condition of :data:`cosim.eval.dataset.CONDITIONS`), one row per file and value of that condition: where in the
data a kind of agent adds sight and finds. No torch."""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from cosim.errors import InputError
from cosim.eval.boxes import footprints, iou_matrix, wrap_angle
from cosim.eval.dataset import CONDITIONS, VEHICLE_CLASSES, EpisodeRef, iter_truth, require_visibility
from cosim.eval.predictions import read_predictions

COLUMNS = ("predictions", "agents", "frames", "ego-blind", "ego-blind seen by setting", "found (ego-blind)",
           "recall ego-blind %", "recall ego-blind seen %", "ego-seen", "found (ego-seen)", "recall ego-seen %")
ERROR_COLUMNS = ("predictions", "found", "along m", "across m", "length m", "width m", "yaw deg (mod 180)",
                 "heading flipped %")


def columns(names: tuple[str, ...], by: str | None) -> tuple[str, ...]:
    """``names`` with the condition ``by`` after the first (the file's name), when rows are split by it."""
    return names if by is None else (names[0], by, *names[1:])


def recall_rows(refs: list[EpisodeRef], files: list[Path], iou: float = 0.3, min_score: float = 0.3,
                by: str | None = None) -> list[dict[str, Any]]:
    """One row per prediction file (columns :data:`COLUMNS`, then :data:`ERROR_COLUMNS` after the first), or
    with ``by`` one per file and value of that episode condition (``columns(COLUMNS, by)``), values sorted."""
    if by is not None and by not in CONDITIONS:
        raise InputError(f"--by {by}: not a condition (one of {', '.join(CONDITIONS)})")
    preds = {}
    for f in files:
        recs = read_predictions(f)
        if not recs:
            raise InputError(f"{f}: no prediction records")
        agents = {r.agents for r in recs}
        if len(agents) != 1:
            raise InputError(f"{f}: records of several settings ({', '.join(sorted(agents))}): one file per setting")
        preds[f] = ({(r.episode, r.tick, r.ego): r for r in recs}, agents.pop())
    ids = {r.id for r in refs}
    for f, (by_key, _a) in preds.items():
        unknown = sorted({k[0] for k in by_key} - ids)
        if unknown:
            raise InputError(f"{f}: episode {unknown[0]} is not in the dataset's chosen split")
    counts: dict[tuple[Path, str], dict[str, int]] = defaultdict(lambda: defaultdict(int))
    errors: dict[tuple[Path, str], list[np.ndarray]] = defaultdict(list)
    wanted = {k for by_key, _a in preds.values() for k in by_key}
    for ref in refs:
        ticks = {k[1] for k in wanted if k[0] == ref.id}
        if not ticks:
            continue
        cell = "all" if by is None else ref.conditions.get(by, "-")
        for truth in iter_truth(ref, ticks=ticks):
            seen = require_visibility(truth, "cosim learn recall")
            veh = np.isin(np.asarray(truth.classes), VEHICLE_CLASSES) & truth.in_area
            ego_sees = truth.seen_by_agent[truth.ego]
            gt_fp = truth.footprints()
            for f, (by_key, setting) in preds.items():
                rec = by_key.get((truth.episode, truth.tick, truth.ego))
                if rec is None:
                    continue
                c = counts[f, cell]
                c["frames"] += 1
                keep = rec.scores >= min_score
                det_cls = np.asarray(rec.classes)
                keep &= np.isin(det_cls, VEHICLE_CLASSES) if len(det_cls) else keep
                det_fp = footprints(rec.centers_m[keep, :2], rec.sizes_m[keep, :2], rec.yaws_rad[keep])
                match = _matches(det_fp, rec.scores[keep], gt_fp[veh], iou)
                found = match >= 0
                hit, true = np.flatnonzero(keep)[match[found]], np.flatnonzero(veh)[found]
                errors[f, cell].append(box_errors(rec.centers_m[hit], rec.sizes_m[hit], rec.yaws_rad[hit],
                                                  truth.centers_m[true], truth.sizes_m[true], truth.yaws_rad[true]))
                blind = ~ego_sees[veh]
                c["ego-blind"] += int(blind.sum())
                c["ego-blind seen by setting"] += int((blind & seen[setting][veh]).sum())
                c["found (ego-blind)"] += int((found & blind).sum())
                c["found (ego-blind seen)"] += int((found & blind & seen[setting][veh]).sum())
                c["ego-seen"] += int((~blind).sum())
                c["found (ego-seen)"] += int((found & ~blind).sum())
    rows = []
    cells = ["all"] if by is None else sorted({cell for _f, cell in counts})
    for f in files:
        for cell in cells:
            rows.append(_row(f, preds[f][1], counts[f, cell], errors[f, cell])
                        | ({} if by is None else {by: cell}))
    return rows


def _row(f: Path, setting: str, c: dict[str, int], errors: list[np.ndarray]) -> dict[str, Any]:
    def pct(a: str, b: str) -> float:
        return round(100.0 * c[a] / c[b], 1) if c[b] else float("nan")

    return {"predictions": f.name, "agents": setting, "frames": c["frames"],
            "ego-blind": c["ego-blind"], "ego-blind seen by setting": c["ego-blind seen by setting"],
            "found (ego-blind)": c["found (ego-blind)"],
            "recall ego-blind %": pct("found (ego-blind)", "ego-blind"),
            "recall ego-blind seen %": pct("found (ego-blind seen)", "ego-blind seen by setting"),
            "ego-seen": c["ego-seen"], "found (ego-seen)": c["found (ego-seen)"],
            "recall ego-seen %": pct("found (ego-seen)", "ego-seen"),
            **error_summary(np.concatenate(errors) if errors else np.zeros((0, 6)))}


def box_errors(det_centers: np.ndarray, det_sizes: np.ndarray, det_yaws: np.ndarray, gt_centers: np.ndarray,
               gt_sizes: np.ndarray, gt_yaws: np.ndarray) -> np.ndarray:
    """(N, 6) errors of N matched boxes: the centre's error along and across the true box [m], length and
    width errors [m], the yaw error [rad]: signed in [-pi, pi) (the heading's), then folded to [0, pi/2]
    (the axis')."""
    d = det_centers[:, :2] - gt_centers[:, :2]
    c, s = np.cos(gt_yaws), np.sin(gt_yaws)
    turn = wrap_angle(det_yaws - gt_yaws)
    axis = np.abs(turn)
    axis = np.minimum(axis, np.pi - axis)
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], det_sizes[:, 0] - gt_sizes[:, 0],
                     det_sizes[:, 1] - gt_sizes[:, 1], turn, axis], axis=1).reshape(-1, 6)


def error_summary(err: np.ndarray) -> dict[str, Any]:
    """The :data:`ERROR_COLUMNS` (but the file's name) of :func:`box_errors` rows: medians of the absolute
    errors, and the share of headings off by more than a quarter turn."""
    if not len(err):
        return {k: float("nan") for k in ERROR_COLUMNS[2:]} | {"found": 0}
    med = np.median(np.abs(err), axis=0)
    return {"found": len(err), "along m": round(float(med[0]), 3), "across m": round(float(med[1]), 3),
            "length m": round(float(med[2]), 3), "width m": round(float(med[3]), 3),
            "yaw deg (mod 180)": round(float(np.degrees(med[5])), 1),
            "heading flipped %": round(100.0 * float(np.mean(np.abs(err[:, 4]) > np.pi / 2)), 1)}


def _matches(det_fp: np.ndarray, scores: np.ndarray, gt_fp: np.ndarray, iou: float) -> np.ndarray:
    """(M,) int: for each ground-truth box the detection (its index in ``det_fp``) matched to it one-to-one,
    best score first, at IoU >= ``iou`` (the greedy rule of cosim eval's matching, cosim.eval.ap.match_frame),
    or -1."""
    out = np.full(len(gt_fp), -1, np.int64)
    if not len(det_fp) or not len(gt_fp):
        return out
    order = np.argsort(-scores, kind="stable")
    ious = iou_matrix(det_fp[order], gt_fp)
    for i in range(len(order)):
        cand = np.where(out >= 0, -1.0, ious[i])
        j = int(np.argmax(cand))
        if cand[j] >= iou:
            out[j] = order[i]
    return out


def write_recall(rows: list[dict[str, Any]], out: Path, iou: float, min_score: float, by: str | None = None
                 ) -> tuple[Path, Path]:
    out.mkdir(parents=True, exist_ok=True)
    cols, error_cols = columns(COLUMNS, by), columns(ERROR_COLUMNS, by)
    lines = [f"Objects in the ego's area with no ego LiDAR return, found by each model (prediction score >= "
             f"{min_score}, BEV IoU >= {iou}){'' if by is None else ', by ' + by}", "",
             "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(str(r[c]) for c in cols) + " |" for r in rows]
    lines += ["", "How tight the found boxes are (the same matches; medians of absolute errors in the true box's "
              "frame)", "", "| " + " | ".join(error_cols) + " |", "|" + "---|" * len(error_cols)]
    lines += ["| " + " | ".join(str(r[c]) for c in error_cols) + " |" for r in rows]
    md = out / "recall.md"
    md.write_text("\n".join(lines) + "\n")
    js = out / "recall.json"
    js.write_text(json.dumps({"iou": iou, "min_score": min_score, "by": by, "rows": rows}, indent=1) + "\n")
    return md, js
