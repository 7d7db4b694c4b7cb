"""``cosim learn recall``: where collaboration helps a trained detector. For each prediction file (one setting
of ``cosim learn predict``), the vehicles in the ego's evaluation area that the ego has no LiDAR return on
(``/<ego>/visibility``), how many of them the setting's agents see, and how many the model finds (a
prediction of at least ``min_score`` matched one-to-one, best score first, at BEV IoU >= ``iou``), beside the
same for the objects the ego does see. No torch."""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from cosim.errors import InputError
from cosim.eval.boxes import footprints, iou_matrix
from cosim.eval.dataset import VEHICLE_CLASSES, EpisodeRef, iter_truth, require_visibility
from cosim.eval.predictions import read_predictions

COLUMNS = ("predictions", "agents", "frames", "ego-blind", "ego-blind seen by setting", "found (ego-blind)",
           "recall ego-blind %", "recall ego-blind seen %", "ego-seen", "found (ego-seen)", "recall ego-seen %")


def recall_rows(refs: list[EpisodeRef], files: list[Path], iou: float = 0.3, min_score: float = 0.3
                ) -> list[dict[str, Any]]:
    """One row per prediction file (columns :data:`COLUMNS`)."""
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
    counts: dict[Path, dict[str, int]] = {f: defaultdict(int) for f in files}
    wanted = {k for by_key, _a in preds.values() for k in by_key}
    for ref in refs:
        ticks = {k[1] for k in wanted if k[0] == ref.id}
        if not ticks:
            continue
        for truth in iter_truth(ref, ticks=ticks):
            seen = require_visibility(truth, "cosim learn recall")
            veh = np.isin(np.asarray(truth.classes), VEHICLE_CLASSES) & truth.in_area
            ego_sees = truth.seen_by_agent[truth.ego]
            gt_fp = truth.footprints()
            for f, (by_key, setting) in preds.items():
                rec = by_key.get((truth.episode, truth.tick, truth.ego))
                if rec is None:
                    continue
                c = counts[f]
                c["frames"] += 1
                keep = rec.scores >= min_score
                det_cls = np.asarray(rec.classes)
                keep &= np.isin(det_cls, VEHICLE_CLASSES) if len(det_cls) else keep
                det_fp = footprints(rec.centers_m[keep, :2], rec.sizes_m[keep, :2], rec.yaws_rad[keep])
                found = _found(det_fp, rec.scores[keep], gt_fp[veh], iou)
                blind = ~ego_sees[veh]
                c["ego-blind"] += int(blind.sum())
                c["ego-blind seen by setting"] += int((blind & seen[setting][veh]).sum())
                c["found (ego-blind)"] += int((found & blind).sum())
                c["found (ego-blind seen)"] += int((found & blind & seen[setting][veh]).sum())
                c["ego-seen"] += int((~blind).sum())
                c["found (ego-seen)"] += int((found & ~blind).sum())
    rows = []
    for f in files:
        c = counts[f]

        def pct(a: str, b: str, c: dict[str, int] = c) -> float:
            return round(100.0 * c[a] / c[b], 1) if c[b] else float("nan")

        rows.append({"predictions": f.name, "agents": preds[f][1], "frames": c["frames"],
                     "ego-blind": c["ego-blind"], "ego-blind seen by setting": c["ego-blind seen by setting"],
                     "found (ego-blind)": c["found (ego-blind)"],
                     "recall ego-blind %": pct("found (ego-blind)", "ego-blind"),
                     "recall ego-blind seen %": pct("found (ego-blind seen)", "ego-blind seen by setting"),
                     "ego-seen": c["ego-seen"], "found (ego-seen)": c["found (ego-seen)"],
                     "recall ego-seen %": pct("found (ego-seen)", "ego-seen")})
    return rows


def _found(det_fp: np.ndarray, scores: np.ndarray, gt_fp: np.ndarray, iou: float) -> np.ndarray:
    """(M,) bool: ground-truth boxes matched one-to-one (best score first) at IoU >= ``iou``: the greedy rule
    of cosim eval's matching (cosim.eval.ap.match_frame)."""
    out = np.zeros(len(gt_fp), bool)
    if not len(det_fp) or not len(gt_fp):
        return out

    order = np.argsort(-scores, kind="stable")
    ious = iou_matrix(det_fp[order], gt_fp)
    for i in range(len(order)):
        cand = np.where(out, -1.0, ious[i])
        j = int(np.argmax(cand))
        if cand[j] >= iou:
            out[j] = True
    return out


def write_recall(rows: list[dict[str, Any]], out: Path, iou: float, min_score: float) -> tuple[Path, Path]:
    out.mkdir(parents=True, exist_ok=True)
    lines = [f"Objects in the ego's area with no ego LiDAR return, found by each model (prediction score >= "
             f"{min_score}, BEV IoU >= {iou})", "", "| " + " | ".join(COLUMNS) + " |",
             "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(str(r[c]) for c in COLUMNS) + " |" for r in rows]
    md = out / "recall.md"
    md.write_text("\n".join(lines) + "\n")
    js = out / "recall.json"
    js.write_text(json.dumps({"iou": iou, "min_score": min_score, "rows": rows}, indent=1) + "\n")
    return md, js
