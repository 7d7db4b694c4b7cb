"""Run pytest on a simulated busy machine: BUSY processes spinning on the CPU beside it.

Developers' machines are not quiet CI runners; this is how to check that the suite still passes there
(tests assert behaviour, and their time limits and bounds scale with the measured load: tests/helpers.py
``load_bound``, tests/conftest.py ``_timeout_for_the_load``). ``make test-under-load`` runs the whole suite
this way; to try some files::

    .venv/bin/python -m tests.under_load --busy 2 -- -n 0 -q tests/test_faults.py tests/test_run.py

The busy loops start before pytest and are killed when it ends (also on Ctrl-C); the exit status is
pytest's. The load averages before and after are printed to stderr.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

SPIN = "while True: pass"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--busy", type=int, default=2, help="busy-loop processes beside pytest (default 2)")
    ap.add_argument("--warm-up", type=float, default=5.0, metavar="S",
                    help="seconds the loops spin before pytest starts, so the load average has risen (default 5)")
    ap.add_argument("pytest_args", nargs="*", help="arguments for pytest (after --)")
    args = ap.parse_args(argv)
    if args.busy < 0:
        ap.error(f"--busy must be >= 0, got {args.busy}")
    loops = [subprocess.Popen([sys.executable, "-c", SPIN]) for _ in range(args.busy)]
    try:
        time.sleep(args.warm_up)
        print(f"under_load: {args.busy} busy loops, load average {os.getloadavg()}, {os.cpu_count()} CPUs",
              file=sys.stderr, flush=True)
        status = subprocess.call([sys.executable, "-m", "pytest", *args.pytest_args])
    finally:
        for p in loops:
            p.kill()
        for p in loops:
            p.wait()
    print(f"under_load: load average at the end {os.getloadavg()}", file=sys.stderr)
    return status


if __name__ == "__main__":
    sys.exit(main())
