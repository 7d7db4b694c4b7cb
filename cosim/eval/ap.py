"""Detection average precision as the collaborative-perception literature computes it.

Per frame, detections are taken in descending score order; each is a true positive when its best BEV
IoU with a still unmatched ground-truth box reaches the threshold (that box is then matched), a false
positive otherwise (so a duplicate of a matched box is a false positive). Over all frames, the
detections are sorted by score (globally, by default) and AP is the VOC all-point interpolated area
under the precision-recall curve: sum over recall steps of (step width) x (the highest precision at
that recall or beyond). This is the definition of OpenCOOD's ``eval_utils`` with its
``global_sort_detections`` switch on; ``frame_order=True`` reproduces the AirV2X release, which
concatenates the per-frame lists in frame order instead (AP then depends on the order of the frames).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cosim.eval.boxes import iou_matrix

THRESHOLDS: tuple[float, ...] = (0.3, 0.5, 0.7)


def match_frame(det_fp: np.ndarray, det_scores: np.ndarray, gt_fp: np.ndarray,
                thresholds: tuple[float, ...] = THRESHOLDS) -> tuple[np.ndarray, dict[float, np.ndarray]]:
    """Greedy matching of one frame's detections to its ground truth.

    ``det_fp`` (N, 4, 2) and ``gt_fp`` (M, 4, 2) footprints, ``det_scores`` (N,). Returns the
    scores in matching order (descending; ties keep the input order) and, per threshold, a bool
    array (N,) in that order: True for a true positive.
    """
    scores = np.asarray(det_scores, np.float64).reshape(-1)
    order = np.argsort(-scores, kind="stable")
    ious = iou_matrix(np.asarray(det_fp)[order], gt_fp) if len(order) else np.zeros((0, len(gt_fp)))
    out: dict[float, np.ndarray] = {}
    for thr in thresholds:
        tp = np.zeros(len(order), bool)
        free = np.ones(ious.shape[1], bool)
        for i in range(len(order)):
            if not free.any():
                break
            cand = np.where(free, ious[i], -1.0)
            j = int(np.argmax(cand))
            if cand[j] >= thr:
                tp[i] = True
                free[j] = False
        out[thr] = tp
    return scores[order], out


def voc_ap(recall: np.ndarray, precision: np.ndarray) -> float:
    """VOC all-point interpolated AP of a precision-recall curve (recall non-decreasing)."""
    mrec = np.concatenate([[0.0], recall, [1.0]])
    mpre = np.concatenate([[0.0], precision, [0.0]])
    mpre = np.maximum.accumulate(mpre[::-1])[::-1]
    steps = np.nonzero(mrec[1:] != mrec[:-1])[0]
    return float(np.sum((mrec[steps + 1] - mrec[steps]) * mpre[steps + 1]))


@dataclass(frozen=True)
class APResult:
    """AP at one threshold with its curve: ``recall``/``precision`` (K,) after each ranked detection."""

    threshold: float
    ap: float  # NaN when there is no ground truth
    n_gt: int
    n_det: int
    n_tp: int
    recall: np.ndarray
    precision: np.ndarray


@dataclass
class DetectionAccumulator:
    """True/false positives and ground-truth counts over many frames, for several IoU thresholds."""

    thresholds: tuple[float, ...] = THRESHOLDS
    n_gt: int = 0
    _scores: list[np.ndarray] = field(default_factory=list)
    _tp: dict[float, list[np.ndarray]] = field(default_factory=dict)

    def add(self, det_fp: np.ndarray, det_scores: np.ndarray, gt_fp: np.ndarray) -> None:
        """One frame: detections (N, 4, 2) with scores (N,) against ground truth (M, 4, 2)."""
        scores, tps = match_frame(det_fp, det_scores, gt_fp, self.thresholds)
        self.n_gt += len(gt_fp)
        self._scores.append(scores)
        for thr in self.thresholds:
            self._tp.setdefault(thr, []).append(tps[thr])

    def merge(self, other: DetectionAccumulator) -> None:
        """Add another accumulator's frames after this one's (same thresholds)."""
        self.n_gt += other.n_gt
        self._scores.extend(other._scores)
        for thr in self.thresholds:
            self._tp.setdefault(thr, []).extend(other._tp.get(thr, []))

    def result(self, threshold: float, frame_order: bool = False) -> APResult:
        """AP at ``threshold``; detections sorted globally by score unless ``frame_order``."""
        scores = np.concatenate(self._scores) if self._scores else np.zeros(0)
        tp = np.concatenate(self._tp.get(threshold, [])) if self._scores else np.zeros(0, bool)
        if not frame_order:
            order = np.argsort(-scores, kind="stable")  # ties keep frame order
            tp = tp[order]
        ctp = np.cumsum(tp)
        cfp = np.cumsum(~tp)
        if self.n_gt == 0:
            return APResult(threshold, float("nan"), 0, len(tp), int(ctp[-1]) if len(tp) else 0,
                            np.zeros(len(tp)), np.zeros(len(tp)))
        recall = ctp / self.n_gt
        precision = ctp / np.maximum(ctp + cfp, 1)
        return APResult(threshold, voc_ap(recall, precision), self.n_gt, len(tp),
                        int(ctp[-1]) if len(tp) else 0, recall, precision)

    def operating_point(self, threshold: float, max_false_positives: float) -> tuple[float, float]:
        """The recall at ``threshold`` (IoU) of the lowest score cut that keeps the false positives at or under
        ``max_false_positives`` (over all frames), and that cut (detections of at least that score are kept;
        inf when even the best one is false). A cut never parts detections of equal score. The point of the
        recall against false positives per frame curve that detection benchmarks quote (e.g. the miss rate at
        one false positive per image)."""
        scores = np.concatenate(self._scores) if self._scores else np.zeros(0)
        tp = np.concatenate(self._tp.get(threshold, [])) if self._scores else np.zeros(0, bool)
        order = np.argsort(-scores, kind="stable")
        scores, tp = scores[order], tp[order]
        last = np.r_[scores[1:] < scores[:-1], True] if len(scores) else np.zeros(0, bool)  # a cut may end here
        ok = last & (np.cumsum(~tp) <= max_false_positives)
        if not ok.any() or self.n_gt == 0:
            return (0.0 if self.n_gt else float("nan")), float("inf")
        k = int(np.flatnonzero(ok)[-1])
        return float(np.cumsum(tp)[k]) / self.n_gt, float(scores[k])
