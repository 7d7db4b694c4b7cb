"""Ray executor: one Ray task per episode attempt, on a fresh worker process each (``max_calls=1``).

Ray's own task retries are off: the batch loop retries, so every attempt lands in the manifest. A
worker that dies (``WorkerCrashedError``, node lost) becomes a failed attempt like any other. At most
``max_in_flight`` tasks are submitted at once so a thousand-episode sweep does not flood the
scheduler. Episode files are written by the task itself to ``--out``, so on a multi-node cluster the
output folder must be a filesystem every node mounts at the same path.
"""

from __future__ import annotations

import logging
import os
import sys
from typing import Any

from cosim.batch.executors import Event
from cosim.batch.job import EpisodeFn, Job, execute, run_real_episode
from cosim.errors import CosimError, InputError

log = logging.getLogger(__name__)


def _task(job: Job, fn: EpisodeFn) -> dict[str, Any]:
    logging.basicConfig(level=logging.WARNING)
    return execute(job, fn, lambda done, total: None)


class RayExecutor:
    name = "ray"

    def __init__(self, *, address: str | None = None, workers: int | None = None,
                 episode_fn: EpisodeFn = run_real_episode, max_in_flight: int | None = None,
                 cpus_per_episode: float = 1.0, **_: Any):
        try:
            import ray
        except ImportError:
            raise InputError("--backend ray needs Ray: pip install 'cosim[ray]' (or pip install 'ray>=2.9')") from None
        self._ray = ray
        self.episode_fn = episode_fn
        self._owns_ray = not ray.is_initialized()
        if self._owns_ray:
            if address in (None, "local"):
                # A private local cluster; workers import what the driver imports (sys.path).
                env = {"PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
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
        self._pending: dict[Any, Job] = {}

    def has_capacity(self) -> bool:
        return len(self._pending) < self.max_in_flight

    def busy(self) -> bool:
        return bool(self._pending)

    def submit(self, job: Job) -> list[Event]:
        ref = self._remote.remote(job, self._fn_ref)
        self._pending[ref] = job
        return [Event("started", job, "ray")]

    def poll(self, timeout_s: float) -> list[Event]:
        if not self._pending:
            return []
        ready, _ = self._ray.wait(list(self._pending), num_returns=len(self._pending), timeout=timeout_s)
        events = []
        for ref in ready:
            job = self._pending.pop(ref)
            try:
                outcome = self._ray.get(ref)
            except self._ray.exceptions.RayError as exc:  # worker crash, node loss, task error
                first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
                outcome = {"ok": False, "episode": job.episode_id, "error": f"{type(exc).__name__}: {first}"}
            events.append(Event("finished", job, f"ray:{outcome.get('host', '?')}", outcome=outcome))
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
