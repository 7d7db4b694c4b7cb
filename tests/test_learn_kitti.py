"""``cosim learn`` on KITTI-layout folders (cosim/learn/kitti.py, docs/realism.md "Scoring a model on real
scans"): small synthetic folders written here with cosim.io.kitti (a flat road at a known height, box-shaped
cars, labels in the rectified camera frame), trained a few steps, predicted and scored; the scoring's rules by
hand-counted cases; the height shift; --init; bad input."""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest

from cosim.errors import InputError
from cosim.eval.ap import DetectionAccumulator
from cosim.eval.boxes import footprints
from cosim.io.kitti import (
    KittiCalib,
    KittiObject,
    boxes_from_velo,
    dont_care,
    format_calib,
    format_label,
    write_velodyne,
)
from cosim.learn.kitti import (
    OPERATING_RECALL,
    OPERATING_SCORE,
    KittiSource,
    ScoreOptions,
    estimate_height_m,
    score_source,
)
from tests.helpers import cli_in_process

HAVE_TORCH = importlib.util.find_spec("torch") is not None  # not imported: collecting this file stays cheap
needs_torch = pytest.mark.skipif(not HAVE_TORCH, reason="PyTorch is not installed (pip install -e '.[learn]')")

HEIGHT_M = 1.73  # the synthetic sensor's height above the road
FOCAL_PX, CX_PX, CY_PX = 700.0, 620.0, 187.0  # image 2: 1242 px wide (no image_2: KITTI's usual width)
P2 = np.array([[FOCAL_PX, 0, CX_PX, 0], [0, FOCAL_PX, CY_PX, 0], [0, 0, 1, 0]], float)
CALIB = KittiCalib(P0=P2, P1=P2, P2=P2, P3=P2, R0_rect=np.eye(3),
                   Tr_velo_to_cam=np.array([[0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0]], float),
                   Tr_imu_to_velo=np.eye(3, 4))


def car(x: float, y: float, yaw: float = 0.0, size=(4.2, 1.8, 1.5)) -> np.ndarray:
    """A box (7,) standing on the road at (x, y)."""
    return np.array([x, y, -HEIGHT_M + size[2] / 2, *size, yaw])


def surface(box: np.ndarray, step_m: float = 0.15) -> np.ndarray:
    """Points (N, 3) on a box's four sides and top, above its lowest 0.2 m."""
    ln, w, h = box[3:6]
    pts = []
    for u in np.arange(-ln / 2, ln / 2 + 1e-9, step_m):
        for v in np.arange(-w / 2, w / 2 + 1e-9, step_m):
            pts.append((u, v, h / 2))
    for z in np.arange(-h / 2 + 0.2, h / 2, step_m):
        for u in np.arange(-ln / 2, ln / 2 + 1e-9, step_m):
            pts += [(u, w / 2, z), (u, -w / 2, z)]
        for v in np.arange(-w / 2, w / 2 + 1e-9, step_m):
            pts += [(ln / 2, v, z), (-ln / 2, v, z)]
    p = np.array(pts)
    c, s = math.cos(box[6]), math.sin(box[6])
    return np.c_[c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1], p[:, 2]] + box[:3]


def road(step_m: float = 0.5) -> np.ndarray:
    x, y = np.meshgrid(np.arange(-30, 60, step_m), np.arange(-30, 30, step_m))
    return np.c_[x.ravel(), y.ravel(), np.full(x.size, -HEIGHT_M)]


def label(kind: str, box: np.ndarray) -> KittiObject:
    loc, ry = boxes_from_velo(box[None], CALIB)
    return KittiObject(type=kind, truncated=0.0, occluded=0, alpha=0.0, bbox=(0, 0, 10, 10), h=box[5], w=box[4],
                       l=box[3], location=loc[0], rotation_y=float(ry[0]))


def write_scan(root: Path, stem: str, objects: list[tuple[str, np.ndarray, int | None]],
               dontcare: list[tuple[float, float, float, float]] = ()) -> None:
    """A scan of the road and the objects (type, box, points: None for a whole surface, else that many points
    at the box's centre), their labels and the calib."""
    for sub in ("velodyne", "label_2", "calib"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    clouds = [road()]
    for _kind, box, n in objects:
        clouds.append(surface(box) if n is None else np.repeat(box[None, :3], n, axis=0))
    xyz = np.concatenate(clouds)
    write_velodyne(root / "velodyne" / f"{stem}.bin", np.c_[xyz, np.full(len(xyz), 0.4)].astype(np.float32))
    lines = [format_label(label(k, b), 4) for k, b, _n in objects] + [format_label(dont_care(r)) for r in dontcare]
    (root / "label_2" / f"{stem}.txt").write_text("".join(line + "\n" for line in lines))
    (root / "calib" / f"{stem}.txt").write_text(format_calib(CALIB))


def small_folder(root: Path, scans: int = 4) -> Path:
    """``scans`` scans with two to three cars ahead each (and one behind)."""
    for k in range(scans):
        write_scan(root, f"{k:06d}", [("Car", car(10 + 3 * k, -3.0), None), ("Car", car(25, 4.0 - k, 0.3), None),
                                      ("Car", car(-12, 0.0), None)])
    return root


def project(xyz: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) in image 2 of velodyne points (N, 3)."""
    uv, _ = CALIB.rect_to_image(CALIB.velo_to_rect(xyz))
    return uv


# ------------------------------------------------------------------------------------------- scoring rules


A, B = car(15, 0), car(30, 2)  # in view, seen
BEHIND = car(-15, 0)
EDGE = car(20, 19.5)  # bearing 44.3 deg: in the front 90 deg, left of image 2
FEW = car(35, -5)  # three points only
PED = np.array([10, -3, -HEIGHT_M + 0.9, 0.6, 0.6, 1.8, 0.0])
DC_AT = car(25, -6)
FALSE = car(12, 8)


@pytest.fixture
def scored_folder(tmp_path) -> Path:
    u, v = project(DC_AT[None, :3])[0]
    write_scan(tmp_path / "k", "000007", [("Car", A, None), ("Car", B, None), ("Car", BEHIND, None),
                                          ("Car", EDGE, None), ("Car", FEW, 3), ("Pedestrian", PED, None)],
               dontcare=[(u - 30, v - 30, u + 30, v + 30)])
    return tmp_path / "k"


def _dets(*pairs):
    boxes = np.array([b for b, _s in pairs], float).reshape(-1, 7)
    return {7: (boxes, np.array([s for _b, s in pairs], float))}


def test_scoring_counts_the_camera_view_and_ignores_dontcare_other_types_and_sparse_cars(scored_folder):
    src = KittiSource(scored_folder, height_m=HEIGHT_M)
    assert abs(math.degrees(math.atan2(EDGE[1], EDGE[0]))) < 45 and project(EDGE[None, :3])[0, 0] < 0
    ped_det = car(PED[0], PED[1])
    preds = _dets((A, 0.9), (BEHIND, 0.8), (ped_det, 0.7), (DC_AT, 0.6), (FALSE, 0.5), (FEW, 0.4))
    s = score_source(src, preds, ScoreOptions()).summary()
    # in the camera's view with >= 5 points: A (found) and B (missed); BEHIND out of view, the pedestrian's and
    # the DontCare region's detections ignored, FEW under 5 points (its detection ignored): FALSE is the only false one
    assert (s["cars"], s["recall 0-20 m"], s["recall 20-40 m"], s["false positives"]) == (2, 1.0, 0.0, 1)
    ref = DetectionAccumulator()
    ref.add(footprints(np.array([A[:2], FALSE[:2]]), np.array([A[3:5], FALSE[3:5]]), np.array([0.0, 0.0])),
            np.array([0.9, 0.5]), footprints(np.array([A[:2], B[:2]]), np.array([A[3:5], B[3:5]]), np.zeros(2)))
    assert s["AP30"] == pytest.approx(100 * ref.result(0.3).ap) and s["AP30"] == pytest.approx(50.0)
    # one frame, a budget of one false positive: A and FALSE are both kept, A of the two labels found
    assert (s[OPERATING_RECALL], s[OPERATING_SCORE]) == (0.5, 0.5)

    front = score_source(src, preds, ScoreOptions(fov="front90")).summary()
    assert front["cars"] == 3 and front["recall 0-20 m"] == 1.0  # EDGE (27.9 m) joins: missed
    assert front["AP30"] == pytest.approx(100 / 3, abs=0.01)
    every = score_source(src, preds, ScoreOptions(fov="all")).summary()
    # as cosim eval: BEHIND is a car now, and found; nothing is left out: the pedestrian's, the DontCare one and
    # FEW's (under 5 points: no label) detections are false
    assert every["cars"] == 4 and every["false positives"] == 4
    sparse = score_source(src, preds, ScoreOptions(min_points=0)).summary()
    assert sparse["cars"] == 3 and sparse["recall 20-40 m"] == 0.5 and sparse["false positives"] == 1
    strict = score_source(src, preds, ScoreOptions(ignore=False)).summary()
    assert strict["false positives"] == 4  # the pedestrian's, the DontCare one, FEW's and FALSE
    none = score_source(src, _dets(), ScoreOptions()).summary()  # a frame without detections: all missed
    assert (none["cars"], none["recall 0-20 m"], none["false positives"], none["AP30"]) == (2, 0.0, 0, 0.0)
    near = score_source(src, preds, ScoreOptions(max_range_m=20)).summary()
    assert near["cars"] == 1 and near["AP30"] == pytest.approx(100.0)


def test_only_the_target_types_classes_detections_are_scored_as_kitti_scores_each_class(scored_folder):
    src = KittiSource(scored_folder, height_m=HEIGHT_M)
    bike = car(FALSE[0], FALSE[1], size=(1.8, 0.7, 1.7))
    boxes = np.array([A, FALSE, bike, B])
    named = {7: (boxes, np.array([0.9, 0.5, 0.6, 0.8]), np.array(["car", "van", "bicycle", "truck"], dtype=object))}
    types = score_source(src, named, ScoreOptions()).summary()
    # Car and Van are the targets: the bicycle and the truck (on B) detections are left out; FALSE (a van) is false
    assert (types["false positives"], types["recall 20-40 m"]) == (1, 0.0)
    every = score_source(src, named, ScoreOptions(det_classes="all")).summary()
    assert (every["false positives"], every["recall 20-40 m"]) == (2, 1.0)  # the bicycle is false, the truck finds B
    unnamed = score_source(src, {7: named[7][:2]}, ScoreOptions()).summary()  # no class names: every detection
    assert unnamed["false positives"] == every["false positives"] and unnamed["AP30"] == every["AP30"]
    cyclists = KittiSource(scored_folder, height_m=HEIGHT_M, types=("Car", "Van", "Truck", "Cyclist"))
    assert score_source(cyclists, named, ScoreOptions()).summary()["false positives"] == 2
    around = score_source(src, named, ScoreOptions(fov="all")).summary()  # cosim eval's rule: every class
    assert around["false positives"] == score_source(src, named, ScoreOptions(fov="all", det_classes="all")
                                                     ).summary()["false positives"]
    with pytest.raises(InputError, match="--det-classes some"):
        ScoreOptions(det_classes="some")


def test_the_reports_errors_say_where_false_positives_stand_and_what_was_near_the_missed(scored_folder):
    from cosim.learn.transfer import _error_counts, error_kind, errors

    src = KittiSource(scored_folder, height_m=HEIGHT_M)
    beside_a = car(A[0] + 2.5, A[1] + 0.5)  # overlaps A (IoU about 0.2): a misplaced box, not background
    near_b = car(B[0] + 1.0, B[1])  # under the score cut: B is missed, but something was there
    preds = _dets((A, 0.9), (beside_a, 0.6), (FALSE, 0.5), (near_b, 0.2))
    o = ScoreOptions()
    frames: list = []
    score_source(src, preds, o, keep=frames)
    e = errors(frames, src, o)
    fps = sorted(e["false_positives"], key=lambda f: -f["score"])
    assert [(f["scan"], f["score"]) for f in fps] == [("000007", 0.6), ("000007", 0.5)]
    assert fps[0]["iou_with_a_vehicle"] > 0 and error_kind(fps[0]) == "on a vehicle (misplaced)"
    # FALSE stands on bare road: the road's own points are under the footprint's lowest 0.15 m
    assert fps[1]["points"] == 0 and fps[1]["top_m"] is None and error_kind(fps[1]) == "empty"
    assert [(m["x_m"], m["best_score_near"]) for m in e["missed"]] == [(B[0], 0.2)]
    assert e["missed"][0]["points"] > 50  # a whole surface
    counts = _error_counts([e, e])
    assert counts["false positives by kind"]["empty"] == 2 and counts["missed"] == 2
    assert counts["false positives by range"] == {"10-20 m": 4}
    assert counts["missed by range"] == {"30-40 m": 2} and counts["missed with a detection near (score > 0.05)"] == 2
    stands = {"iou_with_a_vehicle": 0.0, "points": 40}
    assert [error_kind(stands | {"top_m": t}) for t in (0.5, 1.6, 2.2, 6.0)] == [
        "top 0-1 m", "top 1-2.2 m", "top 2.2-6 m", "top 2.2-6 m"]


def test_score_command_reads_prediction_files(scored_folder, tmp_path, capsys):
    from cosim.eval.predictions import record_json

    src = KittiSource(scored_folder, height_m=HEIGHT_M)
    pred = tmp_path / "p.jsonl"
    boxes = np.array([A, FALSE])
    pred.write_text(record_json(src.id, 7, "ego", "ego", boxes[:, :3], boxes[:, 3:6], boxes[:, 6], ["car", "van"],
                                np.array([0.9, 0.5])) + "\n")
    status, out, err = cli_in_process(capsys, "learn", "score", str(pred), "--kitti", str(scored_folder), "--out",
                                      str(tmp_path / "s"), "--lidar-height-m", str(HEIGHT_M))
    assert status == 0, err
    row = json.loads((tmp_path / "s" / "score.json").read_text())["rows"][0]
    assert (row["cars"], row["false positives"], row["AP30"]) == (2, 1, 50.0)
    assert "| p.jsonl | k | 1 | 2 |" in out


# ------------------------------------------------------------------------------------------ height and samples


def test_height_is_estimated_from_the_ground_and_scans_move_to_the_models_height(tmp_path):
    from cosim.learn.kitti import kitti_samples
    from cosim.learn.samples import Setup

    folder = small_folder(tmp_path / "k", scans=2)
    src = KittiSource(folder)
    assert not src.height_given and src.height_m == pytest.approx(HEIGHT_M, abs=0.02)
    assert estimate_height_m(road()) == pytest.approx(HEIGHT_M, abs=1e-6)
    src = KittiSource(folder, height_m=HEIGHT_M)
    item = kitti_samples([src], Setup(lidar_height_m=1.9), crop_fov=None).item(0)
    cloud, (boxes, _labels) = item["clouds"][0], item["targets"][0]
    assert np.median(cloud[:, 2]) == pytest.approx(-1.9, abs=0.011)  # the road where the model's was
    assert np.sort(boxes[:, 2]) == pytest.approx(np.sort([car(0, 0)[2] - 0.17] * 3), abs=1e-5)
    assert np.unique(cloud[:, 3]) == pytest.approx([102 / 255])  # reflectance 0.4 in counts of 1/255
    bright = KittiSource(folder, height_m=HEIGHT_M, intensity_scale=3.0)
    lit = kitti_samples([bright], Setup(), crop_fov=None).item(0)["clouds"][0]
    assert np.unique(lit[:, 3]) == pytest.approx([1.0])  # 0.4 x 3, clipped to 1
    front = kitti_samples([src], Setup(lidar_height_m=HEIGHT_M), crop_fov="camera").item(0)
    assert front["clouds"][0][:, 0].min() > 0  # cropped to the camera's view: the car behind is no background
    assert len(front["targets"][0][0]) == 2


def test_predictions_move_back_to_the_scans_height(tmp_path, monkeypatch):
    import cosim.learn.train as train_mod
    from cosim.learn.kitti import predict_source
    from cosim.learn.samples import Setup

    src = KittiSource(small_folder(tmp_path / "k", scans=1), height_m=HEIGHT_M)

    def echo(model, item, setup, device):  # a "model" that finds exactly its targets, in its own frame
        boxes = item["targets"][0][0].astype(np.float64)
        return boxes, np.ones(len(boxes)), np.zeros(len(boxes), np.int64)

    class Model:
        training = False

        def eval(self):
            pass

        def train(self, mode=True):
            pass

    monkeypatch.setattr(train_mod, "predict_sample", echo)
    boxes = predict_source(Model(), Setup(lidar_height_m=2.4), src, None)[0][0]
    expect = src.frame("000000").boxes
    order = np.argsort(boxes[:, 0])
    assert boxes[order] == pytest.approx(expect[np.argsort(expect[:, 0])], abs=1e-4)


# --------------------------------------------------------------------------------- training, predicting, --init


@needs_torch
def test_a_kitti_folder_trains_predicts_scores_and_fine_tunes(tmp_path, capsys):
    import torch

    from cosim.eval.predictions import read_predictions
    from cosim.learn.train import load_run

    folder = small_folder(tmp_path / "k")
    common = ["--batch-size", "2", "--threads", "1", "--lr", "5e-3", "-q", "--lidar-height-m", str(HEIGHT_M)]
    status, out, err = cli_in_process(capsys, "learn", "train", "--kitti", str(folder), "--kitti-val", str(folder),
                                      "--out", str(tmp_path / "r"), "--steps", "6", *common)
    assert status == 0, err
    assert "4 samples from k" in out and "steps    6" in out
    log = [json.loads(line) for line in (tmp_path / "r" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log if "loss" in r] == list(range(1, 7)) and "AP30" in log[-1]["val"]
    assert load_run(tmp_path / "r")[1].lidar_height_m == HEIGHT_M

    status, out, err = cli_in_process(capsys, "learn", "predict", str(tmp_path / "r"), "--kitti", str(folder),
                                      "--out", str(tmp_path / "p.jsonl"), "--lidar-height-m", "1.5")
    assert status == 0, err
    assert "moved -0.230 m" in out
    recs = read_predictions(tmp_path / "p.jsonl")  # cosim eval's validator
    assert sorted(r.tick for r in recs) == [0, 1, 2, 3] and {r.episode for r in recs} == {"k"}
    status, out, err = cli_in_process(capsys, "learn", "recall", str(tmp_path / "p.jsonl"), "--kitti", str(folder),
                                      "--out", str(tmp_path / "rec"), "--lidar-height-m", str(HEIGHT_M))
    assert status == 0, err
    row = json.loads((tmp_path / "rec" / "score.json").read_text())["rows"][0]
    assert row["frames"] == 4 and row["cars"] == 8  # two cars ahead per scan, each within 40 m

    status, out, err = cli_in_process(capsys, "learn", "train", "--kitti", str(folder), "--init", str(tmp_path / "r"),
                                      "--out", str(tmp_path / "f"), "--steps", "1", "--batch-size", "2", "--lr",
                                      "1e-12", "--threads", "1", "-q", "--lidar-height-m", "1.6")
    assert status == 0, err
    assert "(from " in out
    before, after = dict(load_run(tmp_path / "r")[0].named_parameters()), load_run(tmp_path / "f")
    assert after[1].lidar_height_m == HEIGHT_M  # the model's height is its initial run's
    assert json.loads((tmp_path / "f" / "summary.json").read_text())["init"] == str(tmp_path / "r")
    for k, v in after[0].named_parameters():  # weights, not batch-norm statistics: those follow the new data
        assert torch.allclose(v, before[k], atol=1e-6), k

    status, out, err = cli_in_process(capsys, "learn", "train", "--kitti", str(folder), "--init", str(tmp_path / "r"),
                                      "--out", str(tmp_path / "g"), "--steps", "1", "--width", "8", "-q")
    assert status == 2 and "is not of this run's shape" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "g" / "checkpoint.pt").exists()

    status, out, err = cli_in_process(capsys, "learn", "transfer", "--run", f"real={tmp_path / 'r'}", "--run",
                                      f"real={tmp_path / 'f'}", "--kitti", str(folder), "--out", str(tmp_path / "t"),
                                      "--picture", str(tmp_path / "t" / "t.png"), "--picture-scans", "2",
                                      "--lidar-height-m", str(HEIGHT_M))
    assert status == 0, err
    report = json.loads((tmp_path / "t" / "transfer.json").read_text())
    assert report["folders"][0]["names"]["real"]["seeds"] == 2 and len(report["runs"]) == 2
    assert (tmp_path / "t" / "t.png").stat().st_size > 10_000 and "| real | 2 |" in out
    row = report["folders"][0]["names"]["real"]
    assert row[OPERATING_RECALL]["n"] == 2 and 0.0 <= row[OPERATING_RECALL]["mean"] <= 1.0
    assert f"| {OPERATING_RECALL} | {OPERATING_SCORE} |" in out


# ------------------------------------------------------------------------------------------------ bad input


def test_bad_kitti_input_one_line_exit_2(tmp_path, capsys):
    folder = small_folder(tmp_path / "k", scans=1)
    (tmp_path / "novelo").mkdir()
    bad = small_folder(tmp_path / "bad", scans=1)
    text = (bad / "label_2" / "000000.txt").read_text().splitlines()
    (bad / "label_2" / "000000.txt").write_text(" ".join(text[0].split()[:14]) + "\n")
    pred = tmp_path / "p.jsonl"
    pred.write_text('{"episode": "other", "tick": 0, "ego": "ego", "agents": "ego", "boxes": []}\n')
    out = str(tmp_path / "o")
    cases = [
        (["learn", "score", str(pred), "--kitti", str(tmp_path / "novelo"), "--out", out], "no velodyne/ folder"),
        (["learn", "score", str(pred), "--kitti", str(bad), "--out", out], "14 columns"),
        (["learn", "score", str(pred), "--kitti", str(folder), "--out", out, "--lidar-height-m", "nan"], "nan"),
        (["learn", "score", str(pred), "--kitti", str(folder), "--out", out], "none of the --kitti folders"),
        (["learn", "score", str(pred), "--kitti", str(folder), "--out", out, "--kitti-split", "val"],
         "no ImageSets/val.txt"),
        (["learn", "transfer", "--run", "x", "--kitti", str(folder), "--out", out], "no run at x"),
    ]
    if HAVE_TORCH:
        cases += [(["learn", "train", "--kitti", str(folder), "--out", out, "--fusion", "late", "--agents", "all"],
                   "one agent"),
                  (["learn", "train", str(tmp_path), "--kitti", str(folder), "--out", out], "not both")]
    for args, needle in cases:
        status, _out, err = cli_in_process(capsys, *args)
        assert status == 2 and needle in err and len(err.strip().splitlines()) == 1, (args, err)
    assert not Path(out).exists()
    with pytest.raises(InputError, match="must be a number above 0"):
        KittiSource(folder, height_m=HEIGHT_M, intensity_scale=float("inf"))


# ------------------------------------------------------------------------------- cosim's own export, two ways


@pytest.mark.integration
def test_predictions_on_cosims_kitti_export_score_as_cosim_eval_on_the_episode(export_episode, tmp_path):
    """The same detections scored on the episode by cosim eval (ego only, LiDAR-visible ground truth) and on its
    KITTI export by cosim learn score (--fov all, every vehicle type, no point threshold): the same AP."""
    import csv

    from cosim.exporters.export import ExportOptions, run_export

    from cosim.eval.dataset import VisibilityRule, load_dataset
    from cosim.eval.evaluate import EvalOptions, evaluate
    from cosim.eval.predictions import parse_record, record_json
    from cosim.learn.kitti import KITTI_CLASSES, predictions_from_file

    out = tmp_path / "kitti"
    run_export(export_episode, "kitti", out, ExportOptions(every=2))
    src = KittiSource(out, height_m=1.9, types=tuple(KITTI_CLASSES))
    rng = np.random.default_rng(7)
    episode_lines, kitti_lines, n_gt = [], [], 0
    with open(src.folder / "frames.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    for row in rows:
        scan = src.frame(row["stem"])
        veh = [i for i, t in enumerate(scan.types) if t in KITTI_CLASSES]
        n_gt += len(veh)
        keep = [i for i in veh if rng.random() < 0.8]  # some missed, the others off by up to 1 m and 0.3 rad
        boxes = scan.boxes[keep] + np.c_[rng.uniform(-1, 1, (len(keep), 2)), np.zeros((len(keep), 4)),
                                         rng.uniform(-0.3, 0.3, len(keep))]
        false = np.c_[rng.uniform(-60, 60, (3, 2)), np.full(3, -1.0), np.tile([4.5, 1.9, 1.6], (3, 1)),
                      rng.uniform(-3, 3, 3)]
        boxes = np.concatenate([boxes, false])
        classes = [KITTI_CLASSES[scan.types[i]] for i in keep] + ["car"] * 3
        scores = rng.random(len(boxes))
        args = (boxes[:, :3], boxes[:, 3:6], boxes[:, 6], classes, scores)
        episode_lines.append(record_json(row["episode"], int(row["tick"]), row["agent_id"], "ego", *args))
        kitti_lines.append(record_json(src.id, int(row["stem"]), "ego", "ego", *args))
    assert len(rows) >= 10 and n_gt >= 30, (len(rows), n_gt)
    records = [parse_record(json.loads(line), Path("p.jsonl"), n + 1) for n, line in enumerate(episode_lines)]
    lidar_only = VisibilityRule(min_points=1, min_pixels=10 ** 9)  # the export labels what the LiDAR returns on
    result = evaluate(load_dataset(export_episode), records, EvalOptions(visible_only=True, rule=lidar_only))
    theirs = result.metrics("ego")["detection"]["vehicle"]
    pred = tmp_path / "kitti.jsonl"
    pred.write_text("".join(line + "\n" for line in kitti_lines))
    mine = score_source(src, predictions_from_file(pred, src),
                        ScoreOptions(fov="all", min_points=0, max_range_m=1000.0)).summary()
    for key in ("AP30", "AP50", "AP70"):
        assert mine[key] == pytest.approx(float(theirs[key]), abs=0.01), (key, mine, theirs)
    assert 5 < mine["AP30"] < 95
    if HAVE_TORCH:  # and a model sees the same scans both ways: its detections on the export are those on the episode
        _a_model_detects_the_same_on_the_export(export_episode, src, rows[:4])


def _a_model_detects_the_same_on_the_export(episode: Path, src: KittiSource, rows: list[dict]) -> None:
    import torch

    from cosim.eval.dataset import load_dataset
    from cosim.learn.data import Samples
    from cosim.learn.kitti import predict_source
    from cosim.learn.samples import Setup
    from cosim.learn.train import TrainOptions, new_model, predict_sample

    cpu = torch.device("cpu")
    setup = Setup()  # no LiDAR height recorded: the export's scans are not moved
    model = new_model(setup, TrainOptions(seed=3), cpu).eval()
    on_export = predict_source(model, setup, src, cpu)
    samples = Samples(load_dataset(episode), setup, every=2)
    index = {key: i for i, key in enumerate(samples.src.keys)}
    found = 0
    for row in rows:
        item = samples.item(index[(row["episode"], int(row["tick"]), row["agent_id"])])
        boxes, scores, _cls = predict_sample(model, item, setup, cpu)
        k_boxes, k_scores, _k_cls = on_export[int(row["stem"])]
        assert k_boxes == pytest.approx(boxes, abs=1e-4) and k_scores == pytest.approx(scores, abs=1e-5), row
        found += len(boxes)
    samples.close()
    assert found > 0


# ------------------------------------------------------------------------------------------ the raw converter

CAM_TO_CAM = """calib_time: x
S_rect_02: 1.242000e+03 3.750000e+02
R_rect_00: 1 0 0 0 1 0 0 0 1
P_rect_00: {p}
P_rect_01: {p}
P_rect_02: {p}
P_rect_03: {p}
"""
TRACKLET = """<item><objectType>{kind}</objectType><h>1.5</h><w>1.8</w><l>4.2</l><first_frame>{first}</first_frame>
<poses><count>{n}</count>{poses}</poses></item>"""
POSE = """<item><tx>{x}</tx><ty>{y}</ty><tz>{z}</tz><rx>0</rx><ry>0</ry><rz>{yaw}</rz><state>2</state>
<occlusion>{occ}</occlusion><occlusion_kf>0</occlusion_kf><truncation>{trunc}</truncation></item>"""


def test_raw_tracklets_become_object_labels_in_the_cameras_view(tmp_path):
    from benchmarks.kitti_raw import main

    day, drive = tmp_path / "day", tmp_path / "day" / "drive_sync"
    (drive / "velodyne_points" / "data").mkdir(parents=True)
    p = " ".join(f"{v:g}" for v in P2.ravel())
    (day / "calib_cam_to_cam.txt").write_text(CAM_TO_CAM.format(p=p))
    (day / "calib_velo_to_cam.txt").write_text("calib_time: x\nR: 0 -1 0 0 0 -1 1 0 0\nT: 0 0 0\n")
    (day / "calib_imu_to_velo.txt").write_text("calib_time: x\nR: 1 0 0 0 1 0 0 0 1\nT: 0 0 0\n")
    for k in range(2):
        write_velodyne(drive / "velodyne_points" / "data" / f"{k:010d}.bin",
                       np.c_[road(), np.full(len(road()), 0.3)].astype(np.float32))
    ahead = [POSE.format(x=12 + k, y=1.0, z=-HEIGHT_M, yaw=0.2, occ=[0, -1][k], trunc=0) for k in range(2)]
    behind = [POSE.format(x=-10, y=0, z=-HEIGHT_M, yaw=0, occ=0, trunc=0)]
    outside = [POSE.format(x=15, y=-3, z=-HEIGHT_M, yaw=0, occ=0, trunc=2)]
    items = [TRACKLET.format(kind="Car", first=0, n=2, poses="".join(ahead)),
             TRACKLET.format(kind="Van", first=1, n=1, poses="".join(behind)),
             TRACKLET.format(kind="Car", first=1, n=1, poses="".join(outside))]
    (drive / "tracklet_labels.xml").write_text(f"<boost_serialization><tracklets><count>3</count>{''.join(items)}"
                                               "</tracklets></boost_serialization>")
    out = tmp_path / "out"
    assert main(["--drive", str(drive), "--calib", str(day), "--out", str(out), "--val-share", "0.5"]) == 0
    src = KittiSource(out, height_m=HEIGHT_M)
    assert src.stems == ["000000", "000001"]
    assert KittiSource(out, height_m=HEIGHT_M, split="val").stems == ["000001"]  # the drive's last frames held out
    for k, stem in enumerate(src.stems):  # the car ahead only: the van behind and the pose out of the image are left
        scan = src.frame(stem)
        assert scan.types == ["Car"]
        assert scan.boxes[0] == pytest.approx([12 + k, 1.0, -HEIGHT_M + 0.75, 4.2, 1.8, 1.5, 0.2], abs=1e-3)
    second = (out / "training" / "label_2" / "000001.txt").read_text().split()
    assert (second[1], second[2]) == ("0.0000", "3")  # in the image: not truncated; occlusion -1: unknown (3)
    assert main(["--drive", str(tmp_path / "none"), "--calib", str(day), "--out", str(tmp_path / "o2")]) == 2


def test_the_lidar_height_comes_from_each_vehicles_own_rig():
    from cosim.learn.kitti import vehicle_lidar_heights_m

    def lidar(z):
        return {"model": "hdl64e", "mount": {"xyz_m": [0.0, 0.0, z]}}

    resolved = {"agents": {"vehicles": {"count": 3, "rigs": {"vehicle_1": {"lidar": lidar(1.2)},
                                                             "vehicle_2": {"lidar": None}}}},
                "sensors": {"vehicle": {"lidar": lidar(1.73)}}}
    assert vehicle_lidar_heights_m(resolved) == [1.73, 1.2]  # vehicle_2 is camera-only
    resolved["sensors"]["vehicle"]["lidar"] = None
    assert vehicle_lidar_heights_m(resolved) == [1.2]
