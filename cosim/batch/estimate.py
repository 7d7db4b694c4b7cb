"""``--dry-run`` estimates: run one short calibration episode and extrapolate to the plan.

Model per episode: wall = startup + per_tick * ticks, size = fixed + bytes_per_tick * ticks. Startup
and the per-tick cost come from the times of the calibration episode's first and last ticks (and the
CPU-seconds per tick, of the episode's whole process tree, from its CPU time at the same marks); the fixed
size is its attachments (scenario, road network, routes), which do not grow with the duration. The wall time of
the batch is the summed episode time divided by the workers (episodes are independent).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from cosim.batch.executors import LocalExecutor
from cosim.batch.job import EpisodeFn, Job, run_real_episode
from cosim.batch.plan import Plan
from cosim.batch.runner import n_ticks
from cosim.errors import CosimError

#: Frames (ticks) of the paper's dataset: 6.73 hours at 5 Hz.
PAPER_FRAMES = 121_000
#: Published costs of CARLA-based generation to print beside ours (docs: README, performance).
CARLA_ANCHORS = ("300-400 GPU-hours for a TransFuser-sized dataset (transfuser#251)",
                 "1-4 FPS reported by CARLA users", "4-8 GB of VRAM per CARLA instance")


@dataclass(frozen=True)
class Estimate:
    episode: str
    calibration_s: float  # simulated seconds of the calibration run
    startup_s: float
    per_tick_s: float
    bytes_per_tick: float
    fixed_bytes: float  # per episode, whatever its length (attachments)
    cpu_s: float  # summed episode wall time of the plan
    wall_s: float  # with the given workers
    bytes: float
    cpu_per_tick_s: float | None = None  # CPU-seconds per tick of the episode's process tree

    def dataset_cost(self, frames: int = PAPER_FRAMES) -> tuple[float | None, float]:
        """(CPU-hours, bytes) of ``frames`` ticks of this rig (the episodes' fixed bytes left out)."""
        cpu_h = None if self.cpu_per_tick_s is None else frames * self.cpu_per_tick_s / 3600.0
        return cpu_h, frames * self.bytes_per_tick


def calibrate(plan: Plan, tmp_dir: Path, *, seconds: float = 2.0, workers: int = 1,
              episode_fn: EpisodeFn = run_real_episode) -> Estimate:
    ep = plan.episodes[0]
    tick_hz = float(ep.scenario.get("tick_hz", 5.0))
    ticks = max(2, round(min(seconds, ep.duration_s) * tick_hz))
    scenario = {**ep.scenario, "duration_s": ticks / tick_hz}
    job = Job(episode_id=ep.id, file=ep.file, out_dir=str(tmp_dir), scenario=scenario, base_dir=ep.base_dir,
              n_ticks=ticks)
    ex = LocalExecutor(1, episode_fn)
    ex.submit(job)
    outcome = None
    try:
        while outcome is None:
            for ev in ex.poll(1.0):
                if ev.kind == "finished":
                    outcome = ev.outcome
    finally:
        ex.shutdown()
    if not outcome or not outcome.get("ok"):
        raise CosimError(f"calibration episode {ep.id} failed: {(outcome or {}).get('error')}")
    fixed = min(_attachment_bytes(job.path), outcome["size_bytes"])
    marks = outcome.get("tick_marks_s") or [outcome["wall_time_s"]]
    first, last = marks[0], outcome["wall_time_s"]
    per_tick = (marks[-1] - first) / (ticks - 1) if len(marks) > 1 else last / ticks
    startup = max(0.0, last - per_tick * ticks)
    bytes_per_tick = (outcome["size_bytes"] - fixed) / ticks
    cpu_marks = outcome.get("tick_cpu_marks_s") or []
    cpu_per_tick = (cpu_marks[-1] - cpu_marks[0]) / (ticks - 1) if len(cpu_marks) > 1 and ticks > 1 else None
    cpu = sum(startup + per_tick * n_ticks(e) for e in plan.episodes)
    total_bytes = sum(fixed + bytes_per_tick * n_ticks(e) for e in plan.episodes)
    return Estimate(episode=ep.id, calibration_s=ticks / tick_hz, startup_s=startup, per_tick_s=per_tick,
                    bytes_per_tick=bytes_per_tick, fixed_bytes=fixed, cpu_s=cpu, wall_s=cpu / max(1, workers),
                    bytes=total_bytes, cpu_per_tick_s=cpu_per_tick)


def _attachment_bytes(path: Path) -> int:
    """Bytes of the episode's attachments (0 when the file is not a readable MCAP)."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            return sum(len(a.data) for a in make_reader(f).iter_attachments())
    except (OSError, McapError, ValueError):
        return 0


__all__ = ["CARLA_ANCHORS", "PAPER_FRAMES", "Estimate", "calibrate"]
