"""How fast `cosim run` stops when a worker is killed (SIGKILL) or hangs (SIGSTOP) while sensors render.

Runs the full paper rig (scenarios/default.yaml) once per worker and signal, waits until the episode's
first ticks are written (so the fault lands while a frame renders), sends the signal to the worker and
prints the seconds from the signal to the exit of `cosim run`, its status, its message, and whether any
worker process outlived it, against the reliability issue's deadlines (exit within 3 s of a worker's
SIGKILL, 12 s of its SIGSTOP; no worker left): the tests (tests/test_faults.py, tests/test_run.py) hold
these deadlines scaled by the machine's load, this benchmark holds them as they are, and exits 1 when a run
misses one. Run it on a quiet machine. Usage (from the repository root):

    python benchmarks/fault_exit_times.py [--repeat N] [--scale 1.0] [--signals KILL STOP] [--roles traffic drones]
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import psutil

REPO = Path(__file__).resolve().parents[1]
WORKER_NAMES = ("cosim-traffic", "cosim-drones")
#: [s] from the signal to the exit of `cosim run`, per signal (the reliability issue's deadlines)
DEADLINES_S = {"SIGKILL": 3.0, "SIGSTOP": 12.0}


def workers_of(pid: int) -> dict[str, psutil.Process]:
    out = {}
    try:
        for p in psutil.Process(pid).children(recursive=True):
            try:
                if p.name() in WORKER_NAMES:
                    out[p.name()] = p
            except psutil.Error:
                continue
    except psutil.Error:
        pass
    return out


def rendering_started(out: Path, name: str) -> bool:
    """True once the episode's temporary file holds more than its header (the first tick is written)."""
    part = out / f".{name}.mcap.partial"
    return part.exists() and part.stat().st_size > 1_000_000


def fault_once(role: str, sig: signal.Signals, scale: float, timeout_s: float = 600) -> dict:
    with tempfile.TemporaryDirectory(prefix="cosim-fault-") as tmp:
        out = Path(tmp)
        cmd = [sys.executable, "-m", "cosim.cli", "run", "scenarios/default.yaml", "--duration", "60", "--out",
               str(out), "-q", "--set", f"sensors.image_scale={scale}"]
        err_path = out.parent / f"{out.name}.stderr"
        err_file = open(err_path, "w+")  # noqa: SIM115 (a file, not a pipe: the exit is timed, not EOF)
        proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=err_file, text=True)
        try:
            deadline = time.monotonic() + timeout_s
            workers: dict[str, psutil.Process] = {}
            while time.monotonic() < deadline and proc.poll() is None:
                workers.update(workers_of(proc.pid))
                if len(workers) == 2 and rendering_started(out, "default_s0"):
                    break
                time.sleep(0.05)
            else:
                raise RuntimeError(f"episode did not start (status {proc.poll()})")
            time.sleep(0.5)  # well inside the next frame's rendering
            victim = workers[f"cosim-{role}"]
            os.kill(victim.pid, sig)
            t0 = time.monotonic()
            proc.wait(timeout=120)
            elapsed = time.monotonic() - t0
            err_file.seek(0)
            err = err_file.read()
            time.sleep(0.5)
            survivors = [p.pid for p in workers.values() if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
            left = sorted(f.name for f in out.iterdir())
        finally:
            if proc.poll() is None:
                proc.kill()
            for p in workers_of(proc.pid).values():
                p.kill()
            err_file.close()
            err_path.unlink(missing_ok=True)
    return {"role": role, "signal": sig.name, "exit_s": elapsed, "status": proc.returncode,
            "message": err.strip().splitlines()[-1] if err.strip() else "", "survivors": survivors, "files": left}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--scale", type=float, default=1.0, help="sensors.image_scale (1.0 = the full rig)")
    ap.add_argument("--signals", nargs="+", default=["KILL", "STOP"])
    ap.add_argument("--roles", nargs="+", default=["traffic", "drones"])
    args = ap.parse_args()
    print(f"load average {os.getloadavg()}, {os.cpu_count()} CPUs")
    missed = 0
    for _ in range(args.repeat):
        for name in args.signals:
            for role in args.roles:
                r = fault_once(role, signal.Signals[f"SIG{name}"], args.scale)
                deadline = DEADLINES_S.get(r["signal"])
                ok = (deadline is None or r["exit_s"] <= deadline) and not r["survivors"] and not r["files"]
                missed += not ok
                print(f"SIG{name:<4} {role:<8} exit {r['exit_s']:5.2f} s (deadline {deadline} s: "
                      f"{'ok' if ok else 'MISSED'})  status {r['status']}  "
                      f"survivors {r['survivors']}  files {r['files']}  | {r['message']}", flush=True)
    print(f"load average {os.getloadavg()}")
    if missed:
        sys.exit(1)


if __name__ == "__main__":
    main()
