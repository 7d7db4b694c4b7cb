"""The batch loop: skip what is verifiably finished, run the rest on an executor, retry, record.

Resume rule: an episode is skipped only when its last manifest record is ``done`` for the same
seed, parameters, file and resolved scenario (``scenario_sha256``), and the file on disk has the
recorded size and sha256. Everything else runs again (the ``.partial`` files a killed run left in the
output folders are removed first, each with a warning). Each attempt is recorded when
it starts (``running``) and when it ends (``done`` or ``failed``), so a crash of the batch itself
leaves a ``running`` record that the next run simply redoes.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cosim.batch.job import Event, Executor, Job
from cosim.batch.manifest import Manifest, manifest_name
from cosim.batch.plan import Episode, Plan
from cosim.batch.progress import BatchProgress
from cosim.io.manifest import latest_records, verify

log = logging.getLogger(__name__)

POLL_S = 0.5
VERIFY_THREADS = 8  # files hashed at once when checking what a previous run finished


@dataclass
class BatchSummary:
    planned: int
    skipped: int = 0
    done: int = 0
    failed: dict[str, str] = field(default_factory=dict)  # episode id -> last error
    retried: int = 0
    wall_time_s: float = 0.0
    manifest: Path | None = None

    @property
    def ok(self) -> bool:
        return not self.failed


def _same(a: Any, b: Any) -> bool:
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def is_finished(out_dir: Path, episode: Episode, record: dict[str, Any] | None) -> bool:
    """The episode's last record is ``done`` for this very episode and its file verifies."""
    return (record is not None and record.get("status") == "done" and record.get("seed") == episode.seed
            and record.get("file") == episode.file and _same(record.get("params"), episode.params)
            and record.get("scenario_sha256") == episode.fingerprint and verify(out_dir, record))


def _base_record(ep: Episode, sweep: str) -> dict[str, Any]:
    return {"episode": ep.id, "sweep": sweep, "split": ep.split, "file": ep.file, "labels": ep.labels,
            "params": ep.params, "seed": ep.seed, "duration_s": ep.duration_s, "scenario_sha256": ep.fingerprint}


def n_ticks(ep: Episode) -> int:
    return round(ep.duration_s * float(ep.scenario.get("tick_hz", 5.0)))


def run_batch(plan: Plan, out_dir: Path | str, executor: Executor, *, retries: int = 2,
              show_progress: bool = True, progress: BatchProgress | None = None) -> BatchSummary:
    """Run every unfinished episode of ``plan`` into ``out_dir``; returns what happened.

    Each episode gets up to ``1 + retries`` attempts in this run. Raises ``KeyboardInterrupt`` after
    stopping the executor when interrupted (the manifest stays consistent).
    """
    started = time.monotonic()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    existing = latest_records(out)
    with ThreadPoolExecutor(max_workers=VERIFY_THREADS) as pool:  # sha256 releases the GIL
        finished = list(pool.map(lambda ep: is_finished(out, ep, existing.get(ep.id)), plan.episodes))
    todo = [ep for ep, done in zip(plan.episodes, finished, strict=True) if not done]
    summary = BatchSummary(planned=len(plan.episodes), skipped=len(plan.episodes) - len(todo))
    by_id = {ep.id: ep for ep in todo}
    attempts = {ep.id: int((existing.get(ep.id) or {}).get("attempts", 0)) for ep in todo}
    from cosim.io.writer import remove_stale_partials

    for folder in sorted({out, *((out / ep.file).parent for ep in plan.episodes)}):
        remove_stale_partials(folder)  # left by a killed run (any episode): removed, each with a warning
    display = progress or BatchProgress(sum(n_ticks(ep) for ep in todo), len(todo),
                                        getattr(executor, "status_lines", 4), enabled=show_progress)
    pending: deque[Job] = deque(
        Job(episode_id=ep.id, file=ep.file, out_dir=str(out.resolve()), scenario=ep.scenario,
            base_dir=ep.base_dir, attempt=1, n_ticks=n_ticks(ep)) for ep in todo
    )
    manifest_path = out / manifest_name(plan.shard)
    summary.manifest = manifest_path
    sweep = plan.sweep.name

    with Manifest(manifest_path) as manifest:

        def handle(events: list[Event]) -> None:
            for ev in events:
                display.event(ev)
                if ev.kind != "finished":
                    continue
                ep, job, outcome = by_id[ev.job.episode_id], ev.job, ev.outcome or {}
                rec = {**_base_record(ep, sweep), "attempts": attempts[ep.id], "worker": ev.worker,
                       "host": outcome.get("host"), "node": outcome.get("node"),
                       "container": outcome.get("container"), "wall_time_s": outcome.get("wall_time_s"),
                       "versions": outcome.get("versions")}
                if outcome.get("ok"):
                    manifest.append({**rec, "status": "done", "size_bytes": outcome["size_bytes"],
                                     "sha256": outcome["sha256"], "error": None})
                    summary.done += 1
                    display.settled(ep.id, job.n_ticks, "done")
                    continue
                error = str(outcome.get("error") or "unknown error")
                if job.attempt <= retries and outcome.get("retryable", True):
                    manifest.append({**rec, "status": "failed", "error": error, "retrying": True})
                    summary.retried += 1
                    display.settled(ep.id, job.n_ticks, "retry", error)
                    pending.append(dataclasses.replace(job, attempt=job.attempt + 1))
                else:
                    manifest.append({**rec, "status": "failed", "error": error})
                    summary.failed[ep.id] = error
                    display.settled(ep.id, job.n_ticks, "failed", error)

        try:
            while pending or executor.busy():
                while pending and executor.has_capacity():
                    job = pending.popleft()
                    ep = by_id[job.episode_id]
                    attempts[ep.id] += 1
                    manifest.append({**_base_record(ep, sweep), "status": "running", "attempts": attempts[ep.id]})
                    handle(executor.submit(job))
                handle(executor.poll(POLL_S))
        finally:
            executor.shutdown()
            display.close()
    summary.wall_time_s = time.monotonic() - started
    return summary
