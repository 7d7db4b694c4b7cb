"""Ray executor: one Ray task per episode attempt, on a fresh worker process each (``max_calls=1``).

Ray's own task retries are off: the batch loop retries, so every attempt lands in the manifest. A
worker that dies (``WorkerCrashedError``, node lost) becomes a failed attempt like any other. At
most ``max_in_flight`` tasks are submitted at once so a thousand-episode sweep does not flood the
scheduler. The progress actor lives on the driver's node, and losing it costs only progress lines.
Episode files are written by the task itself to ``--out``, so on a multi-node cluster the output
folder must be a filesystem every node mounts at the same path.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from typing import Any

from cosim.batch.job import PROGRESS_INTERVAL_S, EpisodeFn, Event, Job, execute, run_real_episode
from cosim.errors import CosimError, InputError
from cosim.preflight import RAY_MISSING

log = logging.getLogger(__name__)

SINK_TIMEOUT_S = 30.0  # a progress poll waits at most this long for the progress actor
RAY_WORKER_NICENESS = "RAY_worker_niceness"  # Ray's setting of its workers' niceness (default 15)


class _ProgressSink:
    """A tiny actor the tasks report tick progress to; the driver drains it when it polls."""

    def __init__(self) -> None:
        self._items: list[tuple[str, int, int]] = []

    def put(self, episode_id: str, done: int, total: int) -> None:
        self._items.append((episode_id, done, total))

    def drain(self) -> list[tuple[str, int, int]]:
        out, self._items = self._items, []
        return out


def _task(job: Job, fn: EpisodeFn, sink: Any) -> dict[str, Any]:
    logging.basicConfig(level=logging.WARNING)
    last = [0.0]

    def progress(done: int, total: int) -> None:
        now = time.monotonic()
        if done >= total or now - last[0] >= PROGRESS_INTERVAL_S:
            last[0] = now
            sink.put.remote(job.episode_id, done, total)  # fire and forget

    import ray

    return {**execute(job, fn, progress), "node": ray.get_runtime_context().get_node_id()}


class RayExecutor:
    name = "ray"

    def __init__(self, *, address: str | None = None, workers: int | None = None,
                 episode_fn: EpisodeFn = run_real_episode, max_in_flight: int | None = None,
                 cpus_per_episode: float = 1.0, **_: Any):
        try:
            import ray
        except ImportError:
            raise InputError(RAY_MISSING) from None
        self._ray = ray
        self.episode_fn = episode_fn
        self._owns_ray = not ray.is_initialized()
        if self._owns_ray:
            if address in (None, "local"):
                # A private local cluster; workers import what the driver imports (sys.path), and run at the
                # driver's priority: Ray starts workers at niceness 15, where an episode beside any other
                # busy process gets a few per cent of a core (20 times slower on a loaded 2-core machine).
                env = {"PYTHONPATH": os.pathsep.join(p for p in sys.path if p), RAY_WORKER_NICENESS: "0"}
                ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False,
                         runtime_env={"env_vars": env})
            else:
                try:
                    ray.init(address=address, log_to_driver=False)
                except (ConnectionError, RuntimeError, ValueError) as exc:
                    raise CosimError(f"cannot connect to the Ray cluster at {address!r}: {exc}") from None
        cpus = int(ray.cluster_resources().get("CPU", 1))
        self.max_in_flight = max_in_flight or max(1, 2 * int(cpus / cpus_per_episode))
        self._remote = ray.remote(max_calls=1, max_retries=0, num_cpus=cpus_per_episode)(_task)
        self._fn_ref = ray.put(episode_fn)
        self._sink = self._new_sink()
        self._pending: dict[Any, tuple[Job, int]] = {}  # task ref -> (job, status slot)
        self.status_lines = min(self.max_in_flight, 8)

    def _new_sink(self) -> Any:
        """The progress actor, on the driver's own node: a worker node lost must not take it along."""
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        here = NodeAffinitySchedulingStrategy(self._ray.get_runtime_context().get_node_id(), soft=True)
        return self._ray.remote(num_cpus=0, scheduling_strategy=here)(_ProgressSink).remote()

    def _drain(self) -> list[tuple[str, int, int]]:
        """Progress reported since the last poll; lost progress (the actor gone) only costs the display."""
        try:
            return self._ray.get(self._sink.drain.remote(), timeout=SINK_TIMEOUT_S)
        except self._ray.exceptions.RayError as exc:
            log.warning("progress reports lost (%s); starting a new progress actor", type(exc).__name__)
            self._sink = self._new_sink()
            return []

    def has_capacity(self) -> bool:
        return len(self._pending) < self.max_in_flight

    def busy(self) -> bool:
        return bool(self._pending)

    @staticmethod
    def worker_name(slot: int) -> str:
        return f"task{slot}"

    def submit(self, job: Job) -> list[Event]:
        ref = self._remote.remote(job, self._fn_ref, self._sink)
        slot = min(set(range(self.max_in_flight)) - {s for _, s in self._pending.values()})
        self._pending[ref] = (job, slot)
        return [Event("started", job, self.worker_name(slot))]

    def poll(self, timeout_s: float) -> list[Event]:
        if not self._pending:
            return []
        ready, _ = self._ray.wait(list(self._pending), num_returns=len(self._pending), timeout=timeout_s)
        events = []
        running = {job.episode_id: (job, slot) for job, slot in self._pending.values()}
        for episode_id, done, total in self._drain():
            if episode_id in running:
                job, slot = running[episode_id]
                events.append(Event("progress", job, self.worker_name(slot), done=done, total=total))
        for ref in ready:
            job, slot = self._pending.pop(ref)
            try:
                outcome = self._ray.get(ref)
            except self._ray.exceptions.RayError as exc:  # worker crash, node loss, task error
                first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
                outcome = {"ok": False, "episode": job.episode_id, "error": f"{type(exc).__name__}: {first}"}
            events.append(Event("finished", job, self.worker_name(slot), outcome=outcome))
        return events

    def shutdown(self) -> None:
        for ref in list(self._pending):
            try:
                self._ray.cancel(ref, force=True)
            except Exception as exc:
                log.debug("cancel failed: %s", exc)
        self._pending.clear()
        if self._owns_ray:
            self._ray.shutdown()
