"""Batch generation: sweeps of episodes over conditions, run locally, on Ray or in shards, resumable.

``cosim batch SWEEP.yaml --out DIR`` = :func:`~cosim.batch.plan.plan_file` (deterministic episode list)
+ :func:`~cosim.batch.runner.run_batch` on an executor (:mod:`cosim.batch.executors`), recorded in an
append-only manifest (:mod:`cosim.batch.manifest`; read with
:mod:`cosim.io.manifest`). ``cosim report DIR`` = :mod:`cosim.batch.report`.
"""

from cosim.batch.plan import Episode, Plan, plan_file, plan_sweep
from cosim.batch.sweep import Sweep, SweepError, load_sweep

__all__ = ["Episode", "Plan", "Sweep", "SweepError", "load_sweep", "plan_file", "plan_sweep"]
