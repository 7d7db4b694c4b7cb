"""Batch progress: an overall bar (simulated ticks, so the ETA is honest across long and short
episodes) plus one status line per worker. Without a terminal it logs one line per finished episode."""

from __future__ import annotations

import sys
import time
from typing import Any

from cosim.batch.job import Event


def _eta(elapsed_s: float, done: float, total: float) -> str:
    if done <= 0 or total <= done:
        return "?" if total > done else "0s"
    s = int(elapsed_s * (total - done) / done)
    h, rem = divmod(s, 3600)
    m, sec = divmod(rem, 60)
    return f"{h}h{m:02d}m" if h else f"{m}m{sec:02d}s"


class BatchProgress:
    """Receives executor events and the batch's decisions; draws or logs them."""

    def __init__(self, total_ticks: int, episodes: int, workers: int, *, enabled: bool = True,
                 stream: Any = None):
        self.stream = stream or sys.stderr
        self.total_ticks = max(1, total_ticks)
        self.episodes = episodes
        self.finished = 0
        self.failed = 0
        self.retried = 0
        self._ticks: dict[str, int] = {}  # episode id -> ticks counted so far
        self._started = time.monotonic()
        self._bars = enabled and hasattr(self.stream, "isatty") and self.stream.isatty()
        self._enabled = enabled
        self._overall: Any = None
        self._workers: dict[str, Any] = {}
        self._n_worker_bars = workers
        if self._bars:
            from tqdm import tqdm

            self._overall = tqdm(total=self.total_ticks, desc="batch", unit="tick", file=self.stream,
                                 dynamic_ncols=True, mininterval=0.5, position=0)
            self._tqdm = tqdm

    def _worker_bar(self, worker: str) -> Any:
        if worker not in self._workers and len(self._workers) < self._n_worker_bars:
            self._workers[worker] = self._tqdm(total=0, position=len(self._workers) + 1, file=self.stream,
                                               bar_format="  {desc}", leave=False)
        return self._workers.get(worker)

    def _counted(self, episode: str, ticks: int) -> None:
        delta = ticks - self._ticks.get(episode, 0)
        self._ticks[episode] = ticks
        if self._overall is not None and delta:
            self._overall.update(delta)

    def _postfix(self) -> None:
        if self._overall is not None:
            self._overall.set_postfix_str(f"{self.finished}/{self.episodes} episodes, {self.failed} failed, "
                                          f"{self.retried} retried", refresh=False)

    def event(self, ev: Event) -> None:
        if not self._bars:
            return
        bar = self._worker_bar(ev.worker)
        if ev.kind == "started" and bar is not None:
            bar.set_description_str(f"{ev.worker}: {ev.job.episode_id} starting (attempt {ev.job.attempt})")
        elif ev.kind == "progress":
            self._counted(ev.job.episode_id, ev.done)
            if bar is not None:
                bar.set_description_str(f"{ev.worker}: {ev.job.episode_id} tick {ev.done}/{ev.total}")
        elif ev.kind == "finished" and bar is not None:
            bar.set_description_str(f"{ev.worker}: idle")

    def settled(self, episode: str, n_ticks: int, status: str, error: str = "") -> None:
        """An episode is over for this batch: ``done``, ``failed`` (for good) or ``retry``."""
        if status == "retry":
            self.retried += 1
            self._counted(episode, 0)
            if self._enabled:
                self._write(f"retrying {episode}: {error}")
        else:
            self.finished += 1
            self.failed += status == "failed"
            self._counted(episode, n_ticks)
            if self._enabled and not self._bars:
                done = sum(self._ticks.values())
                eta = _eta(time.monotonic() - self._started, done, self.total_ticks)
                self._write(f"{episode} {status} ({self.finished}/{self.episodes} episodes, "
                            f"{self.failed} failed, ETA {eta})")
        self._postfix()

    def _write(self, line: str) -> None:
        if self._bars:
            self._tqdm.write(line, file=self.stream)
        else:
            self.stream.write(line + "\n")
            self.stream.flush()

    def close(self) -> None:
        for bar in self._workers.values():
            bar.close()
        if self._overall is not None:
            self._overall.close()
