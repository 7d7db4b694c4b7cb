"""Progress of `cosim run` and `cosim export` (cosim/progress.py): a plain line every N seconds where stderr is
not a terminal, with tick k of n, seconds per tick and the ETA.
"""

from __future__ import annotations

import subprocess
import sys

import pytest

from cosim.progress import progress_display, progress_line
from tests.helpers import REPO

# -------------------------------------------------------------------------------- progress without a terminal


def test_progress_without_a_terminal_is_a_plain_line_every_n_seconds(tmp_path):
    """stderr a file: no tqdm bar (which stays silent there), a line at most every ``every_s`` seconds of
    wall time and one at the end, with tick k of n, seconds per tick and the ETA."""
    now = [100.0]
    with open(tmp_path / "err.txt", "w") as f:
        update, close = progress_display("ep", every_s=10.0, stream=f, clock=lambda: now[0])
        for k in range(1, 201):
            now[0] += 0.5  # 0.5 s per tick: a line every 20 ticks
            update(k, 200)
        close()
    lines = (tmp_path / "err.txt").read_text().splitlines()
    assert len(lines) == 10, lines
    assert lines[0] == "ep: tick 20 of 200 (10 %), 0.5 s/tick, ETA 1 min 30 s"
    assert lines[-1] == "ep: tick 200 of 200 (100 %), 0.5 s/tick, done"
    assert progress_line("ep", 3, 7200, 2.0) == "ep: tick 3 of 7200 (0 %), 2 s/tick, ETA 3 h 59 min"


@pytest.mark.integration  # a labels-only `cosim run` (SUMO), stderr to a file
def test_cosim_run_with_stderr_to_a_file_prints_progress_lines_and_wall_per_simulated_second(tmp_path):
    err = tmp_path / "stderr.txt"
    with open(err, "w") as f:
        r = subprocess.run([sys.executable, "-m", "cosim.cli", "run", "default", "--no-sensors", "--duration", "0.4",
                            "--out", str(tmp_path), "--progress-every", "0"], cwd=REPO, stdout=subprocess.PIPE,
                           stderr=f, text=True, timeout=600)
    text = err.read_text()
    assert r.returncode == 0, text[-3000:]
    assert "default: tick 1 of 2 (50 %)" in text and "default: tick 2 of 2 (100 %), " in text, text
    assert " s/tick, done" in text
    wall = next(line for line in r.stdout.splitlines() if line.startswith("wall"))
    assert " s per simulated second (real-time factor " in wall and "0.00x" not in wall, wall
