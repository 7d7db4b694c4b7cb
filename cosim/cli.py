"""``cosim``: the command line. Thin: parse arguments, call typed functions, map errors to exit codes.

Exit codes: 0 ok, 1 runtime failure, 2 bad input, 130 interrupted.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import sys
from collections.abc import Sequence
from pathlib import Path

import cosim
from cosim import cli_args
from cosim.errors import CosimError, InputError
from cosim.logs import NOTICE

log = logging.getLogger("cosim")

EXIT_OK, EXIT_FAILURE, EXIT_BAD_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130


class ArgumentsError(InputError):
    """Bad usage found by argparse (an unknown option, a missing argument, a value a ``cosim.cli_args`` check
    refused): :func:`main` prints it as one line, like every other bad input, and returns exit status 2."""


class _Parser(argparse.ArgumentParser):
    """argparse whose errors raise :class:`ArgumentsError` with one line naming the option: ``--lr must be a
    finite number, got nan``, ``--out: /tmp/f is a file, not a folder``; no usage block."""

    def error(self, message: str) -> None:  # type: ignore[override]
        m = re.match(r"argument (\S+): (.*)", message, re.S)
        if m:  # "--x must be >= 1, got 0", "--x: no file at y", "dataset: no file or folder at y"
            message = f"{m.group(1)}{' ' if m.group(2).startswith('must ') else ': '}{m.group(2)}"
        raise ArgumentsError(" ".join(message.split()))


def _human_size(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    return f"{n:.1f} GiB"


def _wall_per_sim_s(wall_s: float, sim_s: float) -> str:
    """The summary's speed: wall seconds per simulated second, and the real-time factor to 3 significant
    digits (runs with sensors are far slower than real time: 0.00x said nothing)."""
    if sim_s <= 0 or wall_s <= 0:
        return "real-time factor n/a"
    return f"{wall_s / sim_s:.3g} s per simulated second (real-time factor {sim_s / wall_s:.3g}x)"


def cmd_run(args: argparse.Namespace) -> int:
    from cosim.runner import run_episode
    from cosim.scenario import load_scenario
    from cosim.transport import check_endpoint

    overrides = list(args.set or [])
    if args.duration is not None:
        overrides.append(f"duration_s={args.duration!r}")
    if args.seed is not None:
        overrides.append(f"seed={args.seed}")
    if args.no_sensors:
        overrides.append("sensors.enabled=false")
    if args.clients is not None:
        names = [n.strip() for n in args.clients.split(",") if n.strip()]
        overrides.append("clients=" + json.dumps([{"name": n} for n in names]))
    loaded = load_scenario(args.scenario, overrides)
    if args.listen:
        check_endpoint(args.listen)
    if args.external_workers and not args.listen:
        raise InputError("--external-workers needs --listen tcp/HOST:PORT so the workers can connect")
    out_dir = Path(args.out) if args.out else Path(loaded.scenario.output.dir)
    if args.dry_run:
        import yaml

        from cosim.preflight import check_scenario_inputs
        from cosim.runner import check_output_dir, episode_path

        path = episode_path(loaded, out_dir)
        check_output_dir(path.parent, create=False)
        check_scenario_inputs(loaded)
        resolved = dict(loaded.resolved)  # the YAML shows the output.dir this run would use (--out wins)
        resolved["output"] = {**resolved.get("output", {}), "dir": str(out_dir)}
        print(f"# {path}: {loaded.scenario.n_ticks} ticks, {len(loaded.scenario.agent_ids())} agents")
        print(yaml.safe_dump(resolved, sort_keys=False), end="")
        return EXIT_OK
    from cosim.progress import progress_display

    update, close = progress_display(loaded.scenario.name, enabled=not args.quiet, every_s=args.progress_every)
    try:
        result = run_episode(loaded, out_dir, progress=update, listen=args.listen,
                             external_workers=args.external_workers, prefix=args.prefix,
                             worker_log_level=logging.getLogger().level)
    finally:
        close()
    s = loaded.scenario
    print(
        f"episode  {result.path}\n"
        f"size     {_human_size(result.size_bytes)} ({result.messages} messages)\n"
        f"ticks    {result.ticks} at {s.tick_hz:g} Hz ({result.sim_time_s:g} s simulated)\n"
        f"actors   {result.actors} tracks; agents: {s.agents.vehicles.count} vehicles, "
        f"{s.agents.rsus.count} RSUs, {len(s.agents.drones)} drones\n"
        f"wall     {result.wall_time_s:.1f} s, {_wall_per_sim_s(result.wall_time_s, result.sim_time_s)}"
    )
    from cosim.io import open_episode
    from cosim.io.info import altitude_notes, labels_and_altitudes

    with open_episode(result.path) as ep:
        _, drones, separation_m = labels_and_altitudes(ep)
    for n, note in enumerate(altitude_notes(drones, separation_m)):
        print(f"{'altitude' if n == 0 else '':<9}{note}")
    return EXIT_OK


def cmd_scenarios(args: argparse.Namespace) -> int:
    from cosim.scenario import load_scenario, shipped_scenarios

    for name, path in shipped_scenarios():
        try:
            s = load_scenario(path).scenario
            line = (f"{name:<28} {s.map.kind:<9} {s.environment.weather:<7} {s.environment.lighting:<6} "
                    f"{'+'.join(d.strategy for d in s.agents.drones) or '-':<22} {s.duration_s:g} s  {s.description}")
        except CosimError as exc:
            line = f"{name:<28} INVALID: {exc}"
        print(line.rstrip())
    return EXIT_OK


def cmd_worker(args: argparse.Namespace) -> int:
    from cosim.transport import EXTERNAL_PREFIX, check_endpoint
    from cosim.workers import worker_main

    check_endpoint(args.connect)
    return worker_main(args.role, args.connect, args.prefix or EXTERNAL_PREFIX,
                       logging.getLogger().level or logging.INFO, spawned=False)


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="cosim", description="Headless co-simulation data generator for drone-assisted V2X "
                                          "collaborative perception (SUMO + JSBSim/PyBullet + Zenoh -> MCAP).")
    p.add_argument("--version", action="version", version=f"cosim {cosim.__version__}")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)

    run = sub.add_parser("run", help="generate one episode from a scenario")
    run.add_argument("scenario", help="scenario YAML file, or the name of a shipped scenario")
    run.add_argument("--out", help="output folder (default: the scenario's output.dir)")
    run.add_argument("--duration", type=cli_args.positive_float, help="simulated seconds (overrides duration_s)")
    run.add_argument("--seed", type=cli_args.non_negative_int, help="random seed (overrides seed)")
    run.add_argument("--set", action="append", metavar="KEY=VALUE",
                     help="override any scenario field, e.g. --set environment.weather=foggy (repeatable)")
    run.add_argument("--no-sensors", action="store_true", help="labels and transforms only (sensors.enabled=false)")
    run.add_argument("--listen", metavar="ENDPOINT", help="Zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447")
    run.add_argument("--external-workers", action="store_true",
                     help="do not start workers; wait for `cosim worker ... --connect` on --listen")
    run.add_argument("--prefix", help="Zenoh key prefix of the episode (default: fresh; 'cosim/external' "
                                      "with --external-workers)")
    run.add_argument("--clients", metavar="NAME[,NAME...]",
                     help="closed-loop clients to wait for after every tick (replaces the scenario's clients); "
                          "they connect with cosim.client.connect on --listen / --prefix")
    run.add_argument("--dry-run", action="store_true", help="check the scenario and the output folder and print "
                                                            "the resolved scenario (YAML); build and run nothing")
    run.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    run.add_argument("--progress-every", type=cli_args.at_least(0, "seconds"), default=10.0, metavar="S",
                     help="without a terminal, one progress line (tick k of n, s/tick, ETA) every S seconds "
                          "(default 10)")
    run.set_defaults(func=cmd_run)

    sc = sub.add_parser("scenarios", help="list the shipped scenarios, one line each")
    sc.set_defaults(func=cmd_scenarios)

    wk = sub.add_parser("worker", help="run a simulation worker by hand (for a conductor on another host)")
    wk.add_argument("role", choices=["traffic", "drones"])
    wk.add_argument("--connect", required=True, metavar="ENDPOINT", help="the conductor's endpoint, tcp/HOST:PORT")
    wk.add_argument("--prefix", help="Zenoh key prefix (default: cosim/external, as the conductor uses)")
    wk.set_defaults(func=cmd_worker)

    _register_more(sub)
    return p


def _register_more(sub: argparse._SubParsersAction) -> None:
    """Subcommands contributed by other modules (episode tools, batch)."""
    for module_name in ("cosim.tools", "cosim.batch.cli", "cosim.eval.cli", "cosim.exporters.cli",
                        "cosim.sensors.catalogue", "cosim.learn.cli"):
        try:
            module = __import__(module_name, fromlist=["register"])
        except ModuleNotFoundError as exc:
            if exc.name is None or not module_name.startswith(exc.name):
                raise
            continue
        module.register(sub)


def _end_failed_run(args: argparse.Namespace, status: int, as_program: bool) -> int:
    """A failed or interrupted ``cosim run`` started as a program ends the process here, at once.

    By now the workers are reaped and the episode's temporary file is deleted; what is left are render,
    encoder and writer threads finishing abandoned work and the teardown of the native libraries, which
    take seconds on a loaded machine while the user (or a batch scheduler) waits for the exit status.
    """
    if as_program and args.command == "run":
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)
    return status


def main(argv: Sequence[str] | None = None) -> int:
    """The ``cosim`` program. ``argv`` None: called as the program (a failed ``run`` then ends the process
    without the interpreter's slow teardown); a list: called in-process, always returns the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except ArgumentsError as exc:
        print(f"cosim: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    level = [NOTICE, logging.INFO, logging.DEBUG][min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return EXIT_BAD_INPUT
    try:
        return args.func(args)
    except InputError as exc:
        print(f"cosim: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except CosimError as exc:
        print(f"cosim: failed: {exc}", file=sys.stderr)
        return _end_failed_run(args, EXIT_FAILURE, argv is None)
    except KeyboardInterrupt:
        print("cosim: interrupted; workers stopped, no episode written", file=sys.stderr)
        return _end_failed_run(args, EXIT_INTERRUPTED, argv is None)
    except BrokenPipeError:  # `cosim info EP | head`: the reader went away, which is not an error
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
