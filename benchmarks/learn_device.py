"""Train the ``cosim learn`` ablation settings on a GPU machine that has Python, numpy and torch but none of
cosim's other dependencies (no MCAP reader), from a cache tarball made here (docs/learnability.md, "On a GPU").

Here (with cosim installed):

    cosim learn cache out/learn16 --out out/cache16_tick --every 2
    python benchmarks/learn_device.py pack out/cache16_tick --every 10 --out out/learn_cache_dev.tar.xz

There (a bare copy of the repository tree; the tarball carried beside it):

    python3 benchmarks/learn_device.py run --cache out/learn_cache_dev.tar.xz --out $OUT --steps 500 --parallel 3

``run`` trains every setting of :data:`SETTINGS` (``--parallel`` at a time, each with its own batch-making worker
processes), validates on the cache's val split every fifth of the steps, keeps the checkpoint of the best
val AP50, and scores it on the test split. Per setting it writes ``<name>/summary.json``, ``log.jsonl``,
``test.json`` (AP30/50/70 of the vehicle group against the setting's own visible objects and against the
objects any agent in range sees) and ``pred_test.jsonl`` (records of ``cosim eval``'s format, to score here
with ``cosim eval --gt out/learn16 --pred ...``); ``results.json`` gathers them. Only numpy, torch and the
numpy-only modules of cosim.learn are imported (the AP is cosim.eval.ap's, which needs numpy alone).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

#: name -> (fusion, agents, lidar, fuse, encoders); the paper's agent and fusion ablations, the LiDAR
#: compensation ablation on the ego-only model, and intermediate fusion's options.
SETTINGS: dict[str, tuple[str, str, str, str, str]] = {
    "ego-tick": ("none", "ego", "tick", "max", "shared"),
    "early-V": ("early", "vehicles", "tick", "max", "shared"),
    "early-VI": ("early", "vehicles+rsus", "tick", "max", "shared"),
    "early-VD": ("early", "vehicles+drones", "tick", "max", "shared"),
    "early-VID": ("early", "all", "tick", "max", "shared"),
    "inter-max-VID": ("intermediate", "all", "tick", "max", "shared"),
    "inter-att-VID": ("intermediate", "all", "tick", "attention", "shared"),
    "inter-max-kind-VID": ("intermediate", "all", "tick", "max", "kind"),
    "late-VID": ("late", "all", "tick", "max", "shared"),
}


class CacheSamples:
    """:class:`cosim.learn.data.Samples` over a cache alone (numpy only)."""

    def __init__(self, cache, ids: list[str], setup, every: int):
        from cosim.learn.samples import make_item

        self._make = make_item
        self.cache, self.setup = cache, setup
        self.keys = []
        for e in cache.meta["episodes"]:
            if e["id"] in ids:
                self.keys += [(e["id"], t, ego) for t in range(0, e["n_ticks"], every) for ego in e["egos"]]
        self._last = None
        self._memo: dict[int, dict] = {}

    def __len__(self) -> int:
        return len(self.keys)

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_last": None, "_memo": {}}

    def item(self, i: int) -> dict:
        if i in self._memo:  # a sample is made once per process: epochs repeat on a small cache
            return self._memo[i]
        episode, tick, ego = self.keys[i]
        if self._last is None or self._last[0] != (episode, tick):
            self._last = ((episode, tick), self.cache.record(episode, tick))
        self._memo[i] = self._make(self._last[1], ego, self.setup, episode)
        return self._memo[i]


def score(model, samples, gt_samples, device, lines: list[str] | None = None) -> dict:
    """AP30/50/70 (%) of the vehicle group: against each sample's own targets (the objects its agents see)
    and against ``gt_samples``' targets (the objects any agent in range sees)."""
    import numpy as np

    from cosim.eval.ap import DetectionAccumulator
    from cosim.eval.boxes import footprints
    from cosim.eval.predictions import record_json
    from cosim.learn.train import predict_sample

    own, common = DetectionAccumulator(), DetectionAccumulator()
    was = model.training
    model.eval()
    for i in range(len(samples)):
        item = samples.item(i)
        boxes, scores, cls = predict_sample(model, item, samples.setup, device)
        det = footprints(boxes[:, :2], boxes[:, 3:5], boxes[:, 6])
        gt = np.concatenate([t[0] for t in item["targets"]]) if item["targets"] else np.zeros((0, 7))
        if samples.setup.fusion == "late":  # the union of the agents' visible objects, once each
            gt = np.unique(gt, axis=0)
        own.add(det, scores, footprints(gt[:, :2], gt[:, 3:5], gt[:, 6]))
        g = gt_samples.item(i)["targets"][0][0]
        common.add(det, scores, footprints(g[:, :2], g[:, 3:5], g[:, 6]))
        if lines is not None:
            lines.append(record_json(item["episode"], item["tick"], item["ego"], samples.setup.agents, boxes[:, :3],
                                     boxes[:, 3:6], boxes[:, 6], [samples.setup.classes[k] for k in cls], scores))
    model.train(was)

    def ap(acc, thr):
        v = acc.result(thr).ap
        return round(100.0 * v, 2) if v == v else float("nan")

    return {"AP30": ap(own, 0.3), "AP50": ap(own, 0.5), "AP70": ap(own, 0.7), "AP30_common": ap(common, 0.3),
            "AP50_common": ap(common, 0.5), "n_gt": own.n_gt, "n_gt_common": common.n_gt}


def run_one(args: argparse.Namespace) -> int:
    import torch

    from cosim.learn.samples import CachedEpisodes, Setup
    from cosim.learn.train import BEST, TrainOptions, device_of, fit, load_run

    fusion, agents, lidar, fuse, encoders = SETTINGS[args.name]
    cache = CachedEpisodes(args.root)
    if cache.lidar != lidar:
        print(f"{args.name}: the cache holds lidar {cache.lidar}, not {lidar}: skipped", file=sys.stderr)
        return 0
    setup = Setup(fusion=fusion, agents=agents, lidar=lidar, fuse=fuse, encoders=encoders)
    split = {s: [e["id"] for e in cache.episodes(s)] for s in ("train", "val", "test")}
    every = int(cache.meta["every"])
    train_s = CacheSamples(cache, split["train"], setup, every)
    val_s = CacheSamples(cache, split["val"], setup, every)
    test_s = CacheSamples(cache, split["test"], setup, every)
    gt_setup = Setup(fusion="early", agents="all", lidar=lidar)
    val_gt, test_gt = (CacheSamples(cache, split[s], gt_setup, every) for s in ("val", "test"))
    device = device_of(args.device)
    opts = TrainOptions(steps=args.steps, batch_size=args.batch_size, lr=args.lr, schedule="onecycle",
                        val_steps=max(1, args.steps // 5), save_every=args.steps, seed=args.seed,
                        workers=args.workers, width=args.width)
    run = Path(args.out) / args.name
    t0 = time.perf_counter()
    summary = fit(train_s, lambda m: score(m, val_s, val_gt, device), setup, opts, run, device=device,
                  show_progress=False)
    model, _setup, ckpt = load_run(run / BEST if (run / BEST).exists() else run, device)
    lines: list[str] = []
    test = score(model, test_s, test_gt, device, lines)
    (run / "pred_test.jsonl").write_text("".join(line + "\n" for line in lines))
    test.update({"name": args.name, "setup": setup.to_dict(), "best_step": int(ckpt["step"]),
                 "train_samples": len(train_s), "val_samples": len(val_s), "test_samples": len(test_s),
                 "wall_s": round(time.perf_counter() - t0, 1), "train_wall_s": summary["wall_s"],
                 "device": str(device), "torch": torch.__version__})
    (run / "test.json").write_text(json.dumps(test, indent=1) + "\n")
    print(f"{args.name}: test AP30 {test['AP30']} AP50 {test['AP50']} (common GT {test['AP30_common']} / "
          f"{test['AP50_common']}), best step {test['best_step']}, {test['wall_s']} s", flush=True)
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    src = Path(args.cache)
    if src.is_dir():
        root = src
    else:
        root = Path(tempfile.mkdtemp(prefix="learn_cache_"))
        t0 = time.perf_counter()
        with tarfile.open(src) as tar:
            tar.extractall(root, filter="data")
        print(f"unpacked {src} in {time.perf_counter() - t0:.1f} s", flush=True)
        inner = [p.parent for p in root.rglob("cache.json")]
        root = inner[0]
    names = args.settings or list(SETTINGS)
    unknown = [n for n in names if n not in SETTINGS]
    if unknown:
        print(f"unknown setting {unknown[0]}; choose from {', '.join(SETTINGS)}", file=sys.stderr)
        return 2
    workers = args.workers if args.workers is not None else max(1, ((os.cpu_count() or 2) - args.parallel)
                                                                  // args.parallel)
    t0 = time.perf_counter()
    running: list[tuple[str, subprocess.Popen]] = []
    queue = list(names)
    failed = []
    def write_results() -> dict:
        results = {n: json.loads((out / n / "test.json").read_text()) for n in names
                   if (out / n / "test.json").is_file()}
        (out / "results.json").write_text(json.dumps({"wall_s": round(time.perf_counter() - t0, 1),
                                                      "steps": args.steps, "batch_size": args.batch_size,
                                                      "skipped": skipped, "results": results}, indent=1) + "\n")
        return results

    skipped: list[str] = []
    while queue or running:
        if queue and time.perf_counter() - t0 > args.start_before_s:  # no time left to train another
            skipped += queue
            queue = []
        while queue and len(running) < args.parallel:
            n = queue.pop(0)
            cmd = [sys.executable, __file__, "one", n, "--root", str(root), "--out", str(out), "--steps",
                   str(args.steps), "--batch-size", str(args.batch_size), "--lr", str(args.lr), "--workers",
                   str(workers), "--seed", str(args.seed), "--width", str(args.width)]
            if args.device:
                cmd += ["--device", args.device]
            running.append((n, subprocess.Popen(cmd)))
        time.sleep(1.0)
        for n, p in list(running):
            if p.poll() is not None:
                running.remove((n, p))
                if p.returncode:
                    failed.append(n)
                write_results()
    results = write_results()
    print(f"{len(results)} settings in {time.perf_counter() - t0:.0f} s; failed: {', '.join(failed) or 'none'}; "
          f"not started for time: {', '.join(skipped) or 'none'}")
    return 1 if failed else 0


def cmd_pack(args: argparse.Namespace) -> int:
    """A cache folder as one .tar.xz, keeping every ``--every``-th tick (a multiple of the cache's own)."""
    import numpy as np

    src = Path(args.cache)
    if not (src / "cache.json").is_file():
        print(f"{src}: no cache.json: not a cache folder of cosim learn cache", file=sys.stderr)
        return 2
    meta = json.loads((src / "cache.json").read_text())
    every = args.every or int(meta["every"])
    if every % int(meta["every"]):
        print(f"--every {every} is not a multiple of the cache's {meta['every']}", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        dst = Path(tmp) / src.name
        for e in meta["episodes"]:
            (dst / e["file"]).parent.mkdir(parents=True, exist_ok=True)
            with np.load(src / e["file"]) as z:
                recs = json.loads(z["meta"].tobytes())
                keep = [r for r in recs if r["tick"] % every == 0]
                arrays = {k: z[k] for k in z.files if k != "meta" and int(k.split("/")[0]) % every == 0}
            arrays["meta"] = np.frombuffer(json.dumps(keep).encode(), np.uint8)
            np.savez(dst / e["file"], **arrays)
        (dst / "cache.json").write_text(json.dumps({**meta, "every": every}, indent=1) + "\n")
        with tarfile.open(args.out, "w:xz", preset=args.preset) as tar:
            tar.add(dst, arcname=src.name)
    print(f"{args.out}: {Path(args.out).stat().st_size / 1e6:.1f} MB, every {every} ticks")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="train and score every setting")
    r.add_argument("--cache", required=True, help="cache tarball (.tar.xz) or folder of cosim learn cache")
    r.add_argument("--out", required=True)
    r.add_argument("--settings", nargs="+", help=f"default: all of {', '.join(SETTINGS)}")
    r.add_argument("--parallel", type=int, default=3, help="settings trained at once (default 3)")
    r.add_argument("--workers", type=int, help="batch-making processes per setting (default: the CPUs shared)")
    r.add_argument("--start-before-s", type=float, default=300.0,
                   help="start no setting later than this many seconds after the start (default 300)")
    o = sub.add_parser("one", help="(internal) one setting")
    o.add_argument("name")
    o.add_argument("--root", required=True)
    o.add_argument("--out", required=True)
    o.add_argument("--workers", type=int, default=4)
    for p in (r, o):
        p.add_argument("--steps", type=int, default=600)
        p.add_argument("--batch-size", type=int, default=8)
        p.add_argument("--lr", type=float, default=3e-3)
        p.add_argument("--seed", type=int, default=0)
        p.add_argument("--width", type=int, default=16)
        p.add_argument("--device", help="torch device (default cuda when present)")
    k = sub.add_parser("pack", help="a cache folder as one .tar.xz")
    k.add_argument("cache")
    k.add_argument("--out", required=True)
    k.add_argument("--preset", type=int, default=6)
    k.add_argument("--every", type=int, help="keep ticks 0, every, 2 every... (default: all of the cache's)")
    args = ap.parse_args(argv)
    return {"run": cmd_run, "one": run_one, "pack": cmd_pack}[args.cmd](args)


if __name__ == "__main__":
    sys.exit(main())
