"""What an executor runs: one :class:`Job` (one attempt at one episode) through an episode function.

An episode function has the signature ``fn(job, progress) -> dict`` and must write exactly the file
``job.out_dir / job.file`` (atomically: complete or absent). The default, :func:`run_real_episode`,
runs the real pipeline; tests inject fakes. Functions are passed to worker processes by reference,
so they must be importable module-level functions.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import re
import socket
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from cosim.errors import CosimError, InputError
from cosim.io.manifest import sha256_file

Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class Job:
    """One attempt at one episode; plain data so it pickles to any worker (process or Ray node)."""

    episode_id: str
    file: str  # relative to out_dir
    out_dir: str
    scenario: dict[str, Any]  # resolved scenario data (validated again in the worker)
    base_dir: str  # folder that relative paths in the scenario resolve against
    attempt: int = 1  # 1-based, within this run of the batch
    n_ticks: int = 1

    @property
    def path(self) -> Path:
        return Path(self.out_dir) / self.file


EpisodeFn = Callable[[Job, Progress], dict[str, Any]]


PROGRESS_INTERVAL_S = 0.25  # a worker reports tick progress at most this often


@dataclass(frozen=True)
class Event:
    """What an executor reports about a job. ``kind``: started | progress | finished. ``outcome`` (finished)
    as :func:`execute`."""

    kind: str
    job: Job
    worker: str
    done: int = 0
    total: int = 0
    outcome: dict[str, Any] | None = None


class Executor(Protocol):
    """Where jobs run (:mod:`cosim.batch.executors`: local processes, Ray): every backend speaks
    :class:`Event`."""

    name: str

    def has_capacity(self) -> bool: ...

    def busy(self) -> bool: ...

    def submit(self, job: Job) -> list[Event]: ...

    def poll(self, timeout_s: float) -> list[Event]: ...

    def shutdown(self) -> None: ...


def run_real_episode(job: Job, progress: Progress) -> dict[str, Any]:
    """The production episode function: the full pipeline through :func:`cosim.runner.run_episode`."""
    from cosim.runner import run_episode
    from cosim.scenario.loader import load_scenario_data

    loaded = dataclasses.replace(load_scenario_data(job.scenario), base_dir=Path(job.base_dir))
    result = run_episode(loaded, job.path.parent, progress=progress)
    if result.path.resolve() != job.path.resolve():
        raise CosimError(f"episode {job.episode_id} was written to {result.path}, expected {job.path}")
    return {"ticks": result.ticks, "sim_time_s": result.sim_time_s, "actors": result.actors,
            "messages": result.messages}


_CONTAINER_ID = re.compile(r"(?:docker|containers|libpod|containerd|cri-containerd)[-/:]([0-9a-f]{64})")


@functools.cache
def container_id() -> str | None:
    """The id of the Docker (or Podman, containerd) container this process runs in, else None.

    Read from ``/proc/self/cgroup`` (cgroup v1: ``.../docker/<id>``) or, under cgroup v2 where that
    file says only ``0::/``, from ``/proc/self/mountinfo`` (``/var/lib/docker/containers/<id>/hostname``).
    """
    for name in ("/proc/self/cgroup", "/proc/self/mountinfo"):
        try:
            with open(name, encoding="utf-8", errors="replace") as f:
                found = container_id_in(f.read())
        except OSError:
            continue
        if found:
            return found
    return None


def container_id_in(text: str) -> str | None:
    """The first container id named in a ``/proc/<pid>/cgroup`` or ``mountinfo`` text, else None."""
    found = _CONTAINER_ID.search(text)
    return found.group(1) if found else None


def placement() -> dict[str, Any]:
    """Where this process runs: ``host`` name and ``container`` id (None outside a container)."""
    return {"host": socket.gethostname(), "container": container_id()}


def tree_cpu_s() -> float:
    """CPU seconds (user + system) used so far by this process and its live descendants (simulation workers,
    render processes)."""
    import psutil

    me = psutil.Process()
    total = sum(me.cpu_times()[:2])
    for child in me.children(recursive=True):
        try:
            total += sum(child.cpu_times()[:2])
        except psutil.Error:  # ended meanwhile
            continue
    return total


def versions() -> dict[str, str]:
    import cosim
    from cosim.runner import dependency_versions

    return {"cosim": cosim.__version__, **dependency_versions()}


def execute(job: Job, fn: EpisodeFn, progress: Progress) -> dict[str, Any]:
    """Run one attempt and describe it: ``ok``, ``wall_time_s``, ``size_bytes``, ``sha256`` or ``error``.

    Never raises for an episode failure (the message goes into the outcome); a process crash is
    detected by the executor instead. Bad input found at run time (an :class:`InputError`, e.g. a
    missing map file) is marked ``retryable: False``: running it again cannot help.
    """
    started = time.perf_counter()
    ticks_at: list[float] = []
    cpu_at: list[float] = []

    def on_progress(done: int, total: int) -> None:
        if len(ticks_at) < 2 or done >= total:
            ticks_at.append(time.perf_counter() - started)
            cpu_at.append(tree_cpu_s())
        progress(done, total)

    outcome: dict[str, Any] = {"episode": job.episode_id, **placement(), "pid": os.getpid()}
    try:
        info = fn(job, on_progress)
        path = job.path
        if not path.is_file():
            raise CosimError(f"episode {job.episode_id} finished without writing {path}")
        outcome.update(ok=True, info=info, size_bytes=path.stat().st_size, sha256=sha256_file(path))
    except Exception as exc:  # any failure of one episode is recorded; the batch goes on
        outcome.update(ok=False, error=f"{type(exc).__name__}: {exc}", traceback=traceback.format_exc(limit=8),
                       retryable=not isinstance(exc, InputError))
    outcome["wall_time_s"] = round(time.perf_counter() - started, 3)
    outcome["first_tick_s"] = ticks_at[0] if ticks_at else None
    outcome["tick_marks_s"] = ticks_at
    outcome["tick_cpu_marks_s"] = cpu_at
    try:
        outcome["versions"] = versions()
    except Exception as exc:
        outcome["versions"] = {"error": str(exc)}
    return outcome
