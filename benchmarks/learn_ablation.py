r"""The ablation of docs/learnability.md on a CPU: train every setting of :data:`SETTINGS` from a cache, predict
the test split, score it and write the tables (issue 35).

    cosim batch sweeps/learnability.yaml --out out/learn72 --count 72 --set duration_s=10 --workers 2
    python benchmarks/learn_ablation.py run out/learn72 --out out/ablation2400 --steps 2400 --val-steps 240
    python benchmarks/learn_ablation.py run out/learn72 --out out/ablation3600 --steps 3600 --val-steps 360 \
        --only ego early-VID --cache out/ablation2400/cache
    python benchmarks/learn_ablation.py report out/learn72 --out out/ablation2400 --use ego=out/ablation3600 \
        early-VID=out/ablation3600 --to out/ablation_converged

(the step counts at which every val curve is flat: docs/learnability.md). ``run`` makes the cache (``cosim
learn cache --every 2``) when ``OUT/cache`` is missing (``--cache DIR`` shares another run's), then trains the
settings ``--parallel`` at a time (each one process with one torch thread: on a 2-core machine two at once
keep both cores busy), each followed by its prediction of the test split (and late fusion with each ego-only
model on every agent's cloud) and its tail check: the kept checkpoints of the last 20 % of the steps scored
again on the val split at every cached tick (``cosim learn validate``), five times the frames of the
training's own validation, so that the curves' flatness is read with less noise. Every command is ``cosim
learn`` itself; what it cost (user + system CPU-seconds of its process tree, wall seconds) is appended to
``OUT/jobs.jsonl``. Ctrl-C or SIGTERM stops the running jobs (recording what they cost) and starts no more.
Started again, ``run`` skips the finished jobs and continues a training cut short from its last checkpoint
(``cosim learn train --resume``: saved every 100 steps, and a resumed run gives the same weights as an
uninterrupted one), so the grid can be spread over several sittings; a job's cost is the sum of all its
attempts.

``report`` scores every prediction file with ``cosim eval``'s scoring against two ground truths, the
objects the setting's own agents see and the objects any agent of the full setting (V+I+D) sees (the
common reference that lets settings be compared: the records' ``agents`` field is read as ``all``), per
environment, drone strategy and lighting; gathers mean and spread over seeds, the drones' gain per
environment and strategy (V+I+D - V+I, V+D - V), the val curves' flatness and the CPU of every stage;
runs ``cosim learn recall`` on the seed-0 predictions (objects the ego has no return on, found per
setting), over the whole test split and per environment and drone strategy; and writes ``OUT/ablation.md``
and ``OUT/ablation.json``. ``--use NAME=DIR`` takes a setting from another run's folder instead
(``ego=out/ablation3600``: ego only trained for more steps, and late fusion with those models), ``--to DIR``
writes the report there; the overall table gives each setting's steps and the bytes the collaborators sent per
ego frame (docs/learnability.md, "Bytes sent").

Collaboration as deployed (issue 49): ``run`` and ``report`` with ``--pose-noise POS_M,ROT_DEG``, ``--latency
MS|links``, ``--loss P|links`` (and ``--perturb-seed S``) predict and score the test split under that
perturbation with the trained models (a prediction each, no training), into ``OUT/pred-<tag>`` and
``OUT/ablation-<tag>.md``; the same command without them is the clean grid. ``robustness`` does that for every
level of the protocol (pose error 0.2 to 0.6 m and deg, latency 200 and 400 ms, ``--links``: the simulated
links) and writes ``OUT/robustness.md`` and ``.json``: AP against each level, against bytes sent, and with
``--mixed DIR`` mixed LiDARs against uniform ones; ``--latency-data DIR`` puts the latency and links sweeps on
the test split of the same sweep at 10 Hz (``cosim batch ... --split test --set tick_hz=10``), where 100 ms is
one tick (docs/learnability.md, "The benchmark of collaboration as deployed").
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import NamedTuple

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

class Setting(NamedTuple):
    """One trained setting of the grid: ``cosim learn train --fusion FUSION --agents AGENTS --fuse FUSE`` with
    ``train`` flags added, once per seed."""

    fusion: str
    agents: str
    fuse: str
    seeds: tuple[int, ...]
    train: tuple[str, ...] = ()


#: name -> setting: the paper's agent ablation with intermediate fusion (its models are all intermediate),
#: its fusion ablation on V+I+D, three seeds for ego only and V+I+D, two for the rest of V+I+D. Late fusion is
#: predicted with each ego-only model (:data:`LATE`). Intermediate V+I+D is trained with both per-cell
#: fusions: max (F-Cooper, every other intermediate setting) and attention (AttFuse). Collaboration as
#: deployed (issue 49) adds two: the robust variant, trained under V2X-ViT's and CoAlign's pose error of the
#: middle level (0.4 m, 0.4 deg), one pillar encoder per agent kind and one per LiDAR (for the mixed LiDARs
#: of ``robustness --mixed``: the mix is within each kind, so only the second gives each LiDAR its encoder).
SETTINGS: dict[str, Setting] = {
    "ego": Setting("none", "ego", "max", (0, 1, 2)),
    "inter-VID": Setting("intermediate", "all", "max", (0, 1, 2)),
    "inter-V": Setting("intermediate", "vehicles", "max", (0,)),
    "inter-VI": Setting("intermediate", "vehicles+rsus", "max", (0,)),
    "inter-VD": Setting("intermediate", "vehicles+drones", "max", (0,)),
    "early-VID": Setting("early", "all", "max", (0, 1)),
    "inter-VID-att": Setting("intermediate", "all", "attention", (0, 1)),
    "inter-VID-pose": Setting("intermediate", "all", "max", (0, 1), ("--pose-noise", "0.4,0.4")),
    "inter-VID-kind": Setting("intermediate", "all", "max", (0, 1), ("--encoders", "kind")),
    "inter-VID-sensor": Setting("intermediate", "all", "max", (0, 1), ("--encoders", "sensor")),
}
#: late fusion: each ego-only model on every agent's cloud
LATE = ("late-VID", "ego", "all")
LATE_SEEDS = (0, 1, 2)
#: the order training jobs start in: a long and a short one side by side, the first seed of everything first
ORDER = ("inter-VID/s0", "ego/s0", "inter-V/s0", "inter-VI/s0", "inter-VD/s0", "early-VID/s0", "inter-VID/s1",
         "ego/s1", "inter-VID/s2", "ego/s2", "inter-VID-att/s0", "early-VID/s1", "inter-VID-att/s1",
         "inter-VID-pose/s0", "inter-VID-pose/s1", "inter-VID-kind/s0", "inter-VID-kind/s1", "inter-VID-sensor/s0",
         "inter-VID-sensor/s1")
CONDITIONS = ("environment", "strategy", "lighting")
RECALL_BY = ("environment", "strategy")  # the recall table again per value of these (where drones add sight)
AGENT_LABEL = {"ego": "ego only", "vehicles": "V", "vehicles+rsus": "V+I", "vehicles+drones": "V+D", "all": "V+I+D"}
CACHE_EVERY = 2
TEST_EVERY = 6  # a multiple of the cache's
#: the tail check: the kept checkpoints of the last 20 % of the steps scored again on the val split at every
#: cached tick (5 times the frames of the training's own validation, every 10th tick)
DENSE_EVERY = CACHE_EVERY


def cosim(*args: str) -> list[str]:
    return [sys.executable, "-c", "import sys; from cosim.cli import main; sys.exit(main())", *args]


def timed(cmd: list[str], log: Path, running: set | None = None, lock: threading.Lock | None = None,
          stopping: threading.Event | None = None) -> tuple[int, float, float]:
    """Run ``cmd`` (output to ``log``); exit status, CPU-seconds of its process tree and wall seconds. With
    ``running`` and ``lock``, the process is in ``running`` while it runs (to be stopped by a signal); it is
    not started once ``stopping`` is set."""
    t0 = time.perf_counter()
    with open(log, "a" if "--resume" in cmd else "w") as f:
        with lock or contextlib.nullcontext():
            if stopping is not None and stopping.is_set():
                return -signal.SIGTERM, 0.0, 0.0
            p = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, cwd=REPO)
            if running is not None:
                running.add(p)
        _pid, status, usage = os.wait4(p.pid, 0)
        if running is not None:
            with lock:
                running.discard(p)
    p.returncode = os.waitstatus_to_exitcode(status)
    return p.returncode, usage.ru_utime + usage.ru_stime, time.perf_counter() - t0


def record(out: Path, **rec) -> None:
    with open(out / "jobs.jsonl", "a") as f:
        f.write(json.dumps(rec) + "\n")


def jobs_done(out: Path) -> dict[str, dict]:
    """The finished jobs of ``OUT/jobs.jsonl``: each one's successful record, with the CPU and wall seconds
    of all its attempts (a training stopped and resumed, or started again) and their count."""
    path = out / "jobs.jsonl"
    if not path.is_file():
        return {}
    recs = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    done = {}
    for r in recs:
        if r["rc"] == 0:
            tries = [t for t in recs if t["job"] == r["job"]]
            done[r["job"]] = {**r, "cpu_s": round(sum(t["cpu_s"] for t in tries), 1),
                              "wall_s": round(sum(t["wall_s"] for t in tries), 1), "attempts": len(tries)}
    return done


def cache_dir(args: argparse.Namespace) -> Path:
    """The run's cache: ``--cache`` (another run's, shared) or ``OUT/cache``, made by ``run``."""
    return args.cache or args.out / "cache"


def train_cmd(name: str, seed: int, args: argparse.Namespace, run: Path) -> list[str]:
    st = SETTINGS[name]
    return cosim("learn", "train", str(args.dataset), "--out", str(run), "--fusion", st.fusion, "--agents", st.agents,
                 "--fuse", st.fuse, *st.train, "--cache", str(cache_dir(args)), "--every", str(CACHE_EVERY),
                 "--steps", str(args.steps), "--batch-size", "8", "--lr", str(args.lr), "--schedule", "onecycle",
                 "--val-steps", str(args.val_steps), "--val-every-tick", "10", "--keep-every", str(args.val_steps),
                 "--threads", "1", "--seed", str(seed), "--quiet")


def tail_from(steps: int, val_steps: int) -> int:
    """The flatness window's first step: the last validation at or before 80 % of the steps."""
    return max(val_steps, int(0.8 * steps) // val_steps * val_steps)


def tail_cmd(run: Path, args: argparse.Namespace) -> list[str]:
    return cosim("learn", "validate", str(run), str(args.dataset), "--split", "val", "--every", str(DENSE_EVERY),
                 "--from-step", str(tail_from(args.steps, args.val_steps)), "--cache", str(cache_dir(args)),
                 "--threads", "1")


def perturb_flags(args: argparse.Namespace) -> list[str]:
    """The test perturbation's ``cosim learn predict`` flags (none: the clean grid)."""
    flags = [(f, getattr(args, a, None)) for f, a in (("--pose-noise", "pose_noise"), ("--latency", "latency"),
                                                       ("--loss", "loss"))]
    out = [x for f, v in flags if v is not None for x in (f, str(v))]
    return [*out, "--perturb-seed", str(args.perturb_seed)] if out else []


def perturb_tag(args: argparse.Namespace) -> str:
    """The perturbation's name in folder and job names (``pose-0.2,0.2+latency-100+loss-links+perturb-0``), or "";
    led by ``data-<folder>`` when the test split is another dataset's (``robustness --latency-data``)."""
    flags = perturb_flags(args)
    data = getattr(args, "test_data", None)
    return "+".join([*([f"data-{Path(data).name}"] if data else []),
                     *(f"{flags[i].lstrip('-').split('-')[0]}-{flags[i + 1]}" for i in range(0, len(flags), 2))])


def test_dataset(args: argparse.Namespace) -> Path:
    """The dataset whose test split is predicted and scored: the grid's, or ``robustness --latency-data``'s."""
    return getattr(args, "test_data", None) or args.dataset


def test_every(args: argparse.Namespace) -> int:
    """The test split's tick step: :data:`TEST_EVERY`, times the ticks per second of ``--latency-data`` over the
    grid's (every 12th tick at 10 Hz: the same instants as every 6th at 5 Hz)."""
    return getattr(args, "test_every", None) or TEST_EVERY


def tick_ratio(data: Path, grid: Path) -> int:
    """How many ticks ``data``'s test episodes have for each of ``grid``'s (2: the same sweep at 10 Hz, not
    5); ValueError unless a whole number."""
    from cosim.eval.dataset import load_dataset

    def ticks(folder: Path) -> int:
        test = [r.n_ticks for r in load_dataset(folder) if r.split == "test"]
        if not test:
            raise ValueError(f"{folder}: no test split")
        return test[0]

    n, m = ticks(data), ticks(grid)
    if n % m:
        raise ValueError(f"--latency-data {data}: {n} ticks an episode, not a whole multiple of the grid's {m}")
    return n // m


def pred_dir(args: argparse.Namespace, folder: Path | None = None) -> Path:
    tag = perturb_tag(args)
    return (folder or args.out) / (f"pred-{tag}" if tag else "pred")


def predict_jobs(args: argparse.Namespace, folders: dict[str, Path] | None = None) -> list[tuple[str, list[str]]]:
    """Every prediction of the test split (under ``args``' perturbation), each setting's run and prediction
    file in ``args.out`` or the results folder ``folders`` names for it (``report --use``)."""
    folders = folders or {}
    jobs = []
    tag = perturb_tag(args)
    suffix = f" [{tag}]" if tag else ""

    def one(name: str, base: str, s: int, extra: tuple[str, ...] = ()) -> tuple[str, list[str]]:
        run = folders.get(base, args.out) / "runs" / f"{base}-s{s}"
        pred = pred_dir(args, folders.get(name, args.out)) / f"{name}-s{s}.jsonl"
        cache = [] if getattr(args, "mcap", False) else ["--cache", str(cache_dir(args))]
        return (f"predict {name}/s{s}{suffix}", cosim(
            "learn", "predict", str(run), str(test_dataset(args)), "--split", "test", "--every", str(test_every(args)),
            *cache, *extra, "--threads", "1", "--quiet", *perturb_flags(args),
            "--out", str(pred)))

    for name, st in SETTINGS.items():
        jobs += [one(name, name, s) for s in st.seeds]
    late, base, agents = LATE
    jobs += [one(late, base, s, ("--fusion", "late", "--agents", agents)) for s in LATE_SEEDS]
    return jobs


def selected(args: argparse.Namespace) -> list[str]:
    """The trainings ``run`` takes, in :data:`ORDER`: ``--only``'s settings (default all), ``--seeds``' seeds of
    each (default its own)."""
    keys = [k.split("/s") for k in ORDER]
    return [f"{n}/s{s}" for n, s in keys
            if (not args.only or n in args.only) and (not args.seeds or int(s) in args.seeds)]


def run_all(args: argparse.Namespace) -> int:
    from cosim.learn.samples import cache_meta_path

    unknown = sorted(set(args.only or ()) - set(SETTINGS))
    if unknown:
        print(f"--only {' '.join(unknown)}: not a setting (one of {', '.join(SETTINGS)})", file=sys.stderr)
        return 2
    if args.cache is not None and not cache_meta_path(args.cache).is_file():
        print(f"--cache {args.cache}: not a cache of `cosim learn cache`", file=sys.stderr)
        return 2
    out = args.out
    (out / "logs").mkdir(parents=True, exist_ok=True)
    (out / "runs").mkdir(exist_ok=True)
    pred_dir(args).mkdir(exist_ok=True)
    done = jobs_done(out)
    if args.cache is None and "cache" not in done:
        rc, cpu, wall = timed(cosim("learn", "cache", str(args.dataset), "--out", str(out / "cache"),
                                    "--every", str(CACHE_EVERY)), out / "logs" / "cache.log")
        record(out, job="cache", rc=rc, cpu_s=round(cpu, 1), wall_s=round(wall, 1))
        if rc:
            print(f"cache failed ({out / 'logs' / 'cache.log'})", file=sys.stderr)
            return rc
    preds = dict(predict_jobs(args))
    chains = []
    for key in selected(args):
        name, seed = key.split("/s")
        chain = []
        run = out / "runs" / f"{name}-s{seed}"
        if f"train {key}" not in done:
            resume = (run / "checkpoint.pt").is_file()  # a run cut short: continue it from its checkpoint
            if run.exists() and not resume:  # cut short before its first checkpoint: start it again
                shutil.rmtree(run)
            chain.append((f"train {key}", train_cmd(name, int(seed), args, run) + (["--resume"] if resume else [])))
        late = name == LATE[1] and int(seed) in LATE_SEEDS
        suffix = f" [{perturb_tag(args)}]" if perturb_tag(args) else ""
        for job in (f"predict {key}{suffix}", *([f"predict {LATE[0]}/s{seed}{suffix}"] if late else [])):
            if job not in done:
                chain.append((job, preds[job]))
        if f"tail {key}" not in done:
            chain.append((f"tail {key}", tail_cmd(run, args)))
        if chain:
            chains.append(chain)
    failed, stopped = run_chains(chains, args.parallel, out)
    if stopped:
        print("stopped by a signal: run the same command again to continue", file=sys.stderr)
        return 130
    print(f"{sum(map(len, chains))} jobs; failed: {', '.join(failed) or 'none'}")
    return 1 if failed else 0


def run_chains(chains: list[list[tuple[str, list[str]]]], parallel: int, out: Path) -> tuple[list[str], bool]:
    """Run the chains ``parallel`` at a time (each in a thread that waits for its processes); a chain's jobs
    run in order (a training, then its predictions) and stop at the first that fails. SIGINT or SIGTERM
    stops the running jobs (their cost is recorded like any other's) and starts no more. Returns the
    failed jobs and whether a signal stopped the run."""
    from concurrent.futures import ThreadPoolExecutor

    stopping = threading.Event()
    running: set[subprocess.Popen] = set()
    lock = threading.Lock()

    def stop(signum: int, _frame) -> None:
        stopping.set()
        with lock:
            for p in running:
                p.send_signal(signal.SIGTERM)

    def one(chain: list[tuple[str, list[str]]]) -> str | None:
        for name, cmd in chain:
            if stopping.is_set():
                return None
            print(f"start {name}", flush=True)
            rc, cpu, wall = timed(cmd, out / "logs" / (name.replace(" ", "_").replace("/", "_") + ".log"),
                                  running, lock, stopping)
            record(out, job=name, rc=rc, cpu_s=round(cpu, 1), wall_s=round(wall, 1))
            print(f"end   {name}: rc {rc}, {cpu:.0f} CPU-s, {wall:.0f} s", flush=True)
            if rc:
                return name
        return None

    handlers = {s: signal.signal(s, stop) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        with ThreadPoolExecutor(parallel) as pool:
            failed = [n for n in pool.map(one, chains) if n]
        return failed, stopping.is_set()
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)


# ------------------------------------------------------------------------------------------------ report


def score(refs, path: Path) -> dict[str, dict[str, dict]]:
    """AP30 / AP50 / AP70 of the vehicle group, overall and per condition value, of one prediction file:
    ``own``, against the objects its own agents see, and ``common``, against those any agent of V+I+D sees
    (the records again, read as ``all``), in one pass over the ground truth."""
    from dataclasses import replace

    from cosim.eval.evaluate import EvalOptions, evaluate
    from cosim.eval.predictions import read_predictions

    recs = read_predictions(path)
    setting = recs[0].agents
    sent = sum(r.bytes_sent or 0 for r in recs) / len(recs)
    both = recs if setting == "all" else [*recs, *(replace(r, agents="all") for r in recs)]
    result = evaluate(refs, both, EvalOptions(visible_only=True, metrics=("detection",)))
    keys = [("overall", "all"), *sorted({(b, v) for _s, b, v in result.cells if b in CONDITIONS})]
    tables: dict[str, dict[str, dict]] = {}
    for name, agents in (("own", setting), ("common", "all")):
        tables[name] = {}
        for b, v in keys:
            m = result.metrics(agents, b, v)
            det = m["detection"].get("vehicle", {})
            tables[name][f"{b}={v}"] = {k: det.get(k) for k in ("AP30", "AP50", "AP70")} | {"frames": m["frames"]}
    tables["bytes_per_frame"] = round(sent, 1)  # what the collaborators sent per ego frame
    return tables


def flatness(run: Path) -> dict:
    """Val AP30 / AP50 at each validation and the change of AP30 over the last 20 % of the steps, measured
    from the last validation at or before 80 % of them (so over at least the last 20 %)."""
    from cosim.learn.curves import own_validations
    from cosim.learn.train import read_log

    log = read_log(run)
    vals = own_validations(log)  # not the lines `cosim learn validate` adds
    if not vals:
        return {}
    last = vals[-1]["step"]  # the window: from the last validation at or before 80 % of the steps to the end
    start = max((r["step"] for r in vals if r["step"] <= 0.8 * last), default=vals[0]["step"])
    tail = [r for r in vals if r["step"] >= start]
    ap30 = [r["val"]["AP30"] for r in tail]
    ap50 = [r["val"]["AP50"] for r in vals]
    best = max(range(len(vals)), key=lambda i: (ap50[i] == ap50[i] and ap50[i], -i))  # best.pt: the first best
    dense = {r["step"]: r["val"] for r in log  # the tail check's (`run`'s tail jobs)
             if r.get("split") == "val" and r.get("every") == DENSE_EVERY and r["step"] >= start}
    dense_ap30 = [dense[st]["AP30"] for st in sorted(dense)]
    complete = sorted(dense) == [r["step"] for r in tail]
    return {"steps": [r["step"] for r in vals], "AP30": [r["val"]["AP30"] for r in vals], "AP50": ap50,
            "tail_AP30_change": round(max(ap30) - min(ap30), 2), "tail_from": start, "best_step": vals[best]["step"],
            "dense_tail": {"steps": sorted(dense), "AP30": dense_ap30,
                           "AP30_change": round(max(dense_ap30) - min(dense_ap30), 2) if complete else None}}


def mean_spread(xs: list[float]) -> tuple[float, float]:
    xs = [x for x in xs if x is not None and not math.isnan(x)]
    if not xs:
        return float("nan"), float("nan")
    m = sum(xs) / len(xs)
    return m, (max(xs) - min(xs)) / 2 if len(xs) > 1 else 0.0


def sources(args: argparse.Namespace) -> dict[str, Path]:
    """Each setting's results folder: ``--out``, or the folder ``--use NAME=DIR`` names (late fusion goes
    with its ego-only models unless named itself)."""
    use = {}
    for item in args.use or []:
        name, sep, folder = item.partition("=")
        if not sep or name not in [*SETTINGS, LATE[0]] or not Path(folder).is_dir():
            raise ValueError(f"--use {item}: expected NAME=DIR with NAME one of {', '.join([*SETTINGS, LATE[0]])}"
                             " and DIR a results folder of `run`")
        use[name] = Path(folder)
    if LATE[1] in use:
        use.setdefault(LATE[0], use[LATE[1]])
    return {name: use.get(name, args.out) for name in [*SETTINGS, LATE[0]]}


def report(args: argparse.Namespace, recall_tables: bool = True) -> int:
    """Score every prediction file of ``args``' perturbation and write ``ablation[-TAG].md`` and ``.json``;
    ``recall_tables``: with the ``cosim learn recall`` tables of the seed-0 predictions."""
    from cosim.eval.dataset import load_dataset

    try:
        src = sources(args)
    except ValueError as e:
        print(e, file=sys.stderr)
        return 2
    out = args.to or args.out
    tag = perturb_tag(args)
    (out / "logs").mkdir(parents=True, exist_ok=True)
    refs = [r for r in load_dataset(test_dataset(args)) if r.split == "test"]
    done = {folder: jobs_done(folder) for folder in set(src.values())}
    jobs = {}  # the jobs behind the reported results, from each setting's folder
    for folder, recs in done.items():
        for job, r in recs.items():
            name = job.split(" ")[-1].split("/s")[0]  # "train ego/s1" -> "ego"; "cache" stays "cache"
            if src.get(name, args.out) == folder:
                jobs[job if folder == args.out else f"{job} ({folder})"] = r
    models = [(n, s) for n, st in SETTINGS.items() for s in st.seeds]
    models += [(LATE[0], s) for s in LATE_SEEDS]
    results: dict[str, dict] = {}
    for name, s in models:
        base = LATE[1] if name == LATE[0] else name
        pred = pred_dir(args, src[name]) / f"{name}-s{s}.jsonl"
        if not pred.is_file():
            continue
        # the scores of a prediction file, made once
        cached = src[name] / (f"scores-{tag}" if tag else "scores") / f"{name}-s{s}.json"
        if cached.is_file() and cached.stat().st_mtime > pred.stat().st_mtime:
            scored = json.loads(cached.read_text())
        else:
            t0 = time.process_time()
            scored = {**score(refs, pred), "score_cpu_s": round(time.process_time() - t0, 1)}
            cached.parent.mkdir(exist_ok=True)
            cached.write_text(json.dumps(scored))
            print(f"scored {name}/s{s}", file=sys.stderr)
        curve = flatness(src[base] / "runs" / f"{base}-s{s}")  # read afresh: a tail check may have come since
        own = done[src[name]]
        train = done[src[base]].get(f"train {base}/s{s}", {})
        results[f"{name}/s{s}"] = {
            **scored, "curve": curve if name != LATE[0] else {}, "best_step": curve.get("best_step"),
            "steps": curve["steps"][-1] if curve else None, "folder": str(src[name]),
            "train_cpu_s": train.get("cpu_s"), "train_wall_s": train.get("wall_s"),
            "predict_cpu_s": own.get(f"predict {name}/s{s}" + (f" [{tag}]" if tag else ""), {}).get("cpu_s"),
            "tail_cpu_s": own.get(f"tail {base}/s{s}", {}).get("cpu_s") if name != LATE[0] else None}
    first = [pred_dir(args, src[n]) / f"{n}-s0.jsonl" for n in [*SETTINGS, LATE[0]]
             if (pred_dir(args, src[n]) / f"{n}-s0.jsonl").is_file()]
    recall = []
    for by in (None, *RECALL_BY) if recall_tables else ():  # the whole split, per environment, per strategy
        name = ("recall" if by is None else f"recall-{by}") + (f"-{tag}" if tag else "")
        rc, cpu, wall = timed(cosim("learn", "recall", str(args.dataset), *map(str, first), "--out", str(out / name),
                                    *(["--by", by] if by else [])), out / "logs" / f"{name}.log")
        jobs[name] = {"job": name, "rc": rc, "cpu_s": round(cpu, 1), "wall_s": round(wall, 1)}
        recall.append((out / name / "recall.md").read_text() if rc == 0
                      else f"recall failed: {out / 'logs' / f'{name}.log'}\n")
    stem = f"ablation-{tag}" if tag else "ablation"
    (out / f"{stem}.json").write_text(json.dumps({"results": results, "jobs": jobs, "perturb": tag or None},
                                                 indent=1) + "\n")
    where = ("\n## Where collaboration helps (seed 0, `cosim learn recall`)\n\n" + "\n".join(recall)) if recall else ""
    (out / f"{stem}.md").write_text(tables(results, jobs, tag) + where)
    print(out / f"{stem}.md")
    return 0


def _seed_values(results: dict, name: str, ref: str, key: str, metric: str) -> list[float | None]:
    """One metric of a cell for every seed of a setting."""
    return [r[ref].get(key, {}).get(metric) for k, r in results.items() if k.split("/s")[0] == name]


def _cell(results: dict, name: str, ref: str, key: str, metric: str) -> str:
    vals = _seed_values(results, name, ref, key, metric)
    m, spread = mean_spread(vals)
    if math.isnan(m):
        return "-"
    n = sum(v is not None for v in vals)
    return f"{m:.1f}" + (f" ± {spread:.1f}" if n > 1 else "")


def _bytes(rs: list[dict]) -> str:
    """The mean bytes sent per ego frame over a setting's seeds (prediction files without the field: -)."""
    vals = [r["bytes_per_frame"] for r in rs if r.get("bytes_per_frame") is not None]
    return f"{sum(vals) / len(vals):,.0f}" if vals else "-"


#: the drones' gain: (with drones, without), both intermediate fusion with max
GAINS = (("inter-VID", "inter-VI"), ("inter-VD", "inter-V"))


def _mean(results: dict, name: str, key: str, metric: str) -> float:
    return mean_spread(_seed_values(results, name, "common", key, metric))[0]


def gains(results: dict) -> list[str]:
    """What adding the drones changes, per condition value: the difference of the seed means (common
    reference) of each pair of :data:`GAINS`."""
    keys = ["overall=all", *sorted({key for r in results.values() for key in r["common"]
                                    if key.split("=")[0] in ("environment", "strategy")})]
    lines = ["", "## The drones' gain (common reference, AP30 / AP50; difference of the seed means)", "",
             "| gain | " + " | ".join(k.split("=")[1] if k != "overall=all" else "overall" for k in keys) + " |",
             "|---|" + "---:|" * len(keys)]
    have = {k.split("/s")[0] for k in results}
    for with_d, without in GAINS:
        if with_d not in have or without not in have:
            continue
        cells = []
        for key in keys:
            d = [_mean(results, with_d, key, m) - _mean(results, without, key, m) for m in ("AP30", "AP50")]
            cells.append(" / ".join("-" if math.isnan(x) else f"{x:+.1f}" for x in d))
        label = f"{AGENT_LABEL[SETTINGS[with_d].agents]} - {AGENT_LABEL[SETTINGS[without].agents]}"
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines if len(lines) > 5 else []


def setting_label(name: str) -> str:
    """A setting's name in the tables: ``intermediate (max), V+I+D, trained with pose error 0.4,0.4``."""
    if name == LATE[0]:
        return "late, V+I+D (ego-only models)"
    st = SETTINGS[name]
    kind = {"none": "", "early": "early, ", "intermediate": f"intermediate ({st.fuse}), "}[st.fusion]
    train = dict(zip(st.train[::2], st.train[1::2], strict=True))
    extra = ([f"trained with pose error {train['--pose-noise']}"] if "--pose-noise" in train else []) + \
        ([f"an encoder per {train['--encoders']}"] if "--encoders" in train else [])
    return ", ".join([f"{kind}{AGENT_LABEL[st.agents]}", *extra])


def tables(results: dict, jobs: dict, tag: str = "") -> str:
    names = [n for n in [*SETTINGS, LATE[0]] if any(k.split("/s")[0] == n for k in results)]

    label = setting_label

    def seeds(n: str) -> int:
        return sum(k.split("/s")[0] == n for k in results)

    lines = ["# cosim learn ablation (benchmarks/learn_ablation.py)", "",
             "AP of the vehicle group in %, mean ± half the range over seeds where there are several.",
             f"Test perturbation: {tag or 'none'}.", ""]
    lines += ["## Overall", "", "| setting | seeds | steps | own visible AP30 | AP50 | common AP30 | AP50 | AP70 |"
              " bytes sent per ego frame | best step | val AP30 change over the last validations (from <= 80 % of "
              f"the steps) | the same, every cached tick (every {DENSE_EVERY}) | train CPU-s |",
              "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for n in names:
        rs = [r for k, r in results.items() if k.split("/s")[0] == n]
        steps = ", ".join(sorted({str(r.get("steps")) for r in rs if r.get("steps")})) or "-"
        change = [r["curve"].get("tail_AP30_change") for r in rs if r["curve"]]
        dense = [r["curve"].get("dense_tail", {}).get("AP30_change") for r in rs if r["curve"]]
        cpu = [r["train_cpu_s"] for r in rs if r["train_cpu_s"]]
        best = [str(r["best_step"]) for r in rs if r["best_step"] is not None]
        lines.append(f"| {label(n)} | {seeds(n)} | {steps} | {_cell(results, n, 'own', 'overall=all', 'AP30')} | "
                     f"{_cell(results, n, 'own', 'overall=all', 'AP50')} | "
                     f"{_cell(results, n, 'common', 'overall=all', 'AP30')} | "
                     f"{_cell(results, n, 'common', 'overall=all', 'AP50')} | "
                     f"{_cell(results, n, 'common', 'overall=all', 'AP70')} | {_bytes(rs)} | "
                     f"{', '.join(best) or '-'} | "
                     f"{', '.join(f'{c:.1f}' for c in change) or '-'} | "
                     f"{', '.join('-' if c is None else f'{c:.1f}' for c in dense) or '-'} | "
                     f"{', '.join(f'{c:.0f}' for c in cpu) or '-'} |")
    for cond in CONDITIONS:
        values = sorted({key.split("=", 1)[1] for r in results.values() for key in r["common"]
                         if key.startswith(cond + "=")})
        frames = {v: next((r["common"][f"{cond}={v}"]["frames"] for r in results.values()
                           if f"{cond}={v}" in r["common"]), 0) for v in values}
        lines += ["", f"## By {cond} (common reference: objects any agent of V+I+D sees)", "",
                  "Test frames: " + ", ".join(f"{v} {frames[v]}" for v in values) + ".", "",
                  "| setting | " + " | ".join(f"{v} AP30 | {v} AP50" for v in values) + " |",
                  "|---|" + "---:|" * (2 * len(values))]
        for n in names:
            cells = [_cell(results, n, "common", f"{cond}={v}", m) for v in values for m in ("AP30", "AP50")]
            lines.append(f"| {label(n)} | " + " | ".join(cells) + " |")
    lines += gains(results)
    lines += ["", "## CPU of every stage", "", "| job | CPU-s | wall s |", "|---|---:|---:|"]
    total = 0.0
    for job, r in jobs.items():
        lines.append(f"| {job} | {r['cpu_s']:.0f} | {r['wall_s']:.0f} |")
        total += r["cpu_s"]
    lines.append(f"| all jobs | {total:.0f} | |")
    return "\n".join(lines) + "\n"


# -------------------------------------------------------------------------------------------- robustness

#: issue 49's test-time grid (V2X-ViT's, CoAlign's and Griffin's levels): pose error POS_M,ROT_DEG and
#: latency in ms (whole ticks: the learnability sweep's 5 Hz has no 100 ms, a 10 Hz one does); level 0 of each
#: is the clean grid's own predictions
POSE_LEVELS = ("0.2,0.2", "0.4,0.4", "0.6,0.6")
LATENCY_LEVELS = ("200", "400")
#: the rows of the robustness tables: every fusion mode on V+I+D, ego only, and the robust variants
ROBUST_ROWS = ("ego", "early-VID", "inter-VID", "inter-VID-att", "late-VID", "inter-VID-pose", "inter-VID-kind",
               "inter-VID-sensor")
#: the uniform side of the mixed table for a setting the uniform grid does not train: on one LiDAR per kind,
#: per-sensor encoders are the per-kind model, weight for weight (tests/test_learn.py)
UNIFORM_TWIN = {"inter-VID-sensor": "inter-VID-kind"}


def level(args: argparse.Namespace, pose: str | None = None, latency: str | None = None,
          loss: str | None = None, timed_data: bool = False) -> argparse.Namespace:
    """``args`` with one test perturbation (the others off). A latency reads earlier ticks: its predictions
    read ``--latency-cache`` (a cache made with ``--every 1``), or the episodes' MCAP without one (the grid's
    cache holds every second tick only). ``timed_data``: on ``--latency-data``'s test split when given (the
    same sweep at 10 Hz, where 100 ms is a tick), from its cache or MCAP too."""
    a = argparse.Namespace(**{**vars(args), "pose_noise": pose, "latency": latency, "loss": loss, "test_data": None,
                              "test_every": None})
    if timed_data and args.latency_data is not None:
        a.test_data, a.test_every = args.latency_data, TEST_EVERY * tick_ratio(args.latency_data, args.dataset)
    if latency is not None or a.test_data is not None:
        a.cache, a.mcap = args.latency_cache, args.latency_cache is None
    return a


def levels(args: argparse.Namespace) -> dict[str, list[tuple[str, argparse.Namespace]]]:
    """The sweeps of ``robustness``: name -> [(column, the perturbation's args)], each from the clean grid."""
    clean, timed = ("0", level(args)), ("0", level(args, timed_data=True))  # the same unless --latency-data
    out = {"pose": [clean, *((p, level(args, pose=p)) for p in args.pose_levels)],
           "latency": [timed, *((f"{ms} ms", level(args, latency=ms, timed_data=True)) for ms in args.latency_levels)]}
    if args.links:
        out["links"] = [("ideal", timed[1]), ("links", level(args, latency="links", loss="links", timed_data=True))]
    return out


def robustness(args: argparse.Namespace) -> int:
    """Predict the test split under every level of :func:`levels` with the trained models (no training),
    score each level (``report`` without its recall tables), and write ``robustness.md``, ``.json`` and, with
    ``--picture``, AP30 against pose error and latency."""
    try:
        src = sources(args)
    except ValueError as e:
        print(e, file=sys.stderr)
        return 2
    if args.mixed is not None and not (args.mixed / "ablation.json").is_file():
        print(f"--mixed {args.mixed}: no ablation.json (run `report` on the mixed-LiDAR data's results first)",
              file=sys.stderr)
        return 2
    out = args.to or args.out
    try:
        sweeps = levels(args)
    except ValueError as e:
        print(e, file=sys.stderr)
        return 2
    perturbed = {perturb_tag(a): a for cols in sweeps.values() for _c, a in cols if perturb_tag(a)}
    done = {folder: jobs_done(folder) for folder in set(src.values())}
    for a in perturbed.values():  # the predictions, in the folder of each setting's results
        by_folder: dict[Path, list[list[tuple[str, list[str]]]]] = {}
        for job, cmd in predict_jobs(a, src):
            name, s = job.split(" ")[1].split("/s")
            folder, base = src[name], LATE[1] if name == LATE[0] else name
            if job in done[folder] or f"train {base}/s{s}" not in done[src[base]]:
                continue  # done already, or a setting not trained (or still training: its best.pt is not final)
            pred_dir(a, folder).mkdir(parents=True, exist_ok=True)
            (folder / "logs").mkdir(exist_ok=True)
            by_folder.setdefault(folder, []).append([(job, cmd)])
        for folder, chains in by_folder.items():
            failed, stopped = run_chains(chains, args.parallel, folder)
            if stopped:
                print("stopped by a signal: run the same command again to continue", file=sys.stderr)
                return 130
            if failed:
                print(f"failed: {', '.join(failed)} (logs in {folder / 'logs'})", file=sys.stderr)
                return 1
    scored = {}
    for tag, a in {"": level(args), **perturbed}.items():
        rc = report(a, recall_tables=False)
        if rc:
            return rc
        scored[tag] = json.loads((out / (f"ablation-{tag}.json" if tag else "ablation.json")).read_text())["results"]
    mixed = json.loads((args.mixed / "ablation.json").read_text())["results"] if args.mixed else None
    grid = {name: [(col, scored[perturb_tag(a)]) for col, a in cols] for name, cols in sweeps.items()}
    (out / "robustness.json").write_text(json.dumps({"sweeps": {n: [c for c, _r in cols] for n, cols in grid.items()},
                                                     "results": {t or "clean": r for t, r in scored.items()},
                                                     "mixed": mixed}, indent=1) + "\n")
    (out / "robustness.md").write_text(robustness_tables(grid, mixed, args.latency_data))
    if args.picture:
        robustness_picture(grid, args.picture)
    print(out / "robustness.md")
    return 0


def _ap(results: dict, name: str, key: str = "overall=all") -> str:
    """``AP30 / AP50`` of a setting (mean over its seeds, ± half the range of AP30), common reference."""
    a30, spread = mean_spread(_seed_values(results, name, "common", key, "AP30"))
    a50, _ = mean_spread(_seed_values(results, name, "common", key, "AP50"))
    if math.isnan(a30):
        return "-"
    n = sum(v is not None for v in _seed_values(results, name, "common", key, "AP30"))
    return f"{a30:.1f}" + (f" ± {spread:.1f}" if n > 1 else "") + f" / {a50:.1f}"


def robustness_tables(grid: dict[str, list[tuple[str, dict]]], mixed: dict | None = None,
                      latency_data: Path | None = None) -> str:
    """The markdown of ``robustness``: AP against each sweep's levels (with the fall from the clean column),
    the links as simulated per environment, AP against bytes sent, and mixed LiDARs against uniform ones."""
    first = grid["pose"][0][1]
    rows = [n for n in ROBUST_ROWS if any(k.split("/s")[0] == n for cols in grid.values() for _c, r in cols
                                          for k in r)]
    seeds = {n: sum(k.split("/s")[0] == n for k in first) for n in rows}
    lines = ["# Collaboration as deployed (benchmarks/learn_ablation.py robustness)", "",
             "AP30 / AP50 of the vehicle group in % (common reference: the objects any agent of V+I+D sees), the mean "
             "over seeds with ± half the range of AP30; every model trained on clean data unless its name says "
             "otherwise, each perturbation applied at test only.", ""]
    titles = {"pose": "Against pose error (each collaborator's x, y and yaw; POS_M,ROT_DEG standard deviations)",
              "latency": "Against latency (each collaborator's data from that long before the ego's tick)"}
    for name in ("pose", "latency"):
        cols = grid[name]
        where = ([f"On the test split of `{latency_data}` (the same sweep at another tick rate), its own clean column "
                  "0; the links below too.", ""] if name == "latency" and latency_data is not None else [])
        lines += [f"## {titles[name]}", "", *where,
                  "| setting | seeds | " + " | ".join(c for c, _r in cols) + " | AP30 fall at the last level |",
                  "|---|---:|" + "---:|" * (len(cols) + 1)]
        for n in rows:
            fall = mean_spread(_seed_values(cols[0][1], n, "common", "overall=all", "AP30"))[0] - \
                mean_spread(_seed_values(cols[-1][1], n, "common", "overall=all", "AP30"))[0]
            lines.append(f"| {setting_label(n)} | {seeds[n]} | " + " | ".join(_ap(r, n) for _c, r in cols) +
                         f" | {'-' if math.isnan(fall) else f'{fall:.1f}'} |")
        lines.append("")
    if "links" in grid:
        (_i, ideal), (_l, links) = grid["links"]
        envs = sorted({k.split("=", 1)[1] for r in ideal.values() for k in r["common"] if k.startswith("environment=")})
        lines += ["## The links as simulated (`--latency links --loss links`) against ideal links, per environment",
                  "", "| setting | " + " | ".join(f"{e}: ideal | {e}: links" for e in ["all", *envs]) + " |",
                  "|---|" + "---:|" * (2 * len(envs) + 2)]
        for n in rows:
            keys = ["overall=all", *(f"environment={e}" for e in envs)]
            lines.append(f"| {setting_label(n)} | " + " | ".join(f"{_ap(ideal, n, k)} | {_ap(links, n, k)}"
                                                                  for k in keys) + " |")
        lines.append("")
    lines += ["## AP against bytes sent per ego frame (clean links)", "",
              "| setting | bytes sent per ego frame | AP30 / AP50 |", "|---|---:|---:|"]
    for n in rows:
        lines.append(f"| {setting_label(n)} | {_bytes([r for k, r in first.items() if k.split('/s')[0] == n])} | "
                     f"{_ap(first, n)} |")
    if mixed is not None:
        lines += ["", "## Mixed LiDARs against uniform ones (the same scenes and seeds)", "",
                  "| setting | uniform | mixed | AP30 change |", "|---|---:|---:|---:|"]
        for n in ROBUST_ROWS:
            if not any(k.split("/s")[0] == n for k in mixed):
                continue
            u = n if any(k.split("/s")[0] == n for k in first) else UNIFORM_TWIN.get(n, n)
            d = mean_spread(_seed_values(mixed, n, "common", "overall=all", "AP30"))[0] - \
                mean_spread(_seed_values(first, u, "common", "overall=all", "AP30"))[0]
            lines.append(f"| {setting_label(n)} | {_ap(first, u)} | {_ap(mixed, n)} | "
                         f"{'-' if math.isnan(d) else f'{d:+.1f}'} |")
    return "\n".join(lines) + "\n"


def robustness_picture(grid: dict[str, list[tuple[str, dict]]], path: Path) -> None:
    """AP30 (mean, the seeds' range as error bars) against pose error and latency, a line per setting."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    for ax, name, xlabel in ((axes[0], "pose", "pose error [m, deg] (standard deviation)"),
                             (axes[1], "latency", "latency [ms]")):
        cols = grid[name]
        xs = [float(c.split(",")[0].split(" ")[0]) for c, _r in cols]
        for n in ROBUST_ROWS:
            vals = [[v for v in _seed_values(r, n, "common", "overall=all", "AP30") if v is not None] for _c, r in cols]
            if not any(vals):
                continue
            pts = [(x, sum(v) / len(v), min(v), max(v)) for x, v in zip(xs, vals, strict=True) if v]
            ax.errorbar([p[0] for p in pts], [p[1] for p in pts], yerr=[[p[1] - p[2] for p in pts],
                                                                        [p[3] - p[1] for p in pts]],
                        marker="o", capsize=3, label=setting_label(n))
        ax.set_xlabel(xlabel)
        ax.set_xticks(xs)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("AP30 [%] (common reference)")
    axes[1].legend(fontsize=7, loc="lower left")
    fig.suptitle("cosim learn: collaboration as deployed (trained clean, perturbed at test)")
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="cache, train and predict every setting")
    rp = sub.add_parser("report", help="score the predictions and write OUT/ablation.md and .json")
    rb = sub.add_parser("robustness", help="predict and score under pose error, latency and the simulated links;\n"
                                           "write OUT/robustness.md and .json (issue 49)")
    for q in (r, rp, rb):
        q.add_argument("dataset", type=Path, help="batch folder of sweeps/learnability.yaml")
        q.add_argument("--out", type=Path, required=True)
    for q in (rp, rb):
        q.add_argument("--use", nargs="*", metavar="NAME=DIR",
                       help="take these settings from another run's folder (e.g. ego=out/ablation3600: ego only,\n"
                            "and late fusion with its models, trained for more steps)")
        q.add_argument("--to", type=Path, help="write the report and recall tables here (default: --out)")
    rb.add_argument("--pose-levels", nargs="*", default=list(POSE_LEVELS), metavar="POS_M,ROT_DEG",
                    help=f"pose errors beside the clean grid (default {' '.join(POSE_LEVELS)})")
    rb.add_argument("--latency-levels", nargs="*", default=list(LATENCY_LEVELS), metavar="MS",
                    help=f"latencies beside the clean grid, whole ticks (default {' '.join(LATENCY_LEVELS)}: 5 Hz\n"
                         "data; 100 needs a sweep at --set tick_hz=10)")
    rb.add_argument("--latency-cache", type=Path, metavar="DIR",
                    help="a `cosim learn cache --every 1` of the dataset for the latency and links predictions\n"
                         "(default: they read the MCAP files)")
    rb.add_argument("--latency-data", type=Path, metavar="DIR",
                    help="the latency and links sweeps on this dataset's test split instead, with its own clean\n"
                         "column: the same sweep at 10 Hz, where 100 ms is one tick (cosim batch ... --split test\n"
                         "--set tick_hz=10); --latency-cache is then a cache of it")
    rb.add_argument("--links", action="store_true", help="also --latency links --loss links (the simulated links)")
    rb.add_argument("--mixed", type=Path, metavar="DIR",
                    help="a results folder of `run` and `report` on the same sweep with mixed LiDARs (per-agent rigs)")
    rb.add_argument("--parallel", type=int, default=2)
    rb.add_argument("--cache", type=Path, help="the cache the models were trained from (default: OUT/cache)")
    rb.add_argument("--perturb-seed", type=int, default=0, help="the perturbations' seed (default 0)")
    rb.add_argument("--picture", type=Path, help="write AP30 against pose error and latency here (PNG)")
    r.add_argument("--steps", type=int, default=800)
    r.add_argument("--lr", type=float, default=3e-3)
    r.add_argument("--val-steps", type=int, default=200)
    r.add_argument("--parallel", type=int, default=2)
    r.add_argument("--only", nargs="*", help="only these settings (names of SETTINGS)")
    r.add_argument("--seeds", nargs="*", type=int, metavar="S",
                   help="only these seeds of each setting (e.g. 0 1: issue 49's two seeds a cell)")
    r.add_argument("--cache", type=Path, help="an existing cache to train from (another run's OUT/cache), made\n"
                   "with --every 2 on the same dataset (default: OUT/cache, made when missing)")
    for q in (r, rp):  # the test perturbation (cosim learn predict checks the values)
        q.add_argument("--pose-noise", metavar="POS_M,ROT_DEG", help="predict and score with this pose error")
        q.add_argument("--latency", metavar="MS|links", help="... with this latency")
        q.add_argument("--loss", metavar="P|links", help="... with this message loss")
        q.add_argument("--perturb-seed", type=int, default=0, help="the perturbations' seed (default 0)")
    args = p.parse_args()
    return {"run": run_all, "report": report, "robustness": robustness}[args.cmd](args)


if __name__ == "__main__":
    sys.exit(main())
