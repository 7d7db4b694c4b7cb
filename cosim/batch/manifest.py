"""The batch manifest: an append-only JSONL log, one record per episode attempt, last record wins.

Every line is written with one ``write`` on an ``O_APPEND`` descriptor and fsynced before the batch
goes on, so a crash loses at most the line being written (a torn last line is ignored on reading).
An episode counts as finished only when its last record says ``done`` AND its file exists with the
recorded size and sha256: a file that is merely present proves nothing.

Record fields: ``episode`` (id), ``sweep``, ``split``, ``file`` (relative to the output folder),
``labels``, ``params``, ``seed``, ``duration_s``, ``scenario_sha256`` (of the resolved scenario),
``status`` (running | done | failed), ``attempts`` (all attempts so far, over every run of the batch),
``wall_time_s``, ``size_bytes``, ``sha256``, ``versions``, ``error``, ``retrying``, ``worker``, where
the attempt ran (``host`` name, ``node``: the Ray node id or null for local processes, ``container``:
the Docker container id or null), ``time_unix`` (wall clock of the record; for ordering only).
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import logging
import os
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from cosim.errors import InputError

log = logging.getLogger(__name__)

MANIFEST_GLOB = "manifest*.jsonl"
#: Fields that equal between any two complete runs of the same plan (interrupted or not, any backend).
DETERMINISTIC_FIELDS = ("episode", "split", "file", "labels", "params", "seed", "duration_s", "scenario_sha256",
                        "status", "size_bytes", "sha256")


def manifest_name(shard: tuple[int, int] = (0, 1)) -> str:
    """``manifest.jsonl``, or one file per shard so shards sharing a folder never write the same file."""
    index, count = shard
    return "manifest.jsonl" if count == 1 else f"manifest.shard{index:03d}of{count:03d}.jsonl"


def sha256_file(path: Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


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


def read_records(path: Path) -> list[dict[str, Any]]:
    """Every parseable record of one manifest file, in file order (torn or garbled lines skipped)."""
    out = []
    with open(path, encoding="utf-8", errors="replace") as f:
        for n, line in enumerate(f, 1):
            line = line.strip()
            if not line:
                continue
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                log.warning("%s:%d: skipping a torn manifest line", path, n)
                continue
            if isinstance(rec, dict) and "episode" in rec:
                out.append(rec)
    return out


def manifest_files(out_dir: Path) -> list[Path]:
    return sorted(Path(out_dir).glob(MANIFEST_GLOB))


def latest_records(out_dir: Path) -> dict[str, dict[str, Any]]:
    """The last record of every episode over all manifests in ``out_dir`` (by time, then file order)."""
    best: dict[str, tuple[tuple[float, int, int], dict[str, Any]]] = {}
    for fi, path in enumerate(manifest_files(out_dir)):
        for li, rec in enumerate(read_records(path)):
            key = (float(rec.get("time_unix", 0.0)), fi, li)
            cur = best.get(rec["episode"])
            if cur is None or key >= cur[0]:
                best[rec["episode"]] = (key, rec)
    return {k: v[1] for k, v in sorted(best.items())}


def verify(out_dir: Path, record: dict[str, Any]) -> bool:
    """True when the record says done and its file exists with the recorded size and sha256."""
    if record.get("status") != "done" or not record.get("sha256") or not record.get("file"):
        return False
    path = Path(out_dir) / record["file"]
    try:
        if path.stat().st_size != record.get("size_bytes"):
            return False
    except OSError:
        return False
    return sha256_file(path) == record["sha256"]


def deterministic_view(records: Iterable[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Episode id -> the deterministic fields of its record (to compare two runs)."""
    return {r["episode"]: {k: r.get(k) for k in DETERMINISTIC_FIELDS} for r in records}
