"""Executors: where episodes run. The batch loop submits jobs and polls events; it never blocks on one.

- ``local`` (default): one fresh ``spawn`` process per episode, at most ``workers`` at a time. The
  processes are plain non-daemonic :class:`multiprocessing.Process` objects managed here, so an
  episode may start its own worker processes (traffic, drones). A process that dies without
  reporting (segfault, OOM kill) becomes a failed attempt naming its exit code or signal.
- ``ray``: see :mod:`cosim.batch.ray_backend`.

Both turn work into the same :class:`~cosim.batch.job.Event` stream, so retries, the manifest and progress live in
one place (:mod:`cosim.batch.runner`).
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import multiprocessing.connection as mpc
import os
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from cosim.batch.job import PROGRESS_INTERVAL_S, EpisodeFn, Event, Executor, Job, execute, run_real_episode
from cosim.batch.ray_backend import RayExecutor
from cosim.errors import InputError

log = logging.getLogger(__name__)

# ----------------------------------------------------------------------------------- local pool


def _watch_parent(parent_pid: int) -> None:
    """Stop this episode process if the batch process dies (so no orphan keeps writing)."""
    import _thread

    def loop() -> None:
        while True:
            time.sleep(1.0)
            if os.getppid() != parent_pid:
                _thread.interrupt_main()  # KeyboardInterrupt: the episode cleans up its own workers
                time.sleep(15.0)
                os._exit(70)

    threading.Thread(target=loop, name="parent-watch", daemon=True).start()


def _child_main(job: Job, fn: EpisodeFn, conn: mpc.Connection, parent_pid: int, log_level: int) -> None:
    logging.basicConfig(level=log_level, format=f"%(levelname)s [{job.episode_id}] %(name)s: %(message)s")
    _watch_parent(parent_pid)
    last = [0.0]

    def progress(done: int, total: int) -> None:
        now = time.monotonic()
        if done >= total or now - last[0] >= PROGRESS_INTERVAL_S:
            last[0] = now
            conn.send(("progress", done, total))

    outcome = execute(job, fn, progress)
    conn.send(("finished", outcome))
    conn.close()


def describe_exit(exitcode: int | None) -> str:
    if exitcode is None:
        return "worker process vanished"
    if exitcode < 0:
        try:
            name = signal.Signals(-exitcode).name
        except ValueError:
            name = f"signal {-exitcode}"
        return f"worker process killed by {name}"
    return f"worker process exited with code {exitcode} without reporting a result"


@dataclass
class _Slot:
    index: int
    job: Job
    process: Any
    conn: mpc.Connection
    outcome: dict[str, Any] | None = None


class LocalExecutor:
    """A pool of fresh spawn processes, one per episode."""

    name = "local"

    def __init__(self, workers: int = 1, episode_fn: EpisodeFn = run_real_episode,
                 log_level: int = logging.WARNING, stop_grace_s: float = 20.0):
        if workers < 1:
            raise InputError(f"--workers must be >= 1, got {workers}")
        self.workers = workers
        self.episode_fn = episode_fn
        self.log_level = log_level
        self.stop_grace_s = stop_grace_s
        self._ctx = mp.get_context("spawn")
        self._slots: dict[int, _Slot] = {}
        self.status_lines = min(workers, 16)

    def has_capacity(self) -> bool:
        return len(self._slots) < self.workers

    def busy(self) -> bool:
        return bool(self._slots)

    def submit(self, job: Job) -> list[Event]:
        index = min(set(range(self.workers)) - set(self._slots))
        recv, send = self._ctx.Pipe(duplex=False)
        proc = self._ctx.Process(target=_child_main, name=f"cosim-batch-{index}",
                                 args=(job, self.episode_fn, send, os.getpid(), self.log_level), daemon=False)
        proc.start()
        send.close()
        self._slots[index] = _Slot(index, job, proc, recv)
        return [Event("started", job, self.worker_name(index))]

    @staticmethod
    def worker_name(index: int) -> str:
        return f"w{index}"

    def _drain(self, slot: _Slot, events: list[Event]) -> None:
        while True:
            try:
                if not slot.conn.poll():
                    return
                msg = slot.conn.recv()
            except (EOFError, OSError):
                return
            if msg[0] == "progress":
                events.append(Event("progress", slot.job, self.worker_name(slot.index), done=msg[1], total=msg[2]))
            elif msg[0] == "finished":
                slot.outcome = msg[1]

    def poll(self, timeout_s: float) -> list[Event]:
        events: list[Event] = []
        if not self._slots:
            return events
        waitables: list[Any] = []
        for slot in self._slots.values():
            waitables += [slot.conn, slot.process.sentinel]
        mpc.wait(waitables, timeout=timeout_s)
        for index in sorted(self._slots):
            slot = self._slots[index]
            self._drain(slot, events)
            if slot.process.is_alive() and slot.outcome is None:
                continue
            slot.process.join(timeout=30.0 if slot.outcome is not None else 5.0)
            if slot.process.is_alive():  # reported but hangs on exit: do not wait for it forever
                slot.process.kill()
                slot.process.join(5.0)
            self._drain(slot, events)
            outcome = slot.outcome or {"ok": False, "error": describe_exit(slot.process.exitcode),
                                       "episode": slot.job.episode_id}
            slot.conn.close()
            del self._slots[index]
            events.append(Event("finished", slot.job, self.worker_name(index), outcome=outcome))
        return events

    def shutdown(self) -> None:
        """Stop running episodes: SIGINT first (they clean up their workers), then SIGKILL."""
        for slot in self._slots.values():
            if slot.process.is_alive() and slot.process.pid is not None:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(slot.process.pid, signal.SIGINT)
        deadline = time.monotonic() + self.stop_grace_s
        for slot in self._slots.values():
            slot.process.join(max(0.0, deadline - time.monotonic()))
            if slot.process.is_alive():
                slot.process.kill()
                slot.process.join(5.0)
            slot.conn.close()
        self._slots.clear()


# ------------------------------------------------------------------------------------- registry

ExecutorFactory = Callable[..., Executor]
_EXECUTORS: dict[str, ExecutorFactory] = {}


def register_executor(name: str, factory: ExecutorFactory) -> None:
    if name in _EXECUTORS:
        raise ValueError(f"executor {name!r} is already registered")
    _EXECUTORS[name] = factory


def make_executor(name: str, **kwargs: Any) -> Executor:
    if name not in _EXECUTORS:
        raise InputError(f"unknown backend {name!r}; known: {', '.join(sorted(_EXECUTORS))}")
    return _EXECUTORS[name](**kwargs)


def known_executors() -> list[str]:
    return sorted(_EXECUTORS)


def _make_local(*, workers: int = 1, episode_fn: EpisodeFn = run_real_episode, log_level: int = logging.WARNING,
                **_: Any) -> Executor:
    return LocalExecutor(workers, episode_fn, log_level)


def _make_ray(**kwargs: Any) -> Executor:
    return RayExecutor(**kwargs)


register_executor("local", _make_local)
register_executor("ray", _make_ray)
