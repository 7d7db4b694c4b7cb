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


def test_every_settings_seed_trains_once_with_its_own_flags(tmp_path):
    planned = [(n, s) for n, st in la.SETTINGS.items() for s in st.seeds]
    assert sorted(la.ORDER) == sorted(f"{n}/s{s}" for n, s in planned)
    assert len(set(la.ORDER)) == len(la.ORDER)
    args = argparse.Namespace(dataset=tmp_path, out=tmp_path / "a", cache=None, steps=10, lr=3e-3, val_steps=5)
    robust = la.train_cmd("inter-VID-pose", 1, args, tmp_path / "run")
    assert robust[robust.index("--pose-noise") + 1] == "0.4,0.4" and robust[robust.index("--seed") + 1] == "1"
    assert "--encoders" not in robust and "--pose-noise" not in la.train_cmd("inter-VID", 0, args, tmp_path / "r")
    kind = la.train_cmd("inter-VID-kind", 0, args, tmp_path / "run")
    assert kind[kind.index("--encoders") + 1] == "kind"
    assert la.setting_label("inter-VID-pose") == "intermediate (max), V+I+D, trained with pose error 0.4,0.4"


def _robust_args(tmp_path, **kw) -> argparse.Namespace:
    base = dict(dataset=tmp_path / "data", out=tmp_path / "ablation", use=None, to=None, cache=None,
                pose_levels=["0.2,0.2", "0.6,0.6"], latency_levels=["200"], links=True, mixed=None, parallel=1,
                latency_cache=None, latency_data=None, perturb_seed=3, picture=None, pose_noise=None, latency=None,
                loss=None)
    return argparse.Namespace(**{**base, **kw})


def test_robustness_predicts_the_trained_models_under_every_level_and_tabulates_the_fall(tmp_path, monkeypatch):
    args = _robust_args(tmp_path, picture=tmp_path / "robust.png")
    out = args.out
    done_tag = "pose-0.2,0.2+perturb-3"
    # trained: ego s0 and s1, inter-VID s0; inter-VID s1 still training (its best.pt is not final); no other
    jobs = [{"job": f"train {k}", "rc": 0} for k in ("ego/s0", "ego/s1", "inter-VID/s0")]
    jobs += [{"job": "train inter-VID/s1", "rc": -15}, {"job": f"predict ego/s0 [{done_tag}]", "rc": 0}]
    (out / "runs" / "inter-VID-s1").mkdir(parents=True)
    (out / "runs" / "inter-VID-s1" / "best.pt").write_bytes(b"")
    (out / "jobs.jsonl").write_text("".join(json.dumps({**j, "cpu_s": 1.0, "wall_s": 1.0}) + "\n" for j in jobs))
    ran: list[str] = []

    def fake_run_chains(chains, parallel, folder):
        assert folder == out and all(len(chain) == 1 for chain in chains)
        for chain in chains:
            for job, cmd in chain:  # latency reads earlier ticks: from MCAP (no --latency-cache), not the cache
                assert ("--cache" in cmd) == ("latency" not in job), job
                ran.append(job)
        return [], False

    monkeypatch.setattr(la, "run_chains", fake_run_chains)
    # the scores each level's report would give: AP30 falls by 10 per level for inter-VID, 1 for ego
    ap = {"": 0, done_tag: 1, "pose-0.6,0.6+perturb-3": 3, "latency-200+perturb-3": 2,
          "latency-links+loss-links+perturb-3": 1}
    reported = []

    def fake_report(a, recall_tables=True):
        tag = la.perturb_tag(a)
        reported.append((tag, recall_tables))
        k = ap[tag]
        results = {"ego/s0": _scores(50.0 - k, 30.0), "ego/s1": _scores(52.0 - k, 32.0),
                   "inter-VID/s0": _scores(80.0 - 10 * k, 60.0 - 10 * k, **{"environment=urban": (70.0 - k, 50.0)}),
                   "late-VID/s0": _scores(60.0 - 5 * k, 40.0)}
        for r in results.values():
            r["bytes_per_frame"] = 4096.0
        (a.out / (f"ablation-{tag}.json" if tag else "ablation.json")).write_text(json.dumps({"results": results}))
        return 0

    monkeypatch.setattr(la, "report", fake_report)
    assert la.robustness(args) == 0
    # predictions: every perturbed level of the trained models (late fusion from ego's), none done twice
    assert f"predict ego/s0 [{done_tag}]" not in ran and f"predict ego/s1 [{done_tag}]" in ran
    assert "predict late-VID/s1 [latency-links+loss-links+perturb-3]" in ran
    assert not any("early-VID" in job or "late-VID/s2" in job or "inter-VID/s1" in job for job in ran)
    assert len(ran) == 4 * 5 - 1  # 4 levels x (ego s0, s1, inter-VID s0, late s0, s1), less the one done
    assert sorted(t for t, _r in reported) == sorted(ap) and not any(r for _t, r in reported)
    md = (out / "robustness.md").read_text()
    pose = md.split("## Against pose error")[1].split("##")[0]
    assert "| setting | seeds | 0 | 0.2,0.2 | 0.6,0.6 | AP30 fall at the last level |" in pose
    assert "| intermediate (max), V+I+D | 1 | 80.0 / 60.0 | 70.0 / 50.0 | 50.0 / 30.0 | 30.0 |" in pose
    assert "| ego only | 2 | 51.0 ± 1.0 / 31.0 | 50.0 ± 1.0 / 31.0 | 48.0 ± 1.0 / 31.0 | 3.0 |" in pose
    latency = md.split("## Against latency")[1].split("##")[0]
    assert "| intermediate (max), V+I+D | 1 | 80.0 / 60.0 | 60.0 / 40.0 | 20.0 |" in latency
    links = md.split("## The links as simulated")[1].split("##")[0]
    assert "| intermediate (max), V+I+D | 80.0 / 60.0 | 70.0 / 50.0 | 70.0 / 50.0 | 69.0 / 50.0 |" in links
    assert "| late, V+I+D (ego-only models) | 4,096 | 60.0 / 40.0 |" in md
    saved = json.loads((out / "robustness.json").read_text())
    assert saved["sweeps"]["latency"] == ["0", "200 ms"] and saved["mixed"] is None
    assert (tmp_path / "robust.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_robustness_compares_mixed_lidars_with_uniform_ones_and_refuses_a_folder_without_a_report(tmp_path,
                                                                                                  capsys):
    args = _robust_args(tmp_path, mixed=tmp_path / "mixed")
    assert la.robustness(args) == 2
    assert "--mixed" in capsys.readouterr().err and not args.out.exists()
    uniform = {"inter-VID/s0": _scores(80.0, 60.0), "inter-VID-kind/s0": _scores(79.0, 59.0)}
    mixed = {"inter-VID/s0": _scores(70.0, 50.0), "inter-VID-kind/s0": _scores(76.0, 56.0),
             "inter-VID-sensor/s0": _scores(78.0, 58.0)}
    grid = {"pose": [("0", uniform)], "latency": [("0", uniform)]}
    md = la.robustness_tables(grid, mixed).split("## Mixed LiDARs")[1]
    assert "| intermediate (max), V+I+D | 80.0 / 60.0 | 70.0 / 50.0 | -10.0 |" in md
    assert "| intermediate (max), V+I+D, an encoder per kind | 79.0 / 59.0 | 76.0 / 56.0 | -3.0 |" in md
    # the uniform grid has no per-sensor model: on one LiDAR per kind it is the per-kind one
    assert "| intermediate (max), V+I+D, an encoder per sensor | 79.0 / 59.0 | 78.0 / 58.0 | -1.0 |" in md


def test_run_takes_only_the_named_settings_and_seeds_in_the_grids_order():
    def pick(only=None, seeds=None):
        return la.selected(argparse.Namespace(only=only, seeds=seeds))

    assert pick() == list(la.ORDER)
    assert pick(only=["ego", "early-VID"], seeds=[0, 1]) == ["ego/s0", "early-VID/s0", "ego/s1", "early-VID/s1"]
    assert pick(seeds=[2]) == ["inter-VID/s2", "ego/s2"]  # the only settings with a third seed
    assert pick(only=["inter-V"], seeds=[1]) == []  # inter-V has seed 0 only


def test_latency_data_puts_the_latency_and_links_sweeps_on_its_test_split_at_its_own_tick_step(tmp_path,
                                                                                                 monkeypatch):
    data10 = tmp_path / "learn72_10hz"
    args = _robust_args(tmp_path, latency_data=data10, latency_cache=tmp_path / "cache10", latency_levels=["100"])
    args.out.mkdir(parents=True)
    (args.out / "jobs.jsonl").write_text(json.dumps({"job": "train inter-VID/s0", "rc": 0, "cpu_s": 1.0,
                                                     "wall_s": 1.0}) + "\n")
    monkeypatch.setattr(la, "tick_ratio", lambda data, grid: 2 if (data, grid) == (data10, args.dataset) else 0)
    ran: dict[str, list[str]] = {}

    def fake_run_chains(chains, parallel, folder):
        ran.update(job for chain in chains for job in chain)
        return [], False

    def fake_report(a, recall_tables=True):
        tag = la.perturb_tag(a)
        results = {"inter-VID/s0": _scores(80.0, 60.0)}
        (a.out / (f"ablation-{tag}.json" if tag else "ablation.json")).write_text(json.dumps({"results": results}))
        return 0

    monkeypatch.setattr(la, "run_chains", fake_run_chains)
    monkeypatch.setattr(la, "report", fake_report)
    assert la.robustness(args) == 0

    def data_and_every(job):
        cmd = ran[job]
        return cmd[cmd.index("predict") + 2], cmd[cmd.index("--every") + 1], cmd[cmd.index("--cache") + 1]

    # the clean column of the latency sweep is predicted again, on the 10 Hz data (every 12th tick: the same
    # instants as the grid's every 6th at 5 Hz), from its cache; the pose sweep stays on the grid's data
    assert data_and_every("predict inter-VID/s0 [data-learn72_10hz]") == (str(data10), "12", str(tmp_path / "cache10"))
    assert data_and_every("predict inter-VID/s0 [data-learn72_10hz+latency-100+perturb-3]")[:2] == (str(data10), "12")
    assert data_and_every("predict inter-VID/s0 [data-learn72_10hz+latency-links+loss-links+perturb-3]")[:2] == (
        str(data10), "12")
    assert data_and_every("predict inter-VID/s0 [pose-0.6,0.6+perturb-3]") == (
        str(args.dataset), "6", str(args.out / "cache"))
    assert not any("latency" in job and "data-" not in job for job in ran)
    md = (args.out / "robustness.md").read_text()
    assert f"On the test split of `{data10}`" in md.split("## Against latency")[1].split("##")[0]
    assert "On the test split" not in md.split("## Against latency")[0]


def test_the_tick_ratio_of_latency_data_is_a_whole_number(tmp_path, monkeypatch, capsys):
    import cosim.eval.dataset
    from cosim.eval.dataset import EpisodeRef

    ticks = {"d5": 50, "d10": 100, "d7": 70}
    monkeypatch.setattr(cosim.eval.dataset, "load_dataset", lambda folder: [
        EpisodeRef("train-0", folder / "a.mcap", "train", n_ticks=1),
        EpisodeRef("test-0", folder / "b.mcap", "test", n_ticks=ticks[folder.name])])
    assert la.tick_ratio(tmp_path / "d10", tmp_path / "d5") == 2
    with pytest.raises(ValueError, match="70 ticks an episode, not a whole multiple of the grid's 50"):
        la.tick_ratio(tmp_path / "d7", tmp_path / "d5")
    args = _robust_args(tmp_path, dataset=tmp_path / "d5", latency_data=tmp_path / "d7")
    assert la.robustness(args) == 2
    assert "not a whole multiple" in capsys.readouterr().err and not args.out.exists()
