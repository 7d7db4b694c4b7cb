"""How ``make test`` shares the machine's cores among its pytest-xdist workers (tests/conftest.py calls these
from pytest's hooks).

Every test is one of three kinds (:func:`kind_of`):

- **exclusive** (marked ``exclusive``: a deadline in seconds): no heavy test runs beside it, and at most one
  light one;
- **heavy** (marked ``integration``, ``container`` or ``cluster``: real engines and processes);
- **light** (the rest, the fast lane's unit tests): beside anything, one at a time beside an exclusive test.

:class:`SuiteLock` enforces that with ``flock`` files in the run's folder. :func:`order_units` orders the
units xdist hands out (a group of tests that share a fixture, or one test) so that no core idles while an
exclusive test runs: exclusive tests first, while the other workers run light tests; then the heavy units,
the costliest first (so none starts near the end); then the rest of the light tests, which fill the tail.
:class:`KernelWarmUp` compiles the numba kernels once in the controlling process while the workers start and
run light tests; heavy and exclusive tests, and any light test about to compile a kernel, wait for it.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

EXCLUSIVE, HEAVY, LIGHT = "exclusive", "heavy", "light"
HEAVY_MARKS = frozenset({"integration", "container", "cluster"})
#: rough seconds per test of each kind on the 2-core machine (the suite's durations: a container test about 80 s,
#: the image's build included, a Ray-cluster test about 40, an integration test about 8, a unit test half a
#: second); only their ratios matter: the image's tests are the longest chain on one worker, so they go first
COST_S = {"container": 80.0, "cluster": 40.0, "integration": 8.0, LIGHT: 0.5}


def kind_of(marks: set[str]) -> str:
    """The kind of a test with these marker names."""
    if "exclusive" in marks:
        return EXCLUSIVE
    return HEAVY if marks & HEAVY_MARKS else LIGHT


def cost_of(marks: set[str]) -> float:
    """The rough cost of a test with these marker names (:data:`COST_S`)."""
    for mark in ("container", "cluster"):
        if mark in marks:
            return COST_S[mark]
    return COST_S["integration"] if marks & HEAVY_MARKS or "exclusive" in marks else COST_S[LIGHT]


@dataclass(frozen=True)
class Unit:
    """What xdist hands one worker at a time: the tests of one ``xdist_group``, or one test."""

    key: str
    kind: str  # exclusive if any test of it is, else heavy if any is, else light
    cost: float


def order_units(units: Sequence[Unit]) -> list[Unit]:
    """Exclusive units, the first half of the light ones (by cost), the heavy ones costliest first, then the
    other light ones; each part in its given order otherwise (the sorts are stable)."""
    exclusive = [u for u in units if u.kind == EXCLUSIVE]
    heavy = sorted((u for u in units if u.kind == HEAVY), key=lambda u: -u.cost)
    light = [u for u in units if u.kind == LIGHT]
    half, front, acc = sum(u.cost for u in light) / 2, 0, 0.0
    while front < len(light) and acc < half:
        acc += light[front].cost
        front += 1
    return [*exclusive, *light[:front], *heavy, *light[front:]]


def _flock(fd: int, op: int) -> bool:
    """``flock``; False where a non-blocking request (``op`` with LOCK_NB) would have had to wait."""
    try:
        fcntl.flock(fd, op)
    except BlockingIOError:
        return False
    return True


class SuiteLock:
    """A readers-writer lock shared by the run's workers, plus one companion slot (``flock`` files in ``folder``).

    Heavy tests hold ``suite.lock`` shared, exclusive tests alone. A writer waits at ``suite.turnstile`` first,
    holding it, so readers cannot keep it waiting forever. A light test takes ``suite.lock`` shared when it can
    at once (no writer holds it or waits for it), else the companion slot ``suite.companion``: at most one light
    test runs beside an exclusive one. Consecutive exclusive tests of one worker keep the lock (no re-queueing)."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.held: str | None = None  # None, or the kind it is held for
        self.fds: list[int] = []

    def _open(self, name: str) -> int:
        return os.open(self.folder / name, os.O_CREAT | os.O_RDWR, 0o600)

    def acquire(self, kind: str) -> None:
        assert self.held is None, self.held
        lock, turnstile = self._open("suite.lock"), self._open("suite.turnstile")
        try:
            if kind == EXCLUSIVE:
                _flock(turnstile, fcntl.LOCK_EX)
                _flock(lock, fcntl.LOCK_EX)
            elif kind == HEAVY:
                _flock(turnstile, fcntl.LOCK_EX)
                _flock(turnstile, fcntl.LOCK_UN)
                _flock(lock, fcntl.LOCK_SH)
            else:
                at_once = _flock(turnstile, fcntl.LOCK_EX | fcntl.LOCK_NB)
                reader = at_once and _flock(lock, fcntl.LOCK_SH | fcntl.LOCK_NB)
                if not reader:
                    os.close(lock)
                    lock = self._open("suite.companion")
                    _flock(lock, fcntl.LOCK_EX)
        finally:
            os.close(turnstile)  # the last descriptor of its file: its flock goes with it
        self.fds, self.held = [lock], kind

    def release(self) -> None:
        for fd in self.fds:  # unlock before closing: a child forked during the test may share the descriptor
            fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)
        self.fds, self.held = [], None

    def enter(self, kind: str, next_kind: str | None) -> Callable[[], None]:
        """Hold the lock for a test of ``kind``; returns what to call after it (``next_kind``: the worker's next
        test's, None at its last: an exclusive test followed by another keeps the lock)."""
        if self.held is not None and self.held != kind:
            self.release()
        if self.held is None:
            self.acquire(kind)

        def leave() -> None:
            if not (kind == EXCLUSIVE and next_kind == EXCLUSIVE):
                self.release()

        return leave


class KernelWarmUp:
    """The numba kernels compiled once, in the controlling process, while the workers start and run light tests.

    The controller holds ``kernels.lock`` in the run's folder while it compiles; :meth:`wait` (in a worker)
    returns once it is free, or at once where there is no such file (the cache was warm, or no controller)."""

    FILE = "kernels.lock"

    def __init__(self) -> None:
        self.line = ""
        self._thread: threading.Thread | None = None
        self._done = False

    def start(self, folder: Path, warm: Callable[[], str]) -> None:
        """Lock, then compile in a thread (``warm`` returns the line the summary prints) and unlock."""
        fd = os.open(folder / self.FILE, os.O_CREAT | os.O_RDWR, 0o600)
        fcntl.flock(fd, fcntl.LOCK_EX)

        def run() -> None:
            try:
                self.line = warm()
            except Exception as e:  # the tests that need the kernels compile them and say what fails
                self.line = f"numba kernels: the warm-up failed ({type(e).__name__}: {e})"
            finally:
                fcntl.flock(fd, fcntl.LOCK_UN)
                os.close(fd)

        self._thread = threading.Thread(target=run, name="numba-warm-up", daemon=True)
        self._thread.start()

    def join(self) -> str:
        if self._thread is not None:
            self._thread.join()
        return self.line

    def wait(self, folder: Path) -> None:
        if self._done:
            return
        with contextlib.suppress(FileNotFoundError):
            fd = os.open(folder / self.FILE, os.O_RDONLY)
            try:
                fcntl.flock(fd, fcntl.LOCK_SH)
            finally:
                os.close(fd)
        self._done = True

    def hold_compilations(self, folder: Path) -> None:
        """Make this process's numba compilations wait for the warm-up first (then they load its cache)."""
        if self._done or not (folder / self.FILE).exists():
            return
        from numba.core.dispatcher import Dispatcher

        compile_ = Dispatcher.compile

        def compile_after_the_warm_up(dispatcher, sig):
            self.wait(folder)
            return compile_(dispatcher, sig)

        Dispatcher.compile = compile_after_the_warm_up
