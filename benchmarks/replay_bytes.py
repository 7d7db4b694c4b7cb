"""Bytes `cosim replay` puts on Zenoh per byte of the episode file: payloads as decoded (``--raw``, and what
every replay sent before issue 37) against payloads compressed as the file's chunks are (the default), per
schema, with the JSON attachment counted. Runs no Zenoh: it encodes each payload as the replay does.
Then what ``cosim replay --foxglove`` sends a viewer subscribed to every topic over the WebSocket at
``--rate 1`` (every payload as decoded, plus the 13-byte message-data header and the frame header), per
second of the episode: in all, per agent and for the README's ``--topics /tf /labels/boxes '/vehicle_0/*'``.

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
    websocket: Counter[str] = Counter()  # topic -> bytes on the Foxglove WebSocket
    cpu = time.process_time()
    with open_episode(args.episode) as ep:
        codec = PayloadCodec(ep.chunk_compression)
        duration_s = float(ep.metadata.get("duration_s") or ep.n_ticks / float(ep.metadata["tick_hz"]))
        readme = {t for t in ep.topics if t in ("/tf", "/labels/boxes") or t.startswith("/vehicle_0/")}
        for m in ep.messages():
            payload, how = codec.encode(m.data, m.schema_name)
            websocket[m.topic] += len(m.data) + _WS_MESSAGE_HEADER_B + _ws_frame_header_b(len(m.data) + 13)
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
    per_agent: Counter[str] = Counter()
    for topic, n in websocket.items():
        parts = topic.strip("/").split("/")
        per_agent[parts[0] if len(parts) > 1 and parts[0] in ep.agents else "episode topics"] += n
    print(f"Foxglove WebSocket at --rate 1 ({duration_s:g} s episode, a viewer subscribed to every topic): "
          f"{sum(websocket.values()) / duration_s / 1e6:.1f} MB/s in all; "
          f"--topics /tf /labels/boxes '/vehicle_0/*': "
          f"{sum(n for t, n in websocket.items() if t in readme) / duration_s / 1e6:.1f} MB/s")
    for who, n in sorted(per_agent.items(), key=lambda kv: -kv[1]):
        print(f"  {who:<16} {n / duration_s / 1e6:8.1f} MB/s")


_WS_MESSAGE_HEADER_B = 13  # foxglove.sdk.v1 message data: opcode, subscription id (u32), log time (u64)


def _ws_frame_header_b(payload_b: int) -> int:
    """RFC 6455 server frame header bytes (unmasked) for a binary frame of ``payload_b`` bytes."""
    return 2 if payload_b < 126 else 4 if payload_b < 65536 else 10


if __name__ == "__main__":
    main()
