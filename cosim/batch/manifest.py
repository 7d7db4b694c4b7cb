"""Writing the batch manifest: an append-only JSONL log, one record per episode attempt, last record wins
(reading it, the record fields and what counts as finished: :mod:`cosim.io.manifest`).

Every line is written with one ``write`` on an ``O_APPEND`` descriptor and fsynced before the batch
goes on, so a crash loses at most the line being written (a torn last line is ignored on reading).
"""

from __future__ import annotations

import fcntl
import json
import os
import time
from pathlib import Path
from typing import Any

from cosim.errors import InputError


def manifest_name(shard: tuple[int, int] = (0, 1)) -> str:
    """``manifest.jsonl``, or one file per shard so shards sharing a folder never write the same file."""
    index, count = shard
    return "manifest.jsonl" if count == 1 else f"manifest.shard{index:03d}of{count:03d}.jsonl"


class Manifest:
    """Append-only writer; each :meth:`append` is durable when it returns."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        existed = self.path.exists()
        self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:  # one writer per manifest: a second batch on the same folder and shard would redo work
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(self._fd)
            self._fd = -1
            raise InputError(f"another batch is already writing {self.path}; wait for it, or give each "
                             "concurrent run its own --shard i/k") from None
        if existed:
            self._repair_tail()
        else:
            _fsync_dir(self.path.parent)

    def _repair_tail(self) -> None:
        """A crash mid-write can leave a line without its newline; end it so the next record parses."""
        with open(self.path, "rb") as f:
            f.seek(0, os.SEEK_END)
            if f.tell() == 0:
                return
            f.seek(-1, os.SEEK_END)
            last = f.read(1)
        if last != b"\n":
            os.write(self._fd, b"\n")
            os.fsync(self._fd)

    def append(self, record: dict[str, Any]) -> None:
        record = {**record, "time_unix": round(time.time(), 3)}
        data = (json.dumps(record, sort_keys=True, separators=(",", ":")) + "\n").encode()
        written = os.write(self._fd, data)
        if written != len(data):
            raise OSError(f"short write to {self.path}: {written} of {len(data)} bytes")
        os.fsync(self._fd)

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __enter__(self) -> Manifest:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
