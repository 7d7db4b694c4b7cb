"""Render processes: the sensor suite split over processes so that every core renders.

Open3D holds the GIL while it casts and most of the per-pixel work is numpy between casts, so
threads in one process keep little more than one core busy. :class:`RenderProcesses` starts
``n`` processes (``python -m cosim.sensors.render_process``, over a socket pair); each builds its own
:class:`~cosim.sensors.suite.SensorSuite` (the static scene once per episode) and renders a
fixed share of the agents at every tick: an agent is given, the first time it is seen, to the
process with the fewest cameras so far, and stays there (a standing RSU keeps its static image in
that process).

Each agent is rendered with the generator the parent spawned for it, so the frames do not depend
on the number of processes. The frames come back pickled, except their large arrays (images,
depth, labels, LiDAR points), which the process writes into shared-memory files (under ``/dev/shm``,
unlinked as soon as they are made) whose descriptors it passes over the socket: one file per camera
and one per agent for its other sensors, so that the parent, which hands out arrays backed by the
mappings, frees each camera's memory as soon as the episode writer has dropped that camera (a
mapping and its file go with the last array backed by it), not when the whole tick is written. The
render process copies each array into its file and lets go of it at once, so it does not hold a
tick's arrays twice.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import mmap
import os
import socket
import subprocess
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from multiprocessing.reduction import recvfds, sendfds

import numpy as np

from cosim.errors import CosimError
from cosim.scenario.model import Scenario
from cosim.snapshot import AgentState, WorldSnapshot
from cosim.world.types import World

log = logging.getLogger(__name__)

#: arrays at least this big travel through shared memory, smaller ones are pickled
SHARED_MIN_BYTES = 1 << 16
_ALIGN = 64
CHECK_PERIOD_S = 0.05
#: descriptors passed per socket message (Linux takes at most 253)
_FDS_PER_MESSAGE = 64
START_TIMEOUT_S = 300.0


class RenderProcessError(CosimError):
    """A render process failed (its traceback is in the message) or died."""


@dataclass(frozen=True)
class _Shared:
    """Placeholder for an array in the tick's shared-memory file."""

    offset: int
    dtype: str
    shape: tuple[int, ...]


def _shm_dir() -> str:
    return "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else tempfile.gettempdir()


def _export(obj, arrays: list[np.ndarray], offset: list[int]):
    """``obj`` with its large arrays (inside dataclasses, dicts, tuples) replaced by :class:`_Shared`."""
    if isinstance(obj, np.ndarray):
        if obj.nbytes < SHARED_MIN_BYTES or obj.dtype.hasobject:
            return obj
        at = offset[0]
        arrays.append(obj)
        offset[0] += -(-obj.nbytes // _ALIGN) * _ALIGN
        return _Shared(at, obj.dtype.str, obj.shape)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        changes = {f.name: _export(getattr(obj, f.name), arrays, offset) for f in dataclasses.fields(obj)
                   if f.init}
        return dataclasses.replace(obj, **changes)
    if isinstance(obj, dict):
        return {k: _export(v, arrays, offset) for k, v in obj.items()}
    if isinstance(obj, tuple) and not hasattr(obj, "_fields"):
        return tuple(_export(v, arrays, offset) for v in obj)
    return obj


def _import(obj, buf: mmap.mmap):
    if isinstance(obj, _Shared):
        n = int(np.prod(obj.shape, dtype=np.int64))
        return np.frombuffer(buf, np.dtype(obj.dtype), n, obj.offset).reshape(obj.shape)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        changes = {f.name: _import(getattr(obj, f.name), buf) for f in dataclasses.fields(obj) if f.init}
        return dataclasses.replace(obj, **changes)
    if isinstance(obj, dict):
        return {k: _import(v, buf) for k, v in obj.items()}
    if isinstance(obj, tuple) and not hasattr(obj, "_fields"):
        return tuple(_import(v, buf) for v in obj)
    return obj


@dataclass(frozen=True)
class _Piece:
    """Placeholder for an object whose arrays are in shared file number ``index`` of the reply."""

    index: int
    meta: object


def export_pieces(frames: dict) -> tuple[dict, list[tuple[list[np.ndarray], int]]]:
    """(``frames`` by agent id with their arrays replaced by placeholders, the pieces: arrays and file size of
    each shared file). Each camera is a piece of its own; each agent's other sensors make one more."""
    pieces: list[tuple[list[np.ndarray], int]] = []

    def piece(obj):
        arrays: list[np.ndarray] = []
        offset = [0]
        meta = _export(obj, arrays, offset)
        if not arrays:
            return meta
        pieces.append((arrays, offset[0]))
        return _Piece(len(pieces) - 1, meta)

    out = {}
    for agent_id, af in frames.items():
        cams = {name: piece(cam) for name, cam in af.cameras.items()}
        out[agent_id] = (piece(dataclasses.replace(af, cameras={})), cams)
    return out, pieces


def write_pieces(pieces: list[tuple[list[np.ndarray], int]], tag: str) -> list[int]:
    """One shared file per piece, its arrays copied in and then dropped (``pieces`` holds the last references
    the render process has); the descriptors. Each file is unlinked as soon as it is made: it lives as long
    as a descriptor or a mapping of it, so no crash leaves it behind."""
    fds: list[int] = []
    try:
        for k, (arrays, size) in enumerate(pieces):
            path = os.path.join(_shm_dir(), f"cosim-render-{os.getpid()}-{tag}-{k}")
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_RDWR, 0o600)
            os.unlink(path)
            fds.append(fd)
            os.ftruncate(fd, size)
            with mmap.mmap(fd, size) as mm:
                at = 0
                for i, a in enumerate(arrays):
                    view = np.frombuffer(mm, a.dtype, a.size, at).reshape(a.shape)
                    view[...] = a
                    del view
                    at += -(-a.nbytes // _ALIGN) * _ALIGN
                    arrays[i] = None  # type: ignore[call-overload]  # freed now, not with the whole tick
    except BaseException:
        for fd in fds:
            os.close(fd)
        raise
    return fds


def send_fds(conn: Connection, fds: list[int]) -> None:
    with socket.fromfd(conn.fileno(), socket.AF_UNIX, socket.SOCK_STREAM) as s:
        for k in range(0, len(fds), _FDS_PER_MESSAGE):
            sendfds(s, fds[k:k + _FDS_PER_MESSAGE])


def _recv_fds(conn: Connection, n: int) -> list[int]:
    fds: list[int] = []
    with socket.fromfd(conn.fileno(), socket.AF_UNIX, socket.SOCK_STREAM) as s:
        while len(fds) < n:
            fds.extend(recvfds(s, min(_FDS_PER_MESSAGE, n - len(fds))))
    return fds


def _read_pieces(meta: dict, conn: Connection, n_files: int) -> dict:
    """The frames by agent id, their placeholders backed by the shared files whose descriptors follow on
    ``conn`` (each file mapped on its own, so each camera's memory goes with that camera)."""
    fds = _recv_fds(conn, n_files)
    bufs = []
    try:
        for fd in fds:
            bufs.append(mmap.mmap(fd, os.fstat(fd).st_size))
    finally:
        for fd in fds:
            os.close(fd)

    def load(obj):
        return _import(obj.meta, bufs[obj.index]) if isinstance(obj, _Piece) else obj

    out = {}
    for agent_id, (base, cams) in meta.items():
        out[agent_id] = dataclasses.replace(load(base), cameras={n: load(c) for n, c in cams.items()})
    bufs.clear()  # the arrays keep their mappings alive; ours go
    return out


class RenderProcesses:
    """``n`` render processes over one scenario and world (see the module docstring)."""

    def __init__(self, scenario: Scenario, world: World, n: int, suite_kwargs: dict):
        self._conns: list[Connection] = []
        self._procs = []
        self._outstanding: list[int] = []  # requests whose replies were not read (an abandoned frame)
        self._owner: dict[str, int] = {}
        self._cameras = [0] * n
        self._seq = 0
        self._rig = scenario.rig_for
        try:
            for _ in range(n):
                ours, theirs = socket.socketpair()
                with ours, theirs:
                    p = subprocess.Popen([sys.executable, "-m", "cosim.sensors.render_process", str(theirs.fileno())],
                                         pass_fds=(theirs.fileno(),))
                    conn = Connection(ours.detach())
                self._conns.append(conn)
                self._procs.append(p)
                self._outstanding.append(0)
                conn.send((scenario, world, suite_kwargs))
            for k in range(n):
                self._reply(k, None, START_TIMEOUT_S)
        except BaseException:
            self.close()
            raise

    def _reply(self, k: int, check: Callable[[], None] | None, timeout_s: float | None = None):
        conn, waited = self._conns[k], 0.0
        while not conn.poll(CHECK_PERIOD_S):
            if self._procs[k].poll() is not None:
                raise RenderProcessError(f"render process {k} died (exit code {self._procs[k].returncode})")
            if check is not None:
                check()
            waited += CHECK_PERIOD_S
            if timeout_s is not None and waited > timeout_s:
                raise RenderProcessError(f"render process {k} did not answer within {timeout_s:.0f} s")
        try:
            kind, _, payload = conn.recv()
        except EOFError:
            raise RenderProcessError(f"render process {k} died (exit code {self._procs[k].poll()})") from None
        if kind == "error":
            raise RenderProcessError(f"render process {k} failed:\n{payload}")
        return payload

    def _drain(self, k: int) -> None:
        """Read and drop the replies of abandoned frames."""
        while self._outstanding[k]:
            self._outstanding[k] -= 1
            try:
                _, n_files, _ = self._reply(k, None)
            except RenderProcessError:
                continue
            for fd in _recv_fds(self._conns[k], n_files):
                os.close(fd)

    def _share_of(self, agent: AgentState) -> int:
        k = self._owner.get(agent.agent_id)
        if k is None:
            k = int(np.argmin(self._cameras))
            self._owner[agent.agent_id] = k
            self._cameras[k] += 1 + len(self._rig(agent.agent_id).cameras)
        return k

    def render(self, snapshot: WorldSnapshot, items: list[tuple[AgentState, np.random.Generator]],
               check: Callable[[], None] | None = None):
        """(frames by agent id in the order of ``items``, summed timings) of the agents in ``items``."""
        self._seq += 1
        shares: list[list] = [[] for _ in self._conns]
        for agent, rng in items:
            shares[self._share_of(agent)].append((agent, rng))
        busy = []
        for k, share in enumerate(shares):
            if share:
                self._drain(k)
                self._conns[k].send((self._seq, snapshot, share))
                self._outstanding[k] += 1
                busy.append(k)
        frames: dict = {}
        timing: dict[str, float] = {}
        for k in busy:
            meta, n_files, t = self._reply(k, check)
            frames.update(_read_pieces(meta, self._conns[k], n_files))
            self._outstanding[k] -= 1
            for key, v in t.items():
                timing[key] = timing.get(key, 0.0) + v
        return {agent.agent_id: frames[agent.agent_id] for agent, _ in items}, timing

    def close(self) -> None:
        for conn in self._conns:
            with contextlib.suppress(OSError, ValueError):
                conn.send(None)
        for k, p in enumerate(self._procs):
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
            self._conns[k].close()
        self._conns, self._procs = [], []

