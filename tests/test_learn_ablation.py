"""benchmarks/learn_ablation.py's bookkeeping: the cost of a job stopped and resumed, the settings a report
takes from another run's folder, the drones' gain table, and bad options refused before anything is made.
The grid itself is an experiment (docs/learnability.md), not a test."""

from __future__ import annotations

import argparse
import json

import pytest

from benchmarks import learn_ablation as la


def _scores(ap30: float, ap50: float, **cells: tuple[float, float]) -> dict:
    common = {"overall=all": {"AP30": ap30, "AP50": ap50, "AP70": 0.0, "frames": 10}}
    common |= {key: {"AP30": a, "AP50": b, "AP70": 0.0, "frames": 5} for key, (a, b) in cells.items()}
    return {"common": common, "own": common}


def test_a_jobs_cost_is_the_sum_of_its_attempts(tmp_path):
    lines = [{"job": "train ego/s0", "rc": -15, "cpu_s": 100.0, "wall_s": 110.0},
             {"job": "train ego/s0", "rc": 0, "cpu_s": 50.5, "wall_s": 60.0},
             {"job": "predict ego/s0", "rc": 1, "cpu_s": 3.0, "wall_s": 3.0}]
    (tmp_path / "jobs.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lines))
    done = la.jobs_done(tmp_path)
    assert set(done) == {"train ego/s0"}  # a failed job is not done
    assert done["train ego/s0"]["cpu_s"] == 150.5
    assert done["train ego/s0"]["wall_s"] == 170.0
    assert done["train ego/s0"]["attempts"] == 2


def test_use_takes_ego_only_and_its_late_fusion_from_another_folder(tmp_path):
    other = tmp_path / "ablation3600"
    other.mkdir()
    args = argparse.Namespace(out=tmp_path / "ablation2400", use=[f"ego={other}"])
    src = la.sources(args)
    assert src["ego"] == other and src["late-VID"] == other
    assert {src[n] for n in src if n not in ("ego", "late-VID")} == {args.out}
    for bad in ("eg=" + str(other), "ego", f"ego={tmp_path / 'missing'}"):
        with pytest.raises(ValueError, match="--use"):
            la.sources(argparse.Namespace(out=args.out, use=[bad]))


def test_the_drones_gain_is_the_difference_of_the_seed_means():
    results = {
        "inter-VID/s0": _scores(80.0, 60.0, **{"environment=rural": (82.0, 70.0), "strategy=hover": (81.0, 61.0)}),
        "inter-VID/s1": _scores(82.0, 64.0, **{"environment=rural": (84.0, 72.0), "strategy=hover": (83.0, 63.0)}),
        "inter-VI/s0": _scores(78.0, 55.0, **{"environment=rural": (80.0, 60.0), "strategy=hover": (80.0, 60.0)}),
    }
    lines = la.gains(results)
    header = next(line for line in lines if line.startswith("| gain"))
    assert header == "| gain | overall | rural | hover |"
    row = next(line for line in lines if line.startswith("| V+I+D - V+I"))
    assert row == "| V+I+D - V+I | +3.0 / +7.0 | +3.0 / +11.0 | +2.0 / +2.0 |"
    assert not any(line.startswith("| V+D - V") for line in lines)  # neither V+D nor V was run
    assert la.gains({"inter-VID/s0": results["inter-VID/s0"]}) == []


def test_run_refuses_an_unknown_setting_or_cache_before_making_anything(tmp_path, capsys):
    out = tmp_path / "ablation"
    base = dict(dataset=tmp_path, out=out, steps=10, lr=3e-3, val_steps=5, parallel=1)
    assert la.run_all(argparse.Namespace(**base, only=["eggo"], cache=None)) == 2
    assert "--only eggo: not a setting" in capsys.readouterr().err
    assert la.run_all(argparse.Namespace(**base, only=None, cache=tmp_path / "nocache")) == 2
    assert "not a cache" in capsys.readouterr().err
    assert not out.exists()


def test_a_test_perturbation_predicts_into_its_own_folder_with_its_flags(tmp_path):
    base = dict(dataset=tmp_path, out=tmp_path / "ablation", cache=None, perturb_seed=0)
    clean = argparse.Namespace(**base, pose_noise=None, latency=None, loss=None)
    assert la.perturb_flags(clean) == [] and la.perturb_tag(clean) == ""
    jobs = dict(la.predict_jobs(clean))
    assert "predict ego/s0" in jobs and str(tmp_path / "ablation" / "pred" / "ego-s0.jsonl") in jobs["predict ego/s0"]
    noisy = argparse.Namespace(**{**base, "perturb_seed": 2}, pose_noise="0.2,0.2", latency=None, loss="links")
    assert la.perturb_flags(noisy) == ["--pose-noise", "0.2,0.2", "--loss", "links", "--perturb-seed", "2"]
    tag = la.perturb_tag(noisy)
    assert tag == "pose-0.2,0.2+loss-links+perturb-2"
    cmd = dict(la.predict_jobs(noisy))[f"predict inter-VID/s1 [{tag}]"]
    assert cmd[-1] == str(tmp_path / "ablation" / f"pred-{tag}" / "inter-VID-s1.jsonl")
    assert cmd[cmd.index("--pose-noise") + 1] == "0.2,0.2" and cmd[cmd.index("--loss") + 1] == "links"
