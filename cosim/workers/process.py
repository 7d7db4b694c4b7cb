"""What a worker process does to itself before anything else: its name as ``ps`` shows it, and its death with
the conductor that spawned it; and the scratch folder a worker keeps, named after its process so that the
conductor can remove it after a worker that died without cleaning up (light: no Zenoh, no engines)."""

from __future__ import annotations

import logging
import multiprocessing
import multiprocessing.connection
import os
import shutil
import signal
import sys
import tempfile
import threading
from pathlib import Path

_PR_SET_PDEATHSIG, _PR_SET_NAME = 1, 15  # prctl(2) options


def workdir_prefix(role: str, pid: int | None = None) -> str:
    """The name prefix of a worker's scratch folder in the temporary directory: its role and process id
    (default: this process)."""
    return f"cosim-{role}-{os.getpid() if pid is None else pid}-"


def remove_workdirs(role: str, pid: int) -> list[Path]:
    """Remove what an ended worker process ``pid`` of ``role`` left of its scratch folders (a SIGKILL runs no
    finaliser) and return them. Only for a process known to be gone: its id may be reused after that."""
    gone = sorted(Path(tempfile.gettempdir()).glob(workdir_prefix(role, pid) + "*"))
    for d in gone:
        shutil.rmtree(d, ignore_errors=True)
    return gone


def set_process(role: str, *, die_with_parent: bool) -> None:
    """Name the process ``cosim-<role>`` (as ``ps`` and ``top`` show it) and, for spawned workers, ask Linux
    to SIGKILL it when its parent dies."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
    except OSError:
        logging.getLogger(__name__).debug("libc unavailable; relying on the parent watch and liveliness")
        return
    libc.prctl(_PR_SET_NAME, ctypes.c_char_p(f"cosim-{role}".encode()[:15]), 0, 0, 0)
    if die_with_parent:
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)


def _exit_when_parent_gone(sentinel: int) -> None:
    multiprocessing.connection.wait([sentinel])  # readable once the parent's end of the pipe is closed
    os._exit(1)


def die_with_conductor(role: str) -> None:
    """Make this spawned worker end whenever the conductor that spawned it is gone, in any phase.

    Called first thing in the worker process: PR_SET_PDEATHSIG (Linux) from now on; an immediate exit if
    the conductor died before that was armed (the worker was re-parented); and, for other platforms, a
    thread that exits the process when the pipe multiprocessing keeps to the parent closes.
    """
    set_process(role, die_with_parent=True)
    parent = multiprocessing.parent_process()
    if parent is None:
        return
    if os.getppid() != parent.pid:
        os._exit(1)
    threading.Thread(target=_exit_when_parent_gone, args=(parent.sentinel,), name="cosim-parent-watch",
                     daemon=True).start()
