"""What a new user hit in round 4 (issue 37): progress without a terminal, the dry-run's output folder,
the report's size columns, and exports that say where their episodes went. Each test fails on the code
before the fix. Fast: synthetic episodes, in process; one tiny labels-only `cosim run`.
"""

from __future__ import annotations

import json
import logging
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from cosim.progress import progress_display, progress_line
from tests.helpers import REPO
from tests.helpers import cli_in_process as cli


@pytest.fixture(scope="module")
def episodes(tmp_path_factory) -> list[Path]:
    """Two small synthetic episodes with sensors (visibility included), of 2 and 3 ticks."""
    from cosim.io.synthetic import write_synthetic_episode

    d = tmp_path_factory.mktemp("round4")
    return [write_synthetic_episode(d / "a.mcap", ticks=2, sensors=True),
            write_synthetic_episode(d / "b.mcap", ticks=3, sensors=True)]


def batch_folder(root: Path, episodes: list[Path], splits: list[str], sweep: str = "my_sweep") -> Path:
    """A batch folder as `cosim batch` leaves it: the episodes under their splits and a manifest."""
    root.mkdir(parents=True)
    lines = []
    for i, (ep, split) in enumerate(zip(episodes, splits, strict=True)):
        rel = Path(split) / f"{sweep}-{i:04d}.mcap"
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_bytes(ep.read_bytes())
        lines.append(json.dumps({"episode": f"{sweep}-{i:04d}", "sweep": sweep, "split": split, "file": str(rel),
                                 "status": "done", "duration_s": 1.0}))
    (root / "manifest.jsonl").write_text("\n".join(lines) + "\n")
    return root


# ---------------------------------------------------------------------------------------------- progress


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


# ---------------------------------------------------------------------------------------------- dry run


def test_dry_run_prints_the_output_dir_that_will_be_used(tmp_path, capsys):
    out = tmp_path / "elsewhere"
    status, text, err = cli(capsys, "run", "default", "--dry-run", "--out", str(out))
    assert status == 0, err
    header, body = text.split("\n", 1)
    assert header.startswith(f"# {out}/")
    assert yaml.safe_load(body)["output"]["dir"] == str(out)
    status, text, err = cli(capsys, "run", "default", "--dry-run")
    assert status == 0 and yaml.safe_load(text.split("\n", 1)[1])["output"]["dir"] == "out"
    status, text, err = cli(capsys, "run", "default", "--dry-run", "--progress-every", "-1")
    assert status == 2 and err == "cosim: error: --progress-every must be >= 0 seconds, got -1\n"


# ---------------------------------------------------------------------------------------------- report


def test_report_gives_bytes_frames_and_visible_objects_per_split_and_condition(episodes, tmp_path):
    from cosim.batch.report import build_report
    from cosim.io.reader import open_episode

    root = batch_folder(tmp_path / "batch", episodes, ["train", "val"])
    report = build_report(root, md_path=tmp_path / "report.md", img_dir=tmp_path / "img")
    rows = report.stats["size_per_split_condition"]
    expected = {}
    for ep, split in zip(episodes, ["train", "val"], strict=True):
        with open_episode(ep) as e:
            md = e.metadata
            visible = 0
            for tick in e.ticks():
                seen: set[int] = set()
                for agent in e.agents:
                    if f"/{agent}/visibility" in tick:
                        seen.update(int(o["track_id"]) for o in tick[f"/{agent}/visibility"]["objects"])
                visible += len(seen)
            cond = f"{md['weather']}/{md['lighting']}/{md['environment']}"
            expected[f"{split} {cond}"] = {"split": split, "condition": cond, "episodes": 1,
                                           "bytes": ep.stat().st_size, "frames": len(e), "visible": visible,
                                           "visible_per_frame": visible / len(e)}
    assert rows == expected and all(r["visible"] > 0 for r in rows.values())
    text = report.md_path.read_text()
    assert "| split | condition (weather/lighting/environment) | episodes | bytes on disk | frames |" in text
    r = expected[next(iter(expected))]
    assert (f"| {r['split']} | {r['condition']} | 1 | {r['bytes']:,} | {r['frames']} | "
            f"{r['visible_per_frame']:.1f} |") in text


# ---------------------------------------------------------------------------------------------- exports


def test_export_of_a_sweep_without_splits_says_its_folder_is_not_read_and_names_the_sweep(episodes, tmp_path,
                                                                                          caplog, capsys):
    from cosim.exporters.export import run_export

    root = batch_folder(tmp_path / "batch", episodes[:1], ["all"], sweep="night_sweep")
    with caplog.at_level(logging.WARNING, logger="cosim.exporters.export"):
        result = run_export(root, "airv2x", tmp_path / "x")
    (seq,) = result.written
    assert seq.parent.name == "all"
    assert any("neither loader reads" in m and "--split" in m for m in caplog.messages), caplog.messages
    cond = json.loads((seq / "conditions.json").read_text())
    assert cond["scenario"] == cond["sweep"] == "night_sweep" and cond["episode"] == "night_sweep-0000"
    assert cond["base_scenario"] == "synthetic"
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="cosim.exporters.export"):
        status, out, err = cli(capsys, "export", str(root), "--format", "airv2x", "--out", str(tmp_path / "y"),
                               "--split", "train")
    assert status == 0 and (tmp_path / "y" / "train").is_dir() and "1 sequence(s) written" in out, err
    assert not any("neither loader" in m for m in caplog.messages)
    assert "export airv2x: agent-frame 6 of 6 (100 %), " in err, err  # stderr not a terminal: a plain line


# ---------------------------------------------------------------------------------------------- a busy machine


class _Item:
    """What :func:`tests.conftest._timeout_for_the_load` uses of a pytest item."""

    def __init__(self, marker=None, ini="300"):
        self.markers = [marker] if marker is not None else []
        self.config = type("Config", (), {"getoption": lambda self, name, default=None: None,
                                          "getini": lambda self, name: ini})()

    def get_closest_marker(self, name):
        return self.markers[0] if self.markers else None

    def add_marker(self, marker, append=True):
        self.markers.insert(0 if not append else len(self.markers), marker.mark)


def test_time_limits_scale_with_the_measured_load(monkeypatch):
    """At load 12 on 2 cores every test's limit (its marker's, else the ini's 300 s) is 6 times as long;
    on a quiet machine it stays as written."""
    import tests.conftest as conftest

    monkeypatch.setattr(conftest, "load_factor", lambda: 6.0)
    item = _Item()
    conftest._timeout_for_the_load(item)
    assert item.get_closest_marker("timeout").args == (1800,)
    item = _Item(pytest.mark.timeout(900, method="thread").mark)
    conftest._timeout_for_the_load(item)
    assert item.get_closest_marker("timeout").args == (5400,)
    assert item.get_closest_marker("timeout").kwargs == {"method": "thread"}
    monkeypatch.setattr(conftest, "load_factor", lambda: 1.0)
    item = _Item(pytest.mark.timeout(900).mark)
    conftest._timeout_for_the_load(item)
    assert item.get_closest_marker("timeout").args == (900,)


def test_load_bound_scales_a_deadline_by_load_over_cores(monkeypatch):
    import os

    from tests.helpers import load_bound

    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    monkeypatch.setattr(os, "getloadavg", lambda: (11.7, 8.0, 4.0))
    assert load_bound(3.0) == pytest.approx(3.0 * 11.7 / 2)  # the 5.9 s of the SIGKILL test passes
    monkeypatch.setattr(os, "getloadavg", lambda: (0.5, 1.0, 1.0))
    assert load_bound(3.0) == 3.0


# ---------------------------------------------------------------------------------------------- docs


def test_docs_pedestrian_sizes_are_the_labelled_boxes():
    """docs/events.md's pedestrian sizes are what ``people.posed_box`` labels (issue 37: it said every box was
    0.5 x 0.6 x 1.75 m while statures vary from child to tall adult)."""
    from benchmarks.docs_numbers import DOCS, blocks, pedestrian_boxes

    text = (DOCS / "events.md").read_text()
    [(start, end)] = [(s, e) for name, s, e in blocks(text) if name == "pedestrian_boxes"]
    assert text[start:end] == pedestrian_boxes()
    assert "0.5 x 0.6 x 1.75" not in text
