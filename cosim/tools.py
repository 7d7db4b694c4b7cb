"""Episode tools on the command line: ``cosim info | validate | replay | render | comm``.

Registered into ``cosim`` by :func:`register` (cosim/cli.py calls it). Each command parses its
arguments and calls a typed function in :mod:`cosim.io`; errors are raised as
:class:`~cosim.errors.InputError` (exit 2) or :class:`~cosim.errors.CosimError` (exit 1).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import signal
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from cosim import cli_args
from cosim.errors import InputError

log = logging.getLogger(__name__)

EXIT_OK, EXIT_PROBLEMS, EXIT_INTERRUPTED = 0, 1, 130
EPISODE = cli_args.path("input_file", "episode file")
DPI = cli_args.int_in(10, 600, "dpi")  # a figure of a few thousand pixels a side at most


def _episode(path: str) -> Path:
    p = Path(path)
    if not p.is_file():
        raise InputError(f"no episode file at {p}")
    return p


def parse_ticks(spec: str | None, n_ticks: int) -> list[int]:
    """Ticks from ``"0,10,20"``, ``"0:50:10"`` (start:stop:step) or ``"-1"``; default first, middle, last."""
    if not spec:
        return sorted({0, n_ticks // 2, max(n_ticks - 1, 0)})
    out: list[int] = []
    for part in spec.split(","):
        part = part.strip()
        try:
            if ":" in part:
                nums = [int(x) if x else None for x in part.split(":")]
                out.extend(range(n_ticks)[slice(*nums)])
            else:
                k = int(part)
                out.append(k + n_ticks if k < 0 else k)
        except ValueError:
            raise InputError(f"bad --ticks entry {part!r}: use numbers, START:STOP[:STEP] or -1") from None
    bad = [k for k in out if not 0 <= k < n_ticks]
    if bad:
        raise InputError(f"--ticks {bad} out of range: the episode has ticks 0..{n_ticks - 1}")
    return sorted(set(out))


def cmd_info(args: argparse.Namespace) -> int:
    from cosim.errors import FormatError
    from cosim.io.info import episode_info, format_info

    try:
        info = episode_info(_episode(args.episode), bytes_per_family=not args.no_bytes, full=args.full)
    except FormatError as exc:  # not an episode at all: bad input, like a missing file
        raise InputError(str(exc)) from None
    print(json.dumps(info.as_dict(), indent=2) if args.json else format_info(info, all_topics=args.full))
    return EXIT_OK


def cmd_validate(args: argparse.Namespace) -> int:
    from cosim.io.validate import report_json, validate_episode

    status = EXIT_OK
    for path in args.episodes:
        report = validate_episode(_episode(path), pixels=not args.no_pixels)
        if args.json:
            print(report_json(report))
        elif report.ok:
            print(f"{path}: ok ({report.ticks} ticks, {report.messages} messages, {len(report.topics)} topics)")
        else:
            lines = report.lines()
            print(
                f"{path}: {len(report.problems)} problem(s)"
                + (f" (+{sum(report.suppressed.values())} not shown)" if report.suppressed else "")
            )
            for line in lines:
                print(f"  {line}")
        if not report.ok:
            status = EXIT_PROBLEMS
    return status


def cmd_replay(args: argparse.Namespace) -> int:
    from cosim.io.replay import DEFAULT_FOXGLOVE_HOST, ReplayEndpoints, ReplayOptions, replay_episode
    from cosim.transport import check_endpoint

    for e in (args.connect or []) + (args.listen or []):
        check_endpoint(e)
    if args.foxglove_host and args.foxglove is None:
        raise InputError("--foxglove-host needs --foxglove [PORT]")
    if args.foxglove is not None and not 0 <= args.foxglove <= 65535:
        raise InputError(f"--foxglove port must be 0..65535, got {args.foxglove}")
    opts = ReplayOptions(
        rate=args.rate,
        loop=args.loop,
        topics=args.topics,
        connect=args.connect or [],
        listen=args.listen or [],
        prefix=args.prefix,
        wait_subscribers_s=0.0 if args.no_wait else args.wait,
        wait_viewer=not args.no_wait,
        foxglove_port=args.foxglove,
        foxglove_host=args.foxglove_host or DEFAULT_FOXGLOVE_HOST,
        compress=not args.raw,
    )

    def announce(where: ReplayEndpoints) -> None:
        keys = f"keys {where.prefix}/**"
        for endpoint in where.subscriber_endpoints():
            print(f"zenoh     {endpoint}  (subscribers connect here: connect/endpoints; {keys})", flush=True)
        for endpoint in where.zenoh_connect:
            print(f"zenoh     connected to {endpoint}  ({keys})", flush=True)
        if where.foxglove_url:
            print(f"foxglove  {where.foxglove_url}  (Foxglove: Open connection > Foxglove WebSocket)", flush=True)
        if where.waits_for_viewer:
            print(f"waiting   for a Foxglove viewer: connect it to {where.foxglove_url}; the replay starts when it "
                  "subscribes to a topic (Ctrl-C stops; --no-wait starts at once)", flush=True)

    stop = threading.Event()
    with _stop_on_signals(stop):
        try:
            stats = replay_episode(_episode(args.episode), opts, stop, on_ready=announce)
        except KeyboardInterrupt:
            stop.set()
    if stop.is_set():
        print("cosim: replay stopped", file=sys.stderr)
        return EXIT_INTERRUPTED
    print(
        f"replayed {stats.messages} messages ({stats.loops} pass{'es' if stats.loops != 1 else ''}) "
        f"in {stats.wall_s:.2f} s under {opts.prefix}/"
    )
    return EXIT_OK


@contextlib.contextmanager
def _stop_on_signals(stop: threading.Event) -> Iterator[None]:
    """The first Ctrl-C (or SIGTERM) sets ``stop`` so the replay winds down; a second one interrupts at once.

    The handler runs in the main thread between two bytecodes, possibly inside ``stop.wait`` while that
    thread holds the event's lock; ``stop.set()`` there would wait for that lock forever. So a short thread
    sets it, once the main thread lets go of the lock.
    """

    def first(signum: int, frame: Any) -> None:
        threading.Thread(target=stop.set, name="stop on signal", daemon=True).start()
        signal.signal(signal.SIGINT, signal.default_int_handler)

    previous = {s: signal.signal(s, first) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def cmd_render(args: argparse.Namespace) -> int:
    from cosim.io.reader import open_episode
    from cosim.io.render import render_episode

    path = _episode(args.episode)
    with open_episode(path) as ep:
        ticks = parse_ticks(args.ticks, ep.n_ticks)
        agents = args.agents or None
        unknown = sorted(set(agents or []) - set(ep.agents))
        if unknown:
            raise InputError(f"--agents {unknown} not in the episode; it has {', '.join(ep.agents)}")
        written = render_episode(ep, Path(args.out), ticks, agents=agents, dpi=args.dpi)
    for p in written:
        print(p)
    return EXIT_OK


def cmd_comm(args: argparse.Namespace) -> int:
    from cosim.io.comm_report import comm_report, format_summary, summary_json

    out = Path(args.out) if args.out else None
    rows, n_ticks, written = comm_report(_episode(args.episode), out, args.tick, dpi=args.dpi)
    if args.json:
        print(json.dumps({"ticks": n_ticks, "link_types": summary_json(rows), "plots": [str(p) for p in written]},
                         indent=2))
        return EXIT_OK
    print(format_summary(rows, n_ticks))
    for p in written:
        print(p)
    return EXIT_OK


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``info``, ``validate``, ``replay``, ``render`` and ``comm`` to the ``cosim`` command."""
    p = sub.add_parser("info", help="what an episode holds: scenario, conditions, agents, topics, size")
    p.add_argument("episode", type=EPISODE, help="episode file (.mcap)")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--no-bytes", action="store_true", help="skip the bytes per topic family")
    p.add_argument("--full", action="store_true",
                   help="count the bytes per topic family exactly (reads every message) and list every topic")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("validate", help="check episodes against docs/episode_format.md (exit 1 on problems)")
    p.add_argument("episodes", nargs="+", metavar="episode", type=EPISODE, help="episode file(s) (.mcap)")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--no-pixels", action="store_true", help="skip decoding instance masks (faster)")
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser("replay", help="re-publish an episode over Zenoh with its original timing")
    p.add_argument("episode", type=EPISODE, help="episode file (.mcap)")
    p.add_argument("--rate", type=cli_args.positive_float, default=1.0,
                   help="speed factor (2 = twice as fast; default 1)")
    p.add_argument("--loop", action="store_true", help="start again at the end until interrupted")
    p.add_argument(
        "--topics",
        nargs="+",
        metavar="TOPIC",
        help="topics or patterns to send (default all), e.g. /tf '/vehicle_0/*'",
    )
    p.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help="Zenoh endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)",
    )
    p.add_argument("--listen", action="append", metavar="ENDPOINT", help="Zenoh endpoint to listen on (repeatable)")
    p.add_argument("--prefix", default="cosim/replay", help="key prefix (default cosim/replay)")
    p.add_argument(
        "--wait",
        type=cli_args.at_least(0, "seconds"),
        default=5.0,
        metavar="SECONDS",
        help="wait this long for a Zenoh subscriber before sending (default 5; 0 = do not wait); with --foxglove "
             "the replay waits instead for a Foxglove viewer to subscribe, as long as it takes",
    )
    p.add_argument("--no-wait", action="store_true",
                   help="start at once: wait for no Foxglove viewer and no Zenoh subscriber")
    p.add_argument(
        "--foxglove",
        type=cli_args.non_negative_int,
        nargs="?",
        const=8765,
        metavar="PORT",
        help="also serve the replay to Foxglove over WebSocket (needs foxglove-sdk; default port 8765, 0 = any free)",
    )
    p.add_argument(
        "--foxglove-host",
        metavar="HOST",
        help="address the Foxglove server listens on (default 127.0.0.1; 0.0.0.0 for other machines)",
    )
    p.add_argument("--raw", action="store_true",
                   help="send Zenoh payloads uncompressed (default: compressed as the file's chunks are, where "
                        "that helps; the attachment's 'compression' says how)")
    p.set_defaults(func=cmd_replay)

    p = sub.add_parser("render", help="PNG contact sheets per agent and a BEV plot for chosen ticks")
    p.add_argument("episode", type=EPISODE, help="episode file (.mcap)")
    p.add_argument("--out", required=True, type=cli_args.output_folder, help="output folder")
    p.add_argument("--ticks", help="ticks: '0,10,20', '0:50:10' or '-1' (default: first, middle, last)")
    p.add_argument("--agents", nargs="+", metavar="AGENT", help="agents for contact sheets (default all)")
    p.add_argument("--dpi", type=DPI, default=80, help="figure resolution (default 80; 10 to 600)")
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("comm", help="V2X links of an episode: summary per link type (LOS, SNR, delivery) and plots")
    p.add_argument("episode", type=EPISODE, help="episode file (.mcap) written with comm.enabled")
    p.add_argument("--out", type=cli_args.output_folder,
                   help="folder for comm_quality.png and comm_map_t<tick>.png (default: no plots)")
    p.add_argument("--tick", type=cli_args.non_negative_int, help="tick of the link map (default: the middle one)")
    p.add_argument("--json", action="store_true", help="machine-readable summary")
    p.add_argument("--dpi", type=DPI, default=80, help="figure resolution (default 80; 10 to 600)")
    p.set_defaults(func=cmd_comm)
