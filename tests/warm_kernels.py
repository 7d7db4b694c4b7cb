"""Compile the suite's numba kernels once (``tests/conftest.py`` calls :func:`warm_kernels` in the controlling
process, in the background while the xdist workers start and run light tests: tests/scheduling.py).

Every kernel is ``numba.njit(cache=True)``: compiled at its first call and kept in the ``__pycache__`` folder
beside its source, keyed by the source's modification time. A fresh clone (CI's every run) has no cache,
so the first episodes of the suite's workers each compiled the same kernels at once, about 20 CPU-s per
process (``python -m tests.warm_kernels`` prints what it costs here). One tiny full-rig episode, its
validation (instance pixels) and its AirV2X export (depth images) call every kernel with the types the
product uses, and leave the cache for every later process.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

from tests.helpers import REPO, run_cli

#: Kernels whose cache shows the others are warm too (each module's compiled last in the warm-up episode).
_PROBES = (
    ("sensors/surface.py", "surface.shade_linear-"),
    ("sensors/ray_embree.py", "ray_embree._closest-"),
    ("sensors/kernels.py", "kernels.depth_codes-"),
    ("exporters/kernels.py", "kernels.depth_rgb24_up_rows-"),
    ("cosim/pixel_kernels.py", "pixel_kernels._extents-"),
)


def kernels_cached() -> bool:
    """Whether each probe kernel has a cache index newer than its source."""
    for source, stem in _PROBES:
        src = REPO / source
        index = sorted((src.parent / "__pycache__").glob(f"{stem}*.nbi"))
        if not index or index[-1].stat().st_mtime < src.stat().st_mtime:
            return False
    return True


def warm_kernels() -> str:
    """Fill the kernel cache unless it is warm; returns one line saying what was done (the suite prints it in
    its summary). A failure here is not the suite's to report: the tests that need the kernels say it themselves."""
    if kernels_cached():
        return "numba kernels: cached"
    start = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="cosim-warm-") as tmp:
        episode = Path(tmp) / "default_s0.mcap"
        run = run_cli("run", "scenarios/default.yaml", "--duration", "0.4", "--set", "map.size_m=300",
                      "--set", "sensors.image_scale=0.05", "--out", tmp, "-q", timeout=900)
        if run.returncode != 0 or not episode.exists():
            return f"numba kernels: the warm-up episode failed ({run.stderr.strip()[-300:]})"
        export = subprocess.Popen([sys.executable, "-m", "cosim.cli", "export", str(episode), "--format", "airv2x",
                                   "--out", str(Path(tmp) / "airv2x"), "-q"], cwd=REPO, stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL)
        run_cli("validate", str(episode))
        export.wait(timeout=900)
    return f"numba kernels: compiled in {time.monotonic() - start:.0f} s (cache was cold)"


if __name__ == "__main__":
    print(warm_kernels())
