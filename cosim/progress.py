"""Progress of a long command on stderr: a tqdm bar on a terminal, plain lines everywhere else.

``make run > log``, CI and ``nohup`` give the process a file or pipe as stderr, where a bar is noise (or,
disabled, nothing at all for minutes). There :func:`progress_display` writes one line every ``every_s``
seconds of wall time, and one at the end::

    default: tick 120 of 400 (30 %), 2.41 s/tick, ETA 11 min 15 s
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import TextIO

#: Seconds between two plain progress lines (``cosim run --progress-every``).
DEFAULT_EVERY_S = 10.0


def human_duration(seconds: float) -> str:
    """``42 s``, ``11 min 15 s``, ``2 h 05 min``."""
    s = max(0, round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


def progress_line(desc: str, done: int, total: int, per_s: float | None, unit: str = "tick") -> str:
    """One plain progress line: ``DESC: UNIT k of n (p %), x s/UNIT, ETA t`` (no rate when ``per_s`` is None)."""
    line = f"{desc}: {unit} {done} of {total} ({100 * done / max(1, total):.0f} %)"
    if per_s is not None:
        line += f", {per_s:.3g} s/{unit}, "
        line += "done" if done >= total else f"ETA {human_duration(per_s * (total - done))}"
    return line


def progress_display(desc: str, enabled: bool = True, every_s: float = DEFAULT_EVERY_S, unit: str = "tick",
                     stream: TextIO | None = None,
                     clock: Callable[[], float] = time.monotonic) -> tuple[Callable[[int, int], None],
                                                                           Callable[[], None]]:
    """``(update(done, total), close())`` for a loop of ``total`` steps: a tqdm bar when ``stream`` (default
    stderr) is a terminal, else a :func:`progress_line` at most every ``every_s`` seconds (0: every update)
    and at the last step; the time per step counts from the first update (a world build before it, or the
    first step's warm-up, does not skew the ETA). Nothing when not ``enabled``."""
    out = stream if stream is not None else sys.stderr
    tty = hasattr(out, "isatty") and out.isatty()
    if enabled and tty:
        return _bar(desc, unit, out)
    first: list[tuple[int, float]] = []  # (step, time) of the first update: the rate counts from there
    created = clock()
    last, final = [created], [False]

    def update(done: int, total: int) -> None:
        if not enabled or final[0] or done <= 0:
            return
        now = clock()
        if not first:
            first.append((done, now))
        if done >= total or now - last[0] >= every_s:
            last[0] = now
            final[0] = done >= total
            d0, t0 = first[0]
            # from the first update on; a first update that is also the last: from the display's creation
            per = (now - t0) / (done - d0) if done > d0 else (now - created) / done if final[0] else None
            print(progress_line(desc, done, total, per, unit), file=out, flush=True)

    return update, lambda: None


def _bar(desc: str, unit: str, out: TextIO) -> tuple[Callable[[int, int], None], Callable[[], None]]:
    from tqdm import tqdm

    bar: list[tqdm] = []

    def update(done: int, total: int) -> None:
        if not bar:
            bar.append(tqdm(total=total, desc=desc, unit=unit, file=out, dynamic_ncols=True, mininterval=0.2))
        bar[0].update(done - bar[0].n)

    def close() -> None:
        if bar:
            bar[0].close()

    return update, close
