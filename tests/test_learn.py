"""``cosim learn`` (cosim/learn/, issue 29): the numpy parts, the detector trained on a tiny real LiDAR-only
batch (the loss falls, the predictions pass ``cosim eval``'s validator and score above 0 on the training
episodes), determinism and resume, bad input, and a core that never imports torch."""

from __future__ import annotations

import importlib.util
import json
import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from cosim.learn.grid import REG_CHANNELS, Grid, decode, targets, voxelise
from cosim.learn.nms import circle_nms
from tests.helpers import REPO, cli_in_process, run_cli, run_sweep

HAVE_TORCH = importlib.util.find_spec("torch") is not None
needs_torch = pytest.mark.skipif(not HAVE_TORCH, reason="PyTorch is not installed (pip install -e '.[learn]'; "
                                                        "make test installs it)")

SWEEP = """\
name: learntest
description: two tiny LiDAR-only episodes for the cosim learn tests
seed: 5
base: {base}
set:
  duration_s: 1
  map.size_m: 300
  traffic.density_veh_per_km: 14
  agents.vehicles.count: 2
  agents.rsus.count: 1
  agents.drones: [{{strategy: hover, altitude_m: 40}}]
  environment.lighting: day
  sensors.bev: false
  sensors.vehicle.cameras: []
  sensors.rsu.cameras: []
  sensors.drone.cameras: []
axes:
  environment: {{key: map.kind, values: [urban]}}
count: 2
split: {{train: 1, test: 1}}
"""


# ------------------------------------------------------------------------------------------ numpy parts


def test_voxelise_puts_points_in_their_pillars_and_caps_them():
    g = Grid(x_range=(-8.0, 8.0), y_range=(-4.0, 4.0), pillar_m=1.0, max_points=3, max_pillars=100)
    pts = np.array([[0.5, 0.5, 0.0, 1.0]] * 5 + [[-7.5, 3.5, -1.0, 0.5], [9.0, 0.0, 0.0, 1.0],
                                                 [0.0, 0.0, 5.0, 1.0]], np.float32)
    feats, coords, counts = voxelise(pts, g)
    # the point beyond x 8 and the one above z 1 are cropped; five points share a pillar, capped at three
    assert sorted(map(tuple, coords.tolist())) == [(4, 8), (7, 0)]
    by_cell = dict(zip(map(tuple, coords.tolist()), counts.tolist(), strict=True))
    assert by_cell == {(4, 8): 3, (7, 0): 1}
    assert len(feats) == counts.sum() == 4  # the kept points, pillar after pillar
    row = int(np.nonzero((coords == [4, 8]).all(axis=1))[0][0])
    mine = np.repeat(np.arange(len(counts)), counts) == row
    np.testing.assert_allclose(feats[mine, 7:9], [[0.0, 0.0]] * 3, atol=1e-6)  # at the pillar's centre
    np.testing.assert_allclose(feats[~mine, 7:9], [[0.0, 0.0]], atol=1e-6)
    np.testing.assert_allclose(feats[~mine, :4], pts[5:6])
    _f2, c2, _n2 = voxelise(pts[::-1].copy(), g)
    assert sorted(map(tuple, c2.tolist())) == sorted(map(tuple, coords.tolist()))


def test_voxelise_keeps_every_agents_share_of_an_overfull_pillar():
    # a merged cloud lists the ego's points first: 40 of them, then 40 of a collaborator, in one pillar
    g = Grid(x_range=(-4.0, 4.0), y_range=(-4.0, 4.0), pillar_m=1.0, max_points=8, max_pillars=100)
    ego = np.tile([[0.2, 0.2, -1.0, 1.0]], (40, 1))
    other = np.tile([[0.7, 0.7, -1.0, 0.5]], (40, 1))
    few = np.array([[2.5, 2.5, -1.0, 0.1], [2.5, 2.5, -1.0, 0.2]])
    feats, coords, counts = voxelise(np.concatenate([ego, other, few]).astype(np.float32), g)
    pillar = np.repeat(np.arange(len(counts)), counts)
    by_cell = {tuple(c): (feats[pillar == i], n) for i, (c, n) in enumerate(zip(coords.tolist(), counts.tolist(),
                                                                                 strict=True))}
    f, n = by_cell[(4, 4)]
    assert n == 8
    assert sorted(f[:, 3].tolist()) == [0.5] * 4 + [1.0] * 4  # half the kept points are the collaborator's
    f, n = by_cell[(6, 6)]
    assert n == 2 and f[:2, 3].tolist() == pytest.approx([0.1, 0.2])  # a pillar under the cap keeps all, in order


def test_inside_box_is_the_rotated_footprint():
    from cosim.learn.data import inside_box

    box = np.array([[10.0, 0.0, -1.0, 4.0, 2.0, 1.5, np.pi / 2]])  # 4 m long along y, 2 m wide along x
    xy = np.array([[10.0, 1.9], [10.0, 2.1], [10.9, 0.0], [11.1, 0.0], [11.1, 0.0]])
    assert inside_box(xy[:4], box)[:, 0].tolist() == [True, False, True, False]
    assert inside_box(xy[4:], box, margin_m=0.2)[:, 0].tolist() == [True]


def _one_record() -> dict:
    """A learn record: one ego, one collaborator 30 m ahead, the ego's own box and one car."""
    from cosim.learn.samples import quantise

    on_ego = np.array([[x, y, -0.5] for x in (-2.0, 0.0, 2.0) for y in (-0.8, 0.8)])
    on_car = np.array([[20.0 + dx, 5.0, -0.8] for dx in (-1.0, 0.0, 1.0)])
    ground = np.array([[8.0, -3.0, -1.9]])
    collab_to_ego = np.eye(4)
    collab_to_ego[:3, 3] = [30.0, 0.0, 0.0]  # the collaborator's LiDAR 30 m ahead of the ego's
    collab = np.concatenate([on_ego, on_car, ground]) - [30.0, 0.0, 0.0]
    yaw = 0.3
    return {"tick": 0, "t_ns": 0, "agents": ["vehicle_0", "vehicle_1"],
            "map_from": np.stack([np.eye(4), collab_to_ego]),
            "points": [quantise(ground)[0], quantise(collab)[0]],
            "intensity": [np.full(1, 25, np.uint8), np.full(10, 100, np.uint8)],
            "hits": [np.array([[0], [1]]), np.array([[0, 7, 9], [1, 6, 3]])],
            "label_track_ids": np.array([7, 9]), "label_classes": ["car", "car"],
            "label_centers": np.array([[0.0, 0.0, -1.0], [20.0, 5.0, -1.0]]),
            "label_rotations": np.array([[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)]]),
            "label_sizes": np.array([[4.6, 1.9, 1.5], [4.4, 1.8, 1.5]]), "agent_tracks": {"vehicle_0": 7},
            "links": None}


@pytest.mark.parametrize("fusion", ["early", "late", "intermediate"])
def test_collaborators_returns_on_the_ego_are_cut_and_the_ego_is_no_target(fusion):
    from cosim.learn.samples import Setup, make_item

    item = make_item(_one_record(), "vehicle_0", Setup(fusion=fusion, agents="all"), "ep")
    if fusion == "intermediate":  # clouds in each agent's own frame (here only shifted along x): into the ego's
        assert (item["poses"][:, 0] == 0).all()
        merged = np.concatenate([c + np.array([p[1], p[2], 0.0, 0.0], np.float32)
                                 for c, p in zip(item["clouds"], item["poses"], strict=True)])
    else:
        merged = np.concatenate(item["clouds"])
    assert len(merged) == 1 + 3 + 1  # ego: 1 ground point; collaborator: 3 on the car, 1 ground, not its 6 on the ego
    assert not ((np.abs(merged[:, 0]) < 2.6) & (np.abs(merged[:, 1]) < 1.3)).any()
    collab_boxes = item["targets"][-1][0]
    np.testing.assert_allclose(collab_boxes[:, :2], [[20.0, 5.0]])  # the car the collaborator sees; never the ego
    if fusion == "late":
        assert len(item["targets"][0][0]) == 0  # the ego's own cloud sees no object


def test_voxelise_keeps_the_fullest_pillars_when_too_many():
    g = Grid(x_range=(-4.0, 4.0), y_range=(-4.0, 4.0), pillar_m=1.0, max_points=4, max_pillars=2)
    pts = np.array([[0.5, 0.5, 0, 1]] * 3 + [[1.5, 0.5, 0, 1]] + [[-2.5, -2.5, 0, 1]] * 2, np.float32)
    _, _coords, counts = voxelise(pts, g)
    assert sorted(counts.tolist()) == [2, 3]


@pytest.mark.parametrize("yaws", [(0.3, -2.0), (2.5, -0.9), (math.pi / 2 + 1e-3, -math.pi / 2 + 1e-3),
                                  (math.pi - 1e-3, 0.0)])
def test_targets_decode_back_to_the_boxes(yaws):
    g = Grid()
    boxes = np.array([[10.3, -5.2, -1.0, 4.5, 1.9, 1.6, yaws[0]], [-30.1, 20.7, -0.8, 12.0, 2.5, 3.2, yaws[1]]])
    t = targets(boxes, np.array([0, 3]), g, 6)
    assert t["mask"].sum() == 2 and t["heatmap"].max() == 1.0
    reg = np.zeros((REG_CHANNELS, *g.out_shape), np.float32)
    for n in range(2):
        cy, cx = divmod(int(t["index"][n]), g.out_shape[1])
        reg[:, cy, cx] = t["reg"][n]
    heat = t["heatmap"] * (t["heatmap"] == 1)
    out, _scores, cls = decode(heat, reg, g)
    np.testing.assert_allclose(out[:, :6], boxes[:, :6], atol=1e-5)
    turn = np.angle(np.exp(1j * (out[:, 6] - boxes[:, 6])))  # the heading, not only the axis, comes back
    np.testing.assert_allclose(turn, 0.0, atol=1e-5)
    assert cls.tolist() == [0, 3]
    # a box and the same box turned by pi share the axis channels and differ in the direction target alone
    turned = targets(boxes + np.array([0, 0, 0, 0, 0, 0, math.pi]), np.array([0, 3]), g, 6)
    np.testing.assert_allclose(turned["reg"][:2, :8], t["reg"][:2, :8], atol=1e-5)
    assert (turned["reg"][:2, 8] + t["reg"][:2, 8]).tolist() == [1.0, 1.0]


@needs_torch
def test_regression_loss_scores_the_direction_by_cross_entropy():
    import torch

    from cosim.learn.model import regression_loss

    target = torch.zeros(1, 1, REG_CHANNELS)
    target[0, 0, 8] = 1.0
    index, mask = torch.zeros(1, 1, dtype=torch.long), torch.ones(1, 1)
    right, wrong = torch.zeros(1, REG_CHANNELS, 1, 1), torch.zeros(1, REG_CHANNELS, 1, 1)
    right[0, 8], wrong[0, 8] = 4.0, -4.0
    l_right, l_wrong = (float(regression_loss(r, target, index, mask)) for r in (right, wrong))
    assert l_right == pytest.approx(0.2 * math.log1p(math.exp(-4.0)), rel=1e-5)
    assert l_wrong == pytest.approx(0.2 * math.log1p(math.exp(4.0)), rel=1e-5)


def test_circle_nms_keeps_the_best_of_close_centres():
    centres = np.array([[0.0, 0.0], [0.5, 0.0], [10.0, 0.0], [10.0, 1.9]])
    keep = circle_nms(centres, np.array([0.5, 0.9, 0.3, 0.8]), radius_m=2.0)
    assert keep.tolist() == [1, 3]


def test_default_grid_covers_the_evaluation_area():
    from cosim.eval.dataset import AREA_HALF_M

    g = Grid()
    assert (g.x_range, g.y_range) == ((-AREA_HALF_M[0], AREA_HALF_M[0]), (-AREA_HALF_M[1], AREA_HALF_M[1]))
    assert g.max_pillars >= g.nx * g.ny  # a dense merged cloud loses no pillar
    far = np.array([[130.0, -35.0, -1.0, 4.5, 1.9, 1.6, 0.3]])
    t = targets(far, np.array([0]), g, 1)
    assert t["mask"].sum() == 1 and t["heatmap"].max() == 1.0  # an object the evaluation counts is a target


def test_delivery_draw_is_repeatable():
    from cosim.learn.data import _delivered

    assert not _delivered("ep", 3, "rsu_0", "vehicle_0", 0.0)
    assert _delivered("ep", 3, "rsu_0", "vehicle_0", 1.0)
    draws = [_delivered("ep", t, "rsu_0", "vehicle_0", 0.5) for t in range(200)]
    assert draws == [_delivered("ep", t, "rsu_0", "vehicle_0", 0.5) for t in range(200)]
    assert 60 < sum(draws) < 140


# ------------------------------------------------------------------------------------------ torch-free core


def test_core_and_run_path_never_import_torch(tmp_path):
    code = f"""
import sys
import cosim.cli
cosim.cli.build_parser()
import cosim.eval.evaluate, cosim.io.dataset, cosim.learn.data, cosim.learn.grid, cosim.learn.nms, cosim.learn.cli
assert 'torch' not in sys.modules, 'importing the core imported torch'
rc = cosim.cli.main(['run', 'default', '--duration', '0.2', '--out', {str(tmp_path)!r}, '-q',
                     '--set', 'map.size_m=300', '--set', 'sensors.vehicle.cameras=[]',
                     '--set', 'sensors.rsu.cameras=[]', '--set', 'sensors.drone.cameras=[]'])
assert rc == 0, rc
assert 'torch' not in sys.modules, 'cosim run imported torch'
print('ok')
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=REPO)
    assert r.returncode == 0 and r.stdout.strip().endswith("ok"), r.stderr[-3000:]


def test_learn_without_torch_says_how_to_install(tmp_path):
    fake = tmp_path / "site" / "torch"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text("raise ModuleNotFoundError(\"No module named 'torch'\", name='torch')\n")
    env = {"PYTHONPATH": f"{tmp_path / 'site'}:{REPO}"}
    (tmp_path / "trained").mkdir()  # predict's RUN must exist: the argument check comes before torch is needed
    for args in (["learn", "train", str(tmp_path), "--out", str(tmp_path / "run")],
                 ["learn", "predict", str(tmp_path / "trained"), str(tmp_path), "--out", str(tmp_path / "p.jsonl")]):
        r = run_cli(*args, env=env)
        assert r.returncode == 2, r.stderr
        assert "pip install -e '.[learn]'" in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


# ------------------------------------------------------------------------------------------ trained on real data


def cosim(capsys, *args: str) -> str:
    """``cosim ARGS`` in this process (the main() a user's command runs, without a new interpreter importing torch
    afresh): its standard output; the test fails unless it exits 0."""
    status, out, err = cli_in_process(capsys, *args)
    assert status == 0, err[-3000:]
    return out


@pytest.fixture(scope="module")
def tiny_batch(tmp_path_factory) -> Path:
    sweep = SWEEP.format(base=REPO / "scenarios" / "base" / "paper.yaml")
    return run_sweep(tmp_path_factory.mktemp("learnbatch"), sweep)


@pytest.fixture(scope="module")
def trained(tiny_batch, tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("learnrun") / "run"
    r = run_cli("learn", "train", str(tiny_batch), "--out", str(run), "--steps", "30", "--batch-size", "2",
                "--lr", "5e-3", "--threads", "1", "--seed", "1", "-q")
    assert r.returncode == 0, r.stderr[-3000:]
    assert "steps    30" in r.stdout
    return run


@needs_torch
@pytest.mark.integration
@pytest.mark.timeout(900)
def test_thirty_steps_lower_the_loss(trained):
    rows = [json.loads(line) for line in (trained / "log.jsonl").read_text().splitlines()]
    loss = [r["loss"] for r in rows if "loss" in r]
    assert len(loss) == 30
    assert np.mean(loss[-5:]) < 0.5 * np.mean(loss[:5]), loss


@needs_torch
@pytest.mark.integration
@pytest.mark.timeout(900)
def test_predictions_pass_the_validator_and_score_on_training_episodes(trained, tiny_batch, tmp_path, capsys):
    from cosim.eval.predictions import read_predictions

    preds = tmp_path / "preds.jsonl"
    cosim(capsys, "learn", "predict", str(trained), str(tiny_batch), "--split", "train", "--out", str(preds), "-q")
    records = read_predictions(preds)  # the validator of cosim eval: raises on any malformed record
    assert len(records) == 2 * 5 and {rec.agents for rec in records} == {"ego"}
    cosim(capsys, "eval", "--gt", str(tiny_batch), "--split", "train", "--pred", str(preds), "--visible-only",
          "--out", str(tmp_path / "eval"))
    overall = json.loads((tmp_path / "eval" / "eval.json").read_text())
    ap30 = _ap(overall, "AP30")
    assert ap30 > 0.0, overall


def _ap(doc: dict, key: str) -> float:
    for table in doc["tables"]:
        if table["name"] == "overall":
            row = table["rows"][0]
            return float(row[table["columns"].index(key)])
    raise AssertionError("no overall table")


@needs_torch
@pytest.mark.integration
@pytest.mark.timeout(900)
def test_same_seed_same_weights_and_resume_continues_exactly(tiny_batch, tmp_path):
    import torch

    from cosim.eval.dataset import load_dataset
    from cosim.learn.data import Setup
    from cosim.learn.train import CHECKPOINT, TrainOptions, train

    refs = [r for r in load_dataset(tiny_batch) if r.split == "train"]
    setup = Setup(fusion="early", agents="all")

    def weights(run: Path) -> dict:
        return torch.load(run / CHECKPOINT, weights_only=False)["model"]

    opts = TrainOptions(steps=4, batch_size=2, seed=3, every=2, threads=1)
    train(refs, None, setup, opts, tmp_path / "a", show_progress=False)
    train(refs, None, setup, opts, tmp_path / "b", show_progress=False)
    train(refs, None, setup, TrainOptions(steps=4, batch_size=2, seed=4, every=2, threads=1), tmp_path / "c",
          show_progress=False)
    half = TrainOptions(steps=2, batch_size=2, seed=3, every=2, threads=1)
    train(refs, None, setup, half, tmp_path / "d", show_progress=False)
    train(refs, None, setup, opts, tmp_path / "d", resume=True, show_progress=False)
    a, b, c, d = (weights(tmp_path / n) for n in "abcd")
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not all(torch.equal(a[k], c[k]) for k in a)
    assert all(torch.equal(a[k], d[k]) for k in a), "a resumed run differs from an uninterrupted one"
    assert len((tmp_path / "d" / "log.jsonl").read_text().splitlines()) == 4


@needs_torch
@pytest.mark.integration
@pytest.mark.timeout(900)
def test_late_fusion_detects_per_agent_and_merges(tiny_batch, tmp_path):
    from cosim.eval.dataset import load_dataset
    from cosim.learn.data import Samples, Setup
    from cosim.learn.train import TrainOptions, load_run, predict_sample, train

    refs = [r for r in load_dataset(tiny_batch) if r.split == "train"]
    setup = Setup(fusion="late", agents="all")
    train(refs, None, setup, TrainOptions(steps=2, batch_size=2, every=2, threads=1), tmp_path / "late",
          show_progress=False)
    model, loaded, _ = load_run(tmp_path / "late")
    assert loaded == setup
    samples = Samples(refs, setup, every=2)
    item = max((samples.item(i) for i in range(len(samples))), key=lambda it: len(it["clouds"]))
    assert len(item["clouds"]) >= 2 and all(len(s) == 1 for s in item["sources"])  # one cloud per agent
    boxes, _scores, _ = predict_sample(model, item, setup, model.heat.weight.device, score_min=0.0)
    centres = boxes[:, :2]
    gaps = np.linalg.norm(centres[:, None] - centres[None], axis=2) + np.eye(len(centres)) * 1e9
    assert gaps.min() >= 2.0  # merged: no two kept boxes closer than the NMS radius
    samples.close()


@needs_torch
@pytest.mark.integration
@pytest.mark.timeout(900)
def test_augmented_finer_front_view_model_trains_and_predicts_from_the_cli(tiny_batch, tmp_path, capsys):
    """Every augmentation of issue 48 on, 0.4 m pillars over a front view, width 32, on real episodes, through
    the commands a user types; the run records its grid and options, predict rebuilds them
    (tests/test_learn_augment.py checks each transform)."""
    from cosim.eval.predictions import read_predictions

    run, preds = tmp_path / "run", tmp_path / "preds.jsonl"
    cosim(capsys, "learn", "train", str(tiny_batch), "--out", str(run), "--steps", "3", "--batch-size", "2",
          "--every", "2", "--threads", "1", "--turn", "45", "--scale", "0.95", "1.05", "--translate-m", "0.2",
          "--height-jitter-m", "0.2", "--point-drop", "0.1", "--intensity-scale", "2", "--intensity-noise",
          "0.05", "--gt-sample", "4", "--pillar-m", "0.4", "--range-m", "0", "70.4", "-40", "40", "--width",
          "32", "-q")
    summary = json.loads((run / "summary.json").read_text())
    assert summary["setup"]["grid"]["pillar_m"] == 0.4 and summary["setup"]["grid"]["x_range"] == [0.0, 70.4]
    assert summary["options"]["gt_sample"] == 4 and summary["options"]["width"] == 32
    assert summary["gt_database_objects"] > 0
    cosim(capsys, "learn", "predict", str(run), str(tiny_batch), "--split", "train", "--every", "2", "--out",
          str(preds), "-q")
    records = read_predictions(preds)
    x = np.concatenate([rec.centers_m[:, 0] for rec in records])
    assert len(records) > 0 and len(x) > 0
    assert x.min() >= -0.8  # the front view's boxes: ahead of the sensor (up to one output cell of offset)


@needs_torch
@pytest.mark.integration
@pytest.mark.timeout(900)
def test_bad_input_one_message_exit_2(trained, tiny_batch, tmp_path, capsys):
    import torch

    empty = tmp_path / "empty"
    empty.mkdir()
    cases = [
        (["learn", "train", str(tiny_batch), "--out", str(tmp_path / "r1"), "--split", "nope"], "no episode in split"),
        (["learn", "train", str(empty), "--out", str(tmp_path / "r2")], "no finished episodes"),
        (["learn", "train", str(tiny_batch), "--out", str(tmp_path / "r3"), "--classes", "zeppelin"],
         "no class zeppelin"),
        (["learn", "train", str(tiny_batch), "--out", str(tmp_path / "r4"), "--fusion", "none", "--agents", "all"],
         "fusion none uses the ego alone"),
        (["learn", "train", str(tiny_batch), "--out", str(trained), "--steps", "1"], "already holds a training run"),
        (["learn", "predict", str(tmp_path), str(tiny_batch), "--out", str(tmp_path / "p.jsonl")], "no checkpoint.pt"),
        (["learn", "predict", str(trained), str(tiny_batch), "--out", str(tmp_path / "p.txt")], "a .jsonl file"),
    ]
    ckpt = torch.load(trained / "checkpoint.pt", weights_only=False)
    ckpt["setup"]["classes"] = ["car", "zeppelin", *ckpt["setup"]["classes"][2:]]  # same head, one class unknown
    other = tmp_path / "other"
    other.mkdir()
    torch.save(ckpt, other / "checkpoint.pt")
    cases.append((["learn", "predict", str(other), str(tiny_batch), "--out", str(tmp_path / "p.jsonl")],
                  "no class zeppelin"))
    old_format = tmp_path / "old_format"
    old_format.mkdir()
    torch.save({**torch.load(trained / "checkpoint.pt", weights_only=False), "format": 1}, old_format / "checkpoint.pt")
    cases += [(["learn", "predict", str(old_format), str(tiny_batch), "--out", str(tmp_path / "p.jsonl")],
               "changed the yaw head"),
              (["learn", "train", str(tiny_batch), "--out", str(old_format), "--steps", "2", "--resume"],
               "changed the yaw head")]
    cases += [
        (["learn", "train", str(tiny_batch), "--out", str(tmp_path / "r5"), "--cache", str(empty)], "no cache.json"),
        (["learn", "predict", str(trained), str(tiny_batch), "--out", str(tmp_path / "p.jsonl"), "--fusion",
          "intermediate", "--agents", "all"], "needs a model trained for it"),
        (["learn", "recall", str(tiny_batch), str(tmp_path / "none.jsonl"), "--out", str(tmp_path / "rc")],
         "no prediction file at"),
        (["learn", "recall", str(tiny_batch), str(trained / "log.jsonl"), "--out", str(tmp_path / "rc"), "--by",
          "weekday"], "--by weekday: not a condition"),
        (["learn", "train", str(tiny_batch), "--out", str(tmp_path / "r6"), "--turn", "200"],
         "--turn must be 0 to 180 degrees, got 200"),
        (["learn", "cache", str(tiny_batch), "--out", str(tmp_path / "c"), "--split", "nope"], "no episode in split"),
    ]
    # The first case as the program a user runs; the others in this process (the same main(), without
    # importing torch afresh 18 times).
    (args, words), *rest = cases
    r = run_cli(*args)
    outcomes = [(args, words, r.returncode, r.stderr)]
    outcomes += [(args, words, *cli_in_process(capsys, *args)[::2]) for args, words in rest]
    for args, words, status, err in outcomes:
        assert status == 2, (args, err[-2000:])
        lines = [line for line in err.strip().splitlines() if "Warning" not in line]
        assert words in err and len(lines) == 1, (args, err[-2000:])


@needs_torch
@pytest.mark.integration
@pytest.mark.timeout(900)
def test_early_model_predicts_with_fewer_agents_than_trained(tiny_batch, tmp_path, capsys):
    from cosim.eval.dataset import load_dataset
    from cosim.eval.predictions import SETTINGS, read_predictions
    from cosim.learn.data import Samples, Setup
    from cosim.learn.train import TrainOptions, train

    refs = [r for r in load_dataset(tiny_batch) if r.split == "train"]
    train(refs, None, Setup(fusion="early", agents="all"), TrainOptions(steps=2, batch_size=2, every=2, threads=1),
          tmp_path / "early", show_progress=False)
    for agents in ("vehicles", "vehicles+drones"):
        preds = tmp_path / f"{agents}.jsonl"
        out = cosim(capsys, "learn", "predict", str(tmp_path / "early"), str(tiny_batch), "--split", "train", "--every",
                    "2", "--agents", agents, "--out", str(preds), "-q")
        assert f"fusion early, agents {agents}" in out
        assert {rec.agents for rec in read_predictions(preds)} == {agents}
        samples = Samples(refs, Setup(fusion="early", agents=agents), every=2)
        kinds = {src.rsplit("_", 1)[0] for i in range(len(samples)) for src in samples.item(i)["sources"][0]}
        samples.close()
        assert kinds <= {"vehicle", *SETTINGS[agents]} and "rsu" not in kinds, kinds
    assert "drone" in kinds  # the tiny batch's drone is in range: the +drones setting uses it


# ------------------------------------------------------------------------------------------ issue 35


def test_numpy_only_modules_agree_with_the_ones_they_mirror():
    from cosim.eval.dataset import AREA_HALF_M, VEHICLE_CLASSES
    from cosim.io.dataset import LIDAR_MODES, PAPER_COMM_RANGE_M
    from cosim.learn import grid, samples

    assert grid.AREA_HALF_M == AREA_HALF_M and samples.VEHICLE_CLASSES == VEHICLE_CLASSES
    assert samples.COMM_RANGE_M == PAPER_COMM_RANGE_M and samples.LIDAR_MODES == LIDAR_MODES


def test_training_modules_import_no_mcap_reader():
    code = ("import sys\nimport cosim.learn.train, cosim.learn.model, cosim.learn.samples\n"
            "bad = [m for m in sys.modules if m.split('.')[0] in ('mcap', 'lz4', 'zstandard', 'pydantic', 'yaml') "
            "or m.startswith('cosim.io')]\nassert not bad, bad\nprint('ok')\n")
    if not HAVE_TORCH:
        pytest.skip("PyTorch is not installed")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr[-2000:]


def _record(collab_pose: tuple[float, float, float], obj_xy: tuple[float, float]) -> dict:
    """A learn record: ego vehicle_0 at the map origin, collaborator rsu_0 at (x, y, yaw) in map (= ego frame),
    a car at obj_xy that only the collaborator has returns on (a 3 x 3 block of points on it)."""
    from cosim.learn.samples import quantise

    x, y, yaw = collab_pose
    pose = np.eye(4)
    pose[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    pose[:2, 3] = [x, y]
    obj = np.array([[obj_xy[0] + dx, obj_xy[1] + dy, -1.0] for dx in (-0.3, 0.0, 0.3) for dy in (-0.3, 0.0, 0.3)])
    local = (obj - pose[:3, 3]) @ pose[:3, :3]  # the car's points in the collaborator's LiDAR frame
    ego_pts, _ = quantise(np.array([[-30.3, 20.3, -1.9]]))
    col_pts, _ = quantise(local)
    return {"tick": 0, "t_ns": 0, "agents": ["vehicle_0", "rsu_0"], "map_from": np.stack([np.eye(4), pose]),
            "points": [ego_pts, col_pts], "intensity": [np.full(1, 50, np.uint8), np.full(9, 200, np.uint8)],
            "hits": [np.zeros((2, 0), np.int64), np.array([[9], [9]], np.int64)],
            "label_track_ids": np.array([9]), "label_classes": ["car"],
            "label_centers": np.array([[obj_xy[0], obj_xy[1], -1.0]]),
            "label_rotations": np.array([[0.0, 0.0, 0.0, 1.0]]), "label_sizes": np.array([[4.4, 1.8, 1.5]]),
            "agent_tracks": {}, "links": None}


@needs_torch
@pytest.mark.parametrize("yaw_deg", [0.0, 37.0, 90.0, 180.0, -135.0, 271.5])
def test_intermediate_fusion_puts_a_collaborators_object_in_its_ego_cell(yaw_deg):
    import torch

    from cosim.learn.model import fuse
    from cosim.learn.samples import Setup, make_item
    from cosim.learn.train import batch_arrays

    setup = Setup(fusion="intermediate", agents="all")
    g = setup.grid
    obj = (33.3, -12.7)
    item = make_item(_record((61.0, 17.0, np.radians(yaw_deg)), obj), "vehicle_0", setup, "ep")
    assert [s[0] for s in item["sources"]] == ["vehicle_0", "rsu_0"] and len(item["clouds"][1]) == 9
    assert len(item["targets"][0][0]) == 1  # the car: a target, seen by the collaborator alone
    b = batch_arrays(item["clouds"], setup, [2], [item["poses"]], [item["encoder"]])
    # each pillar's feature: 1 in channel 0 for the ego's pillars, channel 1 for the collaborator's
    agent_of = b["coords"][:, 0] % 2
    feats = torch.zeros(len(agent_of), 2)
    feats[torch.arange(len(agent_of)), torch.from_numpy(agent_of)] = 1.0
    hits = [torch.from_numpy(b[k]) for k in ("cell", "src", "ego")]
    fused = fuse(feats, *hits, g.ny * g.nx, "max").T.reshape(2, g.ny, g.nx)
    col = int((obj[0] - g.x_range[0]) // g.pillar_m)
    row = int((obj[1] - g.y_range[0]) // g.pillar_m)
    ys, xs = np.nonzero(fused[1].numpy())
    assert len(ys) >= 1
    assert (abs(ys - row) <= 1).all() and (abs(xs - col) <= 1).all(), (ys, xs, row, col)  # the car's cell
    assert fused[1, row, col] == 1.0  # the cell under the car's centre point holds the collaborator's feature
    ego_cell = (int((20.3 - g.y_range[0]) // g.pillar_m), int((-30.3 - g.x_range[0]) // g.pillar_m))
    assert fused[0, ego_cell[0], ego_cell[1]] == 1.0 and fused[0].sum() == 1.0  # the ego's own map: unwarped
    attn = fuse(feats, *hits, g.ny * g.nx, "attention").T.reshape(2, g.ny, g.nx)
    assert attn[1, row, col] == 1.0  # attention: the only agent with a pillar there takes the cell


@needs_torch
def test_sparse_fusion_matches_a_cell_by_cell_reference():
    """The warp's hits and both fusions against a plain loop over ego cells and agents: every ego cell centre
    moved into each agent's frame by its 4x4 pose, the agent's pillar there looked up by cell, then the max or
    the softmax of <ego feature, agent feature> / sqrt(C) over the agents that have one."""
    import torch

    from cosim.learn.grid import warp_index
    from cosim.learn.model import fuse

    g = Grid(x_range=(-8.0, 8.0), y_range=(-4.0, 4.0), pillar_m=1.0)
    agent = Grid(x_range=(-20.0, 20.0), y_range=(-20.0, 20.0), pillar_m=1.0)
    rng = np.random.default_rng(3)
    n_b, n_j, c = 2, 3, 4
    present = np.array([[True, True, True], [True, True, False]])
    poses = np.concatenate([np.zeros((n_b, 1, 3)), np.stack([rng.uniform(-np.pi, np.pi, (n_b, n_j - 1)),
                            rng.uniform(-6, 6, (n_b, n_j - 1)), rng.uniform(-3, 3, (n_b, n_j - 1))], axis=2)],
                           axis=1)
    cells = sorted({(m, int(r), int(q)) for m in range(n_b * n_j) if present.reshape(-1)[m]
                    for r, q in rng.integers(10, 30, (150, 2))})
    coords = np.array(cells, np.int64)
    feats = torch.from_numpy(rng.uniform(0, 1, (len(coords), c)))
    cell, src, ego = warp_index(coords, poses, present, g, agent)
    lookup = {cl: i for i, cl in enumerate(cells)}
    want_max = np.zeros((n_b * g.ny * g.nx, c))
    want_att = np.zeros((n_b * g.ny * g.nx, c))
    n_hits = 0
    for b in range(n_b):
        for row in range(g.ny):
            for col in range(g.nx):
                centre = np.array([g.x_range[0] + (col + 0.5) * g.pillar_m, g.y_range[0] + (row + 0.5) * g.pillar_m,
                                   0.0, 1.0])
                found = []
                for j in range(n_j):
                    if not present[b, j]:
                        continue
                    yaw, x, y = poses[b, j]
                    pose = np.eye(4)
                    pose[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
                    pose[:2, 3] = [x, y]
                    ax, ay = (np.linalg.inv(pose) @ centre)[:2]
                    key = (b * n_j + j, int(np.floor(ay - agent.y_range[0])), int(np.floor(ax - agent.x_range[0])))
                    if key in lookup:
                        found.append((j, feats[lookup[key]].numpy()))
                n_hits += len(found)
                if not found:
                    continue
                k = (b * g.ny + row) * g.nx + col
                f = np.stack([v for _j, v in found])
                want_max[k] = f.max(axis=0)
                own = next((v for j, v in found if j == 0), np.zeros(c))
                score = f @ own / np.sqrt(c)
                w = np.exp(score - score.max())
                want_att[k] = (w / w.sum()) @ f
    assert len(cell) == n_hits > 50 and ego.sum() > 0 and (~ego).sum() > 0
    hits = [torch.from_numpy(a) for a in (cell, src, ego)]
    np.testing.assert_allclose(fuse(feats, *hits, len(want_max), "max").numpy(), want_max, atol=1e-12)
    np.testing.assert_allclose(fuse(feats, *hits, len(want_max), "attention").numpy(), want_att, atol=1e-12)


@needs_torch
def test_pillar_encoder_is_the_max_over_each_pillars_points():
    import torch

    from cosim.learn.model import PillarDetector
    from cosim.learn.samples import Setup

    model = PillarDetector(Setup().grid, 6, width=8).eval()
    rng = np.random.default_rng(5)
    counts = np.array([1, 5, 32, 3])
    feats = torch.from_numpy(rng.normal(0, 1, (counts.sum(), 9)).astype(np.float32))
    got = model.encode(feats, torch.from_numpy(counts))
    point = torch.relu(model.pfn_bn(model.pfn(feats)))
    want = torch.stack([p.max(dim=0).values for p in torch.split(point, counts.tolist())])
    assert torch.equal(got, want) and (want > 0).any()


def test_agent_poses_follow_the_flips_and_turns():
    """Each agent's cloud, mirrored and turned in its own frame, lands where the ego's mirrored and turned
    cloud is, through the augmented pose: intermediate fusion's warp sees one consistent scene."""
    from cosim.learn.samples import augment, augment_poses, bev_pose, to_bev_frame

    rng = np.random.default_rng(1)
    ego_cloud = rng.uniform(-30, 30, (50, 4)).astype(np.float32)
    t = np.eye(4)
    yaw = 0.7
    t[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    t[:2, 3] = [12.0, -4.0]
    pose = bev_pose(t)
    local = to_bev_frame(ego_cloud, pose)
    for fx, fy, turn in ((True, False, 0.0), (False, True, 0.0), (True, True, 0.0), (False, False, 0.6),
                         (True, False, -0.3), (True, True, 2.5)):
        moved_ego, _ = augment(ego_cloud, np.zeros((0, 7)), fx, fy, turn)
        moved_local, _ = augment(local, np.zeros((0, 7)), fx, fy, turn)
        new_pose = augment_poses(pose[None], fx, fy, turn)[0]
        np.testing.assert_allclose(to_bev_frame(moved_ego, new_pose), moved_local, atol=1e-4)
        if turn:  # the turn moved the cloud: the check above is not the identity
            assert np.abs(moved_ego[:, :2] - augment(ego_cloud, np.zeros((0, 7)), fx, fy)[0][:, :2]).max() > 1.0


def test_a_turned_box_keeps_its_points_on_its_corners():
    from cosim.eval.boxes import footprints
    from cosim.learn.samples import augment

    box = np.array([[20.0, -6.0, -1.0, 4.6, 1.9, 1.5, 0.2]], np.float32)
    corners = footprints(box[:, :2], box[:, 3:5], box[:, 6])[0]  # (4, 2)
    cloud = np.c_[corners, np.full((4, 1), -1.0), np.ones((4, 1))].astype(np.float32)
    for fx, fy, turn in ((False, False, 0.5), (True, False, -0.7), (False, True, 1.2), (True, True, -2.0)):
        moved, boxes = augment(cloud, box, fx, fy, turn)
        got = footprints(boxes[:, :2], boxes[:, 3:5], boxes[:, 6])[0]
        # the same four corners, in some order (a mirror reverses their winding)
        d = np.linalg.norm(got[:, None, :] - moved[None, :, :2], axis=2)
        assert d.min(axis=1).max() < 1e-4, (fx, fy, turn, got, moved[:, :2])
        np.testing.assert_allclose(boxes[0, 3:6], box[0, 3:6])


@needs_torch
@pytest.mark.integration
@pytest.mark.timeout(900)
def test_cache_gives_the_uncached_samples_bit_for_bit(tiny_batch, tmp_path):
    from cosim.eval.dataset import load_dataset
    from cosim.learn.data import Samples, Setup, write_cache

    refs = load_dataset(tiny_batch)
    out = write_cache(refs, tmp_path / "cache", "tick", 1)
    assert out["episodes"] == 2
    for fusion, agents in (("none", "ego"), ("early", "all"), ("late", "vehicles+drones"), ("intermediate", "all")):
        setup = Setup(fusion=fusion, agents=agents)
        a, b = Samples(refs, setup), Samples(refs, setup, cache=tmp_path / "cache")
        assert len(a) == len(b) > 0
        for i in range(len(a)):
            x, y = a.item(i), b.item(i)
            assert [x[k] for k in ("episode", "tick", "ego", "sources")] == [y[k] for k in ("episode", "tick", "ego",
                                                                                         "sources")]
            assert all(p.dtype == q.dtype and np.array_equal(p, q)
                       for p, q in zip(x["clouds"], y["clouds"], strict=True))
            for (bp, lp), (bq, lq) in zip(x["targets"], y["targets"], strict=True):
                assert np.array_equal(bp, bq) and np.array_equal(lp, lq)
            if fusion == "intermediate":
                assert np.array_equal(x["poses"], y["poses"]) and np.array_equal(x["encoder"], y["encoder"])
        a.close()
        b.close()


@needs_torch
@pytest.mark.integration
@pytest.mark.timeout(900)
def test_compensation_modes_move_points_of_moving_agents(tiny_batch):
    from cosim.eval.dataset import load_dataset
    from cosim.io.dataset import CooperativeDataset

    ref = load_dataset(tiny_batch)[0]
    recs = {m: CooperativeDataset([ref.path], lidar=m).read_tick(ref.path, 3) for m in ("raw", "tick", "objects")}
    moved = [float(np.abs(recs["tick"]["lidar"][i][:, :3] - recs["raw"]["lidar"][i][:, :3]).max())
             for i in range(len(recs["raw"]["agents"]))]
    kinds = [a.rsplit("_", 1)[0] for a in recs["raw"]["agents"]]
    assert max(m for m, k in zip(moved, kinds, strict=True) if k == "vehicle") > 0.01  # a driving vehicle's sweep
    assert all(m < 1e-3 for m, k in zip(moved, kinds, strict=True) if k == "rsu")  # a fixed RSU: float rounding only
    objects = [not np.array_equal(recs["objects"]["lidar"][i], recs["tick"]["lidar"][i]) for i in range(len(moved))]
    assert any(objects)  # some sweep has points on a moving object


@pytest.fixture(scope="module")
def tiny_cache(tiny_batch, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("learncache") / "cache"
    r = run_cli("learn", "cache", str(tiny_batch), "--out", str(out), "-q")
    assert r.returncode == 0, r.stderr[-3000:]
    return out


@needs_torch
@pytest.mark.integration
@pytest.mark.timeout(900)
@pytest.mark.parametrize("fusion", ["early", "late", "intermediate"])
def test_thirty_steps_of_each_fusion_lower_the_loss(tiny_batch, tiny_cache, fusion, tmp_path):
    from cosim.eval.dataset import load_dataset
    from cosim.learn.data import Setup
    from cosim.learn.train import TrainOptions, train

    refs = [r for r in load_dataset(tiny_batch) if r.split == "train"]
    setup = Setup(fusion=fusion, agents="all", fuse="attention" if fusion == "intermediate" else "max")
    train(refs, None, setup, TrainOptions(steps=30, batch_size=2, lr=5e-3, threads=1, seed=1), tmp_path / "run",
          show_progress=False, cache=tiny_cache)
    loss = [json.loads(line)["loss"] for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert len(loss) == 30
    assert np.mean(loss[-5:]) < 0.5 * np.mean(loss[:5]), loss


@needs_torch
@pytest.mark.integration
@pytest.mark.timeout(900)
def test_intermediate_training_is_deterministic_with_workers_and_keeps_the_best(tiny_batch, tiny_cache, tmp_path):
    import torch

    from cosim.eval.dataset import load_dataset
    from cosim.learn.data import Setup
    from cosim.learn.train import BEST, CHECKPOINT, TrainOptions, train

    refs = load_dataset(tiny_batch)
    train_refs = [r for r in refs if r.split == "train"]
    test_refs = [r for r in refs if r.split == "test"]
    setup = Setup(fusion="intermediate", agents="all", encoders="kind")
    for name, workers in (("a", 0), ("b", 2)):
        train(train_refs, test_refs, setup, TrainOptions(steps=4, batch_size=2, seed=3, threads=1, workers=workers,
                                                         val_steps=2, val_every_tick=2, turn_deg=45.0),
              tmp_path / name, show_progress=False, cache=tiny_cache)
    a, b = (torch.load(tmp_path / n / CHECKPOINT, weights_only=False)["model"] for n in "ab")
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert any(k.startswith("kind_pfn") for k in a)  # one encoder per agent kind
    # one encoder per LiDAR, on data with one LiDAR per kind: the per-kind model, weight for weight
    train(train_refs, test_refs, replace(setup, encoders="sensor"),
          TrainOptions(steps=4, batch_size=2, seed=3, threads=1, workers=0, val_steps=2, val_every_tick=2,
                       turn_deg=45.0), tmp_path / "c", show_progress=False, cache=tiny_cache)
    c = torch.load(tmp_path / "c" / CHECKPOINT, weights_only=False)
    assert c["setup"]["sensors"] == ["vehicle", "rsu", "drone"]
    assert {k.replace("sensor_", "kind_"): v for k, v in c["model"].items()}.keys() == a.keys()
    assert all(torch.equal(a[k], c["model"][k.replace("kind_", "sensor_")]) for k in a)
    assert (tmp_path / "a" / BEST).is_file()
    vals = [json.loads(line) for line in (tmp_path / "a" / "log.jsonl").read_text().splitlines() if "val" in line]
    assert [v["step"] for v in vals] == [2, 4]
    best = torch.load(tmp_path / "a" / BEST, weights_only=False)
    assert best["best_ap50"] == max(v["val"]["AP50"] for v in vals)


@needs_torch
@pytest.mark.integration
@pytest.mark.timeout(900)
def test_validate_rescores_kept_checkpoints_as_the_training_did(tiny_batch, tiny_cache, tmp_path, capsys):
    """``cosim learn validate`` on a run's kept checkpoints, from the cache and from a step on, gives the
    training's own validation numbers on the same ticks, and scores each step once per split and ``--every``."""
    from cosim.eval.dataset import load_dataset
    from cosim.learn.data import Setup
    from cosim.learn.train import TrainOptions, read_log, train

    refs = load_dataset(tiny_batch)
    run = tmp_path / "run"
    train([r for r in refs if r.split == "train"], [r for r in refs if r.split == "test"],
          Setup(fusion="early", agents="all"), TrainOptions(steps=4, batch_size=2, seed=3, threads=1, val_steps=2,
                                                             val_every_tick=2, keep_every=2),
          run, show_progress=False, cache=tiny_cache)
    own = {r["step"]: r["val"] for r in read_log(run) if "val" in r}
    assert sorted(own) == [2, 4]
    capsys.readouterr()  # the training's own lines

    def validate(*extra: str) -> dict[int, str]:
        status, out, err = cli_in_process(capsys, "learn", "validate", str(run), str(tiny_batch), "--split", "test",
                                          "--threads", "1", *extra)
        assert status == 0, err
        return {int(line.split()[1].rstrip(":")): line for line in out.splitlines() if line.startswith("step ")}

    assert sorted(validate("--every", "2", "--cache", str(tiny_cache), "--from-step", "4")) == [4]
    assert validate("--every", "2", "--cache", str(tiny_cache), "--from-step", "4") == {}  # scored before
    assert sorted(validate("--every", "2")) == [2]  # from the MCAP files: the step not scored yet
    assert sorted(validate("--every", "4", "--from-step", "3")) == [4]  # another --every: scored again
    rescored = {(r["step"], r["every"]): r["val"] for r in read_log(run) if r.get("split") == "test"}
    assert rescored[(4, 2)] == own[4] and rescored[(2, 2)] == own[2]
    assert set(rescored) == {(4, 2), (2, 2), (4, 4)}


@needs_torch
@pytest.mark.integration
@pytest.mark.timeout(900)
def test_recall_counts_the_objects_the_ego_does_not_see(trained, tiny_batch, tmp_path, capsys):
    preds = []
    for agents in ("ego", "all"):
        p = tmp_path / f"{agents}.jsonl"
        args = ["--fusion", "late", "--agents", "all"] if agents == "all" else []
        cosim(capsys, "learn", "predict", str(trained), str(tiny_batch), "--split", "train", "--out", str(p), "-q",
              *args)
        preds.append(str(p))
    cosim(capsys, "learn", "recall", str(tiny_batch), *preds, "--split", "train", "--out", str(tmp_path / "recall"),
          "--min-score", "0.0")
    rows = json.loads((tmp_path / "recall" / "recall.json").read_text())["rows"]
    assert [row["agents"] for row in rows] == ["ego", "all"]
    ego, allr = rows
    assert ego["frames"] == allr["frames"] == 10 and ego["ego-blind"] == allr["ego-blind"]
    assert ego["ego-blind seen by setting"] == 0  # the ego alone sees none of its blind objects
    assert allr["ego-blind seen by setting"] >= allr["found (ego-blind)"] >= 0
    for row in rows:  # the tightness table scores exactly the matched boxes
        assert row["found"] == row["found (ego-blind)"] + row["found (ego-seen)"]
    assert "How tight the found boxes are" in (tmp_path / "recall" / "recall.md").read_text()
    # by a condition: one row per file and value, whose counts add up to the file's
    cosim(capsys, "learn", "recall", str(tiny_batch), *preds, "--split", "train", "--out", str(tmp_path / "by"),
          "--min-score", "0.0", "--by", "environment")
    by = json.loads((tmp_path / "by" / "recall.json").read_text())
    assert by["by"] == "environment" and [row["environment"] for row in by["rows"]] == ["urban", "urban"]
    for row, whole in zip(by["rows"], rows, strict=True):  # (as JSON text: NaN, a share of nothing, is not == NaN)
        assert json.dumps({k: v for k, v in row.items() if k != "environment"}, sort_keys=True) == json.dumps(
            whole, sort_keys=True)
    assert "| predictions | environment | agents |" in (tmp_path / "by" / "recall.md").read_text()


def test_box_errors_are_measured_in_the_true_box_frame():
    from cosim.learn.recall import box_errors, error_summary

    yaw = 0.7
    along, across = np.array([math.cos(yaw), math.sin(yaw)]), np.array([-math.sin(yaw), math.cos(yaw)])
    gt_c = np.array([[10.0, 5.0, -1.0], [0.0, 0.0, -1.0]])
    det_c = gt_c + np.r_[0.4 * along - 0.1 * across, 0.0][None, :] * np.array([[1.0], [0.0]])
    err = box_errors(det_c, np.array([[4.9, 2.0, 1.5], [4.5, 1.8, 1.5]]), np.array([yaw + math.pi + 0.1, -yaw]),
                     gt_c, np.array([[4.5, 1.8, 1.5], [4.5, 1.8, 1.5]]), np.array([yaw, yaw]))
    np.testing.assert_allclose(err[0, :4], [0.4, -0.1, 0.4, 0.2], atol=1e-9)
    np.testing.assert_allclose(err[0, 5], 0.1, atol=1e-9)  # the axis is off by 0.1 rad; the heading by a half turn
    np.testing.assert_allclose(err[1, 4:], [-2 * yaw, 2 * yaw], atol=1e-9)
    summary = error_summary(err)
    assert summary["found"] == 2 and summary["heading flipped %"] == 50.0
    assert summary["yaw deg (mod 180)"] == pytest.approx(math.degrees((0.1 + 2 * yaw) / 2), abs=0.05)
