"""Circle non-maximum suppression in numpy: of detections whose bird's-eye centres lie closer than a
radius, the best-scored one stays (CenterPoint's rule; no box overlap needed, so it is cheap)."""

from __future__ import annotations

import numpy as np


def circle_nms(centers_xy: np.ndarray, scores: np.ndarray, radius_m: float) -> np.ndarray:
    """Indices of the kept detections, best score first (ties: the earlier index)."""
    centers_xy = np.asarray(centers_xy, np.float64).reshape(-1, 2)
    order = np.argsort(-np.asarray(scores, np.float64), kind="stable")
    keep: list[int] = []
    suppressed = np.zeros(len(order), bool)
    r2 = radius_m * radius_m
    for rank, i in enumerate(order):
        if suppressed[rank]:
            continue
        keep.append(int(i))
        rest = order[rank + 1:]
        d2 = ((centers_xy[rest] - centers_xy[i]) ** 2).sum(axis=1)
        suppressed[rank + 1:] |= d2 < r2
    return np.asarray(keep, np.int64)
