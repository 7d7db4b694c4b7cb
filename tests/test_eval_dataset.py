"""``cosim coverage`` and ``cosim eval`` on a small generated batch with sensors (real pipeline, real MCAP).

One session-scoped batch (2 episodes of 1 s, urban and rural, cameras at 0.1 scale) is shared by
every test here; a labels-only episode checks the messages for data without visibility or BEV.
"""

from __future__ import annotations

import itertools
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from cosim.cli import main
from cosim.errors import InputError
from cosim.eval.baselines import OracleNoise, write_predictions
from cosim.eval.coverage import compute_coverage
from cosim.eval.dataset import VEHICLE_CLASSES, VisibilityRule, load_dataset
from cosim.eval.evaluate import EvalOptions, evaluate
from cosim.eval.predictions import SETTINGS, read_predictions
from cosim.io import open_episode
from cosim.io.synthetic import write_synthetic_episode
from tests.helpers import REPO, run_cli, run_sweep
from tests.helpers import cli_in_process as cli

pytestmark = pytest.mark.integration

SWEEP = """\
name: evaltest
description: two tiny episodes with sensors for the evaluation tests
seed: 3
base: {base}
set:
  duration_s: 1
  map.size_m: 300
  traffic.density_veh_per_km: 10
  agents.rsus.count: 2
  sensors.image_scale: 0.1
axes:
  environment: {{key: map.kind, values: [urban, rural]}}
vary:
  environment.weather: {{choice: [clear, foggy]}}
  environment.lighting: {{choice: [day, night]}}
  agents.vehicles.count: {{choice: [2, 3]}}
count: 2
"""


@pytest.fixture(scope="session")
def batch(tmp_path_factory) -> Path:
    sweep = SWEEP.format(base=REPO / "scenarios" / "base" / "paper.yaml")
    return run_sweep(tmp_path_factory.mktemp("evalbatch"), sweep)


@pytest.fixture(scope="session")
def oracle_run(batch, tmp_path_factory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("oracle")
    r = run_cli("eval", "--gt", str(batch), "--baseline", "oracle-noise", "--visible-only", "--out", str(out))
    assert r.returncode == 0, r.stderr[-3000:]
    return out, r.stdout


def _direct_counts(path: Path, rule: VisibilityRule) -> dict[str, int]:
    """Objects of the vehicle classes in each ego's area and how many the ego / all agents / ground agents see,
    counted straight from /labels/objects, /tf and /<agent>/visibility."""
    counts = {"objects": 0, "ego": 0, "all": 0, "vehicles+rsus": 0}
    with open_episode(path) as ep:
        vis_topics = [f"/{a}/visibility" for a in ep.agents]
        for tick in ep.ticks(topics=["/labels/objects", "/tf", *vis_topics]):
            seen = {a: {o["track_id"] for o in tick.visibility(a)["objects"]
                        if o["lidar_points"] >= rule.min_points or sum(o["pixels"].values()) >= rule.min_pixels}
                    for a in ep.agents}
            for ego in (a for a in ep.agents if a.startswith("vehicle_")):
                ego_from_map = np.linalg.inv(tick.transforms.to_root(f"{ego}/lidar"))
                labels = tick.labels
                for tid, cls, c, aid in zip(labels.track_ids, labels.classes, labels.centers_m, labels.agent_ids,
                                            strict=True):
                    x, y, _ = ego_from_map[:3, :3] @ c + ego_from_map[:3, 3]
                    if aid == ego or cls not in VEHICLE_CLASSES or abs(x) > 140.8 or abs(y) > 40:
                        continue
                    counts["objects"] += 1
                    counts["ego"] += tid in seen[ego]
                    counts["all"] += any(tid in s for s in seen.values())
                    counts["vehicles+rsus"] += any(tid in seen[a] for a in ep.agents if not a.startswith("drone_"))
    return counts


def test_coverage_prints_the_agent_type_table_and_matches_a_direct_count(batch, tmp_path):
    rule = VisibilityRule(min_points=3, min_pixels=2)
    r = run_cli("coverage", str(batch), "--out", str(tmp_path), "--min-points", "3", "--min-pixels", "2")
    assert r.returncode == 0, r.stderr[-3000:]
    assert "### Coverage by collaborating agent types" in r.stdout
    header = next(line for line in r.stdout.splitlines() if line.startswith("| condition"))
    assert "ego alone" in header and "+ vehicles + RSUs" in header and "all agents" in header
    for name in ("coverage.md", "coverage.csv", "coverage.json", "coverage_heatmap.png", "coverage_weather.png"):
        assert (tmp_path / name).stat().st_size > 0
    counts = json.loads((tmp_path / "coverage.json").read_text())["counts"]
    keys = ("ego", "all", "vehicles+rsus")
    total = dict.fromkeys(("objects", *keys), 0)
    for ref in load_dataset(batch):  # one urban and one rural episode: the environment rows are single episodes
        direct = _direct_counts(ref.path, rule)
        assert direct["objects"] > 0
        row = next(c for c in counts if c["breakdown"] == "environment" and c["value"] == ref.conditions["environment"])
        assert row["objects"] == direct["objects"]
        assert {k: row["seen"][k] for k in keys} == {k: direct[k] for k in keys}
        for k in total:
            total[k] += direct[k]
    # the printed overall row shows the same shares
    row = next(line for line in r.stdout.splitlines() if line.startswith("| all |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert int(cells[2]) == total["objects"]
    assert float(cells[3]) == pytest.approx(100 * total["ego"] / total["objects"], abs=0.05)
    assert float(cells[5]) == pytest.approx(100 * total["vehicles+rsus"] / total["objects"], abs=0.05)
    assert float(cells[7]) == pytest.approx(100 * total["all"] / total["objects"], abs=0.05)


def test_perfect_oracle_scores_ap_one_and_writes_tables_and_plots(oracle_run):
    out, stdout = oracle_run
    assert "| agents | frames | GT boxes | detections | AP30 | AP50 | AP70 | mIoU |" in stdout
    for name in ("eval.md", "eval.csv", "eval.json", "eval_overall.png", "eval_lighting.png", "eval_weather.png",
                 "eval_environment.png", "eval_strategy.png", "eval_pr.png", "predictions/oracle-noise.jsonl"):
        assert (out / name).stat().st_size > 0, name
    metrics = json.loads((out / "eval.json").read_text())["metrics"]
    for setting in SETTINGS:
        d = metrics[f"{setting}|overall|all"]["detection"]["vehicle"]
        assert d["n_gt"] > 0
        assert (d["AP30"], d["AP50"], d["AP70"]) == (100.0, 100.0, 100.0), setting
        seg = metrics[f"{setting}|overall|all"]["segmentation"]
        assert seg["iou"]["road"] == 100.0  # the map layers are copied from the ground truth
    md = (out / "eval.md").read_text()
    for title in ("Overall", "Per class", "By lighting", "By weather", "By environment", "By strategy",
                  "BEV segmentation IoU per layer"):
        assert f"### {title}" in md
    csv_tables = {line.split(",")[0] for line in (out / "eval.csv").read_text().splitlines()}
    assert {"overall", "per_class", "by_weather", "segmentation"} <= csv_tables


def test_perfect_oracle_ap_on_all_objects_equals_the_coverage_upper_bound(batch, oracle_run):
    refs = load_dataset(batch)
    preds = read_predictions(oracle_run[0] / "predictions" / "oracle-noise.jsonl")
    result = evaluate(refs, preds, EvalOptions(thresholds=(0.5,)))
    coverage = compute_coverage(refs)
    overall = coverage.counts[("overall", "all")]
    for setting in SETTINGS:
        ap = result.metrics(setting)["detection"]["vehicle"]["AP50"]
        assert ap == pytest.approx(overall.recall(setting), abs=1e-9), setting
    assert overall.recall("ego") < overall.recall("all")  # collaboration adds objects on this batch


def test_growing_noise_lowers_ap70_before_ap30(batch, tmp_path):
    refs = load_dataset(batch)
    aps = []
    for sigma in (0.0, 0.1, 0.2, 0.4):
        model = OracleNoise(pos_sigma_m=sigma, yaw_sigma_deg=10 * sigma, seed=0, settings=("all",), bev=False)
        preds = read_predictions(write_predictions(model, refs, tmp_path / f"{sigma}.jsonl"))
        d = evaluate(refs, preds, EvalOptions(visible_only=True)).metrics("all")["detection"]["vehicle"]
        aps.append((d["AP30"], d["AP50"], d["AP70"]))
    assert aps[0] == (100.0, 100.0, 100.0)
    for (a30, a50, a70), (b30, b50, b70) in itertools.pairwise(aps):
        assert b70 < a70 and b30 <= a30 and b50 <= a50
    for a30, a50, a70 in aps[1:]:
        assert a30 >= a50 >= a70
        assert 100 - a70 > 100 - a30  # the strict threshold loses first and most
    # 10 cm of noise leaves AP30 all but untouched (a two-wheeler's narrow box can fall below IoU 0.3 in the
    # noise's tail), while AP70 already drops
    assert aps[1][0] >= 99.5 and aps[1][2] < 100.0


def test_baseline_predictions_are_deterministic_and_splits_are_checked(batch, tmp_path):
    refs = load_dataset(batch)
    model = OracleNoise(pos_sigma_m=0.3, yaw_sigma_deg=3, miss_rate=0.2, seed=5, bev=False)
    a = write_predictions(model, refs, tmp_path / "a.jsonl").read_bytes()
    b = write_predictions(model, refs, tmp_path / "b.jsonl").read_bytes()
    assert a == b and len(a) > 1000
    other = write_predictions(OracleNoise(pos_sigma_m=0.3, yaw_sigma_deg=3, miss_rate=0.2, seed=6, bev=False), refs,
                              tmp_path / "c.jsonl").read_bytes()
    assert other != a
    with pytest.raises(InputError, match=r"no episode in split 'test'; splits present: all"):
        load_dataset(batch, split="test")
    assert [r.id for r in load_dataset(batch, split="all")] == [r.id for r in refs]


def test_release_compat_mode_skips_frames_without_detections(batch, oracle_run, tmp_path, capsys):
    # The oracle's predictions with every third frame's detections removed, so some frames have none.
    oracle = (oracle_run[0] / "predictions" / "oracle-noise.jsonl").read_text()
    records = [json.loads(line) for line in oracle.splitlines()]
    for i, rec in enumerate(records):
        if i % 3 == 0:
            rec["boxes"] = []
    folder = shutil.copytree(oracle_run[0] / "predictions", tmp_path / "predictions")  # BEV files by relative path
    preds = folder / "oracle-noise.jsonl"
    preds.write_text("".join(json.dumps(rec) + "\n" for rec in records))
    out = tmp_path / "out"
    assert main(["eval", "--gt", str(batch), "--pred", str(preds), "--compat", "airv2x", "--out", str(out)]) == 0
    md = (out / "eval.md").read_text()
    empty = sum(1 for rec in records if rec["boxes"] == [])
    assert empty > 0
    assert f"{empty} frames without detections skipped (release behaviour)" in md
    assert "mode: airv2x" in md


def test_prediction_references_are_checked_against_the_dataset(batch, tmp_path, capsys):
    ep = load_dataset(batch)[0]
    f = tmp_path / "p.jsonl"
    f.write_text(json.dumps({"episode": ep.id, "tick": 0, "ego": "vehicle_0", "boxes": [
        {"center_m": [5, 0, 0], "size_m": [4, 2, 1.5], "yaw_rad": 0, "class": "tank", "score": 0.5}]}) + "\n")
    assert main(["eval", "--gt", str(batch), "--pred", str(f), "--out", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        f"cosim: error: {f}:1: boxes[0].class: unknown class 'tank'; the episode's object classes are "
        + ", ".join(ep.object_classes)]
    f.write_text(json.dumps({"episode": ep.id, "tick": ep.n_ticks, "ego": "vehicle_0", "boxes": []}) + "\n")
    assert main(["eval", "--gt", str(batch), "--pred", str(f), "--out", str(tmp_path / "o")]) == 2
    assert f"{f}:1: tick: {ep.n_ticks} out of range" in capsys.readouterr().err


def test_missing_visibility_or_bev_topics_give_clear_messages(tmp_path, capsys):
    labels_only = write_synthetic_episode(tmp_path / "labels.mcap", ticks=2, sensors=False)
    assert main(["coverage", str(labels_only), "--out", str(tmp_path / "cov")]) == 2
    assert "has no /<agent>/visibility topics" in capsys.readouterr().err

    def drop_bev(tick, topic, msg):
        return None if topic.endswith("/bev") else msg

    no_bev = write_synthetic_episode(tmp_path / "nobev.mcap", ticks=2, edit=drop_bev)
    np.savez(tmp_path / "b.npz", car=np.zeros((320, 512), bool))
    f = tmp_path / "p.jsonl"
    f.write_text(json.dumps({"episode": "nobev", "tick": 0, "ego": "vehicle_0", "boxes": [], "bev": "b.npz"}) + "\n")
    assert main(["eval", "--gt", str(no_bev), "--pred", str(f), "--out", str(tmp_path / "ev")]) == 2
    err = capsys.readouterr().err
    assert f"{f}:1: bev: episode nobev has no /vehicle_0/bev topic" in err and "Traceback" not in err
    # without BEV fields the same episode scores detection alone
    f.write_text(json.dumps({"episode": "nobev", "tick": 0, "ego": "vehicle_0", "boxes": []}) + "\n")
    assert main(["eval", "--gt", str(no_bev), "--pred", str(f), "--out", str(tmp_path / "ev")]) == 0


def test_collaboration_object_split_agrees_with_the_coverage_counts(batch):
    from cosim.eval.collaboration import compute_collaboration

    refs = load_dataset(batch)
    cov = compute_coverage(refs).counts
    collab = compute_collaboration(refs)
    for key in (("overall", "all"), ("environment", "rural"), ("environment", "urban")):
        c, k = cov[key], collab[key]
        assert k.objects == c.objects > 0 and k.ego_ticks == c.frames
        assert k.object_share("nobody") == pytest.approx(100.0 - c.recall("all"))
        assert k.object_share("ego") == pytest.approx(c.recall("ego"))
        assert k.object_share("only collaborators") == pytest.approx(c.recall("all") - c.recall("ego"))
        assert k.object_share("only drones") == pytest.approx(c.recall("all") - c.recall("vehicles+rsus"))
    assert {k[1] for k in collab if k[0] == "episode"} == {r.id for r in refs}


def test_report_prints_visible_objects_per_frame_and_the_coverage_adds(batch, tmp_path, capsys):
    """`cosim report` on a batch with visibility topics: the visible-objects column is the mean per frame of the
    objects some agent sees (not their sum over the episode), and the collaboration tables it prints (not only
    writes) carry `drones add` / `RSUs add` as `cosim coverage` computes them, never n/a here."""
    from cosim.eval.coverage import coverage_adds

    per_frame = {}
    for ref in load_dataset(batch):
        with open_episode(ref.path) as ep:
            seen = [len({o["track_id"] for a in ep.agents for o in tick.visibility(a)["objects"]})
                    for tick in ep.ticks(topics=["/labels/objects", *(f"/{a}/visibility" for a in ep.agents)])]
            md = ep.metadata
        per_frame[f"{md['weather']}/{md['lighting']}/{md['environment']}"] = sum(seen) / len(seen)
    md_path = tmp_path / "report.md"
    assert main(["report", str(batch), "--md", str(md_path)]) == 0
    out = capsys.readouterr().out
    text = md_path.read_text()
    for cond, mean in per_frame.items():
        row = next(line for line in text.splitlines() if line.startswith(f"| all | {cond} | 1 |"))
        assert row.endswith(f"| {mean:.1f} |"), (row, mean)
    drones, rsus = coverage_adds(compute_coverage(load_dataset(batch)))
    assert "### Who sees the objects in the ego's evaluation area" in out
    overall = next(line for line in out.splitlines() if line.startswith("| overall | all |")
                   and line.count("|") == 10)
    assert overall.endswith(f"| {drones['overall', 'all']:.1f} | {rsus['overall', 'all']:.1f} |"), overall
    assert out.count("### ") == 2 and out.rstrip().endswith(text.rstrip().splitlines()[-1])


# ------------------------------------------------------------------------------------ the ego of a prediction


@pytest.mark.parametrize("ego", ["rsu_0", "drone_0"])
def test_eval_rejects_an_ego_that_is_not_a_vehicle(synthetic_episode, tmp_path, capsys, ego):
    f = tmp_path / "p.jsonl"
    f.write_text(json.dumps({"episode": "syn", "tick": 0, "ego": ego, "boxes": []}) + "\n")
    status, _, err = cli(capsys, "eval", "--gt", str(synthetic_episode), "--pred", str(f), "--out",
                         str(tmp_path / "ev"))
    assert status == 2
    assert err.strip().splitlines() == [f"cosim: error: {f}:1: ego: {ego!r} is not a vehicle: the ego of a frame "
                                        "is a connected vehicle (vehicle_0)"]
