"""One render process of :class:`cosim.sensors.procs.RenderProcesses` (``python -m cosim.sensors.render_process FD``):
it builds its own :class:`~cosim.sensors.suite.SensorSuite` from what the parent sends over the socket ``FD``
and renders the agents of each request, the large arrays in shared-memory files (:mod:`cosim.sensors.procs`),
until told to stop. Its own module, beside the parent's side, so that the suite (which starts the processes)
and the process (which builds a suite) do not import each other.
"""

from __future__ import annotations

import os
import signal
import sys
import traceback
from multiprocessing.connection import Connection

from cosim.sensors.procs import export_pieces, send_fds, write_pieces
from cosim.sensors.suite import SensorSuite


def _die_with_parent() -> None:
    """Ask Linux to end this process when its parent ends (elsewhere: the closed socket ends it)."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def main(conn: Connection) -> None:
    """A render process: build the suite, then render the agents of each request until told to stop."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops us
    _die_with_parent()
    try:
        scenario, world, kwargs = conn.recv()
        suite = SensorSuite(scenario, world, encode_images=False, **kwargs)
    except BaseException:
        conn.send(("error", -1, traceback.format_exc()))
        return
    conn.send(("ready", -1, None))
    with suite:
        while True:
            try:
                msg = conn.recv()
            except EOFError:
                return
            if msg is None:
                return
            seq, snapshot, items = msg
            fds: list[int] = []
            try:
                frames, timing = suite.render_agents(snapshot, items)
                meta, pieces = export_pieces(frames)
                del frames  # the pieces hold the arrays now: each goes once copied
                fds = write_pieces(pieces, str(seq))
                del pieces
                reply = ("ok", seq, (meta, len(fds), timing))
            except BaseException:
                reply = ("error", seq, traceback.format_exc())
            try:
                conn.send(reply)
                send_fds(conn, fds)
            except OSError:  # the parent is gone
                return
            finally:
                for fd in fds:
                    os.close(fd)


if __name__ == "__main__":
    main(Connection(int(sys.argv[1])))
