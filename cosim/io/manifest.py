"""Reading a batch folder's manifest: the append-only JSONL log of :mod:`cosim.batch.manifest`, one record per
episode attempt, last record wins. What a batch folder's readers (``cosim eval``, ``cosim export``, ``cosim
report``, resume) need without the batch package.

An episode counts as finished only when its last record says ``done`` AND its file exists with the
recorded size and sha256 (:func:`verify`): a file that is merely present proves nothing. A torn last line
(a crash mid-write) is skipped.

Record fields: ``episode`` (id), ``sweep``, ``split``, ``file`` (relative to the output folder),
``labels``, ``params``, ``seed``, ``duration_s``, ``scenario_sha256`` (of the resolved scenario),
``status`` (running | done | failed), ``attempts`` (all attempts so far, over every run of the batch),
``wall_time_s``, ``size_bytes``, ``sha256``, ``versions``, ``error``, ``retrying``, ``worker``, where
the attempt ran (``host`` name, ``node``: the Ray node id or null for local processes, ``container``:
the Docker container id or null), ``time_unix`` (wall clock of the record; for ordering only).
"""

from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Iterable
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

MANIFEST_GLOB = "manifest*.jsonl"
#: Fields that equal between any two complete runs of the same plan (interrupted or not, any backend).
DETERMINISTIC_FIELDS = ("episode", "split", "file", "labels", "params", "seed", "duration_s", "scenario_sha256",
                        "status", "size_bytes", "sha256")


def sha256_file(path: Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


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
