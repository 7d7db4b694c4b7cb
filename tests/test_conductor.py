"""The conductor's lockstep protocol and failure handling: real processes, real Zenoh, fake engines."""

from __future__ import annotations

import os
import signal
import time

import pytest

from cosim.conductor import Conductor
from cosim.errors import SyncTimeout, WorkerError
from cosim.protocol import EscortTarget
from tests.fakes import fake_worker_main
from tests.helpers import children_of, load_bound

TICK_NS = 200_000_000


def conductor(name: str = "fake", tick_timeout_s: float = 5.0) -> Conductor:
    return Conductor({"name": name}, {}, startup_timeout_s=30, tick_timeout_s=tick_timeout_s,
                     worker_target=fake_worker_main)


def test_lockstep_replies_for_every_tick_and_passes_escort_targets():
    with conductor() as c:
        c.start()
        for tick in range(20):
            targets = {"drone_0": EscortTarget((1.0, 2.0, 0.7), 0.0, (1.0, 0.0, 0.0))} if tick % 2 else {}
            replies = c.step(tick, tick * TICK_NS, targets)
            assert replies["traffic"]["tick"] == tick and replies["drones"]["tick"] == tick
            assert replies["traffic"]["vehicles"][0]["center_m"][0] == pytest.approx(10.0 * tick * 0.2)
            assert replies["drones"]["escorts_seen"] == (["drone_0"] if tick % 2 else [])


def test_two_conductors_on_one_host_do_not_cross():
    with conductor() as a, conductor() as b:
        a.start()
        b.start()
        assert a.prefix != b.prefix and a.endpoint != b.endpoint
        for tick in range(5):
            ra = a.step(tick, tick * TICK_NS, {})
            rb = b.step(tick * 2, tick * 2 * TICK_NS, {})
            assert ra["traffic"]["tick"] == tick and rb["traffic"]["tick"] == tick * 2


@pytest.mark.exclusive
@pytest.mark.parametrize("role", ["drones", "traffic"])
def test_sigkilled_worker_is_named_with_the_tick_within_3_s_and_nothing_is_left(role):
    me = os.getpid()
    with conductor() as c:
        c.start()
        for tick in range(5):
            c.step(tick, tick * TICK_NS, {})
        victim = c._procs[role]
        os.kill(victim.pid, signal.SIGKILL)
        t0 = time.monotonic()
        with pytest.raises(WorkerError) as err:
            for tick in range(5, 100):
                c.step(tick, tick * TICK_NS, {})
        assert time.monotonic() - t0 < load_bound(3.0)
        assert err.value.worker == role
        assert err.value.tick == 5
        assert f"{role} worker at tick 5" in str(err.value)
        assert "signal 9" in str(err.value) or "liveliness" in str(err.value)
    assert children_of(me) == []


@pytest.mark.exclusive
def test_hanging_worker_times_out_naming_worker_and_tick():
    me = os.getpid()
    with conductor("fake-hang-drones-3", tick_timeout_s=1.0) as c:
        c.start()
        for tick in range(3):
            c.step(tick, tick * TICK_NS, {})
        t0 = time.monotonic()
        with pytest.raises(SyncTimeout) as err:
            c.step(3, 3 * TICK_NS, {})
        assert 0.9 < time.monotonic() - t0 < load_bound(3.0)
        assert err.value.worker == "drones" and err.value.tick == 3
    assert children_of(me) == []


def test_worker_error_reply_carries_its_message():
    with conductor("fake-fail-traffic-2") as c:
        c.start()
        c.step(0, 0, {})
        c.step(1, TICK_NS, {})
        with pytest.raises(WorkerError, match=r"traffic worker at tick 2: injected failure at tick 2"):
            c.step(2, 2 * TICK_NS, {})


def test_worker_exiting_abruptly_reports_its_status():
    with conductor("fake-exit-drones-1") as c:
        c.start()
        c.step(0, 0, {})
        with pytest.raises(WorkerError, match=r"drones worker at tick 1: .*(exited with status 3|liveliness)"):
            c.step(1, TICK_NS, {})


@pytest.mark.exclusive
def test_replies_that_arrived_while_the_caller_was_busy_are_not_timeouts():
    """Pipelining: the conductor renders tick k for longer than the timeout while tick k+1's replies wait."""
    with conductor(tick_timeout_s=0.5) as c:
        c.start()
        c.step(0, 0, {})
        pending = c.send_step(1, TICK_NS, {})
        time.sleep(1.0)  # longer than the timeout: a slow sensor frame
        replies = c.collect(pending)
        assert replies["traffic"]["tick"] == 1 and replies["drones"]["tick"] == 1


# ------------------------------------------------------------------------------- waiting for external workers


@pytest.mark.integration  # a `cosim run` process that builds its world
def test_waiting_for_external_workers_is_a_notice_not_a_warning(tmp_path):
    import socket

    from tests.helpers import run_cli

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    r = run_cli("run", "default", "--no-sensors", "--duration", "1", "--set", "map.kind=rural", "--set",
                "map.size_m=300", "--set", "runtime.startup_timeout_s=1", "--external-workers", "--listen",
                f"tcp/127.0.0.1:{port}", "--out", str(tmp_path), timeout=120)
    assert r.returncode == 1 and "did not come up within 1 s" in r.stderr, r.stderr[-2000:]
    assert f"NOTICE cosim.conductor: waiting for external workers: cosim worker traffic|drones --connect " \
           f"tcp/127.0.0.1:{port}" in r.stderr
    assert "WARNING" not in r.stderr
