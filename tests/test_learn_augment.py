"""``cosim learn train``'s augmentations (cosim/learn/augment.py, issue 48) and detector sizes (``--pillar-m``,
``--range-m``, ``--width``): each transform on a synthetic sample does what it says, ground-truth sampling
pastes objects with their points at free places and hides what they occlude, the batches are repeatable
from the seed (worker processes and resume included), and a finer-pillar model trains, saves, loads and
predicts. Synthetic samples only (no episode is made): every test takes seconds."""

from __future__ import annotations

import importlib.util
import math

import numpy as np
import pytest

from cosim.learn.augment import (
    GtDatabase,
    bev_overlap,
    drop_points,
    jitter_intensity,
    paste_objects,
    points_in_boxes,
    rotate,
    scale,
    transform_poses,
    translate,
)
from cosim.learn.grid import Grid, make_grid
from tests.helpers import cli_in_process

HAVE_TORCH = importlib.util.find_spec("torch") is not None
needs_torch = pytest.mark.skipif(not HAVE_TORCH, reason="PyTorch is not installed (pip install -e '.[learn]')")

GROUND_Z_M = -1.7  # the road below a sensor mounted 1.7 m up


def _ground(rng: np.random.Generator, n: int = 6000, reach_m: float = 45.0) -> np.ndarray:
    """(n, 4) points of flat ground around the sensor (x, y in +-reach_m, z at GROUND_Z_M)."""
    xy = rng.uniform(-reach_m, reach_m, (n, 2))
    return np.c_[xy, np.full(n, GROUND_Z_M), rng.uniform(0.1, 0.4, n)].astype(np.float32)


def _car(x: float, y: float, yaw: float, rng: np.random.Generator, n: int = 400) -> tuple[np.ndarray, np.ndarray]:
    """A car box (7,) standing on the ground at (x, y) and n points filling it (n, 4)."""
    box = np.array([x, y, GROUND_Z_M + 0.75, 4.4, 1.8, 1.5, yaw])
    local = rng.uniform(-0.5, 0.5, (n, 3)) * box[3:6] * 0.98
    c, s = math.cos(yaw), math.sin(yaw)
    pts = np.c_[box[0] + c * local[:, 0] - s * local[:, 1], box[1] + s * local[:, 0] + c * local[:, 1],
                box[2] + local[:, 2], rng.uniform(0.2, 0.9, n)]
    return box, pts.astype(np.float32)


def _sample(seed: int, cars: list[tuple[float, float, float]]) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    clouds, boxes = [_ground(rng)], []
    for x, y, yaw in cars:
        b, p = _car(x, y, yaw, rng)
        keep = ~points_in_boxes(clouds[0], b[None], 0.05)[:, 0]  # no ground under the car
        clouds[0] = clouds[0][keep]
        clouds.append(p)
        boxes.append(b)
    return np.concatenate(clouds), np.array(boxes).reshape(-1, 7)


def _all_inside(points: np.ndarray, boxes: np.ndarray, n_each: int) -> None:
    """Each box holds its n_each points (the points are the boxes' points, box after box)."""
    inside = points_in_boxes(points, boxes, 1e-4)
    for m in range(len(boxes)):
        assert inside[m * n_each:(m + 1) * n_each, m].all(), m


# ------------------------------------------------------------------------------ the transforms


def test_rotation_moves_a_point_and_its_box_by_the_angle():
    rng = np.random.default_rng(0)
    box, pts = _car(20.0, 5.0, 0.3, rng)
    got_pts, got_box = rotate(pts, box[None], math.radians(30))
    r = math.hypot(20.0, 5.0)
    bearing = math.atan2(5.0, 20.0) + math.radians(30)
    np.testing.assert_allclose(got_box[0, :2], [r * math.cos(bearing), r * math.sin(bearing)], atol=1e-9)
    assert got_box[0, 6] == pytest.approx(0.3 + math.radians(30))
    np.testing.assert_allclose(np.hypot(got_pts[:, 0], got_pts[:, 1]), np.hypot(pts[:, 0], pts[:, 1]), rtol=1e-5)
    turned = np.arctan2(got_pts[:, 1], got_pts[:, 0]) - np.arctan2(pts[:, 1], pts[:, 0])
    np.testing.assert_allclose(np.angle(np.exp(1j * turned)), math.radians(30), atol=1e-5)
    np.testing.assert_array_equal(got_pts[:, 2:], pts[:, 2:])
    _all_inside(got_pts, got_box, len(pts))


def test_scaling_scales_points_and_boxes_alike():
    rng = np.random.default_rng(1)
    box, pts = _car(-12.0, 3.0, -1.0, rng)
    got_pts, got_box = scale(pts, box[None], 1.05)
    np.testing.assert_allclose(got_pts[:, :3], pts[:, :3] * 1.05, rtol=1e-6)
    np.testing.assert_allclose(got_box[0, :6], box[:6] * 1.05)
    assert got_box[0, 6] == box[6]
    np.testing.assert_array_equal(got_pts[:, 3], pts[:, 3])
    _all_inside(got_pts, got_box, len(pts))


def test_translation_and_height_jitter_move_points_and_boxes_alike():
    rng = np.random.default_rng(2)
    box, pts = _car(8.0, -6.0, 2.0, rng)
    for offset in ([0.3, -0.2, 0.1], [0.0, 0.0, -0.25]):  # global translation; the sensor-height jitter
        got_pts, got_box = translate(pts, box[None], np.array(offset))
        np.testing.assert_allclose(got_pts[:, :3] - pts[:, :3], np.broadcast_to(offset, (len(pts), 3)), atol=1e-5)
        np.testing.assert_allclose(got_box[0, :3] - box[:3], offset, atol=1e-12)
        np.testing.assert_array_equal(got_box[0, 3:], box[3:])
        _all_inside(got_pts, got_box, len(pts))


def test_point_drop_keeps_the_expected_share():
    pts = _ground(np.random.default_rng(3), n=20000)
    for share in (0.1, 0.3):
        kept = drop_points(pts, share, np.random.default_rng(4))
        assert abs(len(kept) / len(pts) - (1 - share)) < 0.015, (share, len(kept))
        # a subset in the same order: every kept point is one of the originals
        assert np.isin(kept[:, 0], pts[:, 0]).all()
    assert len(drop_points(pts, 0.0, np.random.default_rng(4))) == len(pts)


def test_intensity_jitter_scales_adds_noise_and_stays_in_range():
    pts = _ground(np.random.default_rng(5), n=5000)
    doubled = jitter_intensity(pts, 2.0, 0.0, np.random.default_rng(0))
    np.testing.assert_allclose(doubled[:, 3], np.clip(pts[:, 3] * 2.0, 0, 1), rtol=1e-6)
    np.testing.assert_array_equal(doubled[:, :3], pts[:, :3])
    noisy = jitter_intensity(pts, 1.0, 0.05, np.random.default_rng(0))
    d = noisy[:, 3].astype(np.float64) - pts[:, 3]
    assert 0.04 < d.std() < 0.06 and abs(d.mean()) < 0.005
    assert noisy[:, 3].min() >= 0.0 and noisy[:, 3].max() <= 1.0
    bright = jitter_intensity(pts, 5.0, 0.0, np.random.default_rng(0))
    assert bright[:, 3].max() == 1.0  # clipped


def test_bev_overlap_of_rotated_boxes():
    a = np.array([[0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0]])
    near = np.array([[3.9, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0], [4.1, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0],
                     [0.0, 2.2, 0.0, 4.0, 2.0, 1.5, math.pi / 2], [3.5, 3.5, 0.0, 4.0, 2.0, 1.5, math.pi / 4]])
    # 3.9 along x overlaps by 0.1 m, 4.1 is 0.1 m apart; the crossing box at y 2.2 reaches down to y 0.2; the
    # diagonal one is apart along its own axis (it starts at 4.95 - 2 = 2.95 m, the first ends at 3 / sqrt 2)
    assert bev_overlap(a, near).tolist() == [[True, False, True, False]]
    assert bev_overlap(a, near[1:2], margin_m=0.2).tolist() == [[True]]


def test_intermediate_poses_follow_scaling_and_translation():
    """An agent's cloud, scaled in its own frame, lands where the ego's scaled and moved cloud is, through
    the transformed pose: the scene moves as one."""
    from cosim.learn.samples import bev_pose, to_bev_frame

    rng = np.random.default_rng(6)
    ego_cloud = rng.uniform(-30, 30, (50, 4)).astype(np.float32)
    t = np.eye(4)
    t[:2, :2] = [[math.cos(0.7), -math.sin(0.7)], [math.sin(0.7), math.cos(0.7)]]
    t[:2, 3] = [12.0, -4.0]
    pose = bev_pose(t)
    local = to_bev_frame(ego_cloud, pose)
    offset = np.array([0.4, -0.3, 0.2])
    moved_ego, _ = translate(*scale(ego_cloud, np.zeros((0, 7)), 1.04), offset)
    moved_local, _ = translate(*scale(local, np.zeros((0, 7)), 1.04), np.array([0.0, 0.0, offset[2]]))
    new_pose = transform_poses(pose[None], 1.04, offset)[0]
    np.testing.assert_allclose(to_bev_frame(moved_ego, new_pose), moved_local, atol=1e-4)
    assert np.abs(moved_ego[:, :2] - ego_cloud[:, :2]).max() > 0.3  # the check above is not the identity


# ------------------------------------------------------------------------------ ground-truth sampling


class _Samples:
    """Single-agent samples in memory (what cosim.learn.data.Samples gives: ``len``, ``item``, ``setup``)."""

    def __init__(self, scenes: list[tuple[np.ndarray, np.ndarray]], setup=None):
        self.scenes = scenes
        self.setup = setup

    def __len__(self) -> int:
        return len(self.scenes)

    def item(self, i: int) -> dict:
        cloud, boxes = self.scenes[i]
        return {"episode": f"ep{i // 2}", "tick": i % 2, "ego": "vehicle_0", "clouds": [cloud],
                "sources": [["vehicle_0"]], "targets": [(boxes, np.zeros(len(boxes), np.int64))]}


def test_gt_database_holds_objects_with_their_points():
    scenes = [_sample(10, [(15.0, 5.0, 0.2), (-20.0, -8.0, 1.0)]), _sample(11, [(15.0, -6.0, 0.0)])]
    db = GtDatabase.build(_Samples(scenes), min_points=5)
    assert len(db) == 3 and db.sources.tolist() == [0, 0, 1]
    for box, pts in zip(db.boxes, db.points, strict=True):
        assert len(pts) >= 5 and points_in_boxes(pts, box[None]).all()
    assert len(GtDatabase.build(_Samples(scenes), min_points=1000)) == 0


def test_gt_sampling_pastes_objects_at_free_places_with_their_points_and_hides_what_they_occlude():
    source = _sample(20, [(15.0, 5.0, 0.2), (-14.0, -9.0, 1.2), (30.0, -15.0, 0.0)])
    target_cloud, target_boxes = _sample(21, [(15.0, -5.0, 0.0), (29.0, -14.0, 0.3)])  # the last: a collision
    behind = np.array([[30.0, 10.0, -1.1, 0.5]], np.float32)  # on the ray through the pasted car at (15, 5)
    wall_xy = (-14.0, -9.0)  # something standing where the second car would go: not a free place
    wall = np.array([[wall_xy[0], wall_xy[1], -0.5, 0.5]], np.float32)
    target_cloud = np.concatenate([target_cloud, behind, wall])
    db = GtDatabase.build(_Samples([source]), min_points=5)
    labels = np.zeros(len(target_boxes), np.int64)
    pts, boxes, lab = paste_objects(db, target_cloud, target_boxes, labels, 3, np.random.default_rng(0), source=-1)
    assert len(boxes) == 3 and len(lab) == 3  # only the car at (15, 5) had a free place
    pasted = boxes[2]
    np.testing.assert_allclose(pasted[:2], [15.0, 5.0])
    assert pasted[2] - pasted[5] / 2 == pytest.approx(GROUND_Z_M, abs=1e-6)  # on the target's ground
    inside = points_in_boxes(pts, pasted[None], 1e-4)[:, 0]
    assert inside.sum() == len(db.points[0])  # its own points, all of them, and nothing else of the scene
    assert not bev_overlap(pasted[None], boxes[:2]).any()
    assert not (pts[:, :3] == behind[0, :3]).all(axis=1).any(), "the point behind the pasted car is hidden"
    assert (pts[:, :3] == wall[0, :3]).all(axis=1).any()  # the wall stays, and nothing was pasted on it
    # points in front of the car (nearer the sensor on its bearing) stay
    front = target_cloud[(np.hypot(target_cloud[:, 0], target_cloud[:, 1]) < 10)]
    assert np.isin(front[:, 0], pts[:, 0]).all()
    # every pasted box holds its points after a later transform too
    moved_pts, moved_boxes = rotate(*scale(pts, boxes, 0.97), 0.4)
    assert points_in_boxes(moved_pts, moved_boxes[2:3], 1e-4)[:, 0].sum() == len(db.points[0])
    # an object is never pasted into its own tick, and nothing is pasted with count 0
    same, *_ = paste_objects(db, target_cloud, target_boxes, labels, 3, np.random.default_rng(0), source=0)
    assert len(same) == len(target_cloud)
    assert len(paste_objects(db, target_cloud, target_boxes, labels, 0, np.random.default_rng(0))[1]) == 2


# ------------------------------------------------------------------------------ the batches and training

ALL_ON = {"turn_deg": 45.0, "scale_min": 0.95, "scale_max": 1.05, "translate_m": 0.2, "height_m": 0.2,
          "point_drop": 0.1, "intensity_scale": 2.0, "intensity_noise": 0.05, "gt_sample": 4, "gt_min_points": 5}


def _train_samples(grid: Grid | None = None) -> _Samples:
    from cosim.learn.samples import Setup

    cars = [[(15.0, 5.0, 0.2), (-20.0, -8.0, 1.0)], [(25.0, -6.0, 0.0)], [(10.0, 10.0, 1.5), (30.0, 2.0, 0.1)],
            [(-12.0, 4.0, 0.5)]]
    scenes = [_sample(30 + i, c) for i, c in enumerate(cars)]
    if grid is not None:
        scenes = [(grid.crop(p), b[grid.box_inside(b[:, :2])]) for p, b in scenes]
    return _Samples(scenes, Setup(grid=grid) if grid is not None else Setup())


@needs_torch
def test_a_front_view_grid_is_never_mirrored_in_x():
    from cosim.learn.train import TrainOptions, step_batch

    grid = make_grid(0.8, (0.0, 70.4), (-40.0, 40.0))
    samples = _train_samples(grid)
    order = np.arange(len(samples))
    for step in range(8):  # each step draws both mirrors; the x mirror would put every point behind the sensor
        b = step_batch(samples, order, 0, TrainOptions(batch_size=2, seed=0), step)
        assert b["t_mask"].sum() == sum(len(samples.item(j % len(samples))["targets"][0][0]) for j in (0, 1))
        assert (b["feats"][:, 0] >= 0).all()


@needs_torch
def test_every_augmentation_is_repeatable_from_the_seed():
    from cosim.learn.train import TrainOptions, step_batch

    samples = _train_samples()
    db = GtDatabase.build(samples, 5)
    order = np.arange(len(samples))

    def batch(seed: int, step: int, **kw):
        return step_batch(samples, order, 0, TrainOptions(batch_size=2, seed=seed, **{**ALL_ON, **kw}), step, db)

    a, b = batch(0, 3), batch(0, 3)
    assert all(np.array_equal(a[k], b[k]) for k in a)
    for other in (batch(1, 3), batch(0, 4)):
        assert len(a["feats"]) != len(other["feats"]) or not np.array_equal(a["feats"], other["feats"])
    plain = step_batch(samples, order, 0, TrainOptions(batch_size=2, seed=0, turn_deg=45.0), 3)
    off = batch(0, 3, scale_min=1.0, scale_max=1.0, translate_m=0.0, height_m=0.0, point_drop=0.0,
                intensity_scale=1.0, intensity_noise=0.0, gt_sample=0)
    assert all(np.array_equal(plain[k], off[k]) for k in plain)  # all off: the batches of before
    assert (a["t_mask"].sum() > plain["t_mask"].sum())  # ground-truth sampling added targets


@needs_torch
def test_training_with_every_augmentation_is_deterministic_with_workers_and_resume(tmp_path):
    import torch

    from cosim.learn.train import CHECKPOINT, TrainOptions, fit

    samples = _train_samples()
    opts = TrainOptions(steps=4, batch_size=2, seed=2, threads=1, save_every=2, **ALL_ON)
    fit(samples, None, samples.setup, opts, tmp_path / "a", show_progress=False)
    fit(samples, None, samples.setup, TrainOptions(**{**opts.to_dict(), "workers": 2}), tmp_path / "b",
        show_progress=False)
    fit(samples, None, samples.setup, TrainOptions(**{**opts.to_dict(), "steps": 2}), tmp_path / "c",
        show_progress=False)
    summary = fit(samples, None, samples.setup, opts, tmp_path / "c", resume=True, show_progress=False)
    assert summary["gt_database_objects"] == 6
    a, b, c = (torch.load(tmp_path / n / CHECKPOINT, weights_only=False) for n in "abc")
    assert all(torch.equal(a["model"][k], b["model"][k]) for k in a["model"]), "workers changed the weights"
    assert all(torch.equal(a["model"][k], c["model"][k]) for k in a["model"]), "a resumed run differs"
    assert a["options"]["gt_sample"] == 4 and a["options"]["scale_max"] == 1.05  # saved with the run
    from cosim.errors import InputError

    with pytest.raises(InputError, match=r"point_drop 0.1 \(now 0.2\)"):
        fit(samples, None, samples.setup, TrainOptions(**{**opts.to_dict(), "steps": 6, "point_drop": 0.2}),
            tmp_path / "c", resume=True, show_progress=False)


@needs_torch
@pytest.mark.parametrize("width", [16, 32])
def test_a_finer_pillar_model_trains_saves_loads_and_predicts(tmp_path, width):
    import torch

    from cosim.learn.model import PillarDetector
    from cosim.learn.train import TrainOptions, fit, load_run, predict_sample

    grid = make_grid(0.32, (0.0, 40.96), (-20.48, 20.48))  # a KITTI-like front view, shrunk for the test
    assert (grid.nx, grid.ny, grid.out_shape, grid.cell_m) == (128, 128, (64, 64), 0.64)
    samples = _train_samples(grid)
    fit(samples, None, samples.setup, TrainOptions(steps=3, batch_size=2, seed=0, threads=1, width=width,
                                                   turn_deg=10.0, scale_min=0.95, scale_max=1.05),
        tmp_path / "run", show_progress=False)
    model, setup, ckpt = load_run(tmp_path / "run", torch.device("cpu"))
    assert setup.grid == grid and model.grid == grid and ckpt["options"]["width"] == width
    assert model.pfn.out_features == width
    n_params = sum(p.numel() for p in model.parameters())
    assert n_params == sum(p.numel() for p in PillarDetector(grid, 6, width=width).parameters())
    boxes, scores, cls = predict_sample(model, samples.item(0), setup, torch.device("cpu"), score_min=0.0)
    assert boxes.shape[1] == 7 and len(boxes) == len(scores) == len(cls) > 0
    assert (boxes[:, 0] >= grid.x_range[0]).all() and (boxes[:, 0] < grid.x_range[1] + grid.cell_m).all()


def test_make_grid_follows_the_pillar_and_refuses_what_does_not_tile():
    from cosim.errors import InputError

    assert make_grid() == Grid()  # the default grid, as before
    g = make_grid(0.2)
    assert (g.nx, g.ny) == (1408, 400) and g.max_pillars == 1408 * 400  # no pillar dropped
    front = make_grid(0.16, (0.0, 70.4), (-40.0, 40.0))
    assert (front.nx, front.ny) == (440, 500)
    assert Grid().covers(front) and not front.covers(Grid())
    for args, match in (((0.05,), "at least"), ((0.3,), "whole number"), ((0.4, (10.0, 5.0)), "empty")):
        with pytest.raises(InputError, match=match):
            make_grid(*args)


@needs_torch
@pytest.mark.parametrize("flags, message", [
    (["--gt-sample", "4", "--fusion", "early", "--agents", "all"], "--fusion none only"),
    (["--pillar-m", "0.3"], "--range-m"),
    (["--range-m", "0", "70", "-40", "40", "--pillar-m", "0.32"], "--range-m"),
    (["--pillar-m", "0.01"], "--pillar-m"),
    (["--scale", "1.1", "0.9"], "--scale"),
    (["--point-drop", "1"], "--point-drop"),
    (["--intensity-scale", "0.5"], "--intensity-scale"),
    (["--height-jitter-m", "-0.1"], "--height-jitter-m"),
])
def test_bad_augmentation_and_grid_flags_one_message_exit_2(capsys, tmp_path, flags, message):
    status, _out, err = cli_in_process(capsys, "learn", "train", str(tmp_path), "--out", str(tmp_path / "run"),
                                       *flags)
    assert status == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "run").exists()
