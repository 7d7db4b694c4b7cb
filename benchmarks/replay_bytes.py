"""Bytes `cosim replay` puts on Zenoh per byte of the episode file: payloads as decoded (``--raw``, and what
every replay sent before issue 37) against payloads compressed as the file's chunks are (the default), per
schema, with the JSON attachment counted. Runs no Zenoh: it encodes each payload as the replay does.

    nice -n 10 .venv/bin/python benchmarks/replay_bytes.py out/default_s0.mcap
"""

from __future__ import annotations

import argparse
import json
import time
from collections import Counter
from pathlib import Path

from cosim.io import open_episode
from cosim.io.replay import PayloadCodec


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("episode", type=Path)
    args = ap.parse_args()
    size = args.episode.stat().st_size
    raw: Counter[str] = Counter()
    packed: Counter[str] = Counter()
    attach = 0
    cpu = time.process_time()
    with open_episode(args.episode) as ep:
        codec = PayloadCodec(ep.chunk_compression)
        for m in ep.messages():
            payload, how = codec.encode(m.data, m.schema_name)
            raw[m.schema_name] += len(m.data)
            packed[m.schema_name] += len(payload)
            meta = {"topic": m.topic, "log_time_ns": m.log_time_ns, "sequence": m.sequence,
                    "schema": m.schema_name, "encoding": m.message_encoding}
            attach += len(json.dumps({**meta, **({"compression": how} if how else {})}, separators=(",", ":")))
    cpu = time.process_time() - cpu
    print(f"{args.episode}: {size / 1e6:.1f} MB on disk ({ep.chunk_compression or 'uncompressed'} chunks)")
    print(f"{'schema':<28} {'--raw MB':>10} {'default MB':>11}")
    for schema, n in raw.most_common():
        print(f"{schema:<28} {n / 1e6:10.1f} {packed[schema] / 1e6:11.1f}")
    total_raw, total = sum(raw.values()) + attach, sum(packed.values()) + attach
    print(f"{'total (with attachments)':<28} {total_raw / 1e6:10.1f} {total / 1e6:11.1f}")
    print(f"bytes on Zenoh per file byte: --raw {total_raw / size:.2f}, default {total / size:.2f} "
          f"({cpu:.1f} CPU-s to read and encode every payload)")


if __name__ == "__main__":
    main()
