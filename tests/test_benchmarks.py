"""Every script of benchmarks/ still runs (issue 50: benchmarks/comm.py had broken unseen), so none rots.

Each ``.py`` script imports and answers ``--help`` (in this process: cheap; a module that no longer imports,
or a parser that no longer builds, fails here), each shell script parses (``bash -n``), and the scripts that
can run on a tiny input do, as a user runs them (``python benchmarks/X.py ...`` in a fresh interpreter): the
episode readers on conftest.py's synthetic episode, the SUMO ones on a 300 m map for a second or two, the
full-rig measurements in their ``--smoke`` mode (a small map, small cameras, one frame). The numbers they
print mean nothing here; what is checked is that they ran to their last line. The rest (trainings, batches,
full-rig episodes, pictures for docs/img, KITTI folders) are too costly for the suite: their ``--help`` is
checked here and their core functions by the tests named in :data:`CORE_TESTED`.
"""

from __future__ import annotations

import os
import runpy
import subprocess
import sys

import numpy as np
import pytest

from tests.helpers import REPO, load_factor

BENCHMARKS = REPO / "benchmarks"
SCRIPTS = sorted(p.name for p in BENCHMARKS.glob("*.py"))
SHELL_SCRIPTS = sorted(p.name for p in BENCHMARKS.glob("*.sh"))
#: Modules without a command line: the inputs and measures other scripts and the tests import.
LIBRARIES = {"drone_demo.py", "drone_tracking.py"}
#: Scripts whose core the suite runs elsewhere (too costly to run whole here): the test file that does.
CORE_TESTED = {"drone_demo.py": "test_drones.py", "drone_report.py": "test_drones.py",
               "drone_survey.py": "test_drones.py", "drone_tracking.py": "test_run.py",
               "data_quality.py": "test_data_quality.py", "docs_numbers.py": "test_docs_numbers.py",
               "learn_ablation.py": "test_learn_ablation.py"}


def run_script(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """``python benchmarks/ARGS[0] ARGS[1:]`` from the repository root, as the scripts' docstrings run them."""
    return subprocess.run([sys.executable, *args], cwd=REPO, capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(REPO)}, timeout=timeout * load_factor())


def test_the_lists_name_scripts_that_exist():
    assert LIBRARIES | set(CORE_TESTED) <= set(SCRIPTS)
    assert all((REPO / "tests" / f).is_file() for f in CORE_TESTED.values())
    for name in LIBRARIES:
        assert "__main__" not in (BENCHMARKS / name).read_text(), f"{name} has a command line: test its --help"


@pytest.mark.parametrize("script", SCRIPTS)
def test_every_script_imports_and_answers_help(script, capsys, monkeypatch):
    path = BENCHMARKS / script
    if script in LIBRARIES:
        names = runpy.run_path(str(path), run_name=f"benchmarks_{path.stem}")
        assert any(callable(v) and getattr(v, "__module__", "") == f"benchmarks_{path.stem}" for v in names.values())
        return
    monkeypatch.setattr(sys, "argv", [str(path), "--help"])
    with pytest.raises(SystemExit) as done:
        runpy.run_path(str(path), run_name="__main__")
    out = capsys.readouterr().out
    assert done.value.code == 0 and out.startswith("usage: "), out[:500]


@pytest.mark.parametrize("script", SHELL_SCRIPTS)
def test_every_shell_script_parses(script):
    r = subprocess.run(["bash", "-n", str(BENCHMARKS / script)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


# ------------------------------------------------------------------------------------- the episode readers


@pytest.mark.parametrize("args, last", [
    (["render_speed.py", "{ep}", "--ticks", "0", "--out", "{tmp}/pictures"], "BEV plots timed again alone"),
    (["validate_speed.py", "{ep}", "--repeats", "1"], "ok"),
    (["replay_bytes.py", "{ep}"], "MB/s"),
    (["lidar_realism.py", "--episode", "{ep}"], "intensity histogram"),
])
def test_the_episode_readers_run_on_a_small_episode(synthetic_episode, tmp_path, args, last):
    argv = [a.format(ep=synthetic_episode, tmp=tmp_path) for a in args]
    r = run_script(str(BENCHMARKS / argv[0]), *argv[1:])
    assert r.returncode == 0, r.stderr[-3000:]
    assert last in r.stdout.strip().splitlines()[-1], r.stdout[-2000:]


@pytest.mark.integration  # `cosim export` processes
def test_the_export_benchmark_runs_on_a_small_episode(synthetic_episode):
    r = run_script(str(BENCHMARKS / "export.py"), "--episode", str(synthetic_episode))
    assert r.returncode == 0, r.stderr[-3000:]
    rows = [line.split()[0] for line in r.stdout.splitlines() if line.split()[:1] in (["airv2x"], ["opv2v"])]
    assert set(rows) >= {"airv2x", "opv2v"}, r.stdout[-2000:]


def test_the_device_probe_runs_on_a_tiny_tick(tmp_path):
    """Two triangles seen by a 24 x 16 camera; the CPU's triangle ids from Open3D, as ray_backends.py --export
    writes them: the probe's brute-force torch caster (CPU here) must find the same ones."""
    import open3d as o3d

    from benchmarks.device_probe import camera_rays

    vertices = np.array([[-3, -2, 0], [3, -2, 0], [0, 2, 0.5], [-4, 1, 1], [-1, 3, 1], [-4, 3, 1.5]], np.float32)
    triangles = np.array([[0, 1, 2], [3, 4, 5]], np.uint32)
    K = np.array([[12.0, 0, 12.0], [0, 12.0, 8.0], [0, 0, 1]])
    tick = {"vertices": vertices, "triangles": triangles, "rays": np.zeros(0), "cam_K": K,
            "cam_rotation": np.diag([1.0, -1.0, -1.0]), "cam_position": np.array([0.0, 0.0, 6.0]),
            "cam_size": np.array([24, 16]), "near_m": np.float64(0.1)}
    origins, dirs = camera_rays(tick)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices), o3d.core.Tensor(triangles))
    hit = scene.cast_rays(o3d.core.Tensor(np.hstack([origins, dirs]).astype(np.float32)))
    prim = hit["primitive_ids"].numpy().astype(np.int64)
    prim[prim == o3d.t.geometry.RaycastingScene.INVALID_ID] = -1
    assert 0 < np.sum(prim >= 0) < prim.size and set(prim[prim >= 0]) == {0, 1}  # both seen, some misses
    np.savez_compressed(tmp_path / "tick.npz", cpu_prim=prim.reshape(16, 24).astype(np.int32), **tick)
    r = run_script(str(BENCHMARKS / "device_probe.py"), str(tmp_path / "tick.npz"), "--repeats", "1",
                   "--subsample", "1", "--budget-s", "60")
    assert r.returncode == 0, r.stderr[-3000:]
    result = r.stdout.strip().splitlines()[-1]
    assert result.startswith("RESULT best torch") and "agree with the CPU on 100.000 % of 384 pixels" in result, \
        r.stdout[-2000:]


def test_the_posed_people_comparison_runs_and_agrees():
    r = run_script(str(BENCHMARKS / "posed_people.py"), "--people", "2", "--phases", "2")
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.strip().endswith("same vertices and faces: True"), r.stdout[-2000:]


# --------------------------------------------------------------------------------- SUMO and the built world


@pytest.mark.integration  # SUMO (netgenerate, libsumo)
def test_the_traffic_scripts_run_on_a_small_map(tmp_path):
    r = run_script(str(BENCHMARKS / "traffic_acceptance.py"), "--kinds", "rural", "--duration", "2", "--size", "300")
    assert r.returncode == 0, r.stderr[-3000:]
    assert '"kind": "rural"' in r.stdout and '"on_road"' in r.stdout, r.stdout[-2000:]
    r = run_script(str(BENCHMARKS / "pedestrian_boxes.py"), "scenarios/town_urban_day_clear.yaml", "1")
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.strip().splitlines()[-1].startswith("new: ticks 5, pedestrian states"), r.stdout[-2000:]
    r = run_script(str(BENCHMARKS / "world_plot.py"), str(tmp_path / "w.png"), "--kind", "rural", "--size", "300",
                   "--t", "1")
    assert r.returncode == 0, r.stderr[-3000:]
    assert (tmp_path / "w.png").stat().st_size > 1000


@pytest.mark.integration  # the default world (netgenerate) and the full rig, small
@pytest.mark.parametrize("args, last", [
    (["comm.py", "--smoke"], "link model / frame time: "),
    (["sensors.py", "--smoke", "--no-pybullet"], "RESULT CPU per frame "),
])
def test_the_full_rig_measurements_run_in_their_smoke_mode(args, last):
    r = run_script(str(BENCHMARKS / args[0]), *args[1:])
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.strip().splitlines()[-1].startswith(last), r.stdout[-2000:]


def test_a_smoke_mode_is_documented_where_a_script_has_one():
    for path in BENCHMARKS.glob("*.py"):
        text = path.read_text()
        if '"--smoke"' in text:
            assert f"{path.name} --smoke" in text.split('"""', 2)[1], f"{path.name}: say --smoke in the docstring"
