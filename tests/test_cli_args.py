"""Every option of every subcommand refuses a bad value with one line naming it and exit status 2.

The walk builds cosim's own parser and visits every subcommand's arguments, so an option added later is
driven too: each number with what its :mod:`cosim.cli_args` check refuses (NaN, infinities, -1, 0, a fraction
where a count belongs, text), each path with a file where a folder belongs and the reverse, a missing input,
an empty path and a NUL; every choice with a name it does not offer. The calls run :func:`cosim.cli.main` in
this process and stop at argument parsing: nothing is read, written or trained. An untyped option that reads
like a number or a path fails the walk (give it a ``cosim.cli_args`` check), unless :data:`CHECKED_LATER` says
which command checks it, and how the test below drives that check.

The three cases of issue 50 that still gave a traceback run end to end as programs.
"""

from __future__ import annotations

import argparse
import math
import os
import re
from collections.abc import Iterator
from pathlib import Path

import pytest

from cosim import cli_args
from cosim.cli import build_parser, main
from cosim.cli_args import Check
from tests.helpers import REPO, run_cli

#: What the walk drives a number with; a check must refuse the non-finite ones and the text.
NUMBERS = ("nan", "NaN", "inf", "-inf", "1e999", "-1", "0", "0.5", "x", "")
ALWAYS_REFUSED = ("nan", "NaN", "inf", "-inf", "1e999", "x", "")

#: Untyped arguments that read like a path or a number but are checked by their command, before any work,
#: with the message the rest of the project gives (driven by test_arguments_checked_by_their_command).
CHECKED_LATER = {
    ("run", "scenario"): "a scenario file or the name of a shipped one: the scenario loader",
    ("run", "--out"): "cosim.runner.check_output_dir (it also tries a write), before the world is built",
    ("batch", "sweep"): "a sweep file or the name of a shipped one: the sweep loader",
    ("batch", "--out"): "cosim.runner.check_output_dir, before the plan runs",
    ("report", "--prefix"): "a file-name prefix, not a path",
    ("export", "--split"): "a split name (the folder it makes is named after it)",
    ("learn transfer", "--run"): "NAME=RUN pairs: cosim.learn.transfer.parse_runs checks each folder first",
}
#: An untyped argument reads like a path when its help starts by naming one ("output folder", "a run folder
#: and ...", "scenario YAML file"), or it is an --out.
PATH_WORDS = re.compile(r"(an? |the )?([\w-]+ ){0,2}(file|folder|directory|path)s?\b", re.I)


def commands(parser: argparse.ArgumentParser,
             path: tuple[str, ...] = ()) -> Iterator[tuple[tuple[str, ...], argparse.ArgumentParser]]:
    """(command words, parser) of every leaf subcommand under ``parser``."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield path, parser
        return
    for name, sub in subs[0].choices.items():
        yield from commands(sub, (*path, name))


def arguments(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    """The arguments of a subcommand that take a value (flags, help and version left out)."""
    return [a for a in parser._actions if a.nargs != 0 and not isinstance(
        a, argparse._HelpAction | argparse._VersionAction | argparse._SubParsersAction)]


def name_of(action: argparse.Action) -> str:
    """How argparse (and so the one-line message) names the argument."""
    if action.option_strings:
        return "/".join(action.option_strings)
    return action.metavar if isinstance(action.metavar, str) else action.dest


def key_of(words: tuple[str, ...], action: argparse.Action) -> tuple[str, str]:
    return " ".join(words), action.option_strings[-1] if action.option_strings else name_of(action)


COMMANDS = dict(commands(build_parser()))


@pytest.fixture
def place(tmp_path: Path) -> dict[str, str]:
    """A regular file, a folder, paths under the file, a missing path; a good file and folder for the other
    arguments of a call."""
    (tmp_path / "a_file").write_text("x")
    (tmp_path / "a_dir").mkdir()
    (tmp_path / "good.mcap").write_text("x")
    (tmp_path / "good_dir").mkdir()
    if os.geteuid() != 0:  # as root chmod 000 stops no read: the folder-for-a-file cases stand in for it
        (tmp_path / "locked").mkdir()
        (tmp_path / "locked").chmod(0)
        (tmp_path / "locked_file").write_text("x")
        (tmp_path / "locked_file").chmod(0)
    return {"file": str(tmp_path / "a_file"), "dir": str(tmp_path / "a_dir"),
            "under_file": str(tmp_path / "a_file" / "sub"), "file_under_file": str(tmp_path / "a_file" / "x.png"),
            "missing": str(tmp_path / "missing"), "good_file": str(tmp_path / "good.mcap"),
            "good_dir": str(tmp_path / "good_dir"), "new": str(tmp_path / "new"), "root": str(tmp_path)}


def refuses(check, value: str) -> bool:
    try:
        check(value)
    except (argparse.ArgumentTypeError, ValueError, TypeError):
        return True
    return False


def bad_paths(kind: str, place: dict[str, str]) -> list[str]:
    """Values a path check of ``kind`` must refuse."""
    common = ["", place["root"] + "/a\x00b"]
    unreadable = []
    if os.geteuid() != 0:  # unreadable inputs (as root, where chmod 000 stops no read, none)
        unreadable = [str(Path(place["root"]) / name) for name in {
            "input_file": ["locked_file"], "input_folder": ["locked"], "input_path": ["locked", "locked_file"]
        }.get(kind, [])]
    return {
        "output_folder": [place["file"], place["under_file"]],
        "output_file": [place["dir"], place["file_under_file"]],
        "input_file": [place["dir"], place["missing"], *unreadable],
        "input_folder": [place["file"], place["missing"], *unreadable],
        "input_path": [place["missing"], *unreadable],
    }[kind] + common


def good_value(action: argparse.Action, place: dict[str, str]) -> str:
    """A value the argument takes (for the positionals before the one under test)."""
    check = action.type
    if action.choices:
        return str(next(iter(action.choices)))
    if isinstance(check, Check):
        if check.kind in cli_args.NUMBER_KINDS:
            return next(v for v in ("1", "0.5", "0", "10") if not refuses(check, v))
        return {"input_file": place["good_file"], "output_folder": place["new"],
                "output_file": place["new"] + ".x"}.get(check.kind, place["good_dir"])
    return "x"


def argv_for(words: tuple[str, ...], parser: argparse.ArgumentParser, action: argparse.Action, value: str,
             place: dict[str, str]) -> list[str] | None:
    """``cosim WORDS ...`` that hands ``value`` to ``action`` (a positional: with good values for the other
    positionals, so that argparse gives it the value it is meant for); None: argparse cannot pass it as a value."""
    if action.option_strings:
        opt = action.option_strings[-1]
        if action.nargs in (None, "?"):
            return [*words, f"{opt}={value}"]
        if value.startswith("-") and not re.fullmatch(r"-\d+", value):
            return None  # taken for an option among several values
        count = action.nargs if isinstance(action.nargs, int) else 1
        return [*words, opt, *[value] * count]
    if value.startswith("-"):
        return None
    positionals = [a for a in arguments(parser) if not a.option_strings]
    return [*words, *(value if a is action else good_value(a, place) for a in positionals)]


def bad_values(action: argparse.Action, place: dict[str, str]) -> list[str]:
    """What the walk drives ``action`` with: every value its check must refuse."""
    check = action.type
    if isinstance(check, Check) and check.kind in cli_args.PATH_KINDS:
        return bad_paths(check.kind, place)
    if check is not None:
        values = [v for v in NUMBERS if refuses(check, v)]
        if isinstance(check, Check):
            assert set(ALWAYS_REFUSED) <= set(values), (action.option_strings, check)
            if check.kind == "int":
                assert "0.5" in values
        return values
    if action.choices:
        return ["no-such-choice"]
    return []


@pytest.fixture(autouse=True)
def one_parser(monkeypatch):
    """main() builds the parser once per test, not once per call (it is the same parser every time)."""
    import cosim.cli

    parser = build_parser()
    monkeypatch.setattr(cosim.cli, "build_parser", lambda: parser)


def drive(capsys, argv: list[str]) -> tuple[int, str]:
    status = main(argv)
    return status, capsys.readouterr().err


def one_line_naming(status: int, err: str, name: str) -> str | None:
    """Why the outcome is not exit 2 with one line naming ``name`` (None: it is)."""
    lines = err.strip().splitlines()
    if status != 2 or len(lines) != 1 or "Traceback" in err or "\x00" in err:
        return f"exit {status}, {len(lines)} lines"
    if not lines[0].startswith("cosim: error: ") or name not in lines[0]:
        return "the line does not name the argument"
    return None


@pytest.mark.parametrize("words", [pytest.param(w, id=" ".join(w)) for w in COMMANDS])
def test_every_argument_refuses_bad_values_with_one_line_naming_it(capsys, place, words):
    parser = COMMANDS[words]
    before = sorted(os.listdir(place["root"]))
    problems, driven = [], 0
    for action in arguments(parser):
        for value in bad_values(action, place):
            argv = argv_for(words, parser, action, value, place)
            if argv is None:
                continue
            status, err = drive(capsys, argv)
            driven += 1
            why = one_line_naming(status, err, name_of(action))
            if why:
                problems.append(f"cosim {' '.join(argv)!r}: {why}: {err.strip()[-400:]}")
    assert problems == []
    assert sorted(os.listdir(place["root"])) == before  # nothing made, not even an empty folder
    if any(a.type is not None or a.choices for a in arguments(parser)):
        assert driven > 0


def test_every_number_and_path_argument_has_a_check():
    """No bare ``type=float``/``int`` (they take nan, inf and -1) and no untyped path, unless CHECKED_LATER."""
    unchecked = []
    for words, parser in COMMANDS.items():
        for action in arguments(parser):
            key = key_of(words, action)
            if action.type in (float, int):
                unchecked.append(f"{key}: type={action.type.__name__}: use a cosim.cli_args check")
            elif action.type is None and not action.choices and key not in CHECKED_LATER:
                if isinstance(action.default, int | float) and not isinstance(action.default, bool):
                    unchecked.append(f"{key}: a number without a check")
                elif PATH_WORDS.match(action.help or "") or action.dest == "out":
                    unchecked.append(f"{key}: a path without a check (or list it in CHECKED_LATER)")
    assert unchecked == []
    assert set(CHECKED_LATER) <= {key_of(w, a) for w, p in COMMANDS.items() for a in arguments(p)}


def test_the_walk_reaches_every_subcommand_and_its_arguments():
    names = {" ".join(w) for w in COMMANDS}
    assert {"run", "batch", "export", "eval", "coverage", "learn train", "learn predict", "replay", "render",
            "assets"} <= names
    typed = [a for p in COMMANDS.values() for a in arguments(p) if isinstance(a.type, Check)]
    kinds = {a.type.kind for a in typed}
    assert kinds == {*cli_args.NUMBER_KINDS, *cli_args.PATH_KINDS}
    assert len(typed) >= 50


@pytest.mark.parametrize("words, prefix, name", [
    (("run",), ["default", "--dry-run"], "--out"),
    (("batch",), ["smoke", "--dry-run", "--calibrate-s", "0", "--count", "1"], "--out"),
])
def test_arguments_checked_by_their_command(capsys, place, words, prefix, name):
    """CHECKED_LATER's output folders: a file, or a path under one, is one line naming the path, exit 2."""
    for value in (place["file"], place["under_file"]):
        status, err = drive(capsys, [*words, *prefix, name, value])
        assert one_line_naming(status, err, value) is None, err
    for value in (place["dir"], place["missing"]):  # a scenario or sweep that is a folder, or nowhere
        status, err = drive(capsys, [*words, value, "--out", place["new"], "--dry-run"])
        assert one_line_naming(status, err, value) is None, err
    assert not Path(place["new"]).exists()


def test_the_checks_messages(place):
    def message(check, text):
        with pytest.raises(argparse.ArgumentTypeError) as err:
            check(text)
        return str(err.value)

    assert message(cli_args.positive_float, "nan") == "must be a finite number > 0, got nan"
    assert message(cli_args.positive_int, "0") == "must be >= 1, got 0"
    assert message(cli_args.positive_int, "2.5") == "must be a whole number >= 1, got '2.5'"
    assert message(cli_args.at_least(0, "seconds"), "-1") == "must be >= 0 seconds, got -1"
    assert message(cli_args.float_in(0, 180, "degrees"), "200") == "must be 0 to 180 degrees, got 200"
    assert message(cli_args.fraction, "1.5") == "must be 0 to 1, got 1.5"
    assert message(cli_args.int_in(10, 600, "dpi"), "100000") == "must be 10 to 600 dpi, got 100000"
    assert message(cli_args.output_folder, place["file"]) == f"{place['file']} is a file, not a folder"
    assert message(cli_args.output_folder, place["under_file"]) == (
        f"cannot make {place['under_file']}: {place['file']} is a file, not a folder")
    assert message(cli_args.path("input_file", "episode file"), place["dir"]) == (
        f"{place['dir']} is a folder, not an episode file")
    assert message(cli_args.input_path, place["missing"]) == f"no file or folder at {place['missing']}"
    assert message(cli_args.comma_list(cli_args.positive_int), "1,,2").startswith("must be a comma-separated")
    assert cli_args.comma_list(cli_args.positive_int)("1, 2") == [1, 2]
    assert cli_args.finite_float("-1e3") == -1000.0 and math.isfinite(cli_args.finite_float("1e308"))
    assert cli_args.output_folder(place["new"]) == place["new"] and not Path(place["new"]).exists()


def test_an_unreadable_input_is_named(place, monkeypatch):
    """The permission check itself (as root, where the suite runs, chmod 000 stops no read: os.access is
    made to say no)."""
    monkeypatch.setattr(cli_args.os, "access", lambda path, mode: False)
    for check, path in ((cli_args.input_file, place["good_file"]), (cli_args.input_folder, place["good_dir"]),
                        (cli_args.input_path, place["good_dir"])):
        with pytest.raises(argparse.ArgumentTypeError, match=f"^cannot read {re.escape(path)}: permission denied$"):
            check(path)


def test_library_callers_get_the_output_folder_check(place):
    from cosim.errors import InputError

    with pytest.raises(InputError, match=r"^--out: .* is a file, not a folder$"):
        cli_args.check_output_folder(place["file"])
    cli_args.check_output_folder(place["new"])
    assert not Path(place["new"]).exists()


# ------------------------------------------------------------------ the three cases of issue 50 item 1

def _one_line(r) -> list[str]:
    return [ln for ln in r.stderr.strip().splitlines() if "Warning" not in ln]


@pytest.fixture(scope="module")
def episode(tmp_path_factory) -> Path:
    from cosim.io.synthetic import write_synthetic_episode

    return write_synthetic_episode(tmp_path_factory.mktemp("args") / "ep.mcap", ticks=2)


def test_learn_train_with_a_nan_learning_rate_is_one_line(episode, tmp_path):
    run = tmp_path / "run"
    r = run_cli("learn", "train", str(episode), "--out", str(run), "--lr", "nan", "--steps", "1", "-q")
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr[-2000:]
    assert _one_line(r) == ["cosim: error: --lr must be a finite number > 0, got nan"]
    assert not run.exists()


def test_learn_train_into_a_regular_file_is_one_line(episode, tmp_path):
    out = tmp_path / "run"
    out.write_text("mine")
    r = run_cli("learn", "train", str(episode), "--out", str(out), "--steps", "1", "-q")
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr[-2000:]
    assert _one_line(r) == [f"cosim: error: --out: {out} is a file, not a folder"]
    assert out.read_text() == "mine" and os.listdir(tmp_path) == ["run"]


def test_export_into_a_regular_file_is_one_line(episode, tmp_path):
    out = tmp_path / "export"
    out.write_text("mine")
    r = run_cli("export", str(episode), "--format", "opv2v", "--out", str(out))
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr[-2000:]
    assert _one_line(r) == [f"cosim: error: --out: {out} is a file, not a folder"]
    assert out.read_text() == "mine" and os.listdir(tmp_path) == ["export"]


def test_export_checks_its_folder_when_called_as_a_function(episode, tmp_path):
    """run_export refuses the same folders before it makes anything (a script, not the CLI; cosim learn's
    train() does the same with cosim.learn.train.check_run_folder)."""
    from cosim.exporters.export import run_export

    from cosim.errors import InputError

    a_file = tmp_path / "a_file"
    a_file.write_text("mine")
    for out in (a_file, a_file / "sub"):
        with pytest.raises(InputError, match=f"^--out: .*{a_file.name}.* is a file, not a folder$"):
            run_export(episode, "opv2v", out)
    assert os.listdir(tmp_path) == ["a_file"]


# ------------------------------------------------------- checks beyond a type: before anything is made

def test_a_missing_map_file_leaves_no_output_folder(capsys, tmp_path):
    """cosim run and cosim batch check the scenario's inputs before they make the output folder."""
    sweep = tmp_path / "sweep.yaml"
    sweep.write_text(f"name: b\nbase: {REPO / 'scenarios' / 'base' / 'paper.yaml'}\ncount: 1\n"
                     "set:\n  map.kind: net\n  map.file: nowhere.net.xml\n")
    for argv in (["run", "default", "--set", "map.kind=net", "--set", "map.file=nowhere.net.xml", "--out",
                  str(tmp_path / "out")], ["batch", str(sweep), "--out", str(tmp_path / "out")]):
        status, err = drive(capsys, argv)
        assert one_line_naming(status, err, "nowhere.net.xml") is None, err
        assert "not found" in err and not (tmp_path / "out").exists(), err


def test_comm_with_a_tick_out_of_range_leaves_no_plot_folder(capsys, episode, tmp_path):
    status, err = drive(capsys, ["comm", str(episode), "--out", str(tmp_path / "plots"), "--tick", "99"])
    assert one_line_naming(status, err, "--tick 99") is None, err
    assert not (tmp_path / "plots").exists()
