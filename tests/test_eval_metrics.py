"""Evaluation metrics on hand-built cases with known answers: rotated-box IoU, AP, the area, the
prediction validator, segmentation IoU. No episodes: fast."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from cosim.eval.ap import DetectionAccumulator, match_frame, voc_ap
from cosim.eval.boxes import footprints, iou_matrix
from cosim.eval.dataset import FrameTruth
from cosim.eval.evaluate import EvalOptions, EvalResult, SegAccumulator, _score_frame
from cosim.eval.predictions import (
    PredictionError,
    parse_record,
    prediction_files,
    read_predictions,
    record_json,
    write_prediction_lines,
)
from cosim.traffic.metrics import convex_overlap_area
from tests.helpers import run_cli


def box(x=0.0, y=0.0, length=4.0, width=2.0, yaw=0.0) -> np.ndarray:
    return footprints(np.array([[x, y]]), np.array([[length, width]]), np.array([yaw]))


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float(iou_matrix(a, b)[0, 0])


# ------------------------------------------------------------------------------------------ IoU


def test_unit_squares_rotated_45_degrees_overlap_in_a_regular_octagon():
    # the octagon cuts four corner triangles of legs (sqrt(2)/2 - 1/2) * sqrt(2) from the unit square:
    # intersection 2 (sqrt(2) - 1), union 4 - 2 sqrt(2), IoU = 1 / sqrt(2)
    a, b = box(length=1, width=1), box(length=1, width=1, yaw=math.pi / 4)
    inter = convex_overlap_area(a[0], b[0])
    assert inter == pytest.approx(2 * (math.sqrt(2) - 1), abs=1e-12)
    assert iou(a, b) == pytest.approx(1 / math.sqrt(2), abs=1e-12)


@pytest.mark.parametrize("d", [0.0, 0.5, 1.0, 12 / 7, 3.9])
def test_box_shifted_along_its_length(d):
    yaw = 0.7  # any heading: the shift is along the box's own axis
    a = box(length=4.0, yaw=yaw)
    b = box(x=d * math.cos(yaw), y=d * math.sin(yaw), length=4.0, yaw=yaw)
    assert iou(a, b) == pytest.approx((4 - d) / (4 + d), abs=1e-12)


def test_rectangle_and_its_quarter_turn_and_disjoint_boxes():
    assert iou(box(length=4, width=2), box(length=4, width=2, yaw=math.pi / 2)) == pytest.approx(4 / 12)
    assert iou(box(), box(yaw=math.pi)) == pytest.approx(1.0)
    assert iou(box(), box(x=10)) == 0.0
    assert iou(box(), box(x=4.0)) == pytest.approx(0.0, abs=1e-12)  # touching edges


def test_iou_agrees_with_a_fine_raster_on_random_boxes():
    rng = np.random.default_rng(1)
    xs = np.linspace(-5, 5, 1001)
    gx, gy = np.meshgrid(xs, xs)
    pts = np.stack([gx.ravel(), gy.ravel()], axis=1)

    def inside(fp):
        edges = np.roll(fp, -1, axis=0) - fp
        rel = pts[:, None, :] - fp[None, :, :]
        return ((edges[None, :, 0] * rel[..., 1] - edges[None, :, 1] * rel[..., 0]) >= 0).all(axis=1)

    for _ in range(4):
        a = box(*rng.uniform(-1, 1, 2), *rng.uniform(1, 4, 2), rng.uniform(-math.pi, math.pi))
        b = box(*rng.uniform(-1, 1, 2), *rng.uniform(1, 4, 2), rng.uniform(-math.pi, math.pi))
        ia, ib = inside(a[0]), inside(b[0])
        raster = np.count_nonzero(ia & ib) / np.count_nonzero(ia | ib)
        assert iou(a, b) == pytest.approx(raster, abs=0.01)


# ------------------------------------------------------------------------------------------- AP


def _ap(frames, thr=0.5, frame_order=False):
    acc = DetectionAccumulator((0.3, 0.5, 0.7))
    for det, scores, gt in frames:
        acc.add(det, scores, gt)
    return acc.result(thr, frame_order=frame_order).ap


def _stack(*boxes):
    return np.concatenate(boxes) if boxes else np.zeros((0, 4, 2))


def test_perfect_predictions_give_ap_one_at_every_threshold():
    gt = _stack(box(0, 0), box(10, 3, yaw=1.0), box(-20, -5, 1.8, 0.7, 2.0))
    for thr in (0.3, 0.5, 0.7):
        assert _ap([(gt, np.array([0.9, 0.8, 0.7]), gt)], thr) == pytest.approx(1.0)


def test_a_box_with_iou_04_counts_at_03_and_not_at_05():
    d = 4.0 * 3 / 7  # (4 - d) / (4 + d) = 0.4
    det, gt = box(d, 0), box(0, 0)
    assert iou(det, gt) == pytest.approx(0.4)
    assert _ap([(det, np.array([0.9]), gt)], 0.3) == pytest.approx(1.0)
    assert _ap([(det, np.array([0.9]), gt)], 0.5) == 0.0


def test_the_operating_point_is_the_deepest_score_cut_within_the_false_positive_budget():
    gt = _stack(box(0, 0), box(10, 0), box(20, 0), box(30, 0))
    # ranked: true 0.9, false 0.8, true 0.7, false 0.6, true 0.5 (boxes at 0, 10 and 20 found; 30 never)
    det = _stack(box(0, 0), box(0, 40), box(10, 0), box(0, 60), box(20, 0))
    acc = DetectionAccumulator((0.3, 0.5, 0.7))
    acc.add(det, np.array([0.9, 0.8, 0.7, 0.6, 0.5]), gt)
    assert acc.operating_point(0.3, 0) == (0.25, 0.9)
    assert acc.operating_point(0.3, 1) == (0.5, 0.7)
    assert acc.operating_point(0.3, 2) == (0.75, 0.5)
    assert acc.operating_point(0.3, 10) == (0.75, 0.5)
    # a cut never parts equal scores: a false and a true detection tied at 0.7 go in together or not at all
    tied = DetectionAccumulator((0.3,))
    tied.add(det[[0, 1, 2]], np.array([0.9, 0.7, 0.7]), gt)
    assert tied.operating_point(0.3, 0) == (0.25, 0.9)
    assert tied.operating_point(0.3, 1) == (0.5, 0.7)
    # the best detection false and no budget: nothing kept; no ground truth: no recall
    first_false = DetectionAccumulator((0.3,))
    first_false.add(det[[1, 0]], np.array([0.9, 0.8]), gt)
    assert first_false.operating_point(0.3, 0) == (0.0, math.inf)
    empty = DetectionAccumulator((0.3,))
    empty.add(det[:1], np.array([0.9]), np.zeros((0, 4, 2)))
    r, cut = empty.operating_point(0.3, 1)
    assert r != r and cut == math.inf


def test_duplicates_are_false_positives():
    gt = _stack(box(0, 0), box(20, 0))
    det = _stack(box(0, 0), box(0.1, 0), box(20, 0))
    scores, tps = match_frame(det, np.array([0.9, 0.8, 0.7]), gt)
    assert scores.tolist() == [0.9, 0.8, 0.7]
    assert tps[0.5].tolist() == [True, False, True]
    # recall 0.5, 0.5, 1 at precision 1, 1/2, 2/3: AP = 0.5 * 1 + 0.5 * 2/3
    assert _ap([(det, np.array([0.9, 0.8, 0.7]), gt)]) == pytest.approx(0.5 + 0.5 * 2 / 3)


def test_matching_takes_detections_by_score_and_the_best_free_ground_truth():
    gt = _stack(box(0, 0), box(1.0, 0))
    det = _stack(box(0.9, 0), box(0.05, 0))
    # the higher-scored detection takes the ground truth it overlaps most (the one at x=1)
    _, tps = match_frame(det, np.array([0.2, 0.9]), gt)
    assert tps[0.5].tolist() == [True, True]


def test_scores_order_the_precision_recall_curve_across_frames():
    gt, hit, miss = box(0, 0), box(0, 0), box(50, 0)
    frames_fp_first = [(miss, np.array([0.9]), np.zeros((0, 4, 2))), (hit, np.array([0.1]), gt)]
    frames_tp_first = [(miss, np.array([0.1]), np.zeros((0, 4, 2))), (hit, np.array([0.9]), gt)]
    assert _ap(frames_fp_first) == pytest.approx(0.5)  # the false positive ranks first
    assert _ap(frames_tp_first) == pytest.approx(1.0)
    # the release concatenates frames in their order: scores across frames do not matter, order does
    assert _ap(frames_tp_first, frame_order=True) == pytest.approx(0.5)
    assert _ap(frames_tp_first[::-1], frame_order=True) == pytest.approx(1.0)


def test_empty_predictions_give_ap_zero_and_no_ground_truth_gives_nan():
    assert _ap([(np.zeros((0, 4, 2)), np.zeros(0), box())]) == 0.0
    assert math.isnan(_ap([(box(), np.array([0.5]), np.zeros((0, 4, 2)))]))


def test_voc_ap_interpolates_precision_from_the_right():
    # precision 1 at recall 0.25, 0.5 at 0.5, 0.75 at 0.75 (higher later): interpolated 1, 0.75, 0.75
    assert voc_ap(np.array([0.25, 0.5, 0.75]), np.array([1.0, 0.5, 0.75])) == pytest.approx(
        0.25 * 1 + 0.25 * 0.75 + 0.25 * 0.75)


# ------------------------------------------------------------------------ area and frame scoring


def _truth(centers, classes, sizes=None, release=None) -> FrameTruth:
    c = np.asarray(centers, float)
    s = np.asarray(sizes if sizes is not None else [[4.0, 2.0, 1.5]] * len(c), float)
    in_area = (np.abs(c[:, 0]) <= 140.8) & (np.abs(c[:, 1]) <= 40)
    return FrameTruth("ep", 0, "vehicle_0", np.arange(1, len(c) + 1), tuple(classes), c, s, np.zeros(len(c)),
                      in_area, in_area if release is None else np.asarray(release), None, None, np.eye(4))


def _pred(boxes):
    return parse_record({"episode": "ep", "tick": 0, "ego": "vehicle_0", "boxes": boxes}, _PATH, 1)


_PATH = __import__("pathlib").Path("preds.jsonl")


def _b(x, y, cls="car", score=0.9, length=4.0):
    return {"center_m": [x, y, 0.0], "size_m": [length, 2.0, 1.5], "yaw_rad": 0.0, "class": cls, "score": score}


def test_objects_and_detections_outside_the_area_are_ignored():
    truth = _truth([[10, 0, 0], [150, 0, 0], [0, 45, 0]], ["car", "car", "truck"])
    frame = _score_frame(_pred([_b(10, 0), _b(150, 0, score=0.95), _b(-141, 0, score=0.99)]), truth,
                         EvalOptions(), set(), None)
    r = frame.detection["vehicle"].result(0.5)
    assert (r.n_gt, r.n_det, r.ap) == (1, 1, pytest.approx(1.0))


def test_vehicle_group_pools_classes_and_per_class_results_use_names():
    truth = _truth([[10, 0, 0], [30, 0, 0], [50, 0, 0]], ["car", "truck", "drone"])
    frame = _score_frame(_pred([_b(10, 0, "car"), _b(30, 0, "car")]), truth, EvalOptions(), set(), None)
    assert frame.detection["vehicle"].result(0.5).ap == pytest.approx(1.0)  # class-agnostic within vehicles
    assert frame.detection["vehicle"].result(0.5).n_gt == 2  # the drone is not a vehicle class
    assert frame.detection["car"].result(0.5).n_tp == 1  # the truck labelled car is a car false positive
    assert frame.detection["truck"].result(0.5).ap == 0.0
    assert frame.detection["drone"].result(0.5).n_gt == 1


def test_release_mode_uses_the_corner_and_z_band_rule():
    truth = _truth([[10, 0, 0], [20, 0, 0]], ["car", "bus"], release=[True, False])
    pred = _pred([_b(10, 0, score=0.5), _b(20, 0, score=0.9)])
    default = _score_frame(pred, truth, EvalOptions(), set(), None).detection["vehicle"].result(0.5)
    release = _score_frame(pred, truth, EvalOptions(compat="airv2x"), set(), None).detection["vehicle"].result(0.5)
    assert (default.n_gt, default.n_tp, default.ap) == (2, 2, pytest.approx(1.0))
    # the bus is dropped from the ground truth, so its (higher-scored) detection is a false positive
    assert (release.n_gt, release.n_tp, release.ap) == (1, 1, pytest.approx(0.5))


def test_no_ground_truth_is_na_by_default_and_zero_in_release_mode():
    truth = _truth([[300, 0, 0]], ["car"])  # outside the area: no ground truth in the frame
    for options, expected in ((EvalOptions(), None), (EvalOptions(compat="airv2x"), 0.0)):
        cell = _score_frame(_pred([_b(10, 0)]), truth, options, set(), None)
        result = EvalResult({("all", "overall", "all"): cell}, options, ["vehicle"], 1, 1, 0)
        ap = result.metrics("all")["detection"]["vehicle"]["AP50"]
        assert math.isnan(ap) if expected is None else ap == expected


# ----------------------------------------------------------------------------------- segmentation


def test_segmentation_iou_sums_over_frames_and_the_release_averages_frames_with_absent_as_one():
    acc = SegAccumulator()
    gt1, pr1 = np.zeros((4, 4), bool), np.zeros((4, 4), bool)
    gt1[0, :2] = True
    pr1[0, :1] = True  # IoU 1/2
    gt2, pr2 = np.zeros((4, 4), bool), np.zeros((4, 4), bool)  # absent from both
    acc.add("car", pr1, gt1)
    acc.add("car", pr2, gt2)
    assert acc.ious(release=False)["car"] == pytest.approx(0.5)
    assert acc.ious(release=True)["car"] == pytest.approx((0.5 + 1.0) / 2)


# -------------------------------------------------------------------------------------- validator


@pytest.mark.parametrize(
    ("line", "field"),
    [
        ('{"episode": "e", "tick": 0, "ego": "vehicle_0"}', "boxes: missing"),
        ('{"episode": "e", "tick": -1, "ego": "vehicle_0", "boxes": []}', "tick:"),
        ('{"episode": "e", "tick": 0, "ego": "vehicle_0", "boxes": [], "agents": "cars"}', "agents:"),
        ('{"episode": "e", "tick": 0, "ego": "vehicle_0", "boxes": [], "colour": 1}', "colour: unknown key"),
        ('{"episode": "e", "tick": 0, "ego": "vehicle_0", "boxes": [{"center_m": [1, 2], "size_m": [4, 2, 1.5], '
         '"yaw_rad": 0, "class": "car", "score": 0.5}]}', "boxes[0].center_m:"),
        ('{"episode": "e", "tick": 0, "ego": "vehicle_0", "boxes": [{"center_m": [1, 2, 0], "size_m": [4, 0, 1.5], '
         '"yaw_rad": 0, "class": "car", "score": 0.5}]}', "boxes[0].size_m: must be > 0"),
        ('{"episode": "e", "tick": 0, "ego": "vehicle_0", "boxes": [{"center_m": [1, 2, 0], "size_m": [4, 2, 1.5], '
         '"yaw_rad": 0, "class": "car", "score": "high"}]}', "boxes[0].score:"),
        ('{"episode": "e", "tick": 0, "ego": "vehicle_0", "boxes": [{"center_m": [1, 2, 0], "size_m": [4, 2, 1.5], '
         '"yaw_rad": 0, "class": "car"}]}', "boxes[0].score: missing"),
        ('{"episode": "e", "tick": 0, ', "not valid JSON"),
    ],
)
def test_validator_names_file_line_and_field(tmp_path, line, field):
    good = json.dumps({"episode": "e", "tick": 0, "ego": "vehicle_1", "boxes": []})
    f = tmp_path / "p.jsonl"
    f.write_text(good + "\n\n" + line + "\n")
    with pytest.raises(PredictionError) as err:
        read_predictions(f)
    assert str(err.value).startswith(f"{f}:3: ")
    assert field in str(err.value)


def test_validator_refuses_a_second_record_for_the_same_frame(tmp_path):
    rec = json.dumps({"episode": "e", "tick": 0, "ego": "vehicle_0", "boxes": []})
    (tmp_path / "a.jsonl").write_text(rec + "\n")
    (tmp_path / "b.jsonl").write_text(rec + "\n")
    with pytest.raises(PredictionError, match=r"b\.jsonl:1: second record .* \(first at .*a\.jsonl:1\)"):
        read_predictions(tmp_path)


def test_cli_exits_2_with_one_message_on_malformed_predictions(tmp_path):
    f = tmp_path / "bad.jsonl"
    f.write_text('{"episode": "e", "tick": 0, "ego": "vehicle_0", "boxes": [{"center_m": [0, 0, 0], '
                 '"size_m": [4, 2, 1], "yaw_rad": "north", "class": "car", "score": 1}]}\n')
    (tmp_path / "gt").mkdir()  # exists (the argument check passes); the predictions are read before it is
    r = run_cli("eval", "--gt", str(tmp_path / "gt"), "--pred", str(f), "--out", str(tmp_path / "o"))
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [f"cosim: error: {f}:1: boxes[0].yaw_rad: must be a finite number "
                                             "[rad], got 'north'"]
    assert not (tmp_path / "o").exists()


def test_a_prediction_file_is_written_whole_or_not_at_all(tmp_path, monkeypatch):
    lines = [record_json("ep", k, "vehicle_0", "ego", np.zeros((1, 3)), np.ones((1, 3)), np.zeros(1), ["car"],
                         np.array([0.5])) for k in range(3)]
    out = write_prediction_lines(tmp_path / "runs" / "pred.jsonl", lines)
    assert [r.tick for r in read_predictions(out)] == [0, 1, 2]
    assert sorted(p.name for p in out.parent.iterdir()) == ["pred.jsonl"]  # no partial file left
    # killed before the rename: the old file stays as it was, and the partial one is no prediction file
    def killed(self, target):
        raise KeyboardInterrupt

    monkeypatch.setattr(type(out), "replace", killed)
    with pytest.raises(KeyboardInterrupt):
        write_prediction_lines(out, lines[:1])
    assert len(read_predictions(out)) == 3
    assert prediction_files(out.parent) == [out] and (out.parent / ".pred.jsonl.partial").is_file()
