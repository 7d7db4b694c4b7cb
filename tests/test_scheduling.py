"""How the suite shares the cores among its xdist workers (tests/scheduling.py): the order of the units, the
suite lock between worker processes, the numba warm-up that heavy tests wait for."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import threading

import numba

from tests.helpers import REPO, load_factor
from tests.scheduling import EXCLUSIVE, HEAVY, LIGHT, KernelWarmUp, SuiteLock, Unit, cost_of, kind_of, order_units

BLOCKED_S = 0.3  # a request still waiting after this long is taken to wait for the holder


def test_kinds_and_costs_follow_the_marks():
    assert kind_of({"exclusive", "integration"}) == EXCLUSIVE
    assert kind_of({"integration", "timeout"}) == kind_of({"container"}) == kind_of({"cluster"}) == HEAVY
    assert kind_of({"parametrize"}) == kind_of(set()) == LIGHT
    assert cost_of({"container", "integration"}) > cost_of({"cluster"}) > cost_of({"integration"}) > cost_of(set())


def test_exclusive_units_go_first_then_half_the_light_ones_then_the_heavy_costliest_first():
    light = [Unit(f"l{i}", LIGHT, 1.0) for i in range(6)]
    units = [light[0], Unit("h_small", HEAVY, 8), light[1], Unit("x", EXCLUSIVE, 16), light[2],
             Unit("h_big", HEAVY, 80), *light[3:], Unit("h_mid", HEAVY, 24)]
    assert [u.key for u in order_units(units)] == ["x", "l0", "l1", "l2", "h_big", "h_mid", "h_small", "l3", "l4",
                                                   "l5"]
    assert order_units([]) == []
    only_light = order_units(light)
    assert only_light == light


class Request(threading.Thread):
    """One worker asking for the suite lock (each its own descriptors, as separate processes have)."""

    def __init__(self, folder, kind: str) -> None:
        super().__init__(daemon=True)
        self.lock, self.kind, self.got = SuiteLock(folder), kind, threading.Event()
        self.start()

    def run(self) -> None:
        self.lock.acquire(self.kind)
        self.got.set()

    def granted(self, wait_s: float = 10.0) -> bool:
        return self.got.wait(wait_s)


def test_an_exclusive_test_has_at_most_one_light_test_beside_it_and_no_heavy_one(tmp_path):
    exclusive = Request(tmp_path, EXCLUSIVE)
    assert exclusive.granted()
    companion = Request(tmp_path, LIGHT)
    assert companion.granted()  # beside the exclusive test, at once
    second, heavy = Request(tmp_path, LIGHT), Request(tmp_path, HEAVY)
    assert not second.granted(BLOCKED_S) and not heavy.granted(BLOCKED_S)
    companion.lock.release()
    assert second.granted()
    assert not heavy.granted(BLOCKED_S)
    exclusive.lock.release()
    assert heavy.granted()
    second.lock.release()
    assert Request(tmp_path, LIGHT).granted()  # beside a heavy test, as a reader


def test_a_waiting_exclusive_test_holds_back_new_heavy_tests_but_not_light_ones(tmp_path):
    first = Request(tmp_path, HEAVY)
    assert first.granted()
    exclusive = Request(tmp_path, EXCLUSIVE)
    assert not exclusive.granted(BLOCKED_S)  # the running heavy test first
    later = Request(tmp_path, HEAVY)
    light = Request(tmp_path, LIGHT)
    assert light.granted()
    assert not later.granted(BLOCKED_S)  # queued behind the exclusive test: readers cannot starve it
    first.lock.release()
    assert exclusive.granted()
    assert not later.granted(BLOCKED_S)
    exclusive.lock.release()
    assert later.granted()


def test_consecutive_exclusive_tests_keep_the_lock_and_a_kind_change_releases_it(tmp_path):
    worker = SuiteLock(tmp_path)
    leave = worker.enter(EXCLUSIVE, EXCLUSIVE)
    leave()
    assert worker.held == EXCLUSIVE  # kept for the next exclusive test
    other = Request(tmp_path, HEAVY)
    assert not other.granted(BLOCKED_S)
    leave = worker.enter(EXCLUSIVE, HEAVY)
    leave()
    assert worker.held is None
    assert other.granted()


def test_heavy_tests_and_compilations_wait_for_the_warm_up(tmp_path, monkeypatch):
    from numba.core.dispatcher import Dispatcher

    monkeypatch.setattr(Dispatcher, "compile", Dispatcher.compile)  # put back after the test
    release = threading.Event()
    controller = KernelWarmUp()
    controller.start(tmp_path, lambda: "numba kernels: compiled" if release.wait(30) else "never released")
    worker = KernelWarmUp()
    worker.hold_compilations(tmp_path)

    @numba.njit
    def twice(x):
        return 2 * x

    done = {}
    waiting = threading.Thread(target=lambda: done.setdefault("wait", worker.wait(tmp_path)), daemon=True)
    compiling = threading.Thread(target=lambda: done.setdefault("compile", twice(21)), daemon=True)
    waiting.start()
    compiling.start()
    waiting.join(BLOCKED_S)
    compiling.join(BLOCKED_S)
    assert done == {}
    release.set()
    waiting.join(30)
    compiling.join(30)
    assert done == {"wait": None, "compile": 42}
    assert controller.join() == "numba kernels: compiled"


def test_a_failed_warm_up_says_so_and_frees_the_workers(tmp_path):
    def fail() -> str:
        raise OSError("no space left")

    controller = KernelWarmUp()
    controller.start(tmp_path, fail)
    assert controller.join() == "numba kernels: the warm-up failed (OSError: no space left)"
    KernelWarmUp().wait(tmp_path)  # returns: the lock is free


def test_without_a_warm_up_nothing_waits(tmp_path):
    worker = KernelWarmUp()
    worker.hold_compilations(tmp_path)  # no kernels.lock: nothing patched
    worker.wait(tmp_path)
    assert not (tmp_path / KernelWarmUp.FILE).exists()


def test_xdist_hands_out_the_units_in_this_order(tmp_path):
    """A small suite under xdist with tests/conftest.py's hooks, on one worker (which runs the units in the order
    it is handed them): its exclusive test comes first, where xdist's own order puts the biggest group first."""
    (tmp_path / "test_small.py").write_text(textwrap.dedent("""
        import pytest

        @pytest.mark.resource("thing")
        @pytest.mark.parametrize("k", [1, 2, 3])
        def test_grouped(k):
            assert k

        @pytest.mark.exclusive
        def test_deadline():
            assert True
    """))
    (tmp_path / "pytest.ini").write_text("[pytest]\nmarkers =\n    exclusive: deadline\n    resource(name): shared\n")
    env = {**os.environ, "PYTHONPATH": str(REPO), "COSIM_TEST_FAST": "1"}
    r = subprocess.run([sys.executable, "-m", "pytest", "-p", "tests.conftest", "-p", "no:cacheprovider", "-n", "1",
                        "--dist", "loadgroup", "-v", "test_small.py"], cwd=tmp_path, capture_output=True, text=True,
                       env=env, timeout=120 * load_factor())
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    ran = [line.split("::")[1].split("@")[0] for line in r.stdout.splitlines() if line.startswith("[gw0]")]
    assert ran == ["test_deadline", "test_grouped[1]", "test_grouped[2]", "test_grouped[3]"], r.stdout
